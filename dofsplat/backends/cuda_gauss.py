"""The GPU pipeline of a Gaussian scene's frame (``device="cuda"``): ``cpu_gauss``'s stages as
numba-cuda kernels, from the same per-Gaussian maths.

    (LOD cut, on the host) -> project -> bin to tiles, sorted by depth -> composite front to
    back -> background, to linear RGB -> the image and depth copied to the host

As in ``backends.cuda``, nothing per Gaussian or per pixel is written twice: ``device_twin``
compiles the CPU's own functions again as device functions:

    project_gaussian (gauss/project.py, with sh_color), gaussian_alpha, blend, start_pixel,
    seen_share, lens_share, finish_pixel with srgb_value_to_linear (gauss/composite.py)

What is written here is only the parallel structure around them:

* project: one thread per Gaussian;
* bin: tile-Gaussian pairs counted per tile with atomics, offsets by a prefix sum, filled with
  atomics as keys (the depth's float32 bits above the Gaussian's index: positive floats
  order as their bits do), each tile's keys sorted (``backends.cuda._sort_keys``, the
  bitonic sort, one block per tile), so that a tile lists its Gaussians nearest first and equal depths in
  index order, as the CPU's stable sort does;
* composite: one block per 16 x 16 tile, one thread per pixel, the tile's Gaussians loaded
  into shared memory in batches and blended in order (``gaussian_alpha``, ``blend``); the
  block stops when all its pixels are done. With lens visibility, each pixel adds the alpha
  T it saw to its Gaussian's total (an atomic add, where the CPU keeps a row per thread).

The LOD cut is the CPU's (``cpu_gauss.lod_cut``, a numba walk of the tree): the cut is
uploaded each frame. The scene's own arrays are uploaded once and kept on the ``Gaussians``
object, like the surfels' (make a new ``Gaussians`` rather than editing its arrays).

Through a lens the GPU draws each part of the lens whole: the CPU's frame with its layers
off (``cpu_gauss.LAYERS``, ``gauss/layers.py``: not ported yet), 59-184 ms at 1920 x 1080 on
an H200 (bench/RESULTS.md); the layered CPU frame is within a dB of it.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numba
import numpy as np
from numba import cuda

from ..frame import RenderResult, coc_coefficients, lens_parts
from ..gauss.composite import (N_STATE, S_B, S_DEPTH, S_G, S_R, S_T, TILE, blend,
                               finish_pixel, gaussian_alpha, lens_share, seen_share,
                               start_pixel)
from ..gauss.project import (BLUR_NONE, EPS2D, F_CA, F_CB, F_CC, F_CUT, F_DEPTH, F_OPACITY,
                             F_X, F_Y, N_FIELDS, intrinsics, project_gaussian, view_matrix)
from ..colors import linear_to_srgb
from ..gaussians import Gaussians
from .cpu_gauss import BLURS, blur_variance, lod_cut, visibility_cameras
from . import cuda as surfel_cuda
from .cuda import (SIMULATOR, THREADS, _WS, _blocks, _Clock, _fill, _scalar, _upload, device_twin,
                   exclusive_scan)

_project_gaussian = device_twin(project_gaussian)
_gaussian_alpha = device_twin(gaussian_alpha)
_blend = device_twin(blend)
_start_pixel = device_twin(start_pixel)
_seen_share = device_twin(seen_share)
_lens_share = device_twin(lens_share)
_finish_pixel = device_twin(finish_pixel)

PIXELS = TILE * TILE  # threads per block of the compositing: one per pixel of a tile
INDEX_BITS = 32  # a sort key: the depth's bits above the Gaussian's index
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
def _count_pairs(boxes, visible, n_tx, counts, totals):
    """Tile-Gaussian pairs per tile (atomics; a box is [x0, x1) x [y0, y1)), and into totals
    the visible Gaussians and their boxes' pixels (the stats' splats and fragments)."""
    block = cuda.shared.array(2, numba.int64)
    if cuda.threadIdx.x < 2:
        block[cuda.threadIdx.x] = 0
    cuda.syncthreads()
    g = cuda.grid(1)
    if g < visible.shape[0] and visible[g]:
        for ty in range(boxes[g, 2] // TILE, (boxes[g, 3] - 1) // TILE + 1):
            for tx in range(boxes[g, 0] // TILE, (boxes[g, 1] - 1) // TILE + 1):
                cuda.atomic.add(counts, ty * n_tx + tx, 1)
        cuda.atomic.add(block, 0, 1)
        cuda.atomic.add(block, 1, numba.int64(boxes[g, 1] - boxes[g, 0])
                        * numba.int64(boxes[g, 3] - boxes[g, 2]))
    cuda.syncthreads()
    if cuda.threadIdx.x < 2:
        cuda.atomic.add(totals, cuda.threadIdx.x, block[cuda.threadIdx.x])


@cuda.jit
def _fill_keys(boxes, visible, depth_bits, n_tx, cursor, keys):
    """Each visible Gaussian's sort key into the lists of the tiles it touches (any order)."""
    g = cuda.grid(1)
    if g < visible.shape[0] and visible[g]:
        key = (numba.int64(depth_bits[g, F_DEPTH]) << INDEX_BITS) | numba.int64(g)
        for ty in range(boxes[g, 2] // TILE, (boxes[g, 3] - 1) // TILE + 1):
            for tx in range(boxes[g, 0] // TILE, (boxes[g, 1] - 1) // TILE + 1):
                keys[cuda.atomic.add(cursor, ty * n_tx + tx, 1)] = key


@cuda.jit
def _composite(rows, boxes, offsets, keys, n_tx, width, height, color, trans, depth, seen,
               track):
    """One block per tile, one thread per pixel: the tile's Gaussians in key order, blended
    front to back (``gauss.composite.composite_tiles``, pixel by pixel)."""
    batch = cuda.shared.array((PIXELS, N_FIELDS), numba.float32)
    box = cuda.shared.array((PIXELS, 4), numba.int32)
    gid = cuda.shared.array(PIXELS, numba.int32)
    state = cuda.local.array((1, N_STATE), numba.float64)
    t = cuda.blockIdx.x
    tid = cuda.threadIdx.x
    py = (t // n_tx) * TILE + tid // TILE
    px = (t % n_tx) * TILE + tid % TILE
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
        color[py, px, 0] = state[0, S_R]
        color[py, px, 1] = state[0, S_G]
        color[py, px, 2] = state[0, S_B]
        trans[py, px] = state[0, S_T]
        depth[py, px] = state[0, S_DEPTH]


@cuda.jit
def _accumulate(color, trans, depth, part_color, part_trans, part_depth):
    """One lens part's pass into the sums: colour and transmittance added, depth the nearest."""
    i = cuda.grid(1)
    if i < trans.shape[0]:
        for c in range(3):
            color[i, c] += part_color[i, c]
        trans[i] += part_trans[i]
        depth[i] = min(depth[i], part_depth[i])


@cuda.jit
def _finish(color, trans, scale, bg, out):
    """One thread per pixel: the composite over the background, to linear RGBA."""
    i = cuda.grid(1)
    w = trans.shape[1]
    if i < trans.shape[0] * w:
        _finish_pixel(color, trans, i // w, i % w, scale, bg, out)


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


# -- the stages on the host -------------------------------------------------------------------


def device_gaussians(scene) -> dict:
    """The scene's arrays on the GPU: kept on a ``Gaussians`` object between frames (keyed by
    its arrays' identity), uploaded afresh for a LOD cut (a ``GaussianArrays`` made per
    frame, which would only hold on to device memory)."""
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


def bin_cuda(rows, boxes, visible, width: int, height: int):
    """(offsets (T + 1,) int64, keys (P,) int64, totals): each tile's Gaussians, nearest first
    (``cpu_gauss``'s depth_order then bin_tiles), as sort keys (``INDEX_MASK`` holds the row);
    totals: [pairs, visible Gaussians, their boxes' pixels]."""
    n = visible.shape[0]
    n_tx, n_ty = -(-width // TILE), -(-height // TILE)
    n_tiles = n_tx * n_ty
    counts = _WS.get("g.counts", (n_tiles,), np.int64)
    _fill[_blocks(n_tiles), THREADS](counts, 0)
    totals = _WS.get("g.totals", (2,), np.int64)
    _fill[1, 2](totals, 0)
    if n:
        _count_pairs[_blocks(n), THREADS](boxes, visible, n_tx, counts, totals)
    offsets = _WS.get("g.offsets", (n_tiles + 1,), np.int64)
    exclusive_scan(counts, n_tiles, offsets, "g.scan")
    n_pairs = _scalar(offsets, n_tiles)
    keys = _WS.get("g.keys", (n_pairs,), np.int64)
    if n_pairs:
        cursor = _WS.get("g.cursor", (n_tiles,), np.int64)
        cursor.copy_to_device(offsets[:n_tiles])
        _fill_keys[_blocks(n), THREADS](boxes, visible, rows.view(np.int32), n_tx, cursor, keys)
        surfel_cuda._sort_keys[n_tiles, THREADS](offsets, keys)  # (a module attribute: tests note it)
    return offsets, keys, [n_pairs, *(int(v) for v in totals.copy_to_host())]


def composite_cuda(rows, boxes, offsets, keys, width: int, height: int, prefix: str = "g",
                   seen=None):
    """(color (H, W, 3), transmittance (H, W), depth (H, W)) on the GPU, in buffers named by
    prefix; seen: an (N,) float32 device array to add each Gaussian's alpha T into, or None."""
    n_tx, n_ty = -(-width // TILE), -(-height // TILE)
    color = _WS.get(f"{prefix}.color", (height, width, 3), np.float32)
    trans = _WS.get(f"{prefix}.trans", (height, width), np.float32)
    depth = _WS.get(f"{prefix}.depth", (height, width), np.float32)
    track = seen is not None
    if seen is None:
        seen = _WS.get("g.no_seen", (0,), np.float32)
    _composite[n_tx * n_ty, PIXELS](rows, boxes, offsets, keys, n_tx, width, height, color,
                                    trans, depth, seen, track)
    return color, trans, depth


def draw_cuda(arrays: dict, camera, lens, settings, blur: str = "ours", share=None,
              prefix: str = "g"):
    """One pass on the GPU (``cpu_gauss.draw_gaussians``): color, transmittance, depth (device
    buffers named by prefix) and stats."""
    rows, boxes, visible = project_cuda(arrays, camera, lens, settings, blur, share)
    offsets, keys, totals = bin_cuda(rows, boxes, visible, camera.width, camera.height)
    color, trans, depth = composite_cuda(rows, boxes, offsets, keys, camera.width,
                                         camera.height, prefix)
    return color, trans, depth, dict(zip(("tile_pairs", "splats_rendered", "fragments"), totals))


def lens_visibility_cuda(arrays: dict, camera, lens, settings, views: int = 6, scale: int = 2):
    """(N,) float32 on the GPU: ``cpu_gauss.lens_visibility``, from the same views."""
    n = arrays["positions"].shape[0]
    best = _WS.get("g.best", (n,), np.float32)
    seen = _WS.get("g.seen", (n,), np.float32)
    _fill[_blocks(n), THREADS](best, 0.0)
    for cam in visibility_cameras(camera, lens, views, scale):
        rows, boxes, visible = project_cuda(arrays, cam, None, settings)
        offsets, keys, _ = bin_cuda(rows, boxes, visible, cam.width, cam.height)
        _fill[_blocks(n), THREADS](seen, 0.0)
        composite_cuda(rows, boxes, offsets, keys, cam.width, cam.height, "g.small", seen)
        _keep_best_share[_blocks(n), THREADS](rows, visible, seen, best)
    _finish_shares[_blocks(n), THREADS](best)
    return best


def render_gaussians_cuda(scene, camera, lens, settings) -> RenderResult:
    """``cpu_gauss.render_gaussians_cpu`` with ``LAYERS`` off, on the GPU: the same frame up
    to float rounding."""
    warm_up()
    t0 = time.perf_counter()
    clock = _Clock()
    clock.mark("start")
    blur = settings.gaussian_blur
    k = max(settings.lens_samples, settings.gaussian_lens_samples)
    parts = lens_parts(camera, lens, replace(settings, lens_samples=k))
    n_in = len(scene)
    blurred = coc_coefficients(camera, lens, settings)[0] > 0.0
    if settings.lod and settings.gaussian_lod and blurred:
        scene = lod_cut(scene, camera, lens if parts is None else parts.residual, settings)
    arrays = device_gaussians(scene)
    clock.mark("select_ms")
    share = None
    if blur == "ours" and blurred:
        share = lens_visibility_cuda(arrays, camera, lens, settings)
    clock.mark("visibility_ms")
    h, w = camera.height, camera.width
    counts = {"tile_pairs": 0, "splats_rendered": 0, "fragments": 0}
    if parts is None:
        color, trans, depth, counts = draw_cuda(arrays, camera, lens, settings, blur, share)
    else:
        color = _WS.get("g.sum.color", (h, w, 3), np.float32)
        trans = _WS.get("g.sum.trans", (h, w), np.float32)
        depth = _WS.get("g.sum.depth", (h, w), np.float32)
        _fill[_blocks(h * w * 3), THREADS](color.reshape(h * w * 3), 0.0)
        _fill[_blocks(h * w), THREADS](trans.reshape(h * w), 0.0)
        _fill[_blocks(h * w), THREADS](depth.reshape(h * w), np.inf)
        for cam in parts.cameras:
            c, t, d, st = draw_cuda(arrays, cam, parts.residual, settings, blur, share)
            for key in counts:  # summed over the parts, as the CPU's stats are
                counts[key] += st[key]
            _accumulate[_blocks(h * w), THREADS](color.reshape(h * w, 3), trans.reshape(h * w),
                                                 depth.reshape(h * w), c.reshape(h * w, 3),
                                                 t.reshape(h * w), d.reshape(h * w))
    clock.mark("draw_ms")
    image = _WS.get("g.image", (h, w, 4), np.float32)
    bg = _upload(linear_to_srgb(np.asarray(settings.background, np.float64)))
    _finish[_blocks(h * w), THREADS](color, trans, 1.0 if parts is None else
                                     1.0 / len(parts.cameras), bg, image)
    image, depth = image.copy_to_host(), depth.copy_to_host()
    clock.mark("copy_ms")
    stats = {"device": "cuda", "points_in": n_in, "splats_selected": len(scene),
             "lens_samples": 1 if parts is None else len(parts.cameras), **counts,
             "width": w, "height": h, **clock.stages_ms(),
             "total_ms": (time.perf_counter() - t0) * 1000.0}
    return RenderResult(image=image, depth=depth, weight=image[..., 3].copy(), stats=stats)


_WARM = False


def warm_up() -> None:
    """Compile every Gaussian kernel once (a tiny frame through a lens), so that timings
    exclude the JIT. Skipped under the simulator."""
    global _WARM
    if _WARM or SIMULATOR:
        return
    _WARM = True
    from ..camera import Camera, ThinLens
    from ..frame import RenderSettings
    from ..gaussians import Gaussians

    scene = Gaussians(positions=[[0, 0, 0], [0.1, 0, 0]], scales=[[0.1] * 3] * 2,
                      rotations=[[1, 0, 0, 0]] * 2, opacity=[0.5, 0.5],
                      sh=np.zeros((2, 1, 3), np.float32))
    camera = Camera(eye=(0, 0, 1), target=(0, 0, 0), width=8, height=8)
    render_gaussians_cuda(scene, camera, ThinLens(focus_distance=0.5, aperture=0.1),
                          RenderSettings(device="cuda", lod=False))
    render_gaussians_cuda(scene, camera, None, RenderSettings(device="cuda", lod=False))
