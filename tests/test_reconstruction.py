"""The soft surface reconstruction (docs/maths.md, "Surface reconstruction"): the merge
fraction, the resolve against its partition-sum twin, and the contact seam it removes."""


import numpy as np
import pytest

import dofsplat as ds
from dofsplat.raster.abuffer import (MAX_SURFACES, N_ACC, RESOLVE_SCRATCH, merge_fraction,
                                     resolve_pixel)
from dofsplat.slow import _resolve, merge_fraction_reference

MERGE = (20.0, 1 / 3.0, 0.15, 0.5)  # K = 20 px, focus at 3, the default band


def test_merge_fraction_limits():
    k, inv_p, r0, r1 = MERGE
    # a pinhole (K = 0) never merges: the paper's "over"
    assert merge_fraction(1.0, 1.01, 1.0, 0.0, inv_p, r0, r1) == 0.0
    # two surfaces at one depth, far from focus: rho = 1 / C_r -> one layer
    assert merge_fraction(1.5, 1.5, 1.0, k, inv_p, r0, r1) == 1.0
    # a sharp surface before a blurred one: Delta = C_r of the far one, rho > 1 -> "over"
    assert merge_fraction(3.0, 6.0, 1.0, k, inv_p, r0, r1) == 0.0
    # a translucent front is composited over what is behind it
    assert merge_fraction(1.5, 1.5, 0.5, k, inv_p, r0, r1) == 0.0
    # in between: smooth, and the twin agrees
    for d_back in np.linspace(1.5, 2.5, 21):
        m = merge_fraction(1.5, d_back, 1.0, k, inv_p, r0, r1)
        assert 0.0 <= m <= 1.0
        assert m == pytest.approx(merge_fraction_reference(1.5, d_back, 1.0, MERGE), abs=1e-12)


@pytest.mark.parametrize("seed", range(6))
def test_resolve_equals_the_sum_over_partitions(seed):
    """The O(n^2) table against the explicit expectation over all 2^(n-1) runs, 1e-12."""
    rng = np.random.default_rng(seed)
    check_resolve(rng, int(rng.integers(2, MAX_SURFACES + 1)))


@pytest.mark.parametrize("seed", range(12))
def test_resolve_of_no_surface_or_one(seed):
    """resolve_pixel's own path for a pixel with no surface (seed 0) or one (most of a
    frame's pixels), against the same twin, 1e-12."""
    check_resolve(np.random.default_rng(100 + seed), min(seed, 1))


def check_resolve(rng, n):
    """resolve_pixel of n random surfaces against slow._resolve."""
    acc = np.zeros((1, MAX_SURFACES, N_ACC))
    surfaces = []
    for i in range(n):
        w = rng.uniform(0.1, 1.5)
        # close depths, far from focus: merge fractions in (0, 1); some near the focus at 3
        # (CoC under 2 px), where a sharp surface's coverage has its knee (layer_alpha)
        d = rng.uniform(1.2, 1.9) if rng.uniform() < 0.7 else rng.uniform(2.4, 3.2)
        alpha = 1.0 if rng.uniform() < 0.8 else rng.uniform(0.3, 1)
        rgb = rng.uniform(0, 1, 3)
        # the weight of opaque fragments: all, none, or part (a translucent surface merged
        # with an opaque one), so that abuffer.layer_alpha's floor is exercised
        wo = w if alpha == 1.0 else rng.choice([0.0, rng.uniform(0, w)])
        s = [w, *(w * rgb), w * alpha, w * d, wo, d - 0.01, d + 0.01]
        acc[0, i] = s
        surfaces.append(s)
    cnt = np.array([n])
    out = np.empty(7)
    resolve_pixel(acc, cnt, 0, 0.1, 0.2, 0.3, out, np.empty(MAX_SURFACES, np.int64),
                  np.empty(RESOLVE_SCRATCH), *MERGE)
    rgba, depth, nearest = _resolve(surfaces, (0.1, 0.2, 0.3), MERGE)
    np.testing.assert_allclose(out[:4], rgba, atol=1e-12)
    assert out[4] == pytest.approx(depth) and out[5] == pytest.approx(nearest)


