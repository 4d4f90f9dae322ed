"""The resampling kernel: DOF variance, truncation and normalisation, circumellipse."""

import math

import numpy as np
import pytest
from scipy import integrate, optimize

import dofsplat as ds
from dofsplat.slow import circumellipse_appendix, circumellipse_eig
from dofsplat.splat import ewa

from conftest import front_camera


def test_dof_factor_is_the_l2_best_gaussian_for_a_uniform_disc():
    """Minimise ||uniform disc - circular Gaussian||_2 over the variance: a = C_r^2/(2 ln 4)."""
    Cr = 1.0

    def l2_distance_sq(a):
        gauss = lambda r: math.exp(-0.5 * r * r / a) / (2 * math.pi * a)  # noqa: E731
        inside, _ = integrate.quad(lambda r: (1 / (math.pi * Cr ** 2) - gauss(r)) ** 2 * 2 * math.pi * r, 0, Cr)
        outside, _ = integrate.quad(lambda r: gauss(r) ** 2 * 2 * math.pi * r, Cr, np.inf)
        return inside + outside

    res = optimize.minimize_scalar(l2_distance_sq, bounds=(0.05, 2.0), method="bounded",
                                   options={"xatol": 1e-10})
    assert res.x == pytest.approx(1 / (2 * math.log(4)), rel=1e-5)
    assert ewa.DOF_VARIANCE_FACTOR == pytest.approx(1 / (2 * math.log(4)), rel=1e-15)


def single_splat(normal=(0, 0, 1), radius=0.02, tangent=None, radius_v=None, cutoff=2.5,
                 lens=None, exact=True, cam=None, pos=(0.0013, -0.0021, 0.0)):
    s = ds.Surfels(positions=[pos], normals=[normal], radius=[radius], colors=[[1, 1, 1]],
                   tangent=None if tangent is None else [tangent],
                   radius_v=None if radius_v is None else [radius_v])
    cam = cam or front_camera(128, 128)
    settings = ds.RenderSettings(cutoff=cutoff, shading="none", exact_normalization=exact, lod=False)
    return s, cam, ds.render(s, cam, lens, settings)


def expected_area_px(s, cam):
    """|det J| x r_u r_v: the surfel's area in pixels, from the twin's Jacobian."""
    from dofsplat.slow import project_reference
    from dofsplat.splat.project import AMP, C11, C12, C22
    st = ds.RenderSettings(shading="none", exact_normalization=False, cutoff=30, lod=False)
    splats, _, vis = project_reference(s, s.colors, cam, None, st)
    # analytic amplitude at c = 30 is area_px / (2 pi sqrt|W|): recover area_px
    Wdet = 1.0 / (splats[0, C11] * splats[0, C22] - splats[0, C12] ** 2)
    return splats[0, AMP] * 2 * math.pi * math.sqrt(Wdet) * (1 - math.exp(-30))


@pytest.mark.parametrize("case", [
    dict(normal=(0, 0, 1), radius=0.02),  # round, a few pixels
    dict(normal=(0, 0, 1), radius=0.004),  # round, prefilter-dominated
    dict(normal=(0.0, 0.97, 0.243), radius=0.03),  # strongly elliptical: grazing view
    dict(normal=(0, 0, 1), radius=0.05, tangent=(1, 1, 0), radius_v=0.006),  # elliptical surfel
])
def test_single_truncated_kernel_sums_to_its_area(case):
    """One kernel, truncated at c = 2.5, deposits exactly its area in pixels (within 1e-3)."""
    s, cam, res = single_splat(**case)
    area_px = expected_area_px(s, cam)
    assert res.weight.sum() == pytest.approx(area_px, rel=1e-3)


def test_analytic_compensation_is_close_but_not_exact():
    """The paper's 1/(1 - e^-c): right on average, a few % off for small kernels."""
    s, cam, res = single_splat(radius=0.004, exact=False)
    area_px = expected_area_px(s, cam)
    assert res.weight.sum() == pytest.approx(area_px, rel=0.05)


def test_out_of_focus_blob_second_moment():
    """The paper's Gaussian (bokeh="gaussian"): a tiny surfel far out of focus has per-axis
    variance 1 + C_r^2/(2 ln 4) + J V^r J^T.

    Rendered with c = 8, whose truncation shrinks the moment by 1 - c e^-c/(1 - e^-c) = 0.9973.
    """
    cam = front_camera(160, 160, distance=2.0)
    lens = ds.ThinLens(focus_distance=1.0, aperture=0.3, bokeh="gaussian")
    s, cam, res = single_splat(radius=1e-4, cutoff=8.0, lens=lens, cam=cam, pos=(0, 0, 0))
    coc = lens.coc_radius_px(2.0, cam)
    assert coc > 10
    w = res.weight.astype(np.float64)
    ys, xs = np.mgrid[0:160, 0:160] + 0.5
    m = w.sum()
    mx, my = (w * xs).sum() / m, (w * ys).sum() / m
    vx = (w * (xs - mx) ** 2).sum() / m
    vy = (w * (ys - my) ** 2).sum() / m
    c = 8.0
    shrink = 1 - c * math.exp(-c) / (1 - math.exp(-c))
    ax = cam.pixels_per_unit_at_unit_depth
    jvj = (ax / 2.0 * 0.5e-4) ** 2
    expected = (1 + coc ** 2 / (2 * math.log(4)) + jvj) * shrink
    assert vx == pytest.approx(expected, rel=0.03)
    assert vy == pytest.approx(expected, rel=0.03)


