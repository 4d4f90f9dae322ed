"""Thin lens, eye model and CoC (paper eqs. 1-4, PAPER_NOTES section 1)."""

import math

import numpy as np
import pytest

import dofsplat as ds
from dofsplat.camera import (coc_radius_image, coc_radius_px_camera, coc_radius_px_eye,
                             photographic)


def test_coc_eqs_1_to_3_equal_the_reduced_identity():
    """C from eqs. 1-2 scaled by eq. 3 equals (A/2)|1/U - 1/P| N W/(R-L) on random values."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        F = rng.uniform(0.01, 2.0)
        n = rng.uniform(0.7, 32.0)
        P = F * rng.uniform(1.05, 100.0)
        U = F * rng.uniform(1.01, 200.0, size=16)
        W = int(rng.integers(16, 4000))
        near = rng.uniform(0.001, 1.0)
        half = near * math.tan(math.radians(rng.uniform(5, 120)) / 2)
        L, R = -half, half * rng.uniform(0.5, 1.5)  # off-axis frusta too
        C = coc_radius_image(U, F, n, P)
        eq3 = coc_radius_px_camera(C, F, P, W, L, R, near)
        identity = (F / n) / 2 * np.abs(1 / U - 1 / P) * near * W / (R - L)
        np.testing.assert_allclose(eq3, identity, rtol=1e-9, atol=1e-12)


def test_lens_coc_matches_eq3_through_the_camera():
    cam = ds.Camera(eye=(0, 0, 5), target=(0, 0, 0), width=640, height=480, fov_y=50)
    lens = ds.ThinLens(focus_distance=5.0, focal_length=0.05, f_number=2.0)
    L, R, B, T, N = cam.frustum_lrbtn()
    U = np.array([0.5, 1.0, 3.0, 5.0, 12.0, 100.0])
    expected = coc_radius_px_camera(coc_radius_image(U, 0.05, 2.0, 5.0), 0.05, 5.0, 640, L, R, N)
    np.testing.assert_allclose(lens.coc_radius_px(U, cam), expected, rtol=1e-12)
    assert lens.coc_radius_px(5.0, cam) == pytest.approx(0.0, abs=1e-12)


def test_eye_model_eq4_hand_computed():
    """Pupil 4 mm, fixation 0.5 m, object at 1 m, screen 0.6 m away at 4000 px/m.

    By hand: F = P V_p/(P+V_p) = 0.5*0.024/0.524 = 0.0229007634 m; V_u = FU/(U-F) =
    0.0234375 m; V_p = 0.024 m; C = 1/2 |V_u - V_p| F/(n V_u) with n = F/A:
    C = 0.5 * 0.0005625 * 0.004 / 0.0234375 = 4.8e-5 m. C_r = C d_s/V_p R = 4.8e-5 * 25 * 4000 = 4.8 px.
    """
    eye = ds.EyeLens(focus_distance=0.5, screen_distance=0.6, pixels_per_unit=4000.0,
                     pupil_diameter=0.004)
    F = eye.focal_length
    assert F == pytest.approx(0.5 * 0.024 / 0.524, rel=1e-12)
    C = coc_radius_image(1.0, F, F / 0.004, 0.5)
    assert C == pytest.approx(4.8e-5, rel=1e-9)
    assert coc_radius_px_eye(C, 0.6, 4000.0) == pytest.approx(4.8, rel=1e-9)
    assert eye.coc_radius_px(1.0) == pytest.approx(4.8, rel=1e-9)


def test_photographic_mode_matches_sensor_coc():
    """50 mm f/2 on a 36 mm sensor, focus 2 m, object 4 m: C_r = C * W / sensor width."""
    cam, lens = photographic((0, 0, 2), (0, 0, 0), width=1200, height=800, focal_length_mm=50,
                             sensor_width_mm=36, f_number=2.0, focus_m=2.0)
    C = coc_radius_image(4.0, 0.05, 2.0, 2.0)  # metres on the sensor
    assert lens.coc_radius_px(4.0, cam) == pytest.approx(C * 1200 / 0.036, rel=1e-9)
    # a scene in millimetres gives the same picture
    cam_mm, lens_mm = photographic((0, 0, 2000), (0, 0, 0), width=1200, height=800,
                                   focal_length_mm=50, sensor_width_mm=36, f_number=2.0,
                                   focus_m=2.0, unit_m=0.001)
    assert lens_mm.coc_radius_px(4000.0, cam_mm) == pytest.approx(C * 1200 / 0.036, rel=1e-9)


def test_projection_conventions():
    """Camera looks along -z, y up, row 0 at the top, pixel centres at +0.5."""
    cam = ds.Camera(eye=(0, 0, 3), target=(0, 0, 0), width=100, height=50, fov_y=60)
    xy, depth = cam.project(np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0]]))
    np.testing.assert_allclose(depth, 3.0)
    np.testing.assert_allclose(xy[0], [50, 25])
    assert xy[1, 1] < 25  # up is towards row 0
    assert xy[2, 0] > 50
    # 1 unit at depth 3 with a 60 degree vertical fov: 1/(3 tan 30) of the half height
    assert 25 - xy[1, 1] == pytest.approx(25 / (3 * math.tan(math.radians(30))), rel=1e-12)


@pytest.mark.parametrize("kwargs, match", [
    (dict(focus_distance=0.04, focal_length=0.05, f_number=2), "must exceed the focal length"),
    (dict(focus_distance=1, focal_length=0.05, f_number=0), "f-number"),
    (dict(focus_distance=1, focal_length=0.05, f_number=-1), "f-number"),
    (dict(focus_distance=-1, aperture=0.1), "focus distance"),
    (dict(focus_distance=1, aperture=-0.1), "aperture"),
    (dict(focus_distance=1), "needs an aperture"),
    (dict(focus_distance=1, aperture=0.1, f_number=2, focal_length=0.05), "either"),
    # not numbers: a string "3" passed float() and failed in the render
    (dict(focus_distance="3", aperture=0.1), "focus distance must be a number, got '3'"),
    (dict(focus_distance=1, aperture="0.1"), "aperture must be a number, got '0.1'"),
    (dict(focus_distance=1, aperture=0.1, blade_rotation=None), "blade_rotation must be a number"),
])
def test_lens_rejects_impossible_values(kwargs, match):
    with pytest.raises(ds.DofsplatError, match=match):
        ds.ThinLens(**kwargs)


@pytest.mark.parametrize("kwargs, match", [
    (dict(width=0), "positive"), (dict(height=-3), "positive"),
    (dict(fov_y=0), "field of view"), (dict(fov_y=180), "field of view"),
    (dict(eye=(0, 0, 0)), "coincide"), (dict(up=(0, 0, 1)), "parallel"),
    (dict(frustum=(1, -1, -1, 1, 1)), "L < R"), (dict(frustum=(-2, 2, -1, 1, 1)), "aspect"),
    (dict(eye=(0, float("nan"), 1)), "finite"),
    # not numbers: fov_y "40" was accepted and failed in the render
    (dict(fov_y="40"), "fov_y must be a number, got '40'"),
    (dict(near=None), "near must be a number"),
    (dict(frustum="LRBTN"), "five finite numbers"), (dict(eye="abc"), "eye must be three finite"),
])
def test_camera_rejects_impossible_values(kwargs, match):
    args = dict(eye=(0, 0, 1), target=(0, 0, 0), width=64, height=64)
    args.update(kwargs)
    with pytest.raises(ds.DofsplatError, match=match):
        ds.Camera(**args)


def test_photographic_checks_the_camera_first():
    """photographic() with a zero width was a ZeroDivisionError, an eye of the wrong kind a
    numpy UFuncTypeError: now the Camera's own messages."""
    with pytest.raises(ds.DofsplatError, match="image size must be positive, got 0x512"):
        photographic((0, 0, 3), (0, 0, 0), width=0)
    with pytest.raises(ds.DofsplatError, match="camera eye must be three finite numbers"):
        photographic("abc", (0, 0, 0))
