"""Prepared models in the disk cache: a point cloud or a mesh made into surfels once.

Loading a scan or a mesh costs seconds to minutes of preparation (normals, radii, the
per-surfel normalisation; a mesh's sampling). ``load_prepared`` keeps the result in
``dofsplat.cache``'s ``surfels/`` folder when preparation took at least MIN_SECONDS, and
reads it back (milliseconds) when the same file is loaded with the same options by the same
preparation code. The key is a hash of:

* the file's bytes, the names, sizes and times of the files it names beside it (a mesh's
  material library and textures: ``referenced_files``), and a ``texture`` option's file;
* the loader and its options;
* the source of the preparation code (``dofsplat/prep``, ``dofsplat/io``,
  ``dofsplat/surfels.py``, and the renderer's unless ``normalise="none"``: both
  normalisations render, "render" its captures and "object" its level):
  a change to how surfels are made makes old entries unused (the size cap evicts them).

Any load of MIN_SECONDS or more is kept, a large surfel PLY too. A model of STORED_FROM
surfels or more is kept as a ``.dofsplat`` file with its LOD tree (``io.model_file``, what
``dofsplat prepare`` writes; ``keep_stored``): a later render opens it in milliseconds and
reads the pages its frame needs, where an ``.npz`` would be read whole. Its first load
returns the file's memory maps too where the model is large against the memory available.
A model read back from the cache does not repeat the warnings its first load gave (dropped
NaN points, for instance).
Gaussian scenes (``dofsplat.Gaussians``) are never kept: they need no preparation, and
``dofsplat.io.load`` does not look for them here.

Files are written atomically; a cache that cannot be written costs a preparation next time,
no more.
"""

from __future__ import annotations

import hashlib
import os
import sys
import tempfile
import time
import warnings
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .. import cache
from ..errors import DofsplatError
from ..surfels import Material, Surfels

MIN_SECONDS = 0.5  # a model that loads faster is not worth a copy on disk
STORED_FROM = 1 << 21  # surfels from which a model is kept as a .dofsplat file with its tree
FROM_FILE = 16  # ... and its first frame drawn from the file past 1/16 of the memory available
OPTIONAL = ("opacity", "tangent", "radius_v", "weight")
_CODE_HASH: list[str] = []


def load_prepared(path: Path, loader, options: dict, use_cache: bool = True):
    """``loader(path, **options)``, through the cache (module notes): Surfels, or the
    Gaussians of a Gaussian scene (never written to the cache)."""
    key = cache_key(path, loader, options) if use_cache and cache.enabled() else None
    file = cache.cache_folder("surfels") / f"{key}.npz" if key else None
    t0 = time.perf_counter()
    stored = file.with_suffix(".dofsplat") if file is not None else None
    for kept, read in ((stored, read_stored), (file, read_surfels)):  # (a large model, a small)
        if kept is not None and _exists(kept):
            surfels = read(kept)
            if surfels is not None:
                cache.touch(kept)
                surfels.load_info = {"seconds": time.perf_counter() - t0, "from_cache": True,
                                     "cache_file": str(kept)}
                return surfels
    surfels = loader(path, **options)
    seconds = time.perf_counter() - t0
    surfels.load_info = {"seconds": seconds, "from_cache": False, "cache_file": None}
    if file is not None and seconds >= MIN_SECONDS and isinstance(surfels, Surfels):
        if len(surfels) >= STORED_FROM:
            return keep_stored(stored, surfels, path)
        try:
            write_surfels(file, surfels)
            cache.enforce_cap(keep=file)  # (a model larger than the cap goes at once)
            if file.exists():
                surfels.load_info["cache_file"] = str(file)
        except (OSError, DofsplatError):
            pass  # an unwritable cache costs the preparation next time, no more
    return surfels


def keep_stored(stored: Path, surfels: Surfels, source: Path) -> Surfels:
    """A large model kept as a ``.dofsplat`` file (``io.model_file``: its LOD tree built
    now, the render's own), so that a later load opens the file in milliseconds instead of
    reading the model whole. Returned as that file's memory maps, the model in memory
    dropped, where the model and its tree take more than 1/FROM_FILE of the memory available
    now (``machine.available_memory``): the first frame then holds what a later one holds.
    Otherwise, or where the file cannot be kept (an unwritable cache, a model larger than
    the cap), the model in memory, its tree attached so that the render does not build it
    again (the same frames: ``tests/test_cache.py``)."""
    from ..machine import available_memory
    from ..lod.hierarchy import build_hierarchy
    from .model_file import SURFEL_ARRAYS, write_model_file

    info = surfels.load_info
    tree = build_hierarchy(surfels, progress=sys.stderr.isatty())
    try:
        stored.parent.mkdir(parents=True, exist_ok=True)
        write_model_file(stored, surfels, tree, source={"path": str(source)},
                         progress=sys.stderr.isatty())
        size = stored.stat().st_size
        if stored in cache.enforce_cap(keep=stored):  # larger than the cap: gone at once
            warnings.warn(
                f"{source}: the prepared model ({cache.format_bytes(size)} with its LOD tree) "
                f"is larger than the cache ({cache.format_bytes(cache.max_bytes())}): it is "
                f"prepared again next time; `dofsplat prepare {source}` keeps it in a file "
                f"of its own (or raise DOFSPLAT_CACHE_MAX)")
    except (OSError, DofsplatError):
        pass  # an unwritable cache costs the preparation next time, no more
    held = tree.nbytes() + sum(getattr(surfels, name).nbytes for name in SURFEL_ARRAYS
                               if getattr(surfels, name) is not None)
    kept = None
    if _exists(stored) and held * FROM_FILE > available_memory():
        kept = read_stored(stored)
    if kept is None:
        surfels._lod_hierarchy = tree  # (lod.cache.cached_hierarchy takes it)
        if _exists(stored):
            surfels.load_info = {**info, "cache_file": str(stored)}
        return surfels
    kept.load_info = {**info, "cache_file": str(stored)}
    return kept


