"""The rendering pipeline, stage by stage (paper Sections 4-6).

    shade -> project (EWA kernel + DOF blur) -> bin to tiles -> rasterise into the A-buffer
    and resolve (surface reconstruction, compositing over the background)

``render`` is the one public entry point; each stage is a named function below.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from .camera import Camera, EyeLens, ThinLens
from .errors import DofsplatError
from .shading import HEADLIGHT, Light
from .surfels import Surfels


RECONSTRUCTIONS = ("soft", "paper")


@dataclass(frozen=True)
class RenderSettings:
    """How to render; the defaults reproduce the paper's setup (c = 2.5, Phong, headlight)."""

    cutoff: float = 2.5  # c: kernels are truncated where 1/2 x^T W^-1 x reaches c
    dof: bool = True  # False renders a pinhole image whatever the lens
    shading: str = "phong"  # "phong" or "none" (surfel colour unlit)
    lights: tuple[Light, ...] = (HEADLIGHT,)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # linear RGB under everything
    cull_backfaces: bool = True  # drop surfels whose normal faces away from the eye
    z_thickness: float = 0.1  # z-range half-thickness added to each splat, x its radius
    exact_normalization: bool = True  # normalise each kernel by its pixel sum (else 1 - e^-c)
    max_tile_pairs: int = 1 << 26  # binning memory budget (int32 entries) before banding
    lod: bool = True  # splat an LOD cut (Sections 5.3, 6.2): speed independent of the aperture
    lod_pixel_threshold: float = 1.0  # LOD: a node whose disk projects under this radius (px) is drawn whole
    lod_blur_fraction: float = 1.0  # LOD: draw a node when its filter is at most this x the DOF blur (variance)
    show_lod: bool = False  # colour each splat by its LOD level, drawn without the DOF blur (Figure 5)
    device: str = "cpu"  # "cpu", "cuda" (an NVIDIA GPU: dofsplat[cuda]) or "auto" (the GPU if one works)
    taper: bool = False  # LOD nodes' kernels fall to 0 at the cutoff (exp(-q) - e^-c): no hard-edged discs
    reconstruction: str = "soft"  # "soft": merge by parallax, without seams (ours); "paper": z-ranges only (Section 6.4)

    def __post_init__(self):
        if not (math.isfinite(self.cutoff) and self.cutoff > 0):
            raise DofsplatError(f"cutoff must be > 0, got {self.cutoff}")
        if self.cutoff > 30:
            raise DofsplatError(f"cutoff {self.cutoff} is unreasonably large (the kernel is below e^-30 there)")
        if self.shading not in ("phong", "none"):
            raise DofsplatError(f"shading must be 'phong' or 'none', got {self.shading!r}")
        bg = np.asarray(self.background, float)
        if bg.shape != (3,) or not np.all(np.isfinite(bg)) or np.any(bg < 0):
            raise DofsplatError(f"background must be three numbers >= 0, got {self.background}")
        if not (math.isfinite(self.z_thickness) and self.z_thickness >= 0):
            raise DofsplatError(f"z_thickness must be >= 0, got {self.z_thickness}")
        if self.max_tile_pairs < 1:
            raise DofsplatError("max_tile_pairs must be positive")
        if not (math.isfinite(self.lod_pixel_threshold) and self.lod_pixel_threshold >= 0):
            raise DofsplatError(f"lod_pixel_threshold must be >= 0, got {self.lod_pixel_threshold}")
        if not (math.isfinite(self.lod_blur_fraction) and 0 < self.lod_blur_fraction <= 1):
            raise DofsplatError(f"lod_blur_fraction must be in (0, 1], got {self.lod_blur_fraction}")
        if self.reconstruction not in RECONSTRUCTIONS:
            raise DofsplatError(f"reconstruction must be one of {', '.join(RECONSTRUCTIONS)}, "
                                f"got {self.reconstruction!r}")
        if self.show_lod and not self.lod:
            raise DofsplatError("show_lod needs lod=True")
        from .backends import DEVICES

        if self.device not in DEVICES:
            raise DofsplatError(f"device must be one of {', '.join(DEVICES)}, got {self.device!r}")


@dataclass
class RenderResult:
    """A rendered frame.

    image:  (H, W, 4) float32: linear RGB composited over the background, then alpha
            (the total coverage, 1 - the background's remaining transmittance)
    depth:  (H, W) float32: camera depth of the surface that contributes most to the
            pixel, inf where nothing was drawn
    weight: (H, W) float32: accumulated splat weight of the nearest surface (about 1 on a
            well-normalised surface; Section 6.3)
    stats:  points in, splats rendered, fragments, milliseconds per stage
    """

    image: np.ndarray
    depth: np.ndarray
    weight: np.ndarray
    stats: dict = field(default_factory=dict)

    @property
    def rgb(self) -> np.ndarray:
        return self.image[..., :3]

    @property
    def alpha(self) -> np.ndarray:
        return self.image[..., 3]


