"""LAS and LAZ point clouds (ASPRS LAS 1.0 to 1.4, COPC included), read by laspy.

laspy decodes the points (LAZ through its lazrs backend); the coordinates are the scaled
x y z, the colour the point format's red green blue when it has them. LAS stores colour as
16-bit sRGB values: they are scaled by 1/65535 and decoded to linear. Many writers put
8-bit values in those 16-bit fields; when no channel exceeds 255 the scale is 1/255.

LAS files are often georeferenced, with coordinates of 10^5 to 10^7 metres, where float32
(the surfel positions) keeps only centimetres or worse. When float32 would be coarser
than the file's own quantisation, the points are shifted by the (rounded) centre of their
bounding box, with a warning that gives the shift.

LAS coordinates are z-up (x east, y north, z up); dofsplat's are y-up (the default camera
looks along -z with y up). The points are turned -90 degrees about x, (x, y, z) ->
(x, z, -y), so that ``dofsplat render`` shows the scan upright, seen from the south
(from the scan's -y side) rather than from above. Surfels then come from
:func:`dofsplat.prep.pointcloud.points_to_surfels` (PCA normals, radii from the density).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from ..errors import DofsplatError, library_message
from ..surfels import Material, Surfels

LAS_EXTENSIONS = (".las", ".laz")
READ_CHUNK = 1 << 20  # points decoded at a time


def read_las(path, *, material: Material | None = None, k: int | None = None,
             smooth: bool = True, normalise: str = "object") -> Surfels:
    """Load a .las / .laz file as surfels; k: neighbours for normals and radii; smooth:
    move the points onto their neighbourhood's plane; normalise: the per-surfel
    normalisation, "object", "render" or "none" (all three: points_to_surfels)."""
    from dataclasses import replace

    from ..prep.cloudfile import wants_disk
    from ..prep.normalise import check_method
    from ..prep.pointcloud import points_to_surfels
    from .ply import finite_rows

    check_method(normalise)
    path = Path(path)
    if not path.is_file():
        raise DofsplatError(f"no such file: {path}")
    if wants_disk(las_point_count(path)):
        surfels = read_las_on_disk(path, k=k, smooth=smooth, normalise=normalise)
        return surfels if material is None else replace(surfels, material=material)
    positions, colors, scale = read_las_points(path)
    keep = finite_rows(positions, colors, source=str(path))
    if not keep.all():
        positions = positions[keep]
        colors = None if colors is None else colors[keep]
    positions = _recentre(positions, scale, str(path))
    positions = z_up_to_y_up(positions)
    surfels = points_to_surfels(positions, colors, None, k=k, smooth=smooth,
                                normalise=normalise, source=str(path))
    return surfels if material is None else replace(surfels, material=material)


def read_las_points(path) -> tuple[np.ndarray, np.ndarray | None, float]:
    """(positions (N, 3) float64, colours (N, 3) float32 linear or None, the smallest
    coordinate scale of the header) from a LAS / LAZ file, read ``READ_CHUNK`` points at a
    time into the arrays (issue 50: the file's records are never decoded whole beside
    them)."""
    import laspy

    from ..colors import srgb_to_linear

    path = Path(path)
    try:
        with laspy.open(str(path)) as reader:
            header = reader.header
            n = int(header.point_count)
            names = set(header.point_format.dimension_names)
            scale = float(np.min(header.scales))
            positions = np.empty((n, 3), np.float64)
            rgb = (np.empty((n, 3), np.uint16) if {"red", "green", "blue"} <= names
                   else None)
            done = 0
            for points in reader.chunk_iterator(READ_CHUNK):
                m = min(len(points), n - done)
                for axis, values in enumerate((points.x, points.y, points.z)):
                    positions[done:done + m, axis] = np.asarray(values)[:m]
                if rgb is not None:
                    for c, name in enumerate(("red", "green", "blue")):
                        rgb[done:done + m, c] = np.asarray(points[name])[:m]
                done += m
    except PermissionError as e:
        raise DofsplatError(f"{path}: cannot read: {e.strerror}") from e
    except Exception as e:  # laspy and lazrs raise many types for a damaged file
        raise DofsplatError(f"{path}: corrupt or truncated LAS/LAZ file: "
                            f"{library_message(e)}") from e
    if n == 0 or done == 0:
        raise DofsplatError(f"{path}: the file holds no points")
    if done < n:
        raise DofsplatError(f"{path}: corrupt or truncated LAS/LAZ file: the header counts "
                            f"{n:,} points, the file holds {done:,}")
    colors = None
    if rgb is not None:
        top = 255.0 if int(rgb.max()) <= 255 else 65535.0
        colors = np.empty((n, 3), np.float32)
        for start in range(0, n, READ_CHUNK):  # (a chunk of float32 temporaries at a time)
            part = slice(start, start + READ_CHUNK)
            colors[part] = srgb_to_linear(rgb[part].astype(np.float32) / np.float32(top))
    return positions, colors, scale


def las_point_count(path) -> int:
    """The number of points a LAS / LAZ file's header gives."""
    return int(_las_header(Path(path)).point_count)


