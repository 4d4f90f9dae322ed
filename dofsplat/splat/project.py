"""Projection of all surfels to screen-space splats: the numba kernel of the CPU backend.

Output, one row per surfel in an (N, N_FIELDS) array (columns ``SPLAT_FIELDS``; float32 on the
CPU, which halves a frame's largest array and leaves images unchanged to 98 dB):
screen mean, conic (inverse variance), amplitude, z-range, depth, shaded colour, opacity,
CoC radius, unclipped bbox columns, the aperture's radius and reach (splat/bokeh.py), the
unblurred footprint's conic (the splat as a pinhole sees it, for the A-buffer's front pass),
its depth change per pixel (signed, x and y) and an LOD node's colour change per pixel
(``ewa.color_slope``; zero for a surfel); an int32 (N, 4) pixel bounding box (x0, x1, y0, y1,
inclusive) clipped to the image, empty, (0, -1, 0, -1), for a splat within a pixel of the
image that draws none of its pixels (its disk goes into the front map); and a visibility flag. A splat's fragment weight at pixel centre x is

    amp * exp(-1/2 (x - m)^T W^-1 (x - m))   where that exponent is below the cutoff c,

with amp = (surfel area in pixels) / (the kernel's sum over its pixel centres), so that each
splat deposits exactly its area in pixels (Section 6.3's partition of unity, made exact for
point sampling; docs/maths.md).
"""

import math

from ..jit import numba
import numpy as np

from ..parallel import weyl_stride
from .bokeh import aperture_mass, edge_mix, support_bbox
from .ewa import color_slope, kernel_bbox, kernel_pixel_sum, max_eigenvalue, project_surfel

# the rasteriser reads the first N_RASTER_FIELDS (the CUDA backend keeps a batch of them in
# shared memory) and the colour slope (read where it is not zero); the front pass and the
# visibility read the rest too
(MX, MY, C11, C12, C22, AMP, ZLO, ZHI, DEPTH, RED, GREEN, BLUE, ALPHA, X0, X1, FLOOR, RAD,
 REACH, MIX, COC, F11, F12, F22, GZX, GZY, RX, RY, GX, GY, BX, BY) = range(31)
N_FIELDS = 31
# splats per block of project_splats' schedule (a Weyl order of blocks; dofsplat/parallel.py)
PROJECT_BLOCK = 256
N_RASTER_FIELDS = 19
SPLAT_FIELDS = ("mx", "my", "c11", "c12", "c22", "amp", "z_lo", "z_hi", "depth",
                "red", "green", "blue", "alpha", "x0", "x1", "floor", "aperture_radius_px",
                "reach_px", "edge_mix", "coc_radius_px", "f11", "f12", "f22", "gz_x", "gz_y",
                "red_x", "red_y", "green_x", "green_y", "blue_x", "blue_y")

# Kernels whose unclipped bounding box exceeds this many pixels are normalised analytically,
# by 2 pi sqrt|W| (1 - e^-c) (Section 6.3); smaller ones by their exact sum over the pixel
# centres. Point sampling misses the integral of a truncated Gaussian a few pixels wide by
# up to ~2 %; at this size the analytic factor is within ~3e-4 (docs/maths.md).
EXACT_NORMALISATION_MAX_AREA = 16384


@numba.njit(cache=True, nogil=True, parallel=True)
def project_splats(positions, normals, tangents, ru, rv, area, rgb, alpha, lod_cov, view,
                   ax, bx, ay, by, near, width, height, coc_k, inv_focus, cutoff,
                   z_margin, cull_backfaces, exact_norm, floor, disc, blades, moments, out, bbox,
                   visible):
    """Fill ``out`` (N, N_FIELDS), ``bbox`` (N, 4) and ``visible`` (N,) for N surfels.

    positions, normals: (N, 3) float32 world; tangents: (N, 3) for elliptical surfels or
    (0, 3); ru, rv: (N,) disk radii; area: (N,) world area each surfel stands for; rgb (N, 3)
    shaded linear colour; alpha (N,) opacity; lod_cov: (N, 6) world covariances of the
    LOD filter V^{q,l} (xx, xy, xz, yy, yz, zz) or (0, 6);
    view: (12,) rows of camera_from_world[:3]; the rest are scalars (see ewa.project_surfel).
    """
    n = positions.shape[0]
    view_t = (view[0], view[1], view[2], view[3], view[4], view[5], view[6], view[7],
              view[8], view[9], view[10], view[11])
    screen = (ax, bx, ay, by)
    # blocks of splats in a Weyl order (dofsplat/parallel.py): the tree's order is spatial,
    # and near, wide splats cost most (their exact normalisation sums their pixels)
    n_blocks = (n + PROJECT_BLOCK - 1) // PROJECT_BLOCK
    stride = weyl_stride(n_blocks)
    for u in numba.prange(n_blocks):
        b = (u * stride) % n_blocks
        for k in range(b * PROJECT_BLOCK, min((b + 1) * PROJECT_BLOCK, n)):
            project_splat(k, positions, normals, tangents, ru, rv, area, rgb, alpha, lod_cov,
                          view_t, screen, near, width, height, coc_k, inv_focus, cutoff,
                          z_margin, cull_backfaces, exact_norm, floor, disc, blades, moments,
                          out, bbox, visible)


