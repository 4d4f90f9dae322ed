"""``python -m dofsplat``: the command line of :mod:`dofsplat.cli`."""

from .cli import entry

entry()