def render(surfels: Surfels, camera: Camera, lens: ThinLens | EyeLens | None = None,
           settings: RenderSettings | None = None, hierarchy=None) -> RenderResult:
    """Render surfels with depth of field (paper Sections 4-6).

    surfels:   the model (``Surfels``)
    camera:    view, projection and image size (``Camera``)
    lens:      ``ThinLens`` or ``EyeLens``; None, or an aperture of 0, is a pinhole
    settings:  ``RenderSettings`` (cutoff, shading, background, LOD, ...)
    hierarchy: the model's ``dofsplat.lod.Hierarchy`` when ``settings.lod``; built on first
               use and kept on the ``Surfels`` object if not given
    """
    settings = settings or RenderSettings()
    if not isinstance(surfels, Surfels):
        raise DofsplatError("render() needs a Surfels model")
    from .backends import resolve_device

    if resolve_device(settings.device) == "cuda":
        from .backends.cuda import render_cuda

        return render_cuda(surfels, camera, lens, settings, hierarchy)  # the same stages, on the GPU
    warm_up()
    times = {}
    t_start = time.perf_counter()

    t = time.perf_counter()
    source = select(surfels, camera, lens, settings, hierarchy)
    times["select_ms"] = _ms(t)

    t = time.perf_counter()
    rgb = shade_surfels(source, camera, settings)
    times["shade_ms"] = _ms(t)

    t = time.perf_counter()
    blur_lens = None if settings.show_lod else lens
    splats, bbox, visible = project(source, rgb, camera, blur_lens, settings,
                                    workspace=_workspace())
    times["project_ms"] = _ms(t)

    t = time.perf_counter()
    bands = plan_bands(bbox, visible, camera, settings)
    times["bin_ms"] = _ms(t)

    merge = merge_parameters(camera, blur_lens, settings)
    image, depth, weight, raster_stats = rasterize(splats, bbox, visible, bands, camera, settings,
                                                   merge, blur_lens)
    times["bin_ms"] += raster_stats.pop("bin_ms")
    times["raster_ms"] = raster_stats.pop("raster_ms")
    times["front_ms"] = raster_stats.pop("front_ms")
    times["total_ms"] = _ms(t_start)

    stats = {
        "points_in": int(len(surfels)),
        "lod": bool(settings.lod),
        "splats_selected": int(source.size),
        "splats_rendered": int(np.count_nonzero(visible)),
        **raster_stats,
        "width": camera.width,
        "height": camera.height,
        **times,
    }
    return RenderResult(image=image, depth=depth, weight=weight, stats=stats)


# -- stages ------------------------------------------------------------------------------


def select(surfels: Surfels, camera: Camera, lens, settings: RenderSettings, hierarchy=None):
    """What to splat: every surfel, or this frame's LOD cut (Section 6.2). A ``SplatSource``."""
    from .splat.source import from_surfels

    if not settings.lod:
        return from_surfels(surfels)
    from .lod import select_splats

    tree = lod_tree(surfels, hierarchy)
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    source = select_splats(tree, surfels, camera, coc_k, inv_focus, settings.cutoff,
                           settings.lod_pixel_threshold, settings.cull_backfaces,
                           settings.lod_blur_fraction)
    if settings.show_lod:
        source = source._replace(colors=lod_level_colors(source.level))
    return source


def lod_tree(surfels: Surfels, hierarchy=None):
    """The model's LOD ``Hierarchy``: ``hierarchy`` if given (checked), else built or cached."""
    from .lod import hierarchy_for

    tree = hierarchy if hierarchy is not None else hierarchy_for(surfels)
    if tree.n_surfels != len(surfels):
        raise DofsplatError(f"the LOD hierarchy was built for {tree.n_surfels} surfels, "
                            f"the model has {len(surfels)}")
    return tree


def lod_level_colors(level: np.ndarray) -> np.ndarray:
    """(S, 3) float32 linear colours for LOD levels (0 = a surfel), for ``show_lod``."""
    return LOD_PALETTE[np.minimum(level, len(LOD_PALETTE) - 1)]


