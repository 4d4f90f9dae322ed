"""The lens drawn in parts (``RenderSettings.lens_samples``, splat/subaperture.py)."""

import dataclasses
import math

import numpy as np
import pytest

import dofsplat as ds
from dofsplat import demo
from dofsplat.backends.cpu import shade_surfels
from dofsplat.camera import effective_diameter, lens_camera
from dofsplat.cli import main
from dofsplat.errors import DofsplatError
from dofsplat.metrics import compare
from dofsplat.reference import render_reference
from dofsplat.splat.subaperture import (ResidualLens, aperture_second_moment,
                                        subaperture_pattern)


def _numerical_parts(k: int, n: int = 1201):
    """Centroids and areas of the K parts of the unit disc, from a fine grid (numpy twin):
    sectors by angle for K <= 6; a centre disc of area 1/K and K - 1 ring sectors beyond."""
    g = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    x, y = np.meshgrid(g, g)
    inside = x * x + y * y <= 1.0
    angle = np.mod(np.arctan2(y, x), 2.0 * math.pi)
    if k <= 6:
        label = np.floor(angle / (2.0 * math.pi / k)).astype(int)
    else:
        label = 1 + np.floor(angle / (2.0 * math.pi / (k - 1))).astype(int)
        label[x * x + y * y <= 1.0 / k] = 0
    cells = [(label == i) & inside for i in range(k)]
    area = np.array([c.sum() for c in cells], float) / inside.sum()
    centroid = np.array([[x[c].mean(), y[c].mean()] for c in cells])
    return centroid, area


@pytest.mark.parametrize("k", [2, 3, 4, 6, 7, 8, 13])
def test_parts_are_the_centroids_of_equal_areas(k):
    """The closed-form centroids against a 1201^2 grid (its error ~1e-3), equal areas."""
    offsets, rho = subaperture_pattern(k)
    centroid, area = _numerical_parts(k)
    np.testing.assert_allclose(area, 1.0 / k, atol=2e-3)
    np.testing.assert_allclose(offsets, centroid, atol=3e-3)
    # the residual keeps the disc's second moment (1/2): the parts' spread about their
    # centroids, from the grid, is rho^2 / 2 (a disc of radius rho)
    spread = 0.5 - np.mean(np.sum(centroid ** 2, axis=1))
    assert rho ** 2 / 2 == pytest.approx(spread, abs=3e-3)


def test_one_part_is_the_whole_lens_and_bad_counts_are_refused():
    offsets, rho = subaperture_pattern(1)
    assert rho == 1.0 and offsets.tolist() == [[0.0, 0.0]]
    for bad in (0, 65):
        with pytest.raises(ValueError):
            subaperture_pattern(bad)
    for bad in (0, 65, 2.5, True):
        with pytest.raises(DofsplatError):
            ds.RenderSettings(lens_samples=bad)


def test_second_moments_of_apertures():
    """Disc 1/2; a regular n-gon of circumradius 1 against a grid; the paper's Gaussian."""
    assert aperture_second_moment("disc", 0) == 0.5
    assert aperture_second_moment("gaussian", 0) == pytest.approx(2.0 / (2.0 * math.log(4.0)))
    n = 6
    g = (np.arange(1001) + 0.5) / 1001 * 2 - 1
    x, y = np.meshgrid(g, g)
    apothem = math.cos(math.pi / n)
    angles = (np.arange(n) + 0.5) * 2 * math.pi / n  # edge normals, first vertex at 0 deg
    inside = np.all([x * math.cos(a) + y * math.sin(a) <= apothem for a in angles], axis=0)
    assert aperture_second_moment("disc", n) == pytest.approx(
        np.mean((x * x + y * y)[inside]), abs=2e-3)


def test_a_frame_in_parts_is_the_mean_of_its_parts():
    """Slow twin: the K-part frame equals K one-pass frames, each from its part's camera
    (camera.lens_camera) with the residual lens, shaded once from the lens centre, averaged
    (no LOD, so every frame splats the same surfels): equal to float32 rounding."""
    s, cam, lens = demo.contact_scene(96, 72)
    lens = ds.ThinLens(focus_distance=lens.focus_distance, aperture=0.3)
    settings = ds.RenderSettings(lod=False, lens_samples=4)
    ours = ds.render(s, cam, lens, settings)
    assert ours.stats["lens_samples"] == 4
    offsets, rho = subaperture_pattern(4)
    shaded = dataclasses.replace(s, colors=shade_surfels(s, cam, settings))
    one = dataclasses.replace(settings, lens_samples=1, shading="none")
    a = effective_diameter(cam, lens)
    twin = np.mean([ds.render(shaded, lens_camera(cam, 0.5 * a * u, lens.focus_distance),
                              ResidualLens(lens, rho), one).image for u in offsets], axis=0)
    np.testing.assert_allclose(ours.image, twin, atol=2e-6)


