"""Memory of a point cloud's preparation (issue 50): peak RSS per stage, and a bit-for-bit check.

    python bench/prep_memory.py /tmp/synth1m.laz --save /tmp/prep_ref.npz   # before a change
    python bench/prep_memory.py /tmp/synth1m.laz --check /tmp/prep_ref.npz  # after it
    python bench/prep_memory.py /tmp/synth1m.laz --stages                   # RSS per stage
    python bench/prep_memory.py /tmp/synth4m.laz --chunk-points 1e12 --save /tmp/whole.npz
    python bench/prep_memory.py /tmp/synth4m.laz --check /tmp/whole.npz     # chunks vs whole
    python bench/prep_memory.py /tmp/synth20m.laz --render "--size 1920x1080 --aperture 5"
    python bench/prep_memory.py /tmp/synth20m.laz --render "..." --cache   # twice: the later one
    python bench/prep_memory.py /tmp/synth20m.laz --prepare --on-disk on   # the cloud on disk
    python bench/prep_memory.py /tmp/synth4m.laz --on-disk on --sort --check /tmp/sorted.npz

The file is loaded with ``dofsplat.io.load(path, cache="off")`` (the preparation of
``prep.pointcloud.points_to_surfels``). ``--save`` writes the surfel arrays (positions,
normals, radius, colors, opacity, weight) to an .npz; ``--check`` compares them with
``np.array_equal`` (a change that lowers memory must not change a bit). ``--stages`` samples
the process's resident set every 5 ms and prints the highest it reached during each stage
of the preparation (the stage functions are wrapped), in GB and bytes a point; for the
whole run use ``/usr/bin/time -v`` (Maximum resident set size). ``--render ARGS`` runs a
first render instead, ``dofsplat render PATH ARGS --no-cache --lod-cache off`` in this
process (the model prepared and its tree built afresh; the kernels from their cache), and
prints the peak of its stages: reading the file, merging duplicates, the surfels (in chunks
past ``prep.pointcloud.CHUNK_POINTS`` points), the LOD tree and the frame, each as RSS and
as the process's own memory (RssAnon: without the pages of the files it maps, which for a
model kept as a .dofsplat file are the page cache's, mapped around each page a frame reads).
``--cache`` renders through the caches instead: run twice, the second is a later render
(a model of 2^21 surfels or more then opens as its .dofsplat file in the cache). ``--prepare``
runs ``dofsplat prepare PATH --no-cache`` instead of the render (its stages and the file's
write). ``--chunk-points N`` sets that threshold (1e12: the whole cloud at once), so that
``--save`` of one and ``--check`` of the other count the rows in which chunks and the whole
cloud differ. ``--on-disk on`` prepares a LAS/LAZ cloud from a work folder
(``prep.cloudfile``; "off" in memory, "auto" by its size), whose surfels come in the order
of its chunks: ``--sort`` orders the rows by position before ``--save`` or ``--check``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import threading
import time

import numpy as np

FIELDS = ("positions", "normals", "radius", "colors", "opacity", "weight")


def rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def own_bytes() -> int:
    """The process's own memory: RssAnon (RSS less the pages of files it maps: a model
    file's, which the kernel keeps or drops as memory allows, and the libraries')."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) * 1024
    return 0


class StageSampler:
    """A thread that records the highest RSS seen under each stage label."""

    def __init__(self, period: float = 0.005):
        self.period = period
        self.stage = "read"
        self.peaks: dict[str, int] = {}
        self.own: dict[str, int] = {}  # the same for RssAnon
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.is_set():
            self._note()
            time.sleep(self.period)

    def _note(self):
        r, a = rss_bytes(), own_bytes()
        if r > self.peaks.get(self.stage, 0):
            self.peaks[self.stage] = r
        if a > self.own.get(self.stage, 0):
            self.own[self.stage] = a

    @contextlib.contextmanager
    def under(self, label: str):
        outer, self.stage = self.stage, label
        try:
            yield
        finally:
            self._note()
            # the time between two stages is reported as "after" the one that ended
            self.stage = outer if outer != "read" and not outer.startswith("after ") \
                else f"after {label}"

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def wrap(sampler: StageSampler, module: str, name: str, label: str | None = None) -> None:
    """module.name wrapped so that the sampler knows when it runs (under label, or its
    name); left as it is where the module lacks it (an older checkout on PYTHONPATH)."""
    import importlib

    try:
        mod = importlib.import_module(module)
        fn = getattr(mod, name)
    except (ImportError, AttributeError):
        return

    @functools.wraps(fn)
    def staged(*args, **kwargs):
        with sampler.under(label or name):
            return fn(*args, **kwargs)

    setattr(mod, name, staged)


