"""Built-in scenes made in code, no data files needed.

``plane_scene``: the paper's "Plane" (Table 1): a textured square of 512 x 512 = 262,144
surfels seen at a grazing angle, so that depth, and with it the blur, varies across the frame.
``demo_scene``: the plane with three spheres at different depths and one focused on,
the scene that ``dofsplat demo`` renders.
``contact_scene``, ``intersecting_planes_scene``, ``transparent_contact_scene``: surfaces
that touch, cross or show through one another, for the fidelity suite (bench/fidelity.py).
"""

from __future__ import annotations

import math
from dataclasses import replace

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


# -- scenes for the fidelity suite (bench/fidelity.py): occlusion, contact, transparency --

CHECKS = 16  # checks along a side of the checkered floor
CONTACT_SPHERES = (  # (x, z, radius, linear colour): resting on y = 0, centre y = radius
    (-0.85, 1.25, 0.30, (0.9, 0.15, 0.1)),  # near, red
    (0.25, 0.0, 0.40, (0.95, 0.8, 0.2)),  # at the focus, yellow
    (1.05, -1.35, 0.50, (0.15, 0.35, 0.9)),  # far, blue
)
INTERSECT_ANGLE_DEG = 12.0  # the angle between the two planes of intersecting_planes_scene
INTERSECT_AXIS_DEG = 30.0  # their common line, turned this much from the x axis about y
TRANSPARENT_OPACITY = 0.5  # of the sphere and the pane of transparent_contact_scene
PANE_LEAN_DEG = 25.0  # the pane of transparent_contact_scene leans back this much from upright


def checker_texture(u: np.ndarray, v: np.ndarray, checks: int = CHECKS,
                    dark=(0.03, 0.03, 0.03), light=(0.85, 0.85, 0.8)) -> np.ndarray:
    """A plain two-colour checkerboard on [0, 1]^2, ``checks`` squares a side: (M, 3) linear.

    High contrast on purpose: a seam or a leak at a contact or an occlusion edge shows as a
    grey smear across sharp black-and-white edges, which the paper's colourful texture hides.
    """
    odd = ((np.floor(u * checks) + np.floor(v * checks)) % 2).astype(bool)
    return np.where(odd[:, None], np.asarray(light, np.float64), np.asarray(dark, np.float64))


def checker_plane(n: int = 512, size: float = PLANE_SIZE, checks: int = CHECKS,
                  dark=(0.03, 0.03, 0.03), light=(0.85, 0.85, 0.8),
                  center=(0.0, 0.0, 0.0)) -> Surfels:
    """``textured_plane`` with :func:`checker_texture` colours: n x n surfels on y = 0."""
    plane = textured_plane(n, size, center)
    u = (plane.positions[:, 0] - center[0]) / size + 0.5
    v = (plane.positions[:, 2] - center[2]) / size + 0.5
    return replace(plane, colors=checker_texture(u, v, checks, dark, light))


def contact_scene(width: int = 512, height: int = 512):
    """Three spheres resting on a checkered floor, their bottoms exactly on y = 0.

    Where a sphere touches the floor, the two surfaces' z-ranges overlap over a band around
    the contact point: the A-buffer must merge them there and keep them apart elsewhere,
    and the blur must not open a seam between them. The camera is the demo's (a grazing
    view); the near sphere is in front of the focus, the far one behind, and the focus is
    on the middle sphere's contact point, so its contact is sharp and the others' blurred.
    Returns (surfels, camera, lens); the lens aperture is DEMO_APERTURE.
    """
    spacing = PLANE_SIZE / 512
    parts = [checker_plane(512, PLANE_SIZE)]
    parts += [sphere((x, r, z), r, spacing, color) for x, z, r, color in CONTACT_SPHERES]
    cam = Camera(eye=(0.0, 1.2, 3.4), target=(0.0, 0.2, 0.0), width=width, height=height,
                 fov_y=DEMO_FOV_DEG, near=0.01)
    x, z, _, _ = CONTACT_SPHERES[1]
    lens = ThinLens(focus_distance=view_depth(cam, (x, 0.0, z)), aperture=DEMO_APERTURE)
    return concatenate(parts), cam, lens