def test_a_sharp_surface_covers_its_pixel_from_cover_full():
    """abuffer.layer_alpha: a sharp surface's opaque weights w_o cover the pixel from
    COVER_FULL (0.9) up, linearly from w_o at COVER_KNEE (0.85), and below the knee keep
    w_o (a rim's share of the pixel); a blurred one (CoC from 2 x COVER_SHARP_PX) keeps
    min(1, w_o), the share of the lens that sees it; in between linearly in the CoC
    (abuffer.sharpness). Exact values: the rule is piecewise linear."""
    from dofsplat.raster.abuffer import (COVER_FULL, COVER_KNEE, COVER_SHARP_PX, layer_alpha,
                                         sharpness)

    k, inv_p = MERGE[:2]
    assert sharpness(3.0, k, inv_p) == 1.0 and sharpness(3.0, 0.0, 0.0) == 1.0
    assert sharpness(3.0, -1.0, 0.0) == -1.0  # the paper's reconstruction: its min(1, w)
    assert sharpness(1.5, k, inv_p) == 0.0  # C_r = 6.7 px
    d_half = 1.0 / (inv_p + 1.5 * COVER_SHARP_PX / k)  # C_r = 1.5 px
    assert sharpness(d_half, k, inv_p) == pytest.approx(0.5, abs=1e-12)
    mid = 0.5 * (COVER_KNEE + COVER_FULL)
    for wo, sharp, want in [(0.5, 1.0, 0.5), (COVER_KNEE, 1.0, COVER_KNEE),
                            (mid, 1.0, 0.5 * (COVER_KNEE + 1.0)), (COVER_FULL, 1.0, 1.0),
                            (0.95, 1.0, 1.0), (1.3, 1.0, 1.0), (0.95, 0.0, 0.95),
                            (0.95, 0.5, 0.975), (0.5, 0.0, 0.5),
                            # blurred: 1 from BLUR_COVER_FULL (0.98), linear from 0.95
                            (0.965, 0.0, 0.975), (0.98, 0.0, 1.0), (0.99, 0.0, 1.0),
                            (0.965, 0.5, 0.985), (0.96, 1.0, 1.0),
                            # the paper's reconstruction keeps min(1, w_o)
                            (0.97, -1.0, 0.97), (0.88, -1.0, 0.88)]:
        assert layer_alpha(wo, wo, wo, sharp) == pytest.approx(want, abs=1e-12)
    # a translucent surface (no opaque weight) keeps the paper's min(1, w) x mean alpha
    assert layer_alpha(0.95, 0.95 * 0.5, 0.0, 1.0) == pytest.approx(0.475, abs=1e-12)


def test_contact_seam_is_softened():
    """Where the demo's blurred red sphere rests on the floor, the paper's binary
    merge/separate decision draws a hard line with a pale ghost under it; the soft
    reconstruction moves towards the reference there. Measured at 160 x 120, A = 0.75 (CoC
    about 20 px at the sphere), no LOD, against 64 lens samples, in the strip under the
    sphere: soft 27.57 dB, paper 25.73 dB on 2026-11-28 (whole frame 37.62 / 36.29; 26.31 /
    25.83 when the soft reconstruction came, 25.20 / 24.82 with the paper's Gaussian
    kernel). The bound asks for the gain measured less 0.5 dB (float rounding needs far
    less), 1.33 dB: a change that brings back the binary decision, or loses most of the
    gain, fails it."""
    import dataclasses

    from dofsplat.demo import demo_scene
    from dofsplat.metrics import psnr
    from dofsplat.reference import render_reference

    surfels, cam, lens = demo_scene(160, 120)
    lens = dataclasses.replace(lens, aperture=0.75)
    ref = render_reference(surfels, cam, lens, samples=64, progress=False).image
    scores = {}
    for rec in ("soft", "paper"):
        img = ds.render(surfels, cam, lens, ds.RenderSettings(lod=False, reconstruction=rec)).image
        scores[rec] = psnr(img[85:110, :50], ref[85:110, :50])
    assert scores["soft"] > scores["paper"] + 1.33, scores


