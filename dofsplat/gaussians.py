"""Gaussians: a 3D Gaussian Splatting scene as a structure of arrays, beside ``Surfels``.

A 3DGS scene (Kerbl et al. 2023) is a cloud of anisotropic 3-D Gaussians, each with a
centre mu, a covariance Sigma = R S S^T R^T (S = diag(scales), R the rotation of the
quaternion), an opacity o and a view-dependent colour in real spherical harmonics. Unlike a
surfel it has volume, no normal, no front or back side, and its colour is radiance already:
it is drawn unlit, sorted by depth and composited front to back (``dofsplat.gauss``).

The arrays hold what a trainer optimised, decoded from its storage (``dofsplat.io.gaussians``
reads the PLY and the compressed forms): standard deviations, not their logarithms; an
opacity, not its logit; a unit quaternion.

Colour convention (the trainers' own): colour(d) = max(0, 0.5 + sum_k Y_k(d) sh[k]) for the
unit direction d from the camera centre to mu, in the colour space of the photographs the
scene was fitted to (sRGB-encoded values), and blended in that space. ``sh[:, 0]`` is the
PLY's ``f_dc_*``; ``sh[:, 1:]`` its ``f_rest_*`` (stored there channel-major: all of red's
coefficients, then green's, then blue's).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np

from .errors import DofsplatError
from .surfels import _check_shape, _column, _floats, _rows

SH_COEFFICIENTS = {1: 0, 4: 1, 9: 2, 16: 3}  # coefficients per channel -> SH degree
MIN_OPACITY = 1.0 / 255.0  # below this a Gaussian changes no 8-bit pixel (the trainers' cut)


@dataclass
class Gaussians:
    """N 3-D Gaussians with spherical-harmonic colour.

    positions: (N, 3) float32, world units, the centres mu
    scales:    (N, 3) float32 > 0, world units, standard deviations along the own axes
    rotations: (N, 4) float32, unit quaternions (w, x, y, z) turning the own axes into the
               world's (normalised at construction)
    opacity:   (N,)   float32 in [0, 1], the peak opacity o
    sh:        (N, K, 3) float32, K = (degree + 1)^2 in 1, 4, 9, 16: real SH coefficients
               per channel, in 3DGS's basis order and sign convention
    """

    positions: np.ndarray
    scales: np.ndarray
    rotations: np.ndarray
    opacity: np.ndarray
    sh: np.ndarray

    # the up direction a default camera takes (``cli.framing``): trainers' scenes come from
    # COLMAP's OpenCV-style cameras, y down (a reader may set another, e.g. from cameras.json)
    up_hint = (0.0, -1.0, 0.0)
    # a trainer's first camera (eye, target, up, frustum, size), from cameras.json
    # (``io.cameras_json``): the CLI's default view, as a depth capture's sensor is
    capture = None

    def __post_init__(self):
        n = _rows(self.positions, 3, "positions")
        self.positions = _floats(self.positions, "positions")
        self.scales = _floats(self.scales, "scales")
        _check_shape(self.scales, (n, 3), "scales")
        self.rotations = _floats(self.rotations, "rotations")
        _check_shape(self.rotations, (n, 4), "rotations")
        self.opacity = _column(self.opacity, n, "opacity")
        self.sh = _floats(self.sh, "sh")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3 \
                or self.sh.shape[1] not in SH_COEFFICIENTS:
            raise DofsplatError(f"sh must have shape ({n}, K, 3) with K in 1, 4, 9, 16 "
                                f"(SH degree 0-3), got {self.sh.shape}")
        for name in ("positions", "scales", "rotations", "opacity", "sh"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise DofsplatError("Gaussian arrays contain NaN or inf; use "
                                    "Gaussians.from_arrays to drop such rows")
        if np.any(self.scales <= 0):
            raise DofsplatError(f"{int(np.count_nonzero(np.any(self.scales <= 0, axis=1)))} of "
                                f"{n} Gaussians have a scale <= 0")
        q = self.rotations.astype(np.float64)
        norm = np.linalg.norm(q, axis=1)
        if np.any(norm < 1e-12):
            raise DofsplatError(f"{int(np.count_nonzero(norm < 1e-12))} of {n} Gaussians have "
                                "a zero quaternion")
        off = np.abs(norm - 1.0) > 1e-6  # unit ones stay bit for bit (a file's round trip)
        self.rotations[off] = (q[off] / norm[off, None]).astype(np.float32)
        np.clip(self.opacity, 0.0, 1.0, out=self.opacity)

    def __len__(self) -> int:
        return self.positions.shape[0]

    @property
    def sh_degree(self) -> int:
        """The degree of the colour's spherical harmonics, 0 to 3."""
        return SH_COEFFICIENTS[self.sh.shape[1]]

    @classmethod
    def from_arrays(cls, positions, scales, rotations, opacity, sh, *,
                    source: str = "input") -> "Gaussians":
        """Gaussians from raw arrays, dropping (with one warning) the rows that hold NaN or
        inf, a scale <= 0 or a zero quaternion: a trainer's file has a few such rows after a
        diverged step, and they are damage, not scene."""
        n = _rows(positions, 3, "positions")
        arrays = {"positions": positions, "scales": scales, "rotations": rotations,
                  "opacity": opacity, "sh": sh}
        arrays = {k: _floats(v, k) for k, v in arrays.items()}
        if arrays["opacity"].ndim == 0:
            arrays["opacity"] = np.full(n, arrays["opacity"], np.float32)
        keep = np.ones(n, bool)
        for k, a in arrays.items():
            if a.ndim == 0 or a.shape[0] != n:
                raise DofsplatError(f"{k} has {a.shape[0] if a.ndim else 0} rows but positions "
                                    f"has {n}")
            keep &= np.all(np.isfinite(a.reshape(n, -1)), axis=1)
        if arrays["scales"].ndim == 2:
            keep &= np.all(arrays["scales"] > 0, axis=1)
        if arrays["rotations"].ndim == 2:
            keep &= np.linalg.norm(arrays["rotations"].astype(np.float64), axis=1) > 1e-12
        if not keep.any():
            raise DofsplatError(f"{source}: no valid Gaussians (all {n} rows had NaN, inf, a "
                                "zero scale or a zero quaternion)")
        dropped = n - int(keep.sum())
        if dropped:
            warnings.warn(f"{source}: dropped {dropped:,} of {n:,} Gaussians with NaN or inf "
                          "values, a scale <= 0 or a zero quaternion", stacklevel=2)
            arrays = {k: v[keep] for k, v in arrays.items()}
        return cls(**arrays)

    def subset(self, index) -> "Gaussians":
        """The Gaussians selected by a boolean mask or an index array."""
        return replace(self, positions=self.positions[index], scales=self.scales[index],
                       rotations=self.rotations[index], opacity=self.opacity[index],
                       sh=self.sh[index])

    def rotation_matrices(self) -> np.ndarray:
        """(N, 3, 3) float64: R, whose columns are the Gaussians' axes in world space."""
        return quaternion_matrices(self.rotations)

    def covariances(self) -> np.ndarray:
        """(N, 3, 3) float64: Sigma = R S S^T R^T, world units squared."""
        m = self.rotation_matrices() * self.scales.astype(np.float64)[:, None, :]
        return m @ np.swapaxes(m, 1, 2)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lo, hi) of the centres, world units."""
        return self.positions.min(axis=0), self.positions.max(axis=0)

    def view_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The box a default camera frames: the centres of the Gaussians that are seen
        (opacity >= 1/255), between their 1st and 99th percentiles along each axis, widened
        by 3 standard deviations where the box is smaller than a Gaussian. Captures hold a
        halo of large, faint Gaussians far from the subject (the sky, the room), which a
        plain min-max box would frame instead of the subject."""
        seen = self.opacity >= MIN_OPACITY
        p = self.positions[seen] if seen.any() else self.positions
        if len(p) >= 100:
            lo, hi = np.percentile(p, 1, axis=0), np.percentile(p, 99, axis=0)
        else:
            lo, hi = p.min(axis=0), p.max(axis=0)
        lo, hi = lo.astype(np.float32), hi.astype(np.float32)
        r = 3.0 * float(np.max(self.scales))
        if 0.5 * float(np.linalg.norm(hi.astype(np.float64) - lo)) < r:
            lo, hi = lo - r, hi + r
        return lo, hi


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