# one colour per LOD level, leaves first (sRGB designed, stored linear); the last repeats
LOD_PALETTE = (np.array([
    [0.85, 0.85, 0.85], [0.27, 0.46, 0.85], [0.16, 0.70, 0.86], [0.20, 0.75, 0.50],
    [0.55, 0.82, 0.25], [0.95, 0.85, 0.20], [0.98, 0.60, 0.15], [0.92, 0.30, 0.20],
    [0.80, 0.20, 0.55], [0.55, 0.25, 0.70], [0.35, 0.20, 0.45], [0.15, 0.15, 0.15],
], np.float32) ** 2.2).astype(np.float32)


def shade_surfels(source, camera: Camera, settings: RenderSettings) -> np.ndarray:
    """Per-splat shading before splatting (Section 6.5): (S, 3) float32 linear RGB.

    source: a ``SplatSource`` (or ``Surfels``)
    """
    from .splat.shade import shade_fast

    if settings.shading == "none":
        return source.colors
    return shade_fast(source.positions, source.normals, source.colors, source.material,
                      camera, settings.lights, two_sided=not settings.cull_backfaces)


def coc_coefficients(camera: Camera, lens, settings: RenderSettings) -> tuple[float, float]:
    """(K, 1/P) with C_r(U) = K |1/U - 1/P|; (0, 0) for a pinhole."""
    if lens is None or not settings.dof:
        return 0.0, 0.0
    return lens.coc_coefficients(camera)


def project(source, rgb: np.ndarray, camera: Camera, lens, settings: RenderSettings,
            lod_cov: np.ndarray | None = None, workspace: dict | None = None):
    """EWA projection with the DOF blur (eqs. 8, 11, 12): splats (S, N_FIELDS), bbox, visible.

    source: a ``SplatSource`` (its ``lod_cov`` is the LOD filter) or ``Surfels`` (then
    ``lod_cov`` (N, 6), if given, is the LOD filter's world covariance per surfel);
    workspace: a dict whose arrays the splats may reuse (``render`` keeps one per thread),
    else they are new
    """
    from .splat.project import N_FIELDS, project_splats
    from .splat.source import from_surfels

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
    splats = _buffer(workspace, "splats", (n, N_FIELDS), np.float64)
    bbox = _buffer(workspace, "bbox", (n, 4), np.int32)
    visible = _buffer(workspace, "visible", (n,), np.bool_)
    disc, blades, _, moments = aperture_shape(lens, settings)
    project_splats(source.positions, source.normals, tangents, ru, rv, area,
                   np.ascontiguousarray(rgb, np.float32), source.opacity, source.lod_cov, view,
                   ax, bx, ay, by, near, camera.width, camera.height, coc_k, inv_focus,
                   float(settings.cutoff), float(settings.z_thickness),
                   bool(settings.cull_backfaces), bool(settings.exact_normalization),
                   kernel_floor(settings), disc, blades, moments, splats, bbox, visible)
    return splats, bbox, visible


def aperture_shape(lens, settings: RenderSettings):
    """(disc, blades, table, moments): whether kernels carry the aperture's shape
    (splat/bokeh.py), the (N, 2) edge normals of a polygonal aperture ((0, 2) for a round
    one), the table of the Gaussian-disc convolution for this cutoff and its moments."""
    from .splat.bokeh import aperture_moments, aperture_table, blade_normals

    disc = lens is not None and settings.dof and getattr(lens, "bokeh", "gaussian") == "disc"
    if not disc:  # no kernel reads the tables: none built (scipy.stats is not imported)
        return False, np.zeros((0, 2)), np.zeros((1, 1)), np.zeros((1, 1))
    blades = blade_normals(lens.blades, lens.blade_rotation)
    return True, blades, aperture_table(settings.cutoff), aperture_moments(settings.cutoff)


def kernel_floor(settings: RenderSettings) -> float:
    """What a tapered (LOD node's) kernel loses everywhere inside its cutoff: e^-c, else 0."""
    return math.exp(-settings.cutoff) if settings.taper else 0.0


