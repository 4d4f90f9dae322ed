"""Bare points to surfels: normals, their orientation, radii (issue 4, item 3).

A scan or a mesh's vertices give positions (and perhaps colours); a surfel also needs a
normal and a radius. :func:`points_to_surfels` estimates both from each point's k nearest
neighbours (scipy's k-d tree), in five steps:

1. **neighbours**: the k nearest neighbours of every point (exact duplicates are merged
   first: they carry no information and make the distances degenerate);
2. **normals** by local PCA: the eigenvector of the smallest eigenvalue of the covariance
   of the point and its k neighbours (``pca_normals``, a numba kernel, and its numpy twin
   ``pca_normals_slow``); then, unless ``smooth=False``, each point is moved along that
   normal onto the plane (``project_to_planes``): scanner noise and quantisation (the
   lion's coordinates are whole centimetres) put points off the surface, and splats off
   the surface are uneven in depth and coverage;
3. **orientation**: towards the sensor when its position is known (``viewpoint``), else a
   consistent orientation propagated over the neighbour graph (Hoppe et al. 1992, "Surface
   reconstruction from unorganized points"): a minimum spanning tree over the symmetric
   kNN graph with edge cost 1 - |n_i . n_j| carries the sign from one point through each
   connected component, and the component is then turned outward by a vote of its points
   seen from 32 directions around it (``outward_votes``: a visible surface faces its
   viewer);
4. **radii and areas** (``surfel_radii``). Each surfel stands for the area 1 / rho, rho
   the local number of points per unit area from a smooth kernel density over the k
   neighbours: exp(-d^2 / 2s^2) - exp(-R^2 / 2s^2) on the disk of radius R = the distance
   to the k-th neighbour, s = R / 2, divided by its integral. The kernel falls to zero at
   R, so points tied at distance R (common on grids) do not matter, and on any regular
   lattice it sums to the density within about 1.5 %. The disk must also *cover* the
   surface: irregular samples leave gaps that disks of area 1 / rho do not reach (visible
   holes). So the radius is r = max(sqrt(1 / rho), sqrt(2) x the distance to the farthest
   corner of the point's Voronoi cell among its neighbours, in its tangent plane), and
   ``Surfels.weight`` = (1 / rho) / r^2 <= 1 keeps the area right (a splat deposits
   r^2 x weight). On a square grid of spacing h both terms are h (the corners are at
   h / sqrt(2)): r = h and weight = 1, the convention of ``surfels.py``. Radii are capped
   near outliers (a few points far from the rest).

5. **normalisation**: the per-point normalisation of ``dofsplat.prep.normalise`` (paper Section
   6.3; the object-space method unless ``normalise`` says otherwise) corrects the weights so
   that the splats sum to 1 over the surface.

All steps are vectorised or jitted; the 437k-point dragon takes a few seconds on two cores.
A cloud of more than ``CHUNK_POINTS`` points runs steps 1-5 chunk by chunk, each with a halo
of its neighbours, and joins the orientation, the radii's outlier cap and the normalisation's
level across the chunks (``prep.chunks``): memory stays bounded beside the cloud's arrays.
"""

from __future__ import annotations

import math
import sys
import warnings
from dataclasses import replace

from ..jit import numba
import numpy as np

from ..errors import DofsplatError
from ..surfels import Surfels
from .duplicates import _first_of_runs, first_rows, merge_duplicates  # noqa: F401
from .neighbours import QUERY_CHUNK, as_index_array, fibonacci_directions, nearest_neighbours
from .rules import OUTLIER_RADIUS_FACTOR, TIE_FRACTION, outlier_cap, sheet_votes  # noqa: F401

DEFAULT_K = 24  # neighbours for PCA, smoothing and density: the lion scan's 1 cm
# quantisation needs that many for a steady plane fit (of its interior pixels, 0.93 / 0.96
# sum to 1 +- 0.1 with k = 12, 0.949 / 0.967 with 16, 0.960 / 0.970 with 24; the dragon
# reads the same with 16 or 24; docs/maths.md)
MIN_K = 4  # fewer neighbours cannot fit a plane robustly
# more is no better fit (the plane of 256 neighbours already spans a dense scan's features)
# and the neighbour lists take 12 bytes a neighbour and a point (prep.neighbours): K = 256
# on 10 M points is 31 GB, and a K of a million on a million points asked for 16 TB before
# it was refused
MAX_K = 256
ORIENT_K = 6  # neighbours per point in the orientation graph (a sparser graph is faster)
DENSITY_BANDWIDTH = 2.0  # R / s of the density kernel (module docstring)
CLUSTER_RADIUS_FACTOR = 2.0  # radius <= this x the distance to the 4th neighbour
VORONOI_NEIGHBOURS = 10  # neighbours that cut a point's Voronoi cell (coverage radius)
MID_GREY = 0.2140  # linear value of the sRGB mid grey 0.5: the colour of uncoloured points
VOTE_DIRECTIONS = 32  # views that vote for the sign of a component's normals
VOTE_MAX_POINTS = 1 << 16  # points that take part in the vote (a random sample)
# points (or a point's edges) at a time where a step makes (rows, k+1) or (rows, k+1, 3)
# temporaries: 10 MB of them at k = 24, where all rows at once peaked at 2.4 kB a point
# (issue 50). The results do not depend on it: each row is computed alone
ROW_CHUNK = 1 << 14
# more distinct points than this are prepared in chunks of at most this many, each with a
# halo of its neighbours' points (``prep.chunks``), so that memory stays bounded whatever
# the cloud's size (issue 50): at about 0.7 kB a point in the preparation, a chunk of 2^20
# points peaks near 1 GB
CHUNK_POINTS = 1 << 20
ROW_BLOCK = 1 << 20  # surfels a pass over a whole model (``ground_up``) reads at a time


