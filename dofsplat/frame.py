"""What a frame is, below every backend: its settings, its result, and the per-frame
parameters that the CPU (``backends.cpu``) and GPU (``backends.cuda``) stages both derive
from the settings, the camera and the lens (the CoC coefficients, the aperture's tables, the
soft merge's parameters, the LOD tree and its palette). ``dofsplat.render`` dispatches a
frame to a backend; nothing here imports one.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

import numpy as np

from .camera import Camera, EyeLens, ThinLens
from .errors import DofsplatError
from .machine import available_memory
from .shading import HEADLIGHT, Light
from .splat.subaperture import (MAX_LENS_SAMPLES, ResidualLens, aperture_second_moment,
                                subaperture_pattern)
from .surfels import Surfels

DEVICES = ("cpu", "cuda", "auto")  # RenderSettings.device (backends.resolve_device)
RECONSTRUCTIONS = ("soft", "paper")
GAUSSIAN_BLURS = ("ours", "viewers")  # RenderSettings.gaussian_blur
LENS_PARTS = ("everywhere", "needed")  # RenderSettings.lens_parts
MAX_LOD_MIN_NODE = 64  # RenderSettings.lod_min_node: larger would leave LOD little to do


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
    max_splat_rows: int | None = None  # CPU LOD frames: a cut of more splats is drawn band by band, the same image, slower (splat_rows_budget); None: a quarter of the memory available
    lod: bool = True  # splat an LOD cut (Sections 5.3, 6.2): speed independent of the aperture
    lod_pixel_threshold: float = 1.0  # LOD: a node whose disk projects under this radius (px) is drawn whole
    lod_blur_fraction: float = 0.35  # LOD: draw a node when its filter is at most this x the DOF blur (variance); the paper's rule is 1 (docs/maths.md, "The stop's margin")
    lod_color_tolerance: float = 0.02  # LOD: a node with more texture at its own scale than this (RMS, linear RGB: Hierarchy.color_detail) is cut finer, down to 0.3 x the blur fraction; inf: off (docs/maths.md, "A finer cut where the texture needs it")
    lod_backface_drop: bool = True  # LOD with cull_backfaces: a node whose mean normal faces away and that the blur's stop would draw is dropped whole, where the walk otherwise descends to its front-facing minority (issue 50: on a scan with mixed normals most of a blurred cut was single back-facing surfels; docs/maths.md, "A back-facing node under the blur")
    lod_min_node: int = 4  # LOD: the blur's stop draws a node of at least this many surfels; a smaller one is drawn as its surfels (4, the default: not the nodes of 2-3 surfels, which carry most of LOD's loss where surfaces cross; docs/maths.md, "The smallest nodes"); 2: any node, as the paper
    show_lod: bool = False  # colour each splat by its LOD level, drawn without the DOF blur (Figure 5)
    device: str = "cpu"  # "cpu", "cuda" (an NVIDIA GPU: dofsplat[cuda]) or "auto" (the GPU if one works)
    taper: bool = False  # LOD nodes' kernels fall to 0 at the cutoff (exp(-q) - e^-c): no hard-edged discs
    reconstruction: str = "soft"  # "soft": merge by parallax, without seams (ours); "paper": z-ranges only (Section 6.4)
    lens_samples: int = 1  # K: the aperture drawn as K parts, each a frame from its own lens point (splat/subaperture.py); 1 = the paper's one pass
    lens_parts: str = "everywhere"  # with K > 1: "everywhere", or "needed": one pass, and the parts only on the tiles where a pixel held two surfaces or more (and the tiles beside them), blended over a tile (backends/cpu.py, draw_parts_where_needed; the CPU backend)
    gaussian_blur: str = "ours"  # Gaussian scenes: "ours" (the aperture's variance added, opacity spread, the 1/255 cut on the sharp footprint's scale) or "viewers" (the baseline of PlayCanvas and Spark: CoC^2 added, the cut on the spread opacity); gauss/project.py
    gaussian_lens_samples: int = 4  # Gaussian scenes: the lens drawn in this many parts (as lens_samples, which wins when larger): 1.1-7.3 dB closer to the lens reference than one pass at 0.9-1.5 x its cost (bench/RESULTS.md); 1 = one pass
    gaussian_lod: bool = True  # Gaussian scenes: draw coarser Gaussians where the lens blurs (gauss/lod.py; the stop is lod_blur_fraction; lod=False turns it off too): at 35 px 3.8-8.7x faster, 1.9-3.8 dB closer to the lens reference on the donut and playbot, 2.5 dB further on the guitar (bench/RESULTS.md)
    gaussian_antialiased: bool = False  # Gaussian scenes: gsplat's "antialiased" mode, the opacity scaled by sqrt(det before / det after) the 0.3 px^2 low-pass (for scenes trained so; gauss/project.py)
    coarse_blur_px: float = 8.0  # CPU: a splat blurred by an aperture of at least this radius (px) is drawn at every second pixel and interpolated (raster/abuffer.py, rasterize_band); 0: every pixel
    sharp_visibility: bool = False  # pinhole frames too remove the splats hidden behind an opaque front (their z-ranges no longer merge with grazing ones); 1.1-1.5 x a pinhole frame's time (bench/profile.py --sharp-visibility); the reference renderer turns it on (docs/maths.md, "Hidden from the whole lens")

    def __post_init__(self):
        for name in ("cutoff", "z_thickness", "lod_pixel_threshold", "lod_blur_fraction",
                     "lod_color_tolerance", "max_tile_pairs", "coarse_blur_px"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise DofsplatError(f"{name} must be a number, got {value!r}")
        if not isinstance(self.lights, (tuple, list)) or \
                not all(isinstance(light, Light) for light in self.lights):
            raise DofsplatError(f"lights must be a tuple of Light, got {self.lights!r}")
        object.__setattr__(self, "lights", tuple(self.lights))
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
        if self.max_splat_rows is not None and (
                isinstance(self.max_splat_rows, bool)
                or not isinstance(self.max_splat_rows, (int, np.integer)) or self.max_splat_rows < 1):
            raise DofsplatError(f"max_splat_rows must be a positive integer or None, got "
                                f"{self.max_splat_rows!r}")
        if not (math.isfinite(self.lod_pixel_threshold) and self.lod_pixel_threshold >= 0):
            raise DofsplatError(f"lod_pixel_threshold must be >= 0, got {self.lod_pixel_threshold}")
        if not (math.isfinite(self.lod_blur_fraction) and 0 < self.lod_blur_fraction <= 1):
            raise DofsplatError(f"lod_blur_fraction must be in (0, 1], got {self.lod_blur_fraction}")
        if not (self.lod_color_tolerance >= 0):  # inf allowed (off), nan refused
            raise DofsplatError(f"lod_color_tolerance must be >= 0 (inf: off), got "
                                f"{self.lod_color_tolerance}")
        if isinstance(self.lod_min_node, bool) or not isinstance(self.lod_min_node, (int, np.integer)) \
                or not 2 <= self.lod_min_node <= MAX_LOD_MIN_NODE:
            raise DofsplatError(f"lod_min_node must be an integer in 2..{MAX_LOD_MIN_NODE}, "
                                f"got {self.lod_min_node!r}")
        if self.reconstruction not in RECONSTRUCTIONS:
            raise DofsplatError(f"reconstruction must be one of {', '.join(RECONSTRUCTIONS)}, "
                                f"got {self.reconstruction!r}")
        for name in ("lens_samples", "gaussian_lens_samples"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
                    or not 1 <= value <= MAX_LENS_SAMPLES:
                raise DofsplatError(f"{name} must be an integer in 1..{MAX_LENS_SAMPLES}, "
                                    f"got {value!r}")
        if self.lens_parts not in LENS_PARTS:
            raise DofsplatError(f"lens_parts must be one of {', '.join(LENS_PARTS)}, "
                                f"got {self.lens_parts!r}")
        if not (math.isfinite(self.coarse_blur_px) and self.coarse_blur_px >= 0):
            raise DofsplatError(f"coarse_blur_px must be >= 0 (0: off), got {self.coarse_blur_px}")
        if self.show_lod and not self.lod:
            raise DofsplatError("show_lod needs lod=True")
        if self.gaussian_blur not in GAUSSIAN_BLURS:
            raise DofsplatError(f"gaussian_blur must be one of {', '.join(GAUSSIAN_BLURS)}, "
                                f"got {self.gaussian_blur!r}")
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


def frame_arguments(caller: str, surfels, camera, lens, settings, hierarchy=None) -> RenderSettings:
    """``settings``, or ``RenderSettings()`` for None, once what a frame is drawn from has
    been checked: arguments swapped or a lens left out (``render(surfels, camera,
    settings)``) are a DofsplatError naming the argument, not an AttributeError deep in a
    backend. ``caller`` names the function, e.g. "render()"."""
    from .gaussians import Gaussians

    if not isinstance(surfels, (Surfels, Gaussians)):
        raise DofsplatError(f"{caller} needs a model: Surfels or Gaussians, got "
                            f"{type(surfels).__name__}")
    expected = (("camera", camera, Camera, "a Camera"),
                # (a ResidualLens too: a part of the lens, frame.lens_parts, drawn on its own)
                ("lens", lens, (ThinLens, EyeLens, ResidualLens, type(None)),
                 "a ThinLens, an EyeLens or None"),
                ("settings", settings, (RenderSettings, type(None)), "a RenderSettings or None"))
    for name, value, kind, text in expected:
        if not isinstance(value, kind):
            raise DofsplatError(f"{caller}: {name} must be {text}, got {type(value).__name__}")
    if hierarchy is not None:
        from .lod import Hierarchy

        if not isinstance(hierarchy, Hierarchy):
            raise DofsplatError(f"{caller}: hierarchy must be a dofsplat.lod.Hierarchy or None, "
                                f"got {type(hierarchy).__name__}")
    return settings if settings is not None else RenderSettings()


# -- per-frame parameters, shared by the backends ----------------------------------------


def lod_tree(surfels: Surfels, hierarchy=None):
    """The model's LOD ``Hierarchy``: ``hierarchy`` if given, else built or kept
    (``lod.hierarchy_for``). A given tree must carry the model's fingerprint (the hash of
    its surfel arrays, ``lod.fingerprint``), else DofsplatError: another model's tree, even
    one of as many surfels, draws that model's nodes. The model's hash is kept on it
    between frames while its arrays are the same objects."""
    from .lod import fingerprint, hierarchy_for

    if hierarchy is None:
        return hierarchy_for(surfels)
    if hierarchy.n_surfels != len(surfels):
        raise DofsplatError(f"the LOD hierarchy was built for {hierarchy.n_surfels} surfels, "
                            f"the model has {len(surfels)}")
    if hierarchy.fingerprint != fingerprint(surfels, cached=True):
        raise DofsplatError(f"the LOD hierarchy was built for another model of as many "
                            f"surfels ({len(surfels)}; its fingerprint differs): build it for "
                            "this one (dofsplat.lod.build_hierarchy) or pass none")
    return hierarchy


def lod_level_colors(level: np.ndarray) -> np.ndarray:
    """(S, 3) float32 linear colours for LOD levels (0 = a surfel), for ``show_lod``."""
    return LOD_PALETTE[np.minimum(level, len(LOD_PALETTE) - 1)]


# one colour per LOD level, leaves first (sRGB designed, stored linear); the last repeats
LOD_PALETTE = (np.array([
    [0.85, 0.85, 0.85], [0.27, 0.46, 0.85], [0.16, 0.70, 0.86], [0.20, 0.75, 0.50],
    [0.55, 0.82, 0.25], [0.95, 0.85, 0.20], [0.98, 0.60, 0.15], [0.92, 0.30, 0.20],
    [0.80, 0.20, 0.55], [0.55, 0.25, 0.70], [0.35, 0.20, 0.45], [0.15, 0.15, 0.15],
], np.float32) ** 2.2).astype(np.float32)


def coc_coefficients(camera: Camera, lens, settings: RenderSettings) -> tuple[float, float]:
    """(K, 1/P) with C_r(U) = K |1/U - 1/P|; (0, 0) for a pinhole."""
    if lens is None or not settings.dof:
        return 0.0, 0.0
    return lens.coc_coefficients(camera)


@dataclass(frozen=True)
class LensParts:
    """The lens cut into parts for one frame (``splat/subaperture.py``)."""

    offsets: np.ndarray  # (K, 2) the parts' centroids, in aperture radii (x right, y up)
    cameras: tuple  # K ``Camera``s: the frame seen from each centroid (camera.lens_camera)
    rho: float  # the residual aperture's scale
    residual: object  # a ``ResidualLens``: the blur each part draws


def lens_parts(camera: Camera, lens, settings: RenderSettings) -> LensParts | None:
    """The lens's parts, or None when the frame is one pass: a pinhole, ``dof`` off,
    ``lens_samples`` 1 or ``show_lod``."""
    from .camera import effective_diameter, lens_camera

    if lens is None or not settings.dof or settings.show_lod or settings.lens_samples == 1:
        return None
    diameter = effective_diameter(camera, lens)
    if diameter <= 0.0:
        return None
    m2 = aperture_second_moment(getattr(lens, "bokeh", "gaussian"), getattr(lens, "blades", 0))
    offsets, rho = subaperture_pattern(settings.lens_samples, m2)
    cameras = tuple(lens_camera(camera, 0.5 * diameter * u, float(lens.focus_distance))
                    for u in offsets)
    return LensParts(offsets, cameras, rho, ResidualLens(lens, rho))


def backface_rule(settings: RenderSettings) -> int:
    """The LOD walk's back-face rule (``lod.select``'s ``cull_backfaces``): 0 two-sided, 1
    cull, 2 cull and drop a blurred back-facing node (``lod_backface_drop``)."""
    from .lod.select import BACK_DESCEND, BACK_DROP_BLURRED

    if not settings.cull_backfaces:
        return 0
    return BACK_DROP_BLURRED if settings.lod_backface_drop else BACK_DESCEND


def lod_kappa(settings: RenderSettings, parts: LensParts | None = None) -> float:
    """The LOD cut's DOF stop: a node is drawn when its filter is at most this x the DOF
    blur's variance (``lod_blur_fraction``); with the lens in parts the blur is the
    residual's, rho^2 x the whole lens's variance."""
    return settings.lod_blur_fraction * (1.0 if parts is None else parts.rho ** 2)


def aperture_variance(lens) -> float:
    """The variance per axis of the aperture's image at radius 1, the kernel's disc or
    polygon (``subaperture.aperture_second_moment`` / 2): 1/4 for the disc; what an LOD
    node's colour slope counts for it (``ewa.color_slope``)."""
    if lens is None or getattr(lens, "bokeh", "gaussian") != "disc":
        return 0.25  # no aperture in the kernel (its radius is 0): any value
    return 0.5 * aperture_second_moment("disc", getattr(lens, "blades", 0))


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


