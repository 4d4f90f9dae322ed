"""The multisample reference: the lens identity, convergence, and our DOF measured against it."""

import dataclasses
import math

import numpy as np
import pytest

import dofsplat as ds
from dofsplat.camera import coc_radius_image, coc_radius_px_camera
from dofsplat.cli import main
from dofsplat.io import read_image
from dofsplat.metrics import compare
from dofsplat.postfilter import render_postfilter
from dofsplat.reference import (effective_diameter, lens_camera, lens_cameras, lens_samples,
                                render_reference)
from dofsplat.surfels import concatenate

from conftest import front_camera, grid_surfels

UNLIT = ds.RenderSettings(shading="none")


# -- the lens identity (PAPER_NOTES section 1) -----------------------------------------------

CAMERAS = {
    "fov": ds.Camera(eye=(0.3, 0.5, 2.0), target=(0.0, 0.0, 0.0), width=96, height=80,
                     fov_y=40.0, near=0.01),
    # an off-centre glFrustum window, non-square image
    "frustum": ds.Camera(eye=(-1.0, 0.2, 3.0), target=(0.2, 0.1, 0.0), up=(0.1, 1.0, 0.0),
                         width=120, height=90, frustum=(-0.02, 0.06, -0.01, 0.05, 0.05)),
}


@pytest.mark.parametrize("cam_name", sorted(CAMERAS))
@pytest.mark.parametrize("depth", [0.7, 1.3, 2.9, 40.0])  # in front of and behind P
def test_a_points_displacement_over_the_lens_spans_exactly_the_coc(cam_name, depth):
    """Moving the pinhole by o on the lens moves a point at depth U by |o|/(A/2) x C_r(U).

    C_r from eqs. 1-3 (``coc_radius_image`` and ``coc_radius_px_camera``, the printed
    equations); displacements from projecting the point with the reference's own cameras.
    Rim samples (|o| = A/2) move it by exactly C_r: the reference and the CoC agree to 1e-6.
    """
    cam = CAMERAS[cam_name]
    focal_length, f_number, focus = 0.05, 1.4, 1.9
    lens = ds.ThinLens(focus_distance=focus, focal_length=focal_length, f_number=f_number)
    # a world point at camera depth U, off the axis
    m_inv = np.linalg.inv(cam.camera_from_world())
    p_world = (m_inv @ np.array([0.13 * depth, -0.05 * depth, -depth, 1.0]))[:3][None]
    xy0, u = cam.project(p_world)
    np.testing.assert_allclose(u, depth, rtol=1e-12)

    left, right, _, _, near = cam.frustum_lrbtn()
    c_image = coc_radius_image(depth, focal_length, f_number, focus)  # eqs. 1-2
    c_r = coc_radius_px_camera(c_image, focal_length, focus, cam.width, left, right,
                                         near)  # eq. 3

    a = lens.diameter
    rim = [(0.5 * a * math.cos(t), 0.5 * a * math.sin(t)) for t in np.linspace(0, 6, 7)]
    for o in rim:
        shift = np.linalg.norm(lens_camera(cam, o, focus).project(p_world)[0] - xy0)
        assert shift == pytest.approx(c_r, rel=1e-6)

    offsets = lens_samples(200, a)
    shifts = np.array([np.linalg.norm(c.project(p_world)[0] - xy0)
                       for c in lens_cameras(cam, lens, 200)])
    np.testing.assert_allclose(shifts, c_r * np.linalg.norm(offsets, axis=1) / (a / 2),
                               rtol=1e-6)
    # the samples reach the rim: their spread is the CoC disc, to within half a sample ring
    assert shifts.max() == pytest.approx(c_r, rel=0.5 / 200)


