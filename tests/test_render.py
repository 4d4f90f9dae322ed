"""Whole-frame rendering: coverage, partial occlusion, transparency, parity with the twins."""

import dataclasses
import math
import os
import subprocess
import sys

import numba
import numpy as np
import pytest

import dofsplat as ds
from dofsplat.render import project, shade_surfels
from dofsplat.slow import (aperture_shape_reference, merge_parameters_reference,
                           project_reference, rasterize_reference, render_reference)
from dofsplat.surfels import concatenate

from conftest import front_camera, grid_surfels

UNLIT = ds.RenderSettings(shading="none", lod=False)


def interior(a, margin):
    return a[margin:-margin, margin:-margin]


def test_grid_in_focus_has_unit_coverage_and_exact_colour():
    """radius = spacing: interior weights 1 +- 0.1 (Section 6.3's target), so coverage 1
    (abuffer.layer_alpha), and the exact colour."""
    color = np.array([0.6, 0.3, 0.2])
    s = grid_surfels(n=48, spacing=1.0 / 48, color=color)
    cam = front_camera(96, 96, distance=2.5)
    res = ds.render(s, cam, None, UNLIT)
    # the grid spans pixels 21.5 to 74.5: keep well inside it
    w = interior(res.weight, 28)
    assert np.all(np.abs(w - 1) < 0.1)
    # a sum within Section 6.3's 10 % of 1 covers the pixel (abuffer.layer_alpha: nothing
    # behind a sharp opaque surface shows through its kernels' ripple)
    cov = interior(res.alpha, 28)
    assert cov.min() == 1.0
    # over a black background the un-premultiplied colour is the surfel colour exactly
    rgb = interior(res.rgb, 28) / cov[..., None]
    np.testing.assert_allclose(rgb, np.broadcast_to(color, rgb.shape), rtol=1e-5)
    # and outside the model: nothing
    assert res.alpha[:4].max() == 0 and np.isinf(res.depth[:4]).all()


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy's overflow in its area
@pytest.mark.parametrize("aperture", [0.0, 0.1])
def test_a_splat_too_wide_to_store_is_dropped_not_a_crash(aperture):
    """A surfel of radius 1e30 before the camera (a damaged file): its conic underflowed
    float32 and the front pass divided by zero (a segmentation fault in the command line).
    It is dropped (ewa.MAX_SPLAT_VARIANCE), in the kernels and in their slow twin alike, and
    the grid beside it renders as without it."""
    grid = grid_surfels(16, 1.0 / 16)
    huge = dataclasses.replace(grid_surfels(1, 1.0, z=0.1), radius=np.full(1, 1e30, np.float32))
    cam = front_camera(48, 48)
    lens = ds.ThinLens(focus_distance=2.0, aperture=aperture) if aperture else None
    st = ds.RenderSettings(lod=False)
    both = concatenate([grid, huge])
    fast = project(both, shade_surfels(both, cam, st), cam, lens, st)
    slow = project_reference(both, shade_surfels(both, cam, st), cam, lens, st)
    assert not fast[2][-1] and not slow[2][-1] and fast[2][:-1].all()
    for lod in (False, True):
        settings = dataclasses.replace(st, lod=lod)
        alone = ds.render(grid, cam, lens, settings).image
        np.testing.assert_array_equal(ds.render(both, cam, lens, settings).image, alone)


def test_a_sharp_opaque_plane_hides_the_plane_behind_it():
    """The sum of a sharp plane's kernels ripples between its splats (the grid above: down
    to 0.978 inside); with min(1, w) as its opacity a second plane 0.1 behind it showed
    through by that much (colours off by up to 0.015). abuffer.layer_alpha
    counts a sharp opaque surface's sum from COVER_FULL up as covering: the front colour exactly
    (float32's 1e-6)."""
    front = grid_surfels(n=48, spacing=1.0 / 48, color=(0.8, 0.1, 0.1))
    rear = grid_surfels(n=48, spacing=1.0 / 48, z=-0.1, color=(0.1, 0.8, 0.1))
    res = ds.render(concatenate([front, rear]), front_camera(96, 96, distance=2.5), None, UNLIT)
    np.testing.assert_allclose(interior(res.rgb, 28), 0 * interior(res.rgb, 28) + (0.8, 0.1, 0.1),
                               atol=1e-6)