def test_a_translucent_surface_on_an_opaque_one_uncovers_nothing():
    """Adding surfaces in front never lets more background through. Where the transparent
    contact scene's translucent pane and sphere stand on the opaque floor, their blurred
    fragments merge with the floor's; the paper's opacity of a merged surface,
    min(1, sum w) x mean alpha, dilutes the floor's full opacity by the pane's 0.5 (the
    background showed through along the contact: alpha 0.75 where the floor alone has 1,
    at 128 x 128, and that dark line was the fidelity suite's worst tiles).
    abuffer.layer_alpha keeps a merged surface at least as opaque as its opaque fragments'
    coverage: measured, the alpha with the translucent surfaces is nowhere below the
    floor's alone (the least difference is 0). The bound, 0.01, is a 25th of the old loss."""
    from dofsplat.demo import transparent_contact_scene

    surfels, cam, lens = transparent_contact_scene(128, 128)
    settings = ds.RenderSettings(lod=False)
    opaque = surfels.subset(np.flatnonzero(surfels.opacity >= 1.0))
    alone = ds.render(opaque, cam, lens, settings).alpha
    full = ds.render(surfels, cam, lens, settings).alpha
    assert float(np.min(full - alone)) > -0.01


# PSNR of the blurred crossing planes against 32 lens samples, whole frame, measured on
# 2026-11-28 (the same to 1e-12 dB with 1 and 2 numba threads and from a fresh kernel
# cache), and the bound each case is held to: measured - 0.5 dB, room for another CPU's
# float rounding many times over, not for a change of the method. The front's reach behind
# it (abuffer.MERGE_REACH) at 2 instead of 6 costs the frame without LOD 1.18 dB (33.75);
# with LOD that mutant scored 29.95 dB, higher than the code's: the LOD case does not see it
HIDDEN_PSNR = {False: (34.94, 34.44), True: (29.62, 29.12)}  # lod: (measured, bound)


@pytest.fixture(scope="module")
def crossing_planes_blurred():
    """The crossing planes at 128 x 128, A = 0.8 (CoC up to 6.6 px), and their reference of
    32 lens samples: (surfels, camera, lens, reference image)."""
    import dataclasses

    from dofsplat.demo import intersecting_planes_scene
    from dofsplat.reference import render_reference

    surfels, cam, lens = intersecting_planes_scene(128, 128)
    lens = dataclasses.replace(lens, aperture=0.8)
    ref = render_reference(surfels, cam, lens, samples=32, progress=False).image
    return surfels, cam, lens, ref


@pytest.mark.parametrize("lod", [False, True])
def test_a_surface_hidden_from_the_whole_lens_does_not_merge(lod, crossing_planes_blurred):
    """Two planes crossing at 12 degrees (the fidelity suite's ``intersect``), blurred: on
    each side of the crossing the rear plane lies within the front one's z-range over a
    circle of confusion, so the A-buffer used to merge it into the front (a grey haze over
    the whole lower half). A splat hidden at every point of its disk and from every point
    of the lens (its front seen with the parallax between them) is removed
    (``abuffer.splat_visibility``), if its blurred fragments' z-ranges reach the front's.
    Against the reference, whole frame: 16.6 dB before that removal, 27.0 dB when it came
    (with LOD); now HIDDEN_PSNR's."""
    from dofsplat.metrics import psnr

    surfels, cam, lens, ref = crossing_planes_blurred
    img = ds.render(surfels, cam, lens, ds.RenderSettings(lod=lod)).image
    measured, bound = HIDDEN_PSNR[lod]
    assert psnr(img, ref) > bound, f"measured {measured} dB when the bound was set"


