"""Pinhole camera, thin lens and eye model; the circle of confusion (paper Section 4.1).

Conventions (OpenGL): the camera looks along -z of its own frame with y up; a point's
depth U is its distance in front of the lens along the view axis, U = -z_camera. The image
has W x H pixels, row 0 at the top; pixel (i, j) covers [j, j+1) x [i, i+1) and is sampled
at its centre (j + 0.5, i + 0.5).

The projection is glFrustum(L, R, B, T, N, FAR) followed by glViewport(0, 0, W, H), so a
camera-space point (X, Y, Z) lands on

    x_px = (N X / U - L) W / (R - L),      y_px = (T - N Y / U) H / (T - B).

The circle of confusion of eqs. 1-3 reduces to (PAPER_NOTES section 1)

    C_r(U) = (A / 2) |1/U - 1/P| N W / (R - L)      pixels,

which is also the screen displacement of a point at depth U when the pinhole moves by A/2
on the lens with the plane at depth P fixed: the multisample reference and the CoC agree.
The eye model (eq. 4) has the same form with N W / (R - L) replaced by d_s R_px.
The renderer only needs that form: ``lens.coc_coefficients(camera)`` returns (K, 1/P) with
C_r(U) = K |1/U - 1/P|.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace

import numpy as np

from .errors import DofsplatError


@dataclass(frozen=True)
class Camera:
    """A look-at pinhole camera with a glFrustum projection and a W x H viewport.

    Give either ``fov_y`` (vertical field of view in degrees; the frustum is then symmetric
    with near plane ``near``) or ``frustum`` = (L, R, B, T, N) in camera units. The frustum's
    aspect (R-L)/(T-B) must equal W/H (square pixels, the "undistorted image" of eq. 3).
    """

    eye: tuple[float, float, float]  # camera position, world units
    target: tuple[float, float, float]  # a point on the view axis, world units
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)  # world up hint
    width: int = 512  # W, pixels
    height: int = 512  # H, pixels
    fov_y: float | None = 40.0  # vertical field of view, degrees
    frustum: tuple[float, float, float, float, float] | None = None  # (L, R, B, T, N)
    near: float = 1e-3  # near plane N (world units) when fov_y is used; nearer splats are culled

    def __post_init__(self):
        for name in ("eye", "target", "up"):
            try:
                v = np.asarray(getattr(self, name), dtype=np.float64)
            except (TypeError, ValueError):
                v = np.full(1, np.nan)  # not numbers: the message below
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise DofsplatError(f"camera {name} must be three finite numbers, got {getattr(self, name)}")
            object.__setattr__(self, name, tuple(float(x) for x in v))
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool)
                   for v in (self.width, self.height)):
            raise DofsplatError("image width and height must be integers")
        if self.width <= 0 or self.height <= 0:
            raise DofsplatError(f"image size must be positive, got {self.width}x{self.height}")
        if self.width * self.height > 1 << 27:
            raise DofsplatError(f"image size {self.width}x{self.height} is too large (over 134 Mpixel)")
        fwd = np.subtract(self.target, self.eye)
        if np.linalg.norm(fwd) == 0:
            raise DofsplatError("camera eye and target coincide")
        if np.linalg.norm(np.cross(fwd, self.up)) <= 1e-9 * np.linalg.norm(fwd) * np.linalg.norm(self.up):
            raise DofsplatError("camera up vector is parallel to the view direction (or zero)")
        if self.frustum is not None:
            f = self.frustum if isinstance(self.frustum, (tuple, list, np.ndarray)) else ()
            if len(f) != 5 or not all(isinstance(x, numbers.Real) and math.isfinite(x) for x in f):
                raise DofsplatError("frustum must be five finite numbers L R B T N")
            left, right, bottom, top, near = f
            if not (right > left and top > bottom and near > 0):
                raise DofsplatError(f"frustum needs L < R, B < T and N > 0, got {f}")
            aspect_err = abs((right - left) / (top - bottom) / (self.width / self.height) - 1.0)
            if aspect_err > 1e-3:
                raise DofsplatError(
                    f"frustum aspect (R-L)/(T-B) = {(right - left) / (top - bottom):.4f} differs from "
                    f"the image aspect W/H = {self.width / self.height:.4f} (pixels must be square)")
            object.__setattr__(self, "frustum", tuple(float(x) for x in f))
            object.__setattr__(self, "fov_y", None)
        else:
            if self.fov_y is None or not (0.0 < _real("fov_y", self.fov_y) < 180.0):
                raise DofsplatError(f"field of view must be in (0, 180) degrees, got {self.fov_y}")
            if not (math.isfinite(_real("near", self.near)) and self.near > 0):
                raise DofsplatError(f"near plane must be > 0, got {self.near}")
            object.__setattr__(self, "fov_y", float(self.fov_y))
            object.__setattr__(self, "near", float(self.near))

    # -- transforms -------------------------------------------------------------------
    def camera_from_world(self) -> np.ndarray:
        """(4, 4) float64 view matrix: world to camera (camera looks along -z, y up)."""
        eye = np.asarray(self.eye)
        f = np.asarray(self.target) - eye
        f /= np.linalg.norm(f)
        s = np.cross(f, self.up)
        s /= np.linalg.norm(s)
        u = np.cross(s, f)
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = s, u, -f
        m[:3, 3] = -m[:3, :3] @ eye
        return m

    def frustum_lrbtn(self) -> tuple[float, float, float, float, float]:
        """(L, R, B, T, N) of the glFrustum call, camera units."""
        if self.frustum is not None:
            return self.frustum
        top = self.near * math.tan(math.radians(self.fov_y) / 2)
        right = top * self.width / self.height
        return (-right, right, -top, top, self.near)

    def screen_coefficients(self) -> tuple[float, float, float, float]:
        """(a_x, b_x, a_y, b_y): x_px = a_x X/U + b_x, y_px = -a_y Y/U + b_y."""
        left, right, bottom, top, near = self.frustum_lrbtn()
        sx = self.width / (right - left)
        sy = self.height / (top - bottom)
        return near * sx, -left * sx, near * sy, top * sy

    @property
    def pixels_per_unit_at_unit_depth(self) -> float:
        """N W / (R - L): the screen scale of eq. 3 (pixels per camera unit at depth 1)."""
        return self.screen_coefficients()[0]

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (M, 2) and depths U (M,) of world points (M, 3)."""
        m = self.camera_from_world()
        p = np.asarray(points_world, np.float64) @ m[:3, :3].T + m[:3, 3]
        depth = -p[:, 2]
        ax, bx, ay, by = self.screen_coefficients()
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = np.stack([ax * p[:, 0] / depth + bx, -ay * p[:, 1] / depth + by], axis=1)
        return xy, depth

    def ray_through_pixel(self, x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
        """(origin, unit direction) in world space of the ray through pixel position (x, y)."""
        ax, bx, ay, by = self.screen_coefficients()
        d_cam = np.array([(x - bx) / ax, -(y - by) / ay, -1.0])
        m = self.camera_from_world()
        d = m[:3, :3].T @ d_cam
        return np.asarray(self.eye, float), d / np.linalg.norm(d)

    @classmethod
    def framing(cls, lo, hi, width=512, height=512, fov_y=40.0,
                direction=(0.0, 0.0, 1.0), up=(0.0, 1.0, 0.0)) -> "Camera":
        """A camera that looks at the box [lo, hi] from ``direction`` and fits it in view."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        center = (lo + hi) / 2
        radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-9)
        half = math.radians(fov_y) / 2
        half_x = math.atan(math.tan(half) * width / height)
        dist = 1.05 * radius / math.sin(min(half, half_x))
        d = np.asarray(direction, float)
        d /= np.linalg.norm(d)
        return cls(eye=tuple(center + dist * d), target=tuple(center), up=tuple(up),
                   width=width, height=height, fov_y=fov_y, near=dist * 1e-4)


# ----------------------------------------------------------------------------------------
# Lenses. Both give C_r(U) = K |1/U - 1/P| with K in pixels x world units.


@dataclass(frozen=True)
class ThinLens:
    """Thin lens of a camera (eqs. 1-3): focus distance P and lens diameter A.

    Give either ``aperture`` (A) or ``focal_length`` (F) with ``f_number`` (n), A = F/n.
    Lengths are in world units; P is the depth of the focal plane along the view axis.
    ``aperture = 0`` is a pinhole (no depth of field).
    """

    focus_distance: float  # P, world units
    aperture: float | None = None  # A, lens diameter, world units
    focal_length: float | None = None  # F, world units (only to derive A and check P > F)
    f_number: float | None = None  # n = F / A
    bokeh: str = "disc"  # the blur's shape: "disc" (the aperture's, a real lens) or "gaussian" (the paper's)
    blades: int = 0  # straight aperture blades (>= 5) for a polygonal aperture; 0 = round
    blade_rotation: float = 0.0  # degrees, counterclockwise on the screen: the polygon's turn

    def __post_init__(self):
        _check_aperture_shape(self)
        p = _positive("focus distance", self.focus_distance)
        if self.aperture is not None:
            a = _real("aperture", self.aperture)
            if not math.isfinite(a) or a < 0:
                raise DofsplatError(f"aperture must be >= 0, got {self.aperture}")
            if self.f_number is not None:
                raise DofsplatError("give either the aperture or the f-number, not both")
        elif self.f_number is None or self.focal_length is None:
            raise DofsplatError("a thin lens needs an aperture, or a focal length and an f-number")
        if self.f_number is not None:
            _positive("f-number", self.f_number)
        if self.focal_length is not None:
            f = _positive("focal length", self.focal_length)
            if p <= f:
                raise DofsplatError(f"focus distance P = {p:g} must exceed the focal length F = {f:g}")

    @property
    def diameter(self) -> float:
        """A, world units."""
        if self.aperture is not None:
            return float(self.aperture)
        return float(self.focal_length) / float(self.f_number)

    def coc_coefficients(self, camera: Camera) -> tuple[float, float]:
        """(K, 1/P) with C_r(U) = K |1/U - 1/P| pixels (eq. 3 in its reduced form)."""
        return 0.5 * self.diameter * camera.pixels_per_unit_at_unit_depth, 1.0 / self.focus_distance

    def coc_radius_px(self, depth, camera: Camera):
        """CoC radius in pixels at camera depth(s) U (eqs. 1-3)."""
        k, inv_p = self.coc_coefficients(camera)
        return k * np.abs(1.0 / np.asarray(depth, np.float64) - inv_p)


@dataclass(frozen=True)
class EyeLens:
    """The human eye looking at a screen (eq. 4).

    Lengths in world units (metres if the scene is in metres): pupil diameter A (1-8 mm,
    4 mm typical), retina distance V_p (24 mm), fixation distance P, eye-to-screen
    distance d_s, and the screen resolution R in pixels per world unit.
    """

    focus_distance: float  # P, distance to the fixated surface
    screen_distance: float  # d_s
    pixels_per_unit: float  # R, screen pixels per world unit
    pupil_diameter: float = 0.004  # A
    retina_distance: float = 0.024  # V_p
    bokeh: str = "disc"  # the blur's shape: "disc" (a round pupil) or "gaussian" (the paper's)
    blades: int = 0  # straight blades (>= 5) for a polygonal aperture; 0 = round
    blade_rotation: float = 0.0  # degrees, counterclockwise on the screen

    def __post_init__(self):
        _check_aperture_shape(self)
        _positive("focus distance", self.focus_distance)
        _positive("screen distance", self.screen_distance)
        _positive("screen resolution", self.pixels_per_unit)
        _positive("retina distance", self.retina_distance)
        a = _real("pupil_diameter", self.pupil_diameter)
        if not math.isfinite(a) or a < 0:
            raise DofsplatError(f"pupil diameter must be >= 0, got {a}")

    @property
    def diameter(self) -> float:
        return float(self.pupil_diameter)

    @property
    def focal_length(self) -> float:
        """F = P V_p / (P + V_p): the eye accommodates to P (Section 4.1)."""
        return self.focus_distance * self.retina_distance / (self.focus_distance + self.retina_distance)

    def coc_coefficients(self, camera: Camera) -> tuple[float, float]:
        # eq. 4: C_r = C d_s / V_p R with C = (A/2) V_p |1/U - 1/P|
        return 0.5 * self.diameter * self.screen_distance * self.pixels_per_unit, 1.0 / self.focus_distance

    def coc_radius_px(self, depth, camera: Camera | None = None):
        k, inv_p = self.coc_coefficients(camera)
        return k * np.abs(1.0 / np.asarray(depth, np.float64) - inv_p)


BOKEHS = ("disc", "gaussian")
MAX_BLADES = 16


def _check_aperture_shape(lens) -> None:
    if lens.bokeh not in BOKEHS:
        raise DofsplatError(f"bokeh must be one of {', '.join(BOKEHS)}, got {lens.bokeh!r}")
    blades = lens.blades
    if isinstance(blades, bool) or not isinstance(blades, (int, np.integer)) \
            or not (blades == 0 or 5 <= blades <= MAX_BLADES):
        raise DofsplatError(f"blades must be 0 (round) or 5 to {MAX_BLADES}, got {blades!r}")
    if blades and lens.bokeh != "disc":
        raise DofsplatError("blades shape the aperture's image: they need the disc bokeh "
                            "(bokeh='disc'; --bokeh disc on the command line)")
    if not math.isfinite(_real("blade_rotation", lens.blade_rotation)):
        raise DofsplatError(f"blade rotation must be a finite angle, got {lens.blade_rotation}")


# ----------------------------------------------------------------------------------------
# The textbook equations, as printed; the tests check the reduced form against them.


def coc_radius_image(U, F, n, P):
    """Eqs. 1-2: CoC radius C on the image plane, V_u = FU/(U-F), V_p = FP/(P-F)."""
    U = np.asarray(U, np.float64)
    v_u = F * U / (U - F)
    v_p = F * P / (P - F)
    return 0.5 * np.abs(v_u - v_p) * F / (n * v_u)


def coc_radius_px_camera(C, F, P, width, left, right, near):
    """Eq. 3: C_r = C W/(R-L) N/V_p."""
    v_p = F * P / (P - F)
    return C * width / (right - left) * near / v_p


def coc_radius_px_eye(C, screen_distance, pixels_per_unit, retina_distance=0.024):
    """Eq. 4: C_r = C d_s / V_p R."""
    return C * screen_distance / retina_distance * pixels_per_unit


def photographic(eye, target, up=(0.0, 1.0, 0.0), *, width=512, height=512,
                 focal_length_mm=50.0, sensor_width_mm=36.0, f_number=2.8,
                 focus_m: float | None = None, unit_m: float = 1.0, bokeh: str = "disc",
                 blades: int = 0, blade_rotation: float = 0.0) -> tuple[Camera, ThinLens]:
    """A camera and lens from photographic settings.

    focal_length_mm, sensor_width_mm, f_number as on a real camera; focus_m the focus
    distance in metres (default: the distance to ``target``); unit_m the length of one
    world unit in metres; bokeh, blades, blade_rotation the aperture's shape (``ThinLens``). The sensor sits at the image distance V_p = FP/(P-F), so the
    field of view is that of a lens focused at P (focus breathing), and the CoC in pixels
    equals the CoC on the sensor times W / sensor width.
    """
    pinhole = Camera(eye=eye, target=target, up=up, width=width, height=height)  # checks them
    _positive("focal length", focal_length_mm)
    _positive("sensor width", sensor_width_mm)
    _positive("scene unit", unit_m)
    f = focal_length_mm / 1000.0 / unit_m
    s = sensor_width_mm / 1000.0 / unit_m
    if focus_m is None:
        p = float(np.linalg.norm(np.subtract(pinhole.target, pinhole.eye)))
    else:
        p = _positive("focus distance", focus_m) / unit_m
    lens = ThinLens(focus_distance=p, focal_length=f, f_number=f_number, bokeh=bokeh,
                    blades=blades, blade_rotation=blade_rotation)
    v_p = f * p / (p - f)
    near = f  # any N works; keep the frustum in camera units
    right = near * (s / 2) / v_p
    top = right * height / width
    return replace(pinhole, frustum=(-right, right, -top, top, near)), lens


def _real(name, v) -> float:
    """v as a float; a DofsplatError naming it when it is not a number (a string "40"
    passed float() here and failed in the render)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise DofsplatError(f"{name} must be a number, got {v!r}")
    return float(v)


def _positive(name, v) -> float:
    v = _real(name, v)
    if not math.isfinite(v) or v <= 0:
        raise DofsplatError(f"{name} must be > 0, got {v:g}")
    return v


# -- seen from a point of the lens (the reference's samples, the lens's parts) -----------


def effective_diameter(camera: Camera, lens) -> float:
    """The lens diameter A (world units) whose rim samples move points by the lens's C_r."""
    if lens is None:
        return 0.0
    k, _ = lens.coc_coefficients(camera)
    return 2.0 * k / camera.pixels_per_unit_at_unit_depth


def lens_camera(camera: Camera, offset, focus_distance: float) -> Camera:
    """The pinhole camera seen from lens point ``offset`` = (o_x, o_y) with the plane P fixed.

    offset is in the lens plane, along the camera's right (x) and up (y) axes, world units.
    The eye moves by the offset, the view direction stays, and the glFrustum window shifts by
    -offset N/P so that points at depth P keep their pixel.
    """
    ox, oy = float(offset[0]), float(offset[1])
    world_from_camera = np.linalg.inv(camera.camera_from_world())
    shift = world_from_camera[:3, :3] @ np.array([ox, oy, 0.0])
    left, right, bottom, top, near = camera.frustum_lrbtn()
    dx, dy = ox * near / focus_distance, oy * near / focus_distance
    return Camera(eye=tuple(np.add(camera.eye, shift)), target=tuple(np.add(camera.target, shift)),
                  up=camera.up, width=camera.width, height=camera.height,
                  frustum=(left - dx, right - dx, bottom - dy, top - dy, near))
