"""``dofsplat demo``: the built-in scene, a textured plane and three spheres."""

from __future__ import annotations

import math

from .framing import (announce_compiling, camera_from_args, check_arguments, check_outputs,
                      render_and_write)
from .options import DEFAULT_SIZE, EPILOG, HelpFormatter, add_view_options


def add_parser(commands) -> None:
    """The ``demo`` subcommand's options."""
    from ..demo import DEMO_APERTURE, DEMO_FOV_DEG, PLANE_SIZE

    demo = commands.add_parser(
        "demo", allow_abbrev=False, epilog=EPILOG,
        formatter_class=HelpFormatter,
        help="render the built-in scene: a textured plane and three spheres",
        description="Render the built-in demo scene: a textured plane with three spheres, "
                    "the middle one in focus. The scene brings its own camera (vertical field "
                    f"of view {DEMO_FOV_DEG:g} degrees) and lens (diameter {DEMO_APERTURE:g} "
                    f"world units; the plane is {PLANE_SIZE:g} world units wide); the options "
                    "below override them.")
    demo.add_argument("-o", "--output", metavar="OUTPUT", default="demo.png",
                      help="image to write: .png, .npy or .exr (default: demo.png)")
    add_view_options(demo, "demo")
    demo.set_defaults(run=run)


def run(args) -> int:
    """``dofsplat demo``: the built-in scene (a textured plane and three spheres)."""
    check_arguments(args)
    outputs = check_outputs(args)
    surfels, camera, default_focus, default_aperture = demo_view(args)
    return render_and_write(args, outputs, surfels, camera, default_focus, default_aperture)


def demo_view(args):
    """(surfels, camera, default focus distance, default lens diameter) of the demo scene at
    the requested size, with the user's camera options applied."""
    from ..demo import demo_scene

    announce_compiling(args)
    width, height = args.size or DEFAULT_SIZE["demo"]
    surfels, base, scene_lens = demo_scene(width, height)
    camera = camera_from_args(args, base)
    # The scene focuses on its middle sphere; a camera moved by the user focuses on its target.
    moved = args.eye is not None or args.target is not None
    default_focus = math.dist(camera.eye, camera.target) if moved else scene_lens.focus_distance
    return surfels, camera, default_focus, scene_lens.diameter
