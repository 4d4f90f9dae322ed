"""The CUDA backend: ``render``'s stages as numba-cuda kernels (``device="cuda"``).

    select (LOD cut) -> shade -> project -> bin to tiles -> rasterise into the A-buffer
    and resolve

The per-splat maths is not written twice. Every function the CPU kernels call per splat,
per node or per fragment is a ``shared`` (numba.njit) function whose ``.py_func`` is
compiled here once more, as a CUDA device function, by ``device_twin``:

    project_splat (splat/project.py)  -> ewa.project_surfel, kernel_bbox, kernel_pixel_sum
    shade_splat (splat/shade.py), visit_node and gather_splat (lod/select.py)
    insert_fragment, resolve_to_image (raster/abuffer.py); ewa.row_pixel_range, ewa.exponent

``device_twin`` gives the copy of each function a globals dict in which the ``shared``
functions it calls are their own device twins, so nested calls stay on the GPU. What is
written here is only the parallel structure around those calls:

* select: the hierarchy is cut breadth first, one kernel per level of the tree, a thread
  per node of the level (``visit_node``), the next level's nodes appended with an atomic
  counter that stays on the GPU (no round trip per level); the cut, a flag per node, is
  compacted in node order by a prefix sum and gathered (``gather_splat``, the CPU's own
  per-row function);
* shade, project: one thread per splat;
* bin: tile-splat pairs counted per tile with atomics, offsets by a prefix sum, filled with
  atomics, then each tile's list sorted by splat index (a bitonic sort, one block per tile)
  so that fragments reach every pixel in the CPU's order;
* rasterise: one block per 16x16 tile, one thread per pixel, the tile's splats loaded into
  shared memory in batches and walked in index order; each thread keeps its pixel's
  A-buffer (``insert_fragment``) and resolves it (``resolve_to_image``).

So the image equals the CPU's up to floating-point rounding: the kernel value is
``exp(-exponent)`` at each pixel instead of the CPU's forward differences along a row.

Device copies of a model (and its hierarchy) are kept on the ``Surfels`` object between
frames, like the hierarchy itself: edit a model's arrays in place and the GPU keeps the old
copy; make a new ``Surfels`` instead.
"""

from __future__ import annotations

import math
import time
import types
from dataclasses import dataclass

import numba
import numpy as np
from numba import cuda

from ..lod.select import (CULL_TEST_MIN_COUNT, DESCEND, SELECT, gather_gradient, gather_splat,
                          leaves_below, visit_node)
from ..raster.abuffer import (FRONT_FIELDS, FRONT_MARGIN, MAX_SURFACES, N_ACC,
                              RESOLVE_SCRATCH, TILE, front_box, front_fragments,
                              insert_fragment, resolve_to_image, splat_visibility, widen_box)
from ..splat.ewa import exponent, row_pixel_range, row_span
from ..splat.bokeh import aperture_kernel, support_conic
from ..splat.project import (ALPHA, AMP, BLUE, BX, BY, C11, C12, C22, DEPTH, FLOOR, GREEN, GX,
                             GY, MIX, MX, MY, N_FIELDS, N_RASTER_FIELDS, RAD, REACH, RED, RX, RY,
                             X0, X1, ZHI, ZLO, project_splat, slope_splat)
from ..splat.shade import shade_splat
from ..splat.source import SplatSource

SIMULATOR = bool(numba.config.ENABLE_CUDASIM)

# -- the shared maths as device functions ------------------------------------------------

_TWINS: dict = {}


def device_twin(fn):
    """The CUDA device function compiled from the source of a CPU-jitted function.

    fn: a ``shared``/``numba.njit`` dispatcher (or a plain function). Globals of fn that are
    CPU-jitted functions are replaced, in a copy of fn's globals, by their own device
    twins; constants and modules are shared. One twin per function, made lazily: numba
    compiles it on the first kernel that calls it.
    """
    py = getattr(fn, "py_func", fn)
    twin = _TWINS.get(py)
    if twin is None:
        glb = dict(py.__globals__)
        for name in py.__code__.co_names:
            if isinstance(glb.get(name), numba.core.registry.CPUDispatcher):
                glb[name] = device_twin(glb[name])
        clone = types.FunctionType(py.__code__, glb, py.__name__, py.__defaults__, py.__closure__)
        clone.__qualname__, clone.__module__ = py.__qualname__, py.__module__
        clone.__doc__ = py.__doc__
        twin = cuda.jit(device=True)(clone)
        _TWINS[py] = twin
    return twin


_project_splat = device_twin(project_splat)
_slope_splat = device_twin(slope_splat)
_shade_splat = device_twin(shade_splat)
_visit_node = device_twin(visit_node)
_leaves_below = device_twin(leaves_below)
_gather_splat = device_twin(gather_splat)
_gather_gradient = device_twin(gather_gradient)
_insert_fragment = device_twin(insert_fragment)
_resolve_to_image = device_twin(resolve_to_image)
_front_fragments = device_twin(front_fragments)
_front_box = device_twin(front_box)
_splat_visibility = device_twin(splat_visibility)
_row_pixel_range = device_twin(row_pixel_range)
_exponent = device_twin(exponent)
_aperture_kernel = device_twin(aperture_kernel)
_support_conic = device_twin(support_conic)
_row_span = device_twin(row_span)
_widen_box = device_twin(widen_box)

# Block sizes. The simulator runs every thread as a Python thread: smaller blocks there keep
# the tests fast and take the multi-level scan and the global-memory sort on tiny inputs.
THREADS = 32 if SIMULATOR else 256  # threads per block of the one-thread-per-item kernels
PIXELS = TILE * TILE  # threads per block of the rasteriser: one per pixel of a tile
SCAN_BLOCK = 32 if SIMULATOR else 256  # elements per block of the prefix sum
SORT_SHARED = 64 if SIMULATOR else 4096  # tile lists up to this length are sorted in shared memory
SORT_KEYS = SORT_SHARED // 2  # int64 keys sorted in shared memory (_sort_keys)
LOD_BLOCKS = 1024  # the LOD cut's grid at most (its kernel loops over a level's nodes)


@cuda.jit
def probe_kernel(out):
    """Writes 1.0: ``backends.cuda_problem`` runs it to see that kernels compile and run."""
    out[0] = 1.0


# -- kernels: small helpers ----------------------------------------------------------------


