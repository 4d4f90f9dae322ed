"""Surfel PLY files (ASCII or binary, optionally gzip-compressed), via ``plyfile``.

A surfel PLY has one ``vertex`` element with the properties

* required: ``x y z`` (position), ``nx ny nz`` (normal), ``radius`` (world units);
* colour, optional: ``red green blue``; uchar and ushort are sRGB-encoded, float and double
  are linear in [0, 1]; without colour every surfel is grey 0.8;
* opacity, optional: ``opacity`` or ``alpha``; uchar / ushort scaled to [0, 1], float as is;
* elliptical surfels, optional: ``tx ty tz`` (first tangent axis) and ``radius_v``;
* ``weight``, optional: per-surfel normalisation factor.

:func:`write_surfel_ply` writes everything as float32 with linear colour, so that a
write/read round trip gives back the same float32 arrays bit for bit.
"""

from __future__ import annotations

import gzip
import io
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..errors import DofsplatError
from ..surfels import Material, Surfels
from .colors import srgb_to_linear
from .images import atomic_write

REQUIRED = ("x", "y", "z", "nx", "ny", "nz", "radius")
COLOR = ("red", "green", "blue")
ELLIPSE = ("tx", "ty", "tz", "radius_v")
DEFAULT_GREY = 0.8  # linear colour of surfels in files without colour

_GZIP_MAGIC = b"\x1f\x8b"
_HEADER_SNIFF_BYTES = 1 << 16  # the format line is the second line of the header
# Largest value of the unsigned integer types that store [0, 1] quantities.
_UNORM_MAX = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}


# ---------------------------------------------------------------------------------------
# Reading


def read_surfel_ply(path, *, material: Material | None = None) -> Surfels:
    """Load surfels from a ``.ply`` or ``.ply.gz`` file (see the module docstring).

    Rows with NaN or inf are dropped with one warning naming their count; zero normals,
    radii <= 0, a missing ``vertex`` element or missing required properties raise
    DofsplatError, as does a file that is not a PLY or is truncated.
    """
    path = Path(path)
    if not path.is_file():
        raise DofsplatError(f"no such file: {path}")
    columns = _read_vertex_columns(path)
    _check_properties(path, columns)

    positions = _stack(columns, ("x", "y", "z"))
    normals = _stack(columns, ("nx", "ny", "nz"))
    arrays = dict(radius=columns["radius"].astype(np.float32),
                  colors=_colors(path, columns),
                  opacity=_opacity(path, columns),
                  tangent=_stack(columns, ELLIPSE[:3]) if "tx" in columns else None,
                  radius_v=columns["radius_v"].astype(np.float32) if "tx" in columns else None,
                  weight=columns["weight"].astype(np.float32) if "weight" in columns else None)
    # Surfels leaves unit normals untouched, so a write/read round trip is exact
    return Surfels.from_arrays(positions, normals, material=material, source=str(path),
                               **arrays)


def _read_vertex_columns(path: Path) -> dict[str, np.ndarray]:
    """The scalar properties of the ``vertex`` element, name -> (N,) array in file dtype."""
    from plyfile import PlyData, PlyHeaderParseError, PlyListProperty

    try:
        with _open_ply(path) as stream:
            # memory-mapped reading is fast; plyfile's streamed binary reader is a Python
            # loop over every value, which is why gzip input goes through a real file
            ply = PlyData.read(stream, mmap="c")
            if "vertex" not in ply:
                found = ", ".join(repr(e.name) for e in ply.elements) or "none"
                raise DofsplatError(f"{path}: no 'vertex' element (elements found: {found})")
            vertex = ply["vertex"]
            # copies, so that nothing refers to the memory map once the file is closed
            columns = {p.name: np.array(vertex[p.name]) for p in vertex.properties
                       if not isinstance(p, PlyListProperty)}
            count = vertex.count
    except DofsplatError:
        raise
    except PermissionError as e:
        raise DofsplatError(f"{path}: cannot read: {e.strerror}") from e
    except PlyHeaderParseError as e:
        raise DofsplatError(f"{path}: not a PLY file or bad PLY header: {_one_line(e)}") from e
    except Exception as e:  # plyfile, numpy and gzip raise many types for a damaged file
        raise DofsplatError(f"{path}: corrupt or truncated PLY file: {_one_line(e)}") from e
    if count == 0:
        raise DofsplatError(f"{path}: the vertex element is empty (0 surfels)")
    return columns


def _open_ply(path: Path):
    """An open file with the (decompressed) PLY, gzip sniffed by its magic number.

    Binary PLY comes as a binary file, ASCII PLY as a text file: given a binary file,
    plyfile wraps it in a text wrapper of its own that it never closes.
    """
    with open(path, "rb") as f:
        compressed = f.read(2) == _GZIP_MAGIC
    stream = _decompressed(path) if compressed else open(path, "rb")
    try:
        head = stream.read(_HEADER_SNIFF_BYTES)
        stream.seek(0)
        if b"\nformat ascii" in head.split(b"end_header", 1)[0]:
            return io.TextIOWrapper(stream, encoding="ascii")
    except BaseException:
        stream.close()
        raise
    return stream