def wrap_stages(sampler: StageSampler):
    """Wrap the preparation's stage functions so that the sampler knows which one runs."""
    for name in ("_merge_duplicates", "nearest_neighbours", "pca_planes", "project_to_planes",
                 "neighbour_distances", "remeasured_density", "area_radii",
                 "orient_normals", "propagate_orientation", "outward_votes", "surfel_radii"):
        wrap(sampler, "dofsplat.prep.pointcloud", name)
    wrap(sampler, "dofsplat.prep.normalise", "_object_setup", "normalise: neighbours")
    wrap(sampler, "dofsplat.prep.normalise", "object_weights", "normalise: object_weights")
    wrap(sampler, "dofsplat.prep.normalise", "rendered_level", "normalise: rendered_level")


def wrap_render_stages(sampler: StageSampler):
    """Wrap a first render's stages (``--render``); those an older checkout lacks are left
    out, so that the script measures it too (PYTHONPATH=that checkout)."""
    wrap(sampler, "dofsplat.io.las", "read_las_points", "read the file (LAS/LAZ)")
    wrap(sampler, "dofsplat.prep.pointcloud", "_merge_duplicates", "merge duplicates")
    wrap(sampler, "dofsplat.prep.pointcloud", "merge_duplicates", "merge duplicates")
    wrap(sampler, "dofsplat.prep.pointcloud", "points_to_surfels", "surfels")
    # the cloud on disk (``--on-disk on``): the file decoded into the work folder, its
    # chunks written (their duplicates merged within), the surfels from them
    wrap(sampler, "dofsplat.io.las", "_decoded", "read the file into the work folder")
    wrap(sampler, "dofsplat.prep.cloudfile", "write_cloud", "the cloud into chunks")
    wrap(sampler, "dofsplat.prep.pointcloud", "cloud_to_surfels", "surfels")
    # (the normalisation's level renders the model: a tree built within "surfels" is its)
    wrap(sampler, "dofsplat.lod", "build_hierarchy", "LOD tree")
    wrap(sampler, "dofsplat.lod.cache", "build_hierarchy", "LOD tree")
    wrap(sampler, "dofsplat.io.model_file", "write_model_file", "write the model file")


