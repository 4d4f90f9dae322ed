"""dofsplat's disk cache: prepared models and LOD hierarchies, bounded in size.

Two kinds of file live under one folder (``$XDG_CACHE_HOME/dofsplat`` or
``~/.cache/dofsplat``; ``DOFSPLAT_CACHE_DIR`` moves it):

* ``surfels/``: models that took preparation to become surfels (normals, radii and
  normalisation of a point cloud, sampling of a mesh: seconds to minutes), keyed by the
  file's content, the loader's options and the preparation code itself (``io.load``); a
  large one as a ``.dofsplat`` file with its LOD tree (``io.prepared.keep_stored``);
* ``lod/``: LOD hierarchies, keyed by the surfel arrays they were built from
  (``lod.cache``), and Gaussian scenes' trees, ``gaussians-*.npz`` (``gauss.lod``).

The whole cache is held under ``max_bytes()`` (2 GiB unless ``DOFSPLAT_CACHE_MAX`` says
otherwise, e.g. ``500M`` or ``10G``; ``0`` turns the cache off): after each file written,
the files least recently used (their modification time, renewed at each hit) go first. ``dofsplat cache`` shows
the folder's size and clears it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from .errors import DofsplatError

KINDS = {"surfels": "prepared models", "lod": "LOD hierarchies"}
DEFAULT_MAX_BYTES = 2 << 30


def cache_root() -> Path:
    """The cache folder (it may not exist yet)."""
    if os.environ.get("DOFSPLAT_CACHE_DIR"):
        return Path(os.environ["DOFSPLAT_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or (Path.home() / ".cache")
    return Path(base) / "dofsplat"


def cache_folder(kind: str) -> Path:
    """The folder of one kind of cached file (``KINDS``). DofsplatError where the cache
    folder, or a folder above it, is a file (``DOFSPLAT_CACHE_DIR`` naming a file was a
    NotADirectoryError traceback)."""
    if kind not in KINDS:
        raise ValueError(f"unknown cache kind {kind!r}")
    root = cache_root()
    check_folder(root)
    return root / kind


def check_folder(root: Path) -> None:
    """DofsplatError where ``root``, or the nearest of its parents that exists, is not a
    folder (nothing could be cached under it)."""
    for path in (root, *root.parents):
        try:
            if not path.exists():
                continue
        except OSError:
            return  # unreadable: the write that follows says why, or is skipped
        if path.is_dir():
            return
        via = ("DOFSPLAT_CACHE_DIR" if os.environ.get("DOFSPLAT_CACHE_DIR")
               else "XDG_CACHE_HOME" if os.environ.get("XDG_CACHE_HOME") else "the home folder")
        where = "is a file" if path == root else f"lies under {path}, which is a file"
        raise DofsplatError(f"the cache folder {root} {where}, not a folder (set by {via}): "
                            "point DOFSPLAT_CACHE_DIR at a folder, or set DOFSPLAT_CACHE_MAX=0 "
                            "to cache nothing")


def enabled() -> bool:
    """False where ``DOFSPLAT_CACHE_MAX`` is 0: nothing is then written to the cache."""
    return max_bytes() > 0


def max_bytes() -> int:
    """The cache's size cap: ``DOFSPLAT_CACHE_MAX`` (bytes, or with K, M, G; 0 turns the
    cache off), else 2 GiB."""
    text = os.environ.get("DOFSPLAT_CACHE_MAX")
    return DEFAULT_MAX_BYTES if not text else parse_size(text, "DOFSPLAT_CACHE_MAX")


def parse_size(text: str, what: str = "a size") -> int:
    """Bytes from ``500M``, ``2G``, ``1.5G``, ``123456`` (K, M, G are powers of 1024)."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d*)?)\s*([kKmMgGtT]?)i?[bB]?\s*", text)
    if not m:
        raise DofsplatError(f"{what}: expected a size such as 500M or 2G, got {text!r}")
    scale = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}[m[2].lower()]
    return int(float(m[1]) * scale)


def cached_files(kind: str | None = None) -> list[Path]:
    """The cache's files (of one kind, or all), oldest use first."""
    kinds = KINDS if kind is None else (kind,)
    files = []
    for k in kinds:
        folder = cache_folder(k)
        try:
            if folder.is_dir():
                files += [p for p in folder.iterdir()
                          if p.is_file() and not p.name.startswith(".")]
        except OSError as e:
            raise DofsplatError(f"cannot read the cache folder {folder}: {e.strerror or e}") from None
    return sorted(files, key=_mtime)


def cache_info() -> dict:
    """{kind: (files, bytes)} and "total": (files, bytes), for ``dofsplat cache --info``;
    and "work": (folders, bytes), the work folders (``work_folders``), outside the cap."""
    info = {}
    for kind in KINDS:
        files = cached_files(kind)
        info[kind] = (len(files), sum(_size(p) for p in files))
    info["total"] = (sum(n for n, _ in info.values()), sum(b for _, b in info.values()))
    folders = work_folders()
    info["work"] = (len(folders), sum(_size(p) for f in folders for p in f.rglob("*")))
    return info


def work_folders() -> list[Path]:
    """The folders in which clouds larger than memory are prepared (``prep.cloudfile``):
    each is removed when its preparation completes, so those here were interrupted, and a
    run of the same input resumes from its folder."""
    root = cache_root() / "work"
    try:
        return sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
    except OSError as e:
        raise DofsplatError(f"cannot read the cache folder {root}: {e.strerror or e}") from None


def clear_work() -> tuple[int, int]:
    """Remove the work folders (``work_folders``): (folders, bytes) removed."""
    import shutil

    n = b = 0
    for folder in work_folders():
        size = sum(_size(p) for p in folder.rglob("*"))
        shutil.rmtree(folder, ignore_errors=True)
        if not folder.exists():
            n, b = n + 1, b + size
    return n, b


def clear_cache(kind: str | None = None) -> tuple[int, int]:
    """Delete the cached files (of one kind, or all): (files, bytes) removed."""
    n = b = 0
    for p in cached_files(kind):
        size = _size(p)
        try:
            p.unlink()
        except FileNotFoundError:
            continue
        except OSError as e:
            raise DofsplatError(f"cannot remove {p}: {e.strerror or e}") from None
        n, b = n + 1, b + size
    return n, b


def enforce_cap(limit: int | None = None, keep: Path | None = None) -> list[Path]:
    """Delete the least recently used files until the cache fits ``limit`` bytes
    (``max_bytes()``); ``keep`` (the file just written) goes last. Returns what went."""
    limit = max_bytes() if limit is None else limit
    files = cached_files()
    total = sum(_size(p) for p in files)
    if keep is not None:
        files = [p for p in files if p != keep] + [p for p in files if p == keep]
    gone = []
    for p in files:
        if total <= limit:
            break
        size = _size(p)
        try:
            p.unlink()
        except FileNotFoundError:
            pass
        except OSError:
            continue  # a file we may not remove (a shared cache): leave it, try the next
        total -= size
        gone.append(p)
    return gone


def touch(path: Path) -> None:
    """Mark a cached file as just used (its modification time: the eviction order)."""
    try:
        os.utime(path)
    except OSError:
        pass  # a read-only cache still serves


def format_bytes(n: int) -> str:
    for scale, unit in ((1 << 30, "GB"), (1 << 20, "MB"), (1 << 10, "kB")):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def _size(p: Path) -> int:
    try:
        return p.stat().st_size if p.is_file() else 0
    except FileNotFoundError:
        return 0


def _mtime(p: Path) -> float:
    try:
        return p.stat().st_mtime
    except FileNotFoundError:
        return 0.0
