"""PLY files (ASCII or binary, optionally gzip-compressed): surfels, and everything else.

:func:`read_ply` (the loader for ``.ply`` and ``.ply.gz``) reads the header and dispatches
(:func:`ply_kind`): surfel files to :func:`read_surfel_ply`, 3D Gaussian Splatting files (the
trainers' PLY and PlayCanvas's compressed PLY) to :mod:`dofsplat.io.gaussians`, meshes to
:mod:`dofsplat.prep.meshes`, bare points to :mod:`dofsplat.prep.pointcloud`
(docs/formats.md). Binary bodies are read by ``plyfile``, ASCII
bodies by one numpy tokenisation (:func:`_read_ascii_body`).

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
import warnings
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import DofsplatError
from ..gaussians import Gaussians
from ..surfels import Material, Surfels
from ..colors import srgb_to_linear
from .gaussians import is_compressed_ply
from .images import atomic_write

REQUIRED = ("x", "y", "z", "nx", "ny", "nz", "radius")
NORMAL = ("nx", "ny", "nz")
FACE_LISTS = ("vertex_indices", "vertex_index")  # the two names in use for a face's list
UV_NAMES = (("s", "t"), ("u", "v"), ("texture_u", "texture_v"), ("texture_s", "texture_t"))
COLOR = ("red", "green", "blue")
ELLIPSE = ("tx", "ty", "tz", "radius_v")
DEFAULT_GREY = 0.8  # linear colour of surfels in files without colour

_GZIP_MAGIC = b"\x1f\x8b"
_HEADER_SNIFF_BYTES = 1 << 16  # the format line is the second line of the header
# Largest value of the unsigned integer types that store [0, 1] quantities.
_UNORM_MAX = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}
_MAX_LIST = 1 << 16  # a longer face list in an ASCII body is damage, not a polygon


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
    return _read_elements(path)["vertex"]


def _read_elements(path: Path, faces: bool = False,
                   extra: tuple[str, ...] = ()) -> dict[str, dict[str, np.ndarray]]:
    """The ``vertex`` element's scalar properties, with faces=True the ``face`` element's
    vertex lists (under "face": {"indices": (F, L) array or ragged object array}), and the
    scalar properties of the ``extra`` elements that the file has (a compressed 3DGS PLY's
    chunk and sh elements).
    """
    from plyfile import (
        PlyData,
        PlyElementParseError,
        PlyHeaderParseError,
        PlyListProperty,
    )

    try:
        with _open_ply(path) as stream:
            # memory-mapped reading is fast; plyfile's streamed binary reader is a Python
            # loop over every value, which is why gzip input goes through a real file. Face
            # lists memory-map too when they are all triangles (else: the slow reader).
            try:
                ply = PlyData.read(stream, mmap="c",
                                   known_list_len={"face": {n: 3 for n in FACE_LISTS}}
                                   if faces else {})
            except PlyElementParseError as e:
                if not (faces and "unexpected list length" in str(e)):
                    raise
                stream.seek(0)
                ply = PlyData.read(stream, mmap="c")
            if "vertex" not in ply:
                found = ", ".join(repr(e.name) for e in ply.elements) or "none"
                raise DofsplatError(f"{path}: no 'vertex' element (elements found: {found})")
            vertex = ply["vertex"]
            # copies, so that nothing refers to the memory map once the file is closed
            out = {"vertex": {p.name: np.array(vertex[p.name]) for p in vertex.properties
                              if not isinstance(p, PlyListProperty)}}
            count = vertex.count
            for name in extra:
                if name in ply:
                    out[name] = {p.name: np.array(ply[name][p.name])
                                 for p in ply[name].properties
                                 if not isinstance(p, PlyListProperty)}
            if faces and "face" in ply:
                face = ply["face"]
                name = next((n for n in FACE_LISTS if n in face.data.dtype.names), None)
                if name is not None:
                    lists = face[name]
                    out["face"] = {"indices": np.array(lists) if lists.dtype != object
                                   else lists}
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
    return out


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
            f"PLY needs {' '.join(REQUIRED)}, a point cloud x y z with all of nx ny nz or "
            "none: this is not a surfel file nor a point cloud")
    _check_groups(path, columns, (COLOR, ELLIPSE))


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
# Any PLY: surfels, 3D Gaussian splats, a triangle mesh or bare points, told apart by the
# header (see :func:`ply_kind`)


@dataclass(frozen=True)
class PlyProperty:
    """One property of a PLY element: a scalar, or a list (``count_dtype`` is set)."""

    name: str
    dtype: str  # numpy type of the value, or of the list items ("f4", "u1", ...)
    count_dtype: str | None = None  # numpy type of a list's length; None for a scalar


@dataclass(frozen=True)
class PlyElementHeader:
    name: str
    count: int
    properties: tuple[PlyProperty, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.properties)


@dataclass(frozen=True)
class PlyHeader:
    """What a PLY header says; ``body_offset`` is the byte where the data starts."""

    format: str  # "ascii", "binary_little_endian" or "binary_big_endian"
    elements: tuple[PlyElementHeader, ...]
    comments: tuple[str, ...]
    body_offset: int

    def element(self, name: str) -> PlyElementHeader | None:
        return next((e for e in self.elements if e.name == name), None)


def read_ply_header(path) -> PlyHeader:
    """Parse the header of a ``.ply`` or ``.ply.gz`` file (gzip sniffed by magic number)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            compressed = f.read(2) == _GZIP_MAGIC
        opener = gzip.open if compressed else open
        with opener(path, "rb") as f:
            head = f.read(_HEADER_SNIFF_BYTES)
    except PermissionError as e:
        raise DofsplatError(f"{path}: cannot read: {e.strerror}") from e
    except (OSError, EOFError, zlib.error) as e:  # gzip.BadGzipFile is an OSError
        raise DofsplatError(f"{path}: corrupt or truncated PLY file: {_one_line(e)}") from e
    return parse_ply_header(head, str(path))


