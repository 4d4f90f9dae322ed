"""Sub-aperture decomposition of the lens (beyond the paper; docs/maths.md, "the lens in parts").

The paper blurs every splat by the whole aperture and resolves visibility once per pixel in
the A-buffer, whose z-ranges then hold the depths of everything within a circle of
confusion: where surfaces touch or cross, it must merge or separate them wholesale. Here the
aperture is cut into K parts of equal area. Each part is drawn as its own frame: every
splat moves by its parallax to the part's centroid u_k (the lens point whose pinhole view
the part stands for) and is blurred only by the residual aperture, the lens's own shape
scaled by rho; the K frames are resolved separately and averaged. Visibility is then
decided K times, each time over a blur rho times smaller, and the sum of the K residual
kernels, moment-matched, is the aperture's kernel. K = 1 is the paper's single pass.

The parts (``subaperture_pattern``), in units of the aperture's radius, x right, y up:

* K = 2..6: K equal sectors of the unit disc, centroids at radius (2/3) sin(a)/a, a = pi/K;
* K >= 7: a centre disc of area 1/K and K - 1 equal sectors of the ring around it;

and the residual scale rho: the residual has the whole aperture's shape, so its second
moment is rho^2 m (m = E|u|^2 of the aperture: 1/2 for the unit disc, the polygon's own for
blades, 1/ln 4 for the paper's Gaussian of C_r^2 / (2 ln 4) per axis); the K centroids
have mean 0 and mean square s, so rho^2 = 1 - s/m keeps the sum's second moment the
aperture's (for a polygon or the Gaussian the centroids are scaled by sqrt(2m) first, so
that they spread like the aperture does).

Each part is drawn from its own camera, ``camera.lens_camera`` at the world offset u_k A/2
(A: the lens's effective diameter): the eye moves, the frustum shears so that the focal
plane keeps its pixels, and a point at depth U moves by K (1/P - 1/U) (u_x, -u_y) pixels,
(K, 1/P) the CoC coefficients. The parts share the frame's LOD cut (chosen from the lens
centre by the residual blur) and its shading (from the lens centre, as the reference
shades); the projection is made per part, since across a large lens the view itself
changes (footprints, silhouettes): a pure shift of the centre view's splats cost 3 dB on
the demo at a 40 px blur (docs/maths.md).
"""

from __future__ import annotations

import math

import numpy as np

MAX_LENS_SAMPLES = 64  # RenderSettings.lens_samples at most


def aperture_second_moment(bokeh: str, blades: int) -> float:
    """E|u|^2 over the aperture of radius 1 (its kernel at C_r = 1): 1/2 for the disc,
    (1 + 2 cos^2(pi/n)) / 6 for a regular n-gon of circumradius 1, and 2 / (2 ln 4) for the
    paper's Gaussian (its variance C_r^2 / (2 ln 4) per axis)."""
    if bokeh == "gaussian":
        return 1.0 / math.log(4.0)
    if blades:
        return (1.0 + 2.0 * math.cos(math.pi / blades) ** 2) / 6.0
    return 0.5


def subaperture_pattern(k: int, second_moment: float = 0.5) -> tuple[np.ndarray, float]:
    """(offsets, rho): the K parts' centroids, (K, 2) float64 in units of the aperture's
    radius (x right, y up, mean 0), and the residual scale rho (module notes). K = 1 is the
    whole lens: ((0, 0), 1)."""
    if not 1 <= k <= MAX_LENS_SAMPLES:
        raise ValueError(f"lens samples must be 1..{MAX_LENS_SAMPLES}, got {k}")
    if k == 1:
        return np.zeros((1, 2)), 1.0
    if k <= 6:  # K sectors of the disc
        a = math.pi / k
        rc = (2.0 / 3.0) * math.sin(a) / a
        angles = (np.arange(k) + 0.5) * 2.0 * a
        pts = rc * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    else:  # a centre disc of area 1/K and K - 1 sectors of the ring r0 < r < 1
        r0 = math.sqrt(1.0 / k)
        n = k - 1
        a = math.pi / n
        # the centroid of a ring sector: (2/3) sin(a)/a (1 - r0^3) / (1 - r0^2)
        rc = (2.0 / 3.0) * math.sin(a) / a * (1.0 - r0 ** 3) / (1.0 - r0 ** 2)
        angles = (np.arange(n) + 0.5) * 2.0 * a
        ring = rc * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        pts = np.concatenate([np.zeros((1, 2)), ring])
    pts = pts * math.sqrt(2.0 * second_moment)
    spread = float(np.mean(np.sum(pts * pts, axis=1)))
    rho = math.sqrt(max(1.0 - spread / second_moment, 0.0))
    return pts, rho


class ResidualLens:
    """A lens whose blur is ``lens``'s scaled by ``rho`` (a sub-aperture's residual): the
    same focus, bokeh and blades, CoC coefficients (rho K, 1/P). What the per-frame
    parameters (``frame.coc_coefficients``, ``aperture_shape``, ``merge_parameters``) read
    of a lens, and nothing else."""

    def __init__(self, lens, rho: float):
        self.lens = lens
        self.rho = float(rho)
        self.focus_distance = lens.focus_distance
        self.bokeh = getattr(lens, "bokeh", "gaussian")
        self.blades = getattr(lens, "blades", 0)
        self.blade_rotation = getattr(lens, "blade_rotation", 0.0)

    def coc_coefficients(self, camera) -> tuple[float, float]:
        k, inv_focus = self.lens.coc_coefficients(camera)
        return self.rho * k, inv_focus