def points_to_surfels(positions, colors=None, normals=None, *, k: int | None = None,
                      viewpoint=None, smooth: bool = True, normalise: str = "object",
                      progress: bool = True, source: str = "points",
                      chunk_points: int | None = None) -> Surfels:
    """Surfels from a bare point cloud: PCA normals, orientation, radii and areas.

    positions: (N, 3) float, world units
    colors:    (N, 3) float, linear RGB in [0, 1], or None for mid grey (sRGB 0.5)
    normals:   (N, 3) float or None; rows that are zero or not finite (and all rows when
               None) are estimated by PCA. Given normals keep their sign unless
               ``viewpoint`` is given.
    k:         neighbours for PCA and the density (default ``DEFAULT_K`` = 24; 4 to ``MAX_K`` = 256)
    viewpoint: (3,) sensor or camera position, world units, or (N, 3), one per point (the
               scans of a multi-scan capture): every normal is turned towards it. None: estimated normals are oriented consistently by propagation over
               the neighbour graph (outward for closed surfaces); given normals seed it.
    smooth:    move each point along its normal onto the plane fitted to its k neighbours
               (:func:`project_to_planes`): removes scanner noise and coordinate
               quantisation across the surface; False keeps the positions as measured
    normalise: the per-surfel normalisation (:func:`dofsplat.prep.normalise.normalise`) that
               makes the splats sum to 1 over the surface: "object" (default), "render",
               or "none" (the weights of step 4)
    progress:  show tqdm progress bars on stderr (only when it is a terminal)
    source:    name for messages (e.g. the file name)
    chunk_points: more distinct points than this (default ``CHUNK_POINTS``) are prepared in
               chunks of at most this many (``prep.chunks.chunked_surfels``: the same steps
               on each chunk and a halo of its neighbours, bounded memory)

    Rows with NaN or inf positions are dropped with a warning; exact duplicate positions
    are merged (colours averaged, the first normal kept). Raises DofsplatError for fewer
    than 3 distinct points or malformed arrays. Returns ``Surfels`` whose ``weight`` is
    the area each surfel stands for over r^2 (module docstring, step 4), normalised
    unless ``normalise="none"``.
    """
    from .normalise import check_method
    from .normalise import normalise as normalise_surfels

    check_method(normalise)
    pts, cols, nrm = _check_inputs(positions, colors, normals, source)
    n_in = len(pts)
    vp = None
    if viewpoint is not None:
        vp = np.asarray(viewpoint, np.float64)
        if vp.shape not in ((3,), (n_in, 3)) or not np.all(np.isfinite(vp)):
            raise DofsplatError(f"viewpoint must be three finite numbers, or one such row per "
                                f"point, got an array of shape {vp.shape}" if vp.ndim else
                                f"viewpoint must be three finite numbers, got {viewpoint!r}")
    pts, cols, nrm, kept = merge_duplicates(pts, cols, nrm, source)
    if vp is not None and vp.ndim == 2 and kept is not None:
        vp = vp[kept]
    n = len(pts)
    if n < 3:
        raise DofsplatError(f"{source}: need at least 3 distinct points to estimate normals "
                            f"and radii, got {n}")
    k = _check_k(k, n)

    chunk_points = CHUNK_POINTS if chunk_points is None else chunk_points
    if n > chunk_points:  # more than a chunk: in chunks, with bounded memory (issue 50)
        from .chunks import chunked_surfels

        if cols is None:
            cols = np.full((n, 3), MID_GREY, np.float32)
        return chunked_surfels(surfel_stages, pts, cols, nrm, vp, k=k, smooth=smooth,
                               normalise=normalise, chunk_points=chunk_points,
                               progress=progress, source=source)
    stages = 4 if normalise == "none" else 5
    with _stage_bar(stages, f"{source}: points to surfels", progress and n > QUERY_CHUNK) as bar:
        pts, normals_out, radius, area_weight, _ = surfel_stages(pts, nrm, vp, k, smooth, bar)
        if cols is None:
            cols = np.full((n, 3), MID_GREY, np.float32)
        surfels = Surfels(positions=pts, normals=normals_out, radius=radius, colors=cols,
                          weight=area_weight)
        # the surfels hold float32 copies: the normalisation's own neighbour lists need not
        # sit beside these (issue 50)
        del pts, normals_out, radius, area_weight
        if normalise != "none":
            bar.set_postfix_str(f"normalise ({normalise})")
            surfels = normalise_surfels(surfels, normalise, progress=False)
            bar.update()
    return surfels


def cloud_to_surfels(cloud, *, k: int | None = None, smooth: bool = True,
                     normalise: str = "object", progress: bool = True, source: str = "points",
                     store=None) -> Surfels:
    """``points_to_surfels`` of a cloud on disk (a ``cloudfile.CloudFile``, its duplicates
    merged and its points in chunks: ``cloudfile.write_cloud``), chunk by chunk in its own
    chunks, without a viewpoint: Surfels in the cloud's order, whose arrays
    are memory maps of files in store (a folder; None: in memory), where each chunk's
    results are kept as it completes (``chunks.chunked_surfels``). The normals the cloud
    holds (``CloudFile.normals``) are taken as given normals are in memory."""
    from .chunks import chunked_surfels
    from .normalise import check_method

    check_method(normalise)
    n = len(cloud)
    if n < 3:
        raise DofsplatError(f"{source}: need at least 3 distinct points to estimate normals "
                            f"and radii, got {n}")
    return chunked_surfels(surfel_stages, cloud, cloud.colours(), cloud.normals(), None,
                           k=_check_k(k, n), smooth=smooth, normalise=normalise,
                           chunk_points=n, progress=progress, source=source, store=store)


