"""The CPU pipeline of a Gaussian scene's frame (``dofsplat.gauss``), stage by stage:

    project (footprint, colour, the lens's blur) -> sort by depth, bin to tiles ->
    composite front to back -> background, to linear RGB

Through a lens with our blur (``gaussian_blur = "ours"``) the frame first takes the LOD cut
(``lod_cut``) and what the lens sees of each Gaussian (the lens visibility). With the lens
in parts (K = the larger of ``settings.gaussian_lens_samples``, 4 by default, and
``lens_samples``, more where the lens is wide against its focus distance: ``part_count``;
``frame.lens_parts``) the frame is K passes, each seen from its part's
centroid with the residual blur, averaged in linear light; each pass is drawn in layers
(``LAYERS``, ``draw_layered``, ``gauss/layers.py``): slabs of depth, each at the resolution
its blur allows, every image of the frame composited in one loop. A widely blurred layer is
*summed* (``mark_summed``): drawn alone and sharp, blurred, and joined in linear light
(``blur_summed``); the other blurred layers take a lens visibility from sharp views of
their own (``layer_shares``). bench/RESULTS.md, "Gaussian scenes against gsplat and the
lens reference", has the figures and their commands.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np

from ..jit import numba
from ..camera import Camera, effective_diameter, lens_camera
from ..colors import linear_to_srgb
from ..frame import RenderResult, RenderSettings, coc_coefficients, lens_parts
from ..gauss.composite import (DECODE, ENCODE, TILE, add_linear_parts, best_view_shares,
                               bin_tiles, composite_tiles, depth_order, finish_image,
                               finish_linear_image, finish_shares, keep_best_share)
from ..gauss.layers import (BLUR_REACH, IM_HEIGHT, IM_PIXEL0, IM_ROW0, IM_ROW1, IM_SOURCE,
                            IM_SUM, IM_WIDTH, MAX_LAYERS, N_BLUR, N_P, P_BLUR_VARIANCE,
                            P_COC_K, P_CX, P_CY, P_FX, P_FY, P_HEIGHT, P_INV_FOCUS, P_NEAR,
                            P_WIDTH, bin_images, blur_columns, blur_rows, combine_layers,
                            composite_images, filled_tiles, image_table, layer_keys,
                            live_tiles, project_layers)
from ..gauss.project import (BLUR_NONE, BLUR_OURS, BLUR_VIEWERS, EPS2D, N_FIELDS, intrinsics,
                             project_gaussians, project_shifted_views, view_matrix)
from ..gauss.lod import GaussianArrays, cut_arrays, select_cut, tree_for
from ..gaussians import Gaussians
from ..splat.subaperture import aperture_second_moment

NO_SHARE = np.zeros(0, np.float32)  # project_gaussians: no lens visibility
NO_SEEN = np.zeros((0, 0), np.float32)  # composite_tiles: no visible alpha kept
BLURS = {"ours": BLUR_OURS, "viewers": BLUR_VIEWERS}


@dataclass(frozen=True)
class LayerSettings:
    """How the lens in parts is drawn (``draw_layered``) and what it sees
    (``lens_visibility_by_shifts``). The figures are PSNR against the lens reference of the
    donut, the guitar and playbot seen as ``bench/gaussians.py`` sees them (issue 48), at
    640 x 480, 10 and 35 px, against references of 64 samples (2026-11-28)."""

    lod_scale: float = 0.3  # the LOD cut's stop is this x ``lod_blur_fraction`` (0.35 x 0.3, about 0.1): a summed layer draws its Gaussians sharp, merged ones too (at 35 px the guitar and the biker 2.1 dB closer over black, playbot 1.3, the donut -0.7 / +1.7; about the same time at 1920 x 1080; 320 x 240, 64-sample references)
    enabled: bool = True  # False: each part drawn whole at full resolution, and lens_visibility (the frame of 2026-11-28)
    alpha: float = 0.35  # a layer's pixel is at most 1/alpha x its Gaussians' residual blur (standard deviation): 0.6, 0.45 and 0.35 score alike, 0.25 loses 0.5 dB on the guitar at 35 px
    max_level: int = 4  # the coarsest layer is 1/2^max_level the resolution (5 lost 0.5 dB at 35 px)
    split_level: int = 4  # levels up to this are layers of their own (past max_level at its scale; 6: the donut at 35 px +1.0 / -1.2 dB over black / white, the guitar alike, 64-sample references)
    sharp_coc: float = 0.0  # px: Gaussians whose whole-lens C_r is below this are drawn once, from the lens centre (the "sharp slab"), not by each part: 0, none. At 1 px (the default to stop 61) 5-16 % fewer fragments at 1920 x 1080 and 35 px, but 0.0-2.0 dB further from the reference at 320 x 240 and 1920 x 1080 (playbot at 1920 x 1080, 10 px: 52.3 against 54.2), and over white 12.6 dB on the fruit at 10 px, whose in-focus label the rim of a lens 2.3 x as wide as its distance sees at 49 degrees (stop 62)
    part_angle: float = 2.0  # the lens in more parts where it is wide against its focus distance P: at least (D / (P part_angle))^2 of them, so that a part of diameter about D / sqrt(K) sees a Gaussian from directions under part_angle x its depth apart (``part_count``; a footprint, drawn about one view's shape, changes with the view): on the fruit at 35 px (D = 8.1 P, 16 parts) 39.2 dB over black at 320 x 240 (bench/gaussians.py), stop 61's 4 parts 30.8; the other scenes at 1920 x 1080 keep 4
    max_parts: int = 16  # ... at most (32: the fruit at 35 px 38.2 dB against 16's 38.8, stop 61's frame)
    visibility_views: int = 4  # lens visibility: views on the lens's rim, besides its centre (6 scored alike)
    visibility_scale: int = 4  # lens visibility: at 1/this the resolution at least (8 lost 1-4 dB at 640 x 480, 10 and 35 px) ...
    visibility_coc_fraction: float = 0.1  # ... and coarser where the blur allows: a visibility pixel up to this x the median C_r of the frame's Gaussians (``visibility_scale_for``; 0.2 lost 0.23-0.44 dB on playbot)
    visibility_max_scale: int = 16  # ... at most 1/this the resolution ...
    visibility_min_size: int = 120  # ... and never coarser than 1/visibility_scale where that leaves the visibility image fewer pixels than this along its longer side
    visibility_eps2d: float = 1.0 / 12.0  # lens visibility: its views' low-pass, px^2 of their pixels: a pixel's own area variance (the trainers' 0.3: -0.6 to +0.2 dB, 1.2 x the visibility's time)
    summed_level: int = 1  # layers of this level and coarser (a part's blur sigma >= alpha 2^level px) are summed where their blur is wide (``mark_summed``), the others weighed by sharp views of their own (``blurred_layers``, ``layer_shares``; docs/maths.md, "Gaussian scenes", item 2); split_level + 1: none (the frame before stop 59, with the whole frame's lens visibility)
    summed_ratio: float = 1.0  # a blurred layer is summed where a part's blur is at least this x its Gaussians' footprints (the median; ``mark_summed``): 0 (every blurred layer summed) cost the fruit at 10 px 14.7 dB over black at 320 x 240, the others within 0.9 dB (stop 61, 64-sample references)
    sharp_scale: int = 2  # a summed layer is drawn alone and sharp at 1/this the resolution (its "sharp view"; the prototype, stop 60: 1/4 lost up to 4.2 dB, full resolution up to 1.5) ...
    sharp_fraction: float = 0.25  # ... or at 1/(this x its layer's scale) where coarser, a power of 2 (0.5: the donut at 10 px -1.9 dB over black, 320 x 240; 0.25: -0.5..+0.6 dB there, the guitar's 35 px frame at 1920 x 1080 0.86 x the time)
    sharp_max_blur: float = 8.0  # ... and coarser still where its blur would be more than this many of its pixels (so that its margin, 3 blurs, stays bounded at any blur; no 35 px frame of the bench reaches it)
    sharp_eps2d: float = 0.04  # ... with this low-pass, px^2 of its pixels (0.3 lost 0.5-6 dB in the prototype)
    summed_alpha: float = 0.7  # ... then blurred onto its image, whose pixel is at most 1/this x the blur, a power of 2 below its layer's scale (a blurred edge is sampled, where the layers' alpha is for footprints at least that wide: 0.35 scored -3.2..+0.9 dB at 320 x 240, the donut at 10 px -3.2 over black, playbot at 10 px +0.8; 1.0 within -0.3..+0.8 of 0.7, the guitar's blur at 1920 x 1080, 35 px 1.8 x 0.7's time)
    blur_quantile: float = 0.5  # ... by a Gaussian of this quantile of its Gaussians' blur (a part's sigma; 0.25: -0.3..+0.8 dB at 320 x 240)
    share_views: int = 8  # a blurred layer that is not summed: each Gaussian's largest seen share in sharp views of its layer alone from the lens centre and this many points ...
    share_radius: float = 0.7  # ... at this fraction of the lens's radius ...
    share_scale: int = 4  # ... at 1/this the resolution ...
    share_eps2d: float = 0.04  # ... with this low-pass, px^2 of their pixels

LAYERS = LayerSettings()


def part_count(camera: Camera, lens, settings: RenderSettings) -> int:
    """How many parts the lens is drawn in: the larger of ``lens_samples`` and
    ``gaussian_lens_samples`` (4 by default; 1, one pass, is kept), and, where the lens is
    wide against its focus distance, as many as a part's view of a Gaussian asks
    (``LAYERS.part_angle``), up to ``LAYERS.max_parts``."""
    k = max(settings.lens_samples, settings.gaussian_lens_samples)
    if k == 1 or lens is None or LAYERS.part_angle <= 0.0:
        return k
    wide = effective_diameter(camera, lens) / (float(lens.focus_distance) * LAYERS.part_angle)
    return max(k, min(LAYERS.max_parts, math.ceil(wide * wide)))


def render_gaussians_cpu(scene: Gaussians, camera: Camera, lens,
                         settings: RenderSettings) -> RenderResult:
    """A frame of a Gaussian scene (``render`` dispatches here); ``settings.gaussian_blur``
    picks ours or the viewers' blur (``gauss/project.py``)."""
    t0 = time.perf_counter()
    blur = settings.gaussian_blur
    parts = lens_parts(camera, lens, replace(settings,
                                             lens_samples=part_count(camera, lens, settings)))
    n_in = len(scene)
    blurred = coc_coefficients(camera, lens, settings)[0] > 0.0
    lod = settings.lod and settings.gaussian_lod and blurred
    layered = LAYERS.enabled and parts is not None and blur == "ours"
    stats = {"lens_samples": 1 if parts is None else len(parts.cameras)}
    t = time.perf_counter()
    if layered:
        positions = scene.positions  # the scene's, not the cut's (``visibility_scale_for``)
        scene, layers = in_layers(scene, camera, lens, parts, settings, lod)
    elif lod:
        scene = lod_cut(scene, camera, lens if parts is None else parts.residual, settings)
    stats["select_ms"] = _ms(t)
    t = time.perf_counter()
    share = None
    if layered:
        stats["summed_layers"] = len(summed_layers(layers))
    if layered and blurred_layers(layers):
        share = layer_shares(scene, layers, camera, lens, settings)
    elif layered:
        vis_scale = visibility_scale_for(positions, camera, lens, settings)
        share = lens_visibility_by_shifts(scene, camera, lens, settings, scale=vis_scale)
        stats["visibility_scale"] = vis_scale
    elif blur == "ours" and blurred:
        share = lens_visibility(scene, camera, lens, settings)
    stats["visibility_ms"] = _ms(t)
    if layered:
        image, depth, drawn = draw_layered(scene, layers, camera, lens, parts, settings, share)
    else:
        image, depth, drawn = draw_passes(scene, camera, lens, parts, settings, blur, share)
    stats.update(drawn)
    stats.update(points_in=n_in, width=camera.width, height=camera.height,
                 total_ms=(time.perf_counter() - t0) * 1000.0)
    alpha = image[..., 3].copy()
    return RenderResult(image=image, depth=depth, weight=alpha, stats=stats)