def parse_ply_header(data: bytes, source: str = "PLY") -> PlyHeader:
    """Parse a PLY header from the first bytes of a file; DofsplatError if it is not one."""
    if not data.startswith(b"ply") or data[3:4] not in (b"\n", b"\r"):
        raise DofsplatError(f"{source}: not a PLY file (it does not start with 'ply')")
    end = data.find(b"end_header")
    if end < 0:
        raise DofsplatError(f"{source}: not a PLY file or bad PLY header: no end_header in "
                            f"the first {len(data):,} bytes")
    body = end + len(b"end_header")
    body += 2 if data[body:body + 2] == b"\r\n" else 1
    lines = data[:end].decode("ascii", errors="replace").splitlines()[1:]
    fmt, elements, comments = None, [], []

    def bad(why):
        return DofsplatError(f"{source}: not a PLY file or bad PLY header: {why}")

    for line in lines:
        words = line.split()
        if not words:
            continue
        if words[0] in ("comment", "obj_info"):
            comments.append(line.split(None, 1)[1] if len(words) > 1 else "")
        elif words[0] == "format":
            if len(words) != 3 or words[1] not in _FORMATS or words[2] != "1.0":
                raise bad(f"format line {line.strip()!r}")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise bad(f"element line {line.strip()!r}")
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property":
            if not elements:
                raise bad("a property before any element")
            if len(words) == 5 and words[1] == "list" and words[2] in _PLY_TYPES \
                    and words[3] in _PLY_TYPES:
                elements[-1][2].append(PlyProperty(words[4], _PLY_TYPES[words[3]],
                                                   _PLY_TYPES[words[2]]))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append(PlyProperty(words[2], _PLY_TYPES[words[1]]))
            else:
                raise bad(f"property line {line.strip()!r}")
        else:
            raise bad(f"unexpected line {line.strip()!r}")
    if fmt is None:
        raise bad("no format line")
    return PlyHeader(fmt, tuple(PlyElementHeader(n, c, tuple(p)) for n, c, p in elements),
                     tuple(comments), body)


def ply_kind(header: PlyHeader) -> str:
    """What the vertex element holds, by its property names, checked in this order:

    * "gaussians": 3D Gaussian Splatting output (f_dc_0, scale_0, rot_0, ...), or
      PlayCanvas's compressed PLY of one (a chunk element, packed_position, ...);
    * "surfels": a radius (or some but not all of nx ny nz: a damaged surfel file);
    * "mesh": a non-empty face element;
    * "points": anything else with x y z (normals and colours optional).
    """
    vertex = header.element("vertex")
    names = set(vertex.names) if vertex is not None else set()
    if {"f_dc_0", "scale_0", "rot_0"} <= names or is_compressed_ply(header):
        return "gaussians"
    normals = [n for n in NORMAL if n in names]
    if "radius" in names or 0 < len(normals) < 3:
        return "surfels"
    face = header.element("face")
    if face is not None and face.count > 0:
        return "mesh"
    return "points"