def read_stored(file: Path) -> Surfels | None:
    """A model kept as a ``.dofsplat`` file, or None where it is unreadable (it is then
    prepared again and replaced)."""
    from .model_file import read_model_file

    try:
        return read_model_file(file)
    except DofsplatError:
        return None


def cache_key(path: Path, loader, options: dict) -> str:
    """The hash that names a prepared model (module notes)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(_code_hash(render=options.get("normalise") != "none").encode())
    h.update(f"{loader.__module__}.{loader.__qualname__}".encode())
    h.update(repr(sorted((k, str(v)) for k, v in options.items())).encode())
    _hash_file(h, path)
    for used in referenced_files(path):
        st = used.stat()
        h.update(f"{used.name}\0{st.st_size}\0{st.st_mtime_ns}".encode())
    if options.get("texture"):
        texture = Path(options["texture"])
        if texture.is_file():
            _hash_file(h, texture)
    return h.hexdigest()


def write_surfels(file: Path, surfels: Surfels) -> None:
    """The surfel arrays and material as an uncompressed ``.npz``, atomically."""
    arrays = {"positions": surfels.positions, "normals": surfels.normals,
              "radius": surfels.radius, "colors": surfels.colors}
    for name in OPTIONAL:
        value = getattr(surfels, name)
        if value is not None:
            arrays[name] = value
    material = asdict(surfels.material)
    arrays["material"] = np.array([material[k] for k in sorted(material)], np.float64)
    for name, value in (getattr(surfels, "capture", None) or {}).items():
        arrays[f"capture.{name}"] = np.asarray(value)  # a depth camera's view (io.pcd)
    if getattr(surfels, "up_hint", None) is not None:
        arrays["up_hint"] = np.asarray(surfels.up_hint, np.float64)
    if getattr(surfels, "shading_hint", None) is not None:
        arrays["shading_hint"] = np.asarray(surfels.shading_hint)  # a capture's "none"
    file.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{file.name}.", suffix=".tmp", dir=file.parent)
    tmp = Path(name)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, file)
    finally:
        tmp.unlink(missing_ok=True)


def read_surfels(file: Path) -> Surfels | None:
    """A prepared model, or None where the file is unreadable (it is then replaced)."""
    try:
        with np.load(file) as z:
            names = sorted(asdict(Material()))
            material = Material(**dict(zip(names, (float(v) for v in z["material"]))))
            surfels = Surfels(positions=z["positions"], normals=z["normals"],
                              radius=z["radius"], colors=z["colors"], material=material,
                              **{k: z[k] for k in OPTIONAL if k in z.files})
            capture = {k.split(".", 1)[1]: z[k] for k in z.files if k.startswith("capture.")}
            if capture:
                surfels.capture = capture
            if "up_hint" in z.files:
                surfels.up_hint = tuple(float(v) for v in z["up_hint"])
            if "shading_hint" in z.files:
                surfels.shading_hint = str(z["shading_hint"])
            return surfels
    except Exception:  # noqa: BLE001 - a damaged or foreign file: prepare the model again
        return None


def _exists(file: Path) -> bool:
    try:
        return file.exists()
    except OSError:  # an unreadable cache folder: prepare the model
        return False


def _hash_file(h, path: Path) -> None:
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)


# what a model file may name beside it: material libraries, textures, glTF buffers
REFERENCED = (".mtl", ".bin", ".png", ".jpg", ".jpeg", ".tga", ".bmp", ".tif", ".tiff",
              ".webp", ".ktx", ".ktx2", ".dds", ".exr", ".hdr")


def referenced_files(path: Path) -> list[Path]:
    """The files in the model's folder (two levels deep) that its text names: an OBJ's
    material library and the textures that library names, a glTF's buffers and images, a
    PLY's ``comment TextureFile``. Found by name in the model's first MB and in the named
    material libraries, so that an output written beside the model (``render``'s default
    MODEL.png is not named by the model) changes no key."""
    folder = path.parent
    candidates = [p for pattern in ("*", "*/*") for p in folder.glob(pattern)
                  if p.is_file() and p != path and p.suffix.lower() in REFERENCED]
    if not candidates:
        return []
    with open(path, "rb") as f:
        texts = [f.read(1 << 20).decode("latin-1")]
    used: list[Path] = []
    for _ in range(2):  # the model names its .mtl; the .mtl names the textures
        for p in candidates:
            rel = p.relative_to(folder).as_posix()
            if p not in used and any(rel in t or p.name in t for t in texts):
                used.append(p)
                if p.suffix.lower() == ".mtl":
                    texts.append(p.read_text(encoding="latin-1", errors="replace")[:1 << 20])
    return sorted(used)


def _code_hash(render: bool = False) -> str:
    """A hash of the preparation code's source, with the renderer's when the preparation
    renders (computed once per process)."""
    if not _CODE_HASH:
        root = Path(__file__).resolve().parents[1]
        for extra in ((), ("splat/*.py", "raster/*.py", "backends/*.py", "*.py")):
            h = hashlib.blake2b(digest_size=16)
            files = sorted({*(root / "prep").glob("*.py"), *(root / "io").glob("*.py"),
                            root / "surfels.py", *(p for g in extra for p in root.glob(g))})
            for f in files:
                h.update(f.relative_to(root).as_posix().encode())
                h.update(f.read_bytes())
            _CODE_HASH.append(h.hexdigest())
    return _CODE_HASH[1 if render else 0]