def _random_spd(rng):
    a = rng.normal(size=(2, 2)) * rng.uniform(0.1, 10)
    return a @ a.T + 1e-3 * np.eye(2)


def test_circumellipse_contains_both_and_matches_appendix():
    rng = np.random.default_rng(3)
    for _ in range(500):
        M = _random_spd(rng)
        r = rng.uniform(0.01, 20)
        out = np.array(ewa.circumellipse(M[0, 0], M[0, 1], M[1, 1], r))
        D = np.array([[out[0], out[1]], [out[1], out[2]]])
        # contains both: D - M and D - r I are positive semi-definite
        assert np.linalg.eigvalsh(D - M).min() > -1e-9 * np.abs(D).max()
        assert np.linalg.eigvalsh(D - r * np.eye(2)).min() > -1e-9 * np.abs(D).max()
        np.testing.assert_allclose(D, circumellipse_eig(M, r), rtol=1e-9, atol=1e-9)
        a2, b2, c2 = circumellipse_appendix(M[0, 0], 2 * M[0, 1], M[1, 1], r)
        np.testing.assert_allclose([a2, b2 / 2, c2], out, rtol=1e-9, atol=1e-9 * abs(out).max())


def test_circumellipse_limits():
    M = np.array([[2.0, 0.5], [0.5, 1.0]])
    big = 10.0  # circle larger in every direction
    np.testing.assert_allclose(ewa.circumellipse(2.0, 0.5, 1.0, big), (big, 0.0, big), atol=1e-12)
    small = 0.1  # ellipse larger in every direction
    np.testing.assert_allclose(ewa.circumellipse(2.0, 0.5, 1.0, small), (2.0, 0.5, 1.0), atol=1e-12)
    np.testing.assert_allclose(ewa.circumellipse(3.0, 0.0, 3.0, 1.0), (3.0, 0.0, 3.0))
    assert np.linalg.eigvalsh(M).min() > small


def test_general_circumellipse_contains_both_and_reduces_to_appendix():
    from dofsplat.slow import circumellipse_general_eig
    rng = np.random.default_rng(4)
    for _ in range(300):
        A, B = _random_spd(rng), _random_spd(rng)
        out = np.array(ewa.circumellipse_general(A[0, 0], A[0, 1], A[1, 1], B[0, 0], B[0, 1], B[1, 1]))
        D = np.array([[out[0], out[1]], [out[1], out[2]]])
        scale = np.abs(D).max()
        assert np.linalg.eigvalsh(D - A).min() > -1e-9 * scale
        assert np.linalg.eigvalsh(D - B).min() > -1e-9 * scale
        np.testing.assert_allclose(D, circumellipse_general_eig(A, B), rtol=1e-7, atol=1e-9 * scale)
        # a circle as B: Appendix A's circumellipse
        r = rng.uniform(0.01, 20)
        np.testing.assert_allclose(ewa.circumellipse_general(A[0, 0], A[0, 1], A[1, 1], r, 0.0, r),
                                   ewa.circumellipse(A[0, 0], A[0, 1], A[1, 1], r),
                                   rtol=1e-9, atol=1e-9 * max(r, np.abs(A).max()))
    # B containing A returns B; A containing B returns A
    np.testing.assert_allclose(ewa.circumellipse_general(1.0, 0.2, 0.5, 4.0, 0.1, 3.0), (4.0, 0.1, 3.0), rtol=1e-12)
    np.testing.assert_allclose(ewa.circumellipse_general(4.0, 0.1, 3.0, 1.0, 0.2, 0.5), (4.0, 0.1, 3.0), rtol=1e-12)