def intersecting_planes_scene(width: int = 512, height: int = 512):
    """Two textured planes crossing at INTERSECT_ANGLE_DEG along a line through the frame.

    The paper's textured plane (y = 0) and a checkered plane turned about a line in it
    (through the origin, INTERSECT_AXIS_DEG from the x axis, so the line runs diagonally
    across the frame from near left to far right): on one side of the line the checks lie
    above the texture, on the other below it. At so shallow an angle the two surfaces are
    within each other's z-range over a band along the line, and their visibility swaps
    there. The camera is ``plane_scene``'s; the focus is on the line at the frame's centre.
    Returns (surfels, camera, lens); the lens aperture is 0.1 world units.
    """
    turn = math.radians(INTERSECT_AXIS_DEG)
    axis = (math.cos(turn), 0.0, -math.sin(turn))
    tilted = _turned(checker_plane(512, PLANE_SIZE, dark=(0.02, 0.05, 0.25),
                                   light=(0.9, 0.85, 0.7)), axis, INTERSECT_ANGLE_DEG)
    cam = Camera(eye=(0.0, 1.2, 3.2), target=(0.0, 0.0, 0.0), width=width, height=height,
                 fov_y=DEMO_FOV_DEG, near=0.01)
    lens = ThinLens(focus_distance=view_depth(cam, (0.0, 0.0, 0.0)), aperture=0.1)
    return concatenate([textured_plane(512, PLANE_SIZE), tilted]), cam, lens


def transparent_contact_scene(width: int = 512, height: int = 512):
    """Semi-transparent surfaces touching an opaque textured floor.

    A sphere of opacity TRANSPARENT_OPACITY rests on the paper's textured plane (bottom on
    y = 0) at the focus; nearer, a tinted pane of the same opacity leans back PANE_LEAN_DEG
    with its bottom edge on the floor; behind, an opaque sphere. Where a transparent
    surface meets the floor the A-buffer must merge the two without letting the floor's
    colour dilute the transparency (or the other way round), and blurred, the pane must let
    through both what lies behind it and what its own rim half covers. The camera is the
    demo's; the focus is on the transparent sphere's contact point.
    Returns (surfels, camera, lens); the lens aperture is DEMO_APERTURE.
    """
    spacing = PLANE_SIZE / 512
    glass = sphere((0.25, 0.4, 0.0), 0.4, spacing, (0.3, 0.75, 0.35))
    glass = replace(glass, opacity=np.full(len(glass), TRANSPARENT_OPACITY))
    parts = [textured_plane(512, PLANE_SIZE), glass,
             sphere((1.0, 0.35, -1.3), 0.35, spacing, (0.15, 0.35, 0.9)),
             leaning_pane((-0.8, 0.0, 1.1), 1.0, 0.7, PANE_LEAN_DEG, spacing,
                          TRANSPARENT_OPACITY)]
    cam = Camera(eye=(0.0, 1.2, 3.4), target=(0.0, 0.2, 0.0), width=width, height=height,
                 fov_y=DEMO_FOV_DEG, near=0.01)
    lens = ThinLens(focus_distance=view_depth(cam, (0.25, 0.0, 0.0)), aperture=DEMO_APERTURE)
    return concatenate(parts), cam, lens


def leaning_pane(bottom_center, width: float, height: float, lean_deg: float, spacing: float,
                 opacity: float = 1.0) -> Surfels:
    """A rectangular pane standing on y = bottom_center[1], facing +z, leaning back (its top
    towards -z) by ``lean_deg`` from upright: a grid at ``spacing``, radius = spacing, a
    blue tint with a light lattice and a dark rim, the given opacity."""
    gx = np.arange(-width / 2 + spacing / 2, width / 2, spacing)
    gy = np.arange(spacing / 2, height, spacing)
    x, y = (a.ravel() for a in np.meshgrid(gx, gy))
    lean = math.radians(lean_deg)
    up = np.array([0.0, math.cos(lean), -math.sin(lean)])
    normal = np.array([0.0, math.sin(lean), math.cos(lean)])
    positions = np.asarray(bottom_center, np.float64) + x[:, None] * [1.0, 0.0, 0.0] \
        + y[:, None] * up
    u, v = x / width + 0.5, y / height
    lines = (np.abs((u * 6) % 1 - 0.5) > 0.44) | (np.abs((v * 4) % 1 - 0.5) > 0.44)
    rim = (np.minimum(u, 1 - u) * width < 0.04) | ((1 - v) * height < 0.04)
    colors = np.tile([0.2, 0.5, 1.0], (len(x), 1))  # linear
    colors[lines] = (0.92, 0.92, 0.85)
    colors[rim] = (0.03, 0.08, 0.35)
    n = len(x)
    return Surfels(positions=positions, normals=np.tile(normal, (n, 1)),
                   radius=np.full(n, spacing), colors=colors, opacity=np.full(n, opacity))


def view_depth(camera: Camera, point) -> float:
    """The camera depth U (along the view axis, world units) of a world point: the focus
    distance that puts the point in focus."""
    return float(camera.project(np.asarray(point, np.float64)[None, :])[1][0])


def _turned(surfels: Surfels, axis, angle_deg: float) -> Surfels:
    """The surfels turned by ``angle_deg`` about a unit ``axis`` through the origin."""
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    a = math.radians(angle_deg)
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    rotation = np.eye(3) + math.sin(a) * cross + (1.0 - math.cos(a)) * cross @ cross  # Rodrigues
    return replace(surfels, positions=surfels.positions @ rotation.T,
                   normals=surfels.normals @ rotation.T)