def test_the_focal_plane_stays_put_and_depth_is_unchanged():
    cam = CAMERAS["frustum"]
    lens = ds.ThinLens(focus_distance=2.5, aperture=0.3)
    m_inv = np.linalg.inv(cam.camera_from_world())
    pts = (m_inv @ np.array([[0.1, 0.05, -2.5, 1.0], [-0.3, 0.2, -2.5, 1.0]]).T).T[:, :3]
    xy0, u0 = cam.project(pts)
    for c in lens_cameras(cam, lens, 16):
        xy, u = c.project(pts)
        np.testing.assert_allclose(xy, xy0, atol=1e-9)
        np.testing.assert_allclose(u, u0, rtol=1e-12)


def test_lens_samples_cover_the_disc_evenly():
    n, a = 200, 0.4
    o = lens_samples(n, a)
    r = np.linalg.norm(o, axis=1)
    assert r.max() < a / 2
    # equal-area samples: the fraction inside radius rho is rho^2 / (A/2)^2, to 1/n
    for rho in (0.25, 0.5, 0.75):
        assert np.mean(r < rho * a / 2) == pytest.approx(rho ** 2, abs=1.0 / n)
    # and no side of the disc is favoured (the centroid is near the centre)
    assert np.linalg.norm(o.mean(axis=0)) < 0.01 * a


def test_the_eye_model_reference_uses_the_lens_with_the_same_coc():
    """EyeLens (eq. 4): the reference's diameter is the one giving the eye's C_r in pixels."""
    cam = CAMERAS["fov"]
    eye = ds.EyeLens(focus_distance=1.5, screen_distance=0.6, pixels_per_unit=4000.0)
    a = effective_diameter(cam, eye)
    thin = ds.ThinLens(focus_distance=1.5, aperture=a)
    np.testing.assert_allclose(thin.coc_radius_px([0.5, 3.0], cam),
                               eye.coc_radius_px([0.5, 3.0], cam), rtol=1e-12)
    assert effective_diameter(cam, None) == 0.0


# -- the scene: a checkered plane and a square occluder in front of it ----------------------


