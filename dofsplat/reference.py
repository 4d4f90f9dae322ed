"""The multisample (accumulation-buffer) reference renderer (paper Section 7).

The ground truth that the paper judges its images against: many pinhole images, each seen
from a different point of the lens, averaged (Haeberli & Akeley's accumulation buffer, the
paper's reference [11]). Each lens sample moves the pinhole within the lens disc and shears
the frustum so that the focal plane at depth P stays put on the screen:

    eye' = eye + o_x s + o_y u                      (o: the sample, in the lens plane)
    (L', R', B', T') = (L - o_x N/P, R - o_x N/P, B - o_y N/P, T - o_y N/P)

A point at depth U then moves on the screen by o N/P - o N/U (times W/(R-L) pixels), so the
samples on the rim |o| = A/2 move it by exactly C_r(U) = (A/2) |1/U - 1/P| N W/(R-L), the
circle of confusion of eqs. 1-3 (PAPER_NOTES section 1; ``tests/test_reference.py`` checks it
to 1e-6). Every sample is rendered by :func:`dofsplat.render.render` as a pinhole (no DOF
blur, no LOD), so the reference shares the EWA splatting and the A-buffer with our method
and differs only in how the lens is integrated.

Choices, each one so that the reference measures the lens integration and nothing else:

* **Samples**: a Vogel (Fibonacci) spiral over the disc, r_i = (A/2) sqrt((i + 1/2)/N),
  theta_i = i x the golden angle: deterministic, low-discrepancy for every N, each sample
  standing for an equal area 1/N of the disc.
* **Averaging**: the renderer's images are already composited over the background (RGB is
  premultiplied colour plus the background's share), so the plain mean of the RGBA images
  is the mean of the premultiplied colours: what an accumulation buffer adds up.
* **Shading**: per surfel, once, as seen from the lens centre (as our DOF render shades),
  then every sample renders those colours unlit. Phong highlights would otherwise move
  with the pinhole (the headlight with it) and the difference would measure view-dependent
  shading, not depth of field. ``shade_per_sample=True`` shades every sample from its own
  eye instead.
* **Lens diameter**: the one that gives the lens's own CoC in this camera's pixels,
  A = 2K / (N W/(R-L)) with (K, 1/P) = ``lens.coc_coefficients(camera)``: for a
  ``ThinLens`` exactly its diameter, for an ``EyeLens`` (eq. 4) the pupil scaled by
  d_s R / (N W/(R-L)).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time

import numpy as np

from .camera import Camera, EyeLens, ThinLens, effective_diameter, lens_camera
from .errors import DofsplatError
from .backends.cpu import shade_surfels, warm_up
from .frame import RenderResult, RenderSettings, frame_arguments
from .render import render
from .surfels import Surfels

DEFAULT_SAMPLES = 200  # the paper's reference: 200 pinhole images (Section 7)
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))  # radians, the Vogel spiral's turn


def lens_samples(n: int, diameter: float) -> np.ndarray:
    """(n, 2) float64 lens-plane offsets (x right, y up; world units) over a disc of ``diameter``.

    A Vogel spiral: sample i at radius (A/2) sqrt((i + 1/2)/n), angle i x the golden angle.
    """
    i = np.arange(n, dtype=np.float64)
    r = 0.5 * diameter * np.sqrt((i + 0.5) / n)
    theta = i * GOLDEN_ANGLE
    return np.stack([r * np.cos(theta), r * np.sin(theta)], axis=1)


def polygon_samples(n: int, diameter: float, blades: int, rotation_deg: float) -> np.ndarray:
    """(n, 2) lens-plane offsets spread uniformly over a regular polygon (x right, y up).

    The polygon has ``blades`` edges and circumradius diameter/2, its first vertex at
    ``rotation_deg`` counterclockwise from x. Sample i takes a sector by the golden-ratio
    sequence (equal areas: each of the N triangles from the centre) and a point in it by
    (i + 1/2)/n, so the density is uniform over the polygon and every n is deterministic.
    """
    i = np.arange(n, dtype=np.float64)
    u = (i + 0.5) / n  # radial coordinate (area-uniform below)
    v = (i * (math.sqrt(5.0) - 1.0) / 2.0) % 1.0  # golden-ratio sequence over the angle
    sector = np.floor(v * blades)
    t = v * blades - sector  # position across the sector's outer edge, 0..1
    a0 = math.radians(rotation_deg) + sector * 2 * math.pi / blades
    a1 = a0 + 2 * math.pi / blades
    r = 0.5 * diameter * np.sqrt(u)  # area-uniform in the triangle: scale by sqrt(u)
    x = r * ((1 - t) * np.cos(a0) + t * np.cos(a1))
    y = r * ((1 - t) * np.sin(a0) + t * np.sin(a1))
    return np.stack([x, y], axis=1)


def lens_cameras(camera: Camera, lens: ThinLens | EyeLens | None,
                 samples: int = DEFAULT_SAMPLES, offsets=None) -> list[Camera]:
    """The pinhole cameras of the reference: one per lens sample (one camera for a pinhole).

    offsets: (n, 2) lens-plane offsets (world units) to use instead of the Vogel spiral over
    the lens disc, e.g. another aperture shape; ``samples`` is then ignored.
    """
    samples = _check_samples(samples)
    if lens is None or effective_diameter(camera, lens) == 0.0:
        return [camera]
    if offsets is None and getattr(lens, "blades", 0):
        # the polygonal aperture, uniformly (y up in the lens plane, as on the screen)
        offsets = polygon_samples(samples, effective_diameter(camera, lens), lens.blades,
                                  lens.blade_rotation)
    if offsets is None:
        offsets = lens_samples(samples, effective_diameter(camera, lens))
    offsets = np.asarray(offsets, np.float64)
    if offsets.ndim != 2 or offsets.shape[1] != 2 or len(offsets) == 0 \
            or not np.all(np.isfinite(offsets)):
        raise DofsplatError(f"lens offsets must be a non-empty (n, 2) array of finite "
                            f"numbers, got shape {offsets.shape}")
    return [lens_camera(camera, o, float(lens.focus_distance)) for o in offsets]


def render_reference(surfels: Surfels, camera: Camera, lens: ThinLens | EyeLens | None,
                     settings: RenderSettings | None = None, samples: int = DEFAULT_SAMPLES,
                     progress: bool = True, *, shade_per_sample: bool = False,
                     offsets=None) -> RenderResult:
    """The multisample depth-of-field reference: ``samples`` pinhole renders averaged.

    surfels, camera, lens, settings: as for :func:`dofsplat.render.render` (``settings.dof``
    and ``settings.lod`` are ignored: every sample is a full-resolution pinhole render).
    samples: number of lens samples N (the paper uses 200); a pinhole lens (None or A = 0)
    needs one render whatever N.
    progress: show a progress bar on stderr (only when stderr is a terminal).
    offsets: (n, 2) lens-plane points (world units, along the camera's right and up axes)
            to average over instead of the Vogel spiral over the lens disc: another
            aperture shape or weighting (``bench/paper.py`` uses a Gaussian lens to separate
            the shape of our blur kernel from the rest of the error); samples is then ignored.

    Returns a ``RenderResult``:
    image:  (H, W, 4) float32, the mean of the samples' linear RGBA images
    depth:  (H, W) float32, the nearest depth any sample saw, inf where none saw anything
    weight: (H, W) float32, the mean of the samples' splat weights
    stats:  points_in, samples, aperture (the A used, world units), splats_rendered (mean
            per sample), fragments (sum over samples), width, height, shade_ms, render_ms,
            total_ms
    """
    settings = frame_arguments("render_reference()", surfels, camera, lens, settings)
    warm_up()  # timings exclude JIT compilation, as render()'s do
    t_start = time.perf_counter()
    cameras = lens_cameras(camera, lens, samples, offsets)
    pinhole = _pinhole_settings(settings, shaded=not shade_per_sample)

    t = time.perf_counter()
    if not shade_per_sample and isinstance(surfels, Surfels):
        # shade once from the lens centre, as render() does for our DOF image (a Gaussian
        # scene is unlit: each sample evaluates its spherical harmonics from its own eye,
        # as a camera at that point of the lens would see them)
        surfels = dataclasses.replace(surfels, colors=shade_surfels(surfels, camera, settings))
    shade_ms = _ms(t)

    h, w = camera.height, camera.width
    image = np.zeros((h, w, 4), np.float64)
    weight = np.zeros((h, w), np.float64)
    depth = np.full((h, w), np.inf, np.float32)
    splats = frags = 0
    render_ms = 0.0
    for cam in _progress(cameras, progress):
        result = render(surfels, cam, None, pinhole)
        image += result.image
        weight += result.weight
        np.minimum(depth, result.depth, out=depth)
        splats += result.stats["splats_rendered"]
        frags += result.stats["fragments"]
        render_ms += result.stats["total_ms"]
    n = len(cameras)
    stats = {
        "points_in": int(len(surfels)),
        "samples": n,
        "aperture": effective_diameter(camera, lens),
        "splats_rendered": int(round(splats / n)),
        "fragments": int(frags),
        "width": w,
        "height": h,
        "shade_ms": shade_ms,
        "render_ms": render_ms,
        "total_ms": _ms(t_start),
    }
    return RenderResult(image=(image / n).astype(np.float32), depth=depth,
                        weight=(weight / n).astype(np.float32), stats=stats)


# -- helpers -----------------------------------------------------------------------------


def _pinhole_settings(settings: RenderSettings, shaded: bool) -> RenderSettings:
    """``settings`` for one lens sample: no DOF blur, no LOD, unlit if pre-shaded, and the
    front pass that keeps a grazing surface's z-range from merging what it hides
    (``sharp_visibility``: without it two planes crossing at a shallow angle showed the
    hidden one through the other as speckle in every sample).

    Only fields that RenderSettings has are set, so this holds as the settings grow."""
    changes = {"dof": False, "lod": False, "show_lod": False, "sharp_visibility": True}
    if shaded:
        changes["shading"] = "none"
    names = {f.name for f in dataclasses.fields(RenderSettings)}
    return dataclasses.replace(settings, **{k: v for k, v in changes.items() if k in names})


def _check_samples(samples) -> int:
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise DofsplatError(f"the number of lens samples must be a positive integer, "
                            f"got {samples!r}")
    return int(samples)


def _progress(items, enabled: bool):
    from tqdm import tqdm

    show = enabled and len(items) > 1 and sys.stderr.isatty()
    return tqdm(items, desc="reference", unit="sample", file=sys.stderr, disable=not show,
                leave=False)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0