_KIND_WORDS = {"surfels": "a surfel PLY", "gaussians": "a 3D Gaussian Splatting PLY",
               "mesh": "a triangle mesh", "points": "a point cloud (a PLY without faces)"}
# a Gaussian scene is taken as it is: it has no surfel weights to normalise, no normals
_KIND_OPTIONS = {"surfels": ("normalise",), "gaussians": (),
                 "mesh": ("points", "texture", "smooth", "normalise"),
                 "points": ("k", "smooth", "normalise")}


def ply_options(header: PlyHeader) -> tuple[str, tuple[str, ...]]:
    """(what the PLY holds, in words; the options of :func:`read_ply` that apply to it, besides
    ``material``, which applies to all)."""
    kind = ply_kind(header)
    return _KIND_WORDS[kind], _KIND_OPTIONS[kind]


def read_ply(path, *, material: Material | None = None, points: int | str | None = None,
             k: int | None = None, smooth: bool | None = None, texture=None,
             normalise: str | None = None) -> Surfels | Gaussians:
    """Load any PLY file: the header says what it holds (:func:`ply_kind`).

    * surfels: :func:`read_surfel_ply`, as they are (with their stored weights);
    * a 3D Gaussian Splatting scene (the trainers' PLY or PlayCanvas's compressed PLY):
      :class:`dofsplat.Gaussians` (:mod:`dofsplat.io.gaussians`); it takes no options,
      ``material`` neither (Gaussians are drawn unlit);
    * a triangle mesh (polygons are split into fans): sampled by
      :func:`dofsplat.prep.meshes.mesh_to_surfels`, ``points`` samples (None: the default count;
      "vertices": one per vertex); vertex colours red green blue [alpha] (uchar, ushort:
      sRGB; float: linear); per-vertex texture coordinates (s t, u v or texture_u
      texture_v) with ``texture`` (an image file) or the image a ``comment TextureFile``
      line names; ``smooth`` (None: True) puts the samples on the Phong tessellation;
    * bare points: normals (nx ny nz) if present, colours as for meshes, then
      :func:`dofsplat.prep.pointcloud.points_to_surfels` with ``k`` neighbours and ``smooth``
      (None: True, points moved onto their neighbourhood's plane).

    normalise: the per-surfel normalisation (:func:`dofsplat.prep.normalise.normalise`): None
    gives "object" for meshes and points and leaves surfel files as they are; a
    method given is applied to whatever the file holds ("none": nothing).

    ASCII bodies are read by numpy's tokeniser when every face has the same number of
    vertices (plyfile parses ASCII line by line in Python: ten times slower), else and for
    binary bodies by plyfile. Options that do not apply to what the file holds are an error.
    """
    from ..prep.normalise import check_method
    from ..prep.normalise import normalise as normalise_surfels

    if normalise is not None:
        check_method(normalise)
    path = Path(path)
    if not path.is_file():
        raise DofsplatError(f"no such file: {path}")
    header = read_ply_header(path)
    vertex = header.element("vertex")
    if vertex is None:
        found = ", ".join(repr(e.name) for e in header.elements) or "none"
        raise DofsplatError(f"{path}: no 'vertex' element (elements found: {found})")
    if vertex.count == 0:
        raise DofsplatError(f"{path}: the vertex element is empty (0 points)")
    kind = ply_kind(header)
    given = {"points": points, "k": k, "smooth": smooth, "texture": texture,
             "normalise": normalise, "material": material if kind == "gaussians" else None}
    wrong = [name for name, v in given.items() if v is not None and name not in _KIND_OPTIONS[kind]]
    if wrong:
        raise DofsplatError(f"{path} is {_KIND_WORDS[kind]}: option(s) {', '.join(wrong)} do "
                            "not apply to it")
    if kind == "surfels":
        surfels = normalise_surfels(read_surfel_ply(path, material=material), normalise or "none")
        return _apply_view_comments(surfels, header.comments)
    if kind == "gaussians":  # a 3DGS PLY, or PlayCanvas's compressed one (io/gaussians.py)
        from .gaussians import decode_compressed_ply, gaussians_from_columns

        if is_compressed_ply(header):
            return decode_compressed_ply(_read_elements(path, extra=("chunk", "sh")), str(path))
        return gaussians_from_columns(_read_body(path, header, faces=False)["vertex"], str(path))
    missing = [n for n in ("x", "y", "z") if n not in vertex.names]
    if missing:
        raise DofsplatError(f"{path}: vertex element lacks {' '.join(missing)}")
    if kind == "points" and _streamable(path, header):
        from ..prep.cloudfile import wants_disk

        if wants_disk(vertex.count):  # a cloud larger than memory (issue 50)
            return _point_surfels_on_disk(path, header, k, smooth, material,
                                          normalise or "object")
    elements = _read_body(path, header, faces=kind == "mesh")
    columns = elements["vertex"]
    if kind == "mesh":
        return _mesh_surfels(path, header, columns, elements.get("face"), points, texture,
                             material, smooth is not False, normalise or "object")
    return _point_surfels(path, columns, k, smooth, material, normalise or "object")


