"""The lens in layers: each part of the lens drawn as depth slabs, each at the resolution its
blur allows, joined ("over") at full resolution (issue 48's cost; docs/maths.md, "Gaussian
scenes through a lens"; ``backends.cpu_gauss.draw_layered`` calls these in order).

A Gaussian at depth z is blurred, in each part of the lens, by the residual lens: a Gaussian
of standard deviation sigma = rho sqrt(v) C_r(z) pixels (v the aperture's ``blur_variance``,
rho the parts' residual scale). Its footprint is at least that wide, so an image of 1/s the
resolution holds it where sigma >= ``alpha`` s. Because C_r grows monotonically away from
the plane of focus on either side, the Gaussians whose blur allows scale s are a slab of
depth in front of the focus and one behind it, and sorted alpha blending of a depth-ordered
list is "over" of its consecutive runs:

    C = C_1 + T_1 (C_2 + T_2 (C_3 + ...)),   T = T_1 T_2 T_3 ...

so each slab is composited alone, at its own resolution, and a part's slabs are joined per
pixel, front to back (``combine_layers``; a coarse one sampled bilinearly, which adds a tent
of variance s^2 / 6 px^2 to its blur). Front to back: the near side's coarsest layer first,
then its finer ones, the sharp slab, then the far side's finest first (``layer_keys``).
What changes against drawing the part whole: a pixel's early stop (T <= 1e-4) applies
within a layer only, and a coarse layer is sampled, not drawn, at full resolution.

The sharp slab (C_r below ``sharp_coc``; 0 px, none, by default: docs/maths.md, "Gaussian
scenes", item 4) is drawn once, from the lens centre with the whole lens's blur, instead of
once per part.

A widely blurred layer is *summed* (which ones: ``backends.cpu_gauss.mark_summed``): its
Gaussians are drawn alone and sharp, from the part's camera, into a "sharp view"
(``IM_SHARP``: at 1/2 the resolution or coarser, with a margin, its pixels written in
linear light, ``composite.linear_pixel``), and its image (``IM_SUM``) is that view blurred
by a Gaussian of the layer's blur (``blur_rows``, ``blur_columns``). Blurred footprints
blended one "over" another no longer cover one another, and the surface they make
over-covers; the lens reference blurs what each of its views sees, the layer's sharp
coverage. The layers of a part are then joined in runs (``combine_layers``): a summed
layer "over" what is behind it in linear light, as the reference's views average, the
others in the trainer's encoded values (their partial coverage is the trainer's own
blend), each part decoded before the parts are averaged (docs/maths.md, "Gaussian
scenes", item 2).

Every image of a frame, whatever its part, layer and resolution (and the lens visibility's
views, ``cpu_gauss.lens_visibility_by_shifts``), is a row of one table (the ``IM_*``
columns): their rows are listed per tile in one pass (``bin_images``) and all their tiles
composited in one parallel loop (``composite_images``), so that a frame launches a few
kernels, not a few per layer and part.
"""

from __future__ import annotations

import math

import numpy as np

from ..jit import numba
from ..parallel import weyl_stride
from .composite import (MIN_TRANSMITTANCE, N_STATE, S_B, S_DEPTH, S_G, S_R, S_T, TILE,
                        blend_tile, decode, encode, finish_linear_pixel, linear_pixel)
from .project import BLUR_NONE, BLUR_OURS, EPS2D, move_footprint, project_gaussian

# the columns of an image table (int64, a row per image). IM_SHARP: 1 where the image's
# Gaussians are projected without the lens's blur (a summed layer's sharp view, the module
# docstring) and its pixels written in linear light; IM_SUM: 1 where the image is a summed
# layer's, drawn by no Gaussian but blurred from its sharp view, image IM_SOURCE
# (``blur_rows``, ``blur_columns``), in linear light (joined so: ``combine_layers``)
(IM_WIDTH, IM_HEIGHT, IM_SCALE, IM_MARGIN, IM_TILE0, IM_PIXEL0, IM_ROW0, IM_ROW1, IM_SUM,
 IM_SHARP, IM_SOURCE) = range(11)
N_IM = 11
MAX_LAYERS = 16  # a part's images at most (``combine_layers``' runs; the GPU's local arrays)


