"""Per-splat Phong shading, the numba kernel (its numpy twin is ``dofsplat.shading.shade``)."""

import math

from ..jit import numba
import numpy as np

from ..camera import Camera
from ..shading import Light
from ..surfels import Material


def light_arrays(lights: tuple[Light, ...], camera: Camera):
    """(kinds (L,) int64: 0 directional / 1 point, vectors (L, 3) world, colours (L, 3)).

    Directional vectors become unit directions *towards* the light; point lights positions.
    """
    world_from_camera = np.linalg.inv(camera.camera_from_world())
    kinds = np.zeros(len(lights), np.int64)
    vecs = np.zeros((len(lights), 3))
    cols = np.zeros((len(lights), 3))
    for i, light in enumerate(lights):
        v = np.asarray(light.vector, np.float64)
        if light.kind == "directional":
            if light.in_camera_space:
                v = world_from_camera[:3, :3] @ v
            vecs[i] = -v / np.linalg.norm(v)
        else:
            kinds[i] = 1
            vecs[i] = world_from_camera[:3, :3] @ v + world_from_camera[:3, 3] if light.in_camera_space else v
        cols[i] = light.color
    return kinds, vecs, cols


def shade_fast(positions, normals, colors, material: Material, camera: Camera, lights,
               two_sided: bool, gain: bool = False):
    """Same contract as ``dofsplat.shading.shade``; (N, 3) float32. With ``gain``, also
    the (N, 3) float32 factor each colour channel was multiplied by (Phong is
    ambient + diffuse times the colour, plus a specular term that does not depend on it):
    an LOD node's colour gradient is shaded by it (``ewa.color_slope``)."""
    kinds, vecs, cols = light_arrays(tuple(lights), camera)
    out = np.empty(colors.shape, np.float32)
    factor = np.empty(colors.shape if gain else (0, 3), np.float32)
    _phong(positions, normals, colors, np.asarray(camera.eye, np.float64), kinds, vecs, cols,
           float(material.ambient), float(material.diffuse), float(material.specular),
           float(material.shininess), bool(two_sided), out, factor)
    return (out, factor) if gain else out


@numba.njit(cache=True, nogil=True, parallel=True)
def _phong(positions, normals, colors, eye, kinds, vecs, cols, ka, kd, ks, shininess,
           two_sided, out, gain):
    for k in numba.prange(positions.shape[0]):
        shade_splat(k, positions, normals, colors, eye, kinds, vecs, cols, ka, kd, ks, shininess,
                    two_sided, out, gain)


# inlined at numba's level, like gather_node: no per-splat call passing every array
@numba.njit(cache=True, nogil=True, inline="always")
def shade_splat(k, positions, normals, colors, eye, kinds, vecs, cols, ka, kd, ks, shininess,
                two_sided, out, gain):
    """Phong colour of splat k into out[k] and, if gain is (N, 3), the factor on each colour
    channel into gain[k] (``_phong``'s arguments); shared with the CUDA backend."""
    px, py, pz = positions[k, 0], positions[k, 1], positions[k, 2]
    nx, ny, nz = np.float64(normals[k, 0]), np.float64(normals[k, 1]), np.float64(normals[k, 2])
    vx, vy, vz = eye[0] - px, eye[1] - py, eye[2] - pz
    vl = max(math.sqrt(vx * vx + vy * vy + vz * vz), 1e-30)
    vx, vy, vz = vx / vl, vy / vl, vz / vl
    if two_sided and nx * vx + ny * vy + nz * vz < 0.0:
        nx, ny, nz = -nx, -ny, -nz
    r0 = ka * colors[k, 0]
    r1 = ka * colors[k, 1]
    r2 = ka * colors[k, 2]
    g0 = g1 = g2 = ka
    for li in range(kinds.shape[0]):
        lx, ly, lz = vecs[li, 0], vecs[li, 1], vecs[li, 2]
        if kinds[li] == 1:
            lx, ly, lz = lx - px, ly - py, lz - pz
            ll = max(math.sqrt(lx * lx + ly * ly + lz * lz), 1e-30)
            lx, ly, lz = lx / ll, ly / ll, lz / ll
        ndotl = nx * lx + ny * ly + nz * lz
        if ndotl <= 0.0:
            continue
        # reflection of the light direction about the normal
        rx, ry, rz = 2 * ndotl * nx - lx, 2 * ndotl * ny - ly, 2 * ndotl * nz - lz
        spec = ks * max(rx * vx + ry * vy + rz * vz, 0.0) ** shininess
        d = kd * ndotl
        r0 += cols[li, 0] * (d * colors[k, 0] + spec)
        r1 += cols[li, 1] * (d * colors[k, 1] + spec)
        r2 += cols[li, 2] * (d * colors[k, 2] + spec)
        g0 += cols[li, 0] * d
        g1 += cols[li, 1] * d
        g2 += cols[li, 2] * d
    out[k, 0] = r0
    out[k, 1] = r1
    out[k, 2] = r2
    if gain.shape[0] > 0:
        gain[k, 0] = g0
        gain[k, 1] = g1
        gain[k, 2] = g2