@cuda.jit
def _accumulate(image, depth, weight, part_image, part_depth, part_weight, share):
    """One lens part's frame into the frame: image and weight by its share, depth the nearest."""
    i = cuda.grid(1)
    if i < depth.shape[0]:
        for c in range(4):
            image[i, c] += share * part_image[i, c]
        weight[i] += share * part_weight[i]
        depth[i] = min(depth[i], part_depth[i])


@cuda.jit
def _fill(a, value):
    i = cuda.grid(1)
    if i < a.shape[0]:
        a[i] = value


@cuda.jit
def _scan_blocks(src, n, out, block_sums):
    """out[i + 1] = inclusive sum of src within its block; block_sums[b] = the block's total."""
    sh = cuda.shared.array(SCAN_BLOCK, numba.int64)
    tid = cuda.threadIdx.x
    i = cuda.blockIdx.x * SCAN_BLOCK + tid
    v = numba.int64(0)
    if i < n:
        v = numba.int64(src[i])
    sh[tid] = v
    cuda.syncthreads()
    step = 1
    while step < SCAN_BLOCK:  # Hillis-Steele
        add = numba.int64(0)
        if tid >= step:
            add = sh[tid - step]
        cuda.syncthreads()
        sh[tid] += add
        cuda.syncthreads()
        step *= 2
    if i < n:
        out[i + 1] = sh[tid]
    if i == 0:
        out[0] = 0
    if tid == SCAN_BLOCK - 1:
        block_sums[cuda.blockIdx.x] = sh[tid]