def draw_passes(scene, camera: Camera, lens, parts, settings: RenderSettings, blur: str,
                share):
    """One pass (parts None), or each part drawn whole at full resolution, over the
    background and averaged in linear light (``gauss.composite.add_linear_part``): (image
    (H, W, 4) linear RGBA, depth (H, W), stats)."""
    if parts is None:
        color, trans, depth, stats = draw_gaussians(scene, camera, lens, settings, blur, share)
        return to_linear_rgba(color, trans, settings.background), depth, stats
    h, w = camera.height, camera.width
    bg = linear_to_srgb(np.asarray(settings.background, np.float64))
    color = np.zeros((h, w, 3), np.float32)
    trans = np.zeros((h, w), np.float32)
    depth = np.full((h, w), np.inf, np.float32)
    stats = {"splats_rendered": 0, "fragments": 0}
    for cam in parts.cameras:
        c, t, d, s = draw_gaussians(scene, cam, parts.residual, settings, blur, share)
        add_linear_parts(c, t, bg, DECODE, color, trans)
        np.minimum(depth, d, out=depth)
        for key in stats:
            stats[key] += s[key]
    image = np.empty((h, w, 4), np.float32)
    finish_linear_image(color, trans, 1.0 / len(parts.cameras), image)
    return image, depth, stats