def checker_plane(n=64, spacing=1.0 / 32, cell=4):
    s = grid_surfels(n=n, spacing=spacing, z=0.0)
    ij = np.indices((n, n)).reshape(2, -1)
    check = ((ij[0] // cell + ij[1] // cell) % 2).astype(np.float32)
    s.colors[:] = np.stack([0.1 + 0.8 * check, 0.9 - 0.8 * check, np.full_like(check, 0.2)],
                           axis=1)
    return s


SCENE = concatenate([checker_plane(), grid_surfels(n=16, spacing=1.0 / 48, z=1.0,
                                                   color=(0.1, 0.2, 0.9))])
CAM = front_camera(96, 96, distance=2.0)  # plane at depth 2, occluder at depth 1
NOLOD = dataclasses.replace(UNLIT, lod=False)


def test_pinhole_and_tiny_apertures_give_the_pinhole_render():
    """A pinhole lens needs one render; shading once from the centre equals render()'s."""
    lit = ds.RenderSettings(lod=False)
    pinhole = ds.render(SCENE, CAM, None, lit)
    ref = render_reference(SCENE, CAM, ds.ThinLens(focus_distance=2.0, aperture=0.0), lit,
                           samples=50, progress=False)
    assert ref.stats["samples"] == 1
    np.testing.assert_array_equal(ref.image, pinhole.image)
    np.testing.assert_array_equal(ref.depth, pinhole.depth)
    # a lens of 1e-7: shifts of ~1e-5 px; the same picture up to float rounding
    tiny = render_reference(SCENE, CAM, ds.ThinLens(focus_distance=2.0, aperture=1e-7), lit,
                            samples=4, progress=False)
    np.testing.assert_allclose(tiny.image, pinhole.image, atol=1e-4)


def test_the_reference_converges():
    """PSNR between N and 2N samples rises with N (blurred occluder, C_r = 6.6 px).

    Vogel spirals of N and 2N points are not nested, so a single doubling can wobble by a
    few dB; over 4x steps the rise is large: measured 30.7, 46.9, 54.7 dB for N = 2, 8, 32
    (and 59.4, 67.2 dB for N = 64, 128).
    """
    lens = ds.ThinLens(focus_distance=2.0, aperture=0.2)
    assert lens.coc_radius_px(1.0, CAM) == pytest.approx(6.59, abs=0.01)
    psnrs = []
    for n in (2, 8, 32):
        a, b = (render_reference(SCENE, CAM, lens, UNLIT, samples=k, progress=False).image
                for k in (n, 2 * n))
        psnrs.append(compare(a, b)["psnr"])
    assert psnrs[1] > psnrs[0] + 5 and psnrs[2] > psnrs[1] + 5, psnrs


@pytest.fixture(scope="module")
def references():
    """64-sample references of the scene, by (focus, aperture); 64 is within ~0.3 dB of 256."""
    cache = {}

    def get(focus, aperture):
        key = (focus, aperture)
        if key not in cache:
            lens = ds.ThinLens(focus_distance=focus, aperture=aperture)
            cache[key] = render_reference(SCENE, CAM, lens, UNLIT, samples=64,
                                          progress=False).image
        return cache[key]

    return get


# (focus, aperture) -> PSNR of ours against the 64-sample reference, measured with LOD (the
# default) and without (dB); the 256-sample reference gives the same to within 0.3 dB
# (with the aperture's disc; the paper's Gaussian: 49.2, 50.2, 42.9 dB, no LOD; before a sharp
# surface covered its pixel, abuffer.layer_alpha: 51.3, 51.9, 47.9 dB, LOD and no LOD alike,
# which the (2.0, 0.2) row's bound rejects; tests/test_render.py tests that rule itself)
OURS_MEASURED = {
    (2.0, 0.1): (53.3, 53.3),  # focus on the plane, occluder C_r = 3.3 px
    (2.0, 0.2): (56.8, 56.8),  # occluder C_r = 6.6 px
    (1.0, 0.1): (50.1, 50.1),  # focus on the occluder, plane C_r = 3.3 px
}
MARGIN_DB = 3.0  # for platform and float-rounding differences; a real regression costs more


@pytest.mark.parametrize("focus, aperture", sorted(OURS_MEASURED))
def test_our_dof_is_close_to_the_reference(references, focus, aperture):
    """Ours against the reference: PSNR above the measured value less MARGIN_DB.

    With LOD on, the remaining difference is mostly the coarser splats.
    """
    lens = ds.ThinLens(focus_distance=focus, aperture=aperture)
    ref = references(focus, aperture)
    for settings, measured in zip((UNLIT, NOLOD), OURS_MEASURED[(focus, aperture)]):
        ours = ds.render(SCENE, CAM, lens, settings).image
        got = compare(ours, ref)
        assert got["psnr"] > measured - MARGIN_DB, (settings.lod, got)
        assert got["ssim"] > 0.98, (settings.lod, got)


# (focus, aperture) -> PSNR of the post-filter against the 64-sample reference, measured
POSTFILTER_MEASURED = {(2.0, 0.1): 34.5, (2.0, 0.2): 29.0, (1.0, 0.1): 33.8}


@pytest.mark.parametrize("focus, aperture", sorted(POSTFILTER_MEASURED))
def test_the_postfilter_scores_lower_than_ours(references, focus, aperture):
    """The post-process baseline has no partial occlusion (the blurred occluder's rim stays
    opaque, the plane behind it is missing) and leaks between the two surfaces.

    Against our method without LOD (the same splats; measured 49.2, 50.2, 42.9 dB) we ask
    for a 5 dB gap; with LOD (49.2, 48.0, 36.3 dB) only for a lower PSNR.
    """
    lens = ds.ThinLens(focus_distance=focus, aperture=aperture)
    ref = references(focus, aperture)
    post = compare(render_postfilter(SCENE, CAM, lens, NOLOD).image, ref)
    assert post["psnr"] == pytest.approx(POSTFILTER_MEASURED[(focus, aperture)], abs=MARGIN_DB)
    ours = compare(ds.render(SCENE, CAM, lens, NOLOD).image, ref)
    assert post["psnr"] < ours["psnr"] - 5.0, (post, ours)
    assert post["ssim"] < ours["ssim"]
    ours_lod = compare(ds.render(SCENE, CAM, lens, UNLIT).image, ref)
    assert post["psnr"] < ours_lod["psnr"]


# -- API and command line ----------------------------------------------------------------


@pytest.mark.parametrize("samples", [0, -3, 2.5, True, "10"])
def test_bad_sample_counts_are_user_errors(samples):
    with pytest.raises(ds.DofsplatError, match="lens samples"):
        render_reference(SCENE, CAM, ds.ThinLens(focus_distance=2.0, aperture=0.1),
                         samples=samples, progress=False)


def test_reference_stats():
    ref = render_reference(SCENE, CAM, ds.ThinLens(focus_distance=2.0, aperture=0.1), UNLIT,
                           samples=3, progress=False)
    s = ref.stats
    assert s["samples"] == 3 and s["aperture"] == pytest.approx(0.1)
    assert s["points_in"] == len(SCENE) and (s["width"], s["height"]) == (96, 96)
    assert s["total_ms"] >= s["render_ms"] > 0
    assert ref.image.dtype == np.float32 and ref.image.shape == (96, 96, 4)


def test_cli_reference_of_the_demo_scene(tmp_path, capsys):
    out = tmp_path / "ref.npy"
    stats = tmp_path / "ref.json"
    assert main(["reference", "--demo", "--size", "48x36", "--samples", "2", "-o", str(out),
                 "--stats", str(stats)]) == 0
    img = read_image(out)
    assert img.shape == (36, 48, 4) and img[..., 3].max() > 0.5
    assert "2 lens samples" in capsys.readouterr().err
    import json
    record = json.loads(stats.read_text())
    assert record["method"] == "reference" and record["samples"] == 2


@pytest.mark.parametrize("argv, message", [
    (["reference"], "give a model file"),
    (["reference", "model.ply", "--demo"], "not both"),
    (["reference", "--demo", "--samples", "0"], "at least 1"),
    (["reference", "--demo", "--method", "postfilter"], "unrecognized arguments"),
    (["reference", "--demo", "--no-lod"], "unrecognized arguments"),
    (["reference", "--demo", "--show-lod"], "unrecognized arguments"),
])
def test_cli_reference_mistakes(tmp_path, capsys, argv, message):
    out = tmp_path / "r.png"
    assert main(argv + ["-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dofsplat: error: ") and message in err and err.count("\n") == 1
    assert not out.exists()


def test_cli_reference_help_has_no_lod_options(capsys):
    """Every lens sample is a full-resolution pinhole render: LOD options would do nothing."""
    assert main(["reference", "--help"]) == 0
    text = capsys.readouterr().out
    assert "--samples" in text and "--aperture" in text
    assert "level of detail" not in text and "--lod" not in text and "--show-lod" not in text


def test_the_api_exports_the_reference_and_compare():
    assert ds.render_reference is render_reference and ds.compare is compare


def test_explicit_lens_offsets():
    """offsets= replaces the Vogel spiral: the spiral's own offsets give the same image, and
    anything but a non-empty (n, 2) array of finite numbers is a user error."""
    lens = ds.ThinLens(focus_distance=2.0, aperture=0.1)
    by_count = render_reference(SCENE, CAM, lens, UNLIT, samples=6, progress=False)
    by_offsets = render_reference(SCENE, CAM, lens, UNLIT, progress=False,
                                  offsets=lens_samples(6, 0.1))
    np.testing.assert_array_equal(by_offsets.image, by_count.image)
    assert by_offsets.stats["samples"] == 6
    for bad in (np.zeros((0, 2)), np.zeros((3, 3)), [[0.0, np.nan]]):
        with pytest.raises(ds.DofsplatError, match="lens offsets"):
            render_reference(SCENE, CAM, lens, UNLIT, progress=False, offsets=bad)
