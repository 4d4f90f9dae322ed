"""``dofsplat render MODEL``: a model file, framed, focused and rendered with depth of field."""

from __future__ import annotations

import math
import sys

from .framing import (announce_compiling, camera_from_args, capture_camera, centre_focus,
                      check_arguments, check_outputs, framing_camera, render_and_write,
                      settings_from_args)
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
                    "model is seen from its most visible side, filling the frame, focused "
                    "on the surface at the image centre, with a lens "
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


def model_and_view(args):
    """(model, camera, default focus distance, default lens diameter): the demo scene's
    with --demo, else the model file's (``load_model``, ``model_view``); for ``view`` and
    ``animate``."""
    if args.demo:
        from .demo import demo_view

        return demo_view(args)
    surfels = load_model(args)
    return (surfels, *model_view(args, surfels))


def load_model(args):
    """The model file as surfels (from the cache of prepared models where it is there), with
    its LOD hierarchy built or read back when the settings use one."""
    from ..io import load

    announce_compiling(args, args.input)
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
    seen from its sensor, anything else from its most visible side, filling the frame
    (``framing.framing_camera``); the user's camera options applied. The default focus is
    --focus where given, else the distance to --target where one is given, else the surface
    seen at the image centre (``framing.centre_focus``); ``args.default_focus_source`` says
    which, in words."""
    from ..gaussians import Gaussians

    lo, hi = surfels.view_bounds()
    half_diagonal = 0.5 * math.dist(lo.tolist(), hi.tolist())
    capture = getattr(surfels, "capture", None)
    placed = any(getattr(args, a, None) is not None
                 for a in ("eye", "target", "up", "fov", "frustum", "focal_length_mm"))
    if capture is not None and not placed:
        # a depth camera's capture: seen from its sensor, through its own frustum; a
        # Gaussian scene from its trainer's first camera, at render's default width
        size = args.size
        if size is None and isinstance(surfels, Gaussians):
            width = DEFAULT_SIZE["render"][0]
            size = (width, max(1, round(width * capture["size"][1] / capture["size"][0])))
        camera = camera_from_args(args, capture_camera(capture, size))
    else:
        width, height = args.size or DEFAULT_SIZE["render"]
        if args.eye is not None or args.target is not None:
            surfels_to_fit = None  # the user places the camera: the box is framed as before
        else:
            surfels_to_fit = surfels
        base = framing_camera(args, lo, hi, width, height, getattr(surfels, "up_hint", None),
                              surfels=surfels_to_fit)
        camera = camera_from_args(args, base)
    if args.target is not None:
        default_focus, source = math.dist(camera.eye, camera.target), "--target"
    elif getattr(args, "focus", None) is not None:
        default_focus, source = args.focus, "--focus"  # (no probe render: the user's focus)
    else:
        default_focus, source = centre_focus(surfels, camera, settings_from_args(args))
    args.default_focus_source = source
    return camera, default_focus, APERTURE_PER_HALF_DIAGONAL * half_diagonal
