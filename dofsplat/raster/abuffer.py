"""Tile-based A-buffer rasterisation of splats (paper Section 6.4), numba kernels.

The image is cut into TILE x TILE pixel tiles. Splats are binned to the tiles their
bounding box touches (one int32 per tile-splat pair, never one entry per fragment), each
tile's list in increasing splat index. Each tile is then rasterised by one thread into a
small A-buffer of its own that holds up to MAX_SURFACES surfaces per pixel:

* a fragment (weight w, colour, opacity, depth, z-range) whose z-range overlaps a surface
  of the pixel merges into it: weights, weighted colours, weighted opacities and weighted
  depths add, the ranges unite, and surfaces that the united range now overlaps merge too;
* otherwise it starts a new surface; when all MAX_SURFACES are taken it merges into the one
  whose z-range is nearest (a documented approximation; counted in the stats);
* resolve: surfaces front to back by their mean depth, each with colour sum(wc)/sum(w) and
  alpha min(1, sum(w)) x sum(w alpha)/sum(w), composited with "over", background last.

Fragments reach a pixel in splat-index order whatever the thread count, so the image does
not depend on the number of threads.
"""

import math

import numba
import numpy as np

from ..splat.ewa import row_pixel_range, row_start
from ..splat.project import (ALPHA, AMP, BLUE, C11, C12, C22, DEPTH, GREEN, MX, MY, RED, X0,
                             X1, ZHI, ZLO)

TILE = 16
MAX_SURFACES = 8
# per-surface accumulators in the tile A-buffer
S_W, S_WR, S_WG, S_WB, S_WA, S_WD, S_ZLO, S_ZHI = range(8)
N_ACC = 8