def image_table(images) -> np.ndarray:
    """(I, N_IM) int64 from (width, height, scale, margin, row0, row1[, summed[, sharp[,
    source]]]) per image: their tiles and pixels numbered one image after another
    (``IM_TILE0``, ``IM_PIXEL0``); summed and sharp 0, source -1 where not given."""
    table = np.zeros((len(images), N_IM), np.int64)
    tile0 = pixel0 = 0
    for i, (w, h, scale, margin, row0, row1, *flags) in enumerate(images):
        summed, sharp, source = (list(flags) + [0, 0, -1][len(flags):])
        table[i] = (w, h, scale, margin, tile0, pixel0, row0, row1, int(summed), int(sharp),
                    int(source))
        tile0 += -(-w // TILE) * -(-h // TILE)
        pixel0 += w * h
    return table


def layer_keys(z: np.ndarray, coc: np.ndarray, inv_focus: float, sigma_per_coc: float,
               sharp_coc: float, alpha: float, max_level: int, split_level: int | None = None):
    """(key (N,) int64, scales (L,) int64, levels (L,) int64): each Gaussian's layer,
    numbered front to back, and each layer's scale (1/scale of the full resolution) and
    level. z: (N,) depths, coc: (N,) the whole lens's C_r(z), pixels; sigma_per_coc: a
    part's blur's standard deviation at C_r = 1 (rho sqrt(blur_variance)); a Gaussian's
    level is that of the largest power of 2 not above sigma / alpha, at most split_level
    (max_level where None), its layer's scale that power, at most 2^max_level (the levels
    past max_level are layers of their own at that scale); key split_level + 1 is the sharp
    slab (C_r below sharp_coc), in front of it the near side's layers (coarsest first),
    behind it the far side's (finest first). Keys are non-decreasing in z."""
    split = max_level if split_level is None else max(split_level, max_level)
    sigma = sigma_per_coc * coc
    with np.errstate(divide="ignore"):
        level = np.floor(np.log2(np.maximum(sigma / alpha, 1.0)))
    level = np.minimum(level, split).astype(np.int64)
    sharp = split + 1
    key = np.where(z < 1.0 / inv_focus, split - level, sharp + 1 + level)
    key[coc < sharp_coc] = sharp
    levels = np.r_[np.arange(split, -1, -1), 0, np.arange(split + 1)]
    return key, (2 ** np.minimum(levels, max_level)).astype(np.int64), levels.astype(np.int64)


# a projection of ``project_layers``: the camera's intrinsics and image, the lens's blur
(P_FX, P_FY, P_CX, P_CY, P_WIDTH, P_HEIGHT, P_NEAR, P_COC_K, P_INV_FOCUS,
 P_BLUR_VARIANCE) = range(10)
N_P = 10


@numba.njit(cache=True, nogil=True, parallel=True)
def project_layers(positions, scales, rotations, opacity, sh, share, views, campos, cameras,
                   spans, antialiased, sharp_eps2d, images, row_image, rows, boxes, visible):
    """Every projection of a layered frame in one loop, each row then moved onto its image.

    Projection j (``project_gaussian`` with our blur): views[j] (4, 4) world to camera,
    campos[j] (3,), cameras[j] (the ``P_*`` columns), of the Gaussians spans[j, 0] ..
    spans[j, 1] into rows, boxes and visible from row spans[j, 2] (the projections' rows
    one run after another, covering them all). share: (N,) the lens visibility, or (0,).
    A row of a sharp image (``IM_SHARP``, a summed layer's view) is projected without the
    blur or the share, with a low-pass of sharp_eps2d px^2 of that image's pixels, on the
    camera's image widened by the image's margin, so that what the blur carries in from
    outside the frame is drawn. Then row r is moved onto images[row_image[r]] where that
    image's scale is not 1 (``move_footprint``: the same footprint in its pixels). Each row
    is ``project_layer_row``'s."""
    for r in numba.prange(rows.shape[0]):
        project_layer_row(r, positions, scales, rotations, opacity, sh, share, views, campos,
                          cameras, spans, antialiased, sharp_eps2d, images, row_image, rows,
                          boxes, visible)


@numba.njit(cache=True, nogil=True, inline="always")
def project_layer_row(r, positions, scales, rotations, opacity, sh, share, views, campos,
                      cameras, spans, antialiased, sharp_eps2d, images, row_image, rows, boxes,
                      visible):
    """Row r of ``project_layers`` (which see): the per-row maths that the CUDA backend
    compiles as a device function too."""
    j = 0
    while r >= spans[j, 2] + spans[j, 1] - spans[j, 0]:
        j += 1
    a, b, r0 = spans[j, 0], spans[j, 1], spans[j, 2]
    r1 = r0 + b - a
    cam = cameras[j]
    im = row_image[r]
    scale = images[im, IM_SCALE]
    if images[im, IM_SHARP] != 0:
        # the image's margin, in the projection's pixels, on every side
        wide = float(images[im, IM_MARGIN] * scale)
        project_gaussian(r - r0, positions[a:b], scales[a:b], rotations[a:b], opacity[a:b],
                         sh[a:b], views[j], campos[j], cam[P_FX], cam[P_FY], cam[P_CX] + wide,
                         cam[P_CY] + wide, int(cam[P_WIDTH] + 2.0 * wide),
                         int(cam[P_HEIGHT] + 2.0 * wide), cam[P_NEAR], 1e10,
                         sharp_eps2d * scale * scale, antialiased, BLUR_NONE, 0.0,
                         cam[P_INV_FOCUS], 0.0, share[a:a], rows[r0:r1], boxes[r0:r1],
                         visible[r0:r1])
        move_footprint(r, r, rows, visible, rows, boxes, visible, 0.0, 0.0, 0.0, float(scale),
                       0.0, images[im, IM_WIDTH], images[im, IM_HEIGHT])
        return
    project_gaussian(r - r0, positions[a:b], scales[a:b], rotations[a:b], opacity[a:b],
                     sh[a:b], views[j], campos[j], cam[P_FX], cam[P_FY], cam[P_CX],
                     cam[P_CY], int(cam[P_WIDTH]), int(cam[P_HEIGHT]), cam[P_NEAR], 1e10,
                     EPS2D, antialiased, BLUR_OURS, cam[P_COC_K], cam[P_INV_FOCUS],
                     cam[P_BLUR_VARIANCE], share[a:b] if share.shape[0] > 0 else share,
                     rows[r0:r1], boxes[r0:r1], visible[r0:r1])
    if scale != 1:
        move_footprint(r, r, rows, visible, rows, boxes, visible, 0.0, 0.0, 0.0,
                       float(scale), float(images[im, IM_MARGIN]), images[im, IM_WIDTH],
                       images[im, IM_HEIGHT])


@numba.njit(cache=True, nogil=True)
def bin_images(images, order, boxes, visible):
    """(offsets (T + 1,) int64, ids (pairs,) int32, tile_image (T,) int32): the visible rows
    of every image listed per tile (``composite.bin_tiles`` image by image; image i's rows
    are order[images[i, IM_ROW0]:images[i, IM_ROW1]], nearest first; its tiles are numbered
    from IM_TILE0)."""
    n_images = images.shape[0]
    last = n_images - 1
    n_tiles = images[last, IM_TILE0] + (-(-images[last, IM_WIDTH] // TILE)) * (
        -(-images[last, IM_HEIGHT] // TILE))
    counts = np.zeros(n_tiles + 1, np.int64)
    tile_image = np.empty(n_tiles, np.int32)
    for i in range(n_images):
        n_tx = -(-images[i, IM_WIDTH] // TILE)
        n_ty = -(-images[i, IM_HEIGHT] // TILE)
        t0 = images[i, IM_TILE0]
        tile_image[t0:t0 + n_tx * n_ty] = i
        for k in range(images[i, IM_ROW0], images[i, IM_ROW1]):
            g = order[k]
            if not visible[g]:
                continue
            for ty in range(boxes[g, 2] // TILE, (boxes[g, 3] - 1) // TILE + 1):
                for tx in range(boxes[g, 0] // TILE, (boxes[g, 1] - 1) // TILE + 1):
                    counts[t0 + ty * n_tx + tx + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    ids = np.empty(counts[n_tiles], np.int32)
    fill = counts[:n_tiles].copy()
    for i in range(n_images):
        n_tx = -(-images[i, IM_WIDTH] // TILE)
        t0 = images[i, IM_TILE0]
        for k in range(images[i, IM_ROW0], images[i, IM_ROW1]):
            g = order[k]
            if not visible[g]:
                continue
            for ty in range(boxes[g, 2] // TILE, (boxes[g, 3] - 1) // TILE + 1):
                for tx in range(boxes[g, 0] // TILE, (boxes[g, 1] - 1) // TILE + 1):
                    t = t0 + ty * n_tx + tx
                    ids[fill[t]] = g
                    fill[t] += 1
    return counts, ids, tile_image


@numba.njit(cache=True, nogil=True)
def live_tiles(offsets, images, tile_image):
    """(T,) bool: whether a tile or one of its eight neighbours in its image lists any
    Gaussian: the tiles ``combine_layers`` may read, so the empty ones that
    ``composite_images`` writes (``layer_listed_over``)."""
    n_tiles = offsets.shape[0] - 1
    live = np.zeros(n_tiles, np.bool_)
    for t in range(n_tiles):
        mark_live(offsets, images, tile_image, t, live)
    return live


@numba.njit(cache=True, nogil=True, inline="always")
def mark_live(offsets, images, tile_image, t, live):
    """``live_tiles``'s step for tile t: where it lists a Gaussian, it and its neighbours in
    its image are marked live (only ever set True: tiles may be marked in any order)."""
    if offsets[t + 1] == offsets[t]:
        return
    i = tile_image[t]
    n_tx = -(-images[i, IM_WIDTH] // TILE)
    n_ty = -(-images[i, IM_HEIGHT] // TILE)
    local = t - images[i, IM_TILE0]
    tx, ty = local % n_tx, local // n_tx
    for ny in range(max(ty - 1, 0), min(ty + 2, n_ty)):
        for nx in range(max(tx - 1, 0), min(tx + 2, n_tx)):
            live[images[i, IM_TILE0] + ny * n_tx + nx] = True


@numba.njit(cache=True, nogil=True, parallel=True)
def composite_images(rows, boxes, offsets, ids, tile_image, images, live, color,
                     transmittance, depth, seen, lut):
    """``composite.composite_tiles`` for every tile of every image at once: color (P, 3),
    transmittance (P,), depth (P,) float32 hold image i's pixels from images[i, IM_PIXEL0],
    row by row. The tiles are taken in a Weyl order (``parallel.weyl_stride``): numba gives
    each thread one run of the loop, and a run in table order would be one image's. An
    empty tile is written empty (T = 1) without a blend where it is live (T,) (the
    ``live_tiles`` that ``combine_layers`` may read), and not touched elsewhere: a layer's
    full-resolution image is mostly empty, and writing it all was half the composite's time
    (the guitar at 1920 x 1080, 35 px: 58 of 75 ms for a near layer's 4 images). A sharp
    view's pixels (``IM_SHARP``) are written in linear light (``linear_pixel`` with lut,
    ``composite.DECODE``), for its blur."""
    n_tiles = offsets.shape[0] - 1
    track = seen.shape[0] > 0
    stride = weyl_stride(n_tiles)
    for j in numba.prange(n_tiles):
        t = (j * stride) % n_tiles
        tid = numba.get_thread_id() if track else 0
        i = tile_image[t]
        w, h = images[i, IM_WIDTH], images[i, IM_HEIGHT]
        n_tx = -(-w // TILE)
        local = t - images[i, IM_TILE0]
        tx0 = (local % n_tx) * TILE
        ty0 = (local // n_tx) * TILE
        tx1 = min(tx0 + TILE, w)
        ty1 = min(ty0 + TILE, h)
        tw = tx1 - tx0
        base = images[i, IM_PIXEL0]
        if offsets[t + 1] == offsets[t]:  # an empty tile (most of a layer's)
            if not live[t]:
                continue  # never read
            for py in range(ty0, ty1):
                for px in range(tx0, tx1):
                    q = base + py * w + px
                    color[q, 0] = 0.0
                    color[q, 1] = 0.0
                    color[q, 2] = 0.0
                    transmittance[q] = 1.0
                    depth[q] = math.inf
            continue
        state = np.empty((tw * (ty1 - ty0), N_STATE), np.float64)
        done = np.empty(tw * (ty1 - ty0), np.bool_)
        blend_tile(rows, boxes, ids, offsets[t], offsets[t + 1], tx0, ty0, tx1, ty1, state,
                   done, seen, tid)
        sharp = images[i, IM_SHARP] != 0
        for py in range(ty0, ty1):
            for px in range(tx0, tx1):
                p = (py - ty0) * tw + (px - tx0)
                q = base + py * w + px
                if sharp:
                    linear_pixel(state, p, lut)
                color[q, 0] = state[p, S_R]
                color[q, 1] = state[p, S_G]
                color[q, 2] = state[p, S_B]
                transmittance[q] = state[p, S_T]
                depth[q] = state[p, S_DEPTH]


BLUR_REACH = 3.0  # a summed layer's blur is cut at this many standard deviations
N_BLUR = 4  # what the blur carries: the linear colour (premultiplied) and the coverage


@numba.njit(cache=True, nogil=True, parallel=True)
def blur_rows(images, blurs, i, offsets, color, transmittance, scratch):
    """The first half of summed image i's blur (``IM_SUM``; ``blur_columns`` the second):
    each row of its sharp view k = images[i, IM_SOURCE] (linear light, ``IM_SHARP``)
    filtered by a Gaussian of standard deviation blurs[i] (k's pixels) at image i's
    columns: scratch[y, x] (k's rows, i's columns; float32) the linear colour
    (premultiplied) and the coverage. Only the view's tiles that list a Gaussian are read
    (``offsets``: ``bin_images``'s; the others are empty, or not written). Each pixel is
    ``blur_row_pixel``'s."""
    for y in numba.prange(images[images[i, IM_SOURCE], IM_HEIGHT]):
        p0, p1 = listed_span(images, offsets, images[i, IM_SOURCE], y)
        for x in range(images[i, IM_WIDTH]):
            blur_row_pixel(images, blurs, i, offsets, color, transmittance, scratch, y, x, p0,
                           p1)


@numba.njit(cache=True, nogil=True, inline="always")
def listed_span(images, offsets, k, y):
    """(p0, p1): the pixels of image k's row y from its first tile that lists a Gaussian to
    past its last (p0 >= p1 where none does)."""
    n_tx = -(-images[k, IM_WIDTH] // TILE)
    t_row = images[k, IM_TILE0] + (y // TILE) * n_tx
    first, last = n_tx, -1
    for tx in range(n_tx):
        if offsets[t_row + tx + 1] > offsets[t_row + tx]:
            first = min(first, tx)
            last = tx
    return first * TILE, min((last + 1) * TILE, images[k, IM_WIDTH])


@numba.njit(cache=True, nogil=True, inline="always")
def blur_taps(x, i, k, images, sigma):
    """(centre, first tap, last tap): where image i's pixel x's centre falls on the pixels
    of image k (its sharp view) along one axis, and the taps of a blur of standard
    deviation sigma (k's pixels) about it, ``BLUR_REACH`` sigma either side."""
    u = ((x - images[i, IM_MARGIN] + 0.5) * images[i, IM_SCALE] / images[k, IM_SCALE]
         + images[k, IM_MARGIN] - 0.5)
    return u, int(math.ceil(u - BLUR_REACH * sigma)), int(math.floor(u + BLUR_REACH * sigma))


@numba.njit(cache=True, nogil=True, inline="always")
def first_weight(lo, u, sigma):
    """(w, ratio, step): the Gaussian's weight e^(-d^2 / 2 sigma^2) at tap lo (d = lo - u),
    the ratio of the next tap's to it and that ratio's own ratio from tap to tap: the taps'
    weights by two products each (w *= ratio; ratio *= step), three exponentials a pixel."""
    a2 = 0.5 / (sigma * sigma)
    d = lo - u
    return math.exp(-a2 * d * d), math.exp(-a2 * (2.0 * d + 1.0)), math.exp(-2.0 * a2)


@numba.njit(cache=True, nogil=True, inline="always")
def blur_row_pixel(images, blurs, i, offsets, color, transmittance, scratch, y, x, p0, p1):
    """``blur_rows`` at row y of the sharp view, column x of image i: the per-pixel maths
    that the CUDA backend compiles as a device function too. The weights (``first_weight``)
    are normalised over every tap, inside the view or not, listed or not: where nothing is
    listed there is nothing (p0, p1: the row's ``listed_span``)."""
    k = images[i, IM_SOURCE]
    sigma = blurs[i]
    u, lo, hi = blur_taps(x, i, k, images, sigma)
    if hi < p0 or lo >= p1:  # no tap reaches a listed tile
        for c in range(N_BLUR):
            scratch[y, x, c] = 0.0
        return
    w_k = images[k, IM_WIDTH]
    base = images[k, IM_PIXEL0] + y * w_k
    t_row = images[k, IM_TILE0] + (y // TILE) * (-(-w_k // TILE))
    wt, ratio, step = first_weight(lo, u, sigma)
    r = g = b = a = norm = 0.0
    for t in range(lo, hi + 1):
        norm += wt
        if p0 <= t < p1:
            tile = t_row + t // TILE
            if offsets[tile + 1] > offsets[tile]:
                q = base + t
                r += wt * color[q, 0]
                g += wt * color[q, 1]
                b += wt * color[q, 2]
                a += wt * (1.0 - transmittance[q])
        wt *= ratio
        ratio *= step
    inv = 1.0 / norm
    scratch[y, x, 0] = r * inv
    scratch[y, x, 1] = g * inv
    scratch[y, x, 2] = b * inv
    scratch[y, x, 3] = a * inv


@numba.njit(cache=True, nogil=True, parallel=True)
def blur_columns(images, blurs, i, offsets, scratch, color, transmittance, depth, filled):
    """The second half of ``blur_rows``: scratch's columns filtered alike at image i's rows,
    into image i's pixels (linear colour, premultiplied; T = 1 - coverage; the depth of the
    sharp view's nearest pixel), each of its tiles with any coverage set in filled (T,)
    (``filled_tiles``). A pixel whose taps reach no listed tile of the view (offsets:
    ``bin_images``') is written empty without them (``listed_rows_span``: on playbot at
    1920 x 1080, 35 px, the blur 2.6 x faster). Each pixel is ``blur_column_pixel``'s."""
    for y in numba.prange(images[i, IM_HEIGHT]):
        p0, p1 = listed_rows_span(images, blurs, i, offsets, y)
        for x in range(images[i, IM_WIDTH]):
            blur_column_pixel(images, blurs, i, scratch, color, transmittance, depth, filled,
                              y, x, p0, p1)


@numba.njit(cache=True, nogil=True, inline="always")
def listed_rows_span(images, blurs, i, offsets, y):
    """(p0, p1): the union of ``listed_span`` over the rows of image i's sharp view that
    the taps of its row y read (``blur_column_pixel``): outside it every tap of a column
    is zero (``blur_row_pixel``)."""
    k = images[i, IM_SOURCE]
    _, lo, hi = blur_taps(y, i, k, images, blurs[i])
    lo, hi = max(lo, 0), min(hi, images[k, IM_HEIGHT] - 1)
    p0, p1 = images[k, IM_WIDTH], 0
    if lo > hi:  # no tap inside the view
        return p0, p1
    for ty in range(lo // TILE, hi // TILE + 1):  # (a tile's rows share its row's span)
        a, b = listed_span(images, offsets, k, ty * TILE)
        if a < b:
            p0, p1 = min(p0, a), max(p1, b)
    return p0, p1


@numba.njit(cache=True, nogil=True, inline="always")
def blur_column_pixel(images, blurs, i, scratch, color, transmittance, depth, filled, y, x,
                      p0, p1):
    """``blur_columns`` at image i's pixel (x, y): the per-pixel maths that the CUDA backend
    compiles as a device function too (``blur_row_pixel``'s weights). p0, p1: the
    ``listed_rows_span`` of row y: where column x's taps along the view's rows miss it,
    every tap is zero and the pixel is empty, as the sum would make it."""
    k = images[i, IM_SOURCE]
    sigma = blurs[i]
    u, lo_x, hi_x = blur_taps(x, i, k, images, sigma)
    w_i = images[i, IM_WIDTH]
    q = images[i, IM_PIXEL0] + y * w_i + x
    v, lo, hi = blur_taps(y, i, k, images, sigma)
    h_k = images[k, IM_HEIGHT]
    r = g = b = a = 0.0
    if hi_x >= p0 and lo_x < p1:
        wt, ratio, step = first_weight(lo, v, sigma)
        norm = 0.0
        for t in range(lo, hi + 1):
            norm += wt
            if 0 <= t < h_k:
                r += wt * scratch[t, x, 0]
                g += wt * scratch[t, x, 1]
                b += wt * scratch[t, x, 2]
                a += wt * scratch[t, x, 3]
            wt *= ratio
            ratio *= step
        inv = 1.0 / norm
        r, g, b, a = r * inv, g * inv, b * inv, a * inv
    color[q, 0] = r
    color[q, 1] = g
    color[q, 2] = b
    transmittance[q] = 1.0 - min(a, 1.0)
    w_k = images[k, IM_WIDTH]
    col = min(max(int(u + 0.5), 0), w_k - 1)
    row = min(max(int(v + 0.5), 0), h_k - 1)
    depth[q] = depth[images[k, IM_PIXEL0] + row * w_k + col]
    if a > 0.0:
        filled[images[i, IM_TILE0] + (y // TILE) * (-(-w_i // TILE)) + x // TILE] = True


@numba.njit(cache=True, nogil=True, parallel=True)
def filled_tiles(offsets, filled):
    """filled (T,) bool: whether each tile lists a Gaussian (``bin_images``' offsets); a
    summed image's tiles, which list none, are set by its blur (``blur_columns``)."""
    for t in numba.prange(filled.shape[0]):
        filled[t] = offsets[t + 1] > offsets[t]


@numba.njit(cache=True, nogil=True, inline="always")
def layer_listed_over(images, filled, i, x0, y0, x1, y1):
    """Whether image i holds anything (``filled``: a tile that lists a Gaussian, or a summed
    image's tile with any coverage, ``filled_tiles``) in a tile that full-resolution pixels
    [x0, x1) x [y0, y1) read (``over_layer``: both taps of each sample along an axis, at
    scale 1 the pixel itself). Where none does, every pixel they read is empty (T = 1, no
    colour), so the layer is skipped. Where one does, every tile they read was written: a
    summed image's every tile (``blur_columns``), another's ``live_tiles``
    (``composite_images``): a frame tile's samples of a coarse image, like one pixel's two
    taps, span at most two of its tiles along an axis, each then the listed tile or its
    neighbour; at scale 1 the frame's tile is the image's."""
    s = images[i, IM_SCALE]
    m = images[i, IM_MARGIN]
    n_tx = -(-images[i, IM_WIDTH] // TILE)
    t0 = images[i, IM_TILE0]
    second = 0 if s == 1 else 1  # the second tap, one pixel on (read even at weight 0)
    # the first tap of every sample: floor((x + 0.5) / s + m - 0.5) (``layer_sample``)
    lx0 = int(math.floor((x0 + 0.5) / s + m - 0.5)) // TILE
    lx1 = (int(math.floor((x1 - 0.5) / s + m - 0.5)) + second) // TILE
    ly0 = int(math.floor((y0 + 0.5) / s + m - 0.5)) // TILE
    ly1 = (int(math.floor((y1 - 0.5) / s + m - 0.5)) + second) // TILE
    for ty in range(ly0, ly1 + 1):
        for tx in range(lx0, lx1 + 1):
            t = t0 + ty * n_tx + tx
            if filled[t]:
                return True
    return False


@numba.njit(cache=True, nogil=True, inline="always")
def over_layer(images, i, color, transmittance, depth, x0, y0, x1, y1, cols, fracs, total,
               t_acc, t_front, d):
    """Image i "under" the tile [x0, x1) x [y0, y1) of a part's pixels (``combine_layers``):
    total[p, :3] += t_acc[p] C, t_acc[p] *= T, with (C, T) the image's own pixel at scale 1,
    else bilinear between the four nearest of its pixels (pixel (m, m) of an image of scale
    s and margin m is centred on full-resolution point (s/2, s/2)); d[p] takes the depth
    (the nearest pixel's) where t_front t_acc first falls to 1/2 with d[p] still none
    (t_front: the runs' in front, ``combine_layers``). Returns how many pixels fell to
    MIN_TRANSMITTANCE. cols, fracs: (TILE,) scratch. Each pixel is
    ``over_pixel``'s."""
    w = images[i, IM_WIDTH]
    s = images[i, IM_SCALE]
    m = images[i, IM_MARGIN]
    base = images[i, IM_PIXEL0]
    tw = x1 - x0
    inv = 1.0 / s
    for px in range(x0, x1):
        cols[px - x0], fracs[px - x0] = layer_sample(px, inv, m)
    n_done = 0
    for py in range(y0, y1):
        row, ay = layer_sample(py, inv, m)
        q_row = base + row * w
        for px in range(x0, x1):
            n_done += over_pixel(images, i, color, transmittance, depth, q_row + cols[px - x0],
                                 fracs[px - x0], ay, total, t_acc, t_front, d,
                                 (py - y0) * tw + (px - x0))
    return n_done


@numba.njit(cache=True, nogil=True, inline="always")
def layer_sample(x, inv, m):
    """(first tap, the second tap's weight): where full-resolution pixel x's centre falls
    on an image of scale 1/inv and margin m, along one axis (``over_layer``)."""
    f = (x + 0.5) * inv + m - 0.5  # >= 0: a coarse image has a margin
    return int(f), f - int(f)


@numba.njit(cache=True, nogil=True, inline="always")
def over_pixel(images, i, color, transmittance, depth, q, ax, ay, total, t_acc, t_front, d,
               p):
    """One pixel of ``over_layer`` (which see): image i's sample whose first tap is its
    pixel q (the other taps' weights ax, ay from ``layer_sample``; at scale 1 pixel q
    itself) under total[p], t_acc[p], d[p]. Returns 1 where t_acc[p] fell to
    MIN_TRANSMITTANCE here, else 0: the per-pixel maths that the CUDA backend compiles as a
    device function too."""
    t = t_acc[p]
    if t <= MIN_TRANSMITTANCE:
        return 0
    w = images[i, IM_WIDTH]
    if images[i, IM_SCALE] == 1:
        r, g, b, tr, dq = (color[q, 0], color[q, 1], color[q, 2], transmittance[q], depth[q])
    else:
        w00 = (1.0 - ax) * (1.0 - ay)
        w01 = ax * (1.0 - ay)
        w10 = (1.0 - ax) * ay
        w11 = ax * ay
        q10 = q + w
        tr = (w00 * transmittance[q] + w01 * transmittance[q + 1]
              + w10 * transmittance[q10] + w11 * transmittance[q10 + 1])
        if tr == 1.0:
            return 0  # nothing there
        r = (w00 * color[q, 0] + w01 * color[q + 1, 0] + w10 * color[q10, 0]
             + w11 * color[q10 + 1, 0])
        g = (w00 * color[q, 1] + w01 * color[q + 1, 1] + w10 * color[q10, 1]
             + w11 * color[q10 + 1, 1])
        b = (w00 * color[q, 2] + w01 * color[q + 1, 2] + w10 * color[q10, 2]
             + w11 * color[q10 + 1, 2])
        dq = depth[q + (w if ay > 0.5 else 0) + (1 if ax > 0.5 else 0)]
    total[p, 0] += t * r
    total[p, 1] += t * g
    total[p, 2] += t * b
    t_next = t * tr
    # the depth: where T first falls to 1/2, from the first layer behind that which has one
    if t_front[p] * t_next <= 0.5 and d[p] == math.inf:
        d[p] = dq
    t_acc[p] = t_next
    return 1 if t_next <= MIN_TRANSMITTANCE else 0


@numba.njit(cache=True, nogil=True, parallel=True)
def combine_layers(images, filled, part_layers, color, transmittance, depth, background,
                   lut, enc, out_color, out_trans, out_depth, image):
    """Each part's layers joined ("over", the module docstring) at every full-resolution
    pixel, over background (3,) (the trainer's colour space), in linear light (``decode``
    with lut, ``composite.DECODE``), summed over the parts into out_color (H, W, 3) (linear)
    and out_trans (H, W) float32, then the frame: image (H, W, 4) float32, their mean
    (``finish_linear_pixel``). out_depth (H, W) float32: the least over the parts of the
    depth at which a part's transmittance first falls to 1/2 (that layer's median depth, or
    the next layer's behind it where that layer's own is none). part_layers: (K, L) int64,
    each part's images front to back, -1 after the last; filled: (T,) bool, whether a tile
    holds anything (``filled_tiles``).

    A part's layers are joined front to back in runs: consecutive layers blended in the
    trainer's colour space, or consecutive summed ones (``IM_SUM``, in linear light); the
    runs then back to front over the background, each in its own space (``fold_runs``:
    encoded with enc, ``composite.ENCODE``, or decoded at each change), so that where a
    blurred layer half covers what is behind it the two mix in linear light, as the lens
    reference's views do. With no summed layer that is one run: ``part_linear``. A run that
    holds nothing in the tile takes the next layer's space instead of closing (an empty run
    changes nothing: ``fold_runs``), as a pixel's own loop on the GPU does for the pixel.

    By 16 x 16 tiles of the frame: a layer none of whose tiles that the tile reads holds
    anything (``layer_listed_over``) is skipped (empty: T = 1, no colour), and a part stops
    where its transmittance has fallen to MIN_TRANSMITTANCE, as a pixel's blend does."""
    h, w = out_trans.shape
    k_parts = part_layers.shape[0]
    n_tx = -(-w // TILE)
    n_tiles = n_tx * (-(-h // TILE))
    for t in numba.prange(n_tiles):
        x0 = (t % n_tx) * TILE
        y0 = (t // n_tx) * TILE
        x1 = min(x0 + TILE, w)
        y1 = min(y0 + TILE, h)
        tw = x1 - x0
        n_px = tw * (y1 - y0)
        total = np.zeros((n_px, 4))  # linear r, g, b and T, summed over the parts
        part = np.empty((n_px, 3))  # a run's colour, in its space
        runs = np.empty((n_px, MAX_LAYERS, 4))  # a part's runs: colour and T
        run_linear = np.zeros(MAX_LAYERS, np.bool_)
        d_min = np.full(n_px, math.inf)
        t_acc = np.empty(n_px)
        t_front = np.empty(n_px)
        d = np.empty(n_px)
        cols = np.empty(TILE, np.int64)
        fracs = np.empty(TILE)
        for k in range(k_parts):
            part[:] = 0.0
            t_acc[:] = 1.0
            t_front[:] = 1.0
            d[:] = math.inf
            n_done = 0
            n_runs = 0
            drawn = False  # whether the run holds anything (else it takes the next's space)
            for j in range(part_layers.shape[1]):
                i = part_layers[k, j]
                if i < 0:
                    break
                linear = images[i, IM_SUM] != 0
                if n_runs == 0 or (linear != run_linear[n_runs - 1] and drawn):
                    if n_runs > 0:
                        n_done = 0
                        for p in range(n_px):
                            n_done += close_run(runs, n_runs - 1, part, t_acc, t_front, p)
                    n_runs += 1
                    drawn = False
                run_linear[n_runs - 1] = linear
                if n_done < n_px and layer_listed_over(images, filled, i, x0, y0, x1, y1):
                    n_done += over_layer(images, i, color, transmittance, depth, x0, y0, x1,
                                         y1, cols, fracs, part, t_acc, t_front, d)
                    drawn = True
            for p in range(n_px):
                close_run(runs, n_runs - 1, part, t_acc, t_front, p)
                fold_runs(runs, p, n_runs, run_linear, background, lut, enc, total)
                total[p, 3] += t_front[p]
                d_min[p] = min(d_min[p], d[p])
        for p in range(n_px):
            x = x0 + p % tw
            y = y0 + p // tw
            for c in range(3):
                out_color[y, x, c] = total[p, c]
            out_trans[y, x] = total[p, 3]
            out_depth[y, x] = d_min[p]
            finish_linear_pixel(out_color, out_trans, y, x, 1.0 / k_parts, image)


@numba.njit(cache=True, nogil=True, inline="always")
def close_run(runs, r, part, t_acc, t_front, p):
    """Pixel p's run r (``combine_layers``) closed: its colour part[p] and transmittance
    t_acc[p] kept in runs[p, r], t_front[p] times t_acc[p], and the next run started (no
    colour; T = 1, or 0 where t_front has fallen to MIN_TRANSMITTANCE: the pixel is done).
    Returns 1 where it is done, else 0: the per-pixel maths that the CUDA backend compiles
    as a device function too."""
    for c in range(3):
        runs[p, r, c] = part[p, c]
        part[p, c] = 0.0
    runs[p, r, 3] = t_acc[p]
    t_front[p] *= t_acc[p]
    if t_front[p] <= MIN_TRANSMITTANCE:
        t_acc[p] = 0.0
        return 1
    t_acc[p] = 1.0
    return 0


@numba.njit(cache=True, nogil=True, inline="always")
def fold_runs(runs, p, n_runs, run_linear, bg, lut, enc, total):
    """Pixel p's part in linear light, added to total[p, :3]: its runs (``combine_layers``)
    back to front over the background bg (3,) (the trainer's space), each "over" what is
    behind it in its own space (run_linear: linear light, else the trainer's), the values
    clipped to [0, 1] and decoded (lut) or encoded (enc) where the space changes: with one
    run in the trainer's space, ``part_linear``'s. An empty run (T = 1, no colour) is
    passed over: most of a pixel's are, and the tables' round trip would only add their
    error; behind a run where the pixel is done (T <= MIN_TRANSMITTANCE) the background is,
    as a pixel's blend stops there, so that how many runs follow it does not matter."""
    r_, g_, b_ = bg[0], bg[1], bg[2]
    start = n_runs - 1
    for r in range(n_runs):
        if runs[p, r, 3] <= MIN_TRANSMITTANCE:  # the pixel is done here: the background next
            start = r
            break
    encoded = True
    for r in range(start, -1, -1):
        t = runs[p, r, 3]
        if t == 1.0 and runs[p, r, 0] == 0.0 and runs[p, r, 1] == 0.0 and runs[p, r, 2] == 0.0:
            continue
        if run_linear[r]:
            if encoded:
                r_ = decode(min(max(r_, 0.0), 1.0), lut)
                g_ = decode(min(max(g_, 0.0), 1.0), lut)
                b_ = decode(min(max(b_, 0.0), 1.0), lut)
                encoded = False
        elif not encoded:
            r_ = encode(min(max(r_, 0.0), 1.0), enc)
            g_ = encode(min(max(g_, 0.0), 1.0), enc)
            b_ = encode(min(max(b_, 0.0), 1.0), enc)
            encoded = True
        r_ = runs[p, r, 0] + t * r_
        g_ = runs[p, r, 1] + t * g_
        b_ = runs[p, r, 2] + t * b_
    if encoded:
        total[p, 0] += decode(min(max(r_, 0.0), 1.0), lut)
        total[p, 1] += decode(min(max(g_, 0.0), 1.0), lut)
        total[p, 2] += decode(min(max(b_, 0.0), 1.0), lut)
    else:
        total[p, 0] += min(max(r_, 0.0), 1.0)
        total[p, 1] += min(max(g_, 0.0), 1.0)
        total[p, 2] += min(max(b_, 0.0), 1.0)