@pytest.mark.parametrize("lod", [False, True])
def test_a_hidden_surface_in_the_merge_band_does_not_show_through(lod):
    """A plane behind an opaque one, both facing the camera, blurred so that their parallax
    ratio rho (``abuffer.merge_fraction``) lies inside the merge band (0.35: m = 0.6). The
    rear plane is hidden at every point of its disk; its z-ranges are far from the front's,
    so the A-buffer keeps the two apart, but the resolve merges neighbouring surfaces with
    probability m. The front pass used to remove only the m share of such a splat and skip
    the looks through the lens (its fragments "cannot reach" the front's), so the resolve
    merged the remaining 1 - m with probability m: the rear plane's green came through the
    red front at 0.147 everywhere (0.383 with LOD). Now a splat with any merge share is
    looked at, and hidden from the whole lens it is removed. Inside the front, 12 px and
    more from its edge (the pair's parallax is under 1 px), every lens sample of the
    reference sees the front alone: green 0 in 64 samples. Measured now: 0 (no LOD) and
    0.0015 (LOD). The bound, 0.01, is a fifteenth of the old leak."""
    d_front, d_rear, focus = 4.0, 4.4, 10.0
    cam = ds.Camera(eye=(0, 0, 0), target=(0, 0, -1), width=64, height=64, fov_y=30.0)

    def plane(depth, n, color):
        g = (np.arange(n) - (n - 1) / 2) * 0.01
        x, y = (a.ravel() for a in np.meshgrid(g, g))
        return ds.Surfels(np.stack([x, y, np.full_like(x, -depth)], 1),
                          np.tile([0.0, 0.0, 1.0], (x.size, 1)), np.full(x.size, 0.01),
                          np.tile(color, (x.size, 1)))

    from dofsplat.surfels import concatenate

    surfels = concatenate([plane(d_front, 160, (1.0, 0.0, 0.0)),
                           plane(d_rear, 200, (0.0, 1.0, 0.0))])
    unit = ds.ThinLens(focus_distance=focus, aperture=1.0)
    lens = ds.ThinLens(focus_distance=focus, aperture=5.0 / unit.coc_radius_px(d_front, cam))
    k, inv_p = lens.coc_coefficients(cam)
    rho = (k * (1 / d_front - 1 / d_rear) + 1) / (k * (1 / d_front - inv_p))
    assert 0.3 < rho < 0.4  # inside the band (0.15, 0.5)
    img = ds.render(surfels, cam, lens, ds.RenderSettings(shading="none", lod=lod)).image
    assert float(img[20:44, 20:44, 1].max()) < 0.01


def test_a_blurred_lod_surface_covers_its_pixels():
    """An LOD cut's kernels sum to 1 only within a few per cent (irregular nodes, each one
    Gaussian for many surfels), and min(1, w_o) let what lies behind a blurred surface show
    through as speckle. Since ``layer_alpha`` covers a blurred surface's pixel from
    BLUR_COVER_FULL (0.98), the crossing planes' front plane, blurred (128 x 128, A = 0.4,
    CoC up to 6.6 px), covers its lower left, where the rear plane is removed and the black
    background lies behind, as every pinhole sample of the reference does: alpha 1.0000
    there (LOD and no LOD), where min(1, w_o) gave 0.9887 with LOD (0.9967 without).
    The bound, 0.999, is an eleventh of the old loss. Drawn at every pixel: the wide
    blurs' samples (``coarse_blur_px``) leave 0.9912 there, their interpolated weights
    dipping under the knee at a few pixels (docs/maths.md, "Wide blurs at every second
    pixel"); their bound, 0.99, is the samples' measured loss, not a tenth of it."""
    import dataclasses

    from dofsplat.demo import intersecting_planes_scene

    surfels, cam, lens = intersecting_planes_scene(128, 128)
    lens = dataclasses.replace(lens, aperture=0.4)
    every = ds.RenderSettings(coarse_blur_px=0.0)
    alpha = ds.render(surfels, cam, lens, every).image[..., 3]
    assert float(alpha[94:124, 4:51].min()) > 0.999
    alpha = ds.render(surfels, cam, lens, ds.RenderSettings()).image[..., 3]
    assert float(alpha[94:124, 4:51].min()) > 0.99