def surfel_stages(pts: np.ndarray, nrm, vp, k: int, smooth: bool, bar=None, *,
                  vote: bool = True, outliers: bool = True):
    """Steps 1-4 of the module docstring on points without duplicates: (positions (N, 3)
    float64, moved onto their planes where smooth; normals (N, 3) float64; radius (N,);
    area_weight (N,); orientation), ``bar`` updated after each step. nrm: (N, 3) given
    normals (rows of zeros or NaN: none) or None; vp: ``points_to_surfels``' viewpoint or
    None. orientation is None where the normals were turned towards vp or all given; else
    (label (N,), n_comp, tally, has_fixed (n_comp,)): the neighbour graph's components,
    ``outward_votes``' votes with their sums (tally=True) and whether a component holds a
    given normal.
    vote=False leaves the normals as propagated, before the votes turn a component, and
    outliers=False the radii without ``outlier_cap`` (what the preparation in chunks joins
    across chunks: ``prep.chunks``); it then returns (r_area, limit) of
    :func:`area_radii` after the orientation, for that cap."""
    bar = _stage_bar(4, "", False) if bar is None else bar
    n = len(pts)
    bar.set_postfix_str("neighbours")
    # smoothing moves the points, and their distances are measured again after it
    dist, idx = nearest_neighbours(pts, k, distances=not smooth)
    bar.update()

    bar.set_postfix_str("normals")
    given = np.zeros(n, bool)
    if nrm is not None:
        lengths = np.linalg.norm(nrm, axis=1)
        given = np.isfinite(lengths) & (lengths > 1e-12)
    normals_out = np.empty((n, 3), np.float64)
    if smooth or not given.all():
        plane_normals, centroids = pca_planes(pts, idx)
        normals_out[:] = plane_normals
        if smooth:
            pts = project_to_planes(pts, plane_normals, centroids)
            del plane_normals, centroids
    if given.any():
        normals_out[given] = nrm[given] / np.linalg.norm(nrm[given], axis=1)[:, None]
    # the density (step 4) needs only the distances: taken now, they need not sit
    # beside the orientation's graph, and the smoothed points' distances are never
    # held whole (issue 50)
    if smooth:  # the points moved: their neighbours' distances and order changed
        idx, r_area, r_limit = remeasured_density(pts, idx, outliers)
    else:
        r_area, r_limit = area_radii(dist, outliers)
    del dist
    # the later steps read no further than the ORIENT_K or VORONOI_NEIGHBOURS nearest
    idx = np.ascontiguousarray(idx[:, :max(ORIENT_K, VORONOI_NEIGHBOURS) + 1])
    bar.update()

    bar.set_postfix_str("orientation")
    orientation = None
    if vp is not None:
        normals_out = orient_towards(pts, normals_out, vp)
    elif not given.all():
        normals_out, label, n_comp, has_fixed = propagate_orientation(
            pts, normals_out, idx[:, 1:min(k, ORIENT_K) + 1], fixed=given)
        tally = outward_votes(pts, normals_out, label, n_comp, tally=True)
        if vote:
            flip = (tally[0] < 0) & ~has_fixed
            normals_out[flip[label]] *= -1.0
        orientation = label, n_comp, tally, has_fixed
    bar.update()

    bar.set_postfix_str("radii")
    radius, area_weight = surfel_radii(pts, normals_out, idx, r_area, r_limit)
    bar.update()
    if not outliers:
        return pts, normals_out, radius, area_weight, orientation, (r_area, r_limit)
    return pts, normals_out, radius, area_weight, orientation


# A depth capture's surfels: the footprint of a disk of this many pixels (radius) seen from
# the sensor. 1 px would tile the image exactly (r = h, surfels.py); 1.25 px with weight 1
# (each surfel deposits its whole disk, 1.56 x its pixel) keeps the accumulated weight above
# 1 inside surfaces despite the sensor's depth steps (docs/formats.md)
CAPTURE_FOOTPRINT_PX = 1.25
CAPTURE_MAX_STRETCH = 4.0  # r_u / r_v at most: a grazing surface's footprint stays bounded


