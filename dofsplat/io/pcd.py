"""PCD point clouds (the Point Cloud Library's format, v0.5 to v0.7).

The header is a few text lines (FIELDS, SIZE, TYPE, COUNT, WIDTH, HEIGHT, VIEWPOINT, POINTS,
DATA); the data is ``ascii`` (one point per line), ``binary`` (packed rows) or
``binary_compressed``: two little-endian uint32 sizes (compressed, uncompressed), then the
LZF-compressed columns, field after field. The header is parsed here and the data by numpy;
LZF decompression is liblzf's, through python-neo-lzf (the maintained, wheel-built fork of
python-lzf that pypcd4 uses). The PCD readers on PyPI were not used: pypcd4 pulls in
pydantic and trusts the header (it allocates what POINTS says before looking at the file's
size), and open3d is a 400 MB dependency for one format.

Fields read: ``x y z``; ``rgb`` / ``rgba`` packed as 0xAARRGGBB in a uint32 or in the bits
of a float32 (PCL's habit), sRGB; ``normal_x normal_y normal_z``. Others are ignored.

Organised clouds (HEIGHT > 1: a depth camera's image, NaN where there was no depth) lie in
the camera's optical frame: x right, y down, z forward. They are turned 180 degrees about
x, to (x, -y, -z), so that the sensor looks along -z with y up as dofsplat's default camera
does: ``dofsplat render`` then shows the scene as the sensor saw it. Their NaN points are
dropped silently (they are the pixels without depth); in an unorganised cloud NaN points
are dropped with a warning. Normals are turned towards the sensor, the VIEWPOINT's
translation (its rotation, which PCL's viewer applies to the points, is not used), for
organised clouds and for unorganised ones whose VIEWPOINT is not PCL's default
(0 0 0 1 0 0 0, which says nothing); other clouds are oriented by
:func:`dofsplat.prep.pointcloud.points_to_surfels`'s propagation (outwards).

An organised cloud has one point per pixel, so its surfels are sized by the sensor's pixels
(``prep.pointcloud.capture_footprints``: each a disk of 1.25 pixels seen from the sensor, an
ellipse on a tilted surface) rather than by 3-D neighbours, which miss across the sensor's
depth steps and leave holes; and its colours, photographs of a lit scene, are rendered
unshaded by default (``Surfels.shading_hint``; ``--shading phong`` lights them again).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import DofsplatError
from ..surfels import Material, Surfels

PCD_EXTENSIONS = (".pcd",)
_HEADER_MAX = 1 << 16  # bytes: a PCD header is a dozen short lines
_MAX_LZF_RATIO = 120  # LZF cannot expand more than ~88:1; a larger claim is damage
_TYPES = {("I", 1): "<i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8",
          ("U", 1): "<u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8",
          ("F", 4): "<f4", ("F", 8): "<f8"}
_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT",
         "POINTS", "DATA")
_DATA_MODES = ("ascii", "binary", "binary_compressed")
_DEFAULT_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
_PACKED_COLOUR = ("rgb", "rgba")


@dataclass(frozen=True)
class PcdHeader:
    fields: tuple[str, ...]
    dtypes: tuple[str, ...]  # numpy type per field, little-endian
    counts: tuple[int, ...]  # values per field per point
    width: int
    height: int
    viewpoint: tuple[float, ...]  # tx ty tz qw qx qy qz
    points: int
    data: str  # "ascii", "binary" or "binary_compressed"
    body_offset: int  # byte where the data starts

    @property
    def organised(self) -> bool:
        return self.height > 1

    def row_dtype(self) -> np.dtype:
        """The packed row of a binary file; repeated names (PCL's "_" padding) renamed."""
        names = [f if self.fields.index(f) == i else f"{f}#{i}"
                 for i, f in enumerate(self.fields)]
        return np.dtype([(n, t, (c,)) for n, t, c in zip(names, self.dtypes, self.counts)])


def read_pcd(path, *, material: Material | None = None, k: int | None = None,
             smooth: bool = True, normalise: str | None = None) -> Surfels:
    """Load a .pcd file as surfels (see the module docstring); k: neighbours for normals
    and radii; smooth: move the points onto their neighbourhood's plane; normalise: the
    per-surfel normalisation, "object", "render" or "none" (all three: points_to_surfels).
    Default (None): "object" for an unorganised cloud; an organised one (a depth capture)
    gets surfels sized by the sensor's pixels (``prep.pointcloud.capture_footprints``), which
    need none, and, when it has colours (photographs, already lit), the hint to render them
    unshaded (``Surfels.shading_hint``). DofsplatError for a damaged file or one without
    valid points."""
    from ..prep.normalise import check_method
    from ..prep.normalise import normalise as normalise_surfels
    from ..prep.pointcloud import capture_footprints, ground_up, points_to_surfels

    if normalise is not None:
        check_method(normalise)
    path = Path(path)
    if not path.is_file():
        raise DofsplatError(f"no such file: {path}")
    header, columns = read_pcd_columns(path)
    positions, colors, normals, viewpoint, camera = pcd_points(header, columns, str(path))
    surfels = points_to_surfels(positions, colors, normals, k=k, viewpoint=viewpoint,
                                smooth=smooth,
                                normalise="none" if camera is not None else normalise or "object",
                                source=str(path))
    surfels = surfels if material is None else replace(surfels, material=material)
    if camera is not None:
        surfels = capture_footprints(surfels, camera)
        if normalise not in (None, "none"):  # asked for: on top of the pixels' footprints
            surfels = normalise_surfels(surfels, normalise, progress=False)
        surfels.capture = camera  # the CLI's default view: the sensor's
        if colors is not None:
            surfels.shading_hint = "none"  # the colours are photographs: already lit
    else:
        surfels.up_hint = ground_up(surfels)  # a z-up scan is seen upright (prep.pointcloud)
    return surfels


def pcd_points(header: PcdHeader, columns: dict, source: str):
    """(positions (N, 3) float64, colours (N, 3) linear or None, normals or None,
    viewpoint (3,), camera) of the valid points, organised clouds turned into dofsplat's
    frame; camera: ``capture_camera`` for an organised cloud, else None."""
    from ..colors import srgb_to_linear
    from .ply import finite_rows

    missing = [f for f in ("x", "y", "z") if f not in columns]
    if missing:
        raise DofsplatError(f"{source}: the PCD file has no {' '.join(missing)} field "
                            f"(fields: {' '.join(header.fields)})")
    positions = np.stack([columns[f][:, 0] for f in ("x", "y", "z")], axis=1)
    positions = positions.astype(np.float64)
    colors = None
    packed = next((columns[f] for f in _PACKED_COLOUR if f in columns), None)
    if packed is not None and packed.dtype.itemsize == 4:
        bits = packed[:, 0].view(np.uint32)
        rgb = np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF], axis=1)
        colors = srgb_to_linear(rgb.astype(np.float32) / np.float32(255.0))
    normals = None
    if all(f in columns for f in ("normal_x", "normal_y", "normal_z")):
        normals = np.stack([columns[f][:, 0] for f in ("normal_x", "normal_y", "normal_z")],
                           axis=1).astype(np.float64)
    # the sensor's position: known for a capture (organised) or when the file sets one;
    # PCL writes the default 0 0 0 1 0 0 0 when it knows none
    known = header.organised or header.viewpoint != _DEFAULT_VIEWPOINT
    viewpoint = np.asarray(header.viewpoint[:3], dtype=np.float64) if known else None

    camera = None
    if header.organised:
        # pixels without depth are NaN: expected, so dropped without a warning
        keep = np.all(np.isfinite(positions), axis=1)
        keep[keep] = positions[keep, 2] > viewpoint[2]  # in front of the sensor
        if not keep.any():
            raise DofsplatError(f"{source}: no valid points (all {len(keep):,} are NaN or "
                                "behind the sensor)")
        camera = capture_camera(positions, keep, header.width, header.height, viewpoint)
        positions = positions[keep]
        colors = None if colors is None else colors[keep]
        normals = None if normals is None else normals[keep]
        flip = np.array([1.0, -1.0, -1.0])  # optical frame -> y up, looking along -z
        positions, viewpoint = positions * flip, viewpoint * flip
        normals = None if normals is None else normals * flip
    keep = finite_rows(positions, colors, source=source)
    if normals is not None:
        normals = np.where(np.all(np.isfinite(normals), axis=1)[:, None], normals, 0.0)[keep]
    positions = positions[keep]
    colors = None if colors is None else colors[keep]
    return positions, colors, normals, viewpoint, camera


