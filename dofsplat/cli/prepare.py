"""``dofsplat prepare``: a model made ready to render once, as one ``.dofsplat`` file (surfels
and their LOD tree, read through memory maps: ``io.model_file``, docs/outofcore.md)."""

from __future__ import annotations

import sys
from pathlib import Path

from ..errors import DofsplatError
from .cluster import add_cluster_options, check_cluster_args, client_for, close
from .options import (EXIT_OK, MODEL_EXTENSIONS, HelpFormatter, add_input_options,
                      loader_options, prep_cache)


def add_parser(commands) -> None:
    """The ``prepare`` subcommand's options."""
    prepare = commands.add_parser(
        "prepare", allow_abbrev=False, formatter_class=HelpFormatter,
        help="prepare a model once (surfels and LOD tree) as a .dofsplat file to render from",
        description="Load a model as 'render' does (points get normals and radii, meshes "
                    "are sampled, the per-surfel normalisation), build its LOD tree, and "
                    "write both as one .dofsplat file, which render, view and animate open "
                    "in milliseconds and read through memory maps: a frame reads the pages "
                    "of the nodes it draws, and the kernel keeps or drops them as memory "
                    "allows. "
                    "The file is written under a temporary name and renamed when complete, "
                    "so an interrupted run leaves nothing that a render would trust.",
        epilog="examples:\n  dofsplat prepare scan.laz -o scan.dofsplat\n"
               "  dofsplat render scan.dofsplat -o scan.png --f-number 2 --focus-at 400 300")
    prepare.add_argument("input", metavar="INPUT",
                         help="model file: " + ", ".join(
                             e for e in MODEL_EXTENSIONS if e not in (".spz", ".sog", ".dofsplat"))
                         + " (not a Gaussian scene)")
    prepare.add_argument("-o", "--output", metavar="OUT.dofsplat",
                         help="the file to write (default: the input's name with .dofsplat)")
    prepare.add_argument("-q", "--quiet", action="store_true",
                         help="no progress bars, no summary line")
    add_input_options(prepare)
    disk = prepare.add_argument_group(
        "a cloud larger than memory", "A LAS/LAZ or binary PLY cloud whose preparation "
        "would take more than half the memory available is streamed into chunks in a work "
        "folder and prepared from there, a chunk and its halo in memory at a time "
        "(docs/outofcore.md); the folder is removed when done, and a run interrupted "
        "resumes from it.")
    disk.add_argument("--on-disk", choices=("auto", "on", "off"), default="auto",
                      help="prepare the cloud from a work folder: by its size (auto), "
                           "always (on) or never (off) (default: %(default)s)")
    disk.add_argument("--work-dir", metavar="DIR",
                      help="where the work folder goes, with about 190 bytes a point free "
                           "(default: the cache folder's work/)")
    cluster = prepare.add_argument_group(
        "a cluster", "A point cloud of more than a million points is prepared in chunks "
        "(each with a halo of its neighbours, bounded memory); they can run on Dask workers, "
        "with the same result. Each worker holds the whole cloud: on one machine the run "
        "in this process, which gives each chunk every core, is the leaner.")
    add_cluster_options(cluster, "prepare the chunks")
    prepare.set_defaults(run=run)


def run(args) -> int:
    """``dofsplat prepare``: load, build the tree, write the ``.dofsplat`` file."""
    import time

    from ..gaussians import Gaussians
    from ..io import check_writable_path, load
    from ..io.model_file import EXTENSION, write_model_file
    from ..lod.cache import cached_hierarchy
    from ..prep.chunks import on_cluster
    from ..prep.cloudfile import on_disk

    source = Path(args.input)
    out = Path(args.output) if args.output else _default_output(source, EXTENSION)
    if out.suffix.lower() != EXTENSION:
        raise DofsplatError(f"{out}: a prepared model is a {EXTENSION} file; give a name "
                            f"ending in {EXTENSION}")
    check_writable_path(out, "a model file name")
    if source.exists() and out.resolve() == source.resolve():
        raise DofsplatError(f"the output {out} would overwrite the input")
    check_cluster_args(args, "the chunks are prepared in this process")
    progress = not args.quiet and sys.stderr.isatty()
    t0 = time.perf_counter()
    client, cluster = client_for(args)
    try:
        with on_cluster(client), on_disk(args.on_disk, args.work_dir):
            model = load(source, cache=prep_cache(args), **loader_options(args))
    finally:
        close(client, cluster)
    if isinstance(model, Gaussians):
        raise DofsplatError(f"{source} is a Gaussian scene: it needs no preparation (render "
                            "it as it is)")
    # the tree: the LOD cache's where it holds this model's (render built it), else built
    tree = cached_hierarchy(model, progress=progress)
    write_model_file(out, model, tree, source={"path": str(source)}, progress=progress)
    if not args.quiet:
        size = out.stat().st_size
        print(f"wrote {out} ({len(model):,} surfels and their LOD tree, {size / 1e6:,.1f} MB, "
              f"{size / len(model):.0f} bytes a surfel; {time.perf_counter() - t0:.1f} s)",
              file=sys.stderr)
    return EXIT_OK


def _default_output(source: Path, extension: str) -> Path:
    """The input's name with its model extensions replaced (scan.ply.gz -> scan.dofsplat)."""
    name = source.name
    for ext in sorted(MODEL_EXTENSIONS, key=len, reverse=True):
        if name.lower().endswith(ext):
            name = name[:-len(ext)]
            break
    return source.with_name(name + extension)
