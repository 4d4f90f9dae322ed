"""Tile-based A-buffer rasterisation of splats (paper Section 6.4), numba kernels.

The image is cut into TILE x TILE pixel tiles. Splats are binned to the tiles their
bounding box touches (one int32 per tile-splat pair, never one entry per fragment), each
tile's list in increasing splat index. Each tile is then rasterised by one thread into a
small A-buffer of its own that holds up to MAX_SURFACES surfaces per pixel:

* a fragment (weight w, colour, opacity, depth, z-range) whose z-range overlaps a surface
  of the pixel merges into it: weights, weighted colours, weighted opacities, weighted
  depths and the weights of opaque fragments add, the ranges unite, and surfaces that the
  united range now overlaps merge too;
* otherwise it starts a new surface; when all MAX_SURFACES are taken it merges into the one
  whose z-range is nearest (a documented approximation; counted in the stats);
* resolve: surfaces front to back by their mean depth, each with colour sum(wc)/sum(w) and
  alpha min(1, sum(w)) x sum(w alpha)/sum(w), at least the coverage of its opaque
  fragments: min(1, their sum of weights), reaching 1 from a sum of COVER_FULL where the
  surface is sharp (``layer_alpha``), composited with "over", background last.

Fragments reach a pixel in splat-index order whatever the thread count, so the image does
not depend on the number of threads.
"""

import math

from ..jit import numba
import numpy as np

from ..parallel import weyl_stride
from ..splat.bokeh import ROW, aperture_rows, aperture_value, support_conic, table_lerp
from ..splat.ewa import (NARROW_BBOX, NARROW_ROWS, coc_radius_px, column_start, column_step,
                         exponent, pixel_bbox, row_pixel_range, row_span, row_start)
from ..splat.project import (ALPHA, AMP, BLUE, BX, BY, C11, C12, C22, COC, DEPTH, F11, F12, F22,
                             FLOOR, GREEN, GX, GY, GZX, GZY, MIX, MX, MY, RAD, RED, RX, RY, X0,
                             X1, ZHI, ZLO)

TILE = ROW  # 16: the aperture kernel's SIMD rows (splat/bokeh.py) are a tile wide
MAX_SURFACES = 8
# per-surface accumulators in the tile A-buffer
S_W, S_WR, S_WG, S_WB, S_WA, S_WD, S_WO, S_ZLO, S_ZHI = range(9)
N_ACC = 9
# scratch floats that resolve_pixel needs: sort keys, merge fractions, the composite table
RESOLVE_SCRATCH = MAX_SURFACES + MAX_SURFACES + 4 * (MAX_SURFACES + 1)
# items (of 4 or 8 bytes) between two threads' rows of rasterize_band's small buffers: at
# least a 64-byte cache line, so that no line is written by two threads
LINE_PAD = 16

# The front pass: splats at least this opaque hide what lies behind them, over their
# unblurred disk (1/2 x^T F^-1 x < FRONT_CUTOFF: the disk radius is the basis's 2 sigma)
OPAQUE = 0.95
FRONT_CUTOFF = 2.0
FRONT_FIELDS = 3  # the front map's floats per pixel (front_fragments)
# ... over the image and this many pixels round it: the disks of splats just beyond the
# image's edge, whose blur reaches into it, hide or reveal what lies behind them there
# (``front_read``; docs/maths.md, "Beyond the image's edge")
FRONT_MARGIN = 128
# A sharp opaque surface's weights sum to 1 only on average: the sum of its splats' kernels
# ripples by a few per cent between them (down to 0.92 over the magnified floor of the
# fidelity suite's pinhole frames), and min(1, w) would let what lies behind show through
# that much. A sharp surface's opaque weights w_o cover the pixel from COVER_FULL up,
# rising linearly from w_o at COVER_KNEE (a rim's share of the pixel below it is kept);
# the rule fades out as the surface's CoC at its mean depth grows from COVER_SHARP_PX to
# twice that, where blurred kernels overlap enough to sum to 1 and a blurred rim's weights
# are the share of the lens that sees it (``layer_alpha``, ``sharpness``; docs/maths.md,
# "a sharp surface covers its pixel")
COVER_FULL = 0.9
COVER_KNEE = 0.85
COVER_SHARP_PX = 1.0
# A blurred surface's kernels sum to 1 within a few thousandths when they are surfels, but an
# LOD cut's nodes (irregular, each one Gaussian for many surfels) ripple by up to 2-4 % (the
# fidelity suite's crossing planes: weights 0.97-1.02 inside the front plane at a 40 px CoC,
# a development measurement), and what lies behind showed through as speckle. A blurred surface covers its pixel from
# BLUR_COVER_FULL, rising from w_o at BLUR_COVER_KNEE: a blurred rim's share of the lens is
# kept below the knee, and changed by at most 1 - BLUR_COVER_KNEE above it (docs/maths.md,
# "A blurred surface covers its pixel too")
BLUR_COVER_KNEE = 0.95
BLUR_COVER_FULL = 0.98
# the merge band: two surfaces whose parallax ratio rho = (Delta + 1 px) / max(C_r) is below
# MERGE_RHO0 merge, above MERGE_RHO1 stay separate, smoothly in between (docs/maths.md)
MERGE_RHO0 = 0.15
MERGE_RHO1 = 0.5
# the sample points of a splat's visibility: its centre and 8 points on its 1-sigma ellipse
VIS_SAMPLES = 9
# a splat hidden at all of them is looked at from LENS_POINTS points of the lens per sample
# point, on a ring at LENS_RING of the aperture's radius and LENS_MARGIN px more (the front
# pass's disks end where their kernels' tails do not; turned from one sample point to the
# next), and removed as the share of those looks that find it hidden rises from
# HIDDEN_H0 to 1 (docs/maths.md, "Hidden from the whole lens")
LENS_POINTS = 4
LENS_RING = 1.0
LENS_MARGIN = 2.0
HIDDEN_H0 = 0.9
# their unit directions, tabulated (the sines and cosines, 52 for a hidden splat, cost more
# than the rest of the visibility pass): RING[s] for sample point s (row 0, the centre,
# unused), LOOK[s * LENS_POINTS + l] for look l from it; the same angles as the slow twin's
RING = np.array([(0.0, 0.0)] + [(math.cos(a), math.sin(a)) for a in
                                (s * (2.0 * math.pi / (VIS_SAMPLES - 1))
                                 for s in range(VIS_SAMPLES - 1))])
LOOK = np.array([(math.cos(a), math.sin(a)) for a in
                 ((l + s / VIS_SAMPLES) * (2.0 * math.pi / LENS_POINTS)
                  for s in range(VIS_SAMPLES) for l in range(LENS_POINTS))])
# ... if its blurred fragments' z-ranges reach the nearest front's: each surface's depths
# over MERGE_REACH x (its CoC + 1 px) (the A-buffer's united ranges reach beyond one CoC,
# merge after merge: 3 kept 60 % of `intersect`'s gain, 12 no more than 6; docs/maths.md)
MERGE_REACH = 6.0