def capture_camera(positions: np.ndarray, valid: np.ndarray, width: int, height: int,
                   viewpoint: np.ndarray) -> dict:
    """The depth camera that made an organised cloud, from its pixel grid.

    positions: (W H, 3) in the optical frame (x right, y down, z forward), NaN where the
    pixel has no depth; valid: the pixels with depth. A pinhole camera maps a point to pixel
    u = f_x x / z + c_x, v = f_y y / z + c_y: the intrinsics are fitted to the valid pixels
    by least squares. Returns the sensor's view in dofsplat's frame (turned as the points
    are): eye, target, up, frustum (L, R, B, T, N) and size (W, H), for the CLI's default
    camera, which then sees the capture as the sensor did, pixel for pixel."""
    v_idx, u_idx = np.divmod(np.flatnonzero(valid), width)
    p = positions[valid] - np.asarray(viewpoint, np.float64)  # seen from the sensor
    fx, cx = _fit_line(p[:, 0] / p[:, 2], u_idx)
    fy, cy = _fit_line(p[:, 1] / p[:, 2], v_idx)
    if not (fx > 0 and fy > 0):  # a degenerate grid (one column, a flipped image)
        fx = fy = max(width, height) / (2.0 * np.tan(np.radians(30.0)))
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    near = 0.5 * float(np.min(p[:, 2]))
    eye = np.asarray(viewpoint, np.float64) * np.array([1.0, -1.0, -1.0])
    # pixel u covers [u - 1/2, u + 1/2]; the optical y (down) is dofsplat's -y
    return {"eye": eye, "target": eye + [0.0, 0.0, -1.0], "up": np.array([0.0, 1.0, 0.0]),
            "frustum": np.array([near * (-0.5 - cx) / fx, near * (width - 0.5 - cx) / fx,
                                 -near * (height - 0.5 - cy) / fy, near * (0.5 + cy) / fy,
                                 near]),
            "size": np.array([width, height], np.float64)}


