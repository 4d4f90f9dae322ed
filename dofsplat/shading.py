"""Per-splat Phong shading (paper Section 6.5).

Shading happens per surfel, before splatting, so that specular highlights are blurred by
the depth of field like everything else. Lights are directional or point lights, given in
world space or attached to the camera; the default is a single headlight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .errors import DofsplatError
from .surfels import Material


@dataclass(frozen=True)
class Light:
    """A light source.

    kind: "directional" (``vector`` is the direction the light travels) or "point"
    (``vector`` is its position). in_camera_space: the vector is in camera coordinates
    (the light moves with the camera), else world coordinates.
    """

    kind: str = "directional"
    vector: tuple[float, float, float] = (0.0, 0.0, -1.0)
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)  # linear RGB intensity
    in_camera_space: bool = True

    def __post_init__(self):
        if self.kind not in ("directional", "point"):
            raise DofsplatError(f"light kind must be 'directional' or 'point', got {self.kind!r}")
        v = np.asarray(self.vector, float)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise DofsplatError("light vector must be three finite numbers")
        if self.kind == "directional" and np.linalg.norm(v) == 0:
            raise DofsplatError("a directional light needs a non-zero direction")


HEADLIGHT = Light()  # shines along the view direction, from the camera


def shade(positions, normals, colors, material: Material, camera: Camera,
          lights=(HEADLIGHT,), two_sided: bool = False) -> np.ndarray:
    """Phong-shaded linear RGB per surfel, (N, 3) float32.

    c = k_a c + sum_lights L (k_d max(n.l, 0) c + k_s max(r.v, 0)^s), r the reflection of l.
    With ``two_sided`` a normal facing away from the eye is flipped first (for unculled,
    unoriented data).
    """
    p = np.asarray(positions, np.float64)
    n = np.asarray(normals, np.float64)
    c = np.asarray(colors, np.float64)
    eye = np.asarray(camera.eye, np.float64)
    world_from_camera = np.linalg.inv(camera.camera_from_world())
    v = eye - p
    v /= np.maximum(np.linalg.norm(v, axis=1), 1e-30)[:, None]
    if two_sided:
        n = np.where((np.sum(n * v, axis=1) < 0)[:, None], -n, n)
    out = material.ambient * c
    for light in lights:
        vec = np.asarray(light.vector, np.float64)
        if light.kind == "directional":
            if light.in_camera_space:
                vec = world_from_camera[:3, :3] @ vec
            to_light = np.broadcast_to(-vec / np.linalg.norm(vec), p.shape)
        else:
            if light.in_camera_space:
                vec = world_from_camera[:3, :3] @ vec + world_from_camera[:3, 3]
            to_light = vec - p
            to_light = to_light / np.maximum(np.linalg.norm(to_light, axis=1), 1e-30)[:, None]
        ndotl = np.sum(n * to_light, axis=1)
        lit = ndotl > 0
        diffuse = material.diffuse * np.maximum(ndotl, 0.0)
        r = 2.0 * ndotl[:, None] * n - to_light
        spec = material.specular * np.where(
            lit, np.maximum(np.sum(r * v, axis=1), 0.0) ** material.shininess, 0.0)
        out = out + np.asarray(light.color)[None, :] * (diffuse[:, None] * c + spec[:, None])
    return out.astype(np.float32)