def render_stages(path: str, args: str, cache: bool = False, prepare: bool = False,
                  disk: str = "auto") -> None:
    import shlex
    import tempfile

    from dofsplat.cli import main as cli

    sampler = StageSampler()
    wrap_render_stages(sampler)
    no_cache = [] if cache else ["--no-cache", "--lod-cache", "off"]
    with tempfile.TemporaryDirectory() as tmp, sampler, _on_disk(disk):
        t0 = time.perf_counter()
        if prepare:
            rc = cli(["prepare", path, "-o", f"{tmp}/model.dofsplat", "--no-cache",
                      "--on-disk", disk, *shlex.split(args)])
        else:
            rc = cli(["render", path, "-o", f"{tmp}/frame.png", *no_cache,
                      *shlex.split(args)])
        seconds = time.perf_counter() - t0
    what = ("prepare" if prepare else "render through the cache" if cache
            else "first render")
    print(f"{path}: {what} in {seconds:.1f} s (exit {rc}); peak RSS by stage, and of it the "
          "process's own memory (RssAnon: RSS less the mapped files' pages; after X: the time "
          "after it, up to the next)")
    for label, peak in sampler.peaks.items():
        own = sampler.own.get(label, 0)
        label = "the frame (after the tree)" if label == "after LOD tree" else label
        print(f"  {label:28s} {peak / 1e9:6.2f} GB  own {own / 1e9:6.2f} GB")
    print(f"  {'the whole run':28s} {max(sampler.peaks.values()) / 1e9:6.2f} GB  own "
          f"{max(sampler.own.values()) / 1e9:6.2f} GB")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path")
    parser.add_argument("--save", help="write the surfel arrays to this .npz")
    parser.add_argument("--check", help="compare the surfel arrays with this .npz")
    parser.add_argument("--stages", action="store_true", help="peak RSS per stage")
    parser.add_argument("--chunk-points", type=float, metavar="N",
                        help="prepare in chunks past N points (prep.pointcloud.CHUNK_POINTS; "
                             "1e12: the whole cloud at once)")
    parser.add_argument("--render", metavar="ARGS",
                        help="a first render with these dofsplat render options: its stages")
    parser.add_argument("--cache", action="store_true",
                        help="with --render: through the caches (a model file's render, or "
                             "run twice: the first keeps the model, the second reads it)")
    parser.add_argument("--prepare", action="store_true",
                        help="the stages of dofsplat prepare PATH --no-cache (with --render "
                             "ARGS: its options)")
    parser.add_argument("--on-disk", choices=("auto", "on", "off"), default="auto",
                        help="a LAS/LAZ cloud prepared from a work folder (prep.cloudfile)")
    parser.add_argument("--sort", action="store_true",
                        help="order the surfels by position before --save / --check")
    args = parser.parse_args()
    if args.render is not None or args.prepare:
        return render_stages(args.path, args.render or "", cache=args.cache,
                             prepare=args.prepare, disk=args.on_disk)

    from dofsplat.io import load
    from dofsplat.prep import pointcloud

    if args.chunk_points is not None:
        pointcloud.CHUNK_POINTS = int(args.chunk_points)
    t0 = time.perf_counter()
    if args.stages:
        sampler = StageSampler()
        wrap_stages(sampler)
        with sampler, _on_disk(args.on_disk):
            surfels = load(args.path, cache="off")
    else:
        with _on_disk(args.on_disk):
            surfels = load(args.path, cache="off")
    seconds = time.perf_counter() - t0
    n = len(surfels)
    print(f"{args.path}: {n:,} surfels in {seconds:.1f} s")
    if args.stages:
        for label, peak in sampler.peaks.items():
            print(f"  {label:28s} {peak / 1e9:6.2f} GB  {peak / n:7.0f} B/point")
    arrays = {name: getattr(surfels, name) for name in FIELDS}
    if args.sort:
        order = np.lexsort(np.asarray(surfels.positions).T[::-1])
        arrays = {name: np.asarray(a)[order] for name, a in arrays.items()}
    if args.save:
        np.savez(args.save, **arrays)
        print(f"saved {args.save}")
    if args.check:
        ref = np.load(args.check)
        bad = [name for name in FIELDS if not np.array_equal(ref[name], arrays[name])]
        print("identical" if not bad else "DIFFERENT: " + ", ".join(
            f"{name} in {_rows_differing(ref[name], arrays[name]):,} rows" for name in bad))
        raise SystemExit(1 if bad else 0)


def _on_disk(mode: str):
    """prep.cloudfile.on_disk(mode), where this checkout has it."""
    try:
        from dofsplat.prep.cloudfile import on_disk
    except ImportError:
        return contextlib.nullcontext()
    return on_disk(mode)


def _rows_differing(a: np.ndarray, b: np.ndarray) -> int:
    """How many rows of a and b differ (all of them where their shapes do)."""
    if a.shape != b.shape:
        return max(len(a), len(b))
    return int(np.count_nonzero(np.any((a != b).reshape(len(a), -1), axis=1)))


if __name__ == "__main__":
    main()