@cuda.jit
def _scan_add(out, n, block_offsets):
    i = cuda.grid(1)
    if i < n:
        out[i + 1] += block_offsets[i // SCAN_BLOCK]


@cuda.jit
def _scatter_flagged(flags, position, nodes):
    i = cuda.grid(1)
    if i < flags.shape[0] and flags[i] != 0:
        nodes[position[i]] = i


# -- kernels: the stages ---------------------------------------------------------------------


@cuda.jit
def _lod_level(depth, sizes, frontier, next_frontier, flags, start, count, center, bound, extent,
               position, normal, cone, sigma_r2, lod_cov, color_detail, min_geo, a_min, view,
               ax, bx, ay, by, near, width, height, coc_k, inv_focus, cutoff, thr2, kappa,
               color_tol, min_node, cull_backfaces):
    """Level ``depth`` of the breadth-first cut: visit each of its sizes[depth] nodes in
    ``frontier``, flag it or append its children to ``next_frontier`` (sizes[depth + 1]).
    A node inside a subtree of ``leaves_below`` (the CPU's walk; min_geo: a row per inner
    node, a_min 0 to visit every node) is entered as -(i + 1) and gets the culling tests
    alone.

    A grid-stride loop over a size read on the GPU: the host launches one kernel per level
    of the tree without waiting for the previous level's count."""
    sharp = coc_k <= 0.0 and a_min > 0.0
    for t in range(cuda.grid(1), sizes[depth], cuda.gridsize(1)):
        i = frontier[t]
        leaves = i < 0
        if leaves:
            i = -i - 1
        m = count[i]
        what = SELECT  # a leaf: its surfel
        if m > 1:  # an inner node: its attributes are row i - start[i] (lod/hierarchy.py)
            r = i - start[i]
            if not leaves and sharp:
                leaves = _leaves_below(r, center, bound, min_geo, view, a_min, near, thr2)
            if leaves and m < CULL_TEST_MIN_COUNT:
                what = DESCEND
            else:
                what = _visit_node(r, m, center, bound, extent, position, normal, cone,
                                   sigma_r2, lod_cov, color_detail, view, ax, bx, ay, by, near,
                                   width, height, coc_k, inv_focus, cutoff, thr2, kappa,
                                   color_tol, min_node, cull_backfaces, not leaves)
        if what == SELECT:
            flags[i] = 1
        elif what == DESCEND:
            slot = cuda.atomic.add(sizes, depth + 1, 2)
            left, right = i + 1, i + 2 * (m // 2)
            if leaves:
                left, right = -left - 1, -right - 1
            next_frontier[slot] = left
            next_frontier[slot + 1] = right


@cuda.jit
def _gather(nodes, order, start, count, position, normal, color, opacity, area, sigma_r2,
            lod_cov, color_grad, s_pos, s_nrm, s_col, s_alpha, s_tan, s_ru, s_rv, s_weight,
            out_pos, out_nrm, out_col, out_alpha, out_tan, out_ru, out_rv, out_area, out_cov,
            out_grad, out_level, row_start, row_count):
    """Row t: node nodes[t] as a splat (lod/select.py's gather_splat, one thread per row),
    and its colour gradient (zero at the leaves; lod/select.py's gather_gradient).
    start, count: every node's (the tree's shape); row_start, row_count: the rows' own,
    filled here (gather_splat reads them by row, as the CPU's cut_nodes gives them). The
    attribute arrays have a row per inner node (``Hierarchy.expanded``): node i's is
    i - start[i]."""
    t = cuda.grid(1)
    if t < nodes.shape[0]:
        i = nodes[t]
        row_start[t] = start[i]
        row_count[t] = count[i]
        r = i - start[i]
        _gather_splat(t, r, order, row_start, row_count, position, normal, color, opacity,
                      area, sigma_r2, lod_cov, s_pos, s_nrm, s_col, s_alpha, s_tan, s_ru, s_rv,
                      s_weight, out_pos, out_nrm, out_col, out_alpha, out_tan, out_ru, out_rv,
                      out_area, out_cov, out_level)
        _gather_gradient(t, r, row_count, color_grad, out_grad)


@cuda.jit
def _level_colors(level, palette, out):
    t = cuda.grid(1)
    if t < level.shape[0]:
        c = min(numba.int64(level[t]), palette.shape[0] - 1)
        for d in range(3):
            out[t, d] = palette[c, d]


@cuda.jit
def _shade(positions, normals, colors, eye, kinds, vecs, cols, ka, kd, ks, shininess, two_sided,
           out, gain):
    k = cuda.grid(1)
    if k < positions.shape[0]:
        _shade_splat(k, positions, normals, colors, eye, kinds, vecs, cols, ka, kd, ks, shininess,
                     two_sided, out, gain)


@cuda.jit
def _slope(positions, normals, color_grad, gain, view_t, ax, ay, ap_var, out, visible):
    k = cuda.grid(1)
    if k < positions.shape[0]:
        _slope_splat(k, positions, normals, color_grad, gain, view_t, ax, ay, ap_var, out,
                     visible)


@cuda.jit
def _project(positions, normals, tangents, ru, rv, area, rgb, alpha, lod_cov, view_t, ax, bx, ay,
             by, near, width, height, coc_k, inv_focus, cutoff, z_margin, cull_backfaces,
             exact_norm, floor, disc, blades, moments, out, bbox, visible):
    k = cuda.grid(1)
    if k < positions.shape[0]:
        _project_splat(k, positions, normals, tangents, ru, rv, area, rgb, alpha, lod_cov, view_t,
                       (ax, bx, ay, by), near, width, height, coc_k, inv_focus, cutoff, z_margin,
                       cull_backfaces, exact_norm, floor, disc, blades, moments, out, bbox,
                       visible)


@cuda.jit
def _front_boxes(splats, visible, fw, fh, margin, box, use):
    """The front map's disk boxes (raster/abuffer.py's front_boxes): one thread per splat."""
    k = cuda.grid(1)
    if k < splats.shape[0]:
        _front_box(splats, visible, k, fw, fh, margin, box, use)


@cuda.jit
def _front(splats, offsets, ids, n_tx, fw, fh, margin, front):
    """The front pass (raster/abuffer.py's front_band): one thread per tile of the front
    map, serial inside."""
    t = cuda.grid(1)
    if t < offsets.shape[0] - 1:
        px0, py0 = (t % n_tx) * TILE, (t // n_tx) * TILE
        px1, py1 = min(px0 + TILE, fw) - 1, min(py0 + TILE, fh) - 1
        for e in range(offsets[t], offsets[t + 1]):
            _front_fragments(splats, ids[e], px0, px1, py0, py1, front, fw, margin)


@cuda.jit
def _visibility(splats, visible, front, fw, fh, margin, coc_k, inv_focus, rho0, rho1):
    """Each splat's share that survives the front pass (abuffer.apply_visibility)."""
    k = cuda.grid(1)
    if k < splats.shape[0] and visible[k]:
        splats[k, AMP] *= _splat_visibility(splats, k, front, fw, fh, margin, coc_k,
                                            inv_focus, rho0, rho1)


@cuda.jit
def _count_pairs(bbox, visible, n_tx, counts, n_visible):
    """Tile-splat pairs per tile (atomics), and the number of visible splats."""
    block_visible = cuda.shared.array(1, numba.int64)
    if cuda.threadIdx.x == 0:
        block_visible[0] = 0
    cuda.syncthreads()
    k = cuda.grid(1)
    if k < visible.shape[0] and visible[k]:
        for ty in range(bbox[k, 2] // TILE, bbox[k, 3] // TILE + 1):
            for tx in range(bbox[k, 0] // TILE, bbox[k, 1] // TILE + 1):
                cuda.atomic.add(counts, ty * n_tx + tx, 1)
        cuda.atomic.add(block_visible, 0, 1)
    cuda.syncthreads()
    if cuda.threadIdx.x == 0:
        cuda.atomic.add(n_visible, 0, block_visible[0])


@cuda.jit
def _fill_pairs(bbox, visible, n_tx, cursor, ids):
    """Each visible splat's index into the lists of the tiles it touches (any order)."""
    k = cuda.grid(1)
    if k < visible.shape[0] and visible[k]:
        for ty in range(bbox[k, 2] // TILE, bbox[k, 3] // TILE + 1):
            for tx in range(bbox[k, 0] // TILE, bbox[k, 1] // TILE + 1):
                ids[cuda.atomic.add(cursor, ty * n_tx + tx, 1)] = k


@cuda.jit(device=True)
def _bitonic_sort(a, lo, n, tid, n_threads):
    """Sort a[lo:lo + n] ascending with the block's threads (a bitonic network).

    The network of the next power of two p >= n, every comparator ascending ("flip" then
    half-cleaners), so the virtual entries a[lo + n:lo + p], read as +inf, never move and
    are never touched.
    """
    p = 1
    while p < n:
        p *= 2
    size = 2
    while size <= p:
        half = size // 2
        for q in range(tid, p // 2, n_threads):  # flip: mirror pairs of each size-block
            x = (q // half) * size + q % half
            y = (q // half) * size + size - 1 - q % half
            if y < n and a[lo + x] > a[lo + y]:
                a[lo + x], a[lo + y] = a[lo + y], a[lo + x]
        cuda.syncthreads()
        span = half // 2
        while span > 0:  # half-cleaners
            for q in range(tid, p // 2, n_threads):
                x = (q // span) * 2 * span + q % span
                y = x + span
                if y < n and a[lo + x] > a[lo + y]:
                    a[lo + x], a[lo + y] = a[lo + y], a[lo + x]
            cuda.syncthreads()
            span //= 2
        size *= 2


@cuda.jit(device=True)
def sort_block_list(offsets, a, buf):
    """The block's list (block t: a[offsets[t]:offsets[t + 1]]) sorted ascending by its
    threads: in the shared buffer buf when it fits, else where it lies."""
    t = cuda.blockIdx.x
    tid = cuda.threadIdx.x
    lo = offsets[t]
    n = offsets[t + 1] - lo
    if n <= 1:
        return  # the whole block returns: no barrier is left waiting
    if n <= buf.shape[0]:
        for e in range(tid, n, cuda.blockDim.x):
            buf[e] = a[lo + e]
        cuda.syncthreads()
        _bitonic_sort(buf, 0, n, tid, cuda.blockDim.x)
        for e in range(tid, n, cuda.blockDim.x):
            a[lo + e] = buf[e]
    else:
        _bitonic_sort(a, lo, n, tid, cuda.blockDim.x)


@cuda.jit
def _sort_tiles(offsets, ids):
    """One block per tile: sort the tile's splat list by splat index."""
    sort_block_list(offsets, ids, cuda.shared.array(SORT_SHARED, numba.int32))


@cuda.jit
def _sort_keys(offsets, keys):
    """One block per list: sort int64 keys (a Gaussian scene's tiles: backends/cuda_gauss.py),
    in shared memory up to SORT_KEYS (the int32 sort's bytes). Here, beside the device
    functions it calls: numba's simulator swaps its fake ``cuda`` module into a module's
    globals per call, so a kernel that calls another module's device functions that use
    ``cuda`` races between its threads."""
    sort_block_list(offsets, keys, cuda.shared.array(SORT_KEYS, numba.int64))


@cuda.jit
def _rasterize(splats, bbox, offsets, ids, n_tx, width, height, cutoff, bg_r, bg_g, bg_b,
               image, depth, weight, tile_stats, coc_k, inv_focus, rho0, rho1, blades, table,
               u_c, coarse):
    """One block per tile, one thread per pixel: A-buffer insert of the tile's fragments in
    splat order, then resolve (raster/abuffer.py's rasterize_band, pixel by pixel).

    A splat of aperture radius at least coarse (``RenderSettings.coarse_blur_px``) is, as
    on the CPU, its kernel at the samples of every second pixel (those of the tile and the
    next tiles' first row and column) interpolated linearly: each pixel sums its samples'
    weighted fragments into one (``_coarse_fragment``). The CPU keeps the samples' surfaces
    and inserts them at the resolve: the same sums, the same surfaces (the z-ranges of the
    same splats unite), another order of adding."""
    # the raster's fields only: 256 x 19 x 8 bytes = 38 KB of the 48 KB a block may hold
    batch = cuda.shared.array((PIXELS, N_RASTER_FIELDS), numba.float64)
    rows = cuda.shared.array((PIXELS, 3), numba.int32)
    counters = cuda.shared.array(2, numba.int64)
    acc = cuda.local.array((1, MAX_SURFACES, N_ACC), numba.float64)
    cnt = cuda.local.array(1, numba.int64)
    t = cuda.blockIdx.x
    tid = cuda.threadIdx.x
    i = (t // n_tx) * TILE + tid // TILE
    j = (t % n_tx) * TILE + tid % TILE
    inside = i < height and j < width
    cnt[0] = 0
    if tid == 0:
        counters[0] = 0
        counters[1] = 0
    frags = 0
    overflows = 0
    start, end = offsets[t], offsets[t + 1]
    for base in range(start, end, PIXELS):
        # the next PIXELS splats of the tile into shared memory, one per thread
        if base + tid < end:
            k = ids[base + tid]
            for f in range(N_RASTER_FIELDS):
                batch[tid, f] = splats[k, f]
            rows[tid, 0] = bbox[k, 2]
            rows[tid, 1] = bbox[k, 3]
            rows[tid, 2] = k  # an LOD node's colour slope is read from the splat itself
        cuda.syncthreads()
        if inside:
            for s in range(min(PIXELS, end - base)):
                if coarse > 0.0 and abs(batch[s, RAD]) >= coarse:
                    if rows[s, 0] - 1 <= i <= rows[s, 1] + 1 and batch[s, AMP] > 0.0:
                        k = rows[s, 2]
                        cw, cr, cg, cb, own = _coarse_fragment(
                            splats, k, rows[s, 0], rows[s, 1], i, j, width, height, blades,
                            table, u_c)
                        if cw > 0.0:
                            overflows += _insert_fragment(
                                acc, cnt, 0, cw, cr / cw, cg / cw, cb / cw, batch[s, ALPHA],
                                batch[s, DEPTH], batch[s, ZLO], batch[s, ZHI])
                        frags += own
                elif rows[s, 0] <= i <= rows[s, 1] and batch[s, AMP] > 0.0 and batch[s, RAD] != 0.0:
                    # the aperture's shape (splat/bokeh.py)
                    dx, dy = j + 0.5 - batch[s, MX], i + 0.5 - batch[s, MY]
                    if batch[s, X0] <= j <= batch[s, X1] \
                            and dx * dx + dy * dy <= batch[s, REACH] * batch[s, REACH]:
                        c11, c12, c22 = batch[s, C11], batch[s, C12], batch[s, C22]
                        det = c11 * c22 - c12 * c12
                        wk = _aperture_kernel(_exponent(dx, dy, c11, c12, c22), dx, dy,
                                              batch[s, RAD], c22 / det, -c12 / det, c11 / det,
                                              batch[s, MIX], blades, table, u_c)
                        if wk > 0.0:
                            k = rows[s, 2]
                            overflows += _insert_fragment(
                                acc, cnt, 0, batch[s, AMP] * wk,
                                max(batch[s, RED] + splats[k, RX] * dx + splats[k, RY] * dy, 0.0),
                                max(batch[s, GREEN] + splats[k, GX] * dx + splats[k, GY] * dy, 0.0),
                                max(batch[s, BLUE] + splats[k, BX] * dx + splats[k, BY] * dy, 0.0),
                                batch[s, ALPHA], batch[s, DEPTH], batch[s, ZLO], batch[s, ZHI])
                            frags += 1
                elif rows[s, 0] <= i <= rows[s, 1] and batch[s, AMP] > 0.0:
                    mx, my = batch[s, MX], batch[s, MY]
                    c11, c12, c22 = batch[s, C11], batch[s, C12], batch[s, C22]
                    j0, j1 = _row_pixel_range(i, mx, my, c11, c12, c22, cutoff,
                                              int(batch[s, X0]), int(batch[s, X1]))
                    if j0 <= j <= j1:
                        dx, dy = j + 0.5 - mx, i + 0.5 - my
                        q = _exponent(dx, dy, c11, c12, c22)
                        if q < cutoff:
                            k = rows[s, 2]
                            overflows += _insert_fragment(
                                acc, cnt, 0, batch[s, AMP] * (math.exp(-q) - batch[s, FLOOR]),
                                max(batch[s, RED] + splats[k, RX] * dx + splats[k, RY] * dy, 0.0),
                                max(batch[s, GREEN] + splats[k, GX] * dx + splats[k, GY] * dy, 0.0),
                                max(batch[s, BLUE] + splats[k, BX] * dx + splats[k, BY] * dy, 0.0),
                                batch[s, ALPHA], batch[s, DEPTH], batch[s, ZLO], batch[s, ZHI])
                            frags += 1
        cuda.syncthreads()
    if inside:
        res = cuda.local.array(7, numba.float64)
        order = cuda.local.array(MAX_SURFACES, numba.int64)
        scratch = cuda.local.array(RESOLVE_SCRATCH, numba.float64)
        _resolve_to_image(acc, cnt, 0, bg_r, bg_g, bg_b, res, order, scratch, image, depth,
                          weight, i, j, coc_k, inv_focus, rho0, rho1)
    cuda.atomic.add(counters, 0, frags)
    cuda.atomic.add(counters, 1, overflows)
    cuda.syncthreads()
    if tid == 0:
        tile_stats[t, 0] = counters[0]
        tile_stats[t, 1] = counters[1]


@cuda.jit(device=True)
def _coarse_fragment(splats, k, y_lo, y_hi, i, j, width, height, blades, table, u_c):
    """Wide splat k at pixel (i, j) as ``abuffer.rasterize_band`` draws it from its samples:
    (weight, weight x red, green, blue, 1 if the pixel is a sample the tile counts as a
    fragment else 0). y_lo, y_hi: the splat's box rows (widened: ``widen_box``)."""
    py0, px0 = (i // TILE) * TILE, (j // TILE) * TILE
    mx, my = splats[k, MX], splats[k, MY]
    c11, c12, c22 = splats[k, C11], splats[k, C12], splats[k, C22]
    det = c11 * c22 - c12 * c12
    w11, w12, w22 = c22 / det, -c12 / det, c11 / det
    radius, mix, amp = splats[k, RAD], splats[k, MIX], splats[k, AMP]
    b11, b12, b22 = _support_conic(w11, w12, w22, radius, u_c)
    u, v = i - py0, j - px0
    a0, b0 = u >> 1, v >> 1
    a1, b1 = a0 + (u & 1), b0 + (v & 1)
    scale = (0.5 if a1 != a0 else 1.0) * (0.5 if b1 != b0 else 1.0)
    # the rows drawn: the box's, and a row past the image's last
    r_lo = max(y_lo, py0)
    r_hi = min(y_hi + (1 if y_hi == height - 1 else 0), py0 + TILE)
    sw = sr = sg = sb = 0.0
    own = 0
    for a in range(a0, a1 + 1):
        r = py0 + 2 * a
        if r < r_lo or r > r_hi:
            continue
        dy = r + 0.5 - my
        lo, hi = _row_span(dy, b11, b12, b22, 0.5)
        if lo > hi:
            continue
        j0 = max(int(math.floor(mx + lo - 0.5)), int(splats[k, X0]), px0)
        j1 = min(int(math.ceil(mx + hi - 0.5)), int(splats[k, X1]), px0 + TILE, width)
        for b in range(b0, b1 + 1):
            c = px0 + 2 * b
            if c < j0 or c > j1:
                continue
            dx = c + 0.5 - mx
            wk = _aperture_kernel(_exponent(dx, dy, c11, c12, c22), dx, dy, radius, w11, w12,
                                  w22, mix, blades, table, u_c)
            if wk > 0.0:
                w = scale * amp * wk
                sw += w
                sr += w * max(splats[k, RED] + splats[k, RX] * dx + splats[k, RY] * dy, 0.0)
                sg += w * max(splats[k, GREEN] + splats[k, GX] * dx + splats[k, GY] * dy, 0.0)
                sb += w * max(splats[k, BLUE] + splats[k, BX] * dx + splats[k, BY] * dy, 0.0)
                if r == i and c == j:
                    own = 1
    return sw, sr, sg, sb, own


@cuda.jit
def _widen_boxes(splats, bbox, visible, coarse):
    k = cuda.grid(1)
    if k < bbox.shape[0]:
        _widen_box(splats, bbox, visible, k, coarse)


# -- host side: buffers, scan, residency -----------------------------------------------------


def _blocks(n: int, threads: int = THREADS) -> int:
    return max(1, -(-n // threads))


class _Workspace:
    """Device buffers reused between frames (grown when too small), one per name."""

    def __init__(self):
        self._buffers: dict[str, object] = {}

    def get(self, name: str, shape, dtype):
        shape = tuple(int(s) for s in shape)
        size = int(np.prod(shape))
        buf = self._buffers.get(name)
        if buf is None or buf.dtype != np.dtype(dtype) or buf.shape[0] < size:
            buf = cuda.device_array(max(size, 1), dtype)
            self._buffers[name] = buf
        return buf[:size].reshape(shape)

    def clear(self):
        self._buffers.clear()


_WS = _Workspace()


def exclusive_scan(src, n: int, out, name: str = "scan") -> None:
    """out[0] = 0, out[i + 1] = src[0] + ... + src[i] for i < n (int64; out has n + 1 rows)."""
    n_blocks = _blocks(n, SCAN_BLOCK)
    sums = _WS.get(f"{name}.sums", (n_blocks,), np.int64)
    _scan_blocks[n_blocks, SCAN_BLOCK](src, n, out, sums)
    if n_blocks > 1:
        sum_offsets = _WS.get(f"{name}.offsets", (n_blocks + 1,), np.int64)
        exclusive_scan(sums, n_blocks, sum_offsets, name + "+")
        _scan_add[_blocks(n), THREADS](out, n, sum_offsets)


def _scalar(device_array, index: int = 0) -> int:
    return int(device_array[index : index + 1].copy_to_host()[0])


def _upload(a: np.ndarray):
    return cuda.to_device(np.ascontiguousarray(a))


@dataclass
class DeviceScene:
    """A model's arrays on the GPU, and its hierarchy's when LOD is used."""

    key: tuple
    source: SplatSource  # every surfel, as ``splat.source.from_surfels`` gives it
    raw: dict  # surfel arrays that ``gather_node`` reads (tangent, radius_v, weight)
    tree: dict | None
    tree_id: int | None


def _array_key(surfels) -> tuple:
    arrays = (surfels.positions, surfels.normals, surfels.radius, surfels.colors,
              surfels.opacity, surfels.tangent, surfels.radius_v, surfels.weight)
    return tuple((None if a is None else (a.__array_interface__["data"][0], a.shape))
                 for a in arrays)


TREE_ARRAYS = ("order", "start", "count", "center", "bound", "extent", "position", "normal",
               "cone", "color", "opacity", "area", "sigma_r2", "lod_cov", "color_grad",
               "color_detail", "min_geo")


def device_scene(surfels, tree=None) -> DeviceScene:
    """The model (and ``tree``) on the GPU: uploaded once, kept on the ``Surfels`` object."""
    from ..splat.source import from_surfels

    key = _array_key(surfels)
    scene = getattr(surfels, "_cuda_scene", None)
    if scene is None or scene.key != key:
        src = from_surfels(surfels)
        empty = np.zeros(0, np.float32)
        dev = SplatSource(*(_upload(a) if isinstance(a, np.ndarray) else a for a in src))
        raw = {"tangent": _upload(surfels.tangent if surfels.is_elliptical else np.zeros((0, 3), np.float32)),
               "radius_v": _upload(surfels.radius_v if surfels.is_elliptical else empty),
               "weight": _upload(surfels.weight if surfels.weight is not None else empty)}
        scene = DeviceScene(key=key, source=dev, raw=raw, tree=None, tree_id=None)
        surfels._cuda_scene = scene
    if tree is not None and scene.tree_id != id(tree):
        from ..lod import min_leaf_geo

        # a row per inner node: the walk below reads row i - start[i] of every node it
        # visits (the CPU computes the nodes the tree does not store as it reaches them)
        rows = tree.expanded(surfels)
        rows.update(order=tree.order, start=tree.start, count=tree.count,
                    min_geo=min_leaf_geo(tree, surfels, 1))
        scene.tree = {name: _upload(rows[name]) for name in TREE_ARRAYS}
        scene.tree_id = id(tree)
    return scene


# -- host side: the stages -------------------------------------------------------------------


def select_cuda(surfels, scene: DeviceScene, tree, camera, lens, settings,
                parts=None) -> SplatSource:
    """This frame's splats on the GPU: every surfel, or the LOD cut (backends.cpu.select's
    twin; parts: the lens's parts, whose residual blur chooses the cut)."""
    from ..frame import LOD_PALETTE, backface_rule, coc_coefficients, lod_kappa

    if not settings.lod:
        return scene.source
    d = scene.tree
    n_nodes = len(tree)
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    ax, bx, ay, by = camera.screen_coefficients()
    near = float(camera.frustum_lrbtn()[4])
    view = tuple(float(v) for v in camera.camera_from_world()[:3].reshape(12))
    thr2 = float(settings.lod_pixel_threshold) ** 2
    a_min = float(min(abs(ax), abs(ay)))  # the pinhole frame's walk (lod.select_cut)

    # the cut, level by level (a level of a binary tree over N leaves has at most N nodes);
    # sizes[d]: the number of nodes visited at depth d, the root alone at depth 0
    flags = _WS.get("lod.flags", (n_nodes,), np.uint8)
    _fill[_blocks(n_nodes), THREADS](flags, 0)
    fronts = [_WS.get("lod.front0", (tree.n_surfels,), np.int64),
              _WS.get("lod.front1", (tree.n_surfels,), np.int64)]
    sizes = _WS.get("lod.sizes", (tree.depth + 1,), np.int64)
    _fill[_blocks(tree.depth + 1), THREADS](sizes, 0)
    _fill[1, 1](sizes[:1], 1)
    _fill[1, 1](fronts[0][:1], 0)  # the root
    grid = min(_blocks(tree.n_surfels), LOD_BLOCKS)
    for depth in range(tree.depth):
        _lod_level[grid, THREADS](
            depth, sizes, fronts[depth % 2], fronts[1 - depth % 2], flags, d["start"], d["count"],
            d["center"], d["bound"], d["extent"], d["position"], d["normal"], d["cone"],
            d["sigma_r2"], d["lod_cov"], d["color_detail"], d["min_geo"], a_min, view, ax, bx,
            ay, by, near, camera.width, camera.height, float(coc_k), float(inv_focus),
            float(settings.cutoff), thr2,
            float(lod_kappa(settings, parts)), float(settings.lod_color_tolerance),
            int(settings.lod_min_node), backface_rule(settings))

    # the flagged nodes in node (preorder) order, as the CPU's np.flatnonzero gives them
    position = _WS.get("lod.position", (n_nodes + 1,), np.int64)
    exclusive_scan(flags, n_nodes, position, "lod.scan")
    n = _scalar(position, n_nodes)
    nodes = _WS.get("lod.nodes", (n,), np.int64)
    _scatter_flagged[_blocks(n_nodes), THREADS](flags, position, nodes)

    ell = surfels.is_elliptical
    out = SplatSource(
        positions=_WS.get("src.positions", (n, 3), np.float32),
        normals=_WS.get("src.normals", (n, 3), np.float32),
        colors=_WS.get("src.colors", (n, 3), np.float32),
        opacity=_WS.get("src.opacity", (n,), np.float32),
        tangents=_WS.get("src.tangents", (n if ell else 0, 3), np.float32),
        ru=_WS.get("src.ru", (n,), np.float32), rv=_WS.get("src.rv", (n,), np.float32),
        area=_WS.get("src.area", (n,), np.float32),
        lod_cov=_WS.get("src.lod_cov", (n, 6), np.float32),
        color_grad=_WS.get("src.color_grad", (n, 6), np.float32),
        level=_WS.get("src.level", (n,), np.int8), material=surfels.material)
    if n:
        src = scene.source
        _gather[_blocks(n), THREADS](
            nodes, d["order"], d["start"], d["count"], d["position"], d["normal"], d["color"],
            d["opacity"], d["area"], d["sigma_r2"], d["lod_cov"], d["color_grad"], src.positions,
            src.normals, src.colors, src.opacity, scene.raw["tangent"], src.ru,
            scene.raw["radius_v"], scene.raw["weight"], out.positions, out.normals, out.colors,
            out.opacity, out.tangents, out.ru, out.rv, out.area, out.lod_cov, out.color_grad,
            out.level, _WS.get("lod.row_start", (n,), np.int32),
            _WS.get("lod.row_count", (n,), np.int32))
    if settings.show_lod:
        colors = _WS.get("src.level_colors", (n, 3), np.float32)
        if n:
            _level_colors[_blocks(n), THREADS](out.level, _palette(LOD_PALETTE), colors)
        out = out._replace(colors=colors)
    return out


_PALETTES: dict = {}


def _palette(palette: np.ndarray):
    if "lod" not in _PALETTES:
        _PALETTES["lod"] = _upload(palette)
    return _PALETTES["lod"]


def shade_cuda(source: SplatSource, camera, settings):
    """Per-splat Phong on the GPU: (S, 3) float32 and the factor on each colour channel,
    (S, 3) or (0, 3) (backends.cpu.shade_splats' twin)."""
    from ..splat.shade import light_arrays

    none = _WS.get("gain.none", (0, 3), np.float32)
    if settings.shading == "none":
        return source.colors, none
    n = source.size
    out = _WS.get("rgb", (n, 3), np.float32)
    with_gain = source.color_grad.shape[0] > 0 and not settings.show_lod
    gain = _WS.get("gain", (n, 3), np.float32) if with_gain else none
    if n:
        kinds, vecs, cols = light_arrays(tuple(settings.lights), camera)
        m = source.material
        _shade[_blocks(n), THREADS](
            source.positions, source.normals, source.colors, _upload(np.asarray(camera.eye, np.float64)),
            _upload(kinds), _upload(vecs), _upload(cols), float(m.ambient), float(m.diffuse),
            float(m.specular), float(m.shininess), not settings.cull_backfaces, out, gain)
    return out, gain


def project_cuda(source: SplatSource, rgb, camera, lens, settings, gain=None):
    """EWA projection with the DOF blur on the GPU: splats, bbox, visible (backends.cpu.project's twin)."""
    from ..frame import aperture_shape, aperture_variance, coc_coefficients, kernel_floor

    n = source.size
    splats = _WS.get("splats", (n, N_FIELDS), np.float64)
    bbox = _WS.get("bbox", (n, 4), np.int32)
    visible = _WS.get("visible", (n,), np.bool_)
    if n:
        coc_k, inv_focus = coc_coefficients(camera, lens, settings)
        ax, bx, ay, by = camera.screen_coefficients()
        view_t = tuple(float(v) for v in camera.camera_from_world()[:3].reshape(12))
        cutoff = float(settings.cutoff)
        floor = kernel_floor(settings)
        disc, blades, _, moments = aperture_shape(lens, settings)
        _project[_blocks(n), THREADS](
            source.positions, source.normals, source.tangents, source.ru, source.rv, source.area,
            rgb, source.opacity, source.lod_cov, view_t, ax, bx, ay, by,
            float(camera.frustum_lrbtn()[4]), camera.width, camera.height, float(coc_k),
            float(inv_focus), cutoff, float(settings.z_thickness), bool(settings.cull_backfaces),
            bool(settings.exact_normalization), floor, disc, _upload(blades), _upload(moments),
            splats, bbox, visible)
        if source.color_grad.shape[0] == n and not settings.show_lod:  # show_lod: flat colours
            if gain is None:
                gain = _WS.get("gain.none", (0, 3), np.float32)
            _slope[_blocks(n), THREADS](source.positions, source.normals, source.color_grad, gain,
                                        view_t, ax, ay, aperture_variance(lens), splats,
                                        visible)
    return splats, bbox, visible


def bin_cuda(bbox, visible, width, height, prefix="bin"):
    """Tile lists on the GPU: (offsets (T + 1,) int64, ids (P,) int32, visible splats).

    The splats of tile t = ty * n_tx + tx are ids[offsets[t]:offsets[t + 1]] in increasing
    splat index, as raster.abuffer.bin_splats gives them for a width x height image (the
    frame's, or the front map's in ``rasterize_cuda``); prefix names the buffers, so that
    two tile lists can live at once.
    """
    n = visible.shape[0]
    n_tx, n_ty = -(-width // TILE), -(-height // TILE)
    n_tiles = n_tx * n_ty
    counts = _WS.get(f"{prefix}.counts", (n_tiles,), np.int64)
    _fill[_blocks(n_tiles), THREADS](counts, 0)
    n_visible = _WS.get(f"{prefix}.n_visible", (1,), np.int64)
    _fill[1, 1](n_visible, 0)
    if n:
        _count_pairs[_blocks(n), THREADS](bbox, visible, n_tx, counts, n_visible)
    offsets = _WS.get(f"{prefix}.offsets", (n_tiles + 1,), np.int64)
    exclusive_scan(counts, n_tiles, offsets, f"{prefix}.scan")
    n_pairs = _scalar(offsets, n_tiles)
    if n_pairs >= 2**31:
        from ..errors import DofsplatError

        raise DofsplatError(f"{n_pairs} tile-splat pairs exceed the CUDA backend's int32 lists")
    ids = _WS.get(f"{prefix}.ids", (n_pairs,), np.int32)
    if n_pairs:
        cursor = _WS.get(f"{prefix}.cursor", (n_tiles,), np.int64)
        cursor.copy_to_device(offsets[:n_tiles])
        _fill_pairs[_blocks(n), THREADS](bbox, visible, n_tx, cursor, ids)
        _sort_tiles[n_tiles, THREADS](offsets, ids)
    return offsets, ids, _scalar(n_visible)


def rasterize_cuda(splats, bbox, visible, offsets, ids, camera, settings, merge, lens=None):
    """A-buffer rasterisation and resolve on the GPU: image, depth, weight, tile_stats.

    merge: ``frame.merge_parameters``; with K > 0 (or ``settings.sharp_visibility``,
    ``frame.front_pass``) the front pass and the splats' visibility come first, as in
    ``backends.cpu.rasterize``.
    """
    from ..frame import aperture_shape, front_pass

    _, blades, table, _ = aperture_shape(lens, settings)

    w, h = camera.width, camera.height
    coc_k, inv_focus, rho0, rho1 = (float(x) for x in merge)
    if front_pass(merge, settings) and splats.shape[0]:
        m = FRONT_MARGIN
        fw, fh = w + 2 * m, h + 2 * m
        front = _WS.get("front", (fh * fw, FRONT_FIELDS), np.float32)
        front.copy_to_device(np.full((fh * fw, FRONT_FIELDS), np.inf, np.float32))
        n = splats.shape[0]
        box = _WS.get("front.box", (n, 4), np.int32)
        use = _WS.get("front.use", (n,), np.bool_)
        _front_boxes[_blocks(n), THREADS](splats, visible, fw, fh, m, box, use)
        f_offsets, f_ids, _ = bin_cuda(box, use, fw, fh, "front.bin")
        n_tiles = f_offsets.shape[0] - 1
        _front[_blocks(n_tiles), THREADS](splats, f_offsets, f_ids, -(-fw // TILE), fw, fh, m,
                                          front)
        _visibility[_blocks(n), THREADS](splats, visible, front, fw, fh, m, coc_k, inv_focus,
                                         rho0, rho1)
    n_tx, n_ty = -(-w // TILE), -(-h // TILE)
    image = _WS.get("image", (h, w, 4), np.float32)
    depth = _WS.get("depth", (h, w), np.float32)
    weight = _WS.get("weight", (h, w), np.float32)
    tile_stats = _WS.get("tile_stats", (n_tx * n_ty, 2), np.int64)
    bg = [float(c) for c in settings.background]
    _rasterize[n_tx * n_ty, PIXELS](splats, bbox, offsets, ids, n_tx, w, h, float(settings.cutoff),
                                    bg[0], bg[1], bg[2], image, depth, weight, tile_stats,
                                    coc_k, inv_focus, rho0, rho1, _upload(blades),
                                    _upload(table), math.sqrt(2.0 * settings.cutoff),
                                    float(settings.coarse_blur_px))
    return image, depth, weight, tile_stats


# -- the frame --------------------------------------------------------------------------------


@dataclass
class DeviceFrame:
    """A frame left on the GPU: device arrays (image (H, W, 4), depth, weight) and stats.

    The arrays are reused buffers: the next frame overwrites them (copy what you keep).
    """

    image: object
    depth: object
    weight: object
    stats: dict


class _Clock:
    """Stage times: CUDA events on a GPU (read once, at the end), wall time in the simulator."""

    def __init__(self):
        self.marks = []

    def mark(self, name: str) -> None:
        if SIMULATOR:
            self.marks.append((name, time.perf_counter()))
        else:
            ev = cuda.event()
            ev.record()
            self.marks.append((name, ev))

    def stages_ms(self) -> dict:
        out = {}
        for (_, a), (name, b) in zip(self.marks, self.marks[1:]):
            if SIMULATOR:
                ms = (b - a) * 1000.0
            else:
                b.synchronize()
                ms = a.elapsed_time(b)
            out[name] = out.get(name, 0.0) + ms
        return out


def render_frame(surfels, camera, lens, settings, hierarchy=None) -> DeviceFrame:
    """``render``'s pipeline on the GPU, the result left there (for timings and viewers)."""
    from ..frame import lens_parts, lod_tree

    tree = lod_tree(surfels, hierarchy) if settings.lod else None
    scene = device_scene(surfels, tree)
    blur_lens = None if settings.show_lod else lens
    parts = lens_parts(camera, blur_lens, settings)
    clock = _Clock()
    clock.mark("start")
    source = select_cuda(surfels, scene, tree, camera, lens, settings, parts)
    clock.mark("select_ms")
    rgb, gain = shade_cuda(source, camera, settings)
    clock.mark("shade_ms")
    if parts is None:
        image, depth, weight, counts = _draw(source, rgb, camera, blur_lens, settings, clock, gain)
    else:
        # the lens's parts (splat/subaperture.py), each from its own camera, averaged
        h, w = camera.height, camera.width
        image = _WS.get("parts.image", (h, w, 4), np.float32)
        depth = _WS.get("parts.depth", (h, w), np.float32)
        weight = _WS.get("parts.weight", (h, w), np.float32)
        _fill[_blocks(h * w * 4), THREADS](image.reshape(h * w * 4), 0.0)
        _fill[_blocks(h * w), THREADS](depth.reshape(h * w), np.inf)
        _fill[_blocks(h * w), THREADS](weight.reshape(h * w), 0.0)
        counts = np.zeros(4, np.int64)
        share = 1.0 / len(parts.cameras)
        for part_camera in parts.cameras:
            im, dp, wt, c = _draw(source, rgb, part_camera, parts.residual, settings, clock, gain)
            _accumulate[_blocks(h * w), THREADS](image.reshape(h * w, 4), depth.reshape(h * w),
                                                 weight.reshape(h * w), im.reshape(h * w, 4),
                                                 dp.reshape(h * w), wt.reshape(h * w), share)
            clock.mark("raster_ms")
            counts += c
        counts[0] = round(counts[0] / len(parts.cameras))
    stats = {
        "device": "cuda",
        "points_in": int(len(surfels)),
        "lod": bool(settings.lod),
        "lens_samples": 1 if parts is None else len(parts.cameras),
        "splats_selected": int(source.size),
        "splats_rendered": int(counts[0]),
        "fragments": int(counts[1]),
        "abuffer_overflows": int(counts[2]),
        "tile_pairs": int(counts[3]),
        "bands": 1,
        "width": camera.width,
        "height": camera.height,
        **clock.stages_ms(),
    }
    return DeviceFrame(image=image, depth=depth, weight=weight, stats=stats)


def _draw(source, rgb, camera, lens, settings, clock, gain=None):
    """Project, bin and rasterise one view (``backends.cpu.draw``'s twin): image, depth,
    weight (device buffers that the next view overwrites) and (splats rendered, fragments,
    overflows, tile pairs)."""
    from ..frame import merge_parameters

    splats, bbox, visible = project_cuda(source, rgb, camera, lens, settings, gain)
    clock.mark("project_ms")
    if settings.coarse_blur_px > 0.0 and bbox.shape[0]:
        # the boxes of the splats drawn from samples reach the tiles whose samples they
        # give (abuffer.widen_boxes)
        _widen_boxes[_blocks(bbox.shape[0]), THREADS](splats, bbox, visible,
                                                       float(settings.coarse_blur_px))
    offsets, ids, n_visible = bin_cuda(bbox, visible, camera.width, camera.height)
    clock.mark("bin_ms")
    merge = merge_parameters(camera, lens, settings)
    image, depth, weight, tile_stats = rasterize_cuda(splats, bbox, visible, offsets, ids, camera,
                                                      settings, merge, lens)
    clock.mark("raster_ms")
    frags, overflows = tile_stats.copy_to_host().sum(axis=0)
    return image, depth, weight, np.array([n_visible, frags, overflows, ids.shape[0]], np.int64)


def render_cuda(surfels, camera, lens, settings, hierarchy=None):
    """``render`` on the GPU: a ``RenderResult`` with host arrays (render.render calls this)."""
    from ..frame import RenderResult

    warm_up()
    t0 = time.perf_counter()
    frame = render_frame(surfels, camera, lens, settings, hierarchy)
    image = frame.image.copy_to_host()
    depth = frame.depth.copy_to_host()
    weight = frame.weight.copy_to_host()
    frame.stats["total_ms"] = (time.perf_counter() - t0) * 1000.0
    return RenderResult(image=image, depth=depth, weight=weight, stats=frame.stats)


_WARM = False


def warm_up() -> None:
    """Compile every kernel once (one tiny frame with LOD), so that timings exclude the JIT.

    Skipped under the simulator, where nothing is compiled and every thread is Python.
    """
    global _WARM
    if _WARM or SIMULATOR:
        return
    _WARM = True
    from ..camera import Camera, ThinLens
    from ..frame import RenderSettings
    from ..surfels import Surfels

    s = Surfels(positions=[[0, 0, 0], [0.1, 0, 0]], normals=[[0, 0, 1], [0, 0, 1]],
                radius=[0.1, 0.1], colors=[[1, 1, 1], [1, 1, 1]])
    cam = Camera(eye=(0, 0, 1), target=(0, 0, 0), width=8, height=8)
    render_frame(s, cam, ThinLens(focus_distance=0.5, aperture=0.1), RenderSettings(device="cuda"))
