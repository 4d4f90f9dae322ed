"""Per-point normalisation (paper Section 6.3; issue 4, item 4) and its uniformity metric.

The renderer uses a surface's accumulated splat weight as its coverage (Section 6.4), so
the splats must sum to 1 over the surface; on irregular sampling they do not, and
per-pixel post-normalisation is not allowed (it would erase partial coverage). Instead each
surfel gets a ``weight`` once, in preprocessing, that scales the area it stands for
(``Surfels.weight``: a splat deposits the area r_u * r_v * weight). Two ways to compute it:

* ``method="object"``, the "specialised tool" the paper wishes for: evaluate the
  neighbours' basis functions in each surfel's tangent plane, found with a k-d tree, and
  divide the surfel's weight by their sum (:func:`object_weights`). No rendering, no
  resolution, every surfel reached, a few seconds for 400k surfels;
* ``method="render"``, the paper's: render the model from several directions with a large
  cutoff (c = 4, so that truncation does not matter), read each surfel's accumulated
  weight at its own pixel and divide its weight by it (:func:`render_weights`).

Both iterate w <- w / S(w), S the sum at each surfel; a fixed point is a partition of unity
at the surfel centres (the paper does one step). Then, unless ``calibrate=False``, the
weights are scaled by one factor so that the renderer reads them as 1 on average
(:func:`rendered_level`): the object sums are taken in each disk's own plane and miss how
the disks lie against each other on a real scan (the lion reads 0.974 uncalibrated), and a
blurred surface's coverage is min(1, w). :func:`uniformity` measures the result
the paper's way: the fraction of interior surface pixels of a render whose accumulated
weight (``RenderResult.weight``) lies in 1 +- 0.1. docs/maths.md says more;
bench/uniformity.py measures both methods on the dragon, the lion and the plane.
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace

from ..jit import numba
import numpy as np

from ..errors import DofsplatError
from ..surfels import Surfels
from .neighbours import fibonacci_directions, nearest_neighbours

METHODS = ("none", "object", "render")
NORMALISATION_CUTOFF = 4.0  # c for the normalisation kernels: the paper's 3.5 - 4
OBJECT_NEIGHBOURS = 32  # candidates per surfel for the object-space sums
OBJECT_ITERATIONS = 10  # w <- w / S(w) steps: the dragon at 512^2 reads 0.75 after 1, 0.95 after 3, 0.97 after 10
OBJECT_SMOOTH = 0.5  # footprint averaging of the object-space sums (object_weights)
RENDER_VIEWS = 14  # directions on a Fibonacci sphere
RENDER_ITERATIONS = 2
RENDER_MAX_SIZE = 2048  # pixels per side of a normalisation render
RENDER_PX_PER_RADIUS = 2.0  # pixels per median surfel radius in a normalisation render
FACING_MIN_COS = 0.5  # a view reads a surfel only if it faces the camera within 60 degrees
LEVEL_VIEWS = 6  # directions from which rendered_level reads the weights' level
LEVEL_MAX_READING = 2.0  # rendered_level reads a pixel's weight as at most this
LEVEL_MIN_PIXELS = 400  # interior pixels below which the level is not read (taken as 1)
TOLERANCE = 0.1  # the paper's 1 +- 0.1


def normalise(surfels: Surfels, method: str = "object", *, calibrate: bool = True,
              progress: bool = True, **options) -> Surfels:
    """The model with per-surfel normalisation weights, by ``method`` ("none", "object",
    "render"); options go to :func:`object_weights` or :func:`render_weights`.

    calibrate: scale the weights by 1 / :func:`rendered_level` of the normalised model, so
               that its rendered interior weight is 1 on average (module docstring)

    "none" returns the model as it is.
    """
    check_method(method)
    if method == "none":
        if options:
            raise DofsplatError(f"normalisation 'none' takes no options, got {sorted(options)}")
        return surfels
    if method == "object":
        weight = object_weights(surfels, progress=progress, **options)
    else:
        weight = render_weights(surfels, progress=progress, **options)
    normalised = replace(surfels, weight=weight)
    if calibrate:
        level = rendered_level(normalised, progress=progress and len(surfels) > 65536)
        normalised = replace(surfels, weight=(weight / level).astype(np.float32))
    return normalised


def check_method(method) -> str:
    """``method`` if it names a normalisation, else DofsplatError (loaders check it before
    reading a file)."""
    if not isinstance(method, str) or method not in METHODS:
        raise DofsplatError(f"unknown normalisation {method!r}; choose one of "
                            f"{', '.join(METHODS)}")
    return method


# -- object space ------------------------------------------------------------------------


def object_weights(surfels: Surfels, *, iterations: int = OBJECT_ITERATIONS,
                   neighbours: int = OBJECT_NEIGHBOURS, smooth: float = OBJECT_SMOOTH,
                   progress: bool = True) -> np.ndarray:
    """Object-space normalisation weights, (N,) float32.

    For each surfel k, S_k = sum_j a_j w_j G_j(p_k): the basis function of each neighbour
    j (a Gaussian with standard deviations r_u/2, r_v/2 in j's tangent plane, not
    truncated: the paper's "large cutoff"; the renderer normalises each truncated kernel
    to its full area), scaled by the area j stands for (a_j = r_u r_v times its weight
    w_j), evaluated at p_k projected into j's plane. Neighbours that face
    away (n_j . n_k <= 0) or lie off j's plane by more than j's radius belong to another
    sheet and do not count, as the renderer's culling and z-ranges keep them apart. Then
    w_k <- w_k / S_k, ``iterations`` times, starting from the model's weights (or 1).

    neighbours: candidates per surfel (its nearest surfels, itself included)
    smooth:     0 evaluates the sum at p_k; s > 0 averages it over a Gaussian around p_k of
                variance s x (the area k stands for) / 4 (s = 1: k's own basis function,
                the normal equations of a least-squares fit of the sum to 1). Point values
                overshoot between irregular samples, and even on a square grid of r = h
                they read 1.029 (the lattice sum of Gaussians of sigma h/2); s = 0.5 reads
                1.002 there, and on the dragon it is within 0.3 % of s = 1 and 1 % above
                s = 0 (on the lion 3 % below s = 0; bench/RESULTS.md).
    """
    n = len(surfels)
    iterations = _positive_int(iterations, "iterations")
    with _progress(iterations + 1, "normalise (object)", progress and n > 65536,
                   unit="step") as bar:
        idx, args, smooth_var = _object_setup(surfels, neighbours, smooth)
        bar.update()
        weight = _initial_weight(surfels)
        sums = np.empty(n, np.float64)
        for _ in range(iterations):
            _object_sums_kernel(*args, weight, idx, smooth_var, sums)
            weight = weight / np.maximum(sums, 1e-12)
            bar.update()
    return weight.astype(np.float32)


def object_sums(surfels: Surfels, weight=None, *, neighbours: int = OBJECT_NEIGHBOURS,
                smooth: float = OBJECT_SMOOTH) -> np.ndarray:
    """S_k = sum_j a_j w_j G_j(p_k) at every surfel, (N,) float64 (see object_weights).

    weight: (N,) the w_j to use (default: the model's weights, or 1).
    """
    idx, args, smooth_var = _object_setup(surfels, neighbours, smooth)
    w = _initial_weight(surfels) if weight is None else np.asarray(weight, np.float64)
    out = np.empty(len(surfels), np.float64)
    _object_sums_kernel(*args, w, idx, smooth_var, out)
    return out


def object_sums_slow(surfels: Surfels, weight=None, *, neighbours: int = OBJECT_NEIGHBOURS,
                     smooth: float = OBJECT_SMOOTH) -> np.ndarray:
    """numpy twin of :func:`object_sums`, written from the formula in explicit frames."""
    from ..surfels import tangent_frame

    idx, _, _ = _object_setup(surfels, neighbours, smooth)
    w = _initial_weight(surfels) if weight is None else np.asarray(weight, np.float64)
    p = surfels.positions.astype(np.float64)
    nrm = surfels.normals.astype(np.float64)
    ru = surfels.radius.astype(np.float64)
    if surfels.is_elliptical:
        tu, rv = surfels.tangent.astype(np.float64), surfels.radius_v.astype(np.float64)
    else:
        tu, rv = tangent_frame(nrm)[0].astype(np.float64), ru
    tv = np.cross(nrm, tu)
    smooth_var = smooth * 0.25 * ru * rv * _initial_weight(surfels)  # receiver k's
    j = idx
    d = p[:, None, :] - p[j]  # (N, m, 3): p_k - p_j
    u = np.sum(d * tu[j], axis=2)  # p_k in j's tangent frame
    v = np.sum(d * tv[j], axis=2)
    h = np.sum(d * nrm[j], axis=2)
    var_u = (ru[j] / 2) ** 2 + smooth_var[:, None]
    var_v = (rv[j] / 2) ** 2 + smooth_var[:, None]
    e = 0.5 * (u * u / var_u + v * v / var_v)
    same_sheet = (np.sum(nrm[:, None, :] * nrm[j], axis=2) > 0) & (np.abs(h) <= np.maximum(ru[j], rv[j]))
    g = np.exp(-e) / (2 * np.pi * np.sqrt(var_u * var_v))
    area = ru[j] * rv[j] * w[j]
    return np.sum(np.where(same_sheet, area * g, 0.0), axis=1)


# -- in screen space, the paper's way ---------------------------------------------------


def render_weights(surfels: Surfels, *, views: int = RENDER_VIEWS,
                   iterations: int = RENDER_ITERATIONS, cutoff: float = NORMALISATION_CUTOFF,
                   max_size: int = RENDER_MAX_SIZE, px_per_radius: float = RENDER_PX_PER_RADIUS,
                   progress: bool = True) -> np.ndarray:
    """Normalisation weights captured from renders (Section 6.3), (N,) float32.

    The model is rendered (pinhole, unlit, cutoff c = 4, no LOD) from ``views`` directions
    spread over a sphere by a camera far away (a narrow field of view: nearly parallel
    projection), at a resolution that gives the median surfel radius ``px_per_radius``
    pixels (at most ``max_size`` pixels a side). A view reads a surfel's accumulated weight
    at the surfel's projected centre (bilinear between pixel centres) if the surfel faces
    the camera within 60 degrees, is the surface seen there (its depth agrees with the
    pixel's) and the four pixels are interior surface pixels (:func:`interior_mask`). The
    readings are averaged with weights cos^2 of the viewing angle, and the surfel's weight
    is divided by the average; ``iterations`` rounds. Surfels no view reads keep their
    weight.
    """
    from ..render import render

    views = _positive_int(views, "views")
    iterations = _positive_int(iterations, "iterations")
    cameras = normalisation_cameras(surfels, views, max_size, px_per_radius)
    settings = _capture_settings(cutoff)
    weight = _initial_weight(surfels)
    positions = surfels.positions.astype(np.float64)
    normals = surfels.normals.astype(np.float64)
    z_tolerance = 2.0 * np.maximum(surfels.radius, surfels.radius_v if surfels.is_elliptical
                                   else surfels.radius).astype(np.float64)
    with _progress(views * iterations, "normalise (render)", progress) as bar:
        for _ in range(iterations):
            model = replace(surfels, weight=weight.astype(np.float32))
            total = np.zeros(len(surfels))
            count = np.zeros(len(surfels))
            for camera in cameras:
                result = render(model, camera, None, settings)
                reading, confidence = read_back(result, camera, positions, normals,
                                                z_tolerance)
                total += confidence * reading
                count += confidence
                bar.update(1)
            seen = count > 0
            weight[seen] = weight[seen] / np.maximum(total[seen] / count[seen], 1e-6)
    return weight.astype(np.float32)


def rendered_level(surfels: Surfels, *, views: int = LEVEL_VIEWS,
                   max_size: int = RENDER_MAX_SIZE,
                   px_per_radius: float = RENDER_PX_PER_RADIUS,
                   progress: bool = False) -> float:
    """The model's accumulated weight over the interior of its surfaces, on average, as the
    renderer reads it: a float, 1 for a partition of unity.

    The model is rendered (pinhole, unlit, no LOD, the default cutoff) by the capture
    cameras of :func:`render_weights` from ``views`` directions; the weights of the
    interior pixels (:func:`interior_mask`, :func:`edge_margin` inside every edge) of all
    views are pooled and averaged. The mean, not a median: a blurred surface's coverage is
    min(1, w) of its weights blurred, their local mean; but each pixel read as at most
    ``LEVEL_MAX_READING`` (a few surfels with runaway weights, as the "render" method
    leaves on the lion, would otherwise set the level). Where the views find fewer than
    ``LEVEL_MIN_PIXELS`` interior pixels (a handful of surfels) the level cannot be read and
    is 1. On a flat random sampling it reads 1.00, on the lion scan 0.974 and on the
    sampled dragon mesh 0.990 (docs/maths.md; ``python bench/density.py --level``).
    """
    from ..render import RenderSettings, render

    views = _positive_int(views, "views")
    settings = RenderSettings(lod=False, shading="none", dof=False)
    total, count = 0.0, 0
    with _progress(views, "normalise (level)", progress) as bar:
        for camera in normalisation_cameras(surfels, views, max_size, px_per_radius):
            result = render(surfels, camera, None, settings)
            mask = interior_mask(result, camera,
                                 erode=edge_margin(surfels, camera, settings.cutoff))
            reading = np.minimum(result.weight[mask], LEVEL_MAX_READING)
            total += float(reading.sum(dtype=np.float64))
            count += int(mask.sum())
            bar.update(1)
    if count < LEVEL_MIN_PIXELS or not total > 0:
        return 1.0
    return total / count


def normalisation_cameras(surfels: Surfels, views: int, max_size: int = RENDER_MAX_SIZE,
                          px_per_radius: float = RENDER_PX_PER_RADIUS):
    """The capture cameras: ``views`` directions on a Fibonacci sphere, narrow field of view."""
    from ..camera import Camera

    lo, hi = surfels.bounds()
    extent = 1.05 * float(np.linalg.norm(hi.astype(np.float64) - lo)) + 1e-12  # ~ view width
    pixel = float(np.median(surfels.radius)) / px_per_radius
    size = int(min(max_size, max(64, math.ceil(extent / pixel))))
    cameras = []
    for d in fibonacci_directions(views):
        up = (0.0, 1.0, 0.0) if abs(d[1]) < 0.9 else (0.0, 0.0, 1.0)
        cameras.append(Camera.framing(lo, hi, size, size, fov_y=5.0, direction=tuple(d),
                                      up=up))
    return cameras


def read_back(result, camera, positions: np.ndarray, normals: np.ndarray,
              z_tolerance: np.ndarray):
    """Each surfel's accumulated weight at its own pixel in one render, and a confidence.

    Returns (reading (N,), confidence (N,)): confidence is cos^2 of the angle between the
    normal and the direction to the eye where the surfel is read, 0 where it is not.
    """
    h, w = result.weight.shape
    xy, depth = camera.project(positions)
    to_eye = np.asarray(camera.eye) - positions
    cos = np.sum(normals * to_eye, axis=1) / np.maximum(np.linalg.norm(to_eye, axis=1), 1e-300)
    # bilinear between pixel centres (j + 1/2, i + 1/2)
    fx, fy = xy[:, 0] - 0.5, xy[:, 1] - 0.5
    ok = (cos > FACING_MIN_COS) & np.isfinite(fx) & np.isfinite(fy) & (depth > 0)
    ok &= (fx >= 0) & (fx < w - 1) & (fy >= 0) & (fy < h - 1)
    j0 = np.where(ok, np.floor(fx), 0).astype(np.int64)
    i0 = np.where(ok, np.floor(fy), 0).astype(np.int64)
    tx, ty = fx - j0, fy - i0
    interior = interior_mask(result, camera)
    for di in (0, 1):
        for dj in (0, 1):
            ok &= interior[i0 + di, j0 + dj]
            ok &= np.abs(result.depth[i0 + di, j0 + dj] - depth) <= z_tolerance
    wgt = result.weight
    reading = ((1 - ty) * ((1 - tx) * wgt[i0, j0] + tx * wgt[i0, j0 + 1])
               + ty * ((1 - tx) * wgt[i0 + 1, j0] + tx * wgt[i0 + 1, j0 + 1]))
    confidence = np.where(ok, cos * cos, 0.0)
    return np.where(ok, reading, 0.0), confidence


# -- the uniformity metric ---------------------------------------------------------------


def interior_mask(result, camera=None, *, erode: int = 2, depth_jump: float = 0.03,
                  max_angle: float = 80.0) -> np.ndarray:
    """Pixels fully inside a surface, seen not too obliquely: (H, W) bool.

    A pixel is interior if a surface covers it and every pixel within ``erode`` pixels
    (a square window) is covered too, with no depth discontinuity (a relative depth jump
    over ``depth_jump`` to a 4-neighbour: a silhouette in front of another surface) and,
    when ``camera`` is given, a surface seen within ``max_angle`` degrees of face-on (the
    slope of the depth map: tan(angle) = |grad depth| * a_x / depth, a_x the camera's
    pixels per unit at unit depth). Near edges and at grazing angles the nearest surface
    covers a pixel only partly, so its accumulated weight is legitimately below 1.
    """
    from scipy.ndimage import binary_erosion

    depth = result.depth
    covered = np.isfinite(depth)
    d = np.where(covered, depth, 0.0).astype(np.float64)
    good = covered.copy()
    with np.errstate(invalid="ignore", divide="ignore"):
        jump_x = np.abs(d[:, 1:] - d[:, :-1]) > depth_jump * np.minimum(d[:, 1:], d[:, :-1])
        jump_y = np.abs(d[1:, :] - d[:-1, :]) > depth_jump * np.minimum(d[1:, :], d[:-1, :])
    good[:, 1:] &= ~jump_x
    good[:, :-1] &= ~jump_x
    good[1:, :] &= ~jump_y
    good[:-1, :] &= ~jump_y
    if camera is not None and max_angle < 90.0 and min(d.shape) > 1:
        grad_y, grad_x = np.gradient(d)
        with np.errstate(invalid="ignore", divide="ignore"):
            slope = np.hypot(grad_x, grad_y) * camera.pixels_per_unit_at_unit_depth / d
        good &= slope <= math.tan(math.radians(max_angle))
    if erode > 0:
        good = binary_erosion(good, structure=np.ones((3, 3), bool), iterations=int(erode),
                              border_value=0)
    return good


def edge_margin(surfels: Surfels, camera, cutoff: float = 2.5,
                tolerance: float = TOLERANCE) -> int:
    """Pixels from the edge of a render's coverage within which a surface's accumulated
    weight may legitimately be below 1 - tolerance: the ``erode`` for :func:`uniformity`.

    At the edge of a surface (a silhouette, a hole, the rim of a scan) the splats fade out
    over their own width: that is the edge antialiasing of Section 6.4, not a fault of the
    normalisation. A splat of screen radius r px has the resampling kernel
    N(0, (r/2)^2 + 1) per axis (eq. 11 without blur: V^r = (r/2)^2 I and the pixel
    prefilter I), standard deviation s, cut at sqrt(2 c) s. The coverage therefore begins
    sqrt(2 c) s outside the last row of samples. Over a half-plane of kernels the sum at a
    depth x inside the edge is Phi(x / s); the edge lies half a spacing (about r / 2)
    beyond the last row, so the sum reaches 1 - tolerance at Phi^-1(1 - tolerance) s - r / 2
    inside that row. The margin is the sum of the two, rounded up, with r the median
    screen radius of the surfels in front of the camera and in the frame: 4 px for the
    lion and the dragon at 512 x 512 (surfels ~0.8 px) and at ~2 px per radius.
    """
    from statistics import NormalDist

    xy, depth = camera.project(surfels.positions.astype(np.float64))
    inside = (depth > 0) & np.all(np.isfinite(xy), axis=1)
    inside &= (xy[:, 0] >= 0) & (xy[:, 0] <= camera.width)
    inside &= (xy[:, 1] >= 0) & (xy[:, 1] <= camera.height)
    if not inside.any():
        return 0
    radius = surfels.radius[inside].astype(np.float64)
    if surfels.is_elliptical:
        radius = np.sqrt(radius * surfels.radius_v[inside])
    r_px = float(np.median(radius * camera.pixels_per_unit_at_unit_depth / depth[inside]))
    s = math.sqrt((r_px / 2) ** 2 + 1.0)
    z = NormalDist().inv_cdf(1.0 - tolerance)
    return int(math.ceil(math.sqrt(2.0 * cutoff) * s + max(0.0, z * s - r_px / 2)))


def uniformity(result, camera=None, *, tolerance: float = TOLERANCE, erode: int = 2,
               depth_jump: float = 0.03, max_angle: float = 80.0) -> float:
    """Fraction of interior surface pixels whose accumulated weight is in 1 +- tolerance.

    The paper's measure (Sections 6.3, 7: "the splats sum up to 1 +- 0.1"); interior as in
    :func:`interior_mask`. NaN if the render has no interior pixel. ``erode``: pixels
    dropped along every edge; :func:`edge_margin` gives the width over which splats fade
    out at an edge (pass ``erode=edge_margin(surfels, camera, cutoff)``: the measure
    bench/uniformity.py and the tests use), the default 2 a fixed narrower band.
    """
    mask = interior_mask(result, camera, erode=erode, depth_jump=depth_jump,
                         max_angle=max_angle)
    if not mask.any():
        return float("nan")
    w = result.weight[mask]
    return float(np.mean(np.abs(w - 1.0) <= tolerance))


# -- kernels and helpers -----------------------------------------------------------------


@numba.njit(cache=True, nogil=True, parallel=True)
def _object_sums_kernel(positions, normals, tangents, ru, rv, weight, idx, smooth_var, out):
    """out[k] = sum_j a_j w_j G_j(p_k) over the candidates idx[k] (see object_weights).

    G_j has the variances (ru_j/2)^2 + smooth_var[k] and (rv_j/2)^2 + smooth_var[k] along
    j's tangents t_j and n_j x t_j (isotropic for disks, where the frame does not matter):
    its value at p_k is exp(-e) / (2 pi sqrt(var_u var_v)).
    """
    n, m = idx.shape
    elliptical = tangents.shape[0] == n
    scale = 1.0 / (2.0 * math.pi)
    for k in numba.prange(n):
        s = 0.0
        for a in range(m):
            j = idx[k, a]
            nx, ny, nz = normals[j, 0], normals[j, 1], normals[j, 2]
            if nx * normals[k, 0] + ny * normals[k, 1] + nz * normals[k, 2] <= 0:
                continue
            dx = positions[k, 0] - positions[j, 0]
            dy = positions[k, 1] - positions[j, 1]
            dz = positions[k, 2] - positions[j, 2]
            h = nx * dx + ny * dy + nz * dz
            if abs(h) > max(ru[j], rv[j]):
                continue
            su2 = 0.25 * ru[j] * ru[j] + smooth_var[k]
            sv2 = 0.25 * rv[j] * rv[j] + smooth_var[k]
            if elliptical:
                tx, ty, tz = tangents[j, 0], tangents[j, 1], tangents[j, 2]
                u = tx * dx + ty * dy + tz * dz
                bx = ny * tz - nz * ty
                by = nz * tx - nx * tz
                bz = nx * ty - ny * tx
                v = bx * dx + by * dy + bz * dz
                e = 0.5 * (u * u / su2 + v * v / sv2)
            else:
                q = max(dx * dx + dy * dy + dz * dz - h * h, 0.0)
                e = 0.5 * q / su2
            s += weight[j] * ru[j] * rv[j] * math.exp(-e) / math.sqrt(su2 * sv2)
        out[k] = s * scale


def _object_arrays(surfels: Surfels):
    p = surfels.positions.astype(np.float64)
    nrm = surfels.normals.astype(np.float64)
    ru = surfels.radius.astype(np.float64)
    if surfels.is_elliptical:
        return p, nrm, surfels.tangent.astype(np.float64), ru, surfels.radius_v.astype(np.float64)
    return p, nrm, np.zeros((0, 3)), ru, ru


def _object_setup(surfels: Surfels, neighbours: int, smooth: float):
    """Candidate neighbours (N, m), kernel arrays, and the receivers' smoothing variances."""

    neighbours = _positive_int(neighbours, "neighbours")
    if not (math.isfinite(smooth) and smooth >= 0):
        raise DofsplatError(f"smooth must be a number >= 0, got {smooth!r}")
    m = min(neighbours, len(surfels) - 1)
    if m < 1:
        idx = np.zeros((len(surfels), 1), np.int64)
    else:  # (the lists only: their distances would double the memory, issue 50)
        _, idx = nearest_neighbours(surfels.positions.astype(np.float64), m, distances=False)
    args = _object_arrays(surfels)
    smooth_var = smooth * 0.25 * args[3] * args[4] * _initial_weight(surfels)
    return idx, args, smooth_var


def _initial_weight(surfels: Surfels) -> np.ndarray:
    if surfels.weight is None:
        return np.ones(len(surfels), np.float64)
    return surfels.weight.astype(np.float64)


def _capture_settings(cutoff: float):
    import dataclasses

    from ..frame import RenderSettings

    wanted = {"cutoff": float(cutoff), "dof": False, "shading": "none", "lod": False}
    names = {f.name for f in dataclasses.fields(RenderSettings)}
    return RenderSettings(**{k: v for k, v in wanted.items() if k in names})


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise DofsplatError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _progress(total: int, desc: str, enabled: bool, unit: str = "view"):
    from tqdm import tqdm

    show = enabled and total > 1 and sys.stderr.isatty()
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=not show,
                leave=False)