# bin_splats cuts the splats into at most this many runs of at least BIN_RUN splats, binned
# in parallel: a fixed cut, so the ids do not depend on the thread count
BIN_RUNS = 64
BIN_RUN = 16384
NO_COLUMN = (0.0,) * 8  # a wide kernel's rows start afresh (ewa.column_start's place)
# the coarse samples (``rasterize_band``'s coarse): every second pixel of a tile, and the
# next tiles' first row and column
SAMPLES = TILE // 2 + 1


@numba.njit(cache=True, nogil=True, parallel=True)
def tile_rows_pairs(bbox, visible, n_ty):
    """Tile-splat pairs per tile row, (n_ty,) int64: to cut the image into memory-bounded
    bands. Counted in bin_splats' runs, in parallel (serial, it was 2 ms of the demo's
    75 ms pinhole frame on two threads), and summed."""
    n = bbox.shape[0]
    runs = min(max(n // BIN_RUN, 1), BIN_RUNS)
    counts = np.zeros((runs, n_ty), np.int64)
    for c in numba.prange(runs):
        for k in range(c * n // runs, (c + 1) * n // runs):
            if visible[k]:
                nx = bbox[k, 1] // TILE - bbox[k, 0] // TILE + 1
                for ty in range(bbox[k, 2] // TILE, bbox[k, 3] // TILE + 1):
                    counts[c, ty] += nx
    per_row = np.zeros(n_ty, np.int64)
    for c in range(runs):
        for ty in range(n_ty):
            per_row[ty] += counts[c, ty]
    return per_row


@numba.njit(cache=True, nogil=True)
def keep_tile_lists(offsets, ids, keep):
    """(offsets, ids) of ``bin_splats`` with the lists of the tiles not in ``keep`` ((n_tiles,)
    bool, the band's tiles in the lists' order) emptied: those tiles rasterise nothing."""
    n_tiles = offsets.shape[0] - 1
    out_offsets = np.zeros(n_tiles + 1, offsets.dtype)
    for t in range(n_tiles):
        n = offsets[t + 1] - offsets[t] if keep[t] else 0
        out_offsets[t + 1] = out_offsets[t] + n
    out_ids = np.empty(out_offsets[n_tiles], ids.dtype)
    for t in range(n_tiles):
        if keep[t]:
            out_ids[out_offsets[t]:out_offsets[t + 1]] = ids[offsets[t]:offsets[t + 1]]
    return out_offsets, out_ids


@numba.njit(cache=True, nogil=True, parallel=True)
def widen_boxes(splats, bbox, visible, coarse):
    """The boxes of the splats ``rasterize_band`` samples coarsely (aperture radius at least
    coarse pixels) a pixel further up and left, so that a tile's list holds the splats of its
    last sample row and column (the next tiles' first pixels)."""
    for k in numba.prange(bbox.shape[0]):
        widen_box(splats, bbox, visible, k, coarse)


@numba.njit(cache=True, nogil=True, inline="always")
def widen_box(splats, bbox, visible, k, coarse):
    """``widen_boxes`` for splat k."""
    if visible[k] and bbox[k, 0] <= bbox[k, 1] and abs(splats[k, RAD]) >= coarse:
        bbox[k, 0] = max(bbox[k, 0] - 1, 0)
        bbox[k, 2] = max(bbox[k, 2] - 1, 0)


@numba.njit(cache=True, nogil=True, parallel=True)
def keep_tiles(bbox, visible, tiles):
    """Drop (visible[k] = False) the splats whose box reaches no tile of ``tiles`` ((n_ty,
    n_tx) bool, TILE x TILE pixels each): a frame drawn on those tiles only."""
    n_ty, n_tx = tiles.shape
    for k in numba.prange(visible.shape[0]):
        if not visible[k]:
            continue
        hit = False
        for ty in range(max(bbox[k, 2] // TILE, 0), min(bbox[k, 3] // TILE, n_ty - 1) + 1):
            for tx in range(max(bbox[k, 0] // TILE, 0), min(bbox[k, 1] // TILE, n_tx - 1) + 1):
                if tiles[ty, tx]:
                    hit = True
                    break
            if hit:
                break
        visible[k] = hit


@numba.njit(cache=True, nogil=True, parallel=True)
def bin_splats(bbox, visible, n_tx, ty0, ty1):
    """Counting sort of tile-splat pairs (tiles of TILE x TILE pixels) for tile rows
    ty0..ty1-1. TILE is a constant of the compiled code, not an argument: a division by
    it is a shift, and a division by an argument cost this pass and tile_rows_pairs 1.6 x
    the time (the pinhole plane's 2.75 against 1.70 ms, bench/RESULTS.md).

    Returns (offsets, ids): the splats of local tile t = (ty - ty0) * n_tx + tx are
    ids[offsets[t]:offsets[t+1]], in increasing splat index. The splats are cut into runs,
    each counted and scattered by one thread; run c's splats of a tile follow those of runs
    before it.
    """
    n_tiles = (ty1 - ty0) * n_tx
    runs = min(max(bbox.shape[0] // BIN_RUN, 1), BIN_RUNS)
    counts = np.zeros((runs, n_tiles), np.int64)
    ids = np.empty(0, np.int32)
    for c in numba.prange(runs):
        bin_run(c, runs, bbox, visible, n_tx, ty0, ty1, counts, ids, False)
    # each run's first slot in each tile (counts becomes the cursors)
    offsets = np.empty(n_tiles + 1, np.int64)
    total = 0
    for t in range(n_tiles):
        offsets[t] = total
        for c in range(runs):
            m = counts[c, t]
            counts[c, t] = total
            total += m
    offsets[n_tiles] = total
    ids = np.empty(total, np.int32)
    for c in numba.prange(runs):
        bin_run(c, runs, bbox, visible, n_tx, ty0, ty1, counts, ids, True)
    return offsets, ids


@numba.njit(cache=True, nogil=True, inline="always")
def bin_run(c, runs, bbox, visible, n_tx, ty0, ty1, counts, ids, scatter):
    """Run c of ``bin_splats``: its splats' tile-splat pairs counted into counts[c], or with
    ``scatter`` written to ids at the cursors counts[c] (which advance)."""
    n = bbox.shape[0]
    for k in range(c * n // runs, (c + 1) * n // runs):
        if not visible[k]:
            continue
        a, b = max(bbox[k, 2] // TILE, ty0), min(bbox[k, 3] // TILE, ty1 - 1)
        for ty in range(a, b + 1):
            for tx in range(bbox[k, 0] // TILE, bbox[k, 1] // TILE + 1):
                t = (ty - ty0) * n_tx + tx
                if scatter:
                    ids[counts[c, t]] = k
                counts[c, t] += 1


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
    hit, overflow = _surface_for(acc, cnt, p, zlo, zhi)
    if hit < 0:
        acc[p, n, S_W] = w
        acc[p, n, S_WR] = w * r
        acc[p, n, S_WG] = w * g
        acc[p, n, S_WB] = w * b
        acc[p, n, S_WA] = w * a
        acc[p, n, S_WD] = w * d
        acc[p, n, S_WO] = w if a >= OPAQUE else 0.0
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
    if a >= OPAQUE:
        acc[p, hit, S_WO] += w
    _unite(acc, cnt, p, hit, n, zlo, zhi)
    return overflow


@numba.njit(cache=True, nogil=True, inline="always")
def insert_surface(acc, cnt, p, src, s, q, scale):
    """Insert surface q of sample s of ``src`` (the A-buffer of a tile's coarse samples), its
    weights times scale, into pixel p's surfaces, as ``insert_fragment`` inserts a
    fragment. Returns 1 if it overflowed, else 0."""
    zlo, zhi = src[s, q, S_ZLO], src[s, q, S_ZHI]
    n = cnt[p]
    hit, overflow = _surface_for(acc, cnt, p, zlo, zhi)
    if hit < 0:
        for f in range(S_ZLO):
            acc[p, n, f] = scale * src[s, q, f]
        acc[p, n, S_ZLO] = zlo
        acc[p, n, S_ZHI] = zhi
        cnt[p] = n + 1
        return overflow
    for f in range(S_ZLO):
        acc[p, hit, f] += scale * src[s, q, f]
    _unite(acc, cnt, p, hit, n, zlo, zhi)
    return overflow


@numba.njit(cache=True, nogil=True, inline="always")
def _surface_for(acc, cnt, p, zlo, zhi):
    """The surface of pixel p that a z-range joins: (its slot, 0), the first whose range it
    overlaps, or (-1, 0) for a new one; when all MAX_SURFACES are taken, (the one whose
    z-range is nearest, 1): slot 0 if no gap compares (a NaN range: never past the last)."""
    n = cnt[p]
    for i in range(n):
        if zlo <= acc[p, i, S_ZHI] and zhi >= acc[p, i, S_ZLO]:
            return i, 0
    if n < acc.shape[1]:
        return -1, 0
    best = 1e300
    hit = 0
    for i in range(n):
        gap = max(acc[p, i, S_ZLO] - zhi, zlo - acc[p, i, S_ZHI])
        if gap < best:
            best = gap
            hit = i
    return hit, 1


@numba.njit(cache=True, nogil=True, inline="always")
def _unite(acc, cnt, p, hit, n, zlo, zhi):
    """Surface hit of pixel p (of n) took in the range [zlo, zhi]: its range becomes the union,
    and the surfaces the union now reaches merge into it (they are the same surface)."""
    lo, hi = acc[p, hit, S_ZLO], acc[p, hit, S_ZHI]
    acc[p, hit, S_ZLO] = min(lo, zlo)
    acc[p, hit, S_ZHI] = max(hi, zhi)
    if n == 1 or (zlo >= lo and zhi <= hi):
        # the pixel's only surface, or the range did not grow: the pixel's surfaces stay
        # disjoint (they always are), so nothing new can merge
        return
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


@numba.njit(cache=True, nogil=True, inline="always")
def add_samples(acc, cnt, p, sacc, scnt, u, v, rows, cols):
    """Pixel p (row u, column v of its tile) takes the coarse samples around it: the grid
    of every second pixel (``SAMPLES`` x ``SAMPLES`` a tile, its last row and column the
    next tiles' first), interpolated linearly (an even pixel is a sample, an odd one the
    mean of the two beside it); rows, cols: the sample rows and columns drawn (those of the
    image and one past its last row and column). Returns the overflows."""
    a0, b0 = u >> 1, v >> 1
    a1 = a0 + (u & 1) if a0 + (u & 1) < rows else a0
    b1 = b0 + (v & 1) if b0 + (v & 1) < cols else b0
    wa = 0.5 if a1 != a0 else 1.0
    wb = 0.5 if b1 != b0 else 1.0
    overflows = 0
    for a in range(a0, a1 + 1):
        for b in range(b0, b1 + 1):
            s = a * SAMPLES + b
            for q in range(scnt[s]):
                overflows += insert_surface(acc, cnt, p, sacc, s, q, wa * wb)
    return overflows


@numba.njit(cache=True, nogil=True, inline="always")
def sharpness(d, coc_k, inv_focus):
    """How sharp a surface at depth d is, for its coverage (``layer_alpha``): 1 up to a
    CoC radius of COVER_SHARP_PX, 0 from twice that, linear between; 1 in a pinhole frame
    (coc_k = 0); -1 in the paper's reconstruction (coc_k < 0, ``frame.merge_parameters``),
    whose coverage is the paper's min(1, w)."""
    if coc_k < 0.0:
        return -1.0
    if coc_k == 0.0 or d <= 0.0:
        return 1.0
    return min(max(2.0 - coc_radius_px(d, coc_k, inv_focus) / COVER_SHARP_PX, 0.0), 1.0)


@numba.njit(cache=True, nogil=True, inline="always")
def cover_ramp(wo, knee, full):
    """min(1, wo), but 1 from wo = full up, rising linearly from wo at the knee."""
    if wo <= knee:
        return wo
    return min(1.0, knee + (wo - knee) * ((1.0 - knee) / (full - knee)))


@numba.njit(cache=True, nogil=True, inline="always")
def layer_alpha(w, wa, wo, sharp):
    """A surface's opacity from its sums of weights w, weighted opacities wa and weights of
    opaque fragments wo, and its ``sharpness``: the paper's min(1, w) x wa / w, and at
    least the coverage of its opaque fragments (a translucent surface merged with an
    opaque one where they touch does not let the background through): min(1, wo), and
    for a sharp surface a sum from COVER_FULL up covers the pixel (its kernels' ripple),
    rising from wo at COVER_KNEE (a rim's weights below it are kept); for a blurred one
    (sharp < 1) from BLUR_COVER_FULL, rising from BLUR_COVER_KNEE (an LOD cut's ripple);
    the paper's reconstruction (sharp < 0) keeps min(1, wo)."""
    cover = min(1.0, wo)
    if 0.0 <= sharp < 1.0 and wo > BLUR_COVER_KNEE:
        cover += (1.0 - sharp) * (cover_ramp(wo, BLUR_COVER_KNEE, BLUR_COVER_FULL) - cover)
    if sharp > 0.0 and wo > COVER_KNEE:
        cover += sharp * (cover_ramp(wo, COVER_KNEE, COVER_FULL) - cover)
    return max(min(1.0, w) * wa / w, cover)


@numba.njit(cache=True, nogil=True)
def merge_fraction(d_front, d_back, opacity_front, coc_k, inv_focus, rho0, rho1):
    """How much two blurred surfaces at depths d_front < d_back are one layer, in [0, 1].

    Through the lens the two shift against each other by their parallax
    Delta = K |1/d_front - 1/d_back| pixels at most, against blurs of C_r = K |1/d - 1/P|.
    When Delta is small against the blur, every lens sample sees them as the pinhole does
    (what hides what does not change): their blurred fragments add (merge, 1). When it is
    not, the front one's blur reveals what it hides, and "over" is right (0). The ratio
    rho = (Delta + 1) / max(C_r) chooses, smoothly between rho0 and rho1; the 1 px keeps
    sharp surfaces (C_r under a pixel, a pinhole) separate, as the paper's A-buffer does.
    A translucent front is composited over what is behind it at any parallax.
    """
    if coc_k <= 0.0 or d_front <= 0.0 or d_back <= 0.0:
        return 0.0
    c = coc_k * max(abs(1.0 / d_front - inv_focus), abs(1.0 / d_back - inv_focus))
    if c <= 0.0:
        return 0.0
    rho = (coc_k * abs(1.0 / d_front - 1.0 / d_back) + 1.0) / c
    t = min(max((rho - rho0) / (rho1 - rho0), 0.0), 1.0)
    o = min(max((opacity_front - (OPAQUE - 0.05)) / 0.05, 0.0), 1.0)
    return (1.0 - t * t * (3.0 - 2.0 * t)) * o


@numba.njit(cache=True, nogil=True, inline="always")
def front_disk_box(splats, k, margin):
    """The pixel box (x0, x1, y0, y1) of splat k's unblurred disk in the front map, whose
    pixel (i, j) is the image's (i - margin, j - margin); not clipped."""
    mx, my = splats[k, MX] + margin, splats[k, MY] + margin
    # in float64: a thin disk's determinant in float32 lost its digits (or all of them)
    f11, f12, f22 = (np.float64(splats[k, F11]), np.float64(splats[k, F12]),
                     np.float64(splats[k, F22]))
    det = f11 * f22 - f12 * f12
    hx = math.sqrt(2.0 * FRONT_CUTOFF * f22 / det)  # F = inverse of the conic
    hy = math.sqrt(2.0 * FRONT_CUTOFF * f11 / det)
    # the pixel centres within hx, hy of the centre (a box rounded outwards held a row and
    # a column on each side where no centre is inside)
    return pixel_bbox(mx, my, hx, hy)


@numba.njit(cache=True, nogil=True, inline="always")
def front_fragments(splats, k, px0, px1, py0, py1, front, fw, margin):
    """Splat k's unblurred disk into the front map's pixels px0..px1 x py0..py1.

    front: (fh * fw, FRONT_FIELDS) float32, the image and ``margin`` pixels round it
    (``front_map``; map pixel (i, j) is the image's (i - margin, j - margin)): per pixel the
    least depth and the least z_hi of the opaque disks covering it, and the nearest disk's
    z_hi + MERGE_REACH |g| (C_r + 1 px) (how far back the A-buffer's united z-ranges of its
    blurred fragments reach, g its depth change per pixel).
    """
    mx, my = splats[k, MX] + margin, splats[k, MY] + margin
    f11, f12, f22 = splats[k, F11], splats[k, F12], splats[k, F22]
    x0, x1, y0, y1 = front_disk_box(splats, k, margin)
    x0, x1 = max(x0, px0), min(x1, px1)
    y0, y1 = max(y0, py0), min(y1, py1)
    d, zhi = splats[k, DEPTH], splats[k, ZHI]
    gx, gy = splats[k, GZX], splats[k, GZY]
    reach = zhi + MERGE_REACH * math.sqrt(gx * gx + gy * gy) * (splats[k, COC] + 1.0)
    for i in range(y0, y1 + 1):
        for j in range(x0, x1 + 1):
            if exponent(j + 0.5 - mx, i + 0.5 - my, f11, f12, f22) < FRONT_CUTOFF:
                p = i * fw + j
                if d < front[p, 0]:
                    front[p, 0] = d
                    front[p, 2] = reach
                if zhi < front[p, 1]:
                    front[p, 1] = zhi


@numba.njit(cache=True, nogil=True, inline="always")
def front_box(splats, visible, k, fw, fh, margin, box, use):
    """Splat k's box in the front map (``front_disk_box``, clipped to the fw x fh map) into
    box[k], and use[k]: whether it draws a disk (visible, opaque, at a finite point, on the
    map). Shared with the CUDA backend, one thread per splat."""
    use[k] = False
    if visible[k] and splats[k, ALPHA] >= OPAQUE and math.isfinite(splats[k, MX]) \
            and math.isfinite(splats[k, MY]):
        x0, x1, y0, y1 = front_disk_box(splats, k, margin)
        x0, x1, y0, y1 = max(x0, 0), min(x1, fw - 1), max(y0, 0), min(y1, fh - 1)
        if x0 <= x1 and y0 <= y1:
            box[k, 0], box[k, 1], box[k, 2], box[k, 3] = x0, x1, y0, y1
            use[k] = True


@numba.njit(cache=True, nogil=True, parallel=True)
def front_boxes(splats, visible, fw, fh, margin, box, use):
    """``front_box`` of every splat: box (N, 4) int32 and use (N,) bool."""
    for k in numba.prange(splats.shape[0]):
        front_box(splats, visible, k, fw, fh, margin, box, use)


@numba.njit(cache=True, nogil=True, inline="always")
def spread_tile(u, n_tx, n_rows, stride):
    """The tile that a band's pass visits u-th (of n_rows x n_tx): the rows in a Weyl order
    (stride = ``weyl_stride(n_rows)``; dofsplat/parallel.py), so that every thread gets rows
    from the whole band, and each row's tiles in order (they share splats)."""
    return ((u // n_tx) * stride) % n_rows * n_tx + u % n_tx


@numba.njit(cache=True, nogil=True, parallel=True)
def front_band(splats, offsets, ids, n_tx, fw, fh, margin, front):
    """The front pass over the front map's tiles (``bin_splats`` of ``front_boxes``):
    opaque unblurred disks into ``front``."""
    n_tiles = offsets.shape[0] - 1
    n_rows = n_tiles // n_tx
    stride = weyl_stride(n_rows)
    for u in numba.prange(n_tiles):
        t = spread_tile(u, n_tx, n_rows, stride)
        px0, py0 = (t % n_tx) * TILE, (t // n_tx) * TILE
        px1, py1 = min(px0 + TILE, fw) - 1, min(py0 + TILE, fh) - 1
        for e in range(offsets[t], offsets[t + 1]):
            front_fragments(splats, ids[e], px0, px1, py0, py1, front, fw, margin)


@numba.njit(cache=True, nogil=True, inline="always")
def disk_point(s, l11, l21, l22):
    """Sample point s of a splat's visibility, as an offset from its centre: 0 the centre,
    1..VIS_SAMPLES - 1 evenly round its 1-sigma ellipse x = L u (F = L L^T, L lower
    triangular with entries l11, l21, l22)."""
    if s == 0:
        return 0.0, 0.0
    ux, uy = RING[s, 0], RING[s, 1]
    return l11 * ux, l21 * ux + l22 * uy


@numba.njit(cache=True, nogil=True, inline="always")
def front_read(x, y, front, fw, fh, margin):
    """Where the front map is read for a point (x, y) of the image plane: the map's pixel
    under it, if the map has one there and, beyond the image's edge, a disk covers it; else
    the centre of the nearest edge pixel of the image (the front is taken to go on as it
    is there: the margin holds only the disks of splats whose blur reaches into the image).
    Returns the map's pixel index and the shift (ex, ey) from the point to where it is
    read, (0, 0) where the point itself is read. (x, y) must be finite."""
    width, height = fw - 2 * margin, fh - 2 * margin
    cx, cy = x, y
    if x < 0.0:
        cx = 0.5
    elif x >= width:
        cx = width - 0.5
    if y < 0.0:
        cy = 0.5
    elif y >= height:
        cy = height - 0.5
    if cx != x or cy != y:  # beyond the image's edge: the margin, where a disk covers it
        j, i = int(math.floor(x)) + margin, int(math.floor(y)) + margin
        if 0 <= j < fw and 0 <= i < fh and front[i * fw + j, 0] < math.inf:
            return i * fw + j, 0.0, 0.0
    return (int(math.floor(cy)) + margin) * fw + int(math.floor(cx)) + margin, cx - x, cy - y


@numba.njit(cache=True, nogil=True, inline="always")
def front_at(x, y, front, fw, fh, margin, inside):
    """``front_read`` for a point that ``inside`` says lies within the image (its own pixel,
    no shift: the common case, without the tests), else ``front_read`` itself."""
    if inside:
        return (int(y) + margin) * fw + int(x) + margin, 0.0, 0.0
    return front_read(x, y, front, fw, fh, margin)


@numba.njit(cache=True, nogil=True, inline="always")
def within(x, y, rx, ry, width, height):
    """Whether the box x +- rx, y +- ry lies inside the image, half a pixel in from its
    edge (so that rounding cannot carry a point of it out)."""
    return x - rx > 0.5 and x + rx < width - 0.5 and y - ry > 0.5 and y + ry < height - 0.5


@numba.njit(cache=True, nogil=True)
def splat_visibility(splats, k, front, fw, fh, margin, coc_k, inv_focus, rho0, rho1):
    """The share of splat k that survives the front pass, in [0, 1] (docs/maths.md).

    At each of VIS_SAMPLES points of its unblurred disk (the centre, 8 points on the
    1-sigma ellipse), a splat is hidden if its z-range, widened by its depth change over
    the 0.75 px to the pixel centre, begins behind the z-range of the front there; hidden
    by a front of merge fraction m (same layer through the lens), its blur would add to the
    front's where every lens sample sees the front: it is removed by m. Hidden by a front
    far from it in parallax, it stays, and the A-buffer lets the front's blurred rim show
    it (partial occlusion) -- unless the front hides it from the whole lens: hidden at all
    of its points, it is looked at from LENS_POINTS points of the lens per point (the front
    seen from lens point u lies Delta u pixels away, Delta = K (1/U_front - 1/U) its
    parallax), and the share h of those looks that find it hidden removes it by
    smoothstep((h - HIDDEN_H0) / (1 - HIDDEN_H0)).
    """
    mx, my = splats[k, MX], splats[k, MY]
    if not (math.isfinite(mx) and math.isfinite(my)):
        return 1.0  # nowhere to look (the front map is read at finite points only)
    f11, f12, f22 = splats[k, F11], splats[k, F12], splats[k, F22]
    det = f11 * f22 - f12 * f12
    # F (the variance) = L L^T: x = L u for u on the unit circle is the 1-sigma ellipse
    v11, v12, v22 = f22 / det, -f12 / det, f11 / det
    l11 = math.sqrt(v11)
    l21 = v12 / l11
    l22 = math.sqrt(max(v22 - l21 * l21, 0.0))
    # the front is sampled at pixel centres up to ~0.7 px from the sample point: allow the
    # splat's own surface to move that much in depth
    gx, gy = splats[k, GZX], splats[k, GZY]
    grad = math.sqrt(gx * gx + gy * gy)
    zlo, depth = splats[k, ZLO] - 0.75 * grad, splats[k, DEPTH]
    width, height = fw - 2 * margin, fh - 2 * margin
    # the disk's points lie within sqrt(v11), sqrt(v22) of its centre
    inside = within(mx, my, math.sqrt(v11), math.sqrt(v22), width, height)
    removed = 0.0
    hidden = 0
    for s in range(VIS_SAMPLES):
        dx, dy = disk_point(s, l11, l21, l22)
        # a point beyond the image's edge (a splat whose blur reaches into the frame) reads
        # the front map's margin, or the front at the edge with its own depth carried there
        # along its tangent plane
        p, ex, ey = front_at(mx + dx, my + dy, front, fw, fh, margin, inside)
        if zlo + gx * ex + gy * ey > front[p, 1]:
            hidden += 1
            removed += merge_fraction(front[p, 0], depth, 1.0, coc_k, inv_focus, rho0, rho1)
    removed /= VIS_SAMPLES
    if hidden < VIS_SAMPLES or removed >= 1.0 or grad >= 1e29:
        return 1.0 - removed
    # only a splat whose blurred fragments' z-ranges reach those of the front's (the
    # A-buffer unites the z-ranges of the fragments a blur brings to a pixel, which span a
    # surface's depths over its CoC and, merge after merge, beyond): they would merge with
    # the front's. Behind a front they cannot reach, "over" hides it as it should, unless
    # the resolve merges it into the front: with a merge share (removed > 0) it is looked at
    p, ex, ey = front_at(mx, my, front, fw, fh, margin, inside)
    if removed == 0.0 and \
            zlo + gx * ex + gy * ey - MERGE_REACH * grad * (splats[k, COC] + 1.0) > front[p, 2]:
        return 1.0
    # hidden where the pinhole looks: is it hidden from the whole lens? Its own surface,
    # extended along its tangent plane, must not hide it (a convex surface curves away
    # from its tangent plane, behind it)
    looks = 0
    seen = 0
    for s in range(VIS_SAMPLES):
        dx, dy = disk_point(s, l11, l21, l22)
        p, ex, ey = front_at(mx + dx, my + dy, front, fw, fh, margin, inside)
        parallax = LENS_RING * coc_k * abs(1.0 / front[p, 0] - 1.0 / depth) + LENS_MARGIN
        ring_inside = within(mx + dx, my + dy, parallax, parallax, width, height)
        for l in range(LENS_POINTS):
            ox = parallax * LOOK[s * LENS_POINTS + l, 0]
            oy = parallax * LOOK[s * LENS_POINTS + l, 1]
            p, ex, ey = front_at(mx + dx + ox, my + dy + oy, front, fw, fh, margin, ring_inside)
            looks += 1
            if zlo + gx * (ox + ex) + gy * (oy + ey) <= front[p, 1]:
                seen += 1
    h = 1.0 - seen / looks
    t = min(max((h - HIDDEN_H0) / (1.0 - HIDDEN_H0), 0.0), 1.0)
    return 1.0 - max(removed, t * t * (3.0 - 2.0 * t))


@numba.njit(cache=True, nogil=True, parallel=True)
def apply_visibility(splats, visible, front, fw, fh, margin, coc_k, inv_focus, rho0, rho1):
    """Scale every visible splat's amplitude by its ``splat_visibility`` (0: the rasteriser
    skips it)."""
    for k in numba.prange(splats.shape[0]):
        if visible[k]:
            v = splat_visibility(splats, k, front, fw, fh, margin, coc_k, inv_focus, rho0,
                                 rho1)
            splats[k, AMP] *= v


@numba.njit(cache=True, nogil=True, inline="always")
def resolve_to_image(acc, cnt, p, bg_r, bg_g, bg_b, res, order, scratch, image, depth, weight,
                     i, j, coc_k, inv_focus, rho0, rho1):
    """Resolve pixel p's surfaces (``resolve_pixel``) into image pixel (i, j) and its buffers."""
    resolve_pixel(acc, cnt, p, bg_r, bg_g, bg_b, res, order, scratch, coc_k, inv_focus, rho0,
                  rho1)
    image[i, j, 0] = res[0]
    image[i, j, 1] = res[1]
    image[i, j, 2] = res[2]
    image[i, j, 3] = res[3]
    depth[i, j] = res[4]
    weight[i, j] = res[5]


@numba.njit(cache=True, nogil=True, inline="always")
def resolve_pixel(acc, cnt, p, bg_r, bg_g, bg_b, out, order, scratch, coc_k, inv_focus, rho0,
                  rho1):
    """Composite pixel p's surfaces front to back over the background.

    Neighbouring surfaces (in depth) are one layer by their ``merge_fraction`` m: the
    pixel is the expectation, over the partitions of the sorted surfaces into runs, of
    "over" of the merged runs, where a run i..j has probability
    m_i ... m_(j-1) (1 - m_j). With every m = 0 this is the paper's "over" of the
    surfaces; a run's weights, colours and opacities add as a merge does. Computed from
    the back in O(n^2): F(i) = sum_j P_ij (C_ij + (1 - alpha_ij) F(j + 1)).

    out: (7,) receives r, g, b, alpha, depth of the surface that contributes most
    (inf if none), accumulated weight of the nearest surface, number of surfaces;
    order: (MAX_SURFACES,) int scratch; scratch: (RESOLVE_SCRATCH,) float scratch.
    """
    n = cnt[p]
    if n <= 1:
        # no surface, or one (most pixels of a frame): the general composite below, its
        # loops run once, without the scratch table (the same arithmetic)
        alpha = 0.0
        cr = cg = cb = 0.0
        d = np.inf
        w = acc[p, 0, S_W] if n == 1 else 0.0
        if w > 0.0:
            d = acc[p, 0, S_WD] / w
            alpha = layer_alpha(w, acc[p, 0, S_WA], acc[p, 0, S_WO],
                                sharpness(d, coc_k, inv_focus))
            cr, cg, cb = alpha * acc[p, 0, S_WR] / w, alpha * acc[p, 0, S_WG] / w, \
                alpha * acc[p, 0, S_WB] / w
        trans = 1.0 - alpha
        out[0] = cr + trans * bg_r
        out[1] = cg + trans * bg_g
        out[2] = cb + trans * bg_b
        out[3] = 1.0 - trans
        out[4] = d if alpha > 0.0 else np.inf
        out[5] = w
        out[6] = n
        return
    ns = MAX_SURFACES
    for i in range(n):  # insertion sort by mean depth, ties by slot
        d = acc[p, i, S_WD] / acc[p, i, S_W] if acc[p, i, S_W] > 0 else 0.5 * (acc[p, i, S_ZLO] + acc[p, i, S_ZHI])
        m = i
        while m > 0 and scratch[m - 1] > d:
            scratch[m] = scratch[m - 1]
            order[m] = order[m - 1]
            m -= 1
        scratch[m] = d
        order[m] = i
    # merge fractions of neighbours m and m + 1, at scratch[ns + m]
    for m in range(n - 1):
        i = order[m]
        w = acc[p, i, S_W]
        opacity = acc[p, i, S_WA] / w if w > 0.0 else 0.0
        scratch[ns + m] = merge_fraction(scratch[m], scratch[m + 1], opacity, coc_k, inv_focus,
                                         rho0, rho1)
    # the composite table F(m) = (r, g, b, transmittance) at scratch[2 ns + 4 m ...]
    f0 = 2 * ns
    scratch[f0 + 4 * n] = 0.0
    scratch[f0 + 4 * n + 1] = 0.0
    scratch[f0 + 4 * n + 2] = 0.0
    scratch[f0 + 4 * n + 3] = 1.0
    for a in range(n - 1, -1, -1):
        prob = 1.0
        sw = sr = sg = sb = sa = so = sd = 0.0
        fr = fg = fb = ft = 0.0
        for b in range(a, n):
            i = order[b]
            sw += acc[p, i, S_W]
            sr += acc[p, i, S_WR]
            sg += acc[p, i, S_WG]
            sb += acc[p, i, S_WB]
            sa += acc[p, i, S_WA]
            so += acc[p, i, S_WO]
            sd += acc[p, i, S_WD]
            end = prob * (1.0 - scratch[ns + b]) if b < n - 1 else prob
            if end > 0.0:
                alpha = 0.0
                cr = cg = cb = 0.0
                if sw > 0.0:
                    alpha = layer_alpha(sw, sa, so, sharpness(sd / sw, coc_k, inv_focus))
                    cr, cg, cb = alpha * sr / sw, alpha * sg / sw, alpha * sb / sw
                nxt = f0 + 4 * (b + 1)
                fr += end * (cr + (1.0 - alpha) * scratch[nxt])
                fg += end * (cg + (1.0 - alpha) * scratch[nxt + 1])
                fb += end * (cb + (1.0 - alpha) * scratch[nxt + 2])
                ft += end * (1.0 - alpha) * scratch[nxt + 3]
            if b < n - 1:
                prob *= scratch[ns + b]
                if prob <= 0.0:
                    break
        scratch[f0 + 4 * a] = fr
        scratch[f0 + 4 * a + 1] = fg
        scratch[f0 + 4 * a + 2] = fb
        scratch[f0 + 4 * a + 3] = ft
    # the surface that contributes most, by "over" of the separate surfaces
    trans = 1.0
    best = 0.0
    best_depth = np.inf
    for m in range(n):
        i = order[m]
        w = acc[p, i, S_W]
        if w <= 0.0:
            continue
        alpha = layer_alpha(w, acc[p, i, S_WA], acc[p, i, S_WO],
                            sharpness(scratch[m], coc_k, inv_focus))
        if trans * alpha > best:
            best = trans * alpha
            best_depth = scratch[m]
        trans *= 1.0 - alpha
    trans = scratch[f0 + 3]
    out[0] = scratch[f0] + trans * bg_r
    out[1] = scratch[f0 + 1] + trans * bg_g
    out[2] = scratch[f0 + 2] + trans * bg_b
    out[3] = 1.0 - trans
    out[4] = best_depth
    out[5] = acc[p, order[0], S_W] if n > 0 else 0.0
    out[6] = n


@numba.njit(cache=True, nogil=True, parallel=True)
def rasterize_band(splats, bbox, offsets, ids, n_tx, ty0, width, height, cutoff,
                   background, image, depth, weight, tile_stats, coc_k, inv_focus, rho0, rho1,
                   blades, table, u_c, pool, coarse):
    """Rasterise and resolve the tiles of one band (tile rows ty0..) into the output images.

    image: (H, W, 4) float32; depth, weight: (H, W) float32; tile_stats: (n_tiles, 2) int64
    receives fragments generated and A-buffer overflows per tile, and with a third column
    the most surfaces (A-buffer entries) any pixel of the tile held. pool: the number of
    threads' tile buffers, at least numba's thread count (``numba.config.NUMBA_NUM_THREADS``,
    read by the caller: read here it would be a constant of the cached machine code, and a
    process with more threads than the one that compiled it would write past the buffers).
    coarse: a splat whose aperture radius is at least this many pixels (``RAD``; 0: none)
    is drawn at every second pixel only, into an A-buffer of those samples, which each
    pixel then takes interpolated linearly (``add_samples``); its box must reach a pixel
    further up and left (``widen_boxes``), so that the tile holds every splat of the
    samples it shares with the next tiles.
    """
    n_tiles = offsets.shape[0] - 1
    bg_r, bg_g, bg_b = background[0], background[1], background[2]
    round_aperture = blades.shape[0] == 0
    flat = table.reshape(-1)
    # each thread's tile buffers, allocated once per band, not once per tile: a tile's
    # A-buffer is 144 KiB, past malloc's mmap threshold, and a fresh mapping per tile (its
    # page faults) cost 30 ms of a 1280 x 720 frame with nothing in it (bench/RESULTS.md)
    # The small ones are LINE_PAD items longer than they need: a cache line between two
    # threads' rows. Without it two threads' resolve outputs (written at every pixel)
    # shared a line, and the 2-thread raster of a frame with nothing in it took as long as
    # one thread's (bench/RESULTS.md)
    accs = np.empty((pool, TILE * TILE, MAX_SURFACES, N_ACC), np.float64)
    cnts = np.empty((pool, TILE * TILE + LINE_PAD), np.int64)
    cells = np.empty((pool, TILE * TILE + LINE_PAD), np.int32)  # an aperture kernel's table cells
    fracs = np.empty((pool, 2, TILE * TILE + LINE_PAD), np.float32)
    ress = np.empty((pool, 7 + LINE_PAD), np.float64)
    orders = np.empty((pool, MAX_SURFACES + LINE_PAD), np.int64)
    scratches = np.empty((pool, RESOLVE_SCRATCH + LINE_PAD), np.float64)
    n_samples = SAMPLES * SAMPLES if coarse > 0.0 else 1
    saccs = np.empty((pool, n_samples, MAX_SURFACES, N_ACC), np.float64)
    scnts = np.empty((pool, n_samples + LINE_PAD), np.int64)
    n_rows = n_tiles // n_tx
    stride = weyl_stride(n_rows)
    for u in numba.prange(n_tiles):
        t = spread_tile(u, n_tx, n_rows, stride)
        ty = ty0 + t // n_tx
        tx = t % n_tx
        px0, py0 = tx * TILE, ty * TILE
        px1, py1 = min(px0 + TILE, width) - 1, min(py0 + TILE, height) - 1
        me = numba.get_thread_id()
        acc, cnt, cell, frac = accs[me], cnts[me, :TILE * TILE], cells[me], fracs[me]
        cnt[:] = 0
        sacc, scnt = saccs[me], scnts[me, :n_samples]
        scnt[:] = 0
        sampled = False
        frags = 0
        overflows = 0
        for slot in range(offsets[t], offsets[t + 1]):
            k = ids[slot]
            amp = splats[k, AMP]
            if amp <= 0.0:
                continue  # hidden by the front pass
            mx, my = splats[k, MX], splats[k, MY]
            c11, c12, c22 = splats[k, C11], splats[k, C12], splats[k, C22]
            r, g, b, a = splats[k, RED], splats[k, GREEN], splats[k, BLUE], splats[k, ALPHA]
            # an LOD node's colour changes across it (ewa.color_slope; 0 for a surfel)
            rx, ry, gx, gy = splats[k, RX], splats[k, RY], splats[k, GX], splats[k, GY]
            bx, by = splats[k, BX], splats[k, BY]
            d, zlo, zhi = splats[k, DEPTH], splats[k, ZLO], splats[k, ZHI]
            floor = splats[k, FLOOR]
            x0, x1 = int(splats[k, X0]), int(splats[k, X1])
            radius = splats[k, RAD]
            if radius != 0.0:
                # the aperture's shape (splat/bokeh.py): the scales of the tile's rows in SIMD
                # lanes, then a table look-up per fragment
                det = c11 * c22 - c12 * c12
                w11, w12, w22 = c22 / det, -c12 / det, c11 / det
                mix = splats[k, MIX]
                b11, b12, b22 = support_conic(w11, w12, w22, radius, u_c)
                if coarse > 0.0 and abs(radius) >= coarse:
                    # a wide blur: the kernel at the samples (every second pixel of the tile,
                    # and of the next tiles' first row and column), over the box's rows and a
                    # row past the image's last (a sample there serves its last row of pixels)
                    a_lo = (max(bbox[k, 2], py0) - py0 + 1) >> 1
                    a_hi = (min(bbox[k, 3] + (bbox[k, 3] == height - 1), py0 + TILE) - py0) >> 1
                    if round_aperture and a_hi >= a_lo:
                        aperture_rows(cell, frac, a_hi - a_lo + 1, px0 + 0.5 - mx,
                                      py0 + 2 * a_lo + 0.5 - my, radius, c11, c12, c22, w11,
                                      w12, w22, mix, u_c, 2.0)
                    for sa in range(a_lo, a_hi + 1):
                        i = py0 + 2 * sa
                        dy = i + 0.5 - my
                        lo, hi = row_span(dy, b11, b12, b22, 0.5)
                        if lo > hi:
                            continue
                        j0 = max(int(math.floor(mx + lo - 0.5)), x0, px0)
                        j1 = min(int(math.ceil(mx + hi - 0.5)), x1, px0 + TILE, width)
                        for sb in range((j0 - px0 + 1) >> 1, ((j1 - px0) >> 1) + 1):
                            dx = px0 + 2 * sb + 0.5 - mx
                            if round_aperture:
                                e = (sa - a_lo) * TILE + sb
                                wk = table_lerp(cell[e], frac[0, e], frac[1, e], flat)
                            else:
                                wk = aperture_value(
                                    c11 * dx * dx + 2.0 * c12 * dx * dy + c22 * dy * dy,
                                    w11 * dx * dx + 2.0 * w12 * dx * dy + w22 * dy * dy,
                                    dx, dy, radius, mix, blades, table, u_c, c11, w11)
                            if wk > 0.0:
                                overflows += insert_fragment(
                                    sacc, scnt, sa * SAMPLES + sb, amp * wk,
                                    max(r + rx * dx + ry * dy, 0.0),
                                    max(g + gx * dx + gy * dy, 0.0),
                                    max(b + bx * dx + by * dy, 0.0), a, d, zlo, zhi)
                                # the next tiles' samples are theirs to count, and those
                                # past the image's edge no one's
                                if sa < SAMPLES - 1 and sb < SAMPLES - 1 and i < height \
                                        and px0 + 2 * sb < width:
                                    frags += 1
                                sampled = True
                    continue
                ia, ib = max(bbox[k, 2], py0), min(bbox[k, 3], py1)
                if round_aperture:
                    aperture_rows(cell, frac, ib - ia + 1, px0 + 0.5 - mx, ia + 0.5 - my,
                                  radius, c11, c12, c22, w11, w12, w22, mix, u_c, 1.0)
                for i in range(ia, ib + 1):
                    # the row's span over the support's bounding ellipse, a pixel wider
                    lo, hi = row_span(i + 0.5 - my, b11, b12, b22, 0.5)
                    if lo > hi:
                        continue
                    j0 = max(int(math.floor(mx + lo - 0.5)), x0)
                    j1 = min(int(math.ceil(mx + hi - 0.5)), x1)
                    ja, jb = max(j0, px0), min(j1, px1)
                    p = (i - py0) * TILE + (ja - px0)
                    c = (i - ia) * TILE + (ja - px0)  # the pixel's table cell (aperture_rows)
                    dy = i + 0.5 - my
                    # the colour along the row by forward differences, as for a Gaussian
                    dx = ja + 0.5 - mx
                    rr, gg, bb = r + rx * dx + ry * dy, g + gx * dx + gy * dy, b + bx * dx + by * dy
                    if round_aperture:
                        # a loop of its own, without the polygon's branch: the blurred
                        # frames' raster stage 0.95 x (bench/RESULTS.md)
                        for c in range(c, c + jb + 1 - ja):
                            wk = table_lerp(cell[c], frac[0, c], frac[1, c], flat)
                            if wk > 0.0:
                                overflows += insert_fragment(
                                    acc, cnt, p, amp * wk, max(rr, 0.0), max(gg, 0.0),
                                    max(bb, 0.0), a, d, zlo, zhi)
                                frags += 1
                            p += 1
                            rr += rx
                            gg += gx
                            bb += bx
                        continue
                    for j in range(ja, jb + 1):
                        dx = j + 0.5 - mx
                        wk = aperture_value(c11 * dx * dx + 2.0 * c12 * dx * dy + c22 * dy * dy,
                                            w11 * dx * dx + 2.0 * w12 * dx * dy + w22 * dy * dy,
                                            dx, dy, radius, mix, blades, table, u_c, c11, w11)
                        if wk > 0.0:
                            overflows += insert_fragment(
                                acc, cnt, p, amp * wk, max(rr, 0.0), max(gg, 0.0),
                                max(bb, 0.0), a, d, zlo, zhi)
                            frags += 1
                        p += 1
                        rr += rx
                        gg += gx
                        bb += bx
                continue
            step2 = math.exp(-c11)
            ia, ib = max(bbox[k, 2], py0), min(bbox[k, 3], py1)
            # a narrow kernel's rows are scanned whole from the same column: each row's first
            # values follow from the previous row's by forward differences down the column
            # (ewa.column_start, as in ewa.kernel_pixel_sum: six exps per splat and tile
            # instead of two a row)
            narrow = x1 - x0 < NARROW_BBOX and ib - ia < NARROW_ROWS
            ja, jb = max(x0, px0), min(x1, px1)
            if narrow and ja > jb:
                continue
            col = column_start(ja, ia, mx, my, c11, c12, c22) if narrow else NO_COLUMN
            for i in range(ia, ib + 1):
                if narrow:
                    q, dq, e, f = col[0], col[1], col[2], col[3]
                    col = column_step(col, c12, c22)
                else:
                    j0, j1 = row_pixel_range(i, mx, my, c11, c12, c22, cutoff, x0, x1)
                    ja, jb = max(j0, px0), min(j1, px1)
                    if ja > jb:
                        continue
                    # exponent and kernel value by forward differences along the row
                    # (ewa.row_start)
                    q, dq, e, f = row_start(ja, i, mx, my, c11, c12, c22)
                p = (i - py0) * TILE + (ja - px0)
                # the colour along the row, by forward differences too
                dx, dy = ja + 0.5 - mx, i + 0.5 - my
                rr, gg, bb = r + rx * dx + ry * dy, g + gx * dx + gy * dy, b + bx * dx + by * dy
                for _ in range(ja, jb + 1):
                    if q < cutoff:
                        overflows += insert_fragment(acc, cnt, p, amp * (e - floor), max(rr, 0.0),
                                                     max(gg, 0.0), max(bb, 0.0), a, d, zlo, zhi)
                        frags += 1
                    q += dq
                    dq += c11
                    e *= f
                    f *= step2
                    rr += rx
                    gg += gx
                    bb += bx
                    p += 1
        res, order, scratch = ress[me], orders[me], scratches[me]
        layers = 0
        # the samples drawn: those of the image and one row and column past it
        s_rows = min(SAMPLES, ((height - py0) >> 1) + 1)
        s_cols = min(SAMPLES, ((width - px0) >> 1) + 1)
        for i in range(py0, py1 + 1):
            for j in range(px0, px1 + 1):
                p = (i - py0) * TILE + (j - px0)
                if sampled:
                    overflows += add_samples(acc, cnt, p, sacc, scnt, i - py0, j - px0,
                                             s_rows, s_cols)
                layers = max(layers, cnt[p])
                resolve_to_image(acc, cnt, p, bg_r, bg_g, bg_b, res, order, scratch,
                                 image, depth, weight, i, j, coc_k, inv_focus, rho0, rho1)
        tile_stats[t, 0] = frags
        tile_stats[t, 1] = overflows
        if tile_stats.shape[1] > 2:
            tile_stats[t, 2] = layers
