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

The sharp slab (C_r below ``sharp_coc``) is drawn once, from the lens centre with the whole
lens's blur, instead of once per part.

A blurred layer is *summed* (``IM_SUM``; which ones: ``backends.cpu_gauss.mark_summed``):
its Gaussians' blurred footprints added, not blended, each weighted by the share of it that
sharp views of its layer see (``cpu_gauss.layer_shares``), the pixel's coverage the sum
clamped at 1 (``composite.add``, ``finish_sum``). Blended one "over" another, the blurred
footprints of a surface's overlapping Gaussians no longer cover one another and the surface
over-covers; their seen shares add up to its coverage (docs/maths.md, "Gaussian scenes",
item 2). Each part is joined over the background and decoded before the parts are averaged
(``composite.part_linear``): in linear light, as the lens reference averages its views.

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
                        blend_tile, finish_linear_pixel, part_linear)
from .project import BLUR_OURS, EPS2D, F_CUT, F_OPACITY, move_footprint, project_gaussian

# the columns of an image table (int64, a row per image); IM_SUM: 1 where the image's
# Gaussians are added, not blended "over" (a summed layer, the module docstring)
IM_WIDTH, IM_HEIGHT, IM_SCALE, IM_MARGIN, IM_TILE0, IM_PIXEL0, IM_ROW0, IM_ROW1, IM_SUM = range(9)
N_IM = 9


def image_table(images) -> np.ndarray:
    """(I, N_IM) int64 from (width, height, scale, margin, row0, row1[, summed]) per image:
    their tiles and pixels numbered one image after another (``IM_TILE0``, ``IM_PIXEL0``);
    summed 0 where not given."""
    table = np.zeros((len(images), N_IM), np.int64)
    tile0 = pixel0 = 0
    for i, (w, h, scale, margin, row0, row1, *summed) in enumerate(images):
        table[i] = (w, h, scale, margin, tile0, pixel0, row0, row1,
                    int(summed[0]) if summed else 0)
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
                   spans, antialiased, images, row_image, rows, boxes, visible):
    """Every projection of a layered frame in one loop, each row then moved onto its image.

    Projection j (``project_gaussian`` with our blur): views[j] (4, 4) world to camera,
    campos[j] (3,), cameras[j] (the ``P_*`` columns), of the Gaussians spans[j, 0] ..
    spans[j, 1] into rows, boxes and visible from row spans[j, 2] (the projections' rows
    one run after another, covering them all). share: (N,) the lens visibility, or (0,);
    on a summed image (``IM_SUM``) each Gaussian's weight instead: its opacity and cut
    times it, after the blur (a Gaussian of weight 0 is not drawn). Then row r is moved
    onto images[row_image[r]] where that image's scale is not 1 (``move_footprint``: the
    same footprint in its pixels). Each row is ``project_layer_row``'s."""
    for r in numba.prange(rows.shape[0]):
        project_layer_row(r, positions, scales, rotations, opacity, sh, share, views, campos,
                          cameras, spans, antialiased, images, row_image, rows, boxes, visible)


@numba.njit(cache=True, nogil=True, inline="always")
def project_layer_row(r, positions, scales, rotations, opacity, sh, share, views, campos,
                      cameras, spans, antialiased, images, row_image, rows, boxes, visible):
    """Row r of ``project_layers`` (which see): the per-row maths that the CUDA backend
    compiles as a device function too."""
    j = 0
    while r >= spans[j, 2] + spans[j, 1] - spans[j, 0]:
        j += 1
    a, b, r0 = spans[j, 0], spans[j, 1], spans[j, 2]
    r1 = r0 + b - a
    cam = cameras[j]
    im = row_image[r]
    weighted = share.shape[0] > 0 and images[im, IM_SUM] != 0
    project_gaussian(r - r0, positions[a:b], scales[a:b], rotations[a:b], opacity[a:b],
                     sh[a:b], views[j], campos[j], cam[P_FX], cam[P_FY], cam[P_CX],
                     cam[P_CY], int(cam[P_WIDTH]), int(cam[P_HEIGHT]), cam[P_NEAR], 1e10,
                     EPS2D, antialiased, BLUR_OURS, cam[P_COC_K], cam[P_INV_FOCUS],
                     cam[P_BLUR_VARIANCE],
                     share[a:a] if weighted or share.shape[0] == 0 else share[a:b],
                     rows[r0:r1], boxes[r0:r1], visible[r0:r1])
    if weighted and visible[r]:
        weight = share[a + r - r0]
        if weight > 0.0:
            rows[r, F_OPACITY] *= weight
            rows[r, F_CUT] *= weight
        else:
            visible[r] = False
    scale = images[im, IM_SCALE]
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
                     transmittance, depth, seen):
    """``composite.composite_tiles`` for every tile of every image at once: color (P, 3),
    transmittance (P,), depth (P,) float32 hold image i's pixels from images[i, IM_PIXEL0],
    row by row. The tiles are taken in a Weyl order (``parallel.weyl_stride``): numba gives
    each thread one run of the loop, and a run in table order would be one image's. An
    empty tile is written empty (T = 1) without a blend where it is live (T,) (the
    ``live_tiles`` that ``combine_layers`` may read), and not touched elsewhere: a layer's
    full-resolution image is mostly empty, and writing it all was half the composite's time
    (the guitar at 1920 x 1080, 35 px: 58 of 75 ms for a near layer's 4 images)."""
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
                   done, seen, tid, images[i, IM_SUM] != 0)
        for py in range(ty0, ty1):
            for px in range(tx0, tx1):
                p = (py - ty0) * tw + (px - tx0)
                q = base + py * w + px
                color[q, 0] = state[p, S_R]
                color[q, 1] = state[p, S_G]
                color[q, 2] = state[p, S_B]
                transmittance[q] = state[p, S_T]
                depth[q] = state[p, S_DEPTH]