def lod_cut(scene: Gaussians, camera: Camera, lens, settings: RenderSettings) -> GaussianArrays:
    """The scene's LOD cut for this frame (``gauss/lod.py``): coarser Gaussians where the
    lens (a part's residual, with the lens in parts) blurs more than they are wide. The
    cut depends on depth alone, so one serves every part of the lens."""
    tree, rows = lod_rows(scene, camera, lens, settings)
    return cut_arrays(tree, rows)


def lod_rows(scene: Gaussians, camera: Camera, lens, settings: RenderSettings):
    """(tree, rows (M,)): ``lod_cut``'s tree and the rows of it drawn."""
    tree = tree_for(scene)
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    rows = select_cut(tree, view_matrix(camera), intrinsics(camera)[0], camera.near if
                      camera.frustum is None else camera.frustum[4], coc_k, inv_focus,
                      blur_variance(lens), settings.lod_blur_fraction)
    return tree, rows


# -- the lens in layers (gauss/layers.py) -------------------------------------------------

@dataclass
class Layers:
    """A frame's Gaussians by layer (``layer_order``)."""

    order: np.ndarray  # (N,) int64: the frame's Gaussians in memory order
    spans: np.ndarray  # (L, 2) int64: layer j (front to back) is memory rows spans[j, 0] .. spans[j, 1]
    scales: np.ndarray  # (L,) int64: layer j is drawn at 1/scales[j] the resolution
    levels: np.ndarray  # (L,) int64: layer j's level (``layer_keys``)
    summed: np.ndarray  # (L,) bool: layer j is summed, not blended (``mark_summed``)
    blur: np.ndarray  # (L,) float64: a summed layer's blur, the standard deviation (px) of a part's (``mark_summed``)
    sharp: int  # the sharp slab's layer (drawn once, from the lens centre): first in memory


def in_layers(scene: Gaussians, camera: Camera, lens, parts, settings: RenderSettings,
              lod: bool):
    """(arrays, layers): the frame's Gaussians (the LOD cut, chosen by the parts' residual
    blur, where lod; else the scene) gathered once in ``layer_order``'s order."""
    if lod:
        stop = settings.lod_blur_fraction * LAYERS.lod_scale
        tree, rows = lod_rows(scene, camera, parts.residual,
                              replace(settings, lod_blur_fraction=stop))
        layers = layer_order(tree.positions[rows], camera, lens, parts)
        arrays = cut_arrays(tree, rows[layers.order])
    else:
        layers = layer_order(scene.positions, camera, lens, parts)
        o = layers.order
        arrays = GaussianArrays(positions=scene.positions[o], scales=scene.scales[o],
                                rotations=scene.rotations[o], opacity=scene.opacity[o],
                                sh=scene.sh[o], level=np.zeros(len(o), np.int8))
    mark_summed(arrays, layers, camera, lens, parts)
    return arrays, layers


