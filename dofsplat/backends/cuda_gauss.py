"""The GPU pipeline of a Gaussian scene's frame (``device="cuda"``): ``cpu_gauss``'s stages as
numba-cuda kernels, from the same per-Gaussian and per-pixel maths.

    (LOD cut, layer order on the host) -> project -> bin to tiles, sorted -> composite
    front to back -> (the lens in layers: join the layers) -> background, to linear RGB ->
    the image and depth copied to the host

As in ``backends.cuda``, nothing per Gaussian or per pixel is written twice: ``device_twin``
compiles the CPU's own functions again as device functions:

    project_gaussian (gauss/project.py, with sh_color), project_shifted_view and
    move_footprint; gaussian_alpha, blend, start_pixel, seen_share, lens_share,
    best_view_share, linear_pixel, finish_pixel with decode and encode
    (gauss/composite.py); project_layer_row, mark_live, layer_listed_over, layer_sample,
    over_pixel, close_run, fold_runs, listed_span, blur_row_pixel, blur_column_pixel
    (gauss/layers.py)

What is written here is only the parallel structure around them. Every pass is drawn as
images of a table (``gauss.layers.image_table``: one image for a pass drawn whole, the
layers of every lens part, the lens visibility's views), as the CPU's ``bin_images`` and
``composite_images`` draw them:

* project: one thread per row (a Gaussian, or a Gaussian in one layer's projection);
* bin: tile-row pairs counted per tile with atomics, offsets by a prefix sum, filled with
  atomics as int64 keys, each tile's keys sorted (``backends.cuda._sort_keys``, the bitonic
  sort, one block per tile). A pass's keys are the depth's float32 bits above the row
  (positive floats order as their bits do): nearest first, equal depths in row order, as
  the CPU's stable ``depth_order``. The layered frame's are the row alone: the CPU lists a
  layer's rows in memory order (``cpu_gauss.layer_order``: nearest first by the float64
  depth from the lens centre), which the rows' own depths (float32, each from its part's
  camera) need not repeat where they tie or round apart;
* composite: one block per 16 x 16 tile of any image, one thread per pixel, the tile's rows
  loaded into shared memory in batches and blended in order (``gaussian_alpha``,
  ``blend``); the block stops when all its pixels are done. An empty tile that is not
  live (``live_tiles``: one thread per tile) is left unwritten, as on the CPU; With lens visibility each pixel
  adds the alpha T it saw to its row's total (an atomic add, where the CPU keeps a row per
  thread: the shares differ by float rounding only);
* a summed layer's image blurred from its sharp view (``blur_rows``, ``blur_columns``): one
  launch of each per summed image, one thread per pixel;
* the layers joined (``combine_layers``): one thread per pixel of the frame, each part's
  layers front to back in runs (``over_pixel``, ``close_run``), a layer skipped where no
  tile its sample reads holds anything (``layer_listed_over``, ``filled_tiles``), which
  changes nothing, the runs folded back to front (``fold_runs``), as on the CPU.

The LOD cut and the layer order are the CPU's (``cpu_gauss.in_layers``, ``lod_cut``): the
Gaussians they gather are uploaded each frame. A scene drawn as it is (a pinhole, or no LOD
with the parts drawn whole) keeps its arrays on the ``Gaussians`` object, like the
surfels' (make a new ``Gaussians`` rather than editing its arrays). ``cpu_gauss.LAYERS`` is
read at each frame: with it off the GPU draws each part of the lens whole, as the CPU then
does (59-184 ms at 1920 x 1080 on an H200, bench/RESULTS.md).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numba
import numpy as np
from numba import cuda

from ..colors import linear_to_srgb
from ..frame import RenderResult, coc_coefficients, lens_parts
from ..gauss.composite import (DECODE, ENCODE, MIN_TRANSMITTANCE, N_STATE, S_B, S_DEPTH, S_G,
                               S_R, S_T, TILE, add_linear_part, best_view_share, blend,
                               finish_linear_pixel, finish_pixel, gaussian_alpha, lens_share,
                               linear_pixel, seen_share, start_pixel)
from ..gauss.layers import (IM_HEIGHT, IM_MARGIN, IM_PIXEL0, IM_ROW0, IM_ROW1, IM_SCALE,
                            IM_SHARP, IM_SOURCE, IM_SUM, IM_TILE0, IM_WIDTH, MAX_LAYERS, N_BLUR,
                            blur_column_pixel, blur_row_pixel, close_run, fold_runs,
                            image_table, layer_listed_over, layer_sample, listed_rows_span,
                            listed_span, mark_live, over_pixel, project_layer_row)
from ..gauss.project import (BLUR_NONE, EPS2D, F_CA, F_CB, F_CC, F_CUT, F_DEPTH, F_OPACITY,
                             F_X, F_Y, N_FIELDS, intrinsics, project_gaussian,
                             project_shifted_view, view_matrix)
from ..gaussians import Gaussians
from . import cpu_gauss
from . import cuda as surfel_cuda
from .cpu_gauss import (BLURS, blur_variance, blurred_layers, in_layers, layer_plan, lod_cut,
                        part_count, shifted_views, summed_layers, visibility_cameras,
                        weighed_layers)
from .cuda import (SIMULATOR, THREADS, _WS, _blocks, _Clock, _fill, _scalar, _upload, device_twin,
                   exclusive_scan)

_project_gaussian = device_twin(project_gaussian)
_project_shifted_view = device_twin(project_shifted_view)
_project_layer_row = device_twin(project_layer_row)
_gaussian_alpha = device_twin(gaussian_alpha)
_blend = device_twin(blend)
_linear_pixel = device_twin(linear_pixel)
_add_linear_part = device_twin(add_linear_part)
_finish_linear_pixel = device_twin(finish_linear_pixel)
_start_pixel = device_twin(start_pixel)
_seen_share = device_twin(seen_share)
_lens_share = device_twin(lens_share)
_best_view_share = device_twin(best_view_share)
_finish_pixel = device_twin(finish_pixel)
_mark_live = device_twin(mark_live)
_layer_listed_over = device_twin(layer_listed_over)
_layer_sample = device_twin(layer_sample)
_over_pixel = device_twin(over_pixel)
_close_run = device_twin(close_run)
_fold_runs = device_twin(fold_runs)
_blur_row_pixel = device_twin(blur_row_pixel)
_listed_span = device_twin(listed_span)
_blur_column_pixel = device_twin(blur_column_pixel)
_listed_rows_span = device_twin(listed_rows_span)

PIXELS = TILE * TILE  # threads per block of the compositing: one per pixel of a tile
INDEX_BITS = 32  # a sort key: the depth's bits above the row (or the row alone)
INDEX_MASK = (1 << INDEX_BITS) - 1


# -- kernels ----------------------------------------------------------------------------------


@cuda.jit
def _project(positions, scales, rotations, opacity, sh, view, campos, fx, fy, cx, cy, width,
             height, near, far, eps2d, antialiased, blur, coc_k, inv_focus, blur_var, share,
             rows, boxes, visible):
    i = cuda.grid(1)
    if i < positions.shape[0]:
        _project_gaussian(i, positions, scales, rotations, opacity, sh, view, campos, fx, fy,
                          cx, cy, width, height, near, far, eps2d, antialiased, blur, coc_k,
                          inv_focus, blur_var, share, rows, boxes, visible)


@cuda.jit
def _project_layers(positions, scales, rotations, opacity, sh, share, views, campos, cameras,
                    spans, antialiased, sharp_eps2d, images, row_image, rows, boxes, visible):
    """One thread per row: ``gauss.layers.project_layers``."""
    r = cuda.grid(1)
    if r < rows.shape[0]:
        _project_layer_row(r, positions, scales, rotations, opacity, sh, share, views, campos,
                           cameras, spans, antialiased, sharp_eps2d, images, row_image, rows,
                           boxes, visible)


@cuda.jit
def _project_shifted_views(positions, scales, rotations, opacity, sh, view, campos, fx, fy, cx,
                           cy, width, height, near, far, eps2d, antialiased, margin, shifts,
                           inv_focus, no_share, rows, boxes, visible, view_rows, view_boxes,
                           view_visible):
    """One thread per Gaussian: ``gauss.project.project_shifted_views``."""
    i = cuda.grid(1)
    if i < positions.shape[0]:
        _project_shifted_view(i, positions, scales, rotations, opacity, sh, view, campos, fx,
                              fy, cx, cy, width, height, near, far, eps2d, antialiased, margin,
                              shifts, inv_focus, no_share, rows, boxes, visible, view_rows,
                              view_boxes, view_visible)


@cuda.jit
def _count_pairs(images, row_image, boxes, visible, counts, totals):
    """Tile-row pairs per tile of the row's image (atomics; a box is [x0, x1) x [y0, y1)),
    and into totals the visible rows and their boxes' pixels (the stats' splats and
    fragments)."""
    block = cuda.shared.array(2, numba.int64)
    if cuda.threadIdx.x < 2:
        block[cuda.threadIdx.x] = 0
    cuda.syncthreads()
    r = cuda.grid(1)
    if r < visible.shape[0] and visible[r]:
        i = row_image[r]
        t0 = images[i, IM_TILE0]
        n_tx = -(-images[i, IM_WIDTH] // TILE)
        for ty in range(boxes[r, 2] // TILE, (boxes[r, 3] - 1) // TILE + 1):
            for tx in range(boxes[r, 0] // TILE, (boxes[r, 1] - 1) // TILE + 1):
                cuda.atomic.add(counts, t0 + ty * n_tx + tx, 1)
        cuda.atomic.add(block, 0, 1)
        cuda.atomic.add(block, 1, numba.int64(boxes[r, 1] - boxes[r, 0])
                        * numba.int64(boxes[r, 3] - boxes[r, 2]))
    cuda.syncthreads()
    if cuda.threadIdx.x < 2:
        cuda.atomic.add(totals, cuda.threadIdx.x, block[cuda.threadIdx.x])


@cuda.jit
def _fill_keys(images, row_image, boxes, visible, depth_bits, by_depth, cursor, keys):
    """Each visible row's sort key into the lists of the tiles it touches (any order): the
    row, below its depth's bits where by_depth."""
    r = cuda.grid(1)
    if r < visible.shape[0] and visible[r]:
        key = numba.int64(r)
        if by_depth:
            key |= numba.int64(depth_bits[r, F_DEPTH]) << INDEX_BITS
        i = row_image[r]
        t0 = images[i, IM_TILE0]
        n_tx = -(-images[i, IM_WIDTH] // TILE)
        for ty in range(boxes[r, 2] // TILE, (boxes[r, 3] - 1) // TILE + 1):
            for tx in range(boxes[r, 0] // TILE, (boxes[r, 1] - 1) // TILE + 1):
                keys[cuda.atomic.add(cursor, t0 + ty * n_tx + tx, 1)] = key


@cuda.jit
def _composite(rows, boxes, offsets, keys, tile_image, images, live, color, trans, depth,
               seen, track, lut):
    """One block per tile of any image, one thread per pixel: the tile's rows in key order,
    blended front to back (``gauss.layers.composite_images``, pixel by pixel) into color
    (P, 3), trans (P,), depth (P,) from the image's IM_PIXEL0 (a sharp view's in linear
    light, ``linear_pixel`` with lut); an empty tile is written (T = 1) only where live
    (T,) (``live_tiles``), or everywhere where live is (0,)."""
    batch = cuda.shared.array((PIXELS, N_FIELDS), numba.float32)
    box = cuda.shared.array((PIXELS, 4), numba.int32)
    gid = cuda.shared.array(PIXELS, numba.int32)
    state = cuda.local.array((1, N_STATE), numba.float64)
    t = cuda.blockIdx.x
    tid = cuda.threadIdx.x
    if live.shape[0] > 0 and offsets[t + 1] == offsets[t] and not live[t]:
        return  # never read (the whole block leaves, before any barrier)
    i = tile_image[t]
    width, height = images[i, IM_WIDTH], images[i, IM_HEIGHT]
    n_tx = -(-width // TILE)
    local = t - images[i, IM_TILE0]
    py = (local // n_tx) * TILE + tid // TILE
    px = (local % n_tx) * TILE + tid % TILE
    inside = py < height and px < width
    _start_pixel(state, 0)
    done = not inside
    lo = offsets[t]
    hi = offsets[t + 1]
    for start in range(lo, hi, PIXELS):
        if cuda.syncthreads_count(numba.int32(done)) == PIXELS:
            break  # every pixel of the tile is done (the same answer in every thread)
        e = start + tid
        if e < hi:
            g = numba.int32(keys[e] & INDEX_MASK)
            gid[tid] = g
            for f in range(N_FIELDS):
                batch[tid, f] = rows[g, f]
            for f in range(4):
                box[tid, f] = boxes[g, f]
        cuda.syncthreads()
        for b in range(min(PIXELS, hi - start)):
            if done:
                break
            if not (box[b, 0] <= px < box[b, 1] and box[b, 2] <= py < box[b, 3]):
                continue
            alpha = _gaussian_alpha(batch[b, F_X], batch[b, F_Y], batch[b, F_CA],
                                    batch[b, F_CB], batch[b, F_CC], batch[b, F_OPACITY],
                                    batch[b, F_CUT], px, py)
            if alpha == 0.0:
                continue
            w = _blend(state, 0, alpha, batch, b)
            if w < 0.0:
                done = True
            elif track:
                cuda.atomic.add(seen, gid[b], w)
        cuda.syncthreads()
    if inside:
        if images[i, IM_SHARP] != 0:
            _linear_pixel(state, 0, lut)
        q = images[i, IM_PIXEL0] + py * width + px
        color[q, 0] = state[0, S_R]
        color[q, 1] = state[0, S_G]
        color[q, 2] = state[0, S_B]
        trans[q] = state[0, S_T]
        depth[q] = state[0, S_DEPTH]


@cuda.jit
def _live_tiles(offsets, images, tile_image, live):
    """One thread per tile: ``gauss.layers.live_tiles`` (live all False before)."""
    t = cuda.grid(1)
    if t < tile_image.shape[0]:
        _mark_live(offsets, images, tile_image, t, live)


@cuda.jit
def _combine_layers(images, filled, part_layers, color, trans, depth, bg, lut, enc, out_color,
                    out_trans, out_depth, image):
    """One thread per pixel of the frame: ``gauss.layers.combine_layers``, each part's layers
    joined front to back in runs (``over_pixel``, ``close_run``), a layer none of whose
    tiles that the pixel's sample reads holds anything skipped (``layer_listed_over``,
    ``filled_tiles``), the runs back to front over the background in linear light
    (``fold_runs``), then the frame (``finish_linear_pixel``)."""
    total = cuda.local.array((1, 4), numba.float64)  # linear r, g, b and T, over the parts
    part = cuda.local.array((1, 3), numba.float64)  # a run's colour, in its space
    runs = cuda.local.array((1, MAX_LAYERS, 4), numba.float64)
    run_linear = cuda.local.array(MAX_LAYERS, numba.boolean)
    t_acc = cuda.local.array(1, numba.float64)
    t_front = cuda.local.array(1, numba.float64)
    d = cuda.local.array(1, numba.float64)
    h, w = out_trans.shape
    g = cuda.grid(1)
    if g >= h * w:
        return
    y = g // w
    x = g % w
    for c in range(4):
        total[0, c] = 0.0
    d_min = math.inf
    k_parts = part_layers.shape[0]
    for k in range(k_parts):
        for c in range(3):
            part[0, c] = 0.0
        t_acc[0] = 1.0
        t_front[0] = 1.0
        d[0] = math.inf
        n_runs = 0
        drawn = False
        for j in range(part_layers.shape[1]):
            i = part_layers[k, j]
            if i < 0:
                break
            linear = images[i, IM_SUM] != 0
            if n_runs == 0 or (linear != run_linear[n_runs - 1] and drawn):
                if n_runs > 0:
                    _close_run(runs, n_runs - 1, part, t_acc, t_front, 0)
                n_runs += 1
                drawn = False
            run_linear[n_runs - 1] = linear
            if t_acc[0] > MIN_TRANSMITTANCE and _layer_listed_over(images, filled, i, x, y,
                                                                   x + 1, y + 1):
                drawn = True
                inv = 1.0 / images[i, IM_SCALE]
                col, ax = _layer_sample(x, inv, images[i, IM_MARGIN])
                row, ay = _layer_sample(y, inv, images[i, IM_MARGIN])
                _over_pixel(images, i, color, trans, depth,
                            images[i, IM_PIXEL0] + row * images[i, IM_WIDTH] + col, ax, ay,
                            part, t_acc, t_front, d, 0)
        _close_run(runs, n_runs - 1, part, t_acc, t_front, 0)
        _fold_runs(runs, 0, n_runs, run_linear, bg, lut, enc, total)
        total[0, 3] += t_front[0]
        d_min = min(d_min, d[0])
    for c in range(3):
        out_color[y, x, c] = total[0, c]
    out_trans[y, x] = total[0, 3]
    out_depth[y, x] = d_min
    _finish_linear_pixel(out_color, out_trans, y, x, 1.0 / k_parts, image)


@cuda.jit
def _blur_rows(images, blurs, i, offsets, color, trans, scratch):
    """One thread per pixel of scratch (the sharp view's rows, image i's columns):
    ``gauss.layers.blur_rows``."""
    g = cuda.grid(1)
    k = images[i, IM_SOURCE]
    w_i = images[i, IM_WIDTH]
    if g >= images[k, IM_HEIGHT] * w_i:
        return
    y = g // w_i
    p0, p1 = _listed_span(images, offsets, k, y)
    _blur_row_pixel(images, blurs, i, offsets, color, trans, scratch, y, g % w_i, p0, p1)


@cuda.jit
def _blur_columns(images, blurs, i, offsets, scratch, color, trans, depth, filled):
    """One thread per pixel of image i: ``gauss.layers.blur_columns``."""
    g = cuda.grid(1)
    w_i = images[i, IM_WIDTH]
    if g < images[i, IM_HEIGHT] * w_i:
        y = g // w_i
        p0, p1 = _listed_rows_span(images, blurs, i, offsets, y)
        _blur_column_pixel(images, blurs, i, scratch, color, trans, depth, filled, y, g % w_i,
                           p0, p1)


@cuda.jit
def _filled_tiles(offsets, filled):
    """One thread per tile: ``gauss.layers.filled_tiles``."""
    t = cuda.grid(1)
    if t < filled.shape[0]:
        filled[t] = offsets[t + 1] > offsets[t]


@cuda.jit
def _accumulate(color, trans, depth, part_color, part_trans, part_depth, bg, lut):
    """One thread per pixel: one lens part's pass into the sums, over the background in
    linear light (``add_linear_part``), depth the nearest."""
    i = cuda.grid(1)
    w = trans.shape[1]
    if i < trans.shape[0] * w:
        y, x = i // w, i % w
        _add_linear_part(part_color, part_trans, y, x, bg, lut, color, trans)
        depth[y, x] = min(depth[y, x], part_depth[y, x])


@cuda.jit
def _finish_linear(color, trans, scale, out):
    """One thread per pixel: the parts' linear sums to their mean, linear RGBA."""
    i = cuda.grid(1)
    w = trans.shape[1]
    if i < trans.shape[0] * w:
        _finish_linear_pixel(color, trans, i // w, i % w, scale, out)


@cuda.jit
def _finish(color, trans, scale, bg, lut, out):
    """One thread per pixel: the composite over the background, to linear RGBA."""
    i = cuda.grid(1)
    w = trans.shape[1]
    if i < trans.shape[0] * w:
        _finish_pixel(color, trans, i // w, i % w, scale, bg, lut, out)


@cuda.jit
def _keep_best_share(rows, visible, seen, best):
    i = cuda.grid(1)
    if i < visible.shape[0] and visible[i]:
        best[i] = max(best[i], _seen_share(rows, i, numba.float64(seen[i])))


@cuda.jit
def _finish_shares(best):
    i = cuda.grid(1)
    if i < best.shape[0]:
        best[i] = _lens_share(best[i])


@cuda.jit
def _best_view_shares(rows, visible, seen, n, best):
    """One thread per Gaussian: ``gauss.composite.best_view_shares`` (seen: (1, V n))."""
    i = cuda.grid(1)
    if i < n:
        best[i] = _best_view_share(rows, visible, seen, n, i)


# -- the stages on the host -------------------------------------------------------------------

_TABLES = {}  # the colour tables on the GPU, uploaded once (``_coded``)


def _decode():
    """``gauss.composite.DECODE`` (the sRGB decoding table) on the GPU."""
    return _coded(DECODE)


def _coded(table: np.ndarray):
    """A colour table (``gauss.composite.DECODE``, ``ENCODE``) on the GPU, uploaded once."""
    key = id(table)
    if key not in _TABLES:
        _TABLES[key] = _upload(table)
    return _TABLES[key]



def device_gaussians(scene) -> dict:
    """The scene's arrays on the GPU: kept on a ``Gaussians`` object between frames (keyed by
    its arrays' identity), uploaded afresh for a LOD cut or the layer order (a
    ``GaussianArrays`` made per frame, which would only hold on to device memory)."""
    names = ("positions", "scales", "rotations", "opacity", "sh")
    key = tuple((getattr(scene, n).__array_interface__["data"][0], getattr(scene, n).shape)
                for n in names)
    kept = getattr(scene, "_device", None)
    if kept is not None and kept[0] == key:
        return kept[1]
    arrays = {n: _upload(np.asarray(getattr(scene, n), np.float32)) for n in names}
    if isinstance(scene, Gaussians):
        scene._device = (key, arrays)
    return arrays


def project_cuda(arrays: dict, camera, lens, settings, blur: str = "ours", share=None):
    """(rows (N, N_FIELDS), boxes (N, 4), visible (N,)) on the GPU: ``cpu_gauss.project``."""
    n = arrays["positions"].shape[0]
    rows = _WS.get("g.rows", (n, N_FIELDS), np.float32)
    boxes = _WS.get("g.boxes", (n, 4), np.int32)
    visible = _WS.get("g.visible", (n,), np.bool_)
    fx, fy, cx, cy = intrinsics(camera)
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    mode = BLURS[blur] if coc_k > 0.0 else BLUR_NONE
    near = camera.near if camera.frustum is None else camera.frustum[4]
    if share is None:
        share = _WS.get("g.no_share", (0,), np.float32)
    if n:
        _project[_blocks(n), THREADS](
            arrays["positions"], arrays["scales"], arrays["rotations"], arrays["opacity"],
            arrays["sh"], _upload(view_matrix(camera)), _upload(np.asarray(camera.eye, np.float64)),
            fx, fy, cx, cy, camera.width, camera.height, near, 1e10, EPS2D,
            bool(settings.gaussian_antialiased), mode, coc_k, inv_focus, blur_variance(lens),
            share, rows, boxes, visible)
    return rows, boxes, visible


@dataclass
class DeviceImages:
    """An image table (``gauss.layers.image_table``) on the GPU, with what its kernels look up."""

    table: object  # (I, N_IM) int64
    tile_image: object  # (T,) int32: each tile's image
    row_image: object  # (R,) int32: each row's image (image i's rows are IM_ROW0 .. IM_ROW1)
    n_images: int
    n_tiles: int
    n_pixels: int


def device_images(table: np.ndarray, prefix: str = "g") -> DeviceImages:
    """The table on the GPU (buffers named by prefix). Its images' rows must run one after
    another from row 0, as every table of a frame's does; for one image (a pass drawn whole)
    the lookups are ``_zeros``, not uploaded."""
    n_images = len(table)
    per_tile = (-(-table[:, IM_WIDTH] // TILE)) * (-(-table[:, IM_HEIGHT] // TILE))
    per_image = table[:, IM_ROW1] - table[:, IM_ROW0]
    n_tiles, n_rows = int(per_tile.sum()), int(per_image.sum())
    n_pixels = int((table[:, IM_WIDTH] * table[:, IM_HEIGHT]).sum())
    if n_images == 1:
        tile_image, row_image = _zeros(n_tiles), _zeros(n_rows)
    else:
        ids = np.arange(n_images, dtype=np.int32)
        tile_image = _WS.get(f"{prefix}.tile_image", (n_tiles,), np.int32)
        row_image = _WS.get(f"{prefix}.row_image", (n_rows,), np.int32)
        if n_tiles:
            tile_image.copy_to_device(np.repeat(ids, per_tile))
        if n_rows:
            row_image.copy_to_device(np.repeat(ids, per_image))
    return DeviceImages(_upload(table), tile_image, row_image, n_images, n_tiles, n_pixels)


_ZEROS = None  # a device array of int32 zeros, only ever read (``_zeros``)


def _zeros(n: int):
    """(n,) int32 zeros on the GPU: one buffer, filled when it grows, for every pass's
    lookups (not two fills per pass)."""
    global _ZEROS
    if _ZEROS is None or _ZEROS.shape[0] < n:
        _ZEROS = cuda.device_array(max(n, 2 * (0 if _ZEROS is None else _ZEROS.shape[0]), 1024),
                                   np.int32)
        _fill[_blocks(_ZEROS.shape[0]), THREADS](_ZEROS, 0)
    return _ZEROS[:n]


def one_image(width: int, height: int, n: int) -> DeviceImages:
    """The table of a pass drawn whole: one width x height image of rows 0 .. n."""
    return device_images(image_table([(width, height, 1, 0, 0, n)]))


def bin_cuda(images: DeviceImages, rows, boxes, visible, by_depth: bool = True):
    """(offsets (T + 1,) int64, keys (P,) int64, totals): the visible rows of every image
    listed per tile, in key order (``INDEX_MASK`` holds the row): nearest first, equal depths
    in row order, where by_depth (``cpu_gauss``'s depth_order then bin_tiles or
    bin_images), else in row order (``bin_images`` of the rows in order: the layered frame's
    memory order); totals: [pairs, visible rows, their boxes' pixels]."""
    n = visible.shape[0]
    n_tiles = images.n_tiles
    counts = _WS.get("g.counts", (n_tiles,), np.int64)
    _fill[_blocks(n_tiles), THREADS](counts, 0)
    totals = _WS.get("g.totals", (2,), np.int64)
    _fill[1, 2](totals, 0)
    if n:
        _count_pairs[_blocks(n), THREADS](images.table, images.row_image, boxes, visible,
                                          counts, totals)
    offsets = _WS.get("g.offsets", (n_tiles + 1,), np.int64)
    exclusive_scan(counts, n_tiles, offsets, "g.scan")
    n_pairs = _scalar(offsets, n_tiles)
    keys = _WS.get("g.keys", (n_pairs,), np.int64)
    if n_pairs:
        cursor = _WS.get("g.cursor", (n_tiles,), np.int64)
        cursor.copy_to_device(offsets[:n_tiles])
        _fill_keys[_blocks(n), THREADS](images.table, images.row_image, boxes, visible,
                                        rows.view(np.int32), by_depth, cursor, keys)
        surfel_cuda._sort_keys[n_tiles, THREADS](offsets, keys)  # (a module attribute: tests note it)
    return offsets, keys, [n_pairs, *(int(v) for v in totals.copy_to_host())]


def composite_cuda(rows, boxes, offsets, keys, images: DeviceImages, prefix: str = "g",
                   seen=None, live=None):
    """(color (P, 3), transmittance (P,), depth (P,)) on the GPU, every image's pixels from
    its IM_PIXEL0, in buffers named by prefix; seen: a float32 device array to add each
    row's alpha T into, or None; live: a bool device array (T,), the empty tiles to write
    (``live_tiles``), or None for all."""
    n_px = images.n_pixels
    color = _WS.get(f"{prefix}.color", (n_px, 3), np.float32)
    trans = _WS.get(f"{prefix}.trans", (n_px,), np.float32)
    depth = _WS.get(f"{prefix}.depth", (n_px,), np.float32)
    track = seen is not None
    if seen is None:
        seen = _WS.get("g.no_seen", (0,), np.float32)
    if live is None:
        live = _WS.get("g.all_live", (0,), np.bool_)
    if images.n_tiles:
        _composite[images.n_tiles, PIXELS](rows, boxes, offsets, keys, images.tile_image,
                                           images.table, live, color, trans, depth, seen,
                                           track, _decode())
    return color, trans, depth


def draw_cuda(arrays: dict, camera, lens, settings, blur: str = "ours", share=None,
              prefix: str = "g"):
    """One pass on the GPU (``cpu_gauss.draw_gaussians``): color (H, W, 3), transmittance
    (H, W), depth (H, W) (device buffers named by prefix) and stats."""
    w, h = camera.width, camera.height
    rows, boxes, visible = project_cuda(arrays, camera, lens, settings, blur, share)
    images = one_image(w, h, rows.shape[0])
    offsets, keys, totals = bin_cuda(images, rows, boxes, visible)
    color, trans, depth = composite_cuda(rows, boxes, offsets, keys, images, prefix)
    return (color.reshape(h, w, 3), trans.reshape(h, w), depth.reshape(h, w),
            dict(zip(("tile_pairs", "splats_rendered", "fragments"), totals)))


def draw_passes_cuda(arrays: dict, camera, lens, parts, settings, blur: str, share):
    """``cpu_gauss.draw_passes`` on the GPU: one pass (parts None), or each part drawn whole,
    over the background and averaged in linear light: (image (H, W, 4) linear RGBA, depth,
    stats), device buffers."""
    h, w = camera.height, camera.width
    image = _WS.get("g.image", (h, w, 4), np.float32)
    bg = _upload(linear_to_srgb(np.asarray(settings.background, np.float64)))
    if parts is None:
        color, trans, depth, counts = draw_cuda(arrays, camera, lens, settings, blur, share)
        _finish[_blocks(h * w), THREADS](color, trans, 1.0, bg, _decode(), image)
        return image, depth, counts
    color = _WS.get("g.sum.color", (h, w, 3), np.float32)
    trans = _WS.get("g.sum.trans", (h, w), np.float32)
    depth = _WS.get("g.sum.depth", (h, w), np.float32)
    _fill[_blocks(h * w * 3), THREADS](color.reshape(h * w * 3), 0.0)
    _fill[_blocks(h * w), THREADS](trans.reshape(h * w), 0.0)
    _fill[_blocks(h * w), THREADS](depth.reshape(h * w), np.inf)
    counts = {"tile_pairs": 0, "splats_rendered": 0, "fragments": 0}
    for cam in parts.cameras:
        c, t, d, st = draw_cuda(arrays, cam, parts.residual, settings, blur, share)
        for key in counts:  # summed over the parts, as the CPU's stats are
            counts[key] += st[key]
        _accumulate[_blocks(h * w), THREADS](color, trans, depth, c, t, d, bg, _decode())
    _finish_linear[_blocks(h * w), THREADS](color, trans, 1.0 / len(parts.cameras), image)
    return image, depth, counts


def lens_visibility_cuda(arrays: dict, camera, lens, settings, views: int = 6, scale: int = 2):
    """(N,) float32 on the GPU: ``cpu_gauss.lens_visibility``, from the same views."""
    n = arrays["positions"].shape[0]
    best = _WS.get("g.best", (n,), np.float32)
    seen = _WS.get("g.seen", (n,), np.float32)
    _fill[_blocks(n), THREADS](best, 0.0)
    for cam in visibility_cameras(camera, lens, views, scale):
        rows, boxes, visible = project_cuda(arrays, cam, None, settings)
        images = one_image(cam.width, cam.height, n)
        offsets, keys, _ = bin_cuda(images, rows, boxes, visible)
        _fill[_blocks(n), THREADS](seen, 0.0)
        composite_cuda(rows, boxes, offsets, keys, images, "g.small", seen)
        _keep_best_share[_blocks(n), THREADS](rows, visible, seen, best)
    _finish_shares[_blocks(n), THREADS](best)
    return best


# -- the lens in layers (gauss/layers.py) ------------------------------------------------


def layer_shares_cuda(arrays: dict, positions: np.ndarray, layers, camera, lens, settings):
    """(N,) float32 on the GPU, or None: ``cpu_gauss.layer_shares``, each blurred layer's that
    is not summed weighed from its own views (``lens_visibility_by_shifts_cuda`` on its run of
    the arrays)."""
    weighed = weighed_layers(layers)
    if not weighed:
        return None
    n = len(positions)
    share = _WS.get("g.layer_share", (n,), np.float32)
    _fill[_blocks(n), THREADS](share, 1.0)
    ls = cpu_gauss.LAYERS
    for j in weighed:
        a, b = (int(v) for v in layers.spans[j])
        sub = {key: value[a:b] for key, value in arrays.items()}
        lens_visibility_by_shifts_cuda(sub, positions[a:b], camera, lens, settings,
                                       ls.share_scale, views=ls.share_views,
                                       radius=ls.share_radius, eps2d=ls.share_eps2d,
                                       out=share[a:b])
    return share


def lens_visibility_by_shifts_cuda(arrays: dict, positions: np.ndarray, camera, lens,
                                   settings, scale: int | None = None, *,
                                   views: int | None = None, radius: float = 1.0,
                                   eps2d: float | None = None, out=None) -> object:
    """(N,) float32 on the GPU: ``cpu_gauss.lens_visibility_by_shifts`` (positions: the
    frame's Gaussians' (N, 3), on the host; the same keywords), from the same views: one
    projection moved to each view, every view's tiles composited in one launch, seen sums
    by atomics. out: a device array (N,) to write the shares into, else a workspace's."""
    layers = cpu_gauss.LAYERS
    small, margin, shifts, inv_focus, near, view = shifted_views(
        positions, camera, lens, settings, layers.visibility_views if views is None else views,
        cpu_gauss.visibility_scale_for(positions, camera, lens, settings) if scale is None
        else scale)
    shifts = shifts * radius
    w, h = small.width, small.height
    n, m = len(positions), len(shifts)
    fx, fy, cx, cy = intrinsics(small)
    rows = _WS.get("g.rows", (n, N_FIELDS), np.float32)
    boxes = _WS.get("g.boxes", (n, 4), np.int32)
    visible = _WS.get("g.visible", (n,), np.bool_)
    view_rows = _WS.get("g.view_rows", (m * n, N_FIELDS), np.float32)
    view_boxes = _WS.get("g.view_boxes", (m * n, 4), np.int32)
    view_visible = _WS.get("g.view_visible", (m * n,), np.bool_)
    best = _WS.get("g.best", (n,), np.float32) if out is None else out
    if not n:
        return best
    # (no colour is needed: the SH's constant term alone is the cheapest)
    _project_shifted_views[_blocks(n), THREADS](
        arrays["positions"], arrays["scales"], arrays["rotations"], arrays["opacity"],
        arrays["sh"][:, :1], _upload(view), _upload(np.asarray(small.eye, np.float64)), fx, fy,
        cx + margin, cy + margin, w + 2 * margin, h + 2 * margin, near, 1e10,
        layers.visibility_eps2d if eps2d is None else eps2d,
        bool(settings.gaussian_antialiased), margin, _upload(shifts),
        inv_focus, _WS.get("g.no_share", (0,), np.float32), rows, boxes, visible, view_rows,
        view_boxes, view_visible)
    images = device_images(image_table([(w, h, 1, 0, v * n, (v + 1) * n) for v in range(m)]))
    offsets, keys, _ = bin_cuda(images, view_rows, view_boxes, view_visible)
    seen = _WS.get("g.seen", (m * n,), np.float32)
    _fill[_blocks(m * n), THREADS](seen, 0.0)
    no_tile = _WS.get("g.no_tile", (images.n_tiles,), np.bool_)  # only seen is read
    _fill[_blocks(images.n_tiles), THREADS](no_tile, False)
    composite_cuda(view_rows, view_boxes, offsets, keys, images, "g.small", seen, no_tile)
    _best_view_shares[_blocks(n), THREADS](view_rows, view_visible, seen.reshape(1, m * n), n,
                                           best)
    return best


def draw_layered_cuda(arrays: dict, layers, camera, lens, parts, settings, share):
    """``cpu_gauss.draw_layered`` on the GPU: (image (H, W, 4) linear RGBA, depth (H, W),
    device buffers, and stats). Every projection in one launch (a thread per row), every
    image's tiles in one, the layers joined in one; share: the lens visibility (N,), or None."""
    h, w = camera.height, camera.width
    n = arrays["positions"].shape[0]
    views, campos, cameras, spans, table, part_layers, blurs = layer_plan(n, layers, camera,
                                                                          lens, parts, settings)
    image = _WS.get("g.image", (h, w, 4), np.float32)
    out_depth = _WS.get("g.out.depth", (h, w), np.float32)
    bg = _upload(linear_to_srgb(np.asarray(settings.background, np.float64)))
    if not len(table):  # nothing in the frame: the background
        color = _WS.get("g.out.color", (h, w, 3), np.float32)
        trans = _WS.get("g.out.trans", (h, w), np.float32)
        _fill[_blocks(h * w * 3), THREADS](color.reshape(h * w * 3), 0.0)
        _fill[_blocks(h * w), THREADS](trans.reshape(h * w), 1.0)
        _fill[_blocks(h * w), THREADS](out_depth.reshape(h * w), np.inf)
        _finish[_blocks(h * w), THREADS](color, trans, 1.0, bg, _decode(), image)
        return image, out_depth, {"tile_pairs": 0, "splats_rendered": 0, "fragments": 0,
                                  "layers": 0}
    images = device_images(table)
    n_rows = int(np.sum(spans[:, 1] - spans[:, 0]))
    rows = _WS.get("g.rows", (n_rows, N_FIELDS), np.float32)
    boxes = _WS.get("g.boxes", (n_rows, 4), np.int32)
    visible = _WS.get("g.visible", (n_rows,), np.bool_)
    if share is None:
        share = _WS.get("g.no_share", (0,), np.float32)
    if n_rows:
        _project_layers[_blocks(n_rows), THREADS](
            arrays["positions"], arrays["scales"], arrays["rotations"], arrays["opacity"],
            arrays["sh"], share, _upload(views), _upload(campos), _upload(cameras),
            _upload(spans), bool(settings.gaussian_antialiased), cpu_gauss.LAYERS.sharp_eps2d,
            images.table, images.row_image, rows, boxes, visible)
    offsets, keys, totals = bin_cuda(images, rows, boxes, visible, by_depth=False)
    live = _WS.get("g.live", (images.n_tiles,), np.bool_)
    _fill[_blocks(images.n_tiles), THREADS](live, False)
    _live_tiles[_blocks(images.n_tiles), THREADS](offsets, images.table, images.tile_image,
                                                  live)
    color, trans, depth = composite_cuda(rows, boxes, offsets, keys, images, live=live)
    filled = _WS.get("g.filled", (images.n_tiles,), np.bool_)
    _filled_tiles[_blocks(images.n_tiles), THREADS](offsets, filled)
    summed = np.flatnonzero(table[:, IM_SUM])
    if len(summed):  # each summed image blurred from its sharp view, through one scratch
        source = table[summed, IM_SOURCE]
        scratch = _WS.get("g.blur", (int(table[source, IM_HEIGHT].max()),
                                     int(table[summed, IM_WIDTH].max()), N_BLUR), np.float32)
        device_blurs = _upload(blurs)
        for i in summed:
            k = table[i, IM_SOURCE]
            _blur_rows[_blocks(int(table[k, IM_HEIGHT] * table[i, IM_WIDTH])), THREADS](
                images.table, device_blurs, int(i), offsets, color, trans, scratch)
            _blur_columns[_blocks(int(table[i, IM_HEIGHT] * table[i, IM_WIDTH])), THREADS](
                images.table, device_blurs, int(i), offsets, scratch, color, trans, depth,
                filled)
    _combine_layers[_blocks(h * w), THREADS](
        images.table, filled, _upload(part_layers), color, trans, depth, bg, _decode(),
        _coded(ENCODE),
        _WS.get("g.out.color", (h, w, 3), np.float32), _WS.get("g.out.trans", (h, w), np.float32),
        out_depth, image)
    stats = dict(zip(("tile_pairs", "splats_rendered", "fragments"), totals))
    stats["layers"] = len(table)
    stats["summed_layers"] = len(summed_layers(layers))
    return image, out_depth, stats


def render_gaussians_cuda(scene, camera, lens, settings) -> RenderResult:
    """``cpu_gauss.render_gaussians_cpu`` on the GPU, with ``cpu_gauss.LAYERS`` as it is at
    the call: the same frame up to float rounding."""
    warm_up()
    t0 = time.perf_counter()
    clock = _Clock()
    clock.mark("start")
    blur = settings.gaussian_blur
    parts = lens_parts(camera, lens, replace(settings,
                                             lens_samples=part_count(camera, lens, settings)))
    n_in = len(scene)
    blurred = coc_coefficients(camera, lens, settings)[0] > 0.0
    lod = settings.lod and settings.gaussian_lod and blurred
    layered = cpu_gauss.LAYERS.enabled and parts is not None and blur == "ours"
    if layered:
        positions = scene.positions  # the scene's, not the cut's (``visibility_scale_for``)
        scene, layers = in_layers(scene, camera, lens, parts, settings, lod)
    elif lod:
        scene = lod_cut(scene, camera, lens if parts is None else parts.residual, settings)
    arrays = device_gaussians(scene)
    clock.mark("select_ms")
    share = None
    if layered and blurred_layers(layers):
        share = layer_shares_cuda(arrays, scene.positions, layers, camera, lens, settings)
    elif layered:
        share = lens_visibility_by_shifts_cuda(
            arrays, scene.positions, camera, lens, settings,
            cpu_gauss.visibility_scale_for(positions, camera, lens, settings))
    elif blur == "ours" and blurred:
        share = lens_visibility_cuda(arrays, camera, lens, settings)
    clock.mark("visibility_ms")
    h, w = camera.height, camera.width
    if layered:
        image, depth, counts = draw_layered_cuda(arrays, layers, camera, lens, parts, settings,
                                                 share)
    else:
        image, depth, counts = draw_passes_cuda(arrays, camera, lens, parts, settings, blur,
                                                share)
    clock.mark("draw_ms")
    image, depth = image.copy_to_host(), depth.copy_to_host()
    clock.mark("copy_ms")
    stats = {"device": "cuda", "points_in": n_in, "splats_selected": len(scene),
             "lens_samples": 1 if parts is None else len(parts.cameras), **counts,
             "width": w, "height": h, **clock.stages_ms(),
             "total_ms": (time.perf_counter() - t0) * 1000.0}
    return RenderResult(image=image, depth=depth, weight=image[..., 3].copy(), stats=stats)


_WARM = False


def warm_up() -> None:
    """Compile every Gaussian kernel once (tiny frames: a pinhole, through a lens in layers,
    in one pass, in parts drawn whole), so that timings exclude the JIT. Skipped under the
    simulator."""
    global _WARM
    if _WARM or SIMULATOR:
        return
    _WARM = True
    from ..camera import Camera, ThinLens
    from ..frame import RenderSettings

    scene = Gaussians(positions=[[0, 0, 0], [0.1, 0, 0]], scales=[[0.1] * 3] * 2,
                      rotations=[[1, 0, 0, 0]] * 2, opacity=[0.5, 0.5],
                      sh=np.zeros((2, 1, 3), np.float32))
    camera = Camera(eye=(0, 0, 1), target=(0, 0, 0), width=8, height=8)
    lens = ThinLens(focus_distance=0.5, aperture=0.1)
    for settings in (RenderSettings(), RenderSettings(gaussian_lens_samples=1),
                     RenderSettings(gaussian_blur="viewers")):
        render_gaussians_cuda(scene, camera, lens, replace(settings, device="cuda", lod=False))
    render_gaussians_cuda(scene, camera, None, RenderSettings(device="cuda", lod=False))