def read_las_on_disk(path, *, k: int | None = None, smooth: bool = True,
                     normalise: str = "object", progress: bool = True) -> Surfels:
    """``read_las`` of a cloud larger than memory (issue 50): the points streamed into a
    work folder in chunks and prepared chunk by chunk from there
    (``io.on_disk.prepare_on_disk``), the same surfels as the in-memory preparation's
    where each point's neighbourhoods fit in its chunk's halo, in the order of the
    chunks."""
    from .on_disk import prepare_on_disk

    path = Path(path)
    return prepare_on_disk(path, las_point_count(path),
                           lambda folder, bar: _decoded(path, folder, bar),
                           k=k, smooth=smooth, normalise=normalise, progress=progress)


def _decoded(path: Path, folder: Path, bar):
    """The file's points decoded once into folder (input.f64, input.rgb): (blocks, lo, hi)
    for ``cloudfile.write_cloud``: blocks() reads them back ``cloudfile.BLOCK`` points at
    a time, recentred, turned y-up and their colours linear, as ``read_las`` does with the
    points in memory; lo, hi (3,) their bounds."""
    from ..colors import srgb_to_linear
    from ..prep.cloudfile import BLOCK, read_rows
    from ..prep.pointcloud import MID_GREY

    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    top = 0
    done = 0
    header = _las_header(path)
    n = int(header.point_count)
    has_rgb = {"red", "green", "blue"} <= set(header.point_format.dimension_names)
    scale = float(np.min(header.scales))
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "input.f64", "wb") as fp, open(folder / "input.rgb", "wb") as fc:
        for p, rgb in _las_chunks(path, n, has_rgb):
            if not np.all(np.isfinite(p)):
                raise DofsplatError(f"{path}: the file holds coordinates that are not "
                                    "finite numbers")
            np.minimum(lo, p.min(axis=0), out=lo)
            np.maximum(hi, p.max(axis=0), out=hi)
            fp.write(p.tobytes())
            if rgb is not None:
                top = max(top, int(rgb.max()))
                fc.write(rgb.tobytes())
            done += len(p)
            bar.update(len(p))
    if n == 0 or done == 0:
        raise DofsplatError(f"{path}: the file holds no points")
    if done < n:
        raise DofsplatError(f"{path}: corrupt or truncated LAS/LAZ file: the header counts "
                            f"{n:,} points, the file holds {done:,}")
    shift = _shift(lo, hi, scale, str(path))
    scale_rgb = np.float32(255.0 if top <= 255 else 65535.0)

    def blocks():
        for a in range(0, n, BLOCK):
            b = min(a + BLOCK, n)
            p = read_rows(folder / "input.f64", np.float64, a, b)
            if shift is not None:
                p += shift
            p = z_up_to_y_up(p)
            if has_rgb:
                rgb = read_rows(folder / "input.rgb", np.uint16, a, b)
                c = np.clip(srgb_to_linear(rgb.astype(np.float32) / scale_rgb), 0.0, 1.0)
            else:
                c = np.full((b - a, 3), MID_GREY, np.float32)
            yield p, c

    if shift is not None:
        lo, hi = lo + shift, hi + shift
    corners = z_up_to_y_up(np.stack([lo, hi]))
    return blocks, corners.min(axis=0), corners.max(axis=0)


