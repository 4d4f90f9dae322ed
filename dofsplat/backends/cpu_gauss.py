"""The CPU pipeline of a Gaussian scene's frame (``dofsplat.gauss``), stage by stage:

    project (footprint, colour, the lens's blur) -> sort by depth, bin to tiles ->
    composite front to back -> background, to linear RGB

With the lens in parts (K = the larger of ``settings.gaussian_lens_samples``, 4 by default,
and ``lens_samples``; ``frame.lens_parts``) the frame is K such passes, each seen from its
part's centroid with the residual blur, averaged.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from ..jit import numba
from ..camera import Camera
from ..colors import linear_to_srgb
from ..frame import RenderResult, RenderSettings, coc_coefficients, lens_parts
from ..gauss.composite import (TILE, bin_tiles, composite_tiles, depth_order, finish_image,
                               finish_shares, keep_best_share)
from ..gauss.project import (BLUR_NONE, BLUR_OURS, BLUR_VIEWERS, EPS2D, N_FIELDS, intrinsics,
                             project_gaussians, view_matrix)
from ..gauss.lod import GaussianArrays, cut_arrays, select_cut, tree_for
from ..gaussians import Gaussians
from ..splat.subaperture import aperture_second_moment

NO_SHARE = np.zeros(0, np.float32)  # project_gaussians: no lens visibility
NO_SEEN = np.zeros((0, 0), np.float32)  # composite_tiles: no visible alpha kept
BLURS = {"ours": BLUR_OURS, "viewers": BLUR_VIEWERS}


def render_gaussians_cpu(scene: Gaussians, camera: Camera, lens,
                         settings: RenderSettings) -> RenderResult:
    """A frame of a Gaussian scene (``render`` dispatches here); ``settings.gaussian_blur``
    picks ours or the viewers' blur (``gauss/project.py``)."""
    t0 = time.perf_counter()
    blur = settings.gaussian_blur
    k = max(settings.lens_samples, settings.gaussian_lens_samples)
    parts = lens_parts(camera, lens, replace(settings, lens_samples=k))
    n_in = len(scene)
    if settings.lod and settings.gaussian_lod and coc_coefficients(camera, lens, settings)[0] > 0.0:
        scene = lod_cut(scene, camera, lens if parts is None else parts.residual, settings)
    share = None
    if blur == "ours" and coc_coefficients(camera, lens, settings)[0] > 0.0:
        share = lens_visibility(scene, camera, lens, settings)
    if parts is None:
        color, trans, depth, stats = draw_gaussians(scene, camera, lens, settings, blur, share)
    else:
        color = np.zeros((camera.height, camera.width, 3), np.float64)
        trans = np.zeros((camera.height, camera.width), np.float64)
        depth = np.full((camera.height, camera.width), np.inf, np.float32)
        stats = {"splats_rendered": 0, "fragments": 0}
        for cam in parts.cameras:
            c, t, d, s = draw_gaussians(scene, cam, parts.residual, settings, blur, share)
            color += c
            trans += t
            np.minimum(depth, d, out=depth)
            for key in stats:
                stats[key] += s[key]
    image = to_linear_rgba(color, trans, settings.background,
                           1.0 if parts is None else 1.0 / len(parts.cameras))
    stats.update(points_in=n_in, width=camera.width, height=camera.height,
                 total_ms=(time.perf_counter() - t0) * 1000.0)
    alpha = image[..., 3].copy()
    return RenderResult(image=image, depth=depth, weight=alpha, stats=stats)


def lod_cut(scene: Gaussians, camera: Camera, lens, settings: RenderSettings) -> GaussianArrays:
    """The scene's LOD cut for this frame (``gauss/lod.py``): coarser Gaussians where the
    lens (a part's residual, with the lens in parts) blurs more than they are wide. The
    cut depends on depth alone, so one serves every part of the lens."""
    tree = tree_for(scene)
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    rows = select_cut(tree, view_matrix(camera), intrinsics(camera)[0], camera.near if
                      camera.frustum is None else camera.frustum[4], coc_k, inv_focus,
                      blur_variance(lens), settings.lod_blur_fraction)
    return cut_arrays(tree, rows)


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
    # the pixels of the drawn Gaussians' boxes: what the compositing may visit
    box = boxes[visible].astype(np.int64)
    stats["fragments"] = int(np.sum((box[:, 1] - box[:, 0]) * (box[:, 3] - box[:, 2])))
    return color, trans, depth, stats


def project(scene: Gaussians, camera: Camera, lens, settings: RenderSettings,
            blur: str = "ours", share=None):
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
                      else camera.frustum[4], 1e10, EPS2D, settings.gaussian_antialiased,
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
                 out)
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
        rows, boxes, visible = project(scene, cam, None, settings)
        n_tx, n_ty = -(-cam.width // TILE), -(-cam.height // TILE)
        offsets, ids = bin_tiles(depth_order(rows, visible), boxes, n_tx, n_ty)
        h, w = cam.height, cam.width
        seen = np.zeros((numba.get_num_threads() + 1, len(scene)), np.float32)
        composite_tiles(rows, boxes, offsets, ids, n_tx, w, h, np.empty((h, w, 3), np.float32),
                        np.empty((h, w), np.float32), np.empty((h, w), np.float32), seen)
        keep_best_share(rows, visible, seen.sum(axis=0), best)
    finish_shares(best)
    return best


def visibility_cameras(camera: Camera, lens, views: int = 6, scale: int = 2) -> list[Camera]:
    """The pinhole views of ``lens_visibility``: from the lens centre and ``views`` points on
    its rim, at 1/scale the resolution, focused where the lens is."""
    from ..camera import effective_diameter, lens_camera

    small = replace(camera, width=max(1, camera.width // scale),
                    height=max(1, camera.height // scale))
    radius = 0.5 * effective_diameter(camera, lens)
    offsets = [(radius * math.cos(2 * math.pi * k / views),
                radius * math.sin(2 * math.pi * k / views)) for k in range(views)]
    return [small] + [lens_camera(small, o, float(lens.focus_distance)) for o in offsets]


# -- helpers -----------------------------------------------------------------------------

COMPILE_SECONDS = 25  # the Gaussian kernels' cold compile on 2 cores (22 s, a loaded machine)


def kernels_compiled() -> bool:
    """Whether numba's disk cache holds the Gaussian kernels for the current source (False
    on a first run, when ``warm_up`` compiles them: about COMPILE_SECONDS)."""
    from .cpu import kernel_cached

    return kernel_cached(project_gaussians) and kernel_cached(composite_tiles)


def warm_up() -> None:
    """Compile (or load) the Gaussian kernels: a frame of two Gaussians through a lens."""
    scene = Gaussians(positions=[[0, 0, 0], [0.1, 0, 0]], scales=[[0.1] * 3] * 2,
                      rotations=[[1, 0, 0, 0]] * 2, opacity=[0.5, 0.5],
                      sh=np.zeros((2, 1, 3), np.float32))
    camera = Camera(eye=(0, 0, 1), target=(0, 0, 0), width=8, height=8)
    from ..camera import ThinLens

    render_gaussians_cpu(scene, camera, ThinLens(focus_distance=0.5, aperture=0.1),
                         RenderSettings())

