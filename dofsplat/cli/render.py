"""``dofsplat render MODEL``: a model file, framed, focused and rendered with depth of field."""

from __future__ import annotations

import math
import sys

from .framing import (camera_from_args, capture_camera, check_arguments, check_outputs,
                      framing_camera, median_depth, render_and_write)
from .options import (APERTURE_PER_HALF_DIAGONAL, DEFAULT_SIZE, EPILOG, MODEL_EXTENSIONS,
                      HelpFormatter, add_input_options, add_view_options, default_output,
                      loader_options, prep_cache)


def add_parser(commands) -> None:
    """The ``render`` subcommand's options."""
    render = commands.add_parser(
        "render", allow_abbrev=False, epilog=EPILOG,
        formatter_class=HelpFormatter,
        help="render a model file: surfels, points, a mesh or Gaussian splats",
        description="Render a model with depth of field. Without camera options the "
                    "model is framed from its +z side, focused on its centre, with a lens "
                    f"diameter of {APERTURE_PER_HALF_DIAGONAL:g} x the half diagonal of its "
                    "bounding box.")
    render.add_argument("input", metavar="INPUT",
                        help="model file: surfels, points, a mesh or 3D Gaussian splats: "
                             + ", ".join(MODEL_EXTENSIONS) + " (docs/formats.md)")
    render.add_argument("-o", "--output", metavar="OUTPUT",
                        help="image to write: .png (8-bit sRGB), .npy (float32 linear RGBA, "
                             "H x W x 4) or .exr (float32 linear RGBA + Z) (default: the "
                             "model's name with .png, in the current folder)")
    add_input_options(render)
    add_view_options(render, "render")
    render.set_defaults(run=run)


def run(args) -> int:
    """``dofsplat render``: load a model, frame it, render it, write the outputs."""
    check_arguments(args)
    if args.output is None:
        args.output = default_output(args.input)
    outputs = check_outputs(args)
    surfels = load_model(args)
    camera, default_focus, default_aperture = model_view(args, surfels)
    return render_and_write(args, outputs, surfels, camera, default_focus, default_aperture)


def load_model(args):
    """The model file as surfels (from the cache of prepared models where it is there), with
    its LOD hierarchy built or read back when the settings use one."""
    from ..io import load

    surfels = load(args.input, cache=prep_cache(args), **loader_options(args))
    args.load_info = getattr(surfels, "load_info", None)
    if args.shading is None:  # a capture's photographed colours: unshaded (io.pcd)
        args.shading = getattr(surfels, "shading_hint", None)
    from ..gaussians import Gaussians

    if args.lod and not isinstance(surfels, Gaussians):  # (a Gaussian scene has no surfel tree)
        from ..lod.cache import cached_hierarchy

        log = None if args.quiet else (lambda m: print(f"dofsplat: {m}", file=sys.stderr))
        cached_hierarchy(surfels, args.lod_cache, progress=not args.quiet and sys.stderr.isatty(),
                         log=log)
    return surfels


def model_view(args, surfels):
    """(camera, default focus distance, default lens diameter) of a model: a depth capture
    seen from its sensor, anything else framed whole; the user's camera options applied."""
    lo, hi = surfels.view_bounds()
    half_diagonal = 0.5 * math.dist(lo.tolist(), hi.tolist())
    capture = getattr(surfels, "capture", None)
    placed = any(getattr(args, a) is not None for a in ("eye", "target", "up", "fov", "frustum"))
    if capture is not None and not placed:
        # a depth camera's capture: seen from its sensor, through its own frustum
        camera = camera_from_args(args, capture_camera(capture, args.size))
        default_focus = median_depth(surfels, camera)
    else:
        width, height = args.size or DEFAULT_SIZE["render"]
        base = framing_camera(args, lo, hi, width, height, getattr(surfels, "up_hint", None))
        camera = camera_from_args(args, base)
        default_focus = math.dist(camera.eye, camera.target)
    return camera, default_focus, APERTURE_PER_HALF_DIAGONAL * half_diagonal
