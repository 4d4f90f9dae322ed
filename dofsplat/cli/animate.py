"""``dofsplat animate MODEL -o OUT --frames N``: a focus pull, an aperture change or a camera
move as a video or a folder of frames, in this process or on a Dask cluster
(:mod:`dofsplat.sequence`)."""

from __future__ import annotations

import sys
from pathlib import Path

from ..errors import DofsplatError
from .cluster import add_cluster_options, check_cluster_args, client_for, close
from .framing import (check_arguments, lens_from_args, photographic_camera,
                      settings_from_args)
from .options import (EXIT_OK, UNITS, HelpFormatter, add_input_options, add_view_options,
                      finite_number, non_negative, positive_number)

_EXAMPLES = """\
examples:
  dofsplat animate --demo -o pull.mp4 --frames 48 --focus-from 1.5 --focus-to 4
  dofsplat animate scan.laz -o turn.mp4 --frames 120 --orbit 360 --workers 2
  dofsplat animate scan.laz -o frames --frames 48 --keyframes moves.json
  dofsplat animate scan.laz -o pull.mp4 --frames 48 --aperture-from 0 --aperture-to 0.2 \\
      --scheduler tcp://scheduler:8786
"""


# every frame's camera and lens is planned before the first renders: 1e8 frames sat silent
# for minutes (and a 24 fps hour is 86,400 frames)
MAX_FRAMES = 100_000


def add_parser(commands) -> None:
    """The ``animate`` subcommand's options."""
    p = commands.add_parser(
        "animate", allow_abbrev=False, epilog=_EXAMPLES + "\n" + UNITS,
        formatter_class=HelpFormatter,
        help="a focus pull, aperture change or orbit as a video or frames",
        description="Render a sequence: the camera and lens change over N frames, by the "
                    "shortcuts below or by a keyframe file, and each frame is what 'render' "
                    "draws for that frame's camera and lens. The model is loaded once. OUT "
                    "is an .mp4 (H.264), a .gif or a folder of frames (frame_0000.png, ...); "
                    "frames already in the folder are kept, so an interrupted run resumes "
                    "(Ctrl-C says how many were kept; the same command again resumes). A "
                    "folder that holds the frames of another model (the folder records the "
                    "model's content hash) or of other arguments is refused, its frames "
                    "left alone. "
                    "Needs pip install 'dofsplat[animate]' (Dask, PyAV).")
    p.add_argument("input", metavar="INPUT", nargs="?",
                   help="model file, as for 'render' (or give --demo)")
    p.add_argument("--demo", action="store_true", help="the built-in demo scene")
    p.add_argument("-o", "--output", metavar="OUT", required=True,
                   help="an .mp4, a .gif, or a folder for the frames")
    seq = p.add_argument_group("sequence")
    seq.add_argument("--frames", metavar="N", type=int, required=True,
                     help=f"number of frames (at most {MAX_FRAMES:,})")
    seq.add_argument("--fps", metavar="F", type=positive_number, default=24.0,
                     help="frames per second of the video (default: 24)")
    seq.add_argument("--focus-from", metavar="P0", type=positive_number,
                     help="focus distance of the first frame, world units")
    seq.add_argument("--focus-to", metavar="P1", type=positive_number,
                     help="focus distance of the last frame")
    seq.add_argument("--aperture-from", metavar="A0", type=non_negative,
                     help="lens diameter of the first frame, world units")
    seq.add_argument("--aperture-to", metavar="A1", type=non_negative,
                     help="lens diameter of the last frame")
    seq.add_argument("--orbit", metavar="DEG", type=finite_number,
                     help="turn the camera by DEG degrees about the target, around the up "
                          "axis, over the sequence")
    seq.add_argument("--keyframes", metavar="FILE.json",
                     help="time-stamped camera and lens values, interpolated "
                          "(README, Sequences); the shortcuts add theirs")
    seq.add_argument("--easing", choices=("smooth", "linear"), default="smooth",
                     help="between keyframes: smooth (default; starts and stops gently) or "
                          "linear")
    seq.add_argument("--frame-format", choices=("png", "npy", "exr"), default="png",
                     help="the frames' format in a folder (default: png)")
    add_cluster_options(seq, "render")
    add_input_options(p)
    add_view_options(p, "render")
    p.set_defaults(run=run)


