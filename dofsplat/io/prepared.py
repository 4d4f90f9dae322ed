"""Prepared models in the disk cache: a point cloud or a mesh made into surfels once.

Loading a scan or a mesh costs seconds to minutes of preparation (normals, radii, the
per-surfel normalisation; a mesh's sampling). ``load_prepared`` keeps the result in
``dofsplat.cache``'s ``surfels/`` folder when preparation took at least MIN_SECONDS, and
reads it back (milliseconds) when the same file is loaded with the same options by the same
preparation code. The key is a hash of:

* the file's bytes (and, for a mesh, the names, sizes and times of the files beside it:
  its material library and textures), and a ``texture`` option's file;
* the loader and its options;
* the source of the preparation code (``dofsplat/prep``, ``dofsplat/io``,
  ``dofsplat/surfels.py``): a change to how surfels are made makes old entries unused (the
  size cap then evicts them).

Files are written atomically; a cache that cannot be written costs a preparation next time,
no more.
"""

from __future__ import annotations

import hashlib
import os
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .. import cache
from ..surfels import Material, Surfels

MIN_SECONDS = 0.5  # a model that loads faster is not worth a copy on disk
OPTIONAL = ("opacity", "tangent", "radius_v", "weight")
_CODE_HASH: list[str] = []


def load_prepared(path: Path, loader, options: dict, use_cache: bool = True) -> Surfels:
    """``loader(path, **options)``, through the cache (module notes)."""
    key = cache_key(path, loader, options) if use_cache and cache.enabled() else None
    file = cache.cache_folder("surfels") / f"{key}.npz" if key else None
    t0 = time.perf_counter()
    if file is not None and file.exists():
        surfels = read_surfels(file)
        if surfels is not None:
            cache.touch(file)
            surfels.load_info = {"seconds": time.perf_counter() - t0, "from_cache": True,
                                 "cache_file": str(file)}
            return surfels
    surfels = loader(path, **options)
    seconds = time.perf_counter() - t0
    surfels.load_info = {"seconds": seconds, "from_cache": False, "cache_file": None}
    if file is not None and seconds >= MIN_SECONDS:
        try:
            write_surfels(file, surfels)
            cache.enforce_cap(keep=file)
            surfels.load_info["cache_file"] = str(file)
        except OSError:
            pass  # an unwritable cache costs the preparation next time, no more
    return surfels


def cache_key(path: Path, loader, options: dict) -> str:
    """The hash that names a prepared model (module notes)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(_code_hash().encode())
    h.update(f"{loader.__module__}.{loader.__qualname__}".encode())
    h.update(repr(sorted((k, str(v)) for k, v in options.items())).encode())
    _hash_file(h, path)
    for sibling in sorted(path.parent.iterdir()) if _is_mesh(path) else ():
        if sibling != path and sibling.is_file():
            st = sibling.stat()
            h.update(f"{sibling.name}\0{st.st_size}\0{st.st_mtime_ns}".encode())
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
    file.parent.mkdir(parents=True, exist_ok=True)
    tmp = file.with_name(f".{file.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
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
            return surfels
    except Exception:  # noqa: BLE001 - a damaged or foreign file: prepare the model again
        return None


def _hash_file(h, path: Path) -> None:
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)


def _is_mesh(path: Path) -> bool:
    from .mesh import MESH_EXTENSIONS

    return path.name.lower().endswith(tuple(MESH_EXTENSIONS))


def _code_hash() -> str:
    """A hash of the preparation code's source (computed once per process)."""
    if not _CODE_HASH:
        root = Path(__file__).resolve().parents[1]
        h = hashlib.blake2b(digest_size=16)
        files = sorted([*(root / "prep").glob("*.py"), *(root / "io").glob("*.py"),
                        root / "surfels.py"])
        for f in files:
            h.update(f.name.encode())
            h.update(f.read_bytes())
        _CODE_HASH.append(h.hexdigest())
    return _CODE_HASH[0]