@numba.njit(cache=True, nogil=True, inline="always")
def layer_listed_over(images, offsets, i, x0, y0, x1, y1):
    """Whether image i lists a Gaussian in a tile that full-resolution pixels [x0, x1) x
    [y0, y1) read (``over_layer``: both taps of each sample along an axis, at scale 1 the
    pixel itself). Where none does, every pixel they read is empty (T = 1, no colour), so
    the layer is skipped. Where one does, every tile they read is a ``live_tiles`` one, so
    was written (``composite_images``): a frame tile's samples of a coarse image, like one
    pixel's two taps, span at most two of its tiles along an axis, each then the listed
    tile or its neighbour; at scale 1 the frame's tile is the image's."""
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
            if offsets[t + 1] > offsets[t]:
                return True
    return False


@numba.njit(cache=True, nogil=True, inline="always")
def over_layer(images, i, color, transmittance, depth, x0, y0, x1, y1, cols, fracs, total,
               t_acc, d):
    """Image i "under" the tile [x0, x1) x [y0, y1) of a part's pixels (``combine_layers``):
    total[p, :3] += t_acc[p] C, t_acc[p] *= T, with (C, T) the image's own pixel at scale 1,
    else bilinear between the four nearest of its pixels (pixel (m, m) of an image of scale
    s and margin m is centred on full-resolution point (s/2, s/2)); d[p] takes the depth
    (the nearest pixel's) where t_acc first falls to 1/2 with d[p] still none. Returns how
    many pixels fell to MIN_TRANSMITTANCE. cols, fracs: (TILE,) scratch. Each pixel is
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
                                 fracs[px - x0], ay, total, t_acc, d, (py - y0) * tw + (px - x0))
    return n_done


@numba.njit(cache=True, nogil=True, inline="always")
def layer_sample(x, inv, m):
    """(first tap, the second tap's weight): where full-resolution pixel x's centre falls
    on an image of scale 1/inv and margin m, along one axis (``over_layer``)."""
    f = (x + 0.5) * inv + m - 0.5  # >= 0: a coarse image has a margin
    return int(f), f - int(f)


@numba.njit(cache=True, nogil=True, inline="always")
def over_pixel(images, i, color, transmittance, depth, q, ax, ay, total, t_acc, d, p):
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
    if t_next <= 0.5 and d[p] == math.inf:
        d[p] = dq
    t_acc[p] = t_next
    return 1 if t_next <= MIN_TRANSMITTANCE else 0


@numba.njit(cache=True, nogil=True, parallel=True)
def combine_layers(images, offsets, part_layers, color, transmittance, depth, background,
                   lut, out_color, out_trans, out_depth, image):
    """Each part's layers joined front to back ("over", the module docstring) at every
    full-resolution pixel, over background (3,) (the trainer's colour space) and decoded
    (``part_linear`` with lut, ``composite.DECODE``), summed over the parts into out_color
    (H, W, 3) (linear) and out_trans (H, W) float32, then the frame: image (H, W, 4)
    float32, their mean (``finish_linear_pixel``). out_depth (H, W) float32: the least
    over the parts of the depth at which a part's transmittance first falls to 1/2 (that
    layer's median depth, or the next layer's behind it where that layer's own is none).
    part_layers: (K, L) int64, each part's images front to back, -1 after the last;
    offsets: ``bin_images``'s, each tile's list.

    By 16 x 16 tiles of the frame: a layer none of whose tiles that the tile reads lists a
    Gaussian (``layer_listed_over``) is skipped (empty: T = 1, no colour), and a part stops where its transmittance has fallen
    to MIN_TRANSMITTANCE, as a pixel's blend does."""
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
        part = np.empty((n_px, 3))  # a part's colour, the trainer's space
        d_min = np.full(n_px, math.inf)
        t_acc = np.empty(n_px)
        d = np.empty(n_px)
        cols = np.empty(TILE, np.int64)
        fracs = np.empty(TILE)
        for k in range(k_parts):
            part[:] = 0.0
            t_acc[:] = 1.0
            d[:] = math.inf
            n_done = 0
            for j in range(part_layers.shape[1]):
                i = part_layers[k, j]
                if i < 0 or n_done == n_px:
                    break
                if layer_listed_over(images, offsets, i, x0, y0, x1, y1):
                    n_done += over_layer(images, i, color, transmittance, depth, x0, y0, x1,
                                         y1, cols, fracs, part, t_acc, d)
            for p in range(n_px):
                for c in range(3):
                    total[p, c] += part_linear(part[p, c], t_acc[p], background[c], lut)
                total[p, 3] += t_acc[p]
                d_min[p] = min(d_min[p], d[p])
        for p in range(n_px):
            x = x0 + p % tw
            y = y0 + p // tw
            for c in range(3):
                out_color[y, x, c] = total[p, c]
            out_trans[y, x] = total[p, 3]
            out_depth[y, x] = d_min[p]
            finish_linear_pixel(out_color, out_trans, y, x, 1.0 / k_parts, image)