def run(args) -> int:
    """Check everything, load the model once, plan the frames, render, assemble."""
    from .. import sequence
    from . import render

    _check(args)
    check_arguments(args)
    out = Path(args.output)
    keys, easing = ([], args.easing)
    if args.keyframes is not None:
        keys, easing_file = sequence.load_keyframes(args.keyframes)
        easing = easing_file if args.easing == "smooth" else args.easing
    keys = keys + _shortcut_keyframes(args, sequence.Keyframe)
    if out.suffix.lower() == ".mp4":
        _need_av()

    surfels, camera, default_focus, default_aperture = render.model_and_view(args)
    settings = settings_from_args(args)
    lens = None
    if settings.dof:
        focus = args.focus if args.focus is not None else default_focus
        lens = lens_from_args(args, focus, default_aperture)
        camera = photographic_camera(args, camera, focus)
    if args.focus_at is not None and settings.dof:
        keys = [sequence.Keyframe(0.0, {"focus_at": tuple(args.focus_at)})] + keys

    client, cluster = client_for(args)
    log = None if args.quiet else (lambda m: print(f"dofsplat: {m}", file=sys.stderr,
                                                   flush=True))
    try:
        sequence.animate(surfels, keys, args.frames, camera, lens, settings, output=out,
                         fps=args.fps, easing=easing, frame_format=args.frame_format,
                         client=client, progress=not args.quiet and sys.stderr.isatty(),
                         log=log)
    finally:
        close(client, cluster)
    if not args.quiet:
        # (H.264 wants even sizes: an .mp4 is a pixel larger where the frame size is odd)
        w, h = camera.width, camera.height
        if out.suffix.lower() == ".mp4":
            w, h = w + w % 2, h + h % 2
        print(f"wrote {out} ({args.frames} frame{'s' if args.frames != 1 else ''}, {w}x{h}"
              + (f", {args.fps:g} fps" if out.suffix else "") + ")", file=sys.stderr)
    return EXIT_OK


def _check(args) -> None:
    """The user's mistakes, before any loading or writing."""
    from ..sequence import VIDEO_SUFFIXES

    if (args.input is None) == (not args.demo):
        raise DofsplatError("give either a model file or --demo (the built-in scene), not both"
                            if args.demo else "give a model file to animate, or --demo")
    if args.frames < 1:
        raise DofsplatError(f"--frames must be at least 1, got {args.frames}")
    if args.frames > MAX_FRAMES:
        raise DofsplatError(f"--frames {args.frames:,} is more than {MAX_FRAMES:,} (over an hour "
                            "at 24 fps); render a long sequence in parts, each into its own "
                            "folder")
    out = Path(args.output)
    if out.suffix and out.suffix.lower() not in VIDEO_SUFFIXES:
        raise DofsplatError(f"{out}: write a sequence as .mp4, .gif or a folder (a name "
                            "without an extension)")
    if out.suffix and out.is_dir():
        raise DofsplatError(f"{out} is a folder: give a file name for the video")
    if not out.suffix and out.exists() and not out.is_dir():
        raise DofsplatError(f"{out} exists and is not a folder")
    if not out.resolve().parent.is_dir():
        raise DofsplatError(f"the folder of {out} does not exist")
    from ..io import check_writable_path

    # a file made and removed where the video, or the folder's frames, will be
    check_writable_path(out / "frame.png" if out.is_dir() else out,
                        "a video file name or a folder")
    for a, b in (("focus_from", "focus_to"), ("aperture_from", "aperture_to")):
        if (getattr(args, a) is None) != (getattr(args, b) is None):
            raise DofsplatError(f"--{a.replace('_', '-')} and --{b.replace('_', '-')} go "
                                "together")
    if args.focus_at is not None and args.focus_from is not None:
        raise DofsplatError("--focus-at focuses the first frame: give it or --focus-from, "
                            "not both")
    check_cluster_args(args, "frames render in this process")
    if args.no_dof and (args.focus_from is not None or args.aperture_from is not None):
        raise DofsplatError("--no-dof has no lens to change: drop --focus-from/--aperture-from")
    if args.keyframes is not None and not Path(args.keyframes).is_file():
        if Path(args.keyframes).is_dir():
            raise DofsplatError(f"{args.keyframes}: a folder, not a keyframe file")
        raise DofsplatError(f"no such keyframe file: {args.keyframes}")
    if args.depth is not None or args.stats is not None:
        raise DofsplatError("--depth and --stats describe one frame: use 'dofsplat render' "
                            "for them")
    if args.method != "ours":
        raise DofsplatError("animate renders with --method ours")
    if out.suffix and args.frame_format != "png":
        raise DofsplatError(f"--frame-format {args.frame_format} is for a folder of frames (a "
                            "name without an extension); a video is made from PNG frames")


def _shortcut_keyframes(args, Keyframe) -> list:
    first, last = {}, {}
    if args.focus_from is not None:
        first["focus"], last["focus"] = (args.focus_from,), (args.focus_to,)
    if args.aperture_from is not None:
        first["aperture"], last["aperture"] = (args.aperture_from,), (args.aperture_to,)
    if args.orbit is not None:
        first["orbit"], last["orbit"] = (0.0,), (args.orbit,)
    return [Keyframe(0.0, first), Keyframe(1.0, last)] if first else []


def _need_av() -> None:
    try:
        import av  # noqa: F401
    except ImportError:
        raise DofsplatError("an .mp4 needs PyAV: pip install 'dofsplat[animate]' (or write "
                            "a .gif or a folder of frames)") from None

