"""The post-process baseline: a depth-driven blur of a pinhole image (paper Section 2).

What most real-time renderers do instead of our method, and what the paper calls
post-filtering (Potmesil & Chakravarty 1981, with Chen's uniform circle of confusion): render
a sharp pinhole image with its depth buffer, give every pixel the CoC of its depth, and
spread each pixel's colour over its own circle. We implement the spread as a gather
("scatter as gather"), so each output pixel is computed once and in parallel:

    r_q      = clamp(K |1/z_q - 1/P|, 1/2, r_max)        the CoC radius of pixel q (eqs. 1-3)
    r'_q     = min(r_q, r_p)  if z_q > z_p  else r_q     the usual depth test (below)
    cov_pq   = clamp(r'_q + 1/2 - |p - q|, 0, 1)         q's disc at p, antialiased edge
    w_pq     = cov_pq / (pi r'_q^2 + pi/12)              the disc's area: energy spreads out
    out_p    = sum_q w_pq c_q / sum_q w_pq               (RGB and alpha alike)

The depth test is the one game engines use: a pixel behind p may spread onto p no further
than p's own CoC, so a blurred background does not bleed onto a sharp object in front of it
(``depth_test=False`` gives the plain Potmesil/Chen filter, which does). The denominator
pi r^2 + pi/12 is the exact integral of the antialiased disc. Depth inf (nothing drawn) is
at infinity, 1/z = 0. A CoC of at most half a pixel leaves the pixel as it was.

The artefacts that remain are those of any post-filter, which our method avoids
(``bench/RESULTS.md`` shows them): no partial occlusion (the pinhole image has nothing of
what lies behind a foreground object, so the blurred rim of that object cannot turn
transparent, and the sharp background keeps its hard edge inside it), and intensity
leakage between differently focused surfaces (a sharp surface's colour keeps its full
weight next to a blurred one, whose spread onto it is diluted by the normalisation).

The kernel is numba-jitted and parallel over rows; ``postfilter_slow`` is its numpy twin.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings

from .jit import numba
import numpy as np

from .camera import Camera, EyeLens, ThinLens
from .errors import DofsplatError
from .frame import RenderResult, RenderSettings, frame_arguments
from .render import render
from .surfels import Surfels

MAX_RADIUS_PX = 64.0  # CoC radii are clamped here: the gather costs pi r_max^2 per pixel
MIN_RADIUS_PX = 0.5  # a pixel always covers itself


def coc_radius_map(depth: np.ndarray, coc_k: float, inv_focus: float,
                   max_radius: float = MAX_RADIUS_PX) -> np.ndarray:
    """(H, W) float32 CoC radius in pixels per pixel of a depth buffer, clamped to [1/2, r_max].

    depth: (H, W) camera depth U, world units, inf where nothing was drawn.
    (coc_k, inv_focus): (K, 1/P) of ``lens.coc_coefficients(camera)``, C_r = K |1/U - 1/P|.
    """
    depth = np.asarray(depth, np.float64)
    with np.errstate(divide="ignore"):
        inv_depth = np.where(np.isfinite(depth) & (depth > 0), 1.0 / depth, 0.0)
    r = coc_k * np.abs(inv_depth - inv_focus)
    return np.clip(r, MIN_RADIUS_PX, max(max_radius, MIN_RADIUS_PX)).astype(np.float32)


def postfilter(image: np.ndarray, depth: np.ndarray, coc_k: float, inv_focus: float, *,
               depth_test: bool = True, max_radius: float = MAX_RADIUS_PX,
               blades: np.ndarray | None = None) -> np.ndarray:
    """Blur a pinhole image by the CoC of its depth buffer (see the module notes).

    image: (H, W, C) float, linear (C = 4: RGB composited over the background, alpha)
    depth: (H, W) float, camera depth U in world units, inf where nothing was drawn
    coc_k, inv_focus: the lens's (K, 1/P), C_r = K |1/U - 1/P| pixels
    depth_test: limit what lies behind a pixel to that pixel's CoC (module notes)
    max_radius: CoC radii above this many pixels are clamped (with a warning)
    blades: (N, 2) unit edge normals of a polygonal aperture (``splat.bokeh.blade_normals``):
            each pixel spreads over that polygon of circumradius r_q, turned by 180 degrees
            before the focal plane, instead of a disc

    Returns (H, W, C) float32.
    """
    image = _check_image(image)
    depth = np.asarray(depth, np.float32)
    if depth.shape != image.shape[:2]:
        raise DofsplatError(f"depth has shape {depth.shape} but the image is {image.shape[:2]}")
    if not (math.isfinite(max_radius) and max_radius > 0):
        raise DofsplatError(f"max_radius must be > 0, got {max_radius}")
    radius = coc_radius_map(depth, coc_k, inv_focus, max_radius)
    _warn_if_clamped(depth, coc_k, inv_focus, max_radius)
    search = _search_radius(radius)
    out = np.empty_like(image)
    blades = np.zeros((0, 2)) if blades is None else np.ascontiguousarray(blades, np.float64)
    _gather(image, depth, radius, search, bool(depth_test), blades, float(inv_focus), out)
    return out


def render_postfilter(surfels: Surfels, camera: Camera, lens: ThinLens | EyeLens | None,
                      settings: RenderSettings | None = None, *, depth_test: bool = True,
                      max_radius: float = MAX_RADIUS_PX) -> RenderResult:
    """A pinhole render, then :func:`postfilter` by ``lens``: the post-process baseline.

    Arguments as for :func:`dofsplat.render.render`; ``settings.dof = False`` (or no lens)
    returns the pinhole image. The result's depth and weight are the pinhole render's;
    stats are the pinhole render's plus filter_ms, max_coc_px and method "postfilter".
    """
    settings = frame_arguments("render_postfilter()", surfels, camera, lens, settings)
    # the sharp frame as the reference draws its samples (``sharp_visibility``)
    pinhole = render(surfels, camera, None,
                     dataclasses.replace(settings, dof=False, sharp_visibility=True))
    _warm_up()
    t = time.perf_counter()
    if lens is None or not settings.dof:
        coc_k, inv_focus = 0.0, 0.0
    else:
        coc_k, inv_focus = lens.coc_coefficients(camera)
    from .frame import aperture_shape

    blades = aperture_shape(lens, settings)[1]  # the lens's polygon, if it has blades
    image = postfilter(pinhole.image, pinhole.depth, coc_k, inv_focus, depth_test=depth_test,
                       max_radius=max_radius, blades=blades)
    filter_ms = (time.perf_counter() - t) * 1000.0
    stats = dict(pinhole.stats, method="postfilter", filter_ms=filter_ms,
                 max_coc_px=float(coc_radius_map(pinhole.depth, coc_k, inv_focus,
                                                 max_radius).max()))
    stats["total_ms"] = pinhole.stats["total_ms"] + filter_ms
    return RenderResult(image=image, depth=pinhole.depth, weight=pinhole.weight, stats=stats)


# -- the gather ----------------------------------------------------------------------------


def _search_radius(radius: np.ndarray) -> np.ndarray:
    """(H, W) float32: the largest CoC radius within reach of each pixel.

    A pixel q can reach p only if r_q >= |p - q| - 1/2, so p need look no further than the
    largest r_q in the square of half-size r_max + 1 around it (a separable max filter).
    """
    from scipy.ndimage import maximum_filter

    reach = int(math.ceil(float(radius.max()))) + 1
    return maximum_filter(radius, size=2 * reach + 1, mode="nearest")


@numba.njit(cache=True, parallel=True, nogil=True)
def _gather(image, depth, radius, search, depth_test, blades, inv_focus, out):
    h, w = depth.shape
    for i in numba.prange(h):
        row = np.int64(i)  # prange's index may be unsigned; the offsets below are signed
        acc = np.empty(image.shape[2], np.float64)  # float64 sums, one scratch per row
        for j in range(w):
            _gather_pixel(image, depth, radius, search, depth_test, blades, inv_focus, row, j,
                          acc, out)


@numba.njit(cache=True, nogil=True)
def aperture_distance(dx, dy, blades, flip):
    """|(dx, dy)| for a disc; for a polygon the gauge whose level r is the polygon of
    circumradius r, max_i(n_i . d) / cos(pi/N), turned over when flip."""
    n = blades.shape[0]
    if n == 0:
        return math.sqrt(dx * dx + dy * dy)
    best = -1e300
    for k in range(n):
        best = max(best, flip * (blades[k, 0] * dx + blades[k, 1] * dy))
    return best / math.cos(math.pi / n)


@numba.njit(cache=True, nogil=True)
def aperture_area(r, blades):
    """Area of the aperture's image of radius r: pi r^2, or the N-gon's (N/2) r^2 sin(2 pi/N)."""
    n = blades.shape[0]
    if n == 0:
        return math.pi * r * r
    return 0.5 * n * r * r * math.sin(2.0 * math.pi / n)


@numba.njit(cache=True, nogil=True)
def _gather_pixel(image, depth, radius, search, depth_test, blades, inv_focus, i, j, acc, out):
    """out[i, j] = sum_q w_pq c_q / sum_q w_pq over the pixels q that reach (i, j)."""
    h, w, nc = image.shape
    zp = depth[i, j]
    rp = radius[i, j]
    reach = int(math.ceil(search[i, j] + 0.5))
    acc[:] = 0.0
    wsum = 0.0
    for di in range(max(-reach, -i), min(reach, h - 1 - i) + 1):
        for dj in range(max(-reach, -j), min(reach, w - 1 - j) + 1):
            rq = radius[i + di, j + dj]
            if depth_test and depth[i + di, j + dj] > zp:
                rq = min(rq, rp)
            # q spreads onto p = q + (dj, di); before the focal plane its polygon is turned
            flip = -1.0 if depth[i + di, j + dj] * inv_focus < 1.0 else 1.0
            cov = rq + 0.5 - aperture_distance(-dj, -di, blades, flip)
            if cov <= 0.0:
                continue
            wq = min(cov, 1.0) / (aperture_area(rq, blades) + math.pi / 12.0)
            wsum += wq
            for c in range(nc):
                acc[c] += wq * image[i + di, j + dj, c]
    for c in range(nc):
        out[i, j, c] = acc[c] / wsum


def postfilter_slow(image, depth, coc_k, inv_focus, *, depth_test=True,
                    max_radius=MAX_RADIUS_PX, blades=None) -> np.ndarray:
    """numpy twin of :func:`postfilter`: the module's formulas, one offset at a time."""
    image = np.asarray(image, np.float64)
    depth = np.asarray(depth, np.float64)
    h, w = depth.shape
    r = coc_radius_map(depth, coc_k, inv_focus, max_radius).astype(np.float64)
    reach = int(math.ceil(r.max())) + 1
    pad = lambda a, v: np.pad(a, [(reach, reach), (reach, reach)] + [(0, 0)] * (a.ndim - 2),
                              constant_values=v)
    img_p, z_p, r_p = pad(image, 0.0), pad(depth, np.inf), pad(r, -1.0)  # -1: never reaches
    acc = np.zeros_like(image)
    wsum = np.zeros((h, w))
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            sl = np.s_[reach + di:reach + di + h, reach + dj:reach + dj + w]
            rq = r_p[sl]
            if depth_test:
                rq = np.where(z_p[sl] > depth, np.minimum(rq, r), rq)
            if blades is None or len(blades) == 0:
                dist, area = math.hypot(di, dj), math.pi * rq * rq
            else:  # the polygon's gauge of the offset q -> p = (-dj, -di), turned over near
                flip = np.where(z_p[sl] * inv_focus < 1, -1.0, 1.0)
                dist = np.max([flip * (n[0] * -dj + n[1] * -di) for n in blades], axis=0)
                dist = dist / math.cos(math.pi / len(blades))
                area = 0.5 * len(blades) * rq * rq * math.sin(2 * math.pi / len(blades))
            cov = np.clip(rq + 0.5 - dist, 0.0, 1.0)
            wq = np.where(cov > 0, cov / (area + math.pi / 12.0), 0.0)
            wsum += wq
            acc += wq[..., None] * img_p[sl]
    return (acc / wsum[..., None]).astype(np.float32)


_WARM = False


def _warm_up() -> None:
    """Compile (or load from numba's cache) the gather, so that filter_ms excludes JIT."""
    global _WARM
    if not _WARM:
        _WARM = True
        postfilter(np.zeros((2, 2, 4), np.float32), np.ones((2, 2), np.float32), 1.0, 0.5)


def _check_image(image) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or 0 in image.shape:
        raise DofsplatError(f"image must have shape (H, W, C), got {image.shape}")
    image = np.ascontiguousarray(image, np.float32)
    if not np.all(np.isfinite(image)):
        raise DofsplatError("image has NaN or inf values")
    return image


def _warn_if_clamped(depth, coc_k, inv_focus, max_radius) -> None:
    largest = float(coc_radius_map(depth, coc_k, inv_focus, np.inf).max())
    if largest > max_radius:
        warnings.warn(f"the post-filter clamps CoC radii of up to {largest:.0f} px to "
                      f"{max_radius:g} px", stacklevel=3)