def test_a_plane_hidden_beyond_the_frame_edge_stays_hidden():
    """Two planes 0.03 apart, both blurred by a CoC of 9.4 px (parallax 0.17 px: one layer
    through the lens), larger than the frame. The rear one is hidden from the whole lens and
    removed (abuffer.splat_visibility); its splats beyond the frame's edge, whose blur
    reaches in, used to be kept (their sample points fell off the front map) and merged
    into the front: green up to 0.39 in the corners and 0.135 inside, where the front's
    colour has 0.1. The front map now goes on at the edge as it is there: the front's
    colour exactly (float32's 1e-6)."""
    front = grid_surfels(n=160, spacing=1.0 / 48, color=(0.8, 0.1, 0.1))
    rear = grid_surfels(n=160, spacing=1.0 / 48, z=-0.03, color=(0.1, 0.8, 0.1))
    lens = ds.ThinLens(focus_distance=1.5, aperture=0.8)
    res = ds.render(concatenate([front, rear]), front_camera(64, 64, distance=2.5), lens, UNLIT)
    assert res.alpha.min() > 0.9999
    np.testing.assert_allclose(res.rgb / res.alpha[..., None], 0 * res.rgb + (0.8, 0.1, 0.1),
                               atol=1e-6)


def checker_plane(n=64, spacing=1.0 / 32, z=0.0):
    s = grid_surfels(n=n, spacing=spacing, z=z)
    ij = np.indices((n, n)).reshape(2, -1)
    check = ((ij[0] // 4 + ij[1] // 4) % 2).astype(np.float32)
    s.colors[:] = np.stack([check, 1 - check, 0.2 * np.ones_like(check)], axis=1)
    return s


def test_blurred_occluder_lets_the_sharp_plane_show_through_its_rim():
    """Partial occlusion: at the blurred rim the far plane is seen, unblurred, behind the occluder.

    Each pixel must be the "over" of the occluder (rendered alone) onto the plane (alone):
    the A-buffer keeps the two surfaces apart, so nothing of one leaks into the other.
    """
    cam = front_camera(96, 96, distance=2.0)
    lens = ds.ThinLens(focus_distance=2.0, aperture=0.3)  # plane at z=0 in focus
    plane = checker_plane()
    occluder = grid_surfels(n=12, spacing=1.0 / 48, z=1.0, color=(0.1, 0.1, 0.9))
    both = ds.render(concatenate([plane, occluder]), cam, lens, UNLIT)
    plane_only = ds.render(plane, cam, lens, UNLIT)
    occ_only = ds.render(occluder, cam, lens, UNLIT)
    assert lens.coc_radius_px(1.0, cam) > 8  # the occluder really is blurred
    a = occ_only.alpha[..., None]
    expected = occ_only.rgb + (1 - a) * plane_only.rgb  # premultiplied occluder over plane
    rim_and_beyond = occ_only.alpha < 0.95
    np.testing.assert_allclose(both.rgb[rim_and_beyond], expected[rim_and_beyond], atol=2e-3)
    # inside, where the occluder hides the plane from the whole lens, the plane's splats are
    # removed (abuffer.splat_visibility): the plane's share, (1 - a) x plane, may be missing
    # (measured: pixels of alpha 0.97 and more differ, by up to 0.004)
    assert np.all(np.abs(both.rgb - expected) <= (1 - a) * plane_only.rgb + 2e-3)
    rim = (occ_only.alpha > 0.2) & (occ_only.alpha < 0.8)
    assert rim.sum() > 100
    # in the rim the plane's checker (red/green) is clearly visible through the occluder
    assert (both.rgb[rim][:, 0] - both.rgb[rim][:, 1]).std() > 0.1


def test_sharp_object_over_blurred_plane_keeps_its_colour():
    """No intensity leakage: the blurred background never bleeds into a sharp foreground."""
    cam = front_camera(96, 96, distance=2.0)
    lens = ds.ThinLens(focus_distance=1.0, aperture=0.3)  # focus on the near square
    plane = checker_plane()
    color = np.array([0.1, 0.2, 0.9])
    near = grid_surfels(n=24, spacing=1.0 / 48, z=1.0, color=color)
    res = ds.render(concatenate([plane, near]), cam, lens, UNLIT)
    assert lens.coc_radius_px(2.0, cam) > 8  # the plane really is blurred
    inner = ds.render(near, cam, lens, UNLIT).alpha >= 1.0  # full coverage of the near square
    assert inner.sum() > 400
    np.testing.assert_allclose(res.rgb[inner], np.broadcast_to(color, (inner.sum(), 3)), atol=1e-6)


def test_half_transparent_plane_over_opaque_plane_is_over():
    cam = front_camera(64, 64, distance=2.0)
    front = grid_surfels(n=40, spacing=1.0 / 40, z=0.5, color=(0.9, 0.1, 0.1), opacity=0.5)
    back = grid_surfels(n=64, spacing=1.0 / 32, z=0.0, color=(0.1, 0.1, 0.9))
    bg = (0.2, 0.2, 0.2)
    settings = ds.RenderSettings(shading="none", background=bg, lod=False)
    both = ds.render(concatenate([front, back]), cam, None, settings)
    f = ds.render(front, cam, None, ds.RenderSettings(shading="none", lod=False))  # over black: premultiplied
    b = ds.render(back, cam, None, settings)
    expected = f.rgb + (1 - f.alpha[..., None]) * b.rgb
    np.testing.assert_allclose(both.rgb, expected, atol=1e-5)
    centre = interior(f.alpha, 24)
    assert np.all(np.abs(centre - 0.5) < 0.05)  # coverage 1 +- 0.1 times opacity 0.5
    c = both.rgb[32, 32]
    np.testing.assert_allclose(c, 0.5 * np.array([0.9, 0.1, 0.1]) + 0.5 * np.array([0.1, 0.1, 0.9]),
                               atol=0.05)


def random_scene(seed, n=250, elliptical=False):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-1, 1, (n, 3)) * [1.0, 0.8, 0.6]
    nrm = rng.normal(size=(n, 3))
    nrm[:, 2] = np.abs(nrm[:, 2]) + 0.2
    kw = {}
    if elliptical:
        kw = dict(tangent=rng.normal(size=(n, 3)), radius_v=rng.uniform(0.01, 0.1, n))
    return ds.Surfels(positions=pos, normals=nrm, radius=rng.uniform(0.02, 0.15, n),
                      colors=rng.uniform(0, 1, (n, 3)), opacity=rng.uniform(0.2, 1, n), **kw)


@pytest.mark.parametrize("seed, elliptical, aperture, cull, shading, sharp", [
    (0, False, 0.0, True, "phong", False),
    (1, False, 0.4, True, "none", False),
    (2, True, 0.25, False, "phong", False),
    (3, True, 0.0, False, "none", False),
    (4, False, 0.0, False, "none", True),
])
def test_kernels_equal_their_numpy_twins(seed, elliptical, aperture, cull, shading, sharp):
    """Projection, rasterisation and the whole frame against the slow twins, within 1e-4."""
    s = random_scene(seed, elliptical=elliptical)
    if sharp:  # opaque: the front pass looks at opaque disks only
        s = dataclasses.replace(s, opacity=np.ones(len(s)))
    cam = ds.Camera(eye=(0.3, 0.2, 4), target=(0, 0, 0), width=56, height=40, fov_y=35)
    lens = ds.ThinLens(focus_distance=3.6, aperture=aperture) if aperture else None
    st = ds.RenderSettings(background=(0.1, 0.2, 0.3), cull_backfaces=cull, shading=shading, lod=False,
                           sharp_visibility=sharp)
    rgb = shade_surfels(s, cam, st)
    fast = project(s, rgb, cam, lens, st)
    slow = project_reference(s, rgb, cam, lens, st)
    np.testing.assert_array_equal(fast[2], slow[2])
    vis = fast[2]
    assert vis.sum() > 50
    np.testing.assert_allclose(fast[0][vis], slow[0][vis], rtol=1e-4, atol=1e-6)
    np.testing.assert_array_equal(fast[1][vis], slow[1][vis])
    # rasteriser on identical input
    res = ds.render(s, cam, lens, st)
    img, depth, weight, frags = rasterize_reference(
        *fast, cam.width, cam.height, st.cutoff, st.background,
        merge=merge_parameters_reference(cam, lens, st),
        blades=aperture_shape_reference(lens, st)[1], sharp_visibility=sharp,
        coarse=st.coarse_blur_px)
    np.testing.assert_allclose(res.image, img, atol=1e-4)
    if sharp:  # the front pass removed something, or the case tests nothing new
        plain = ds.render(s, cam, lens, dataclasses.replace(st, sharp_visibility=False))
        assert np.abs(plain.image - res.image).max() > 1e-3
    np.testing.assert_allclose(res.weight, weight, atol=1e-4)
    np.testing.assert_array_equal(np.isinf(res.depth), np.isinf(depth))
    fin = np.isfinite(depth)
    np.testing.assert_allclose(res.depth[fin], depth[fin], rtol=1e-4)
    assert res.stats["fragments"] == frags
    # and the all-twin pipeline
    img2 = render_reference(s, cam, lens, st)[0]
    np.testing.assert_allclose(res.image, img2, atol=1e-4)


def deep_scene(seed, n=120):
    """Surfels spread 3.2 units in depth before a camera 4 units away, half of them opaque
    and half translucent (opacity 0.2-0.9): focused at 3, an aperture of 8 blurs them by
    circles of confusion of 0.4 to 36 px (median 18), so nearly every splat is drawn with
    the aperture's kernel, and a few lie within SMALL_APERTURE of the kernel's sigma."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-1, 1, (n, 3)) * [0.9, 0.7, 1.6]
    nrm = rng.normal(size=(n, 3))
    nrm[:, 2] = np.abs(nrm[:, 2]) + 0.5
    opacity = np.where(rng.uniform(size=n) < 0.5, 1.0, rng.uniform(0.2, 0.9, n))
    return ds.Surfels(positions=pos, normals=nrm, radius=rng.uniform(0.03, 0.12, n),
                      colors=rng.uniform(0, 1, (n, 3)), opacity=opacity)


def stacked_floors(n=20, gap=0.4):
    """Two opaque floors (y = 0 and y = gap, normals +y) seen from above at 60 degrees: the
    upper one hides the lower one at every point of 40 % of its disks, some (CoC + 1) |g|
    behind it (|g|, the depth change per pixel along the floor, 0.025-0.047), where the
    front pass's MERGE_REACH decides whether a hidden splat is looked at through the lens."""
    from dofsplat.surfels import concatenate

    to_floor = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # z -> y
    floors = []
    for y, color in ((0.0, (0.1, 0.3, 0.8)), (gap, (0.8, 0.2, 0.1))):
        s = grid_surfels(n=n, spacing=1.6 / n, color=color, z=y)
        floors.append(dataclasses.replace(s, positions=s.positions @ to_floor.T,
                                          normals=s.normals @ to_floor.T))
    return concatenate(floors)


def twin_frame(s, cam, lens, st):
    """The frame of the kernels against the slow twins' (slow.py, its own constants,
    tables and frame parameters): the projected splats to rtol 1e-4 (float32 rows), the
    same bounding boxes, and the rasteriser's image, weights, depths and fragment count on
    the same splats; the image within 1e-4 (float32 accumulation; measured 1e-7 to 1e-6)."""
    rgb = shade_surfels(s, cam, st)
    fast = project(s, rgb, cam, lens, st)
    slow = project_reference(s, rgb, cam, lens, st)
    np.testing.assert_array_equal(fast[2], slow[2])
    vis = fast[2]
    np.testing.assert_allclose(fast[0][vis], slow[0][vis], rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(fast[1][vis], slow[1][vis])
    res = ds.render(s, cam, lens, st)
    img, depth, weight, frags = rasterize_reference(
        *fast, cam.width, cam.height, st.cutoff, st.background,
        merge=merge_parameters_reference(cam, lens, st),
        blades=aperture_shape_reference(lens, st)[1], coarse=st.coarse_blur_px)
    np.testing.assert_allclose(res.image, img, atol=1e-4)
    np.testing.assert_allclose(res.weight, weight, atol=1e-4)
    fin = np.isfinite(depth)
    np.testing.assert_array_equal(np.isfinite(res.depth), fin)
    np.testing.assert_allclose(res.depth[fin], depth[fin], rtol=1e-4)
    assert res.stats["fragments"] == frags
    return fast, res


@pytest.mark.parametrize("blades", [0, 6])
def test_aperture_kernels_equal_their_numpy_twins(blades):
    """Real aperture kernels (splat/bokeh.py) against the twins: circles of confusion of
    0.4-36 px, 119 of the 120 splats drawn with the disc or the hexagon (the frames of
    ``test_kernels_equal_their_numpy_twins`` reach 0.78 px and draw none), half of them
    translucent. SMALL_APERTURE of 4 instead of 1 moves the image by 0.05 here."""
    from dofsplat.splat.project import COC, RAD

    cam = ds.Camera(eye=(0.3, 0.2, 4), target=(0, 0, 0), width=48, height=36, fov_y=35)
    lens = ds.ThinLens(focus_distance=3.0, aperture=8.0, bokeh="disc", blades=blades)
    st = ds.RenderSettings(background=(0.1, 0.2, 0.3), shading="none", lod=False)
    fast, _ = twin_frame(deep_scene(0), cam, lens, st)
    vis = fast[2]
    coc = fast[0][vis, COC]
    assert coc.max() > 30 and np.median(coc) > 10
    assert np.count_nonzero(fast[0][vis, RAD]) >= 0.9 * vis.sum()
    # most drawn from the coarse samples (raster/abuffer.py: coarse_blur_px), some not
    wide = np.abs(fast[0][vis, RAD]) >= st.coarse_blur_px
    assert 0.5 * vis.sum() < wide.sum() < vis.sum()


def test_the_front_pass_reach_equals_its_numpy_twin():
    """Two opaque floors 0.4 apart, blurred by a CoC of up to 2.4 px: the upper one hides
    the lower at every point of many of its disks, where the front pass looks through the
    lens only if the lower surface lies within MERGE_REACH (CoC + 1) |g| of the front's
    reach (``abuffer.splat_visibility``): the fragments and the image against the twins.
    With the twins' MERGE_REACH at 2 instead of 6 the frame keeps splats that 6 removes:
    26,402 fragments instead of 19,738, the image 0.023 apart (measured)."""
    cam = ds.Camera(eye=(0.0, 2.5, 1.5), target=(0, 0, 0), width=40, height=30, fov_y=35)
    lens = ds.ThinLens(focus_distance=3.0, aperture=0.8, bokeh="disc")
    st = ds.RenderSettings(background=(0.1, 0.2, 0.3), shading="none", lod=False)
    twin_frame(stacked_floors(), cam, lens, st)


def test_an_lod_cut_with_aperture_kernels_equals_its_numpy_twin():
    """An LOD cut (nodes with their filter V^q, colour slopes and the taper) drawn with
    aperture kernels of CoC up to 36 px, against the twins."""
    from dofsplat.backends.cpu import select, shade_splats

    s = deep_scene(3, n=400)
    cam = ds.Camera(eye=(0.3, 0.2, 4), target=(0, 0, 0), width=40, height=30, fov_y=35)
    lens = ds.ThinLens(focus_distance=3.0, aperture=8.0, bokeh="disc")
    st = ds.RenderSettings(background=(0.1, 0.2, 0.3), lod_blur_fraction=1.0,
                           lod_color_tolerance=math.inf, lod_min_node=2, taper=True)
    src = select(s, cam, lens, st)
    assert (src.level > 0).sum() > 10  # nodes, not only surfels
    as_surfels = ds.Surfels(positions=src.positions, normals=src.normals, radius=src.ru,
                            colors=src.colors, opacity=src.opacity,
                            weight=src.area / (src.ru * src.rv))
    rgb, gain = shade_splats(src, cam, st)
    fast = project(src, rgb, cam, lens, st, gain=gain)
    slow = project_reference(as_surfels, rgb, cam, lens, st, lod_cov=src.lod_cov,
                             color_grad=src.color_grad, gain=gain)
    np.testing.assert_array_equal(fast[2], slow[2])
    vis = fast[2]
    np.testing.assert_allclose(fast[0][vis], slow[0][vis], rtol=2e-4, atol=1e-5)
    res = ds.render(s, cam, lens, st)
    img = rasterize_reference(*fast, cam.width, cam.height, st.cutoff, st.background,
                              merge=merge_parameters_reference(cam, lens, st),
                              coarse=st.coarse_blur_px)[0]
    np.testing.assert_allclose(res.image, img, atol=1e-4)


def test_the_slow_constants_equal_the_kernels():
    """slow.py writes its constants out (``TWIN_CONSTANTS``) rather than importing them, so
    that a constant changed in a kernel's module fails the twin comparisons; a change made
    on purpose is made in both, and this test names the one forgotten."""
    import importlib

    from dofsplat import slow

    for name, where in slow.TWIN_CONSTANTS.items():
        module, attr = where.split(":")
        assert getattr(importlib.import_module(module), attr) == getattr(slow, name), where


def test_the_slow_aperture_table_is_the_convolution():
    """The twins' aperture table (a Gauss-Legendre quadrature of the Gaussian-disc
    convolution, slow.disc_convolution) against the kernels' (scipy's non-central
    chi-square, bokeh.aperture_table): the same to 1e-12 (measured 7e-15), for three
    cutoffs; its moments and mass table (bokeh.aperture_moments) to 1e-6 (2e-7 absolute). And the
    quadrature itself at points with a closed form: the centre (T = 1), the Gaussian's
    tail far outside the disc, and the disc's edge for a wide disc (1/2)."""
    from dofsplat.slow import (aperture_moments_reference, aperture_table_reference,
                               disc_convolution)
    from dofsplat.splat.bokeh import aperture_moments, aperture_table

    for cutoff in (2.0, 2.5, 4.0):
        np.testing.assert_allclose(aperture_table_reference(cutoff), aperture_table(cutoff),
                                   rtol=0, atol=1e-12)
    # (each integrates the table's rows by the trapezoid rule, on 20001 and 4001 points:
    # 5e-8 apart at most, measured)
    np.testing.assert_allclose(aperture_moments_reference(2.5), aperture_moments(2.5),
                               rtol=1e-6, atol=2e-7)
    assert disc_convolution(-3.0, 3.0) == pytest.approx(1.0, abs=1e-12)  # d = 0
    assert disc_convolution(0.0, 40.0) == pytest.approx(0.5, abs=0.01)  # edge of a wide disc
    # a small disc is a Gaussian: T(d) = exp(-d^2 / 2) as b -> 0
    assert disc_convolution(2.0 - 1e-3, 1e-3) == pytest.approx(math.exp(-2.0), rel=1e-5)


def test_the_slow_frame_parameters_equal_the_kernels():
    """The twins' own frame parameters (merge band, blade normals, aperture variance, taper)
    against frame.py's, for round and polygonal lenses and both reconstructions."""
    from dofsplat.frame import aperture_shape, aperture_variance, kernel_floor, merge_parameters
    from dofsplat.slow import aperture_variance_reference, kernel_floor_reference

    cam = front_camera(32, 24)
    for lens in (None, ds.ThinLens(focus_distance=2.0, aperture=0.3),
                 ds.ThinLens(focus_distance=1.5, aperture=0.2, bokeh="disc", blades=5,
                             blade_rotation=17.0)):
        for st in (ds.RenderSettings(), ds.RenderSettings(reconstruction="paper", taper=True)):
            assert merge_parameters_reference(cam, lens, st) == merge_parameters(cam, lens, st)
            disc, blades, _, _ = aperture_shape(lens, st)
            mine = aperture_shape_reference(lens, st)
            assert mine[0] == disc
            np.testing.assert_allclose(mine[1], blades, atol=1e-15)
            assert aperture_variance_reference(lens) == pytest.approx(aperture_variance(lens),
                                                                      rel=1e-14)
            assert kernel_floor_reference(st) == kernel_floor(st)


@pytest.mark.parametrize("lod", [False, True])
@pytest.mark.parametrize("aperture", [0.3, 2.0])
def test_image_does_not_depend_on_thread_count_or_banding(lod, aperture):
    """The same image from any number of threads and bands; at aperture 2 most splats are
    drawn from the coarse samples, which neighbouring tiles and bands share."""
    s = random_scene(5, n=2000)
    cam = ds.Camera(eye=(0, 0, 4), target=(0, 0, 0), width=96, height=80, fov_y=35)
    lens = ds.ThinLens(focus_distance=3.0, aperture=aperture)
    st = ds.RenderSettings(lod=lod)
    if aperture > 1.0:  # the samples are drawn (the frame is not the fine one)
        fine = ds.render(s, cam, lens, ds.RenderSettings(lod=lod, coarse_blur_px=0.0))
        assert np.abs(fine.image - ds.render(s, cam, lens, st).image).max() > 1e-4
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = ds.render(s, cam, lens, st)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        many = ds.render(s, cam, lens, st)
    finally:
        numba.set_num_threads(before)
    np.testing.assert_array_equal(one.image, many.image)
    banded = ds.render(s, cam, lens, ds.RenderSettings(max_tile_pairs=200, lod=lod))
    assert banded.stats["bands"] > 2
    np.testing.assert_array_equal(banded.image, many.image)
    assert banded.stats["fragments"] == many.stats["fragments"]


def test_a_process_with_more_threads_reads_the_cached_kernels_safely(tmp_path):
    """numba's disk cache keeps machine code across processes: a kernel that read the thread
    count while compiling would size its per-thread tile buffers for the process that
    compiled it (this session's 2 threads, conftest) and, run by a process with more
    threads, write past them (glibc aborts: "free(): invalid next size"; a GPU machine's
    16 threads found it). A process with 6 threads renders from this session's cache, and
    its frame equals this process's to the bit (the image does not depend on the threads)."""
    s = random_scene(5, n=2000)
    cam = ds.Camera(eye=(0, 0, 4), target=(0, 0, 0), width=256, height=192, fov_y=35)
    lens = ds.ThinLens(focus_distance=3.0, aperture=0.3)
    here = ds.render(s, cam, lens, ds.RenderSettings()).image
    np.savez(tmp_path / "scene.npz", positions=s.positions, normals=s.normals,
             radius=s.radius, colors=s.colors, opacity=s.opacity)
    script = (
        "import sys, numpy as np, dofsplat as ds\n"
        "d = np.load(sys.argv[1])\n"
        "s = ds.Surfels(**{k: d[k] for k in d.files})\n"
        "cam = ds.Camera(eye=(0, 0, 4), target=(0, 0, 0), width=256, height=192, fov_y=35)\n"
        "lens = ds.ThinLens(focus_distance=3.0, aperture=0.3)\n"
        "np.save(sys.argv[2], ds.render(s, cam, lens, ds.RenderSettings()).image)\n")
    env = dict(os.environ, NUMBA_NUM_THREADS="6")
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path / "scene.npz"),
                           str(tmp_path / "image.npy")], env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    np.testing.assert_array_equal(np.load(tmp_path / "image.npy"), here)