def random_kernels(seed: int, count: int):
    """Random kernels, narrow and wide (W = A A^T + I, the prefilter's floor), each at a
    random centre: (W, W^-1, mx, my, ewa.kernel_bbox at c = 2.5)."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        a = rng.normal(size=(2, 2)) * rng.uniform(0.2, 4.0)
        w = a @ a.T + np.eye(2)
        mx, my = rng.uniform(10, 20, 2)
        yield w, np.linalg.inv(w), mx, my, ewa.kernel_bbox(mx, my, w[0, 0], w[1, 1], 2.5)


def test_kernel_pixel_sum_equals_a_direct_sum():
    """The exact normalisation's pixel sum (forward differences along and, for narrow
    kernels, down the rows) equals exp(-q) summed directly over the pixel centres inside
    the cutoff, to 1e-12 (measured 7e-15), for random kernels narrow and wide."""
    from dofsplat.splat.ewa import kernel_pixel_sum

    for w, c, mx, my, (x0, x1, y0, y1) in random_kernels(seed=1, count=300):
        fast = kernel_pixel_sum(mx, my, c[0, 0], c[0, 1], c[1, 1], 2.5, x0, x1, y0, y1, 0.0)
        # directly, over a window 3 px wider than the box all round
        ys, xs = np.mgrid[y0 - 3:y1 + 4, x0 - 3:x1 + 4] + 0.5
        dx, dy = xs - mx, ys - my
        q = 0.5 * (c[0, 0] * dx * dx + 2 * c[0, 1] * dx * dy + c[1, 1] * dy * dy)
        assert fast == pytest.approx(np.exp(-q)[q < 2.5].sum(), rel=1e-12)


def test_kernel_bbox_is_the_pixels_the_kernel_can_draw():
    """A Gaussian's box holds every pixel centre inside its cutoff (1/2 x^T W^-1 x < c,
    found directly over a window 4 px wider) and no column or row whose centres all lie
    farther than sqrt(2 c W_ii) from the mean, where no centre can be inside. The box
    before 2026-11-27 rounded outwards and took one such column or row on each side in
    most cases: 9.3 M pixels scanned for the pinhole plane's 3.8 M fragments, 4.8 M now."""
    for w, c, mx, my, (x0, x1, y0, y1) in random_kernels(seed=7, count=400):
        ys, xs = np.mgrid[y0 - 4:y1 + 5, x0 - 4:x1 + 5]
        dx, dy = xs + 0.5 - mx, ys + 0.5 - my
        inside = 0.5 * (c[0, 0] * dx * dx + 2 * c[0, 1] * dx * dy + c[1, 1] * dy * dy) < 2.5
        assert inside.any()
        assert x0 <= xs[inside].min() and xs[inside].max() <= x1
        assert y0 <= ys[inside].min() and ys[inside].max() <= y1
        # (and the slack for the rasteriser's float32 rows: ewa.BOX_SLACK, 1e-3 px and
        # 1e-6 of a reach and a coordinate under 25 px here, so under 2e-3 px)
        hx, hy = math.sqrt(5 * w[0, 0]) + 2e-3, math.sqrt(5 * w[1, 1]) + 2e-3
        for j in (x0, x1):
            assert abs(j + 0.5 - mx) < hx
        for i in (y0, y1):
            assert abs(i + 0.5 - my) < hy


@pytest.mark.parametrize("tilt_deg, turn_deg", [(60.0, 0.0), (75.0, 35.0), (30.0, -110.0)])
def test_depth_gradient_is_the_tangent_planes(tilt_deg, turn_deg):
    """A splat's (gz_x, gz_y) is the depth change per pixel (x right, y down) along its
    tangent plane (the front pass carries a splat's surface along it). On a plane the
    depth of a neighbouring surfel, a few pixels away, is its first-order prediction
    depth + g . (m' - m) up to the curvature of 1/depth, which is affine in the pixel:
    measured, the worst residual is 0.9-1.8 % of the depth change; the bound, 3 %, is far
    below what a wrong sign or a swapped axis gives (100 % and more)."""
    from dofsplat.backends.cpu import project
    from dofsplat.splat.project import DEPTH, GZX, GZY, MX, MY

    n, spacing = 24, 1.0 / 24
    ij = np.indices((n, n)).reshape(2, -1).T.astype(float)
    flat = np.column_stack([(ij - (n - 1) / 2) * spacing, np.zeros(n * n)])
    a, b = math.radians(tilt_deg), math.radians(turn_deg)
    tilt = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    turn = np.array([[math.cos(b), -math.sin(b), 0], [math.sin(b), math.cos(b), 0], [0, 0, 1]])
    rot = tilt @ turn
    s = ds.Surfels(positions=flat @ rot.T, normals=np.tile(rot[:, 2], (n * n, 1)),
                   radius=np.full(n * n, spacing), colors=np.full((n * n, 3), 0.5))
    cam = front_camera(128, 128, distance=2.5)
    splats, _, visible = project(s, s.colors, cam, None, ds.RenderSettings(lod=False))
    assert visible.all()
    sp = splats.astype(np.float64)
    grid = np.arange(n * n).reshape(n, n)
    worst, checked = 0.0, 0
    for k, l in [(grid[i, j], grid[i + di, j + dj]) for i in range(n - 1) for j in range(n - 1)
                 for di, dj in ((1, 0), (0, 1))]:
        predicted = sp[k, GZX] * (sp[l, MX] - sp[k, MX]) + sp[k, GZY] * (sp[l, MY] - sp[k, MY])
        actual = sp[l, DEPTH] - sp[k, DEPTH]
        if abs(actual) > 1e-4:
            worst = max(worst, abs(predicted - actual) / abs(actual))
            checked += 1
    assert checked > n * n // 2
    assert worst < 0.03
