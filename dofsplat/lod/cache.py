"""Keeping a model's LOD hierarchy on disk, so that repeated renders do not rebuild it.

By default the tree goes to the user's cache folder (``$XDG_CACHE_HOME/dofsplat/lod`` or
``~/.cache/dofsplat/lod``), named by the model's fingerprint, so that nothing is written
beside the user's data unasked; a given file name (``--lod-cache lion.lod.npz``) keeps it
next to the model instead. A saved tree carries the fingerprint of the surfel arrays it
was built from: a changed model, or a changed loader that produces other surfels, makes
it stale and it is rebuilt (and the file replaced).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

from .hierarchy import Hierarchy, build_hierarchy, fingerprint


def cache_folder() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or (Path.home() / ".cache")
    return Path(base) / "dofsplat" / "lod"


def cached_hierarchy(surfels, cache: str | os.PathLike | None = "auto", progress: bool = False,
                     log: Callable[[str], None] | None = None) -> Hierarchy:
    """The model's hierarchy: loaded from the cache when fresh, else built (and saved).

    cache: "auto" (the user cache folder), "off" (build, save nothing), or the path of an
           ``.npz`` file to read and write
    log:   called with one line when a tree is built (and where it was saved)
    The tree is also kept on the ``Surfels`` object, where ``render`` finds it.
    """
    if cache is None or str(cache) == "off":
        path = None
    elif str(cache) == "auto":
        path = cache_folder() / f"{fingerprint(surfels)}.npz"
    else:
        path = Path(cache)
    tree = Hierarchy.load(path, surfels) if path is not None else None
    if tree is None:
        tree = build_hierarchy(surfels, progress=progress)
        message = (f"built the LOD hierarchy ({len(tree):,} nodes, {tree.depth} levels) "
                   f"in {tree.build_seconds:.1f} s")
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                tree.save(path)
                message += f", kept in {path}"
            except OSError as exc:  # an unwritable cache costs a rebuild next time, no more
                message += f"; could not keep it in {path} ({exc.strerror or exc})"
        if log is not None:
            log(message)
    surfels._lod_hierarchy = tree
    return tree