def mark_summed(arrays, layers: Layers, camera: Camera, lens, parts) -> None:
    """Set ``layers.summed`` and ``layers.blur``: a layer other than the sharp slab is
    summed where its level is ``LAYERS.summed_level`` or coarser and its blur is wide
    against its Gaussians' own footprints: the median over them of a part's blur (standard
    deviation, px) over the footprint's (f sqrt(s2 s3) / z, the two largest scales) at
    least ``summed_ratio``. A summed layer is its sharp view (at 1/2 the resolution or
    coarser) blurred by ``blur``, its Gaussians' blur's ``blur_quantile``: where the blur is
    narrower than the footprints, what the view holds is finer than it can draw, and the
    layer stays blended (docs/maths.md, "Gaussian scenes", item 2)."""
    view = view_matrix(camera)
    coc_k, inv_focus = lens.coc_coefficients(camera)
    sigma_k = parts.rho * math.sqrt(blur_variance(lens)) * coc_k
    fx = intrinsics(camera)[0]
    summed = np.zeros(len(layers.scales), np.bool_)
    blur = np.zeros(len(layers.scales))
    for j in blurred_layers(layers):  # (only their rows: this is every frame's work)
        a, b = layers.spans[j]
        z = np.asarray(arrays.positions[a:b], np.float64) @ view[2, :3] + view[2, 3]
        s = np.sort(np.asarray(arrays.scales[a:b], np.float64), axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            # blur sigma_k |1/z - 1/P| over the footprint f sqrt(s2 s3) / z (negative
            # behind the camera, where nothing is drawn)
            ratio = (sigma_k * np.abs(1.0 - z * inv_focus) * np.sign(z)
                     / (fx * np.sqrt(s[:, 1] * s[:, 2])))
        summed[j] = np.median(ratio) >= LAYERS.summed_ratio
        ahead = z > 0.0
        if summed[j] and np.any(ahead):
            blur[j] = np.quantile(sigma_k * np.abs(1.0 / z[ahead] - inv_focus),
                                  LAYERS.blur_quantile)
    layers.summed = summed & (blur > 0.0)
    layers.blur = blur


def layer_order(positions: np.ndarray, camera: Camera, lens, parts) -> Layers:
    """The Gaussians by layer (``gauss.layers.layer_keys``, from their depths from the lens
    centre: every part's are the same, a part's camera moving within the lens plane), in
    memory: the sharp slab first, then the other layers front to back, nearest first within
    each, so that a part projects one run of rows and each of its layers is a run of that."""
    view = view_matrix(camera)
    z = np.asarray(positions, np.float64) @ view[2, :3] + view[2, 3]
    coc_k, inv_focus = lens.coc_coefficients(camera)
    with np.errstate(divide="ignore"):
        coc = coc_k * np.abs(1.0 / z - inv_focus)
    key, scales, levels = layer_keys(z, coc, inv_focus,
                                     parts.rho * math.sqrt(blur_variance(lens)),
                                     LAYERS.sharp_coc, LAYERS.alpha, LAYERS.max_level,
                                     LAYERS.split_level)
    sharp = (len(scales) - 1) // 2
    # the keys grow with depth: sorted nearest first they run in order, and moving the
    # sharp slab to the front keeps every layer a run
    by_depth = np.argsort(z, kind="stable")
    in_sharp = key[by_depth] == sharp
    order = np.concatenate([by_depth[in_sharp], by_depth[~in_sharp]])
    counts = np.bincount(key, minlength=len(scales))
    spans = np.zeros((len(scales), 2), np.int64)
    start = spans[sharp, 1] = counts[sharp]
    for j in range(len(scales)):
        if j != sharp:
            spans[j] = start, start + counts[j]
            start += counts[j]
    return Layers(order=order, spans=spans, scales=scales, levels=levels,
                  summed=np.zeros(len(scales), np.bool_), blur=np.zeros(len(scales)),
                  sharp=sharp)


def summed_layers(layers: Layers) -> list[int]:
    """The layers (their indices in ``layers``) whose Gaussians are summed, not blended
    (``mark_summed``'s choice among the ``blurred_layers``; docs/maths.md, "Gaussian
    scenes", item 2)."""
    return [int(j) for j in np.flatnonzero(layers.summed)]


def layer_shares(scene: GaussianArrays, layers: Layers, camera: Camera, lens,
                 settings: RenderSettings) -> np.ndarray:
    """(N,) float32, or None where no layer needs it: each Gaussian's lens visibility in the
    ``blurred_layers`` that are not summed (its clipped share, ``lens_share``, largest over
    sharp views of its layer alone from the lens centre and ``LAYERS.share_views`` points
    at ``share_radius`` of the lens's radius, ``lens_visibility_by_shifts``), 1 in the rest
    (a summed layer is drawn sharp, and a layer blurred under 0.7 px takes none)."""
    weighed = weighed_layers(layers)
    if not weighed:
        return None
    share = np.ones(len(scene), np.float32)
    for j in weighed:
        a, b = layers.spans[j]
        sub = GaussianArrays(positions=scene.positions[a:b], scales=scene.scales[a:b],
                             rotations=scene.rotations[a:b], opacity=scene.opacity[a:b],
                             sh=scene.sh[a:b], level=scene.level[a:b])
        share[a:b] = lens_visibility_by_shifts(
            sub, camera, lens, settings, views=LAYERS.share_views, scale=LAYERS.share_scale,
            radius=LAYERS.share_radius, eps2d=LAYERS.share_eps2d)
    return share


def weighed_layers(layers: Layers) -> list[int]:
    """The ``blurred_layers`` that are not summed: those ``layer_shares`` weighs."""
    return [j for j in blurred_layers(layers) if not layers.summed[j]]


def blurred_layers(layers: Layers) -> list[int]:
    """The layers (their indices, with any Gaussian) of level ``LAYERS.summed_level`` or
    coarser, the sharp slab aside: those that are summed (``mark_summed``) or else weighed
    by ``layer_shares`` (the lens visibility's clipped share, item 1 of docs/maths.md's
    "Gaussian scenes", so that what no view sees does not bleed out of them)."""
    return [j for j, level in enumerate(layers.levels)
            if j != layers.sharp and level >= LAYERS.summed_level
            and layers.spans[j, 1] > layers.spans[j, 0]]


def draw_layered(scene: GaussianArrays, layers: Layers, camera: Camera, lens, parts,
                 settings: RenderSettings, share=None):
    """The lens in parts, each drawn in layers (``gauss/layers.py``): (image (H, W, 4) linear
    RGBA, depth (H, W), stats). The sharp slab is projected once, from the lens centre with
    the whole lens's blur; the other layers from each part's camera with the residual blur
    (a summed layer's without it, onto its sharp view), then moved onto their layer's image
    (``project_layers``, one loop); every image is composited in one loop
    (``composite_images``); each summed layer's image is blurred from its sharp view
    (``blur_summed``); each part's layers are joined per pixel and the parts averaged
    (``combine_layers``). share: the lens visibility, or None."""
    stats = {}
    t = time.perf_counter()
    h, w = camera.height, camera.width
    views, campos, cameras, spans, table, part_layers, blurs = layer_plan(
        len(scene), layers, camera, lens, parts, settings)
    if not len(table):  # nothing in front of the camera
        empty = np.zeros((h, w, 3), np.float32), np.ones((h, w), np.float32)
        return (to_linear_rgba(*empty, settings.background), np.full((h, w), np.inf, np.float32),
                {"splats_rendered": 0, "fragments": 0, "layers": 0})
    rows, boxes, visible = project_plan(scene, views, campos, cameras, spans, table, share,
                                        settings.gaussian_antialiased, LAYERS.sharp_eps2d)
    n_rows = len(rows)
    stats["project_ms"] = _ms(t)
    t = time.perf_counter()
    offsets, ids, tile_image = bin_images(table, np.arange(n_rows, dtype=np.int32), boxes,
                                          visible)
    stats["sort_ms"] = _ms(t)
    t = time.perf_counter()
    n_px = int(table[-1, IM_PIXEL0] + table[-1, IM_WIDTH] * table[-1, IM_HEIGHT])
    color = np.empty((n_px, 3), np.float32)
    trans = np.empty(n_px, np.float32)
    depth = np.empty(n_px, np.float32)
    composite_images(rows, boxes, offsets, ids, tile_image, table,
                     live_tiles(offsets, table, tile_image), color, trans, depth, NO_SEEN,
                     DECODE)
    stats["composite_ms"] = _ms(t)
    t = time.perf_counter()
    filled = np.empty(len(tile_image), np.bool_)
    filled_tiles(offsets, filled)
    blur_summed(table, blurs, offsets, color, trans, depth, filled)
    stats["blur_ms"] = _ms(t)
    t = time.perf_counter()
    out_depth = np.empty((h, w), np.float32)
    image = np.empty((h, w, 4), np.float32)
    combine_layers(table, filled, part_layers, color, trans,
                   depth, linear_to_srgb(np.asarray(settings.background, np.float64)), DECODE,
                   ENCODE, np.empty((h, w, 3), np.float32), np.empty((h, w), np.float32),
                   out_depth, image)
    stats["combine_ms"] = _ms(t)
    stats["splats_rendered"] = int(np.count_nonzero(visible))
    stats["fragments"] = box_pixels(boxes, visible)
    stats["layers"] = len(table)
    return image, out_depth, stats


def blur_summed(table, blurs, offsets, color, trans, depth, filled) -> None:
    """Each summed image (``IM_SUM``) blurred from its sharp view (``gauss.layers.blur_rows``,
    ``blur_columns``), one after another through one scratch buffer; its tiles with any
    coverage set in filled."""
    summed = np.flatnonzero(table[:, IM_SUM])
    if not len(summed):
        return
    source = table[summed, IM_SOURCE]
    scratch = np.empty((int(table[source, IM_HEIGHT].max()), int(table[summed, IM_WIDTH].max()),
                        N_BLUR), np.float32)
    for i in summed:
        blur_rows(table, blurs, i, offsets, color, trans, scratch)
        blur_columns(table, blurs, i, offsets, scratch, color, trans, depth, filled)


def project_plan(scene, views, campos, cameras, spans, table, share=None,
                 antialiased: bool = False, sharp_eps2d: float = 0.04):
    """(rows (R, N_FIELDS) float32, boxes (R, 4) int32, visible (R,) bool): every projection
    of a ``layer_plan`` (``gauss.layers.project_layers``), each row on its image. share: the
    lens visibility (N,), or None."""
    n_rows = int(np.sum(spans[:, 1] - spans[:, 0]))
    row_image = np.repeat(np.arange(len(table), dtype=np.int32),
                          table[:, IM_ROW1] - table[:, IM_ROW0])
    rows = np.empty((n_rows, N_FIELDS), np.float32)
    boxes = np.zeros((n_rows, 4), np.int32)
    visible = np.zeros(n_rows, np.bool_)
    project_layers(scene.positions, scene.scales, scene.rotations, scene.opacity, scene.sh,
                   NO_SHARE if share is None else share, views, campos, cameras, spans,
                   antialiased, sharp_eps2d, table, row_image, rows, boxes, visible)
    return rows, boxes, visible


def layer_plan(n: int, layers: Layers, camera: Camera, lens, parts, settings: RenderSettings):
    """What ``draw_layered`` (and the GPU's) projects and composites for a frame of n
    Gaussians in ``layer_order``: (views (J, 4, 4), campos (J, 3), cameras (J, N_P), spans
    (J, 3) int64: the projections, each (first Gaussian, last, first row); table (I, N_IM):
    the images; part_layers (K, L) int64: each part's images front to back, -1 after;
    blurs (I,) float64: a summed image's blur, px of its sharp view, else 0). The sharp slab
    is projected once, from the lens centre with the whole lens's blur; the other layers
    from each part's camera with the residual blur, but a summed layer (``mark_summed``)
    is two images: its sharp view (``IM_SHARP``, at 1/``sharp_scale`` the resolution or
    ``sharp_fraction`` of its layer's scale, with a margin of what its blur carries in from
    outside the frame) and its image (``IM_SUM``, blurred from the view at a pixel of at
    most 1/``summed_alpha`` its blur)."""
    h, w = camera.height, camera.width
    n_sharp = int(layers.spans[layers.sharp, 1])
    n_rest = n - n_sharp
    k = len(parts.cameras)
    # the projections: (camera, lens, first Gaussian, last, first row)
    jobs = [(camera, lens, 0, n_sharp, 0)] + [
        (cam, parts.residual, n_sharp, n, n_sharp + p * n_rest)
        for p, cam in enumerate(parts.cameras)]
    cameras = np.zeros((len(jobs), N_P))
    for j, (cam, jlens, *_) in enumerate(jobs):
        cameras[j, [P_FX, P_FY, P_CX, P_CY]] = intrinsics(cam)
        cameras[j, [P_WIDTH, P_HEIGHT]] = cam.width, cam.height
        cameras[j, P_NEAR] = cam.near if cam.frustum is None else cam.frustum[4]
        cameras[j, [P_COC_K, P_INV_FOCUS]] = coc_coefficients(cam, jlens, settings)
        cameras[j, P_BLUR_VARIANCE] = blur_variance(jlens)
    # the images: the sharp slab, then each part's other layers (a coarse one with a pixel
    # of margin, so that bilinear sampling never leaves it; a summed one flagged); each
    # part's list front to back
    summed = set(summed_layers(layers))
    images = [] if n_sharp == 0 else [(w, h, 1, 0, 0, n_sharp)]
    blurs = [0.0] * len(images)
    part_layers = np.full((k, len(layers.scales)), -1, np.int64)
    if len(layers.scales) > MAX_LAYERS:
        raise ValueError(f"layer_plan: {len(layers.scales)} layers, at most {MAX_LAYERS}")
    ss = LAYERS.sharp_scale
    for p in range(k):
        col = 0
        for j, scale in enumerate(layers.scales):
            a, b = layers.spans[j]
            if b == a:
                continue
            r0 = a + p * n_rest
            if j == layers.sharp:
                part_layers[p, col] = 0
            elif j in summed:
                # its sharp view (margin: what the blur carries in from outside the frame),
                # then its own image, blurred from that
                blur = max(layers.blur[j], 0.5)
                vs = max(ss, pow2_floor(LAYERS.sharp_fraction * scale),
                         pow2_ceil(blur / LAYERS.sharp_max_blur))
                sigma = blur / vs
                vm = int(math.ceil(BLUR_REACH * sigma)) + 1
                images.append((-(-w // vs) + 2 * vm, -(-h // vs) + 2 * vm, vs, vm, r0,
                               r0 + b - a, False, True))
                bs = min(scale, pow2_floor(blur / LAYERS.summed_alpha))
                images.append((-(-w // bs) + 2, -(-h // bs) + 2, bs, 1, r0 + b - a,
                               r0 + b - a, True, False, len(images) - 1))
                blurs += [0.0, sigma]
                part_layers[p, col] = len(images) - 1
            else:
                margin = 0 if scale == 1 else 1
                images.append((-(-w // scale) + 2 * margin, -(-h // scale) + 2 * margin, scale,
                               margin, r0, r0 + b - a))
                blurs.append(0.0)
                part_layers[p, col] = len(images) - 1
            col += 1
    return (np.stack([view_matrix(job[0]) for job in jobs]),
            np.array([job[0].eye for job in jobs], np.float64), cameras,
            np.array([job[2:] for job in jobs], np.int64), image_table(images), part_layers,
            np.array(blurs, np.float64))


def pow2_floor(x: float) -> int:
    """The largest power of 2 not above x, at least 1."""
    return 2 ** int(math.floor(math.log2(max(x, 1.0))))


def pow2_ceil(x: float) -> int:
    """The smallest power of 2 not below x, at least 1."""
    return 2 ** int(math.ceil(math.log2(max(x, 1.0))))


def draw_gaussians(scene: Gaussians, camera: Camera, lens, settings: RenderSettings,
                   blur: str = "ours", share=None):
    """One pass: (color (H, W, 3), transmittance (H, W), depth (H, W), stats). share: the
    Gaussians' ``lens_visibility``, or None."""
    stats = {}
    t = time.perf_counter()
    rows, boxes, visible = project(scene, camera, lens, settings, blur, share)
    stats["project_ms"] = _ms(t)
    t = time.perf_counter()
    n_tx, n_ty = -(-camera.width // TILE), -(-camera.height // TILE)
    offsets, ids = bin_tiles(depth_order(rows, visible), boxes, n_tx, n_ty)
    stats["sort_ms"] = _ms(t)
    t = time.perf_counter()
    h, w = camera.height, camera.width
    color = np.empty((h, w, 3), np.float32)
    trans = np.empty((h, w), np.float32)
    depth = np.empty((h, w), np.float32)
    composite_tiles(rows, boxes, offsets, ids, n_tx, w, h, color, trans, depth, NO_SEEN)
    stats["composite_ms"] = _ms(t)
    stats["splats_rendered"] = int(np.count_nonzero(visible))
    stats["fragments"] = box_pixels(boxes, visible)
    return color, trans, depth, stats


def box_pixels(boxes, visible) -> int:
    """The pixels of the drawn Gaussians' boxes (what the compositing may visit): the
    frame's "fragments". Without copying the visible rows (29 to 5 ms for a frame's 1.1 M
    rows at 1920 x 1080)."""
    width = (boxes[:, 1] - boxes[:, 0]).astype(np.int64)
    return int(np.dot(width * (boxes[:, 3] - boxes[:, 2]), visible))


def project(scene: Gaussians, camera: Camera, lens, settings: RenderSettings,
            blur: str = "ours", share=None, eps2d: float = EPS2D):
    """(rows (N, N_FIELDS) float32, boxes (N, 4) int32, visible (N,) bool): ``project_gaussians``
    for this camera and lens (share: ``lens_visibility``'s, or None)."""
    n = len(scene)
    rows = np.empty((n, N_FIELDS), np.float32)
    boxes = np.zeros((n, 4), np.int32)
    visible = np.zeros(n, np.bool_)
    fx, fy, cx, cy = intrinsics(camera)
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    mode = BLURS[blur] if coc_k > 0.0 else BLUR_NONE
    project_gaussians(scene.positions, scene.scales, scene.rotations, scene.opacity, scene.sh,
                      view_matrix(camera), np.asarray(camera.eye, np.float64), fx, fy, cx, cy,
                      camera.width, camera.height, camera.near if camera.frustum is None
                      else camera.frustum[4], 1e10, eps2d, settings.gaussian_antialiased,
                      mode, coc_k, inv_focus, blur_variance(lens),
                      NO_SHARE if share is None else share, rows, boxes, visible)
    return rows, boxes, visible


def blur_variance(lens) -> float:
    """The lens blur's variance per axis at C_r = 1 px: half the aperture's second moment
    (a disc's 1/4, a polygon's), or the paper's Gaussian bokeh's 1 / (2 ln 4)."""
    if lens is None:
        return 0.0
    return 0.5 * aperture_second_moment(getattr(lens, "bokeh", "gaussian"),
                                        getattr(lens, "blades", 0))


def to_linear_rgba(color, trans, background, scale: float = 1.0) -> np.ndarray:
    """(H, W, 4) float32: the composite over the background in the trainer's colour space
    (the background, given in linear RGB, encoded to it), decoded to linear RGB, and alpha
    1 - T (``gauss.composite.finish_pixel``): so that the image written (encoded again)
    holds the trainer's values. color and trans are scaled by ``scale`` first."""
    out = np.empty(trans.shape + (4,), np.float32)
    finish_image(color, trans, float(scale), linear_to_srgb(np.asarray(background, np.float64)),
                 DECODE, out)
    return out


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0


def lens_visibility(scene: Gaussians, camera: Camera, lens, settings: RenderSettings,
                    views: int = 6, scale: int = 2) -> np.ndarray:
    """(N,) float32 in [0, 1]: how much of each Gaussian the lens sees. The largest share of
    its alpha that is visible (alpha T summed over pixels, over its footprint's integral) in
    pinhole views from the lens centre and ``views`` points on the lens's rim, at 1/scale
    the resolution, over SHARE_SEEN, at most 1: what no view sees is 0, what some view sees
    a twentieth of or more is 1 (docs/maths.md, "Gaussian scenes": a surface's overlapping
    Gaussians each see a part of their footprint, and scaling them by that part left the
    surface too thin; only the hidden ones are to go)."""
    best = np.zeros(len(scene), np.float32)
    for cam in visibility_cameras(camera, lens, views, scale):
        rows, visible, seen = seen_in_view(scene, cam, settings)
        keep_best_share(rows, visible, seen, best)
    finish_shares(best)
    return best


def seen_in_view(scene, camera: Camera, settings: RenderSettings, eps2d: float = EPS2D):
    """(rows, visible, seen (N,) float32): a pinhole view's projection (with the low-pass
    eps2d, px^2) and each Gaussian's visible alpha, alpha T summed over its pixels
    (``composite.seen_share`` makes it a share of the footprint's integral)."""
    rows, boxes, visible = project(scene, camera, None, settings, eps2d=eps2d)
    n_tx, n_ty = -(-camera.width // TILE), -(-camera.height // TILE)
    offsets, ids = bin_tiles(depth_order(rows, visible), boxes, n_tx, n_ty)
    h, w = camera.height, camera.width
    seen = np.zeros((numba.get_num_threads() + 1, len(scene)), np.float32)
    composite_tiles(rows, boxes, offsets, ids, n_tx, w, h, np.empty((h, w, 3), np.float32),
                    np.empty((h, w), np.float32), np.empty((h, w), np.float32), seen)
    return rows, visible, seen.sum(axis=0)


def lens_visibility_by_shifts(scene, camera: Camera, lens, settings: RenderSettings,
                              views: int | None = None, scale: int | None = None, *,
                              radius: float = 1.0, eps2d: float | None = None) -> np.ndarray:
    """(N,) float32 in [0, 1]: ``lens_visibility``'s shares, from one projection (views,
    scale: ``LAYERS.visibility_views`` and ``visibility_scale`` where None). The views from
    the lens's rim differ from the centre's by a shear (``lens_camera``: a point at depth z
    moves by the rim's K (1/P - 1/z) (cos a, -sin a) pixels), so the centre's pinhole
    footprints (with ``LAYERS.visibility_eps2d`` for the low-pass) are projected once, over
    the image and a margin of the largest such move (at most half the image), sorted once
    (the depths are every view's), and each view's are those footprints moved
    (``project_shifted_views``: the mean exactly, the shape as the centre sees it); all the
    views' tiles are composited in one loop. Against ``lens_visibility`` from the same views
    the frame's PSNR against the lens reference was the same to 0.01 dB (playbot, 10 px).
    radius: the rim views at this fraction of the lens's radius; eps2d: their low-pass
    (``LAYERS.visibility_eps2d`` where None)."""
    views = LAYERS.visibility_views if views is None else views
    if scale is None:
        scale = visibility_scale_for(scene.positions, camera, lens, settings)
    small, margin, shifts, inv_focus, near, view = shifted_views(scene.positions, camera, lens,
                                                                 settings, views, scale)
    shifts = shifts * radius
    w, h = small.width, small.height
    n = len(scene)
    fx, fy, cx, cy = intrinsics(small)
    m = len(shifts)
    rows = np.empty((n, N_FIELDS), np.float32)
    boxes = np.zeros((n, 4), np.int32)
    visible = np.zeros(n, np.bool_)
    view_rows = np.empty((m * n, N_FIELDS), np.float32)
    view_boxes = np.zeros((m * n, 4), np.int32)
    view_visible = np.zeros(m * n, np.bool_)
    # (no colour is needed: the SH's constant term alone is the cheapest)
    project_shifted_views(scene.positions, scene.scales, scene.rotations, scene.opacity,
                          scene.sh[:, :1], view, np.asarray(small.eye, np.float64), fx, fy,
                          cx + margin, cy + margin, w + 2 * margin, h + 2 * margin, near, 1e10,
                          LAYERS.visibility_eps2d if eps2d is None else eps2d,
                          settings.gaussian_antialiased, margin,
                          shifts, inv_focus, rows, boxes, visible, view_rows, view_boxes,
                          view_visible)
    order = depth_order(rows, visible).astype(np.int32)
    table = image_table([(w, h, 1, 0, v * len(order), (v + 1) * len(order)) for v in range(m)])
    view_order = (np.arange(m, dtype=np.int32)[:, None] * n + order[None, :]).ravel()
    offsets, ids, tile_image = bin_images(table, view_order, view_boxes, view_visible)
    n_px = m * w * h
    seen = np.zeros((numba.get_num_threads() + 1, m * n), np.float32)
    # (only seen is read: no empty tile is written)
    composite_images(view_rows, view_boxes, offsets, ids, tile_image, table,
                     np.zeros(len(tile_image), np.bool_), np.empty((n_px, 3), np.float32), np.empty(n_px, np.float32),
                     np.empty(n_px, np.float32), seen, DECODE)
    best = np.empty(n, np.float32)
    best_view_shares(view_rows, view_visible, seen, n, best)
    return best


def visibility_scale_for(positions: np.ndarray, camera: Camera, lens,
                         settings: RenderSettings) -> int:
    """The lens visibility's scale for a frame (``lens_visibility_by_shifts``): the largest
    power of 2 within ``LAYERS.visibility_coc_fraction`` x the median whole-lens C_r (px) of
    the Gaussians in front of the camera (positions (N, 3)), at least
    ``LAYERS.visibility_scale`` and at most ``visibility_max_scale``, and coarser than
    ``visibility_scale`` only while the image keeps ``visibility_min_size`` pixels along its
    longer side (a small frame keeps 1/4: without this floor, tests/test_gaussians.py's LOD
    frame at 96 x 72 and a 46 px blur, its visibility at 1/16 while the full frame's was at
    1/8, fell from 41.0 to 31.9 dB against it). The visibility is of
    blurred Gaussians, so its pixel may grow with the blur: a frame drawn at a higher
    resolution with the same lens gets the same visibility image, where a fixed 1/4 cost
    its composite 16 x the work at 4 x the width. At 1920 x 1080 (``python
    bench/gaussians.py --visibility --size 1920x1080 --samples 32``, 2026-11-28): with the
    bench's 35 px lens (C_r 210 px at that width) the rule's 1/8 (the guitar, the biker,
    playbot) and 1/16 (the donut) scored within -0.05..+0.04 dB of 1/4, where 1/16 lost
    0.44 dB on playbot; with its 10 px lens (60 px) 1/16 lost up to 2.2
    dB, and the rule keeps 1/4 there. At 960 x 720 the same lenses' 1/8 lost up to 1.0
    and 0.23 dB (``--size 960x720``): the rule keeps 1/4 but for the donut. The frame's scene, not its LOD cut, whose rows crowd where
    the blur is small (about 100,000 of a large scene's Gaussians, evenly taken, for the
    median)."""
    view = view_matrix(camera)
    step = max(1, len(positions) // 100_000)
    z = np.asarray(positions[::step], np.float64) @ view[2, :3] + view[2, 3]
    near = camera.near if camera.frustum is None else camera.frustum[4]
    z = z[z > near]
    if not len(z):
        return LAYERS.visibility_scale
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    median = coc_k * float(np.median(np.abs(1.0 / z - inv_focus)))
    scale = LAYERS.visibility_scale
    longer = max(camera.width, camera.height)
    while (2 * scale <= min(LAYERS.visibility_coc_fraction * median,
                            LAYERS.visibility_max_scale)
           and longer // (2 * scale) >= LAYERS.visibility_min_size):
        scale *= 2
    return scale


def shifted_views(positions: np.ndarray, camera: Camera, lens, settings: RenderSettings,
                  views: int, scale: int):
    """The views of ``lens_visibility_by_shifts`` (and the GPU's): (the camera at 1/scale the
    resolution, margin px, shifts (views + 1, 2): the centre's and the rim's, pixels at
    1/P - 1/z = 1, inv_focus = 1/P, near, its view matrix (4, 4)). The margin is the
    largest move of a Gaussian in front of the camera (positions (N, 3)), at most half the
    image."""
    small = replace(camera, width=max(1, camera.width // scale),
                    height=max(1, camera.height // scale))
    w, h = small.width, small.height
    fx, fy, _, _ = intrinsics(small)
    coc_k, inv_focus = coc_coefficients(small, lens, settings)
    near = small.near if small.frustum is None else small.frustum[4]
    view = view_matrix(small)
    z = np.asarray(positions, np.float64) @ view[2, :3] + view[2, 3]
    front = z[z > near]
    reach = coc_k * float(np.max(np.abs(1.0 / front - inv_focus))) if len(front) else 0.0
    margin = int(math.ceil(min(reach, 0.5 * max(w, h))))
    radius = 0.5 * effective_diameter(small, lens)
    angles = 2.0 * math.pi * np.arange(views) / max(views, 1)
    shifts = np.zeros((views + 1, 2))  # the centre, then the rim
    shifts[1:, 0] = fx * radius * np.cos(angles)
    shifts[1:, 1] = -fy * radius * np.sin(angles)
    return small, margin, shifts, inv_focus, near, view


def visibility_cameras(camera: Camera, lens, views: int = 6, scale: int = 2) -> list[Camera]:
    """The pinhole views of ``lens_visibility``: from the lens centre and ``views`` points on
    its rim, at 1/scale the resolution, focused where the lens is."""
    small = replace(camera, width=max(1, camera.width // scale),
                    height=max(1, camera.height // scale))
    radius = 0.5 * effective_diameter(camera, lens)
    offsets = [(radius * math.cos(2 * math.pi * k / views),
                radius * math.sin(2 * math.pi * k / views)) for k in range(views)]
    return [small] + [lens_camera(small, o, float(lens.focus_distance)) for o in offsets]


# -- helpers -----------------------------------------------------------------------------

COMPILE_SECONDS = 40  # the Gaussian kernels' cold compile on 2 cores (38 s on a loaded machine; the parts drawn whole alone: 11 s)


def kernels_compiled() -> bool:
    """Whether numba's disk cache holds the Gaussian kernels for the current source (False
    on a first run, when ``warm_up`` compiles them: about COMPILE_SECONDS)."""
    from .cpu import kernel_cached

    return all(kernel_cached(kernel) for kernel in (project_gaussians, composite_tiles,
                                                    project_layers, composite_images,
                                                    combine_layers))


def warm_up() -> None:
    """Compile (or load) the Gaussian kernels: frames of two Gaussians, a pinhole, through a
    lens (the lens in layers) and in one pass (``lens_visibility``)."""
    from ..camera import ThinLens

    scene = Gaussians(positions=[[0, 0, 0], [0.1, 0, 0]], scales=[[0.1] * 3] * 2,
                      rotations=[[1, 0, 0, 0]] * 2, opacity=[0.5, 0.5],
                      sh=np.zeros((2, 1, 3), np.float32))
    camera = Camera(eye=(0, 0, 1), target=(0, 0, 0), width=8, height=8)
    lens = ThinLens(focus_distance=0.5, aperture=0.1)
    render_gaussians_cpu(scene, camera, None, RenderSettings())
    render_gaussians_cpu(scene, camera, lens, RenderSettings())
    render_gaussians_cpu(scene, camera, lens, RenderSettings(gaussian_lens_samples=1))
