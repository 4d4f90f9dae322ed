"""``dofsplat reference``: the multisample reference, pinhole renders averaged over the lens."""

from __future__ import annotations

from ..errors import DofsplatError
from . import demo, render
from .framing import ESTIMATE_FROM
from .options import EPILOG, HelpFormatter, add_input_options, add_view_options, positive_int

# each sample is a full pinhole frame: 1e8 of them would run for years without a word
MAX_SAMPLES = 100_000


def sample_count(text: str) -> int:
    """--samples: a whole number in 1..MAX_SAMPLES."""
    import argparse

    value = positive_int(text)
    if value > MAX_SAMPLES:
        raise argparse.ArgumentTypeError(f"at most {MAX_SAMPLES:,} lens samples (each one is "
                                         f"a pinhole frame), got {text!r}")
    return value


def add_parser(commands) -> None:
    """The ``reference`` subcommand's options."""
    reference = commands.add_parser(
        "reference", allow_abbrev=False, epilog=EPILOG,
        formatter_class=HelpFormatter,
        help="the multisample reference: pinhole renders over the lens, averaged",
        description="Render the ground truth that depth of field approximates: N pinhole "
                    "images seen from points spread over the lens, each with its frustum "
                    "sheared so that the focal plane stays fixed, averaged (the paper's "
                    "multisampling reference; it takes N times as long as a pinhole render). "
                    "Takes a model file like 'render', or --demo for the built-in scene, and "
                    "the same camera and lens options, so that 'dofsplat compare' can set "
                    "the two images side by side.")
    reference.add_argument("input", metavar="INPUT", nargs="?",
                           help="model file, as for 'render' (or give --demo)")
    reference.add_argument("--demo", action="store_true",
                           help="render the built-in demo scene, with its camera and lens")
    reference.add_argument("-o", "--output", metavar="OUTPUT", default="reference.png",
                           help="image to write: .png, .npy or .exr (default: reference.png)")
    reference.add_argument("--samples", metavar="N", type=sample_count, default=200,
                           help="number of lens samples (default: 200, as in the paper; at "
                                f"most {MAX_SAMPLES:,}); from {ESTIMATE_FROM:,} on, the time "
                                "it will take is estimated first, from one pinhole frame")
    add_input_options(reference)
    add_view_options(reference, "reference")
    reference.set_defaults(run=run, method="reference")


def run(args) -> int:
    """``dofsplat reference``: the multisample reference of a model, or of the demo scene."""
    if (args.input is None) == (not args.demo):
        raise DofsplatError("give either a model file or --demo (the built-in scene), "
                            "not both" if args.demo else
                            "give a model file to render, or --demo for the built-in scene")
    # every lens sample is a full-resolution pinhole render: no LOD hierarchy to build (the
    # parser has no LOD options for this command; the shared code reads these, so any LOD
    # option added later gets RenderSettings' default here rather than an AttributeError)
    from ..frame import RenderSettings

    lod_defaults = RenderSettings()
    args.lod, args.show_lod = False, False
    args.lod_threshold = getattr(args, "lod_threshold", lod_defaults.lod_pixel_threshold)
    args.lod_blur_fraction = getattr(args, "lod_blur_fraction", lod_defaults.lod_blur_fraction)
    return demo.run(args) if args.demo else render.run(args)