def _read_body(path: Path, header: PlyHeader, faces: bool) -> dict:
    """The vertex columns (and face lists): the fast ASCII reader, else plyfile."""
    if header.format == "ascii":
        try:
            with _open_ply(path) as stream:
                data = stream.buffer.read() if hasattr(stream, "buffer") else stream.read()
        except (OSError, EOFError, zlib.error) as e:  # gzip.BadGzipFile is an OSError
            raise DofsplatError(f"{path}: corrupt or truncated PLY file: {_one_line(e)}") from e
        elements = _read_ascii_body(data, header, str(path))
        if elements is not None:
            return elements
    return _read_elements(path, faces=faces)


def _read_ascii_body(data: bytes, header: PlyHeader, source: str) -> dict | None:
    """All elements of an ASCII PLY body, through one numpy tokenisation of the text.

    Returns {element: {property: array}} (list properties as (count, L) arrays), or None
    when a list's length varies from row to row (polygons of mixed sizes: plyfile reads
    those). A short body is DofsplatError.
    """
    try:
        tokens = np.array(data[header.body_offset:].split(), dtype=np.float64)
    except (ValueError, OverflowError) as e:
        raise DofsplatError(f"{source}: corrupt PLY file: a value that is not a number "
                            f"({_one_line(e)})") from e
    at, out = 0, {}
    for element in header.elements:
        # the row layout from the first row: one token per scalar, 1 + L per list
        layout, width = [], 0
        for prop in element.properties:
            if prop.count_dtype is None:
                layout.append((prop, width, 0))
                width += 1
                continue
            if element.count == 0:
                layout.append((prop, width, 0))
                width += 1
                continue
            if at + width >= tokens.size:
                raise DofsplatError(f"{source}: truncated PLY file: the {element.name} "
                                    "element ends early")
            length = tokens[at + width]
            if not (0 <= length <= _MAX_LIST and length == np.floor(length)):  # NaN fails too
                raise DofsplatError(f"{source}: corrupt PLY file: a {element.name} list of "
                                    f"length {length:g}")
            layout.append((prop, width, int(length)))
            width += 1 + int(length)
        need = element.count * width
        if at + need > tokens.size and len(layout) != sum(1 for p in element.properties
                                                          if p.count_dtype is None):
            return None  # lists whose lengths vary: plyfile parses them (or says why not)
        if at + need > tokens.size:
            raise DofsplatError(f"{source}: truncated PLY file: the {element.name} element "
                                f"needs {need:,} values, {tokens.size - at:,} are left")
        rows = tokens[at:at + need].reshape(element.count, width)
        columns = {}
        with np.errstate(invalid="ignore", over="ignore"):
            for prop, col, length in layout:
                if prop.count_dtype is None:
                    columns[prop.name] = rows[:, col].astype(prop.dtype)
                elif element.count == 0:
                    columns[prop.name] = np.zeros((0, 0), prop.dtype)
                else:
                    if not np.all(rows[:, col] == length):
                        return None
                    columns[prop.name] = rows[:, col + 1:col + 1 + length].astype(prop.dtype)
        out[element.name] = columns
        at += need
    if at != tokens.size:
        return None  # more values than the header declares: let plyfile say what is wrong
    vertex = out.get("vertex", {})
    face = out.get("face", {})
    name = next((n for n in FACE_LISTS if n in face), None)
    result = {"vertex": {k: v for k, v in vertex.items() if v.ndim == 1}}
    if name is not None:
        result["face"] = {"indices": face[name]}
    return result