def capture_footprints(surfels: Surfels, capture: dict,
                       footprint_px: float = CAPTURE_FOOTPRINT_PX) -> Surfels:
    """A depth capture's surfels sized by the sensor's pixels, not by 3-D neighbours.

    A capture has one point per pixel: each surfel stands for the piece of its tangent plane
    that its pixel sees. With J the 2 x 2 Jacobian from the tangent plane to the capture's
    pixels (the sensor's pinhole, ``capture``: eye, frustum, size in dofsplat's frame), the
    ellipse that projects to a circle of ``footprint_px`` pixels is V = footprint_px^2
    (J^T J)^-1: its axes are the eigenvectors of J^T J, its radii footprint_px / sqrt(eig).
    Seen from the sensor every surfel is then a disk of footprint_px pixels, so coverage
    does not depend on how the surface is tilted (3-D neighbours miss across depth steps
    and under-cover tilted surfaces: holes). Radii along a grazing surface are capped at
    CAPTURE_MAX_STRETCH x the other. Returns elliptical surfels (tangent, radius_v) with
    weight 1, the per-surfel normalisation replaced (the pixel grid is the partition).
    """
    eye = np.asarray(capture["eye"], np.float64)
    width, height = (float(v) for v in capture["size"])
    left, right, bottom, top, near = (float(v) for v in capture["frustum"])
    fx, fy = width * near / (right - left), height * near / (top - bottom)  # pixels
    p = surfels.positions.astype(np.float64) - eye  # the sensor looks along -z, y up
    z = np.maximum(-p[:, 2], 1e-12)
    n = surfels.normals.astype(np.float64)
    a = np.cross(n, [0.0, 1.0, 0.0])
    flat = np.linalg.norm(a, axis=1) < 1e-6
    a[flat] = np.cross(n[flat], [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a, axis=1)[:, None]
    b = np.cross(n, a)
    # rows of d(pixel)/d(world): u = fx x / z, v = -fy y / z with z = -p_z
    du = np.stack([fx / z, np.zeros_like(z), fx * p[:, 0] / z ** 2], axis=1)
    dv = -np.stack([np.zeros_like(z), fy / z, fy * p[:, 1] / z ** 2], axis=1)
    jac = np.stack([np.stack([(du * a).sum(1), (du * b).sum(1)], axis=1),
                    np.stack([(dv * a).sum(1), (dv * b).sum(1)], axis=1)], axis=1)  # (N, 2, 2)
    lam, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", jac, jac))  # ascending
    lam = np.maximum(lam, 1e-300)
    r_v = footprint_px / np.sqrt(lam[:, 1])
    r_u = np.minimum(footprint_px / np.sqrt(lam[:, 0]), CAPTURE_MAX_STRETCH * r_v)
    tangent = a * vec[:, 0, 0:1] + b * vec[:, 1, 0:1]
    return replace(surfels, radius=r_u.astype(np.float32), radius_v=r_v.astype(np.float32),
                   tangent=tangent.astype(np.float32),
                   weight=np.ones(len(surfels), np.float32))


# fraction of a scan's area that must face +z, flat (n_z > GROUND_COS), to call it z-up
GROUND_AREA = 0.1
GROUND_COS = 0.95


def ground_up(surfels: Surfels) -> tuple[float, float, float] | None:
    """(0, 0, 1) when a scan shows a ground facing +z, else None (y-up, the default).

    Bare point clouds carry no up axis, and scans are often z-up (surveying's convention,
    the lion's PLY) where meshes are y-up (graphics'). A scan of anything standing on the
    ground has a large flat area facing up: if at least GROUND_AREA of the area faces +z
    (n_z > GROUND_COS) and more than twice what faces +y, the scan is taken as z-up (the
    lion: 19 % against 2 %; the Stanford meshes, y-up: 4 % at most), unless it is flat in
    x-y (its z extent under a tenth of its largest: a facade or a floor alone, which the
    default view shows face-on). The coordinates are not changed: the default camera takes
    the hint (``Surfels.up_hint``)."""
    total = up_z = up_y = 0.0
    for s in range(0, len(surfels), ROW_BLOCK):  # (a model of memory maps: a block at a time)
        rows = slice(s, s + ROW_BLOCK)
        area = surfels.radius[rows].astype(np.float64) ** 2
        if surfels.weight is not None:
            area = area * surfels.weight[rows]
        n = surfels.normals[rows]
        total += float(area.sum())
        up_z += float(area[n[:, 2] > GROUND_COS].sum())
        up_y += float(area[n[:, 1] > GROUND_COS].sum())
    if total <= 0:
        return None
    lo, hi = surfels.bounds()
    extent = hi - lo
    if extent[2] < 0.1 * float(extent.max()):
        return None  # a flat scan in x-y (a facade, a floor alone): nothing stands up
    up_z, up_y = up_z / total, up_y / total
    return (0.0, 0.0, 1.0) if up_z >= GROUND_AREA and up_z > 2.0 * up_y else None


# -- steps -------------------------------------------------------------------------------


def pca_normals(positions: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Unit normals by local PCA: (N, 3) float64, sign arbitrary.

    positions: (N, 3) float64; idx: (N, m) int32 or int64 neighbour indices (the point
    itself may be among them). The normal is the eigenvector of the smallest eigenvalue of the
    neighbourhood's covariance matrix.
    """
    return pca_planes(positions, idx)[0]


def pca_planes(positions: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares plane of each neighbourhood: (normals (N, 3), centroids (N, 3)).

    The plane passes through the centroid of the points idx[i] and is normal to
    :func:`pca_normals`' vector (sign arbitrary).
    """
    n = len(positions)
    normals = np.empty((n, 3), np.float64)
    centroids = np.empty((n, 3), np.float64)
    _pca_kernel(np.ascontiguousarray(positions, np.float64),
                np.ascontiguousarray(as_index_array(idx)), normals, centroids)
    return normals, centroids


def project_to_planes(positions: np.ndarray, normals: np.ndarray,
                      centroids: np.ndarray) -> np.ndarray:
    """Each point moved along its normal onto its neighbourhood's plane (smoothing).

    p' = p - ((p - c) . n) n, with (n, c) from :func:`pca_planes`: scanner noise and
    coordinate quantisation move points off the surface, mostly along its normal, and a
    rendered surfel off the surface is seen at the wrong depth and the wrong place
    (terraces, merge mistakes, uneven coverage). Tangential positions are kept, so the
    sampling density does not change. The few points that would land exactly on another
    one keep their measured position. Returns a new (N, 3) float64 array.
    """
    offset = np.sum((positions - centroids) * normals, axis=1)
    out = positions - offset[:, None] * normals
    for _ in range(4):  # a restored point could in principle meet another one
        first, duplicates = first_rows(out)
        if not duplicates:
            break
        again = first != np.arange(len(out))
        out[again] = positions[again]
    return out


def neighbour_distances(positions: np.ndarray, idx: np.ndarray):
    """(dist, idx) as ``nearest_neighbours`` returns them, for given neighbour lists.

    The distances from each point to its listed neighbours, each row sorted by distance
    (the point itself, at 0, stays first): after points move a little
    (:func:`project_to_planes`) their neighbour lists stay valid but not their distances.
    Computed ROW_CHUNK rows at a time: the (N, m, 3) differences of all points at once
    were the peak of a preparation's memory (issue 50).
    """
    dist = np.empty(idx.shape, np.float64)
    sorted_idx = np.empty_like(idx)
    for rows in _row_blocks(len(idx)):
        dist[rows], sorted_idx[rows] = _sorted_distances(positions, idx, rows)
    return dist, sorted_idx


def remeasured_density(positions: np.ndarray, idx: np.ndarray, outliers: bool = True):
    """:func:`neighbour_distances` and then :func:`area_radii` of its distances, a block
    of rows at a time: (idx (N, m) sorted, r_area (N,), limit (N,)), the same values
    without the (N, m) float64 distances ever whole (8 bytes a neighbour and a point:
    issue 50). For the smoothed points, whose distances nothing else needs.
    """
    n = len(idx)
    sorted_idx = np.empty_like(idx)
    r_area = np.empty(n, np.float64)
    spacing = np.empty(n, np.float64)
    for rows in _row_blocks(n):
        dist, sorted_idx[rows] = _sorted_distances(positions, idx, rows)
        r_area[rows] = _area_radius(dist)
        spacing[rows] = dist[:, _spacing_column(dist.shape[1])]
    return sorted_idx, r_area, _radius_limit(r_area, spacing, outliers)


def pca_normals_slow(positions: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """numpy twin of :func:`pca_normals` (batched ``eigh``)."""
    nb = positions[idx]  # (N, m, 3)
    c = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", c, c)
    _, vecs = np.linalg.eigh(cov)
    return vecs[:, :, 0]


def orient_towards(positions: np.ndarray, normals: np.ndarray, viewpoint) -> np.ndarray:
    """Flip each normal so that it faces ``viewpoint`` (3,) or its row of (N, 3):
    n . (viewpoint - p) >= 0."""
    facing = np.sum(normals * (np.asarray(viewpoint, np.float64) - positions), axis=1)
    return np.where((facing < 0)[:, None], -normals, normals)


def orient_normals(positions: np.ndarray, normals: np.ndarray, idx: np.ndarray,
                   fixed: np.ndarray | None = None) -> np.ndarray:
    """Consistent orientation by propagation over a minimum spanning tree (Hoppe 1992).

    positions, normals: (N, 3) float64; idx: (N, m) neighbour indices (without the point
    itself); fixed: (N,) bool, normals whose sign is known (kept as they are). The graph is
    the symmetric kNN graph with edge cost 1 - |n_i . n_j| (small between nearly parallel
    normals), so the sign travels along the smoothest paths. Each connected component
    without a fixed normal gets its sign afterwards from :func:`outward_votes` (outward
    for a closed surface).
    """
    out, label, n_comp, has_fixed = propagate_orientation(positions, normals, idx, fixed)
    flip = (outward_votes(positions, out, label, n_comp) < 0) & ~has_fixed
    out[flip[label]] *= -1.0
    return out


def propagate_orientation(positions: np.ndarray, normals: np.ndarray, idx: np.ndarray,
                          fixed: np.ndarray | None = None):
    """:func:`orient_normals` before its votes: (normals signed consistently within each
    component of the graph, label (N,), n_comp, has_fixed (n_comp,): whether a component
    holds a fixed normal, whose sign it then keeps)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import (
        breadth_first_order,
        connected_components,
        minimum_spanning_tree,
    )

    n, m = idx.shape
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    rows = np.repeat(np.arange(n, dtype=idx.dtype), m)
    cols = idx.ravel()
    keep = cols != rows
    rows, cols = rows[keep], cols[keep]
    # cost > 0 everywhere: csgraph drops explicit zeros. In chunks of edges: the (edges, 3)
    # products of all of them at once were the orientation's peak of memory (issue 50)
    cost = np.empty(len(rows), np.float64)
    step = ROW_CHUNK * m
    for start in range(0, len(rows), step):
        r, c = rows[start:start + step], cols[start:start + step]
        cost[start:start + step] = 1.0 + 1e-6 - np.abs(np.sum(normals[r] * normals[c], axis=1))
    graph = coo_matrix((cost, (rows, cols)), shape=(n, n)).tocsr()
    del rows, cols, cost, keep
    graph = graph.maximum(graph.T)

    # roots: a virtual node n joined to every fixed point and to one point of each
    # component that has none
    n_comp, label = connected_components(graph, directed=False)
    roots = list(np.nonzero(fixed)[0])
    has_fixed = np.zeros(n_comp, bool)
    has_fixed[label[fixed]] = True
    first = np.unique(label, return_index=True)[1]  # any point of each component
    roots.extend(r for r in first if not has_fixed[label[r]])
    roots = np.asarray(roots, np.int64)
    # (overwrite: the graph is not needed after, and a copy of it was the orientation's
    # peak of memory)
    tree = minimum_spanning_tree(graph, overwrite=True).tocoo()
    del graph
    virt_rows = np.full(len(roots), n)
    t_rows = np.concatenate([tree.row, virt_rows])
    t_cols = np.concatenate([tree.col, roots])
    t_cost = np.concatenate([tree.data, np.full(len(roots), 1e-9)])
    full = coo_matrix((t_cost, (t_rows, t_cols)), shape=(n + 1, n + 1)).tocsr()
    order, parent = breadth_first_order(full, n, directed=False, return_predecessors=True)
    signs = _propagate_signs(order, parent, normals, np.ones(n), n)
    return normals * signs[:, None], label, n_comp, has_fixed


def outward_votes(positions: np.ndarray, normals: np.ndarray, label: np.ndarray,
                  n_comp: int, *, directions: int = VOTE_DIRECTIONS,
                  max_points: int = VOTE_MAX_POINTS, seed: int = 0, tally: bool = False):
    """How outward each component's (consistently oriented) normals are: (n_comp,) votes,
    > 0 outward, < 0 inward.

    Visibility from outside: the cloud is looked at from ``directions`` directions d
    spread over the sphere, each through a grid of cells two point spacings wide; the
    point nearest the viewer in each cell is visible, and a visible surface faces its
    viewer, so it votes n . d for its component. (At most ``max_points`` points, drawn at
    random, take part: the vote needs the shape, not every point.) A closed surface votes
    outward from every side. An open sheet, such as the ground under a scanned statue, is
    seen from both sides and cancels out, while what stands on it is hidden from below by
    it and votes from above and around. Hoppe's single root (the point farthest from the
    centroid, oriented away from it) is a rim point of the ground on the lion scan, and
    turned the whole scan inside out after a small change of k; so did a vote of the
    extreme points along each direction. A component that no view sees falls back to
    that extreme-point vote, and one whose vote is a near tie (under ``TIE_FRACTION`` of
    the votes' total weight: a single open sheet, seen alike from both sides) faces up
    (+y, the world's up), else +z, else +x.
    """

    n = len(positions)
    rng = np.random.default_rng(seed)
    pick = np.arange(n) if n <= max_points else np.sort(rng.choice(n, max_points, replace=False))
    pts, nrm, lab = positions[pick], normals[pick], label[pick]
    cell = 0.0
    if len(pts) > 1:
        from scipy.spatial import cKDTree

        cell = 2.0 * float(np.median(cKDTree(pts).query(pts, 2)[0][:, 1]))
    cell = cell if cell > 0 else 1.0
    dirs = fibonacci_directions(directions)
    votes = np.zeros(n_comp)
    mass = np.zeros(n_comp)  # sum of |n . d| over the votes: what a clear decision has
    extreme = np.zeros(n_comp)
    for d in dirs:
        a = np.cross(d, (0.0, 1.0, 0.0) if abs(d[1]) < 0.9 else (1.0, 0.0, 0.0))
        a /= np.linalg.norm(a)
        b = np.cross(d, a)
        iu, iv = _grid_cells(pts @ a, cell), _grid_cells(pts @ b, cell)
        key = iu * (int(iv.max()) + 1) + iv
        depth = pts @ d
        order = np.lexsort((-depth, key))  # by cell, nearest the viewer first
        seen = order[np.r_[0, np.nonzero(np.diff(key[order]))[0] + 1]]
        facing = nrm[seen] @ d
        votes += np.bincount(lab[seen], facing, n_comp)
        mass += np.bincount(lab[seen], np.abs(facing), n_comp)
    raw = votes.copy() if tally else None
    # a sheet that looks the same from both sides (a scanned wall, a flat patch) gets no
    # clear vote: by convention it faces up (+y, the world's up), else +z, else +x
    unclear = (np.abs(votes) < TIE_FRACTION * mass) & (mass > 0)
    mean = None
    if unclear.any() or tally:
        mean = np.stack([np.bincount(label, normals[:, a], n_comp) for a in (1, 2, 0)], axis=1)
    if unclear.any():
        votes[unclear] = sheet_votes(mean)[unclear]
    unseen = votes == 0
    if unseen.any():  # components missing from the sample, or hidden everywhere
        order = np.argsort(label, kind="stable")
        p_all, n_all, l_all = positions[order], normals[order], label[order]
        del order
        starts = np.r_[0, np.nonzero(np.diff(l_all))[0] + 1]
        for chunk in range(0, directions, 8):  # (N, 8) at a time: bounded memory
            extreme += _extreme_support(p_all, n_all, l_all, starts, dirs[chunk:chunk + 8],
                                        n_comp)
        votes[unseen] = extreme[unseen]
    if tally:
        return votes, raw, mass, mean
    return votes


def area_radii(dist: np.ndarray, outliers: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The radius of the area each surfel stands for, and the cap on its radii, from the
    neighbour distances alone (the first half of :func:`surfel_radii`).

    dist: (N, k+1) from ``nearest_neighbours``. Returns (r_area (N,), limit (N,)) float64:
    r_area = sqrt(1 / rho), rho the smooth kernel density (module docstring, step 4), and
    limit = the smaller of ``CLUSTER_RADIUS_FACTOR`` x the distance to the 4th neighbour
    and ``OUTLIER_RADIUS_FACTOR`` x the median r_area.
    """
    r_area = np.empty(len(dist), np.float64)
    for rows in _row_blocks(len(dist)):  # (rows, k+1) temporaries, not (N, k+1)
        r_area[rows] = _area_radius(dist[rows])
    return r_area, _radius_limit(r_area, dist[:, _spacing_column(dist.shape[1])], outliers)


def surfel_radii(positions: np.ndarray, normals: np.ndarray, idx: np.ndarray,
                 r_area: np.ndarray, limit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Disk radii that cover the surface, and the area each surfel stands for.

    positions, normals: (N, 3) float64; idx: (N, k+1) from ``nearest_neighbours`` (or
    ``neighbour_distances``); r_area, limit: (N,) from :func:`area_radii`.
    Returns (radius (N,), area_weight (N,)), area_weight = area / radius^2 <= 1 being the
    ``Surfels.weight`` that makes each surfel stand for its area (module docstring):

    * area = 1 / rho from the smooth kernel density; r_area = sqrt(area);
    * coverage: r_cover = sqrt(2) x the distance to the farthest corner of the point's
      Voronoi cell among its neighbours, in its tangent plane; on a square grid of spacing
      h the corners are at h / sqrt(2), so r_cover = h = r_area, and a surface sampled
      irregularly gets the wider disks its gaps need (NaN at the edge of a scan: r_area);
    * radius = max(r_area, r_cover), both capped at ``limit``.
    """
    corner = np.empty(len(positions), np.float64)
    m = min(idx.shape[1], VORONOI_NEIGHBOURS + 1)
    _cell_reach_kernel(np.ascontiguousarray(positions, np.float64),
                       np.ascontiguousarray(normals, np.float64),
                       as_index_array(idx)[:, :m], corner)  # (a view: no copy)
    r_cover = math.sqrt(2.0) * corner
    r_area = np.minimum(r_area, limit)
    radius = np.minimum(np.fmax(r_area, r_cover), limit)  # fmax: NaN -> r_area
    return radius, (r_area / radius) ** 2


# -- numba kernels and helpers -----------------------------------------------------------


def _row_blocks(n: int):
    """Slices of ROW_CHUNK rows that cover 0 .. n."""
    for start in range(0, n, ROW_CHUNK):
        yield slice(start, min(n, start + ROW_CHUNK))


def _sorted_distances(positions: np.ndarray, idx: np.ndarray, rows: slice):
    """The rows' distances to their listed neighbours and the lists, each row sorted by
    distance (stable: ties keep the lists' order): ((rows, m) float64, (rows, m))."""
    dist = np.linalg.norm(positions[idx[rows]] - positions[rows, None, :], axis=2)
    order = np.argsort(dist, axis=1, kind="stable")
    return np.take_along_axis(dist, order, axis=1), np.take_along_axis(idx[rows], order, axis=1)


def _spacing_column(m: int) -> int:
    """The column of the 4th neighbour's distance (the cluster cap's spacing) of m."""
    return min(4, m - 1)


def _radius_limit(r_area: np.ndarray, spacing: np.ndarray, outliers: bool = True) -> np.ndarray:
    """The cap on the radii (:func:`area_radii`). Outliers: a small cluster far from
    everything has its k-th neighbour, hence the kernel, far away; keep its disks within
    a few of its own spacings, and lone fliers within a few typical radii (``outlier_cap``;
    outliers=False leaves that cap to the caller, whose median is the whole cloud's)."""
    if not outliers:
        return CLUSTER_RADIUS_FACTOR * spacing
    return np.minimum(CLUSTER_RADIUS_FACTOR * spacing, outlier_cap(r_area))


def _area_radius(dist: np.ndarray) -> np.ndarray:
    """sqrt(1 / rho), rho the smooth kernel density over each row of neighbour distances
    (module docstring, step 4): dist (rows, k+1) from ``nearest_neighbours``."""
    reach = dist[:, -1:]  # > 0: duplicates are merged before the query
    s2 = (reach / DENSITY_BANDWIDTH) ** 2
    phi = np.exp(-dist * dist / (2 * s2)) - np.exp(-reach * reach / (2 * s2))
    q = 0.5 * DENSITY_BANDWIDTH ** 2
    integral = 2 * math.pi * s2[:, 0] * (1 - math.exp(-q) * (1 + q))
    rho = np.clip(phi, 0, None).sum(axis=1) / integral
    return 1.0 / np.sqrt(rho)


@numba.njit(cache=True, nogil=True, parallel=True)
def _pca_kernel(positions, idx, out, centroids):
    n, m = idx.shape
    for p in numba.prange(n):
        mx = my = mz = 0.0
        for a in range(m):
            j = idx[p, a]
            mx += positions[j, 0]
            my += positions[j, 1]
            mz += positions[j, 2]
        mx /= m
        my /= m
        mz /= m
        cxx = cxy = cxz = cyy = cyz = czz = 0.0
        for a in range(m):
            j = idx[p, a]
            dx = positions[j, 0] - mx
            dy = positions[j, 1] - my
            dz = positions[j, 2] - mz
            cxx += dx * dx
            cxy += dx * dy
            cxz += dx * dz
            cyy += dy * dy
            cyz += dy * dz
            czz += dz * dz
        nx, ny, nz = _smallest_eigenvector(cxx, cxy, cxz, cyy, cyz, czz)
        out[p, 0] = nx
        out[p, 1] = ny
        out[p, 2] = nz
        centroids[p, 0] = mx
        centroids[p, 1] = my
        centroids[p, 2] = mz


@numba.njit(cache=True, nogil=True)
def _smallest_eigenvector(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (cyclic Jacobi)."""
    a = np.empty((3, 3))
    a[0, 0], a[0, 1], a[0, 2] = a00, a01, a02
    a[1, 0], a[1, 1], a[1, 2] = a01, a11, a12
    a[2, 0], a[2, 1], a[2, 2] = a02, a12, a22
    v = np.eye(3)
    scale = abs(a00) + abs(a11) + abs(a22) + 1e-300
    for _sweep in range(16):
        off = abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2])
        if off <= 1e-15 * scale:
            break
        for p in range(2):
            for q in range(p + 1, 3):
                apq = a[p, q]
                if abs(apq) <= 1e-300:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for r in range(3):  # A <- A J (columns p, q)
                    arp, arq = a[r, p], a[r, q]
                    a[r, p] = c * arp - s * arq
                    a[r, q] = s * arp + c * arq
                for r in range(3):  # A <- J^T A (rows p, q)
                    apr, aqr = a[p, r], a[q, r]
                    a[p, r] = c * apr - s * aqr
                    a[q, r] = s * apr + c * aqr
                for r in range(3):
                    vrp, vrq = v[r, p], v[r, q]
                    v[r, p] = c * vrp - s * vrq
                    v[r, q] = s * vrp + c * vrq
    best = 0
    if a[1, 1] < a[best, best]:
        best = 1
    if a[2, 2] < a[best, best]:
        best = 2
    x, y, z = v[0, best], v[1, best], v[2, best]
    norm = math.sqrt(x * x + y * y + z * z)
    return x / norm, y / norm, z / norm


@numba.njit(cache=True, nogil=True, parallel=True)
def _cell_reach_kernel(positions, normals, idx, out):
    """Distance from each point to the farthest corner of its Voronoi cell in its tangent plane.

    The cell is cut by the bisectors of the neighbours idx[p, 1:] projected into the plane;
    its corners are the pairwise bisector intersections that satisfy every bisector. An
    open cell (the neighbours all on one side: the edge of a scan) gives NaN.
    """
    n, m = idx.shape
    for p in numba.prange(n):
        nx, ny, nz = normals[p, 0], normals[p, 1], normals[p, 2]
        # tangent frame: cross the normal with the axis it is least aligned with
        ax, ay, az = abs(nx), abs(ny), abs(nz)
        if ax <= ay and ax <= az:
            ux, uy, uz = 0.0, nz, -ny
        elif ay <= az:
            ux, uy, uz = -nz, 0.0, nx
        else:
            ux, uy, uz = ny, -nx, 0.0
        ul = math.sqrt(ux * ux + uy * uy + uz * uz)
        ux, uy, uz = ux / ul, uy / ul, uz / ul
        vx, vy, vz = ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux
        qx = np.empty(m - 1)
        qy = np.empty(m - 1)
        ang = np.empty(m - 1)
        for a in range(1, m):
            j = idx[p, a]
            dx = positions[j, 0] - positions[p, 0]
            dy = positions[j, 1] - positions[p, 1]
            dz = positions[j, 2] - positions[p, 2]
            qx[a - 1] = ux * dx + uy * dy + uz * dz
            qy[a - 1] = vx * dx + vy * dy + vz * dz
            ang[a - 1] = math.atan2(qy[a - 1], qx[a - 1])
        ang.sort()
        gap = ang[0] + 2.0 * math.pi - ang[m - 2]
        for a in range(1, m - 1):
            gap = max(gap, ang[a] - ang[a - 1])
        if gap >= math.pi:
            out[p] = np.nan
            continue
        reach = 0.0
        for a in range(m - 1):
            ca = 0.5 * (qx[a] * qx[a] + qy[a] * qy[a])
            for b in range(a + 1, m - 1):
                det = qx[a] * qy[b] - qy[a] * qx[b]
                if abs(det) <= 1e-12 * (ca + 1e-300):
                    continue
                cb = 0.5 * (qx[b] * qx[b] + qy[b] * qy[b])
                x = (ca * qy[b] - cb * qy[a]) / det
                y = (qx[a] * cb - qx[b] * ca) / det
                r2 = x * x + y * y
                if r2 <= reach * reach:
                    continue
                inside = True
                for c in range(m - 1):
                    cc = 0.5 * (qx[c] * qx[c] + qy[c] * qy[c])
                    if x * qx[c] + y * qy[c] > cc * (1.0 + 1e-9) + 1e-300:
                        inside = False
                        break
                if inside:
                    reach = math.sqrt(r2)
        out[p] = reach


def _extreme_support(positions, normals, label, starts, dirs, n_comp: int) -> np.ndarray:
    """Per component, the sum over the directions d in dirs (m, 3) of n . d at its points
    farthest along d: (n_comp,). The points are sorted by component (label), whose runs
    begin at starts. Its (N, m) arrays live one or two at a time and go on return: four at
    once were the peak of a large cloud's orientation (issue 50)."""
    reach = positions @ dirs.T
    top = np.maximum.reduceat(reach, starts, axis=0)
    on_top = reach >= top[label]
    del reach
    support = normals @ dirs.T
    support[~on_top] = 0.0
    return np.bincount(label, support.sum(axis=1), n_comp)


def _grid_cells(x: np.ndarray, cell: float, most: int = 1 << 20) -> np.ndarray:
    """Cell index of each coordinate, 0 .. ``most``: cells of ``cell``, widened when the
    extent would need more (wild coordinates must not overflow the int64 keys)."""
    with np.errstate(all="ignore"):
        x = x - np.min(x)
        top = float(np.max(x))
        width = max(cell, top / most) if np.isfinite(top) else np.inf
        i = np.floor(x / width) if width > 0 and np.isfinite(width) else np.zeros_like(x)
    return np.clip(np.nan_to_num(i, nan=0.0, posinf=most, neginf=0.0), 0, most).astype(np.int64)


@numba.njit(cache=True, nogil=True)
def _propagate_signs(order, parent, normals, signs0, root):
    """Signs along a BFS order of a tree: each node agrees with its (already signed) parent."""
    signs = signs0.copy()
    for a in range(order.shape[0]):
        i = order[a]
        if i == root:
            continue
        p = parent[i]
        if p == root or p < 0:
            continue  # a root: its sign is signs0's
        dot = (normals[i, 0] * normals[p, 0] + normals[i, 1] * normals[p, 1]
               + normals[i, 2] * normals[p, 2])
        signs[i] = signs[p] if dot >= 0 else -signs[p]
    return signs


def _check_inputs(positions, colors, normals, source):
    pts = np.asarray(positions, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise DofsplatError(f"{source}: positions must have shape (N, 3), got {pts.shape}")
    if pts.shape[0] == 0:
        raise DofsplatError(f"{source}: the point cloud is empty")
    n = len(pts)
    cols = nrm = None
    if colors is not None:
        cols = np.asarray(colors, dtype=np.float32)
        if cols.shape != (n, 3):
            raise DofsplatError(f"{source}: colors must have shape ({n}, 3), got {cols.shape}")
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != (n, 3):
            raise DofsplatError(f"{source}: normals must have shape ({n}, 3), got {nrm.shape}")
    keep = np.all(np.isfinite(pts), axis=1)
    if cols is not None:
        keep &= np.all(np.isfinite(cols), axis=1)
    dropped = n - int(keep.sum())
    if dropped:
        if not keep.any():
            raise DofsplatError(f"{source}: no valid points (all {n} had NaN or inf values)")
        warnings.warn(f"{source}: dropped {dropped} of {n} points with NaN or inf values",
                      stacklevel=3)
        pts = pts[keep]
        cols = None if cols is None else cols[keep]
        nrm = None if nrm is None else nrm[keep]
    if cols is not None:
        cols = np.clip(cols, 0.0, 1.0)
    return pts, cols, nrm


def _check_k(k, n: int) -> int:
    if k is None:
        k = DEFAULT_K
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not MIN_K <= k <= MAX_K:
        raise DofsplatError(f"k (neighbours) must be an integer from {MIN_K} to {MAX_K}, "
                            f"got {k!r}")
    return int(min(k, n - 1))


def _stage_bar(total: int, desc: str, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", file=sys.stderr,
                disable=not (enabled and sys.stderr.isatty()), leave=False)
