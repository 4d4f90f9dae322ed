"""The post-process baseline (dofsplat.postfilter): kernel against its twin, its properties
and its artefacts, and ``--method postfilter``. Its score against the reference is in
test_reference.py."""

import json
import math

import numpy as np
import pytest

import dofsplat as ds
from dofsplat.cli import main
from dofsplat.io import read_image
from dofsplat.postfilter import (coc_radius_map, postfilter, postfilter_slow,
                                 render_postfilter)

from conftest import front_camera, grid_surfels


def random_frame(h=24, w=30, seed=0):
    rng = np.random.default_rng(seed)
    image = rng.random((h, w, 4)).astype(np.float32)
    depth = rng.uniform(0.5, 4.0, (h, w)).astype(np.float32)
    depth[:3, :5] = np.inf  # empty pixels: the background at infinity
    return image, depth


@pytest.mark.parametrize("depth_test, blades", [(True, 0), (False, 0), (True, 5), (False, 6)])
def test_kernel_matches_its_numpy_twin(depth_test, blades):
    from dofsplat.splat.bokeh import blade_normals

    image, depth = random_frame()
    coc_k, inv_focus = 6.0, 1.0 / 1.5  # radii from 0.5 to 8 px
    normals = blade_normals(blades, 10.0)
    fast = postfilter(image, depth, coc_k, inv_focus, depth_test=depth_test, blades=normals)
    slow = postfilter_slow(image, depth, coc_k, inv_focus, depth_test=depth_test,
                           blades=normals)
    np.testing.assert_allclose(fast, slow, atol=2e-6)  # float32 output of float64 sums


def test_no_blur_leaves_the_image_as_it_was():
    image, depth = random_frame()
    np.testing.assert_allclose(postfilter(image, depth, 0.0, 0.0), image, rtol=1e-6)
    # in focus everywhere: a depth equal to the focus distance
    flat = np.full(depth.shape, 2.0, np.float32)
    np.testing.assert_allclose(postfilter(image, flat, 10.0, 0.5), image, rtol=1e-6)


def test_a_constant_image_stays_constant():
    """The gather is normalised: whatever the depths, a flat colour stays that colour."""
    _, depth = random_frame()
    image = np.broadcast_to(np.float32([0.2, 0.5, 0.7, 1.0]), depth.shape + (4,)).copy()
    for depth_test in (True, False):
        np.testing.assert_allclose(postfilter(image, depth, 8.0, 0.5, depth_test=depth_test),
                                   image, rtol=1e-6)


def test_a_point_at_constant_depth_spreads_over_its_coc():
    """One bright pixel on a fronto-parallel plane becomes a flat disc of radius C_r that
    keeps its energy (within 2 %: the pixel grid against the disc's area pi r^2 + pi/12)."""
    h = w = 41
    depth = np.full((h, w), 4.0, np.float32)
    coc_k, inv_focus = 6.0 / (1.0 - 0.25), 1.0  # C_r(4) = 6 px
    assert coc_radius_map(depth, coc_k, inv_focus)[0, 0] == pytest.approx(6.0)
    image = np.zeros((h, w, 4), np.float32)
    image[20, 20] = 1.0
    out = postfilter(image, depth, coc_k, inv_focus)[..., 0]
    assert out.sum() == pytest.approx(1.0, rel=0.02)
    yy, xx = np.indices((h, w))
    d = np.hypot(yy - 20, xx - 20)
    assert out[d >= 6.5].max() == 0.0  # nothing beyond the antialiased edge
    inside = out[d <= 5.5]
    assert inside.max() / inside.min() < 1.05  # flat: Chen's uniform CoC


def two_halves(focus_left: bool):
    """Left: an object at depth 1 (red); right: a background at depth 5 (green)."""
    h, w = 20, 40
    image = np.zeros((h, w, 4), np.float32)
    image[:, :20] = (1.0, 0.0, 0.0, 1.0)
    image[:, 20:] = (0.0, 1.0, 0.0, 1.0)
    depth = np.full((h, w), 5.0, np.float32)
    depth[:, :20] = 1.0
    focus = 1.0 if focus_left else 5.0
    coc_k = 8.0 / abs(1.0 / 5.0 - 1.0) if focus_left else 8.0 / abs(1.0 - 1.0 / 5.0)
    return image, depth, coc_k, 1.0 / focus


def test_the_depth_test_stops_a_blurred_background_leaking_onto_a_sharp_object():
    image, depth, coc_k, inv_focus = two_halves(focus_left=True)  # background C_r = 8 px
    kept = postfilter(image, depth, coc_k, inv_focus, depth_test=True)
    np.testing.assert_allclose(kept[:, :20], image[:, :20], atol=1e-6)
    leaked = postfilter(image, depth, coc_k, inv_focus, depth_test=False)
    assert leaked[:, 19, 1].min() > 0.1  # green on the sharp red object: intensity leakage