def _point_surfels(path: Path, columns: dict, k, smooth, material, normalise) -> Surfels:
    """Bare points (normals optional) to surfels through :mod:`dofsplat.prep.pointcloud`."""
    from ..prep.pointcloud import ground_up, points_to_surfels

    _check_groups(path, columns, (COLOR, NORMAL))
    positions = _stack64(columns, ("x", "y", "z"))
    normals = _stack64(columns, NORMAL) if "nx" in columns else None
    colors = _colors(path, columns) if "red" in columns else None
    opacity = _opacity(path, columns)
    keep = finite_rows(positions, normals, colors, opacity, source=str(path))
    positions, normals, colors, opacity = (None if a is None else a[keep]
                                           for a in (positions, normals, colors, opacity))
    surfels = points_to_surfels(positions, colors, normals, k=k, smooth=smooth is not False,
                                normalise=normalise, source=str(path))
    if opacity is not None and len(surfels) == len(opacity):
        surfels = replace(surfels, opacity=opacity)
    surfels = surfels if material is None else replace(surfels, material=material)
    surfels.up_hint = ground_up(surfels)  # a z-up scan is seen upright (prep.pointcloud)
    return surfels


def _streamable(path: Path, header: PlyHeader) -> bool:
    """Whether a point cloud PLY can be read a block at a time from its file: binary, not
    compressed, its vertex element first and of scalar properties, without opacity (which
    the surfels take only where no duplicates were merged)."""
    vertex = header.element("vertex")
    if header.format == "ascii" or header.elements[0] is not vertex:
        return False
    if any(p.count_dtype is not None for p in vertex.properties):
        return False
    if {"opacity", "alpha"} & set(vertex.names):
        return False
    with open(path, "rb") as f:
        return f.read(2) != _GZIP_MAGIC


def _point_surfels_on_disk(path: Path, header: PlyHeader, k, smooth, material,
                           normalise) -> Surfels:
    """``_point_surfels`` of a cloud larger than memory: its vertices read a block at a time
    into chunks in a work folder and prepared from there (``io.on_disk.prepare_on_disk``):
    the same surfels where each point's neighbourhoods fit in its chunk's halo, in the
    order of the chunks."""
    from ..prep.pointcloud import ground_up
    from .on_disk import prepare_on_disk

    vertex = header.element("vertex")
    _check_groups(path, {name: None for name in vertex.names}, (COLOR, NORMAL))
    surfels = prepare_on_disk(path, vertex.count, lambda folder, bar: _ply_blocks(path, header,
                                                                                   bar),
                              k=k, smooth=smooth is not False, normalise=normalise)
    surfels = surfels if material is None else replace(surfels, material=material)
    surfels.up_hint = ground_up(surfels)
    return surfels


