"""The CPU backend: ``render``'s stages as numba kernels (``device="cpu"``, the default).

    select (LOD cut) -> shade -> project (EWA kernel + DOF blur) -> bin to tiles ->
    front pass -> rasterise into the A-buffer and resolve

Each stage is a named function below; the kernels they call live with the maths they
implement (``dofsplat.splat``, ``dofsplat.raster``, ``dofsplat.lod``). ``backends.cuda`` is
the same pipeline on the GPU, from the same per-splat maths; ``dofsplat.frame`` holds the
settings, the result and the per-frame parameters both derive.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import replace

import numpy as np

from ..camera import Camera, ThinLens
from ..frame import (RenderResult, RenderSettings, aperture_shape, aperture_variance,
                     backface_rule, coc_coefficients,
                     front_pass, kernel_floor, lens_parts, lod_kappa, lod_level_colors,
                     lod_tree, merge_parameters, splat_rows_budget)
from ..surfels import Surfels


def render_cpu(surfels: Surfels, camera: Camera, lens, settings: RenderSettings,
               hierarchy=None) -> RenderResult:
    """``render`` on the CPU (its arguments; ``render.render`` calls this)."""
    warm_up()
    times = {}
    t_start = time.perf_counter()
    blur_lens = None if settings.show_lod else lens
    parts = lens_parts(camera, blur_lens, settings)

    if parts is None and settings.lod:
        # the cut gathered, shaded and projected a chunk at a time (draw_cut)
        t = time.perf_counter()
        tree = lod_tree(surfels, hierarchy)
        cut = select_cut(surfels, camera, lens, settings, tree)
        times["select_ms"] = _ms(t)
        image, depth, weight, frame_stats = draw_cut(surfels, tree, cut, camera, blur_lens,
                                                     settings, times)
        n_selected = cut[0].size
    else:
        t = time.perf_counter()
        source = select(surfels, camera, lens, settings, hierarchy, parts)
        times["select_ms"] = _ms(t)

        t = time.perf_counter()
        rgb, gain = shade_splats(source, camera, settings)
        times["shade_ms"] = _ms(t)

        if parts is None:
            image, depth, weight, frame_stats = draw(source, rgb, camera, blur_lens, settings, gain)
        elif settings.lens_parts == "needed":
            # the one pass from its own cut, chosen by the whole lens's blur (coarser)
            one, one_rgb, one_gain = source, rgb, gain
            if settings.lod:
                one = select(surfels, camera, lens, settings, hierarchy)
                one_rgb, one_gain = shade_splats(one, camera, settings)
            image, depth, weight, frame_stats = draw_parts_where_needed(
                (one, one_rgb, one_gain), (source, rgb, gain), camera, blur_lens, parts,
                settings)
        else:
            image, depth, weight, frame_stats = draw_parts(source, rgb, parts, settings, gain)
        n_selected = source.size
    for stage in ("project_ms", "bin_ms", "front_ms", "raster_ms"):
        times[stage] = frame_stats.pop(stage)
    frame_stats.pop("tile_layers")  # per tile, for the lens's parts (not a number to report)
    times["total_ms"] = _ms(t_start)

    stats = {
        "points_in": int(len(surfels)),
        "lod": bool(settings.lod),
        "lens_samples": 1 if parts is None else len(parts.offsets),
        "splats_selected": int(n_selected),
        **frame_stats,
        "width": camera.width,
        "height": camera.height,
        **times,
    }
    return RenderResult(image=image, depth=depth, weight=weight, stats=stats)


def draw(source, rgb, camera: Camera, lens, settings: RenderSettings, gain=None, tiles=None):
    """Project, bin and rasterise one view of the splats: (image, depth, weight, stats).
    tiles: None, or (n_ty, n_tx) bool: only the splats that reach these tiles are drawn,
    after the front pass has seen them all (the image elsewhere is not the view's)."""
    t = time.perf_counter()
    splats, bbox, visible = project(source, rgb, camera, lens, settings, workspace=_workspace(),
                                    gain=gain)
    return draw_splats(splats, bbox, visible, camera, lens, settings, _ms(t), tiles)


# nodes of an LOD cut gathered, shaded and projected at a time (draw_cut): 2^20 of them
# hold 125 MB, where a whole pinhole cut of 10 M surfels (5.2 M nodes) held 650 MB
CUT_CHUNK = 1 << 20
VISIBLE_CHUNK = 1 << 18  # draw_cut's chunks: a chunk's rows are projected aside (36 MB)


def draw_cut(surfels: Surfels, tree, cut, camera: Camera, lens, settings: RenderSettings,
             times: dict):
    """``draw`` for an LOD cut (``select_cut``: its nodes, first leaves, counts, rows): each
    CUT_CHUNK nodes are gathered (``lod.gather_cut``), shaded and projected into their rows
    of one splat buffer before the next are, so the gathered nodes of the whole cut never exist at
    once. The splats are those of ``draw(select(...))``, row for row. A cut of more than
    ``frame.splat_rows_budget`` nodes is drawn band by band instead (``draw_cut_banded``).
    Adds the gathers and the shading to times["select_ms"] and times["shade_ms"]."""
    from ..splat.project import N_FIELDS

    n = cut[0].size
    budget = splat_rows_budget(settings)
    if n > budget:
        return draw_cut_banded(surfels, tree, cut, camera, lens, settings, times, budget)
    workspace = _workspace()
    splats = _buffer(workspace, "splats", (n, N_FIELDS), np.float32)
    bbox = _buffer(workspace, "bbox", (n, 4), np.int32)
    visible = _buffer(workspace, "visible", (n,), np.bool_)
    clock = {"select_ms": 0.0, "shade_ms": 0.0, "project_ms": 0.0}
    # the visible splats only, in cut order: the rows of the culled ones (back faces the
    # walk leaves to the projection, a third of a scan's cut) are never written, so their
    # pages are never touched
    kept = project_cut(surfels, tree, cut, camera, lens, settings, (splats, bbox, visible),
                       clock, chunk=VISIBLE_CHUNK, scratch=workspace)
    times["select_ms"] += clock["select_ms"]
    times["shade_ms"] = clock["shade_ms"]
    return draw_splats(splats[:kept], bbox[:kept], visible[:kept], camera, lens, settings,
                       clock["project_ms"])


def project_cut(surfels: Surfels, tree, cut, camera: Camera, lens, settings: RenderSettings,
                out, clock: dict, chunk: int | None = None, scratch: dict | None = None) -> int:
    """Gather, shade and project the nodes of ``cut`` ``chunk`` (default CUT_CHUNK) at a
    time into ``out`` (splats, bbox, visible: one row per node), adding each stage's
    milliseconds to clock["select_ms"], ["shade_ms"] and ["project_ms"]; returns the rows
    filled. scratch: a workspace (``_workspace``) for a chunk's rows, which are projected
    there and only the visible ones copied into ``out``, in cut order (its first rows)."""
    from ..lod import gather_cut

    splats, bbox, visible = out
    n = cut[0].size
    chunk = CUT_CHUNK if chunk is None else chunk
    filled = 0
    for lo in range(0, n, chunk):
        hi = min(lo + chunk, n)
        t = time.perf_counter()
        source = gather_cut(tree, surfels, tuple(a[lo:hi] for a in cut))
        if settings.show_lod:
            source = source._replace(colors=lod_level_colors(source.level))
        clock["select_ms"] += _ms(t)
        t = time.perf_counter()
        rgb, gain = shade_splats(source, camera, settings)
        clock["shade_ms"] += _ms(t)
        t = time.perf_counter()
        if scratch is None:
            project(source, rgb, camera, lens, settings, gain=gain,
                    out=(splats[lo:hi], bbox[lo:hi], visible[lo:hi]))
            filled = hi
        else:
            m = hi - lo
            rows = (_buffer(scratch, "chunk_splats", (m, splats.shape[1]), np.float32),
                    _buffer(scratch, "chunk_bbox", (m, 4), np.int32),
                    _buffer(scratch, "chunk_visible", (m,), np.bool_))
            project(source, rgb, camera, lens, settings, gain=gain, out=rows)
            keep = np.flatnonzero(rows[2])
            k = keep.size
            np.take(rows[0], keep, axis=0, out=splats[filled:filled + k])
            np.take(rows[1], keep, axis=0, out=bbox[filled:filled + k])
            visible[filled:filled + k] = True
            filled += k
        clock["project_ms"] += _ms(t)
        del source, rgb, gain
    return filled


def project_boxes(surfels: Surfels, tree, cut, camera: Camera, lens, settings: RenderSettings,
                  rows, bbox, visible, front, clock: dict) -> None:
    """``draw_cut_banded``'s first pass: the pixel box and visibility of every node of
    ``cut`` into bbox and visible, gathered and projected ``len(rows)`` at a time into
    ``rows`` (scratch), unshaded, without the Gaussian kernels' pixel sums and without the
    colour slopes (none of which changes a box, a visibility or a front disk); and, if
    ``front`` is a front map (``rasterize``), each chunk's opaque disks drawn into it
    (``front_chunk``), in cut order as the one-buffer frame draws them. Adds to
    clock["select_ms"], ["project_ms"] and ["front_ms"]."""
    from ..lod import gather_cut
    from ..raster.abuffer import FRONT_MARGIN, widen_boxes

    boxes = replace(settings, exact_normalization=False)
    n, chunk = cut[0].size, rows.shape[0]
    for lo in range(0, n, chunk):
        hi = min(lo + chunk, n)
        t = time.perf_counter()
        source = gather_cut(tree, surfels, tuple(a[lo:hi] for a in cut))
        clock["select_ms"] += _ms(t)
        t = time.perf_counter()
        out = (rows[:hi - lo], bbox[lo:hi], visible[lo:hi])
        project(source, source.colors, camera, lens, boxes, slopes=False, out=out)
        if settings.coarse_blur_px > 0.0:  # as rasterize bins them, for the bands' choice
            widen_boxes(*out, float(settings.coarse_blur_px))
        clock["project_ms"] += _ms(t)
        del source
        if front is not None:
            t = time.perf_counter()
            front_chunk(out[0], out[2], camera, front, FRONT_MARGIN)
            clock["front_ms"] += _ms(t)


def draw_cut_banded(surfels: Surfels, tree, cut, camera: Camera, lens,
                    settings: RenderSettings, times: dict, budget: int):
    """``draw_cut`` for a cut of more than ``budget`` nodes (``frame.splat_rows_budget``),
    with about that many splat rows in memory at once (a pinhole cut of 10 M surfels is
    5.2 M nodes: 650 MB of rows); more only where one tile row alone touches more splats.

    A first pass gathers and projects the whole cut, a budget at a time, for its splats'
    boxes and the front pass's disks (``project_boxes``); the image's tile rows are then
    cut into bands that each touch at most budget splats (and max_tile_pairs tile pairs);
    each band's splats are gathered, shaded and projected again, in cut order, into one
    buffer and rasterised (``rasterize``'s ``rows``). A projection is the same arithmetic
    whichever rows it fills, each tile receives its splats in cut order, and the front map
    is drawn in cut order as the one-buffer frame's is, so the frame is ``draw_cut``'s bit
    for bit. It costs a second gather and projection of the cut, one more per band
    boundary a splat spans, and a raster pass per band (bench/RESULTS.md)."""
    from ..raster.abuffer import FRONT_MARGIN, TILE
    from ..splat.project import N_FIELDS

    n = cut[0].size
    bbox = np.empty((n, 4), np.int32)
    visible = np.empty(n, np.bool_)
    rows = np.empty((min(budget, CUT_CHUNK, n), N_FIELDS), np.float32)
    clock = {"select_ms": 0.0, "shade_ms": 0.0, "project_ms": 0.0, "front_ms": 0.0}
    merge = merge_parameters(camera, lens, settings)
    front = None
    if front_pass(merge, settings):
        front = front_map(camera, FRONT_MARGIN)
    project_boxes(surfels, tree, cut, camera, lens, settings, rows, bbox, visible, front, clock)
    t = time.perf_counter()
    bands = plan_bands(bbox, visible, camera, settings, max_splats=budget)
    bin_ms = _ms(t)

    def band_rows(ty0: int, ty1: int):
        nonlocal rows
        # the band's splats, in cut order: visible, and their boxes reach into the band
        pick = np.flatnonzero(visible & (bbox[:, 2] < ty1 * TILE) & (bbox[:, 3] >= ty0 * TILE))
        m = pick.size
        if m > rows.shape[0]:  # grown, not doubled: one buffer of rows at a time
            rows = None
            rows = np.empty((m, N_FIELDS), np.float32)
        out = (rows[:m], np.empty((m, 4), np.int32), np.empty(m, np.bool_))
        project_cut(surfels, tree, tuple(a[pick] for a in cut), camera, lens, settings, out,
                    clock, chunk=min(CUT_CHUNK, budget))
        return out

    image, depth, weight, stats = rasterize(None, None, None, bands, camera, settings, merge,
                                            lens, rows=band_rows, front=front)
    times["select_ms"] += clock["select_ms"]
    times["shade_ms"] = clock["shade_ms"]
    stats["splats_rendered"] = int(np.count_nonzero(visible))
    stats["project_ms"] = clock["project_ms"]
    stats["bin_ms"] += bin_ms
    stats["front_ms"] += clock["front_ms"]
    return image, depth, weight, stats


def draw_splats(splats, bbox, visible, camera: Camera, lens, settings: RenderSettings,
                project_ms: float, tiles=None):
    """Bin and rasterise projected splats (``draw``'s second half): (image, depth, weight,
    stats); tiles: ``draw``'s."""
    t = time.perf_counter()
    bands = plan_bands(bbox, visible, camera, settings)
    bin_ms = _ms(t)
    image, depth, weight, stats = rasterize(splats, bbox, visible, bands, camera, settings,
                                            merge_parameters(camera, lens, settings), lens,
                                            tiles=tiles)
    stats["splats_rendered"] = int(np.count_nonzero(visible))
    stats["project_ms"] = project_ms
    stats["bin_ms"] += bin_ms
    return image, depth, weight, stats


def draw_parts(source, rgb, parts, settings: RenderSettings, gain=None, tiles=None):
    """The lens's parts (``splat/subaperture.py``), each ``draw``n from its own camera with
    the residual blur, averaged: (image, depth, weight, stats summed over the parts;
    splats_rendered is the mean per part). depth is the nearest any part saw, as the
    reference's. tiles: ``draw``'s, for every part."""
    cam = parts.cameras[0]
    image = np.zeros((cam.height, cam.width, 4), np.float32)
    depth = np.full((cam.height, cam.width), np.inf, np.float32)
    weight = np.zeros((cam.height, cam.width), np.float32)
    total: dict = {}
    share = np.float32(1.0 / len(parts.cameras))
    for part_camera in parts.cameras:
        im, dp, wt, stats = draw(source, rgb, part_camera, parts.residual, settings, gain,
                                 tiles)
        image += im * share  # float32 sums of K <= 64 frames: rounding far below 1/255
        weight += wt * share
        np.minimum(depth, dp, out=depth)
        for key, value in stats.items():
            total[key] = total.get(key, 0) + value
    total["splats_rendered"] = int(round(total["splats_rendered"] / len(parts.cameras)))
    return image, depth, weight, total


def draw_parts_where_needed(one, part_splats, camera: Camera, lens, parts,
                            settings: RenderSettings):
    """The lens in parts only where visibility is in doubt (``lens_parts="needed"``).

    One pass draws the whole frame through the whole lens. Where each pixel's A-buffer held
    one surface (or none), one surface covers the pixel's circle of confusion and the parts
    would draw the same thing; where a pixel held two or more (surfaces at different depths
    meeting under a blur), the parts decide visibility better (docs/maths.md, "The lens in
    parts"). So each part's front pass sees every splat (its visibility looks a circle of
    confusion away), but only the splats that reach the tiles with such a pixel, or the
    tiles beside them, are rasterised; the parts are blended into the one pass: weight 1 on
    the doubtful tiles, falling linearly to 0 one tile beyond them.
    Returns ``draw_parts``'s (image, depth, weight, stats), stats summed over the one pass
    and the parts, with ``parts_tiles``: the share of tiles drawn in parts. one,
    part_splats: (source, rgb, gain) of the one pass and of the parts (with LOD, the cuts
    chosen by the whole lens's blur and by a part's)."""
    from scipy import ndimage

    from ..raster.abuffer import TILE

    image, depth, weight, stats = draw(*one[:2], camera, lens, settings, one[2])
    doubt = stats["tile_layers"] >= 2
    stats["parts_tiles"] = float(doubt.mean())
    if not doubt.any():
        return image, depth, weight, stats
    beside = ndimage.binary_dilation(doubt, np.ones((3, 3), bool))
    source, rgb, gain = part_splats
    p_image, p_depth, p_weight, p_stats = draw_parts(source, rgb, parts, settings, gain, beside)
    # the blend: 1 on the doubtful tiles' pixels, to 0 over one tile beyond them
    h, w = camera.height, camera.width
    core = np.repeat(np.repeat(doubt, TILE, axis=0), TILE, axis=1)[:h, :w]
    blend = np.clip(1.0 - ndimage.distance_transform_edt(~core) / TILE, 0.0, 1.0)
    blend = blend.astype(np.float32)
    image += blend[..., None] * (p_image - image)
    weight += blend * (p_weight - weight)
    depth = np.where(blend > 0.0, np.minimum(depth, p_depth), depth)
    for key, value in p_stats.items():
        if key != "splats_rendered":
            stats[key] = stats.get(key, 0) + value
    return image, depth, weight, stats


# -- stages ------------------------------------------------------------------------------


def select_cut(surfels: Surfels, camera: Camera, lens, settings: RenderSettings,
               hierarchy=None, parts=None):
    """This frame's LOD cut, ``select``'s before the gather: (nodes in preorder, their first
    leaves, their counts, their rows in the tree's arrays), int32 each (``lod.select_cut``)."""
    from ..lod import select_cut as cut

    tree = lod_tree(surfels, hierarchy)
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    return cut(tree, surfels, camera, coc_k, inv_focus, settings.cutoff,
               settings.lod_pixel_threshold, backface_rule(settings), lod_kappa(settings, parts),
               settings.lod_color_tolerance, settings.lod_min_node)


def select(surfels: Surfels, camera: Camera, lens, settings: RenderSettings, hierarchy=None,
           parts=None):
    """What to splat: every surfel, or this frame's LOD cut (Section 6.2). A ``SplatSource``.

    parts: the lens's parts (``frame.lens_parts``): nodes are then chosen by the residual
    blur, which each part draws (the frustum still widened by the whole lens's)."""
    from ..lod import gather_cut
    from ..splat.source import from_surfels

    if not settings.lod:
        return from_surfels(surfels)
    tree = lod_tree(surfels, hierarchy)
    source = gather_cut(tree, surfels, select_cut(surfels, camera, lens, settings, tree, parts))
    if settings.show_lod:
        source = source._replace(colors=lod_level_colors(source.level))
    return source


def shade_surfels(source, camera: Camera, settings: RenderSettings) -> np.ndarray:
    """Per-splat shading before splatting (Section 6.5): (S, 3) float32 linear RGB.

    source: a ``SplatSource`` (or ``Surfels``)
    """
    return shade_splats(source, camera, settings)[0]


def shade_splats(source, camera: Camera, settings: RenderSettings):
    """``shade_surfels``, and the shading's factor on each colour channel, (S, 3) float32,
    which the projection applies to the LOD nodes' colour gradients; (0, 3) (a factor of 1)
    unshaded or without gradients."""
    from ..splat.shade import shade_fast

    none = np.ones((0, 3), np.float32)
    if settings.shading == "none":
        return source.colors, none
    grad = getattr(source, "color_grad", None)
    if grad is None or grad.shape[0] == 0 or settings.show_lod:
        return shade_fast(source.positions, source.normals, source.colors, source.material,
                          camera, settings.lights, two_sided=not settings.cull_backfaces), none
    return shade_fast(source.positions, source.normals, source.colors, source.material,
                      camera, settings.lights, two_sided=not settings.cull_backfaces, gain=True)


def project(source, rgb: np.ndarray, camera: Camera, lens, settings: RenderSettings,
            lod_cov: np.ndarray | None = None, workspace: dict | None = None, gain=None,
            out=None, slopes: bool = True):
    """EWA projection with the DOF blur (eqs. 8, 11, 12): splats (S, N_FIELDS), bbox, visible.

    source: a ``SplatSource`` (its ``lod_cov`` is the LOD filter) or ``Surfels`` (then
    ``lod_cov`` (N, 6), if given, is the LOD filter's world covariance per surfel);
    workspace: a dict whose arrays the splats may reuse (``render`` keeps one per thread),
    else they are new; gain: (S, 3) the shading's factor on the colour (``shade_splats``),
    applied to the nodes' colour gradients, or None for 1; out: (splats, bbox, visible)
    arrays of S rows to fill instead (``draw_cut``); slopes: False leaves the nodes'
    colour slopes unset (a pass for the boxes alone, ``project_boxes``)
    """
    from ..splat.project import N_FIELDS, project_splats, slope_splats
    from ..splat.source import from_surfels

    if isinstance(source, Surfels):
        source = from_surfels(source)
    if lod_cov is not None:
        source = source._replace(lod_cov=np.ascontiguousarray(lod_cov, np.float32))
    n = source.size
    tangents, ru, rv, area = source.tangents, source.ru, source.rv, source.area
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    ax, bx, ay, by = camera.screen_coefficients()
    near = camera.frustum_lrbtn()[4]
    view = np.ascontiguousarray(camera.camera_from_world()[:3].reshape(12))
    if out is not None:
        splats, bbox, visible = out
    else:
        splats = _buffer(workspace, "splats", (n, N_FIELDS), np.float32)
        bbox = _buffer(workspace, "bbox", (n, 4), np.int32)
        visible = _buffer(workspace, "visible", (n,), np.bool_)
    disc, blades, _, moments = aperture_shape(lens, settings)
    project_splats(source.positions, source.normals, tangents, ru, rv, area,
                   np.ascontiguousarray(rgb, np.float32), source.opacity, source.lod_cov, view,
                   ax, bx, ay, by, near, camera.width, camera.height, coc_k, inv_focus,
                   float(settings.cutoff), float(settings.z_thickness),
                   bool(settings.cull_backfaces), bool(settings.exact_normalization),
                   kernel_floor(settings), disc, blades, moments, splats, bbox, visible)
    if slopes and source.color_grad.shape[0] == n and not settings.show_lod:  # show_lod: flat colours
        slope_splats(source.positions, source.normals, source.color_grad,
                     np.ones((0, 3), np.float32) if gain is None else gain, view, ax, ay,
                     aperture_variance(lens), splats, visible)
    return splats, bbox, visible


def plan_bands(bbox, visible, camera: Camera, settings: RenderSettings,
               max_splats: int | None = None) -> list[tuple[int, int]]:
    """Cut the tile rows into bands whose tile-splat pairs fit the memory budget
    (``settings.max_tile_pairs``) and, given max_splats, that each touch at most that many
    splats (``draw_cut_banded``). A band is at least one tile row."""
    from ..raster.abuffer import TILE, tile_rows_pairs

    n_ty = -(-camera.height // TILE)
    per_row = tile_rows_pairs(bbox, visible, n_ty)
    if max_splats is not None:
        # splats touching tile rows a..b-1: those that begin at or before b - 1, less
        # those that end before a
        # (a visible splat's box may be empty, (0, -1, 0, -1): it draws no fragment, only a
        # disk into the front map; splat/project.py)
        drawn = visible & (bbox[:, 2] <= bbox[:, 3])
        first = np.bincount(bbox[drawn, 2] // TILE, minlength=n_ty).cumsum()
        last = np.concatenate([[0], np.bincount(bbox[drawn, 3] // TILE, minlength=n_ty).cumsum()])
    bands, start, acc = [], 0, 0
    for ty in range(n_ty):
        if (acc and acc + per_row[ty] > settings.max_tile_pairs) or (
                max_splats is not None and ty > start and first[ty] - last[start] > max_splats):
            bands.append((start, ty))
            start, acc = ty, 0
        acc += int(per_row[ty])
    bands.append((start, n_ty))
    return bands


def rasterize(splats, bbox, visible, bands, camera: Camera, settings: RenderSettings,
              merge=(0.0, 0.0, 0.15, 0.5), lens=None, rows=None, front=None, tiles=None):
    """A-buffer rasterisation and resolve, band by band (Section 6.4).

    lens: the lens whose aperture shape the splats carry (``aperture_shape``).
    merge: ``merge_parameters``; with K > 0 (or ``settings.sharp_visibility``,
    ``frame.front_pass``) a front pass first finds, per pixel, the nearest opaque unblurred
    disk, and every splat hidden behind a front of the same layer, or from the whole lens
    (``abuffer.splat_visibility``), gives up that share of its weight (docs/maths.md,
    "Surface reconstruction"). Changes ``splats`` and ``visible`` in place.
    rows: None, or a function (ty0, ty1) -> (splats, bbox, visible) that projects afresh the
    splats of each band, in their order (``draw_cut_banded``; splats, bbox and visible are
    then None, and the time it takes is not counted here); front: the front map, drawn
    already (``draw_cut_banded``), else it is drawn here when the front pass runs; tiles:
    None, or (n_ty, n_tx) bool: after the front pass, only these tiles are rasterised, from
    the splats that reach them (``abuffer.keep_tiles``, ``keep_tile_lists``).
    """
    import numba

    from ..raster.abuffer import (FRONT_MARGIN, TILE, apply_visibility, bin_splats,
                                 keep_tile_lists, keep_tiles, rasterize_band, widen_boxes)

    w, h = camera.width, camera.height
    n_tx = -(-w // TILE)
    image = np.empty((h, w, 4), np.float32)
    depth = np.empty((h, w), np.float32)
    weight = np.empty((h, w), np.float32)
    background = np.asarray(settings.background, np.float64)
    coc_k, inv_focus, rho0, rho1 = (float(x) for x in merge)
    _, blades, table, _ = aperture_shape(lens, settings)
    u_c = math.sqrt(2.0 * settings.cutoff)
    frags = overflows = pairs = 0
    bin_ms = raster_ms = front_ms = 0.0
    layers = np.zeros((-(-h // TILE), n_tx), np.int64)  # the most surfaces a pixel held, per tile

    if rows is not None and front is None and front_pass(merge, settings):
        raise ValueError("rasterize: bands projected afresh need their front map drawn first")
    margin = FRONT_MARGIN
    fw, fh = w + 2 * margin, h + 2 * margin
    if front is None and front_pass(merge, settings):
        t = time.perf_counter()
        front = front_map(camera, margin)
        front_chunk(splats, visible, camera, front, margin)
        apply_visibility(splats, visible, front, fw, fh, margin, coc_k, inv_focus, rho0, rho1)
        front_ms = _ms(t)
    coarse = float(settings.coarse_blur_px)
    if coarse > 0.0 and rows is None:
        widen_boxes(splats, bbox, visible, coarse)
    if tiles is not None and rows is None:
        keep_tiles(bbox, visible, tiles)
    for ty0, ty1 in bands:
        sp, bb, vis = (splats, bbox, visible) if rows is None else rows(ty0, ty1)
        if coarse > 0.0 and rows is not None:
            widen_boxes(sp, bb, vis, coarse)
        if rows is not None and front is not None:
            # each band's rows are new: the visibility of its splats, from the whole front
            t = time.perf_counter()
            apply_visibility(sp, vis, front, fw, fh, margin, coc_k, inv_focus, rho0, rho1)
            front_ms += _ms(t)
        t = time.perf_counter()
        offsets, ids = bin_splats(bb, vis, n_tx, ty0, ty1)
        if tiles is not None:
            offsets, ids = keep_tile_lists(offsets, ids, tiles[ty0:ty1].reshape(-1))
        bin_ms += _ms(t)
        t = time.perf_counter()
        tile_stats = np.zeros((len(offsets) - 1, 3), np.int64)
        rasterize_band(sp, bb, offsets, ids, n_tx, ty0, w, h, float(settings.cutoff),
                       background, image, depth, weight, tile_stats, coc_k, inv_focus, rho0,
                       rho1, blades, table, u_c, numba.config.NUMBA_NUM_THREADS, coarse)
        raster_ms += _ms(t)
        layers[ty0:ty1] = tile_stats[:, 2].reshape(-1, n_tx)
        frags += int(tile_stats[:, 0].sum())
        overflows += int(tile_stats[:, 1].sum())
        pairs += len(ids)
    stats = {"fragments": frags, "abuffer_overflows": overflows, "tile_pairs": pairs,
             "bands": len(bands), "bin_ms": bin_ms, "raster_ms": raster_ms,
             "front_ms": front_ms, "tile_layers": layers}
    return image, depth, weight, stats


def front_map(camera: Camera, margin: int):
    """An empty front map (``abuffer.front_fragments``): the image and ``margin`` pixels
    round it, ((H + 2 margin) * (W + 2 margin), FRONT_FIELDS) float32 of inf."""
    from ..raster.abuffer import FRONT_FIELDS

    fw, fh = camera.width + 2 * margin, camera.height + 2 * margin
    return np.full((fh * fw, FRONT_FIELDS), np.inf, np.float32)


def front_chunk(splats, visible, camera: Camera, front, margin: int) -> None:
    """The front pass's opaque unblurred disks of some splats into ``front`` (``front_map``
    of that margin), binned by boxes of their own (``abuffer.front_boxes``) over the whole
    map; called on the chunks of a cut in its order, it draws the map the whole cut draws
    at once."""
    from ..raster.abuffer import TILE, bin_splats, front_band, front_boxes

    fw, fh = camera.width + 2 * margin, camera.height + 2 * margin
    n = splats.shape[0]
    box = np.empty((n, 4), np.int32)
    use = np.empty(n, np.bool_)
    front_boxes(splats, visible, fw, fh, margin, box, use)
    n_tx = -(-fw // TILE)
    offsets, ids = bin_splats(box, use, n_tx, 0, -(-fh // TILE))
    front_band(splats, offsets, ids, n_tx, fw, fh, margin, front)


# -- helpers -----------------------------------------------------------------------------

_WARM = False
# Seconds a cold first run spends compiling the renderer's kernels (``warm_up``), measured
# on the developers' 2-core machine (shared, so a range; README, "numba"); the preparation's
# are ``prep.PREP_COMPILE_SECONDS``.
COMPILE_SECONDS = 90


def kernel_cached(kernel) -> bool:
    """Whether numba's disk cache holds ``kernel`` (a ``cache=True`` dispatcher) compiled
    from the current source. Reads numba's cache index (a private interface): True if it
    cannot, so that a changed numba says nothing rather than fails."""
    try:
        return bool(kernel._cache._cache_file._load_index())
    except Exception:  # noqa: BLE001
        return True


def kernels_compiled() -> bool:
    """Whether numba's disk cache holds the rasteriser for the current source; False on a
    first run (or after an upgrade), when ``warm_up`` compiles every kernel: about
    COMPILE_SECONDS."""
    from ..raster.abuffer import rasterize_band

    return kernel_cached(rasterize_band)


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel, so that timings exclude JIT.

    On a first run (``kernels_compiled`` is False) the rasteriser, half of the compile time,
    compiles in a second process into numba's disk cache (``compile_rasteriser``) while this
    one compiles the LOD cut and the projection: on two cores the first frame waits about
    half as long (``bench/compile_time.py``). If that process fails, this one compiles the
    rasteriser itself."""
    global _WARM
    if _WARM:
        return
    _WARM = True
    # one small frame compiles every kernel: their argument types do not change between
    # pinhole and DOF frames, or disk and elliptical surfels
    s = Surfels(positions=[[0, 0, 0], [0.1, 0, 0]], normals=[[0, 0, 1], [0, 0, 1]],
                radius=[0.1, 0.1], colors=[[1, 1, 1], [1, 1, 1]])
    cam = Camera(eye=(0, 0, 1), target=(0, 0, 0), width=8, height=8)
    lens, settings = ThinLens(focus_distance=0.5, aperture=0.1), RenderSettings()
    helper = None if kernels_compiled() else _start_rasteriser_compile()
    if helper is not None:
        try:
            source = select(s, cam, lens, settings)
            project(source, shade_surfels(source, cam, settings), cam, lens, settings)
        finally:
            helper.wait()  # its kernels are in the disk cache now: the frame below loads them
    render_cpu(s, cam, lens, settings)


def compile_rasteriser() -> None:
    """Compile the rasterisation kernels (binning, front pass, A-buffer) into numba's disk
    cache, on inputs made here rather than by the projection (the same types and layouts as
    ``project`` gives: ``tests/test_render.py`` checks that a frame after this compiles no
    rasteriser kernel again). Run by ``warm_up`` in a second process."""
    from ..splat.project import N_FIELDS

    cam = Camera(eye=(0, 0, 1), target=(0, 0, 0), width=8, height=8)
    lens, settings = ThinLens(focus_distance=0.5, aperture=0.1), RenderSettings()
    splats = np.zeros((2, N_FIELDS), np.float32)
    bbox = np.zeros((2, 4), np.int32)
    visible = np.zeros(2, np.bool_)
    bands = plan_bands(bbox, visible, cam, settings)
    rasterize(splats, bbox, visible, bands, cam, settings, merge_parameters(cam, lens, settings),
              lens)


def _start_rasteriser_compile():
    """``compile_rasteriser`` in a new Python process (None if one cannot start)."""
    import subprocess
    import sys

    code = "from dofsplat.backends.cpu import compile_rasteriser; compile_rasteriser()"
    try:
        return subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        return None


_LOCAL = threading.local()
# a buffer larger than this is not kept between frames (a 10 M-surfel frame's splats, 1.9 GB,
# would stay allocated after render returned)
WORKSPACE_MAX_BYTES = 256 << 20


def _workspace() -> dict:
    """This thread's frame buffers, reused by the next frame: a frame's tens of MB of fresh
    pages cost as much as the projection itself on some machines (page faults: 52 against
    104 ms for the plane's 186,000 splats on the 2-core EPYC)."""
    ws = getattr(_LOCAL, "workspace", None)
    if ws is None:
        ws = _LOCAL.workspace = {}
    return ws


def _buffer(workspace: dict | None, name: str, shape: tuple, dtype) -> np.ndarray:
    """An uninitialised array of this shape: from ``workspace`` when it holds one large
    enough (a view of its first rows), else new (and kept there, up to
    WORKSPACE_MAX_BYTES)."""
    if workspace is None or math.prod(shape) * np.dtype(dtype).itemsize > WORKSPACE_MAX_BYTES:
        return np.empty(shape, dtype)
    have = workspace.get(name)
    if have is None or have.dtype != dtype or have.shape[1:] != shape[1:] or have.shape[0] < shape[0]:
        have = workspace[name] = np.empty((max(shape[0], 1),) + tuple(shape[1:]), dtype)
    return have[:shape[0]]


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0