def _decompressed(path: Path):
    """A temporary file with the gzip file's contents, which plyfile can memory-map."""
    plain = tempfile.TemporaryFile()
    try:
        with gzip.open(path, "rb") as gz:
            shutil.copyfileobj(gz, plain, 1 << 20)
        plain.seek(0)
    except BaseException:
        plain.close()
        raise
    return plain


def _check_properties(path: Path, columns: dict[str, np.ndarray]) -> None:
    missing = [p for p in REQUIRED if p not in columns]
    if missing:
        raise DofsplatError(
            f"{path}: vertex element lacks required properties {' '.join(missing)}; a surfel "
            f"PLY needs {' '.join(REQUIRED)} (bare points without normals and radius are "
            "not a surfel file)")
    for group in (COLOR, ELLIPSE):
        present = [p for p in group if p in columns]
        if present and len(present) < len(group):
            missing = [p for p in group if p not in columns]
            raise DofsplatError(f"{path}: vertex element has {' '.join(present)} but lacks "
                                f"{' '.join(missing)}; give all of {' '.join(group)} or none")


def _stack(columns, names) -> np.ndarray:
    return np.stack([columns[n] for n in names], axis=1).astype(np.float32)


def _colors(path: Path, columns) -> np.ndarray:
    """(N, 3) float32 linear RGB from the red/green/blue properties, or grey."""
    n = len(columns["x"])
    if "red" not in columns:
        return np.full((n, 3), DEFAULT_GREY, np.float32)
    rgb = np.stack([columns[c] for c in COLOR], axis=1)
    if rgb.dtype in _UNORM_MAX:
        # integer colours are sRGB-encoded, as image files are
        return srgb_to_linear(rgb / _UNORM_MAX[rgb.dtype]).astype(np.float32)
    if np.issubdtype(rgb.dtype, np.floating):
        return rgb.astype(np.float32)
    raise DofsplatError(f"{path}: colour properties of type {rgb.dtype} are not supported "
                        "(use uchar or ushort for sRGB, float or double for linear)")


def _opacity(path: Path, columns) -> np.ndarray | None:
    name = "opacity" if "opacity" in columns else "alpha" if "alpha" in columns else None
    if name is None:
        return None
    a = columns[name]
    if a.dtype in _UNORM_MAX:
        return (a / _UNORM_MAX[a.dtype]).astype(np.float32)  # alpha is linear, not sRGB
    if np.issubdtype(a.dtype, np.floating):
        return a.astype(np.float32)
    raise DofsplatError(f"{path}: property {name!r} of type {a.dtype} is not supported "
                        "(use uchar, ushort, float or double)")


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or "no details"
    return f"{type(e).__name__}: {text}"


# ---------------------------------------------------------------------------------------
# Writing


def write_surfel_ply(path, surfels: Surfels, binary: bool = True) -> Path:
    """Write surfels as a PLY file; a name ending in ``.gz`` is gzip-compressed.

    All properties are float32 (little-endian when binary): x y z nx ny nz radius,
    red green blue (linear, not sRGB), opacity, then tx ty tz radius_v for elliptical
    surfels and weight when present. The write is atomic. Returns the path.
    """
    from plyfile import PlyData, PlyElement

    path = Path(path)
    vertex = PlyElement.describe(_vertex_records(surfels), "vertex")
    ply = PlyData([vertex], text=not binary, byte_order="<",
                  comments=["dofsplat surfels: float32, linear RGB colour"])

    def write(tmp):
        if path.name.lower().endswith(".gz"):
            # mtime=0: the same surfels give the same bytes
            with open(tmp, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as gz:
                ply.write(gz)
        else:
            ply.write(tmp)

    return atomic_write(path, write)


def _vertex_records(s: Surfels) -> np.ndarray:
    """(N,) structured float32 array with one field per PLY property."""
    columns = {"x": s.positions[:, 0], "y": s.positions[:, 1], "z": s.positions[:, 2],
               "nx": s.normals[:, 0], "ny": s.normals[:, 1], "nz": s.normals[:, 2],
               "radius": s.radius,
               "red": s.colors[:, 0], "green": s.colors[:, 1], "blue": s.colors[:, 2],
               "opacity": s.opacity}
    if s.is_elliptical:
        columns.update(tx=s.tangent[:, 0], ty=s.tangent[:, 1], tz=s.tangent[:, 2],
                       radius_v=s.radius_v)
    if s.weight is not None:
        columns["weight"] = s.weight
    records = np.empty(len(s), dtype=[(name, "<f4") for name in columns])
    for name, values in columns.items():
        records[name] = values
    return records