def _fit_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(slope, intercept) of y = slope x + intercept by least squares."""
    if len(x) < 2 or np.ptp(x) == 0:
        return 0.0, 0.0
    slope, intercept = np.polyfit(x, y.astype(np.float64), 1)
    return float(slope), float(intercept)


def read_pcd_columns(path) -> tuple[PcdHeader, dict[str, np.ndarray]]:
    """The header and the columns of a PCD file: field name -> (POINTS, COUNT) array."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except PermissionError as e:
        raise DofsplatError(f"{path}: cannot read: {e.strerror}") from e
    except OSError as e:
        raise DofsplatError(f"{path}: cannot read: {e}") from e
    header = parse_pcd_header(data[:_HEADER_MAX], str(path))
    body = data[header.body_offset:]
    if header.data == "ascii":
        columns = _ascii_columns(header, body, str(path))
    elif header.data == "binary":
        columns = _binary_columns(header, body, str(path))
    else:
        columns = _compressed_columns(header, body, str(path))
    return header, columns


def parse_pcd_header(data: bytes, source: str = "PCD") -> PcdHeader:
    """Parse the header lines up to and including DATA; DofsplatError if they are wrong."""
    def bad(why):
        return DofsplatError(f"{source}: not a PCD file or bad PCD header: {why}")

    values: dict[str, list[str]] = {}
    at = 0
    while True:
        end = data.find(b"\n", at)
        if end < 0:
            raise bad("no DATA line" if values else "no PCD header lines")
        line = data[at:end].decode("ascii", errors="replace").strip()
        at = end + 1
        if not line or line.startswith("#"):
            continue
        words = line.split()
        key = words[0].upper()
        if key not in _KEYS:
            raise bad(f"unexpected line {line[:60]!r}")
        values[key] = words[1:]
        if key == "DATA":
            break

    def ints(key, default=None):
        if key not in values:
            if default is None:
                raise bad(f"no {key} line")
            return default
        if not all(re.fullmatch(r"\d{1,12}", w) for w in values[key]) or not values[key]:
            raise bad(f"{key} must be whole numbers >= 0, got {' '.join(values[key])[:60]!r}")
        return [int(w) for w in values[key]]

    fields = values.get("FIELDS")
    if not fields:
        raise bad("no FIELDS line")
    sizes = ints("SIZE")
    types = [t.upper() for t in values.get("TYPE", [])]
    counts = ints("COUNT", [1] * len(fields))
    if not (len(sizes) == len(types) == len(counts) == len(fields)):
        raise bad(f"FIELDS, SIZE, TYPE and COUNT must have one entry per field "
                  f"({len(fields)}, {len(sizes)}, {len(types)}, {len(counts)})")
    dtypes = []
    for f, t, s, c in zip(fields, types, sizes, counts):
        if (t, s) not in _TYPES:
            raise bad(f"field {f!r} has TYPE {t} SIZE {s} (I and U take 1, 2, 4, 8; F 4, 8)")
        if not 1 <= c <= 4096:
            raise bad(f"field {f!r} has COUNT {c}")
        dtypes.append(_TYPES[(t, s)])
    width = ints("WIDTH", [-1])[0]
    height = ints("HEIGHT", [1])[0]
    points = ints("POINTS", [width * height if width >= 0 else -1])[0]
    if width < 0:
        width = points
    if points < 0:
        raise bad("neither POINTS nor WIDTH")
    if width * height != points:
        raise bad(f"WIDTH x HEIGHT = {width} x {height} is not POINTS = {points}")
    viewpoint = _DEFAULT_VIEWPOINT
    if "VIEWPOINT" in values:
        try:
            viewpoint = tuple(float(v) for v in values["VIEWPOINT"])
        except ValueError:
            viewpoint = ()
        if len(viewpoint) != 7 or not all(np.isfinite(viewpoint)):
            raise bad(f"VIEWPOINT needs 7 numbers, got {' '.join(values['VIEWPOINT'])[:60]!r}")
    mode = values["DATA"][0].lower() if values["DATA"] else ""
    if mode not in _DATA_MODES:
        raise bad(f"DATA must be one of {', '.join(_DATA_MODES)}, got {mode!r}")
    return PcdHeader(tuple(fields), tuple(dtypes), tuple(counts), width, height, viewpoint,
                     points, mode, at)


