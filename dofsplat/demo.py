"""Built-in scenes made in code, no data files needed.

``plane_scene``: the paper's "Plane" (Table 1): a textured square of 512 x 512 = 262,144
surfels seen at a grazing angle, so that depth, and with it the blur, varies across the frame.
``demo_scene``: the plane with three spheres at different depths and one focused on,
the scene that ``dofsplat demo`` renders.
"""

from __future__ import annotations

import math

import numpy as np

from .camera import Camera, ThinLens
from .surfels import Material, Surfels, concatenate

PLANE_SIZE = 4.0  # world units, the side of the textured plane
DEMO_FOV_DEG = 45.0  # vertical field of view of the demo camera
DEMO_APERTURE = 0.12  # lens diameter of the demo scene, world units


def plane_texture(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A colourful test texture on [0, 1]^2: checks, hue ramps and fine lines. (M, 3) linear."""
    checks = ((np.floor(u * 16) + np.floor(v * 16)) % 2).astype(np.float64)
    hue = 2 * math.pi * (u + 0.5 * v)
    base = 0.5 + 0.5 * np.stack([np.cos(hue), np.cos(hue - 2.094), np.cos(hue + 2.094)], axis=1)
    rgb = base * (0.35 + 0.65 * checks)[:, None]
    lines = (np.abs(((u * 64) % 1) - 0.5) > 0.44) | (np.abs(((v * 64) % 1) - 0.5) > 0.44)
    rgb[lines] = 0.9
    return np.clip(rgb, 0.0, 1.0) ** 2.2  # the ramps are designed in sRGB: to linear


def textured_plane(n: int = 512, size: float = 4.0, center=(0.0, 0.0, 0.0)) -> Surfels:
    """An n x n grid of surfels on the y = 0 plane (normal +y), side ``size``, radius = spacing."""
    h = size / n
    g = (np.arange(n) + 0.5) / n
    u, v = np.meshgrid(g, g)
    u, v = u.ravel(), v.ravel()
    pos = np.stack([(u - 0.5) * size, np.zeros_like(u), (v - 0.5) * size], axis=1) + center
    return Surfels(positions=pos, normals=np.tile([0.0, 1.0, 0.0], (n * n, 1)),
                   radius=np.full(n * n, h), colors=plane_texture(u, v),
                   material=Material(specular=0.1))


def sphere(center, radius: float, spacing: float, color, stripes: int = 8) -> Surfels:
    """A sphere sampled by a Fibonacci lattice at about ``spacing``, radius = spacing."""
    n = max(16, int(4 * math.pi * radius * radius / spacing ** 2))
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    normal = np.stack([r * np.cos(phi), z, r * np.sin(phi)], axis=1)
    lon = np.arctan2(normal[:, 2], normal[:, 0])
    band = (np.floor((lon / (2 * math.pi) + 0.5) * stripes) % 2)[:, None]
    col = np.asarray(color, np.float64)[None, :] * (0.55 + 0.45 * band)
    spacing_actual = math.sqrt(4 * math.pi / n) * radius
    return Surfels(positions=np.asarray(center) + radius * normal, normals=normal,
                   radius=np.full(n, spacing_actual), colors=col)


def plane_scene(width: int = 512, height: int = 512):
    """The paper's plane: 262,144 surfels, camera at a grazing angle, focus mid-plane.

    Returns (surfels, camera, lens); the lens aperture is 0.1 world units.
    """
    surf = textured_plane(512, PLANE_SIZE)
    cam = Camera(eye=(0.0, 1.2, 3.2), target=(0.0, 0.0, 0.0), width=width, height=height,
                 fov_y=DEMO_FOV_DEG, near=0.01)
    lens = ThinLens(focus_distance=math.dist(cam.eye, cam.target), aperture=0.1)
    return surf, cam, lens


def demo_scene(width: int = 800, height: int = 600):
    """Plane and three spheres (near, focused, far). Returns (surfels, camera, lens)."""
    spacing = PLANE_SIZE / 512
    parts = [
        textured_plane(512, PLANE_SIZE),
        sphere((-0.9, 0.35, 1.3), 0.35, spacing, (0.9, 0.15, 0.1)),  # near, red
        sphere((0.25, 0.35, 0.0), 0.35, spacing, (0.95, 0.8, 0.2)),  # in focus, yellow
        sphere((1.1, 0.35, -1.4), 0.35, spacing, (0.15, 0.35, 0.9)),  # far, blue
    ]
    surf = concatenate(parts)
    cam = Camera(eye=(0.0, 1.2, 3.4), target=(0.0, 0.2, 0.0), width=width, height=height,
                 fov_y=DEMO_FOV_DEG, near=0.01)
    focus = float(np.linalg.norm(np.subtract((0.25, 0.35, 0.0), cam.eye)))
    lens = ThinLens(focus_distance=focus, aperture=DEMO_APERTURE)
    return surf, cam, lens