def test_tile_order_visits_every_row_once_and_spreads_each_run():
    """The raster and front passes take tile row (k stride) mod n for k = 0 .. n - 1, the
    projection its blocks of splats likewise (dofsplat/parallel.py): every row exactly
    once, and a thread's contiguous run of k (numba's static schedule) spread over the
    band, not one part of it. The bound: the run of the first half of k takes between 40
    and 60 % of the rows of each half of the band (a Weyl sequence with a step near n / phi
    is within a few rows of a half)."""
    from dofsplat.parallel import weyl_stride
    from dofsplat.raster.abuffer import spread_tile

    for n_rows, n_tx in [(1, 1), (5, 3), (32, 32), (68, 120)]:  # the passes' own mapping
        stride = weyl_stride(n_rows)
        tiles = [spread_tile(u, n_tx, n_rows, stride) for u in range(n_rows * n_tx)]
        np.testing.assert_array_equal(np.sort(tiles), np.arange(n_rows * n_tx))
    for n in [1, 2, 3, 4, 7, 64, 97, 1020, 1024, 8160]:
        stride = weyl_stride(n)
        order = (np.arange(n) * stride) % n
        assert math.gcd(stride, n) == 1
        np.testing.assert_array_equal(np.sort(order), np.arange(n))
        if n >= 64:
            first = order[: n // 2]  # the rows the first of two threads draws
            top = np.count_nonzero(first < n // 2)
            assert 0.4 * (n // 2) <= top <= 0.6 * (n // 2), (n, top)


@pytest.mark.parametrize("band", [(0, 9), (3, 7)])
def test_binning_equals_a_stable_sort(band):
    """bin_splats (runs of splats counted and scattered in parallel) lists each tile's
    splats in increasing index, as a stable sort of the tile-splat pairs does; enough splats
    for several runs, invisible ones among them, a band of tile rows."""
    from dofsplat.raster.abuffer import BIN_RUN, TILE, bin_splats

    rng = np.random.default_rng(7)
    n, tile, n_tx, ty0, ty1 = 3 * BIN_RUN + 123, TILE, 12, *band
    x0, y0 = rng.integers(0, 12 * tile, n), rng.integers(0, 9 * tile, n)
    bbox = np.stack([x0, np.minimum(x0 + rng.integers(0, 40, n), 12 * tile - 1),
                     y0, np.minimum(y0 + rng.integers(0, 40, n), 9 * tile - 1)], 1).astype(np.int32)
    visible = rng.uniform(size=n) > 0.1
    pairs = [((ty - ty0) * n_tx + tx, k) for k in np.flatnonzero(visible)
             for ty in range(max(bbox[k, 2] // tile, ty0), min(bbox[k, 3] // tile, ty1 - 1) + 1)
             for tx in range(bbox[k, 0] // tile, bbox[k, 1] // tile + 1)]
    tiles = np.array([t for t, _ in pairs])
    order = np.argsort(tiles, kind="stable")
    offsets, ids = bin_splats(bbox, visible, n_tx, ty0, ty1)
    np.testing.assert_array_equal(ids, np.array([k for _, k in pairs])[order])
    np.testing.assert_array_equal(offsets, np.searchsorted(tiles[order],
                                                           np.arange((ty1 - ty0) * n_tx + 1)))


def test_tile_row_pairs_count_every_pair_once():
    """tile_rows_pairs (counted in bin_splats' runs, in parallel) against a count of the
    tile-splat pairs in numpy: enough splats for several runs, invisible ones among them."""
    from dofsplat.raster.abuffer import BIN_RUN, TILE, tile_rows_pairs

    rng = np.random.default_rng(11)
    n, tile, n_ty = 3 * BIN_RUN + 77, TILE, 9
    x0, y0 = rng.integers(0, 12 * tile, n), rng.integers(0, n_ty * tile, n)
    bbox = np.stack([x0, np.minimum(x0 + rng.integers(0, 40, n), 12 * tile - 1),
                     y0, np.minimum(y0 + rng.integers(0, 40, n), n_ty * tile - 1)], 1).astype(np.int32)
    visible = rng.uniform(size=n) > 0.1
    want = np.zeros(n_ty, np.int64)
    b = bbox[visible]
    nx = b[:, 1] // tile - b[:, 0] // tile + 1
    for lo, hi, w in zip(b[:, 2] // tile, b[:, 3] // tile, nx):
        want[lo:hi + 1] += w
    np.testing.assert_array_equal(tile_rows_pairs(bbox, visible, n_ty), want)


def test_focus_distance_at_reads_the_visible_surface():
    s = grid_surfels(n=32, spacing=1.0 / 32, z=0.25)
    cam = front_camera(64, 64, distance=2.0)
    assert ds.focus_distance_at(s, cam, 32, 32) == pytest.approx(1.75, rel=1e-4)
    with pytest.raises(ds.DofsplatError, match="no surface"):
        ds.focus_distance_at(s, cam, 1, 1)
    with pytest.raises(ds.DofsplatError, match="outside"):
        ds.focus_distance_at(s, cam, 64, 3)


def test_arguments_of_the_wrong_kind_are_named():
    """A lens left out (render(surfels, camera, settings)), arguments swapped or a dict for
    the settings: a DofsplatError naming the argument, before anything renders (they were
    AttributeErrors from inside the backend)."""
    from dofsplat.postfilter import render_postfilter

    s = grid_surfels(n=4, spacing=0.25)
    cam = front_camera(16, 16, distance=2.0)
    lens = ds.ThinLens(focus_distance=2.0, aperture=0.1)
    for call, message in [
            (lambda: ds.render(s, cam, ds.RenderSettings()),
             r"render\(\): lens must be a ThinLens, an EyeLens or None, got RenderSettings"),
            (lambda: ds.render(s, lens, cam), r"render\(\): camera must be a Camera, got ThinLens"),
            (lambda: ds.render(s, cam, lens, {"cutoff": 2.0}),
             r"render\(\): settings must be a RenderSettings or None, got dict"),
            (lambda: ds.render(s, cam, lens, hierarchy="tree.npz"),
             r"render\(\): hierarchy must be a dofsplat\.lod\.Hierarchy or None, got str"),
            (lambda: ds.render_reference(s, cam, lens, {}, samples=2),
             r"render_reference\(\): settings must be a RenderSettings or None, got dict"),
            (lambda: render_postfilter(s, None, lens),
             r"render_postfilter\(\): camera must be a Camera, got NoneType"),
            (lambda: ds.focus_distance_at(s, None, 8, 8),
             r"focus_distance_at\(\): camera must be a Camera, got NoneType"),
            (lambda: ds.focus_distance_at(s, cam, "8", 8),
             r"focus_distance_at\(\): x and y must be numbers")]:
        with pytest.raises(ds.DofsplatError, match=message):
            call()


@pytest.mark.parametrize("kwargs, message", [
    (dict(cutoff="2.5"), "cutoff must be a number, got '2.5'"),
    (dict(lod_color_tolerance=None), "lod_color_tolerance must be a number, got None"),
    (dict(max_tile_pairs="many"), "max_tile_pairs must be a number"),
    (dict(lights=ds.HEADLIGHT), "lights must be a tuple of Light"),
    (dict(lights=None), "lights must be a tuple of Light, got None"),
    (dict(coarse_blur_px="8"), "coarse_blur_px must be a number"),
    (dict(coarse_blur_px=-1.0), r"coarse_blur_px must be >= 0 \(0: off\), got -1.0"),
    (dict(coarse_blur_px=float("nan")), "coarse_blur_px must be >= 0"),
])
def test_settings_of_the_wrong_kind_are_named(kwargs, message):
    """RenderSettings' numbers and lights of the wrong kind: a DofsplatError naming the
    field (a TypeError from a comparison, or from the shading in the render, before)."""
    with pytest.raises(ds.DofsplatError, match=message):
        ds.RenderSettings(**kwargs)
    assert ds.RenderSettings(lights=[ds.HEADLIGHT]).lights == (ds.HEADLIGHT,)


def test_culling_behind_camera_and_back_faces():
    s = ds.Surfels(positions=[[0, 0, 0], [0, 0, 3], [0.2, 0, 0]],
                   normals=[[0, 0, 1], [0, 0, 1], [0, 0, -1]], radius=[0.05] * 3,
                   colors=[[1, 1, 1]] * 3)
    cam = front_camera(32, 32, distance=2.0)
    assert ds.render(s, cam).stats["splats_rendered"] == 1
    two_sided = ds.render(s, cam, None, ds.RenderSettings(cull_backfaces=False, lod=False))
    assert two_sided.stats["splats_rendered"] == 2


def test_shading_kernel_equals_numpy_twin():
    from dofsplat.shading import shade
    from dofsplat.splat.shade import shade_fast
    s = random_scene(9, n=500)
    cam = ds.Camera(eye=(0.3, 0.2, 4), target=(0, 0, 0))
    lights = (ds.HEADLIGHT, ds.Light("point", (1.0, 2.0, 3.0), (0.5, 0.4, 0.3), in_camera_space=False),
              ds.Light("directional", (1.0, -1.0, -1.0), (0.2, 0.2, 0.6), in_camera_space=False),
              ds.Light("point", (0.0, 1.0, 0.0), (0.3, 0.3, 0.3), in_camera_space=True))
    mat = ds.Material(ambient=0.1, diffuse=0.7, specular=0.6, shininess=20)
    for two_sided in (False, True):
        a = shade(s.positions, s.normals, s.colors, mat, cam, lights, two_sided)
        b = shade_fast(s.positions, s.normals, s.colors, mat, cam, lights, two_sided)
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6)
        assert a.max() > a.min() + 0.5  # the lights do something


def test_frames_reusing_the_workspace_equal_fresh_ones():
    """render() keeps its splat buffers between frames (backends.cpu._workspace): a frame after a
    larger and a smaller one equals the same frame with fresh buffers, bit for bit."""
    import importlib

    render_module = importlib.import_module("dofsplat.backends.cpu")

    big, small = random_scene(7, n=600), random_scene(8, n=40)
    cam = ds.Camera(eye=(0.3, 0.2, 4), target=(0, 0, 0), width=48, height=40, fov_y=35)
    lens = ds.ThinLens(focus_distance=3.6, aperture=0.3)
    st = ds.RenderSettings(lod=False)
    render_module._LOCAL.workspace = {}
    first = ds.render(big, cam, lens, st).image
    ds.render(small, cam, lens, st)
    assert render_module._LOCAL.workspace["splats"].shape[0] == 600  # kept, not shrunk
    again = ds.render(big, cam, lens, st).image
    np.testing.assert_array_equal(first, again)
    render_module._LOCAL.workspace = {}
    np.testing.assert_array_equal(ds.render(big, cam, lens, st).image, first)
