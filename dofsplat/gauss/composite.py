"""Sorting Gaussians by depth into 16 x 16 tiles and blending them front to back per pixel.

As the trainers do (3DGS, gsplat's ``RasterizeToPixels3DGSFwd``): every Gaussian whose box
meets a tile is listed for it, nearest first (by the camera depth of its centre; equal
depths keep the scene's order, as gsplat's stable radix sort does). Each pixel then walks its
tile's list:

    s = 1/2 (a dx^2 + c dy^2) + b dx dy        (d = mean - pixel centre; skipped if s < 0)
    alpha = min(0.999, o e^-s)                 (skipped if below the Gaussian's cut, 1/255)
    T' = T (1 - alpha); stop before T' <= 1e-4 (that Gaussian is not added)
    C += alpha T colour; T = T'

and C + T background is the pixel, in the trainer's colour space. A pixel's depth is the
depth of the Gaussian at which T first falls to 1/2 (the median depth: what autofocus and
the depth output see), inf where it never does.
"""

from __future__ import annotations

import math

import numpy as np

from ..colors import linear_to_srgb, srgb_to_linear
from ..jit import numba
from .project import (F_B, F_CA, F_CB, F_CC, F_CUT, F_DEPTH, F_G, F_OPACITY, F_R, F_X, F_Y,
                      MAX_ALPHA)

TILE = 16
MIN_TRANSMITTANCE = 1e-4  # a pixel stops before its transmittance falls to this
MEDIAN_TRANSMITTANCE = 0.5  # the depth output: where T falls to this
SPAN_SLACK = 0.01  # px: a row's chord of a footprint is walked this much wider (float32 rows)
SPAN_MIN = 8  # px: a footprint's rows in a tile are walked along its chord where wider than this
SHARE_SEEN = 0.05  # lens visibility: a Gaussian seen this much (a share of its footprint) counts as seen