@pytest.mark.parametrize("lod", [False, True])
def test_a_front_that_ends_beyond_the_frame_reveals_what_it_hides(lod):
    """The front map reaches FRONT_MARGIN pixels beyond the image (``abuffer.front_read``):
    where a surface ends just outside the frame, the surface behind it, whose blur reaches
    in, shows through the front's blurred edge as it does in a wider frame. The fidelity
    suite's two crossing planes at 96 x 96, the largest CoC 7.5 px (its 40 px at 512): the
    textured plane's near edge lies a few pixels below the frame. The frame against the
    middle of a frame 24 px wider each way at the same pixel scale: 52.91 dB (no LOD) and
    53.48 dB (LOD) measured on 2026-11-28, where a front map of the image alone, taken to go
    on as it is at the edge, gave 37.6 and 34.4 dB (the rear plane removed along the
    bottom: alpha 0.86 in the last row, 0.92 in the wider frame). What remains is where the
    crossing line leaves the frame on the right: the wider frame's margin holds disks of
    splats whose blur does not reach the narrow frame, so it never projects them. The
    bound is the measured value less 0.5 dB (float rounding needs far less)."""
    import dataclasses
    import math

    from dofsplat.demo import intersecting_planes_scene
    from dofsplat.metrics import psnr

    n, m = 96, 24
    surfels, cam, lens = intersecting_planes_scene(n, n)
    lens = dataclasses.replace(lens, aperture=0.4029)  # bench/fidelity.py's, for 40 px
    half = math.tan(math.radians(cam.fov_y) / 2) * (n + 2 * m) / n
    wide = dataclasses.replace(cam, width=n + 2 * m, height=n + 2 * m,
                               fov_y=2 * math.degrees(math.atan(half)))
    st = ds.RenderSettings(lod=lod)
    img = ds.render(surfels, cam, lens, st).image
    crop = ds.render(surfels, wide, lens, st).image[m:m + n, m:m + n]
    bound = {False: 52.41, True: 52.98}[lod]
    assert psnr(img, crop) > bound


def test_visibility_equals_its_slow_twin():
    """``abuffer.splat_visibility`` (its sample points and looks through the lens read from
    tables) against ``slow.visibility_reference`` (their angles' sines and cosines), every
    50th splat of the crossing planes blurred, on one front map, to 1e-6: the twin, reading
    the float32 front, takes 1 / depth in float32 (numpy's scalar rules) where the kernel
    works in float64; 3.3e-7 measured, 4e-16 with a float64 copy of the front. The frame
    takes every branch: splats kept whole, removed whole (hidden from the whole lens) and
    in part."""
    import dataclasses

    from dofsplat.backends.cpu import front_chunk, front_map, project, shade_surfels
    from dofsplat.demo import intersecting_planes_scene
    from dofsplat.frame import merge_parameters
    from dofsplat.raster.abuffer import FRONT_MARGIN, splat_visibility
    from dofsplat.slow import visibility_reference

    surfels, cam, lens = intersecting_planes_scene(96, 96)
    lens = dataclasses.replace(lens, aperture=0.8)
    st = ds.RenderSettings(lod=False)
    splats, _, visible = project(surfels, shade_surfels(surfels, cam, st), cam, lens, st)
    # the front map drawn by the fast pass (``front_reference`` is its twin in the frames of
    # tests/test_render.py; over these 400,000 splats it takes a minute)
    m = FRONT_MARGIN
    front = front_map(cam, m)
    front_chunk(splats, visible, cam, front, m)
    merge = merge_parameters(cam, lens, st)
    ks = np.flatnonzero(visible)[::50]
    fast = np.array([splat_visibility(splats, k, front, cam.width + 2 * m, cam.height + 2 * m,
                                      m, *merge) for k in ks])
    slow = np.array([visibility_reference(splats[k], front, merge, cam.width) for k in ks])
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-6)
    assert (fast == 1).sum() > 100 and (fast == 0).sum() > 100, (fast == 0).sum()
    assert ((fast > 0) & (fast < 1)).sum() > 10
