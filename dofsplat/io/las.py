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

    from ..prep.normalise import check_method
    from ..prep.pointcloud import points_to_surfels
    from .ply import finite_rows

    check_method(normalise)
    path = Path(path)
    if not path.is_file():
        raise DofsplatError(f"no such file: {path}")
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
    extent = float(np.max(np.abs(positions)))
    quantum = scale if math.isfinite(scale) and scale > 0 else 1e-3
    if extent * 2.0**-24 <= 0.5 * quantum:
        return positions
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    shift = -np.round(0.5 * (lo + hi))
    warnings.warn(f"{source}: coordinates reach {extent:,.0f}, beyond float32 precision; "
                  f"shifted by ({', '.join(f'{v:,.0f}' for v in shift)}): camera positions "
                  "are in these shifted (and y-up) coordinates", stacklevel=3)
    positions += shift  # (in place: the readers' own array)
    return positions
