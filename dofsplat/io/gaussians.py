"""3D Gaussian Splatting scenes (Kerbl et al. 2023) as elliptical surfels.

A 3DGS PLY (the ``point_cloud.ply`` a 3DGS trainer writes; :func:`dofsplat.io.ply.read_ply`
recognises it by f_dc_0, scale_0 and rot_0) has one vertex per Gaussian with

* ``x y z``: the centre;
* ``f_dc_0..2``: the degree-0 spherical-harmonic coefficients of the colour;
* ``opacity``: a logit (the opacity is its sigmoid);
* ``scale_0..2``: the logarithms of the standard deviations along the Gaussian's axes;
* ``rot_0..3``: a quaternion (w, x, y, z), not normalised, rotating the axes into the world;
* optionally ``f_rest_*`` (higher SH degrees) and ``nx ny nz`` (zeros in 3DGS output).

Each Gaussian becomes one elliptical surfel: its two largest axes span the disk, the
smallest is the normal. A Gaussian with standard deviation s along an axis becomes a
radius of 2s along it (the surfel convention: disk radius r is a Gaussian sigma of r/2),
``tangent`` along the largest axis. The colour is the SH degree-0 term,
0.5 + C0 f_dc (C0 = 1 / (2 sqrt(pi))), clamped to [0, 1]; 3DGS fits it to photographs
and blends in their space, so it is taken as sRGB and decoded to linear. Opacity is the
sigmoid of the logit; Gaussians under 1/255 opacity are left out (they are invisible).

What is lost: the third axis (a surfel is flat: thick, blobby Gaussians turn into disks),
the higher SH degrees, so all view-dependent colour (every surfel shows its diffuse
average from every side), and 3DGS's sorted front-to-back alpha blending of every
Gaussian: the A-buffer merges splats whose depth ranges overlap into one surface (weighted
average of colour and opacity) and blends only distinct surfaces. The splats are also
culled when they face away from the camera (``--no-cull`` keeps both sides).
"""

from __future__ import annotations

import numpy as np

from ..errors import DofsplatError
from ..surfels import Material, Surfels
from ..colors import srgb_to_linear

SH_C0 = 0.28209479177387814  # the degree-0 real spherical harmonic, 1 / (2 sqrt(pi))
REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
            "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
MIN_OPACITY = 1.0 / 255.0  # below this a Gaussian cannot change an 8-bit pixel
MIN_AXIS_RATIO = 1e-3  # the shorter disk axis is kept at least this fraction of the longer
_MAX_LOG_SCALE = 60.0  # exp(60) ~ 1e26: beyond this a scale is damage, not a Gaussian


def gaussians_to_surfels(columns: dict[str, np.ndarray], *, material: Material | None = None,
                         source: str = "3DGS") -> Surfels:
    """Elliptical surfels from the vertex columns of a 3DGS PLY (see the module docstring).

    columns: property name -> (N,) array. Rows with NaN or inf, a zero quaternion or an
    absurd scale are dropped with one warning; DofsplatError if none is left or a required
    property is missing.
    """
    missing = [n for n in REQUIRED if n not in columns]
    if missing:
        raise DofsplatError(f"{source}: a 3D Gaussian Splatting PLY needs {' '.join(REQUIRED)}; "
                            f"this one lacks {' '.join(missing)}")
    col = {n: np.asarray(columns[n], dtype=np.float64) for n in REQUIRED}
    n = len(col["x"])
    if n == 0:
        raise DofsplatError(f"{source}: no Gaussians in the file")
    positions = np.stack([col["x"], col["y"], col["z"]], axis=1)

    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        rotation = quaternion_matrices(np.stack([col[f"rot_{i}"] for i in range(4)], axis=1))
        log_scale = np.stack([col[f"scale_{i}"] for i in range(3)], axis=1)
        sane = np.all(np.abs(log_scale) < _MAX_LOG_SCALE, axis=1)
        sigma = np.exp(np.where(sane[:, None], log_scale, 0.0))
        sigma[~sane] = np.nan  # dropped by from_arrays
        opacity = 1.0 / (1.0 + np.exp(-col["opacity"]))
        rgb = 0.5 + SH_C0 * np.stack([col[f"f_dc_{i}"] for i in range(3)], axis=1)

    # axes sorted by their standard deviation: smallest (the normal), middle, largest
    order = np.argsort(np.nan_to_num(sigma, nan=0.0), axis=1)
    rows = np.arange(n)
    axis = lambda i: rotation[rows, :, order[:, i]]  # noqa: E731 - the rotation's columns
    s_mid, s_max = sigma[rows, order[:, 1]], sigma[rows, order[:, 2]]
    radius = 2.0 * s_max
    radius_v = np.maximum(2.0 * s_mid, MIN_AXIS_RATIO * radius)
    colors = srgb_to_linear(np.clip(np.nan_to_num(rgb, nan=-1.0), 0.0, 1.0))
    colors[~np.all(np.isfinite(rgb), axis=1)] = np.nan  # dropped by from_arrays

    visible = ~(opacity < MIN_OPACITY)  # NaN opacities stay, to be dropped and counted
    if not visible.any():
        raise DofsplatError(f"{source}: every Gaussian has opacity below {MIN_OPACITY:.4f} "
                            "(nothing to render)")
    pick = lambda a: a[visible]  # noqa: E731
    return Surfels.from_arrays(pick(positions), pick(axis(0)), pick(radius), pick(colors),
                               pick(opacity), tangent=pick(axis(2)), radius_v=pick(radius_v),
                               material=material, source=source)


def quaternion_matrices(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices from (N, 4) quaternions (w, x, y, z), normalised here.

    A zero or non-finite quaternion gives a matrix of NaN (its row is then dropped).
    """
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = q / np.where(norm > 0, norm, np.nan)[:, None]
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1),
    ], axis=1)