def _check_points(header: PcdHeader, source: str) -> None:
    if header.points == 0:
        raise DofsplatError(f"{source}: the PCD file holds no points (POINTS 0)")


def _ascii_columns(header: PcdHeader, body: bytes, source: str) -> dict:
    _check_points(header, source)
    per_point = sum(header.counts)
    need = header.points * per_point
    words = body.split()
    if len(words) < need:
        raise DofsplatError(f"{source}: truncated PCD file: {header.points:,} points need "
                            f"{need:,} values, the file has {len(words):,}")
    try:
        values = np.array(words[:need], dtype=np.float64).reshape(header.points, per_point)
    except (ValueError, OverflowError) as e:
        raise DofsplatError(f"{source}: corrupt PCD file: a value that is not a number") from e
    columns, at = {}, 0
    with np.errstate(invalid="ignore", over="ignore"):
        for f, t, c in zip(header.fields, header.dtypes, header.counts):
            block = values[:, at:at + c]
            if f not in columns:
                packed = f in _PACKED_COLOUR and t == "<f4"
                columns[f] = _packed_from_text(block) if packed else block.astype(t)
            at += c
    return columns


def _packed_from_text(values: np.ndarray) -> np.ndarray:
    """A float-typed packed colour read from text, as uint32 bits.

    PCL writes it as the uint32 integer (an opaque colour's float bits are a NaN); older
    writers printed the float itself (a tiny denormal when alpha is 0), whose float32 bits
    are the colour. A whole number in [0, 2^32) is the first kind.
    """
    whole = (values == np.round(values)) & (values >= 0) & (values < 2.0**32)
    as_int = np.where(whole, values, 0).astype(np.uint64).astype(np.uint32)
    as_bits = values.astype(np.float32).view(np.uint32)
    return np.where(whole, as_int, as_bits)


def _binary_columns(header: PcdHeader, body: bytes, source: str) -> dict:
    _check_points(header, source)
    row = header.row_dtype()
    need = header.points * row.itemsize
    if len(body) < need:
        raise DofsplatError(f"{source}: truncated PCD file: {header.points:,} points need "
                            f"{need:,} bytes of data, the file has {len(body):,}")
    rows = np.frombuffer(body, dtype=row, count=header.points)
    return {f: np.array(rows[n]) for f, n in zip(header.fields, row.names)
            if f == n}


def _compressed_columns(header: PcdHeader, body: bytes, source: str) -> dict:
    import lzf

    _check_points(header, source)
    if len(body) < 8:
        raise DofsplatError(f"{source}: truncated PCD file: no compressed data")
    compressed, uncompressed = np.frombuffer(body[:8], dtype="<u4")
    compressed, uncompressed = int(compressed), int(uncompressed)
    sizes = [np.dtype(t).itemsize * c for t, c in zip(header.dtypes, header.counts)]
    need = header.points * sum(sizes)
    if uncompressed != need:
        raise DofsplatError(f"{source}: corrupt PCD file: {header.points:,} points need "
                            f"{need:,} bytes, the compressed block holds {uncompressed:,}")
    if compressed > len(body) - 8:
        raise DofsplatError(f"{source}: truncated PCD file: the compressed block has "
                            f"{compressed:,} bytes, the file {len(body) - 8:,}")
    if need > _MAX_LZF_RATIO * compressed + 1024:
        raise DofsplatError(f"{source}: corrupt PCD file: {compressed:,} compressed bytes "
                            f"cannot hold {need:,}")
    try:
        raw = lzf.decompress(body[8:8 + compressed], uncompressed)
    except ValueError as e:
        raise DofsplatError(f"{source}: corrupt PCD file: the LZF data is damaged") from e
    if raw is None or len(raw) != uncompressed:
        raise DofsplatError(f"{source}: corrupt PCD file: the LZF data does not decompress "
                            f"to {uncompressed:,} bytes")
    # the columns lie one after the other: all points' x, then all y, ...
    columns, at = {}, 0
    for f, t, c, size in zip(header.fields, header.dtypes, header.counts, sizes):
        block = np.frombuffer(raw, dtype=t, count=header.points * c, offset=at)
        if f not in columns:
            columns[f] = block.reshape(header.points, c).copy()
        at += header.points * size
    return columns
