"""What the projection kernel splats: the surfels themselves, or an LOD cut through them."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..surfels import Material, Surfels


class SplatSource(NamedTuple):
    """S splats as flat arrays, the kernels' input.

    positions: (S, 3) float32 world; normals: (S, 3) float32 unit
    colors:    (S, 3) float32 linear RGB (before shading); opacity: (S,) float32
    tangents:  (S, 3) float32 first tangent axis, a zero row meaning "derive it from the
               normal", or (0, 3) when every splat is circular
    ru, rv:    (S,) float32 disk radii of the leaf basis V^r = diag((r_u/2)^2, (r_v/2)^2)
    area:      (S,) float32 the area each splat stands for, world units^2
    lod_cov:   (S, 6) float32 world covariance of the LOD low-pass filter V^{q,l}
               (xx, xy, xz, yy, yz, zz; world units^2; zeros for a surfel), or (0, 6)
    color_grad: (S, 6) float32 an LOD node's colour gradient in its tangent frame
               (``lod/hierarchy.py``; zeros for a surfel), or (0, 6)
    level:     (S,) int8 LOD level (0 = a surfel), or None without LOD
    material:  the model's Phong material
    """

    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    opacity: np.ndarray
    tangents: np.ndarray
    ru: np.ndarray
    rv: np.ndarray
    area: np.ndarray
    lod_cov: np.ndarray
    color_grad: np.ndarray
    level: np.ndarray | None
    material: Material

    @property
    def size(self) -> int:
        """S, the number of splats (``len`` is the tuple's field count)."""
        return self.positions.shape[0]


def from_surfels(surfels: Surfels) -> SplatSource:
    """Every surfel, as it is (no LOD)."""
    ru = surfels.radius
    if surfels.is_elliptical:
        tangents, rv = surfels.tangent, surfels.radius_v
    else:
        tangents, rv = np.zeros((0, 3), np.float32), surfels.radius
    area = ru * rv  # the area a surfel stands for (surfels.py)
    if surfels.weight is not None:
        area = area * surfels.weight
    return SplatSource(positions=surfels.positions, normals=surfels.normals,
                       colors=surfels.colors, opacity=surfels.opacity, tangents=tangents,
                       ru=ru, rv=rv, area=area.astype(np.float32), lod_cov=np.zeros((0, 6), np.float32),
                       color_grad=np.zeros((0, 6), np.float32), level=None, material=surfels.material)