def plan_bands(bbox, visible, camera: Camera, settings: RenderSettings) -> list[tuple[int, int]]:
    """Cut the tile rows into bands whose tile-splat pairs fit the memory budget."""
    from .raster.abuffer import TILE, tile_rows_pairs

    n_ty = -(-camera.height // TILE)
    per_row = tile_rows_pairs(bbox, visible, TILE, n_ty)
    bands, start, acc = [], 0, 0
    for ty in range(n_ty):
        if acc and acc + per_row[ty] > settings.max_tile_pairs:
            bands.append((start, ty))
            start, acc = ty, 0
        acc += int(per_row[ty])
    bands.append((start, n_ty))
    return bands


def merge_parameters(camera: Camera, lens, settings: RenderSettings) -> tuple[float, float, float, float]:
    """(K, 1/P, rho0, rho1) of the soft merge (``abuffer.merge_fraction``); K = 0 turns it off.

    The paper's reconstruction, and a pinhole, composite separate surfaces with "over" only.
    """
    from .raster.abuffer import MERGE_RHO0, MERGE_RHO1

    if settings.reconstruction == "paper":
        return 0.0, 0.0, MERGE_RHO0, MERGE_RHO1
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    return coc_k, inv_focus, MERGE_RHO0, MERGE_RHO1


def rasterize(splats, bbox, visible, bands, camera: Camera, settings: RenderSettings,
              merge=(0.0, 0.0, 0.15, 0.5), lens=None):
    """A-buffer rasterisation and resolve, band by band (Section 6.4).

    lens: the lens whose aperture shape the splats carry (``aperture_shape``).
    merge: ``merge_parameters``; with K > 0 a front pass first finds, per pixel, the
    nearest opaque unblurred disk, and every splat hidden behind a front of the same layer
    (``abuffer.splat_visibility``) gives up that share of its weight (docs/maths.md,
    "Surface reconstruction"). Changes ``splats`` and ``visible`` in place.
    """
    from .raster.abuffer import (TILE, apply_visibility, bin_splats, front_band,
                                 rasterize_band)

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
    binned = {}
    if coc_k > 0.0:
        t = time.perf_counter()
        front = np.full((h * w, 2), np.inf, np.float32)
        for ty0, ty1 in bands:
            offsets, ids = bin_splats(bbox, visible, TILE, n_tx, ty0, ty1)
            if len(bands) == 1:
                binned[ty0] = offsets, ids  # one band: bin once for both passes
            front_band(splats, bbox, offsets, ids, n_tx, ty0, w, h, front)
        apply_visibility(splats, visible, front, w, h, coc_k, inv_focus, rho0, rho1)
        front_ms = _ms(t)
    for ty0, ty1 in bands:
        t = time.perf_counter()
        offsets, ids = binned.pop(ty0, None) or bin_splats(bbox, visible, TILE, n_tx, ty0, ty1)
        bin_ms += _ms(t)
        t = time.perf_counter()
        tile_stats = np.zeros((len(offsets) - 1, 2), np.int64)
        rasterize_band(splats, bbox, offsets, ids, n_tx, ty0, w, h, float(settings.cutoff),
                       background, image, depth, weight, tile_stats, coc_k, inv_focus, rho0,
                       rho1, blades, table, u_c)
        raster_ms += _ms(t)
        frags += int(tile_stats[:, 0].sum())
        overflows += int(tile_stats[:, 1].sum())
        pairs += len(ids)
    stats = {"fragments": frags, "abuffer_overflows": overflows, "tile_pairs": pairs,
             "bands": len(bands), "bin_ms": bin_ms, "raster_ms": raster_ms,
             "front_ms": front_ms}
    return image, depth, weight, stats


# -- helpers -----------------------------------------------------------------------------

_WARM = False


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel, so that timings exclude JIT."""
    global _WARM
    if _WARM:
        return
    _WARM = True
    # one small frame compiles every kernel: their argument types do not change between
    # pinhole and DOF frames, or disk and elliptical surfels
    s = Surfels(positions=[[0, 0, 0], [0.1, 0, 0]], normals=[[0, 0, 1], [0, 0, 1]],
                radius=[0.1, 0.1], colors=[[1, 1, 1], [1, 1, 1]])
    cam = Camera(eye=(0, 0, 1), target=(0, 0, 0), width=8, height=8)
    render(s, cam, ThinLens(focus_distance=0.5, aperture=0.1))


def focus_distance_at(surfels: Surfels, camera: Camera, x: float, y: float,
                      settings: RenderSettings | None = None) -> float:
    """Depth of the surface seen at pixel position (x, y) in a pinhole render: for autofocus."""
    settings = settings or RenderSettings()
    if not (0 <= x < camera.width and 0 <= y < camera.height):
        raise DofsplatError(f"focus pixel ({x:g}, {y:g}) lies outside the {camera.width}x{camera.height} image")
    pinhole = render(surfels, camera, None, settings)
    d = float(pinhole.depth[int(y), int(x)])
    if not math.isfinite(d):
        raise DofsplatError(f"no surface is seen at pixel ({x:g}, {y:g}) to focus on")
    return d


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