def _las_header(path: Path):
    """The LAS / LAZ file's header (laspy's), or DofsplatError."""
    import laspy

    try:
        with laspy.open(str(path)) as reader:
            return reader.header
    except PermissionError as e:
        raise DofsplatError(f"{path}: cannot read: {e.strerror}") from e
    except Exception as e:  # laspy and lazrs raise many types for a damaged file
        raise DofsplatError(f"{path}: corrupt or truncated LAS/LAZ file: "
                            f"{library_message(e)}") from e


def _las_chunks(path: Path, n: int, has_rgb: bool):
    """The file's points, ``READ_CHUNK`` at a time: (positions (M, 3) float64, colours
    (M, 3) uint16 as stored, or None), at most n in all; DofsplatError for a damaged
    file."""
    import laspy

    done = 0
    try:
        with laspy.open(str(path)) as reader:
            for points in reader.chunk_iterator(READ_CHUNK):
                m = min(len(points), n - done)
                p = np.empty((m, 3), np.float64)
                for axis, values in enumerate((points.x, points.y, points.z)):
                    p[:, axis] = np.asarray(values)[:m]
                rgb = (np.stack([np.asarray(points[c])[:m] for c in ("red", "green", "blue")],
                                axis=1).astype(np.uint16) if has_rgb else None)
                done += m
                yield p, rgb
    except PermissionError as e:
        raise DofsplatError(f"{path}: cannot read: {e.strerror}") from e
    except Exception as e:  # laspy and lazrs raise many types for a damaged file
        raise DofsplatError(f"{path}: corrupt or truncated LAS/LAZ file: "
                            f"{library_message(e)}") from e


def z_up_to_y_up(positions: np.ndarray) -> np.ndarray:
    """(x, y, z) -> (x, z, -y): LAS's z-up frame turned -90 degrees about x into y-up, in
    place (positions (N, 3) float64, which it returns)."""
    y = positions[:, 1].copy()
    positions[:, 1] = positions[:, 2]
    np.negative(y, out=positions[:, 2])
    return positions


def _recentre(positions: np.ndarray, scale: float, source: str) -> np.ndarray:
    """Shift points far from the origin so that float32 keeps the file's precision (in
    place: positions (N, 3) float64, which it returns)."""
    shift = _shift(positions.min(axis=0), positions.max(axis=0), scale, source)
    if shift is not None:
        positions += shift  # (in place: the readers' own array)
    return positions


def _shift(lo: np.ndarray, hi: np.ndarray, scale: float, source: str) -> np.ndarray | None:
    """The shift (3,) that ``_recentre`` gives points of bounds lo, hi (3,), with its
    warning, or None where float32 keeps the file's precision as they are."""
    extent = float(max(np.max(np.abs(lo)), np.max(np.abs(hi))))
    quantum = scale if math.isfinite(scale) and scale > 0 else 1e-3
    if extent * 2.0**-24 <= 0.5 * quantum:
        return None
    shift = -np.round(0.5 * (lo + hi))
    warnings.warn(f"{source}: coordinates reach {extent:,.0f}, beyond float32 precision; "
                  f"shifted by ({', '.join(f'{v:,.0f}' for v in shift)}): camera positions "
                  "are in these shifted (and y-up) coordinates", stacklevel=4)
    return shift
