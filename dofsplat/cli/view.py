"""``dofsplat view MODEL``: the model in the browser viewer (:mod:`dofsplat.viewer`): orbit,
click to focus, turn the aperture, see the depth of field change."""

from __future__ import annotations

import sys

from ..errors import DofsplatError
from .framing import check_arguments, lens_from_args, settings_from_args
from .options import EXIT_OK, UNITS, HelpFormatter, add_input_options, add_view_options


def add_parser(commands) -> None:
    """The ``view`` subcommand's options."""
    p = commands.add_parser(
        "view", allow_abbrev=False, epilog="examples:\n  dofsplat view --demo\n"
        "  dofsplat view scan.laz --port 8081 --no-browser\n\n" + UNITS,
        formatter_class=HelpFormatter,
        help="the model in a browser viewer: orbit, click to focus",
        description="Serve the model in a web viewer (viser): orbit, pan and zoom with the "
                    "mouse, click on the model to focus there, set the focus distance, lens "
                    "and LOD in the panel, save the frame. The options below set the first "
                    "view, lens and rendering, as for 'render'. Needs pip install "
                    "'dofsplat[view]'.")
    p.add_argument("input", metavar="INPUT", nargs="?",
                   help="model file, as for 'render' (or give --demo)")
    p.add_argument("--demo", action="store_true", help="the built-in demo scene")
    srv = p.add_argument_group("server")
    srv.add_argument("--port", metavar="N", type=int, default=8080,
                     help="the port to serve on (default: 8080)")
    srv.add_argument("--host", metavar="ADDR", default="127.0.0.1",
                     help="the address to listen on (default: 127.0.0.1, this machine only; "
                          "0.0.0.0 shares the model with every interface's network)")
    srv.add_argument("--no-browser", action="store_true",
                     help="do not open a browser; only print the address")
    srv.add_argument("--save-dir", metavar="DIR", default=".",
                     help="where 'Save image' writes its PNG and JSON (default: the current "
                          "folder; the panel shows the full path)")
    add_input_options(p)
    add_view_options(p, "render")
    p.set_defaults(run=run)


def run(args) -> int:
    """Check the options, open the page, then load the model (the kernels compile
    meanwhile, on a first run) and serve until Ctrl-C."""
    from pathlib import Path

    from . import render

    if (args.input is None) == (not args.demo):
        raise DofsplatError("give either a model file or --demo (the built-in scene), not both"
                            if args.demo else "give a model file to view, or --demo")
    if not 0 <= args.port <= 65535:
        raise DofsplatError(f"--port must be 0..65535, got {args.port}")
    if args.method != "ours":
        raise DofsplatError("the viewer renders with --method ours")
    for flag, name in (("--depth", "depth"), ("--stats", "stats")):
        if getattr(args, name, None) is not None:
            raise DofsplatError(f"view has no {flag[2:]} output ({flag} is for render and "
                                "demo; 'Save image' in the page writes the frame)")
    if not Path(args.save_dir).expanduser().is_dir():
        raise DofsplatError(f"--save-dir: no such folder: {args.save_dir}")
    try:
        import viser  # noqa: F401 - fail before loading the model
    except ImportError:
        raise DofsplatError("the viewer needs viser: pip install 'dofsplat[view]'") from None
    check_arguments(args)
    if not args.demo:
        from ..io import model_options

        model_options(args.input)  # a missing file or an unknown format: before the server
    from .framing import announce_compiling

    announce_compiling(args, None if args.demo else args.input)

    def load():
        from ..viewer import Scene

        surfels, camera, default_focus, default_aperture = render.model_and_view(args)
        settings = settings_from_args(args)
        args.no_dof = False  # the viewer always has a lens: its diameter may be set to 0
        lens = lens_from_args(args, args.focus or default_focus, default_aperture)
        if args.focus_at is not None:
            from dataclasses import replace

            from ..render import focus_distance_at

            lens = replace(lens, focus_distance=focus_distance_at(
                surfels, camera, *args.focus_at, settings=settings))
        return Scene(surfels, camera, lens, settings)

    from ..viewer import serve

    log = (lambda m: None) if args.quiet else None
    from .framing import gaussian_scene

    serve(load, port=args.port, host=args.host, open_browser=not args.no_browser, log=log,
          save_dir=args.save_dir, say_compiling=False,
          gaussian=not args.demo and gaussian_scene(args.input))
    if not args.quiet:
        print("dofsplat: viewer stopped", file=sys.stderr)
    return EXIT_OK
