"""The ``dofsplat`` command line: render a surfel model, or the built-in demo scene.

    dofsplat render MODEL.ply -o OUT.png [camera, lens and rendering options]
    dofsplat demo [-o demo.png] [the same options; the scene supplies the defaults]
    dofsplat reference (MODEL.ply | --demo) [-o reference.png] [--samples N] [the same options]
    dofsplat compare A B [--diff DIFF.png] [--json FILE.json]
    dofsplat convert INPUT -o OUT.ply [--k K] [--normalise object|render|none]
    dofsplat prepare INPUT [-o OUT.dofsplat] [the same input options]
    dofsplat view (MODEL | --demo) [--port N] [--no-browser] [the same options]
    dofsplat animate (MODEL | --demo) -o OUT.mp4 --frames N [--focus-from P0 --focus-to P1 ...]
    dofsplat cache [--info | --clear [all|surfels|lod]]

One module per subcommand, each with ``add_parser(commands)`` and ``run(args)``;
:mod:`.options` holds the argument types and the option groups they share, :mod:`.framing`
the way from options to camera, lens, settings and written outputs.

``render`` and ``demo`` take ``--method ours|postfilter`` (our DOF, or the post-process
baseline of :mod:`dofsplat.postfilter`); ``reference`` averages pinhole renders over the
lens (:mod:`dofsplat.reference`); ``compare`` prints PSNR and SSIM (:mod:`dofsplat.metrics`).

A command runs in this order, so that a user mistake costs no rendering time and leaves no
file behind: parse and check the arguments, check the output paths, load the model (or
build the demo scene), set up camera, lens and settings, autofocus (``--focus-at``),
render, write the outputs (atomically, by :mod:`dofsplat.io`), print one summary line.

:func:`main` returns the exit status: 0 on success, 2 for a user mistake (one line
``dofsplat: error: ...`` on stderr), 130 on Ctrl-C. Anything else is a bug and keeps its
traceback. numpy, numba and the renderer are imported only when a command runs.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

from ..errors import DofsplatError
from . import animate, cache, compare, convert, demo, prepare, reference, render, view
from .framing import format_count
from .options import (EPILOG, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, HelpFormatter, Parser,
                      attach_negative_values, default_output)

__all__ = ["main", "entry", "build_parser", "default_output", "format_count", "EXIT_OK", "EXIT_USAGE",
           "EXIT_INTERRUPTED"]

COMMANDS = (render, demo, view, reference, animate, compare, convert, prepare, cache)  # in the order --help lists them


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0, 2 for a user mistake, 130)."""
    parser = build_parser()
    try:
        try:
            args = parser.parse_args(attach_negative_values(sys.argv[1:] if argv is None
                                                            else list(argv)))
        except SystemExit as e:  # --help and --version exit through here, status 0
            return e.code if isinstance(e.code, int) else EXIT_OK
        if getattr(args, "quiet", False):
            # every progress bar (loaders, hierarchy, reference) is tqdm's: one switch
            os.environ["TQDM_DISABLE"] = "1"
        with warnings.catch_warnings():
            warnings.showwarning = show_warning
            return args.run(args)
    except DofsplatError as e:
        print_error(str(e))
        return EXIT_USAGE
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED  # quietly, as a shell's own commands end on Ctrl-C
    except SystemError as e:
        # Ctrl-C inside a numba kernel: the KeyboardInterrupt is pending when the kernel
        # returns, and CPython reports "returned a result with an exception set" over it
        if caused_by_interrupt(e):
            return EXIT_INTERRUPTED
        raise


def entry() -> None:
    """The ``dofsplat`` console script: :func:`main`, then exit with its status. After Ctrl-C
    the process ends at once (``os._exit``, the outputs' temporary files already removed):
    tearing the interpreter down while numba's threads or its compiler were mid-call could
    crash it (a segmentation fault, status -11, in one of four interrupted renders)."""
    status = main()
    if status == EXIT_INTERRUPTED:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)


def caused_by_interrupt(e: BaseException) -> bool:
    """Whether a KeyboardInterrupt lies in e's chain of causes and contexts."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = Parser(
        prog="dofsplat", allow_abbrev=False, epilog=EPILOG,
        formatter_class=HelpFormatter,
        description="Render surfel models (points with normals and radii) with depth of "
                    "field, by EWA surface splatting (Krivanek & Zara 2003).")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for command in COMMANDS:
        command.add_parser(commands)
    parser.set_defaults(run=no_command)
    return parser


def no_command(args) -> int:
    raise DofsplatError("no command given: use 'dofsplat render INPUT -o OUTPUT' or "
                        "'dofsplat demo' (dofsplat --help tells more)")


# -- messages ----------------------------------------------------------------------------


def print_error(message: str) -> None:
    print(f"dofsplat: error: {one_line(message)}", file=sys.stderr)


def show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"dofsplat: warning: {one_line(str(message))}", file=sys.stderr)


def one_line(message: str) -> str:
    return " ".join(part.strip() for part in message.splitlines() if part.strip()) or "failed"