def test_parts_keep_each_splats_area():
    """A lone out-of-focus surfel deposits its area whatever K (each part is normalised),
    so the image's total coverage is the one-pass frame's to 1 %."""
    s = ds.Surfels(positions=[[0, 0, 0]], normals=[[0, 0, 1]], radius=[0.01], colors=[[1, 1, 1]])
    cam = ds.Camera(eye=(0, 0, 2), target=(0, 0, 0), width=64, height=64, fov_y=30)
    lens = ds.ThinLens(focus_distance=1.0, aperture=0.2)
    total = [ds.render(s, cam, lens, ds.RenderSettings(shading="none", lod=False,
                                                       lens_samples=k)).alpha.sum()
             for k in (1, 4, 7)]
    assert total[1] == pytest.approx(total[0], rel=0.01)
    assert total[2] == pytest.approx(total[0], rel=0.01)


@pytest.fixture(scope="module")
def contact_blurred():
    """The contact scene at 192 x 144, aperture 0.3 (a largest CoC of ~19 px), and its
    32-sample reference: (surfels, camera, lens, reference image)."""
    s, cam, lens = demo.contact_scene(192, 144)
    lens = ds.ThinLens(focus_distance=lens.focus_distance, aperture=0.3)
    ref = render_reference(s, cam, lens, ds.RenderSettings(), samples=32, progress=False).image
    return s, cam, lens, ref


@pytest.mark.parametrize("lod", [True, False], ids=["lod", "no-lod"])
def test_contact_seam_is_closer_to_the_reference_in_parts(lod, contact_blurred):
    """Spheres resting on a checkered floor (the fidelity suite's contact scene) at 192 x 144,
    a largest CoC of ~19 px, against the 32-sample reference. One pass merges or separates
    the blurred sphere and the floor wholesale (the seam) and, with LOD, blurs the checks
    twice; 4 parts measured 5.9 dB (LOD) and 4.0 dB (no LOD) closer (32 samples; 7.0 and
    5.2 before one pass removed what is hidden from the whole lens). The bound, 3 dB, is
    under both; one pass is 0 dB better than itself, so it fails there."""
    s, cam, lens, ref = contact_blurred
    psnr = {k: compare(ds.render(s, cam, lens, ds.RenderSettings(lens_samples=k, lod=lod)).image,
                       ref)["psnr"] for k in (1, 4)}
    assert psnr[4] >= psnr[1] + 3.0, psnr


def test_pinholes_and_dof_off_are_one_pass():
    s, cam, lens = demo.contact_scene(48, 36)
    settings = ds.RenderSettings(lens_samples=4)
    assert ds.render(s, cam, None, settings).stats["lens_samples"] == 1
    assert ds.render(s, cam, lens, dataclasses.replace(settings, dof=False)).stats["lens_samples"] == 1
    assert ds.render(s, cam, lens, dataclasses.replace(settings, show_lod=True)).stats["lens_samples"] == 1


def test_cli_lens_samples(tmp_path, capsys):
    out = tmp_path / "d.png"
    assert main(["demo", "--size", "64x48", "--lens-samples", "4", "-o", str(out),
                 "--stats", str(tmp_path / "d.json")]) == 0
    assert out.exists()
    import json
    assert json.loads((tmp_path / "d.json").read_text())["settings"]["lens_samples"] == 4
    assert main(["demo", "--size", "64x48", "--lens-samples", "0", "-o",
                 str(tmp_path / "x.png")]) == 2
    assert "lens samples must be 1..64" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


# -- the parts where needed (RenderSettings.lens_parts = "needed") ---------------------------