def test_no_partial_occlusion_the_blurred_objects_rim_stays_opaque():
    """A blurred object in front of a sharp background spreads outwards only: inside its
    silhouette it stays its own colour, where a lens would show the background through it."""
    image, depth, coc_k, inv_focus = two_halves(focus_left=False)  # object C_r = 8 px
    out = postfilter(image, depth, coc_k, inv_focus)
    np.testing.assert_allclose(out[:, :20, :3], image[:, :20, :3], atol=1e-6)
    assert out[:, 20, 0].min() > 0.1  # outside, the object's blur does cover the background


def test_clamped_radii_warn_and_mistakes_raise():
    image, depth = random_frame()
    with pytest.warns(UserWarning, match="clamps CoC radii"):
        postfilter(image, depth, 100.0, 1.0, max_radius=4.0)
    with pytest.raises(ds.DofsplatError, match="depth has shape"):
        postfilter(image, depth[:, :-1], 1.0, 1.0)
    with pytest.raises(ds.DofsplatError, match="NaN"):
        postfilter(np.full_like(image, np.nan), depth, 1.0, 1.0)
    with pytest.raises(ds.DofsplatError, match="max_radius"):
        postfilter(image, depth, 1.0, 1.0, max_radius=0.0)


def test_render_postfilter_is_the_filtered_pinhole_render():
    scene = grid_surfels(n=32, spacing=1.0 / 32)
    cam = front_camera(48, 48, distance=2.0)
    lens = ds.ThinLens(focus_distance=1.2, aperture=0.1)
    settings = ds.RenderSettings(lod=False)
    pinhole = ds.render(scene, cam, None, settings)
    got = render_postfilter(scene, cam, lens, settings)
    k, inv_p = lens.coc_coefficients(cam)
    np.testing.assert_array_equal(got.image, postfilter(pinhole.image, pinhole.depth, k, inv_p))
    np.testing.assert_array_equal(got.depth, pinhole.depth)
    assert got.stats["method"] == "postfilter"
    # the empty background counts as infinitely far: C_r = K/P there
    assert got.stats["max_coc_px"] == pytest.approx(k * inv_p, rel=1e-6)
    assert got.stats["total_ms"] >= got.stats["filter_ms"]
    # no lens: the pinhole image
    np.testing.assert_allclose(render_postfilter(scene, cam, None, settings).image,
                               pinhole.image, rtol=1e-6)


def test_cli_method_postfilter(tmp_path, capsys):
    out, stats = tmp_path / "pf.npy", tmp_path / "pf.json"
    assert main(["demo", "--size", "64x48", "--method", "postfilter", "-o", str(out),
                 "--stats", str(stats), "-q"]) == 0
    assert read_image(out).shape == (48, 64, 4)
    record = json.loads(stats.read_text())
    assert record["method"] == "postfilter" and record["filter_ms"] >= 0
    assert math.isfinite(record["max_coc_px"])
    assert main(["demo", "--size", "64x48", "--method", "blur", "-o", str(out)]) == 2
    assert "invalid choice" in capsys.readouterr().err


def test_polygon_postfilter_spreads_a_point_into_a_hexagon():
    """One bright pixel at a CoC of 12 px through 6 blades: a hexagon, whose radius at its
    edges is cos 30 = 0.87 of that at its vertices, and whose weights sum as the disc's."""
    from dofsplat.splat.bokeh import blade_normals

    image = np.zeros((41, 41, 4), np.float32)
    image[20, 20] = 1.0
    depth = np.full((41, 41), 3.0, np.float32)
    coc_k, inv_focus = 24.0, 1.0  # r = 24 |1/3 - 1| = 16 px
    depth[20, 20] = 2.0  # r = 12 px for the bright pixel (behind: no depth-test cut)
    out = postfilter(image, depth, coc_k, inv_focus, blades=blade_normals(6, 0.0))[..., 0]
    lit = out > 0.5 * out[20, 20]
    ys, xs = np.nonzero(lit)
    vertex = np.abs(xs - 20).max()  # a vertex on the x axis at rotation 0
    edge = np.abs(ys - 20).max()  # an edge across the y axis
    # the extents are whole pixels: the vertex at the CoC, 12 px, the edge at the largest
    # whole pixel inside 12 cos 30 = 10.39 (abs=0.1 on the ratio let a disc's 11 pass)
    assert (vertex, edge) == (12, math.floor(12 * math.cos(math.pi / 6)))