SPLAT_ROW_BYTES = 124  # a CPU splat row: N_FIELDS float32 (splat/project.py)
MIN_SPLAT_ROWS = 1 << 19  # the automatic budget never bands below this (65 MB of rows)


def splat_rows_budget(settings: RenderSettings) -> int:
    """How many splat rows a CPU frame may hold at once (``backends.cpu.draw_cut``):
    ``settings.max_splat_rows``, or by default as many as fit in a quarter of the memory
    available now (``machine.available_memory``), at least MIN_SPLAT_ROWS. A CPU frame whose LOD cut has more splats is drawn band by
    band: the same image, bit for bit, slower (docs/maths.md, "Memory and determinism").
    Frames without LOD or with the lens in parts, and the GPU's, do not use it."""
    if settings.max_splat_rows is not None:
        return int(settings.max_splat_rows)
    return max(MIN_SPLAT_ROWS, available_memory() // (4 * SPLAT_ROW_BYTES))


def front_pass(merge, settings: RenderSettings) -> bool:
    """Whether the A-buffer's front pass runs (``backends.cpu.rasterize``): with the soft
    merge of a blurred frame (K > 0), and in a sharp frame with ``sharp_visibility``."""
    return merge[0] > 0.0 or (settings.sharp_visibility and settings.reconstruction == "soft")


def merge_parameters(camera: Camera, lens, settings: RenderSettings) -> tuple[float, float, float, float]:
    """(K, 1/P, rho0, rho1) of the soft merge (``abuffer.merge_fraction``); K <= 0 turns it
    off.

    The paper's reconstruction, and a pinhole, composite separate surfaces with "over" only.
    The paper's is K = -1, which also keeps its coverage min(1, w) (``abuffer.sharpness``:
    a pinhole's sharp surfaces cover their pixel from a weight of COVER_FULL).
    """
    from .raster.abuffer import MERGE_RHO0, MERGE_RHO1

    if settings.reconstruction == "paper":
        return -1.0, 0.0, MERGE_RHO0, MERGE_RHO1
    coc_k, inv_focus = coc_coefficients(camera, lens, settings)
    return coc_k, inv_focus, MERGE_RHO0, MERGE_RHO1
