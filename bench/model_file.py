"""Rendering from a prepared ``.dofsplat`` file against the same model held in memory (issue 50).

    python bench/model_file.py MODEL.dofsplat [--size 1920x1080] [--cocs 0 10 40]

Each frame runs in a process of its own, so that its peak memory is its own: the model
opened from the file (memory maps: the pages a frame reads come from the page cache and
count as the process's file-backed memory, which the kernel can drop) or read whole into
memory first (the in-memory path: the arrays copied from the file, the tree with them), the
default camera of ``dofsplat render`` (focused on the surface at the image centre), a pinhole
frame and frames whose largest circle of confusion is about each ``--cocs`` px. Printed:
the wall time of the frame (after opening the model; numba's kernels are compiled by a
first frame in the same process, not timed), the process's peak memory and its anonymous
memory after the frame (its own allocations: the figure that must stay bounded), the MB of
the file the frame read (the file is evicted from the page cache before it is opened,
read-ahead is off for the frame, ``madvise(MADV_RANDOM)``, and the pages it brought into
the cache are counted with ``mincore``), and whether the two images are the same.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import ctypes, json, mmap, os, resource, sys, time
import numpy as np

def resident_pages(path):
    # pages of the file in the page cache (mincore over a fresh read-only mapping)
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mmap.restype = ctypes.c_void_p
    libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int,
                          ctypes.c_int, ctypes.c_long]
    size = os.path.getsize(path)
    fd = os.open(path, os.O_RDONLY)
    addr = libc.mmap(None, size, mmap.PROT_READ, mmap.MAP_SHARED, fd, 0)
    vec = (ctypes.c_ubyte * ((size + 4095) // 4096))()
    libc.mincore(ctypes.c_void_p(addr), ctypes.c_size_t(size), vec)
    libc.munmap(ctypes.c_void_p(addr), ctypes.c_size_t(size))
    os.close(fd)
    return int(np.count_nonzero(np.frombuffer(vec, np.uint8) & 1))

def evict(path):
    fd = os.open(path, os.O_RDONLY)
    os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    os.close(fd)

from dofsplat.io import load
from dofsplat import render, RenderSettings

path, width, height, coc, in_memory, out = sys.argv[1:7]
width, height, coc = int(width), int(height), float(coc)
model = load(path)
if in_memory == "1":  # the same model, every array in memory
    from dataclasses import fields
    tree = model._lod_hierarchy
    for f in fields(model):
        value = getattr(model, f.name)
        if isinstance(value, np.ndarray):
            setattr(model, f.name, np.array(value))
    for f in fields(tree):
        value = getattr(tree, f.name)
        if isinstance(value, np.ndarray):
            setattr(tree, f.name, np.array(value))
    model._lod_hierarchy = tree
    from dofsplat.fingerprint import content_hash
    from dofsplat.lod.hierarchy import TREE_FIELDS, fingerprint_salt
    from dofsplat.fingerprint import remember_hash
    remember_hash(model, TREE_FIELDS, fingerprint_salt(), tree.fingerprint)
    model.remember_bounds(model.bounds(), model.view_bounds())
sys.path.insert(0, sys.argv[7])  # bench/
from model_file import frame_view
camera, lens = frame_view(model, path, width, height, coc)
from dataclasses import replace
small = replace(camera, width=64, height=48)
render(model, small, lens, RenderSettings())  # compile
if in_memory == "0":  # the model opened afresh from a cold file (the above read most of it)
    import gc
    del model
    gc.collect()
    evict(path)
    model = load(path)
    for value in list(vars(model).values()) + list(vars(model._lod_hierarchy).values()):
        if isinstance(value, np.memmap) and value._mmap is not None:
            value._mmap.madvise(mmap.MADV_RANDOM)  # no read-ahead: the pages the frame reads
before = resident_pages(path)
t = time.perf_counter()
frame = render(model, camera, lens, RenderSettings())
seconds = time.perf_counter() - t
status = dict(line.split(":", 1) for line in open("/proc/self/status") if ":" in line)
kb = lambda key: int(status[key].split()[0]) if key in status else -1
np.save(out, frame.image)
read_mb = (resident_pages(path) - before) * 4096 / 1e6
print(json.dumps({"seconds": seconds, "read_mb": read_mb, "peak_rss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                  "rss_anon_kb": kb("RssAnon"), "rss_file_kb": kb("RssFile"),
                  "splats": frame.stats.get("splats_rendered")}))
"""


def frame_view(model, path, width, height, coc):
    """(camera, lens) of ``dofsplat render``'s default view of the model at this size, the
    lens (None for coc 0) focused on the surface at the image centre, its CoC coc px at the
    model's far side: C_r = K |1/z - 1/P| (this bench's frames, and ``cut_census.py``'s)."""
    import numpy as np

    from dofsplat import ThinLens
    from dofsplat.cli import build_parser
    from dofsplat.cli.render import model_view

    args = build_parser().parse_args(["render", str(path), "--size", f"{width}x{height}"])
    args.input = str(path)
    camera, focus, _ = model_view(args, model)
    if coc <= 0:
        return camera, None
    lo, hi = model.view_bounds()
    far = (float(np.linalg.norm(np.asarray(camera.eye) - 0.5 * (lo + hi)))
           + 0.5 * float(np.linalg.norm(hi - lo)))
    k_per_aperture = ThinLens(focus_distance=focus, aperture=1.0).coc_coefficients(camera)[0]
    return camera, ThinLens(focus_distance=focus,
                            aperture=coc / (k_per_aperture * abs(1 / far - 1 / focus)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--size", default="1920x1080")
    parser.add_argument("--cocs", type=float, nargs="+", default=[0.0, 10.0, 40.0])
    args = parser.parse_args(argv)
    import numpy as np

    width, height = (int(v) for v in args.size.lower().split("x"))
    print(f"{args.model} ({args.model.stat().st_size / 1e6:,.0f} MB), {width}x{height}, "
          f"{platform.processor() or platform.machine()}, {__import__('os').cpu_count()} cores")
    print("| CoC px | from | s | peak RSS MB | anonymous MB after | file MB read by the frame | splats | same image |")
    print("|---:|---|---:|---:|---:|---:|---:|---|")
    for coc in args.cocs:
        images = {}
        for in_memory in ("0", "1"):
            out = f"/tmp/model_file_bench_{in_memory}.npy"
            result = subprocess.run([sys.executable, "-c", CHILD, str(args.model), str(width),
                                     str(height), str(coc), in_memory, out,
                                     str(Path(__file__).resolve().parent)],
                                    capture_output=True, text=True)
            if result.returncode:
                print(result.stderr[-2000:])
                return 1
            row = json.loads(result.stdout.strip().splitlines()[-1])
            images[in_memory] = np.load(out)
            same = "" if in_memory == "0" else (
                "yes" if np.array_equal(images["0"], images["1"]) else "NO")
            read = f"{row['read_mb']:,.0f}" if in_memory == "0" else "-"
            print(f"| {coc:.0f} | {'file' if in_memory == '0' else 'memory'} | "
                  f"{row['seconds']:.2f} | {row['peak_rss_kb'] / 1024:,.0f} | "
                  f"{row['rss_anon_kb'] / 1024:,.0f} | {read} | {row['splats']:,} | {same} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