def test_keep_tiles_and_keep_tile_lists_equal_their_numpy_twins():
    """abuffer.keep_tiles drops a splat exactly when its box's tiles (clipped to the map)
    meet no kept tile; keep_tile_lists empties the other tiles' lists, order kept."""
    from dofsplat.raster.abuffer import TILE, bin_splats, keep_tile_lists, keep_tiles

    rng = np.random.default_rng(3)
    n, n_ty, n_tx = 400, 6, 8
    x0 = rng.integers(-20, n_tx * TILE, n)
    y0 = rng.integers(-20, n_ty * TILE, n)
    bbox = np.stack([x0, x0 + rng.integers(0, 60, n), y0, y0 + rng.integers(0, 60, n)],
                    1).astype(np.int32)
    bbox[:, [0, 2]] = np.maximum(bbox[:, [0, 2]], 0)
    visible = rng.random(n) < 0.8
    tiles = rng.random((n_ty, n_tx)) < 0.3
    twin = visible.copy()
    for k in np.flatnonzero(visible):
        ty = slice(bbox[k, 2] // TILE, min(bbox[k, 3] // TILE, n_ty - 1) + 1)
        tx = slice(bbox[k, 0] // TILE, min(bbox[k, 1] // TILE, n_tx - 1) + 1)
        twin[k] = tiles[ty, tx].any()
    kept = visible.copy()
    keep_tiles(bbox, kept, tiles)
    np.testing.assert_array_equal(kept, twin)
    assert 0 < kept.sum() < visible.sum()
    bbox[:, 1] = np.minimum(bbox[:, 1], n_tx * TILE - 1)
    bbox[:, 3] = np.minimum(bbox[:, 3], n_ty * TILE - 1)
    offsets, ids = bin_splats(bbox, visible, n_tx, 0, n_ty)
    o2, i2 = keep_tile_lists(offsets, ids, tiles.reshape(-1))
    for t, keep in enumerate(tiles.reshape(-1)):
        want = ids[offsets[t]:offsets[t + 1]] if keep else []
        np.testing.assert_array_equal(i2[o2[t]:o2[t + 1]], want)


def test_parts_where_needed_over_one_surface_is_the_one_pass():
    """A blurred plane facing the camera, alone: no pixel holds two surfaces, so no tile is
    drawn in parts and the frame is the one pass's, bit for bit (the parts are never
    drawn)."""
    s = demo.textured_plane(64, 1.0)
    cam = ds.Camera(eye=(0.0, 0.0, 2.0), target=(0, 0, 0), width=96, height=72, fov_y=40)
    lens = ds.ThinLens(focus_distance=1.5, aperture=0.3)
    needed = ds.render(s, cam, lens, ds.RenderSettings(lens_samples=4, lens_parts="needed"))
    one = ds.render(s, cam, lens, ds.RenderSettings())
    assert needed.stats["parts_tiles"] == 0.0
    np.testing.assert_array_equal(needed.image, one.image)


def test_parts_where_needed_draws_the_contact_as_the_parts_do(contact_blurred):
    """Spheres on a floor (the contact scene), 192 x 144, a largest CoC of ~19 px: the
    doubtful tiles (two surfaces in a pixel: 34 % of them) are drawn in parts and blended,
    the rest in one pass. Against the 32-sample reference (measured: one pass 44.26, parts
    49.02, needed 49.00 dB) the bounds ask for the parts' score less 1 dB, and 1.5 dB over
    one pass: a frame drawn in one pass fails both."""
    s, cam, lens, ref = contact_blurred
    frames = {name: ds.render(s, cam, lens, ds.RenderSettings(**kw)) for name, kw in (
        ("one", {}), ("parts", {"lens_samples": 4}),
        ("needed", {"lens_samples": 4, "lens_parts": "needed"}))}
    psnr = {k: compare(f.image, ref)["psnr"] for k, f in frames.items()}
    assert 0.2 < frames["needed"].stats["parts_tiles"] < 0.5
    assert psnr["needed"] >= psnr["parts"] - 1.0, psnr
    assert psnr["needed"] >= psnr["one"] + 1.5, psnr


def test_lens_parts_is_validated_and_on_the_command_line(tmp_path):
    with pytest.raises(DofsplatError, match="lens_parts must be one of everywhere, needed"):
        ds.RenderSettings(lens_parts="some")
    import json
    out = tmp_path / "d.png"
    assert main(["demo", "--size", "64x48", "--lens-samples", "4", "--lens-parts", "needed",
                 "-o", str(out), "--stats", str(tmp_path / "d.json")]) == 0
    assert json.loads((tmp_path / "d.json").read_text())["settings"]["lens_parts"] == "needed"


def test_a_lone_point_keeps_the_apertures_shape_with_the_parts_where_needed():
    """A lone out-of-focus surfel drawn in 4 parts shows 4 lobes; with the parts where
    needed it holds one surface everywhere, so it is the one pass's disc (or hexagon), bit
    for bit: issue 49's bokeh."""
    s = ds.Surfels(positions=[[0, 0, 0]], normals=[[0, 0, 1]], radius=[0.01], colors=[[1, 1, 1]])
    cam = ds.Camera(eye=(0, 0, 2), target=(0, 0, 0), width=64, height=64, fov_y=30)
    for blades in (0, 6):
        lens = ds.ThinLens(focus_distance=1.0, aperture=0.2, blades=blades)
        base = ds.RenderSettings(shading="none", lod=False)
        one = ds.render(s, cam, lens, base)
        parts = ds.render(s, cam, lens, dataclasses.replace(base, lens_samples=4))
        needed = ds.render(s, cam, lens, dataclasses.replace(base, lens_samples=4,
                                                            lens_parts="needed"))
        np.testing.assert_array_equal(needed.image, one.image)
        # the lobes differ from the disc by 28 % (round) and 35 % (hexagon) of its peak
        # alpha: the test can fail
        alpha = one.image[..., 3]
        assert np.abs(parts.image[..., 3] - alpha).max() > 0.15 * alpha.max()
