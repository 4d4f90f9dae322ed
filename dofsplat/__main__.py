"""``python -m dofsplat``: the command line of :mod:`dofsplat.cli`."""

from .cli import main

raise SystemExit(main())