# inlined at numba's level (1.5-2.4 x faster than a call, bench/RESULTS.md). Its arguments
# stay under 30: past CPython's STACK_USE_GUIDELINE a call is compiled as f(*args), which
# numba's inliner refuses ("Calling a closure with *args"), and then every array of the
# call went through memory per splat
@numba.njit(cache=True, nogil=True, inline="always")
def project_splat(k, positions, normals, tangents, ru, rv, area, rgb, alpha, lod_cov, view_t,
                  screen, near, width, height, coc_k, inv_focus, cutoff, z_margin,
                  cull_backfaces, exact_norm, floor, disc, blades, moments, out, bbox, visible):
    """Splat k of ``project_splats`` (its arguments; view_t: the view as a 12-tuple, screen:
    (ax, bx, ay, by) of ``Camera.screen_coefficients``, floor:
    e^-c to taper LOD nodes' kernels, else 0; disc: draw the aperture's shape, a polygon of
    ``blades`` (N, 2), the unit normals of its edges, or a disc if (0, 2), and ``bokeh.aperture_moments`` for the kernels' masses). Shared with the CUDA backend, one thread per splat."""
    ax, bx, ay, by = screen
    n = positions.shape[0]
    elliptical = tangents.shape[0] == n
    has_lod = lod_cov.shape[0] == n
    visible[k] = False
    p = (np.float64(positions[k, 0]), np.float64(positions[k, 1]), np.float64(positions[k, 2]))
    nn = (np.float64(normals[k, 0]), np.float64(normals[k, 1]), np.float64(normals[k, 2]))
    t = (0.0, 0.0, 0.0)
    if elliptical:
        t = (np.float64(tangents[k, 0]), np.float64(tangents[k, 1]), np.float64(tangents[k, 2]))
    cov = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if has_lod:
        cov = (np.float64(lod_cov[k, 0]), np.float64(lod_cov[k, 1]), np.float64(lod_cov[k, 2]),
               np.float64(lod_cov[k, 3]), np.float64(lod_cov[k, 4]), np.float64(lod_cov[k, 5]))
    (ok, mx, my, w11, w12, w22, area_px, depth, zlo, zhi, coc_r, f11, f12, f22,
     gz_x, gz_y, radius) = project_surfel(
        p, nn, t, np.float64(ru[k]), np.float64(rv[k]), np.float64(area[k]), view_t,
        ax, bx, ay, by, near, coc_k, inv_focus, cov, cutoff, z_margin, cull_backfaces, disc)
    if not ok:
        return
    mix = edge_mix(radius, w11, w22)
    if radius != 0.0:
        x0, x1, y0, y1 = support_bbox(mx, my, w11, w12, w22, radius, mix,
                                      math.sqrt(2.0 * cutoff))
    else:
        x0, x1, y0, y1 = kernel_bbox(mx, my, w11, w22, cutoff)
    if x0 > width or x1 < -1 or y0 > height or y1 < -1:
        return  # outside the view frustum, by more than a pixel
    cx0, cx1 = max(x0, 0), min(x1, width - 1)
    cy0, cy1 = max(y0, 0), min(y1, height - 1)
    if cx0 > cx1 or cy0 > cy1:
        # no pixel of the image, but within one: the splat draws no fragment (an empty box
        # makes no tile pair), and its opaque disk still goes into the front map beyond the
        # edge (abuffer.front_box), where a surface just behind it, blurred a little more,
        # reaches in (tests/test_render.py, "beyond the frame edge")
        cx0, cx1, cy0, cy1 = 0, -1, 0, -1
    det = w11 * w22 - w12 * w12
    c11, c12, c22 = w22 / det, -w12 / det, w11 / det
    # LOD nodes are tapered (their truncation edge would show as a disc); surfels keep the
    # paper's truncated Gaussian, whose wider tail sums more evenly over a surface
    node = has_lod and lod_cov[k, 0] + lod_cov[k, 3] + lod_cov[k, 5] > 0.0
    floor_k = floor if node else 0.0
    norm = 0.0
    reach = abs(radius) + math.sqrt(2.0 * cutoff * max_eigenvalue(w11, w12, w22))
    if radius != 0.0:
        # an aperture kernel's mass by quadrature over the direction (bokeh.aperture_mass):
        # at least a pixel wide, its sum over pixel centres is the integral to ~5e-3 (1 % for
        # polygons)
        norm = aperture_mass(radius, w11, w12, w22, mix, blades, moments)
        floor_k = 0.0  # the table is tapered already
    elif exact_norm and (x1 - x0 + 1) * (y1 - y0 + 1) <= EXACT_NORMALISATION_MAX_AREA:
        norm = kernel_pixel_sum(mx, my, c11, c12, c22, cutoff, x0, x1, y0, y1, floor_k)
    if norm > 0.0:
        amp = area_px / norm
    else:
        # the integral of exp(-q) - floor over q < c is 2 pi sqrt|W| (1 - e^-c - c floor)
        mass = 1.0 - math.exp(-cutoff) - cutoff * floor_k
        amp = area_px / (2.0 * math.pi * mass * math.sqrt(det))
    out[k, MX] = mx
    out[k, MY] = my
    out[k, C11] = c11
    out[k, C12] = c12
    out[k, C22] = c22
    out[k, AMP] = amp
    out[k, ZLO] = zlo
    out[k, ZHI] = zhi
    out[k, DEPTH] = depth
    out[k, RED] = rgb[k, 0]
    out[k, GREEN] = rgb[k, 1]
    out[k, BLUE] = rgb[k, 2]
    out[k, ALPHA] = alpha[k]
    out[k, COC] = coc_r
    out[k, X0] = x0  # unclipped bbox columns (ewa.row_pixel_range)
    out[k, X1] = x1
    f_inv = 1.0 / (f11 * f22 - f12 * f12)
    out[k, F11] = f22 * f_inv
    out[k, F12] = -f12 * f_inv
    out[k, F22] = f11 * f_inv
    out[k, GZX] = gz_x
    out[k, GZY] = gz_y
    out[k, FLOOR] = floor_k
    out[k, RAD] = radius
    out[k, REACH] = reach
    out[k, MIX] = mix
    for f in range(RX, BY + 1):
        out[k, f] = 0.0  # a surfel's colour is flat; slope_splats sets the nodes'
    bbox[k, 0] = cx0
    bbox[k, 1] = cx1
    bbox[k, 2] = cy0
    bbox[k, 3] = cy1
    visible[k] = True


