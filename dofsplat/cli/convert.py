"""``dofsplat convert``: any model file to normalised surfels in a surfel PLY, done once; a
3D Gaussian Splatting scene (SPZ, SOG, compressed PLY) to a standard 3DGS PLY."""

from __future__ import annotations

import sys
from pathlib import Path

from ..errors import DofsplatError
from .options import (EXIT_OK, MODEL_EXTENSIONS, HelpFormatter, add_input_options,
                      default_normalisation, loader_options, prep_cache)


def add_parser(commands) -> None:
    """The ``convert`` subcommand's options."""
    convert = commands.add_parser(
        "convert", allow_abbrev=False, formatter_class=HelpFormatter,
        help="turn a model file into normalised surfels, saved as a surfel PLY",
        description="Load any model file as 'render' does (points get normals and radii, "
                    "meshes and Gaussian splats become surfels, points and meshes get the "
                    "per-surfel normalisation so that splats sum to 1 over the surface, paper "
                    "Section 6.3), and save the surfels, so that this is done once. A 3D "
                    "Gaussian Splatting scene (.spz, SOG, compressed or standard 3DGS PLY) "
                    "is saved as Gaussians in a standard 3DGS PLY instead.",
        epilog="examples:\n  dofsplat convert scan.laz -o scan-surfels.ply\n"
               "  dofsplat convert dragon.ply.gz -o dragon.ply --points vertices "
               "--normalise render")
    convert.add_argument("input", metavar="INPUT",
                         help="model file: " + ", ".join(MODEL_EXTENSIONS)
                         + ", .spz, .sog, a SOG meta.json, lod-meta.json or their folder")
    convert.add_argument("-o", "--output", metavar="OUT.ply", required=True,
                         help="surfel PLY (or 3DGS PLY, for Gaussians) to write (.ply, "
                              "binary, or .ply.gz)")
    convert.add_argument("-q", "--quiet", action="store_true",
                         help="no progress bars, no summary line")
    add_input_options(convert)
    convert.set_defaults(run=run)


def run(args) -> int:
    """``dofsplat convert``: any model file to a normalised surfel PLY, done once; Gaussians
    to a 3DGS PLY."""
    import time

    from ..gaussians import Gaussians
    from ..io import SAVERS, check_writable_path, load, save_surfels

    out = Path(args.output)
    if not any(out.name.lower().endswith(ext) for ext in SAVERS):
        raise DofsplatError(f"{out}: a converted model is saved as a PLY; give a name "
                            f"ending in {' or '.join(sorted(SAVERS))}")
    check_writable_path(out, "a surfel file name")
    if Path(args.input).exists() and out.resolve() == Path(args.input).resolve():
        raise DofsplatError(f"the output {out} would overwrite the input")
    t0 = time.perf_counter()
    model = load(args.input, cache=prep_cache(args), **loader_options(args))
    save_surfels(out, model)  # Gaussians go to a 3DGS PLY
    if not args.quiet:
        if isinstance(model, Gaussians):
            what = f"{len(model):,} Gaussians, SH degree {model.sh_degree}, a 3DGS PLY"
        else:
            how = args.normalise or default_normalisation(Path(args.input))
            what = f"{len(model):,} surfels, normalisation: {how}"
        print(f"wrote {out} ({what}, {time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    return EXIT_OK