def _ply_blocks(path: Path, header: PlyHeader, bar):
    """(blocks, lo, hi) for ``cloudfile.write_cloud`` from a streamable point cloud PLY
    (``_streamable``), after a pass over its vertices for their bounds: blocks() reads
    ``cloudfile.BLOCK`` vertices at a time and gives their positions, colours (linear, as
    ``_colors``; mid grey without) and normals (or None), the rows with a value that is not
    finite dropped, as ``finite_rows`` drops them in memory (one warning for them all)."""
    from ..prep.cloudfile import BLOCK
    from ..prep.pointcloud import MID_GREY

    vertex = header.element("vertex")
    order = "<" if header.format == "binary_little_endian" else ">"
    dtype = np.dtype([(p.name, order + p.dtype) for p in vertex.properties])
    n = vertex.count

    def rows():
        try:
            with open(path, "rb") as f:
                f.seek(header.body_offset)
                for a in range(0, n, BLOCK):
                    m = min(BLOCK, n - a)
                    records = np.fromfile(f, dtype, m)
                    if len(records) < m:
                        raise DofsplatError(f"{path}: truncated PLY file: the vertex "
                                            f"element needs {n:,} vertices, "
                                            f"{a + len(records):,} are left")
                    yield records
        except OSError as e:
            raise DofsplatError(f"{path}: cannot read: {e.strerror or e}") from e

    def block(records):
        columns = {name: records[name] for name in dtype.names}
        p = _stack64(columns, ("x", "y", "z"))
        nrm = _stack64(columns, NORMAL) if "nx" in columns else None
        c = _colors(path, columns) if "red" in columns else None
        keep = np.all(np.isfinite(p), axis=1)
        for a in (nrm, c):
            if a is not None:
                keep &= np.all(np.isfinite(a), axis=1)
        c = (np.full((len(p), 3), MID_GREY, np.float32) if c is None
             else np.clip(c, 0.0, 1.0))
        if keep.all():
            return p, c, nrm
        return p[keep], c[keep], None if nrm is None else nrm[keep]

    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    kept = 0
    for records in rows():
        p = block(records)[0]
        kept += len(p)
        if len(p):
            np.minimum(lo, p.min(axis=0), out=lo)
            np.maximum(hi, p.max(axis=0), out=hi)
        bar.update(len(records))
    if kept == 0:
        raise DofsplatError(f"{path}: no valid points (all {n:,} have NaN or inf values)")
    if kept < n:
        warnings.warn(f"{path}: dropped {n - kept:,} of {n:,} points with NaN or inf values",
                      stacklevel=2)
    return (lambda: (block(records) for records in rows())), lo, hi


def finite_rows(positions, *others, source: str = "", what="points") -> np.ndarray:
    """Mask of the rows where every given (N, ...) array is finite; warns with the count of
    the others and raises DofsplatError when none is left."""
    n = len(positions)
    keep = np.ones(n, bool)
    for a in (positions, *others):
        if a is not None:
            keep &= np.all(np.isfinite(np.asarray(a).reshape(n, -1)), axis=1)
    dropped = n - int(keep.sum())
    if dropped == n:
        raise DofsplatError(f"{source}: no valid {what} (all {n:,} have NaN or inf values)")
    if dropped:
        warnings.warn(f"{source}: dropped {dropped:,} of {n:,} {what} with NaN or inf values",
                      stacklevel=2)
    return keep


def _mesh_surfels(path: Path, header: PlyHeader, columns: dict, face: dict | None, count,
                  texture, material, smooth, normalise) -> Surfels:
    """A PLY triangle mesh (polygons split into fans) to surfels by sampling."""
    from ..prep.meshes import MeshPart, mesh_to_surfels
    from .mesh import load_texture

    if face is None:
        raise DofsplatError(f"{path}: the face element has no vertex_indices list")
    _check_groups(path, columns, (COLOR,))
    vertices = _stack64(columns, ("x", "y", "z"))
    bad = int(np.count_nonzero(~np.all(np.isfinite(vertices), axis=1)))
    if bad:
        warnings.warn(f"{path}: {bad:,} of {len(vertices):,} vertices have NaN or inf "
                      "coordinates; the faces around them are left out", stacklevel=2)
    faces = triangulate(face["indices"], len(vertices), str(path))
    vertex_colors = None
    if "red" in columns:
        vertex_colors = np.ones((len(vertices), 4), np.float32)
        vertex_colors[:, :3] = _colors(path, columns)
        alpha = _opacity(path, columns)
        if alpha is not None:
            vertex_colors[:, 3] = alpha
    uv = next((_stack64(columns, pair) for pair in UV_NAMES
               if all(n in columns for n in pair)), None)
    image = None
    if texture is not None:
        if uv is None:
            raise DofsplatError(f"{path}: a texture needs texture coordinates per vertex "
                                f"({', '.join(' '.join(p) for p in UV_NAMES)}); the mesh has none")
        image = load_texture(texture)
    elif uv is not None:
        named = [c.split(None, 1)[1] for c in header.comments
                 if c.startswith("TextureFile ") and len(c.split(None, 1)) == 2]
        if named and (path.parent / named[0]).is_file():
            image = load_texture(path.parent / named[0])
    blend = vertex_colors is not None and bool(np.any(vertex_colors[:, 3] < 1.0))
    part = MeshPart(vertices, faces, vertex_colors=vertex_colors, uv=uv, texture=image,
                    alpha_mode="BLEND" if blend else "OPAQUE")
    return mesh_to_surfels(part, count, material=material, smooth=smooth,
                           normalise=normalise, source=str(path))