@numba.njit(cache=True, nogil=True)
def tile_rows_pairs(bbox, visible, tile, n_ty):
    """Tile-splat pairs per tile row, (n_ty,) int64: to cut the image into memory-bounded bands."""
    per_row = np.zeros(n_ty, np.int64)
    for k in range(bbox.shape[0]):
        if visible[k]:
            nx = bbox[k, 1] // tile - bbox[k, 0] // tile + 1
            for ty in range(bbox[k, 2] // tile, bbox[k, 3] // tile + 1):
                per_row[ty] += nx
    return per_row


@numba.njit(cache=True, nogil=True)
def bin_splats(bbox, visible, tile, n_tx, ty0, ty1):
    """Counting sort of tile-splat pairs for tile rows ty0..ty1-1.

    Returns (offsets, ids): the splats of local tile t = (ty - ty0) * n_tx + tx are
    ids[offsets[t]:offsets[t+1]], in increasing splat index.
    """
    n_tiles = (ty1 - ty0) * n_tx
    counts = np.zeros(n_tiles + 1, np.int64)
    for k in range(bbox.shape[0]):
        if not visible[k]:
            continue
        a, b = max(bbox[k, 2] // tile, ty0), min(bbox[k, 3] // tile, ty1 - 1)
        for ty in range(a, b + 1):
            for tx in range(bbox[k, 0] // tile, bbox[k, 1] // tile + 1):
                counts[(ty - ty0) * n_tx + tx + 1] += 1
    offsets = np.cumsum(counts)
    cursor = offsets[:-1].copy()
    ids = np.empty(offsets[-1], np.int32)
    for k in range(bbox.shape[0]):
        if not visible[k]:
            continue
        a, b = max(bbox[k, 2] // tile, ty0), min(bbox[k, 3] // tile, ty1 - 1)
        for ty in range(a, b + 1):
            for tx in range(bbox[k, 0] // tile, bbox[k, 1] // tile + 1):
                t = (ty - ty0) * n_tx + tx
                ids[cursor[t]] = k
                cursor[t] += 1
    return offsets, ids


@numba.njit(cache=True, nogil=True, inline="always")
def _merge_into(acc, cnt, p, i, j):
    """Merge surface j of pixel p into surface i, then delete j (the last one takes its slot)."""
    for f in range(S_ZLO):
        acc[p, i, f] += acc[p, j, f]
    acc[p, i, S_ZLO] = min(acc[p, i, S_ZLO], acc[p, j, S_ZLO])
    acc[p, i, S_ZHI] = max(acc[p, i, S_ZHI], acc[p, j, S_ZHI])
    last = cnt[p] - 1
    if j != last:
        for f in range(N_ACC):
            acc[p, j, f] = acc[p, last, f]
    cnt[p] = last


# inlined at numba's level: it halves the rasteriser's time (bench/RESULTS.md)
@numba.njit(cache=True, nogil=True, inline="always")
def insert_fragment(acc, cnt, p, w, r, g, b, a, d, zlo, zhi):
    """Insert one fragment into pixel p's surfaces. Returns 1 if it overflowed, else 0."""
    n = cnt[p]
    hit = -1
    for i in range(n):
        if zlo <= acc[p, i, S_ZHI] and zhi >= acc[p, i, S_ZLO]:
            hit = i
            break
    overflow = 0
    if hit < 0 and n == acc.shape[1]:
        # A-buffer full: merge into the surface whose z-range is nearest (slot 0 if no gap
        # compares, e.g. a NaN range: never write past the last slot)
        best = 1e300
        hit = 0
        for i in range(n):
            gap = max(acc[p, i, S_ZLO] - zhi, zlo - acc[p, i, S_ZHI])
            if gap < best:
                best = gap
                hit = i
        overflow = 1
    if hit < 0:
        acc[p, n, S_W] = w
        acc[p, n, S_WR] = w * r
        acc[p, n, S_WG] = w * g
        acc[p, n, S_WB] = w * b
        acc[p, n, S_WA] = w * a
        acc[p, n, S_WD] = w * d
        acc[p, n, S_ZLO] = zlo
        acc[p, n, S_ZHI] = zhi
        cnt[p] = n + 1
        return overflow
    acc[p, hit, S_W] += w
    acc[p, hit, S_WR] += w * r
    acc[p, hit, S_WG] += w * g
    acc[p, hit, S_WB] += w * b
    acc[p, hit, S_WA] += w * a
    acc[p, hit, S_WD] += w * d
    acc[p, hit, S_ZLO] = min(acc[p, hit, S_ZLO], zlo)
    acc[p, hit, S_ZHI] = max(acc[p, hit, S_ZHI], zhi)
    # the united range may now reach other surfaces: they are the same surface
    j = 0
    while j < cnt[p]:
        if j != hit and acc[p, j, S_ZLO] <= acc[p, hit, S_ZHI] and acc[p, j, S_ZHI] >= acc[p, hit, S_ZLO]:
            last = cnt[p] - 1
            _merge_into(acc, cnt, p, hit, j)
            if hit == last:  # the merged-into surface moved into slot j
                hit = j
            j = 0
            continue
        j += 1
    return overflow


@numba.njit(cache=True, nogil=True, inline="always")
def resolve_to_image(acc, cnt, p, bg_r, bg_g, bg_b, res, order, scratch, image, depth, weight,
                     i, j):
    """Resolve pixel p's surfaces (``resolve_pixel``) into image pixel (i, j) and its buffers."""
    resolve_pixel(acc, cnt, p, bg_r, bg_g, bg_b, res, order, scratch)
    image[i, j, 0] = res[0]
    image[i, j, 1] = res[1]
    image[i, j, 2] = res[2]
    image[i, j, 3] = res[3]
    depth[i, j] = res[4]
    weight[i, j] = res[5]


@numba.njit(cache=True, nogil=True)
def resolve_pixel(acc, cnt, p, bg_r, bg_g, bg_b, out, order, depth):
    """Composite pixel p's surfaces front to back over the background.

    out: (7,) receives r, g, b, alpha, depth of the surface that contributes most
    (inf if none), accumulated weight of the nearest surface, number of surfaces;
    order, depth: (MAX_SURFACES,) scratch space.
    """
    n = cnt[p]
    for i in range(n):  # insertion sort by mean depth, ties by slot
        d = acc[p, i, S_WD] / acc[p, i, S_W] if acc[p, i, S_W] > 0 else 0.5 * (acc[p, i, S_ZLO] + acc[p, i, S_ZHI])
        m = i
        while m > 0 and depth[m - 1] > d:
            depth[m] = depth[m - 1]
            order[m] = order[m - 1]
            m -= 1
        depth[m] = d
        order[m] = i
    trans = 1.0
    cr = cg = cb = 0.0
    best = 0.0
    best_depth = np.inf
    for m in range(n):
        i = order[m]
        w = acc[p, i, S_W]
        if w <= 0.0:
            continue
        alpha = min(1.0, w) * acc[p, i, S_WA] / w
        contrib = trans * alpha
        cr += contrib * acc[p, i, S_WR] / w
        cg += contrib * acc[p, i, S_WG] / w
        cb += contrib * acc[p, i, S_WB] / w
        if contrib > best:
            best = contrib
            best_depth = depth[m]
        trans *= 1.0 - alpha
    out[0] = cr + trans * bg_r
    out[1] = cg + trans * bg_g
    out[2] = cb + trans * bg_b
    out[3] = 1.0 - trans
    out[4] = best_depth
    out[5] = acc[p, order[0], S_W] if n > 0 else 0.0
    out[6] = n


@numba.njit(cache=True, nogil=True, parallel=True)
def rasterize_band(splats, bbox, offsets, ids, n_tx, ty0, width, height, cutoff,
                   background, image, depth, weight, tile_stats):
    """Rasterise and resolve the tiles of one band (tile rows ty0..) into the output images.

    image: (H, W, 4) float32; depth, weight: (H, W) float32; tile_stats: (n_tiles, 2) int64
    receives fragments generated and A-buffer overflows per tile.
    """
    n_tiles = offsets.shape[0] - 1
    bg_r, bg_g, bg_b = background[0], background[1], background[2]
    for t in numba.prange(n_tiles):
        ty = ty0 + t // n_tx
        tx = t % n_tx
        px0, py0 = tx * TILE, ty * TILE
        px1, py1 = min(px0 + TILE, width) - 1, min(py0 + TILE, height) - 1
        acc = np.empty((TILE * TILE, MAX_SURFACES, N_ACC), np.float64)
        cnt = np.zeros(TILE * TILE, np.int64)
        frags = 0
        overflows = 0
        for e in range(offsets[t], offsets[t + 1]):
            k = ids[e]
            mx, my = splats[k, MX], splats[k, MY]
            c11, c12, c22 = splats[k, C11], splats[k, C12], splats[k, C22]
            amp = splats[k, AMP]
            r, g, b, a = splats[k, RED], splats[k, GREEN], splats[k, BLUE], splats[k, ALPHA]
            d, zlo, zhi = splats[k, DEPTH], splats[k, ZLO], splats[k, ZHI]
            x0, x1 = int(splats[k, X0]), int(splats[k, X1])
            step2 = math.exp(-c11)
            for i in range(max(bbox[k, 2], py0), min(bbox[k, 3], py1) + 1):
                j0, j1 = row_pixel_range(i, mx, my, c11, c12, c22, cutoff, x0, x1)
                ja, jb = max(j0, px0), min(j1, px1)
                if ja > jb:
                    continue
                # exponent and kernel value by forward differences along the row (ewa.row_start)
                q, dq, e, f = row_start(ja, i, mx, my, c11, c12, c22)
                p = (i - py0) * TILE + (ja - px0)
                for _ in range(ja, jb + 1):
                    if q < cutoff:
                        overflows += insert_fragment(acc, cnt, p, amp * e, r, g, b, a, d, zlo, zhi)
                        frags += 1
                    q += dq
                    dq += c11
                    e *= f
                    f *= step2
                    p += 1
        res = np.empty(7, np.float64)
        order = np.empty(MAX_SURFACES, np.int64)
        depth_scratch = np.empty(MAX_SURFACES, np.float64)
        for i in range(py0, py1 + 1):
            for j in range(px0, px1 + 1):
                p = (i - py0) * TILE + (j - px0)
                resolve_to_image(acc, cnt, p, bg_r, bg_g, bg_b, res, order, depth_scratch,
                                 image, depth, weight, i, j)
        tile_stats[t, 0] = frags
        tile_stats[t, 1] = overflows