@numba.njit(cache=True, nogil=True, parallel=True)
def slope_splats(positions, normals, color_grad, gain, view, ax, ay, ap_var, out, visible):
    """The LOD nodes' colour slopes (fields RX..BY, ``ewa.color_slope``) of splats that
    ``project_splats`` filled: color_grad (N, 6) the nodes' colour gradients
    (``lod/hierarchy.py``; zero rows for surfels), gain (N, 3) the shading's factor on the
    colour (``splat/shade.py``) or (0, 3) for 1; ap_var: the aperture's variance per axis at
    radius 1 (``ewa.color_slope``).

    A pass of its own: in project_splat's loop the extra arrays cost the projection of every
    frame 60 % more (bench/RESULTS.md), with or without nodes (they took its call past 30
    arguments, which numba does not inline: see project_splat)."""
    view_t = (view[0], view[1], view[2], view[3], view[4], view[5], view[6], view[7],
              view[8], view[9], view[10], view[11])
    for k in numba.prange(positions.shape[0]):
        slope_splat(k, positions, normals, color_grad, gain, view_t, ax, ay, ap_var, out,
                    visible)


@numba.njit(cache=True, nogil=True, inline="always")  # as project_splat
def slope_splat(k, positions, normals, color_grad, gain, view_t, ax, ay, ap_var, out, visible):
    """Splat k of ``slope_splats``; shared with the CUDA backend, one thread per splat."""
    if not visible[k]:
        return
    g = (np.float64(color_grad[k, 0]), np.float64(color_grad[k, 1]), np.float64(color_grad[k, 2]),
         np.float64(color_grad[k, 3]), np.float64(color_grad[k, 4]), np.float64(color_grad[k, 5]))
    if g[0] == 0.0 and g[1] == 0.0 and g[2] == 0.0 and g[3] == 0.0 and g[4] == 0.0 \
            and g[5] == 0.0:
        return
    gn = (1.0, 1.0, 1.0)
    if gain.shape[0] == positions.shape[0]:
        gn = (np.float64(gain[k, 0]), np.float64(gain[k, 1]), np.float64(gain[k, 2]))
    # the kernel's Gaussian variance W from its conic, and its aperture disc
    c11, c12, c22 = np.float64(out[k, C11]), np.float64(out[k, C12]), np.float64(out[k, C22])
    inv = 1.0 / (c11 * c22 - c12 * c12)
    p = (np.float64(positions[k, 0]), np.float64(positions[k, 1]), np.float64(positions[k, 2]))
    nn = (np.float64(normals[k, 0]), np.float64(normals[k, 1]), np.float64(normals[k, 2]))
    sl = color_slope(p, nn, g, gn, view_t, ax, ay, c22 * inv, -c12 * inv, c11 * inv,
                     abs(np.float64(out[k, RAD])), ap_var)
    out[k, RX] = sl[0]
    out[k, RY] = sl[1]
    out[k, GX] = sl[2]
    out[k, GY] = sl[3]
    out[k, BX] = sl[4]
    out[k, BY] = sl[5]
