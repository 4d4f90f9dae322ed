"""Keeping a model's LOD hierarchy on disk, so that repeated renders do not rebuild it.

By default the tree goes to the user's cache folder (``$XDG_CACHE_HOME/dofsplat/lod`` or
``~/.cache/dofsplat/lod``; ``dofsplat.cache`` bounds its size), named by the model's
fingerprint, so that nothing is written
beside the user's data unasked; a given file name (``--lod-cache lion.lod.npz``) keeps it
next to the model instead. A saved tree carries the fingerprint of the surfel arrays it
was built from: a changed model, or a changed loader that produces other surfels, makes
it stale and it is rebuilt (and the file replaced).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

from .. import cache
from ..errors import DofsplatError
from .hierarchy import Hierarchy, build_hierarchy, built_for, default_small, fingerprint


def cache_folder() -> Path:
    return cache.cache_folder("lod")


def cached_hierarchy(surfels, cache_arg: str | os.PathLike | None = "auto",
                     progress: bool = False,
                     log: Callable[[str], None] | None = None) -> Hierarchy:
    """The model's hierarchy: loaded from the cache when fresh, else built (and saved).

    cache_arg: "auto" (the user cache folder, size-capped), "off" (build, save nothing),
           or the path of an ``.npz`` file to read and write
    log:   called with one line when a tree is built and saved (where), or took a second
    The tree is also kept on the ``Surfels`` object, where ``render`` finds it.
    """
    kept = getattr(surfels, "_lod_hierarchy", None)
    if kept is not None and getattr(kept, "leaf_ordered", False):
        return kept  # a stored model's own tree (io.model_file), checked when it was opened
    if built_for(kept, surfels):
        return kept  # built with the model (io.prepared.keep_stored, lod.hierarchy_for)
    if cache_arg is None or str(cache_arg) == "off":
        path = None
    elif str(cache_arg) == "auto":
        path = cache_folder() / f"{fingerprint(surfels)}.npz" if cache.enabled() else None
    else:
        path = Path(cache_arg)
    tree = None
    if path is not None:
        try:
            tree = Hierarchy.load(path, surfels)
        except DofsplatError:
            if str(cache_arg) != "auto":
                raise  # the user's own file: say what is wrong with it
            try:
                path.unlink(missing_ok=True)  # a damaged cache entry: rebuilt below
            except OSError:
                pass  # an unreadable cache folder (a file where it should be): rebuilt, not kept
    if (tree is not None and str(cache_arg) == "auto"
            and tree.small != default_small(tree.n_surfels)):
        tree = None  # kept before COMPACT_FROM moved: the same frames, not today's memory
    if tree is not None and str(cache_arg) == "auto":
        cache.touch(path)  # just used: evicted last
    if tree is None:
        tree = build_hierarchy(surfels, progress=progress)
        message = (f"built the LOD hierarchy ({len(tree):,} nodes, {tree.depth} levels) "
                   f"in {tree.build_seconds:.1f} s")
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                tree.save(path)
                if str(cache_arg) == "auto":
                    cache.enforce_cap(keep=path)  # (a tree larger than the cap goes at once)
                message += f", kept in {path}" if path.exists() else ", larger than the cache"
            except (OSError, DofsplatError) as exc:  # an unwritable cache costs a rebuild
                why = getattr(exc, "strerror", None) or exc
                message += f"; could not keep it in {path} ({why})"
        if log is not None and (path is not None or tree.build_seconds >= 1.0):
            log(message)  # (a quick build that is kept nowhere is not worth a line)
    surfels._lod_hierarchy = tree
    return tree