def depth_order(rows: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """The visible Gaussians' indices, nearest first; equal depths in index order."""
    index = np.flatnonzero(visible)
    return index[np.argsort(rows[index, F_DEPTH], kind="stable")]


@numba.njit(cache=True, nogil=True)
def bin_tiles(order, boxes, n_tx, n_ty):
    """(offsets (T + 1,) int64, ids (pairs,) int32): the Gaussians of ``order`` listed per
    tile (tile t = ty n_tx + tx holds ids[offsets[t]:offsets[t + 1]]), in ``order``'s order."""
    n_tiles = n_tx * n_ty
    counts = np.zeros(n_tiles + 1, np.int64)
    for g in order:
        for ty in range(boxes[g, 2] // TILE, (boxes[g, 3] - 1) // TILE + 1):
            for tx in range(boxes[g, 0] // TILE, (boxes[g, 1] - 1) // TILE + 1):
                counts[ty * n_tx + tx + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    ids = np.empty(counts[n_tiles], np.int32)
    fill = counts[:n_tiles].copy()
    for g in order:
        for ty in range(boxes[g, 2] // TILE, (boxes[g, 3] - 1) // TILE + 1):
            for tx in range(boxes[g, 0] // TILE, (boxes[g, 1] - 1) // TILE + 1):
                t = ty * n_tx + tx
                ids[fill[t]] = g
                fill[t] += 1
    return counts, ids


# a pixel's blend state (``blend``): transmittance, colour, median depth
S_T, S_R, S_G, S_B, S_DEPTH = range(5)
N_STATE = 5


@numba.njit(cache=True, nogil=True, inline="always")
def start_pixel(state, p):
    """Pixel p's state before any Gaussian: T = 1, no colour, no depth."""
    state[p, S_T] = 1.0
    state[p, S_R] = 0.0
    state[p, S_G] = 0.0
    state[p, S_B] = 0.0
    state[p, S_DEPTH] = math.inf


@numba.njit(cache=True, nogil=True, inline="always")
def gaussian_alpha(mx, my, ca, cb, cc, opacity, cut, px, py):
    """The alpha of a Gaussian (mean mx, my; conic ca, cb, cc; opacity; cut) at pixel
    (px, py), or 0.0 where it is skipped (s < 0, or alpha below its cut)."""
    dx = mx - (px + 0.5)
    dy = my - (py + 0.5)
    s = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
    if s < 0.0:
        return 0.0
    alpha = min(MAX_ALPHA, opacity * math.exp(-s))
    if alpha < cut:
        return 0.0
    return alpha


@numba.njit(cache=True, nogil=True, inline="always")
def blend(state, p, alpha, rows, g):
    """Row g's Gaussian, at this alpha, over pixel p's state (the module docstring's
    step): the weight alpha T added, or -1.0 where the pixel is done (T would fall to
    MIN_TRANSMITTANCE: nothing is added, and nothing more will be)."""
    t_before = state[p, S_T]
    next_trans = t_before * (1.0 - alpha)
    if next_trans <= MIN_TRANSMITTANCE:
        return -1.0
    w = alpha * t_before
    state[p, S_R] += w * rows[g, F_R]
    state[p, S_G] += w * rows[g, F_G]
    state[p, S_B] += w * rows[g, F_B]
    if next_trans <= MEDIAN_TRANSMITTANCE < t_before:
        state[p, S_DEPTH] = rows[g, F_DEPTH]
    state[p, S_T] = next_trans
    return w


@numba.njit(cache=True, nogil=True, parallel=True)
def composite_tiles(rows, boxes, offsets, ids, n_tx, width, height, color, transmittance,
                    depth, seen):
    """Blend each tile's list front to back into color (H, W, 3) float32 (without the
    background: that is background x transmittance), transmittance (H, W) float32 and
    depth (H, W) float32. seen: (threads, N) float32 to add each Gaussian's visible alpha
    (sum over pixels of alpha T) into, a row per thread (``numba.get_thread_id``), or (0, 0)
    to skip it. Each tile is ``blend_tile``'s."""
    n_tiles = offsets.shape[0] - 1
    track = seen.shape[0] > 0
    for t in numba.prange(n_tiles):
        tid = numba.get_thread_id() if track else 0
        tx0 = (t % n_tx) * TILE
        ty0 = (t // n_tx) * TILE
        tx1 = min(tx0 + TILE, width)
        ty1 = min(ty0 + TILE, height)
        tw = tx1 - tx0
        state = np.empty((tw * (ty1 - ty0), N_STATE), np.float64)
        done = np.empty(tw * (ty1 - ty0), np.bool_)
        blend_tile(rows, boxes, ids, offsets[t], offsets[t + 1], tx0, ty0, tx1, ty1, state,
                   done, seen, tid)
        for py in range(ty0, ty1):
            for px in range(tx0, tx1):
                p = (py - ty0) * tw + (px - tx0)
                color[py, px, 0] = state[p, S_R]
                color[py, px, 1] = state[p, S_G]
                color[py, px, 2] = state[p, S_B]
                transmittance[py, px] = state[p, S_T]
                depth[py, px] = state[p, S_DEPTH]


@numba.njit(cache=True, nogil=True, inline="always")
def blend_tile(rows, boxes, ids, k0, k1, tx0, ty0, tx1, ty1, state, done, seen, tid):
    """One tile's pixels [tx0, tx1) x [ty0, ty1) blended front to back from its list
    ids[k0:k1] into state (a row per pixel, row by row; ``start_pixel`` first), done a flag
    per pixel; seen: ``composite_tiles``'s (thread tid's row), or (0, 0).

    Gaussian by Gaussian, over the pixels of its box within the tile only (a tile's list
    holds many Gaussians that reach a few of its pixels); each pixel's blend is the one of
    the module docstring, in the same order, so the result is the pixel-by-pixel walk's
    (the CUDA backend's, a thread per pixel, with the same ``gaussian_alpha`` and ``blend``)."""
    track = seen.shape[0] > 0
    tw = tx1 - tx0
    n_px = tw * (ty1 - ty0)
    for p in range(n_px):
        start_pixel(state, p)
        done[p] = False
    n_done = 0
    for k in range(k0, k1):
        if n_done == n_px:
            break
        g = ids[k]
        mx, my = rows[g, F_X], rows[g, F_Y]
        ca, cb, cc = rows[g, F_CA], rows[g, F_CB], rows[g, F_CC]
        opacity, cut = rows[g, F_OPACITY], rows[g, F_CUT]
        # alpha reaches the cut where 2 s = a dx^2 + 2 b dx dy + c dy^2 <= 2 ln(o / cut): on
        # each row an interval of dx (the ellipse's chord), found with a margin, so that
        # gaussian_alpha decides every pixel it might reach and the rest are not visited
        # (where the box's row in the tile is wider than SPAN_MIN: a narrow one is walked)
        bx0, bx1 = max(boxes[g, 0], tx0), min(boxes[g, 1], tx1)
        chords = bx1 - bx0 > SPAN_MIN
        reach2 = 2.0 * math.log(max(opacity / cut, 1.0)) if chords else 0.0
        for py in range(max(boxes[g, 2], ty0), min(boxes[g, 3], ty1)):
            px0, px1 = bx0, bx1
            if chords:
                dy = my - (py + 0.5)
                disc = (cb * dy) ** 2 - ca * (cc * dy * dy - reach2)
                if disc < 0.0:
                    continue
                root = math.sqrt(disc)
                # dx = mx - (px + 0.5) within [(-b dy - root) / a, (-b dy + root) / a]
                px0 = max(bx0, int(math.ceil(mx - 0.5 - (-cb * dy + root) / ca - SPAN_SLACK)))
                px1 = min(bx1, int(math.floor(mx - 0.5 - (-cb * dy - root) / ca
                                              + SPAN_SLACK)) + 1)
            for px in range(px0, px1):
                p = (py - ty0) * tw + (px - tx0)
                if done[p]:
                    continue
                alpha = gaussian_alpha(mx, my, ca, cb, cc, opacity, cut, px, py)
                if alpha == 0.0:
                    continue
                w = blend(state, p, alpha, rows, g)
                if w < 0.0:
                    done[p] = True
                    n_done += 1
                elif track:
                    seen[tid, g] += w


@numba.njit(cache=True, nogil=True, inline="always")
def seen_share(rows, i, seen):
    """The share of row i's alpha energy that a view saw, at most 1: seen (its alpha T
    summed over the pixels) over its footprint's integral, o 2 pi sqrt(det cov2d)
    (det cov2d = 1 / det conic)."""
    ca, cb, cc = float(rows[i, F_CA]), float(rows[i, F_CB]), float(rows[i, F_CC])
    energy = float(rows[i, F_OPACITY]) * 2.0 * math.pi / math.sqrt(ca * cc - cb * cb)
    return min(seen / energy, 1.0)


@numba.njit(cache=True, nogil=True, inline="always")
def lens_share(best):
    """A Gaussian's lens visibility from the largest share any view saw: over SHARE_SEEN,
    at most 1 (``backends.cpu_gauss.lens_visibility``)."""
    return min(best / SHARE_SEEN, 1.0)


@numba.njit(cache=True, nogil=True, parallel=True)
def seen_shares(rows, visible, seen, out):
    """out[i] = ``seen_share`` of each visible row (0 for the others); seen: (N,) its alpha T
    summed over the pixels."""
    for i in numba.prange(visible.shape[0]):
        out[i] = seen_share(rows, i, float(seen[i])) if visible[i] else 0.0


@numba.njit(cache=True, nogil=True, parallel=True)
def keep_best_share(rows, visible, seen, best):
    """best[i] = max(best[i], seen_share) for the visible rows; seen: (N,) the view's alpha
    T summed per Gaussian."""
    for i in numba.prange(visible.shape[0]):
        if visible[i]:
            best[i] = max(best[i], seen_share(rows, i, float(seen[i])))


@numba.njit(cache=True, nogil=True, parallel=True)
def best_view_shares(rows, visible, seen, n, best):
    """best[i] = ``lens_share`` of the largest ``seen_share`` of Gaussian i over V views
    whose rows are stacked (view v's row of it at v n + i; rows (V n, N_FIELDS), visible
    (V n,); seen (threads, V n), summed here): ``keep_best_share`` over the views, then
    ``finish_shares``. Each Gaussian's is ``best_view_share``'s."""
    for i in numba.prange(n):
        best[i] = best_view_share(rows, visible, seen, n, i)


@numba.njit(cache=True, nogil=True, inline="always")
def best_view_share(rows, visible, seen, n, i):
    """Gaussian i's ``lens_share`` of its largest ``seen_share`` over the stacked views of
    ``best_view_shares`` (which see): the per-Gaussian maths that the CUDA backend compiles
    as a device function too (its seen: one row, summed by atomics)."""
    n_views = rows.shape[0] // max(n, 1)
    share = 0.0
    for v in range(n_views):
        r = v * n + i
        if visible[r]:
            total = 0.0
            for t in range(seen.shape[0]):
                total += seen[t, r]
            share = max(share, seen_share(rows, r, total))
    return lens_share(share)


@numba.njit(cache=True, nogil=True, parallel=True)
def finish_shares(best):
    """best[i] = lens_share(best[i]) for every Gaussian, in place."""
    for i in numba.prange(best.shape[0]):
        best[i] = lens_share(best[i])


DECODE_STEPS = 4096  # the decoding table's intervals (linear between: within 8e-8 of the curve)


def decode_table() -> np.ndarray:
    """(DECODE_STEPS + 1,) float64: ``colors.srgb_to_linear`` at DECODE_STEPS + 1 even steps
    of [0, 1], for ``decode``."""
    return srgb_to_linear(np.linspace(0.0, 1.0, DECODE_STEPS + 1))


DECODE = decode_table()


@numba.njit(cache=True, nogil=True, inline="always")
def decode(x, lut):
    """``colors.srgb_to_linear`` of one value x in [0, 1], for the kernels (and their CUDA
    twins): linear between the steps of lut (``DECODE``, ``decode_table``), within 8e-8 of
    the curve (float32's own step near 1 is 6e-8), where a power per value took the 35 px
    frames at 1920 x 1080 1.1-1.7 x longer (every part is decoded: 25 million values in 4
    parts; bench/RESULTS.md, "Over a white background: blurred layers summed")."""
    f = x * (lut.shape[0] - 1)
    i = min(int(f), lut.shape[0] - 2)
    return lut[i] + (f - i) * (lut[i + 1] - lut[i])


def encode_table() -> np.ndarray:
    """(DECODE_STEPS + 1,) float64: ``colors.linear_to_srgb`` of u^2 at DECODE_STEPS + 1 even
    steps of u in [0, 1], for ``encode`` (in the square root the curve is nearly straight:
    linear between the steps, within 3e-7 of it)."""
    return linear_to_srgb(np.linspace(0.0, 1.0, DECODE_STEPS + 1) ** 2)


ENCODE = encode_table()


@numba.njit(cache=True, nogil=True, inline="always")
def encode(x, lut):
    """``colors.linear_to_srgb`` of one value x in [0, 1], for the kernels (and their CUDA
    twins): linear between the steps of lut (``ENCODE``, ``encode_table``) in sqrt(x)."""
    f = math.sqrt(x) * (lut.shape[0] - 1)
    i = min(int(f), lut.shape[0] - 2)
    return lut[i] + (f - i) * (lut[i + 1] - lut[i])


@numba.njit(cache=True, nogil=True, inline="always")
def linear_pixel(state, p, lut):
    """Pixel p's blend (``blend``: colour in the trainer's space, premultiplied by its
    coverage 1 - T) in linear light: its mean colour (the colour over the coverage),
    clipped to [0, 1] and decoded (``decode`` with lut), times the coverage; none where
    the coverage is under 1e-7 (a summed layer's sharp view, ``gauss/layers.py``)."""
    a = 1.0 - state[p, S_T]
    for c in range(S_R, S_B + 1):
        if a > 1e-7:
            state[p, c] = decode(min(max(state[p, c] / a, 0.0), 1.0), lut) * a
        else:
            state[p, c] = 0.0


@numba.njit(cache=True, nogil=True, inline="always")
def part_linear(value, t, bg, lut):
    """One channel of a lens part's pixel in linear light: its composite (value, of
    transmittance t, the trainer's colour space) over the background bg (the same space),
    clipped to [0, 1] and decoded (``decode``): a frame's pixel (``finish_pixel``), or each
    part's, the parts of the lens averaged so, as the lens reference averages its views
    (docs/maths.md, "Gaussian scenes")."""
    return decode(min(max(value + t * bg, 0.0), 1.0), lut)


@numba.njit(cache=True, nogil=True, inline="always")
def finish_pixel(color, trans, y, x, scale, bg, lut, out):
    """out[y, x] (RGBA): the composite over the background, in linear RGB. color (H, W, 3)
    and trans (H, W) are scaled by ``scale`` (1/K for the sums of K lens parts); bg (3,) is
    the background in the trainer's colour space. The composite C + T bg is clipped to
    [0, 1] there and decoded (``part_linear``, with lut); alpha is 1 - T."""
    t = trans[y, x] * scale
    for c in range(3):
        out[y, x, c] = part_linear(color[y, x, c] * scale, t, bg[c], lut)
    out[y, x, 3] = 1.0 - t


@numba.njit(cache=True, nogil=True, inline="always")
def add_linear_part(color, trans, y, x, bg, lut, out_color, out_trans):
    """One lens part's pixel (color (H, W, 3), trans (H, W)) added in linear light
    (``part_linear``) into out_color[y, x], its T into out_trans[y, x]."""
    t = trans[y, x]
    for c in range(3):
        out_color[y, x, c] += part_linear(color[y, x, c], t, bg[c], lut)
    out_trans[y, x] += t


@numba.njit(cache=True, nogil=True, inline="always")
def finish_linear_pixel(color, trans, y, x, scale, out):
    """out[y, x] (RGBA): the sums of ``add_linear_part`` over K parts times scale = 1/K:
    the linear colour and alpha 1 - T."""
    for c in range(3):
        out[y, x, c] = color[y, x, c] * scale
    out[y, x, 3] = 1.0 - trans[y, x] * scale


@numba.njit(cache=True, nogil=True, parallel=True)
def add_linear_parts(color, trans, bg, lut, out_color, out_trans):
    """``add_linear_part`` over the image, a row per task."""
    for y in numba.prange(trans.shape[0]):
        for x in range(trans.shape[1]):
            add_linear_part(color, trans, y, x, bg, lut, out_color, out_trans)


@numba.njit(cache=True, nogil=True, parallel=True)
def finish_linear_image(color, trans, scale, out):
    """``finish_linear_pixel`` over the image, a row per task."""
    for y in numba.prange(trans.shape[0]):
        for x in range(trans.shape[1]):
            finish_linear_pixel(color, trans, y, x, scale, out)


@numba.njit(cache=True, nogil=True, parallel=True)
def finish_image(color, trans, scale, bg, lut, out):
    """``finish_pixel`` over the image, a row per task."""
    for y in numba.prange(trans.shape[0]):
        for x in range(trans.shape[1]):
            finish_pixel(color, trans, y, x, scale, bg, lut, out)