def triangulate(lists, n_vertices: int, source: str = "mesh") -> np.ndarray:
    """(F, 3) int64 triangles from face vertex lists: an (F, L) array or a ragged object
    array of index arrays; polygons become fans (v0, vi, vi+1), faces under 3 vertices go."""
    if isinstance(lists, np.ndarray) and lists.dtype != object:
        groups = [lists.reshape(len(lists), -1)]
    else:
        by_length: dict[int, list] = {}
        for f in lists:
            by_length.setdefault(len(f), []).append(f)
        groups = [np.array(v) for v in by_length.values()]
    tris = []
    for g in groups:
        if g.shape[1] < 3 or len(g) == 0:
            continue
        if not np.issubdtype(g.dtype, np.integer):
            with np.errstate(invalid="ignore"):
                if not np.all(np.isfinite(g)) or np.any(g != np.round(g)):
                    raise DofsplatError(f"{source}: face vertex indices that are not whole "
                                        "numbers")
        g = g.astype(np.int64)
        for i in range(1, g.shape[1] - 1):
            tris.append(np.stack([g[:, 0], g[:, i], g[:, i + 1]], axis=1))
    faces = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= n_vertices):
        raise DofsplatError(f"{source}: a face refers to vertex {int(faces.max())} (or below 0), "
                            f"but there are {n_vertices:,} vertices")
    return faces


def _check_groups(path: Path, columns: dict, groups) -> None:
    for group in groups:
        present = [p for p in group if p in columns]
        if present and len(present) < len(group):
            missing = [p for p in group if p not in columns]
            raise DofsplatError(f"{path}: vertex element has {' '.join(present)} but lacks "
                                f"{' '.join(missing)}; give all of {' '.join(group)} or none")


def _stack64(columns, names) -> np.ndarray:
    return np.stack([np.asarray(columns[n], dtype=np.float64) for n in names], axis=1)


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
                  comments=["dofsplat surfels: float32, linear RGB colour"]
                  + _view_comments(surfels))

    def write(tmp):
        if path.name.lower().endswith(".gz"):
            # mtime=0: the same surfels give the same bytes
            with open(tmp, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as gz:
                ply.write(gz)
        else:
            ply.write(tmp)

    return atomic_write(path, write)


# How the model wants to be seen, kept in a surfel PLY's header (``dofsplat convert``): a
# depth capture's sensor view and its unlit colours (io.pcd), the scan's up direction
VIEW_COMMENT = "dofsplat view"


def _view_comments(s: Surfels) -> list[str]:
    """``comment dofsplat view <name> <numbers or word>`` lines for the surfels' view hints:
    capture.<key> (``Surfels.capture``), up_hint, shading_hint."""
    lines = []
    for key, value in (getattr(s, "capture", None) or {}).items():
        numbers = np.asarray(value, np.float64).reshape(-1)
        lines.append(f"{VIEW_COMMENT} capture.{key} " + " ".join(repr(float(v)) for v in numbers))
    if getattr(s, "up_hint", None) is not None:
        lines.append(f"{VIEW_COMMENT} up_hint " + " ".join(repr(float(v)) for v in s.up_hint))
    if getattr(s, "shading_hint", None) is not None:
        lines.append(f"{VIEW_COMMENT} shading_hint {s.shading_hint}")
    return lines


def _apply_view_comments(s: Surfels, comments) -> Surfels:
    """The view hints of ``_view_comments`` back onto the surfels (lines it cannot read are
    left alone: a comment is no reason to refuse a model)."""
    capture = {}
    for line in comments:
        words = line.split()
        if len(words) < 4 or " ".join(words[:2]) != VIEW_COMMENT:
            continue
        name, values = words[2], words[3:]
        try:
            if name.startswith("capture."):
                capture[name.split(".", 1)[1]] = np.array([float(v) for v in values])
            elif name == "up_hint" and len(values) == 3:
                s.up_hint = tuple(float(v) for v in values)
            elif name == "shading_hint" and len(values) == 1:
                s.shading_hint = values[0]
        except ValueError:
            continue
    if {"eye", "target", "up", "size", "frustum"} <= capture.keys():
        s.capture = capture
    return s


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
