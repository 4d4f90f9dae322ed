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

from ..jit import numba
from .project import (F_B, F_CA, F_CB, F_CC, F_CUT, F_DEPTH, F_G, F_OPACITY, F_R, F_X, F_Y,
                      MAX_ALPHA)

TILE = 16
MIN_TRANSMITTANCE = 1e-4  # a pixel stops before its transmittance falls to this
MEDIAN_TRANSMITTANCE = 0.5  # the depth output: where T falls to this


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


@numba.njit(cache=True, nogil=True, parallel=True)
def composite_tiles(rows, boxes, offsets, ids, n_tx, width, height, color, transmittance,
                    depth, seen):
    """Blend each tile's list front to back into color (H, W, 3) float32 (without the
    background: that is background x transmittance), transmittance (H, W) float32 and
    depth (H, W) float32. seen: (threads, N) float32 to add each Gaussian's visible alpha
    (sum over pixels of alpha T) into, a row per thread (``numba.get_thread_id``), or (0, 0)
    to skip it.

    Gaussian by Gaussian, over the pixels of its box within the tile only (a tile's list
    holds many Gaussians that reach a few of its pixels); each pixel's blend is the one of
    the module docstring, in the same order, so the result is the pixel-by-pixel walk's."""
    n_tiles = offsets.shape[0] - 1
    track = seen.shape[0] > 0
    for t in numba.prange(n_tiles):
        tid = numba.get_thread_id() if track else 0
        tx0 = (t % n_tx) * TILE
        ty0 = (t // n_tx) * TILE
        tx1 = min(tx0 + TILE, width)
        ty1 = min(ty0 + TILE, height)
        tw = tx1 - tx0
        n_px = tw * (ty1 - ty0)
        trans = np.ones(n_px, np.float64)
        rgb = np.zeros((n_px, 3), np.float64)
        d = np.full(n_px, math.inf, np.float32)
        done = np.zeros(n_px, np.bool_)
        n_done = 0
        for k in range(offsets[t], offsets[t + 1]):
            if n_done == n_px:
                break
            g = ids[k]
            mx, my = rows[g, F_X], rows[g, F_Y]
            ca, cb, cc = rows[g, F_CA], rows[g, F_CB], rows[g, F_CC]
            opacity, cut = rows[g, F_OPACITY], rows[g, F_CUT]
            for py in range(max(boxes[g, 2], ty0), min(boxes[g, 3], ty1)):
                dy = my - (py + 0.5)
                for px in range(max(boxes[g, 0], tx0), min(boxes[g, 1], tx1)):
                    p = (py - ty0) * tw + (px - tx0)
                    if done[p]:
                        continue
                    dx = mx - (px + 0.5)
                    s = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if s < 0.0:
                        continue
                    alpha = min(MAX_ALPHA, opacity * math.exp(-s))
                    if alpha < cut:
                        continue
                    t_before = trans[p]
                    next_trans = t_before * (1.0 - alpha)
                    if next_trans <= MIN_TRANSMITTANCE:
                        done[p] = True
                        n_done += 1
                        continue
                    w = alpha * t_before
                    if track:
                        seen[tid, g] += w
                    rgb[p, 0] += w * rows[g, F_R]
                    rgb[p, 1] += w * rows[g, F_G]
                    rgb[p, 2] += w * rows[g, F_B]
                    if next_trans <= MEDIAN_TRANSMITTANCE < t_before:
                        d[p] = rows[g, F_DEPTH]
                    trans[p] = next_trans
        for py in range(ty0, ty1):
            for px in range(tx0, tx1):
                p = (py - ty0) * tw + (px - tx0)
                color[py, px, 0] = rgb[p, 0]
                color[py, px, 1] = rgb[p, 1]
                color[py, px, 2] = rgb[p, 2]
                transmittance[py, px] = trans[p]
                depth[py, px] = d[p]
