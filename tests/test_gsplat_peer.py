"""The gsplat peer (bench/gsplat_peer.py, issue 48): its camera mapping, its compositing
against a literal per-pixel port of gsplat's kernel, one Gaussian against its closed form,
and the stored references of tests/data. Bench tests: they need torch and gsplat (the
``gsplat-peer`` extra) and skip without them."""

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: numba shares the cores
pytest.importorskip("torch")
pytest.importorskip("gsplat.cuda._torch_impl")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import gsplat_peer as peer  # noqa: E402

from dofsplat.camera import Camera, lens_camera  # noqa: E402
from dofsplat.gaussians import Gaussians  # noqa: E402

DATA = Path(__file__).resolve().parent / "data"
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
Y0 = 0.28209479177387814  # the degree-0 real SH basis function, 1 / (2 sqrt(pi))
C1 = 0.4886025119029199  # degree 1: sqrt(3) / (2 sqrt(pi))


def one_gaussian(position, std, opacity, sh):
    sh = np.asarray(sh, np.float32).reshape(1, -1, 3)
    return Gaussians(positions=np.array([position], np.float32),
                     scales=np.full((1, 3), std, np.float32),
                     rotations=np.array([[1.0, 0.0, 0.0, 0.0]], np.float32),
                     opacity=np.array([opacity], np.float32), sh=sh)


# -- camera --------------------------------------------------------------------------------


@pytest.mark.parametrize("offset", [None, (0.05, -0.03)])
def test_camera_mapping_puts_points_on_dofsplat_pixels(offset):
    """gsplat's pinhole (Utils.cuh persp_proj, through the torch twin) puts a world point on
    the pixel position dofsplat's Camera.project gives it: both sample pixel (i, j) at
    (j + 0.5, i + 0.5), so K has no half-pixel shift. Also for an off-centre frustum
    (lens_camera). Measured: 4e-5 px, float32's rounding of coordinates near 400 px."""
    import torch
    from gsplat.cuda._torch_impl import _fully_fused_projection

    camera = Camera(eye=(0.3, -0.2, 2.5), target=(0.1, 0.05, 0.0), width=640, height=480,
                    fov_y=40.0)
    if offset is not None:
        camera = lens_camera(camera, offset, 2.0)
    points = np.array([[0.1, 0.05, 0.0], [0.4, -0.3, 0.2], [-0.5, 0.6, -0.4], [0.9, 0.7, 0.3]])
    viewmat, K = peer.camera_to_gsplat(camera)
    _, means2d, depths, _, _ = _fully_fused_projection(
        torch.tensor(points, dtype=torch.float32), torch.eye(3).expand(4, 3, 3) * 1e-4,
        torch.tensor(viewmat, dtype=torch.float32)[None],
        torch.tensor(K, dtype=torch.float32)[None], 640, 480)
    xy, depth = camera.project(points)
    np.testing.assert_allclose(means2d[0].numpy(), xy, atol=2e-4)
    np.testing.assert_allclose(depths[0].numpy(), depth, rtol=1e-6)
    np.testing.assert_allclose(peer.project_points(viewmat, K, points), xy, atol=1e-9)
    if offset is None:  # the target is the image's centre, a pixel corner in both
        np.testing.assert_allclose(xy[0], (320.0, 240.0), atol=1e-9)
        np.testing.assert_allclose(K[:2, 2], (320.0, 240.0), atol=1e-9)


# -- compositing against its slow twin -------------------------------------------------------


def composite_slow(means2d, conics, opacities, colors, radii, depths, width, height):
    """RasterizeToPixels3DGSFwd.cu read literally, one pixel and one Gaussian at a time: the
    Gaussians of the pixel's tile (those whose tile box holds it, IntersectTile.cu) in depth
    order, float32 scalars throughout."""
    ts = peer.TILE_SIZE
    image = np.zeros((height, width, 3), np.float32)
    alpha_out = np.zeros((height, width), np.float32)
    stopped = 0
    boxes = {}  # Gaussian -> its tile box [x0, x1) x [y0, y1)
    for g in range(len(radii)):
        if radii[g, 0] > 0 and radii[g, 1] > 0:
            mx, my = means2d[g] / np.float32(ts)
            rx, ry = radii[g].astype(np.float32) / np.float32(ts)
            boxes[g] = (max(0.0, np.floor(mx - rx)), np.ceil(mx + rx),
                        max(0.0, np.floor(my - ry)), np.ceil(my + ry))
    for i in range(height):
        for j in range(width):
            tx, ty = j // ts, i // ts
            members = [g for g, (x0, x1, y0, y1) in boxes.items()
                       if x0 <= tx < x1 and y0 <= ty < y1]
            members.sort(key=lambda g: (depths[g], g))
            px, py = np.float32(j + 0.5), np.float32(i + 0.5)
            T = np.float32(1.0)
            out = np.zeros(3, np.float32)
            for g in members:
                dx, dy = means2d[g, 0] - px, means2d[g, 1] - py
                a, b, c = conics[g]
                sigma = np.float32(0.5) * (a * dx * dx + c * dy * dy) + b * dx * dy
                alpha = min(np.float32(0.999), opacities[g] * np.exp(-sigma))
                if sigma < 0 or alpha < np.float32(1.0 / 255.0):
                    continue
                next_T = T * (np.float32(1.0) - alpha)
                if next_T <= np.float32(1e-4):
                    stopped += 1
                    break
                out += colors[g] * (alpha * T)
                T = next_T
            image[i, j] = out
            alpha_out[i, j] = 1.0 - T
    return image, alpha_out, stopped


def test_compositing_matches_the_kernel_read_literally():
    """The vectorised compositing (cumulative products per tile) against its slow twin on
    80 overlapping Gaussians, half of them opaque so that pixels stop early (next_T <= 1e-4),
    in a 50 x 37 image (partial edge tiles). Float32 both; only the colour sums' order
    differs, hence 2e-6."""
    rng = np.random.default_rng(48)
    n = 80
    camera = Camera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), width=50, height=37,
                    fov_y=40.0, near=0.01)
    sh = rng.normal(0.0, 0.4, (n, 4, 3)).astype(np.float32)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    gaussians = Gaussians(positions=rng.uniform(-0.6, 0.6, (n, 3)).astype(np.float32),
                          scales=rng.uniform(0.03, 0.3, (n, 3)).astype(np.float32),
                          rotations=q / np.linalg.norm(q, axis=1, keepdims=True),
                          opacity=np.where(rng.random(n) < 0.5, 1.0, rng.uniform(0.0, 1.0, n)),
                          sh=sh)
    viewmat, K = peer.camera_to_gsplat(camera)
    f = peer.project(gaussians, viewmat, K, 50, 37, eps2d=0.3, antialiased=False,
                     near_plane=0.01, far_plane=1e10)
    colors = peer.sh_colors(gaussians, viewmat, f["visible"])
    tile_ids, gauss_ids = peer.intersect_tiles(f["means2d"], f["radii"], f["depths"], 50, 37)
    image, alpha = peer.composite(f["means2d"], f["conics"], f["opacities"], colors, tile_ids,
                                  gauss_ids, 50, 37, np.zeros(3, np.float32))
    slow_image, slow_alpha, stopped = composite_slow(f["means2d"], f["conics"], f["opacities"],
                                                     colors, f["radii"], f["depths"], 50, 37)
    assert stopped > 50  # the early stop is exercised
    assert f["visible"].sum() > 60
    np.testing.assert_allclose(alpha, slow_alpha, atol=2e-6)
    np.testing.assert_allclose(image, slow_image, atol=2e-6)
    # and the public function agrees with the stages
    image2, alpha2 = peer.gsplat_render(gaussians, camera)
    np.testing.assert_array_equal(image2, image)
    np.testing.assert_array_equal(alpha2, alpha)


# -- one Gaussian: closed forms ---------------------------------------------------------


def test_one_gaussian_footprint_is_the_pinholes_plus_the_low_pass():
    """An isotropic Gaussian of std s on the view axis at distance z has the screen
    variance v = (f s / z)^2 + eps2d (J Sigma J^T with J = f/z at the axis, plus gsplat's
    0.3 px^2). Every pixel's alpha is o exp(-r^2 / 2v) where that is >= 1/255 (the kernel's
    cut; the footprint's box ends on that contour, sqrt(2 ln(255 o)) < 3.33 std devs) and 0
    beyond, and so the alpha integrates to 2 pi v (o - 1/255). The sum over pixels meets the
    integral to the sampling of the cut's rim: measured 2e-4 relative; bound 2e-3."""
    s, z, o = 0.05, 2.0, 0.6
    camera = Camera(eye=(0.0, 0.0, z), target=(0.0, 0.0, 0.0), width=96, height=96,
                    fov_y=30.0, near=0.01)
    color = np.array([0.2, 0.45, 0.7])
    g = one_gaussian((0.0, 0.0, 0.0), s, o, (color - 0.5) / Y0)
    image, alpha = peer.gsplat_render(g, camera)
    f = camera.pixels_per_unit_at_unit_depth
    v = (f * s / z) ** 2 + 0.3
    jj, ii = np.meshgrid(np.arange(96) + 0.5, np.arange(96) + 0.5)
    expected = o * np.exp(-((jj - 48.0) ** 2 + (ii - 48.0) ** 2) / (2 * v))
    expected[expected < 1 / 255] = 0.0
    np.testing.assert_allclose(alpha, expected, atol=1e-6)
    assert abs(alpha.sum() / (2 * np.pi * v * (o - 1 / 255)) - 1) < 2e-3
    np.testing.assert_allclose(image, alpha[..., None] * color, atol=1e-6)


def test_low_pass_and_antialiased_mode():
    """eps2d is the low-pass's variance in px^2; the antialiased mode scales the opacity by
    sqrt(det cov2d / det(cov2d + eps2d I)) = (f s/z)^2 / v here, so the integral of alpha
    keeps the unfiltered Gaussian's 2 pi (f s / z)^2 o (less the cut)."""
    s, z, o = 0.035, 2.0, 0.9  # f s / z = 1.04 px on the screen
    camera = Camera(eye=(0.0, 0.0, z), target=(0.0, 0.0, 0.0), width=32, height=32,
                    fov_y=30.0, near=0.01)
    g = one_gaussian((0.0, 0.0, 0.0), s, o, np.zeros(3))
    v0 = (camera.pixels_per_unit_at_unit_depth * s / z) ** 2
    for eps2d in (0.3, 1.0):
        v = v0 + eps2d
        _, alpha = peer.gsplat_render(g, camera, eps2d=eps2d)
        # pixel (16, 16) is sampled at (16.5, 16.5), r^2 = 0.5 from the centre (16, 16)
        assert abs(alpha[16, 16] - o * np.exp(-0.25 / v)) < 1e-6
        _, alpha = peer.gsplat_render(g, camera, eps2d=eps2d, antialiased=True)
        o_aa = o * v0 / v
        assert abs(alpha[16, 16] - o_aa * np.exp(-0.25 / v)) < 1e-6
        assert abs(alpha.sum() / (2 * np.pi * v * (o_aa - 1 / 255)) - 1) < 0.02


def test_sh_direction_runs_from_the_camera_to_the_mean():
    """gsplat's degree-1 colour is 0.5 + Y0 c0 + C1 (-y c1 + z c2 - x c3) at the unit direction
    d = (mean - camera centre) / |...| in world space, then clamped at 0 and not above 1."""
    eye = np.array([0.4, -0.3, 2.0])
    mean = np.array([0.25, 0.1, -0.2])
    camera = Camera(eye=tuple(eye), target=tuple(mean), width=32, height=32, fov_y=30.0)
    sh = np.zeros((4, 3))
    sh[0] = [0.5, 3.0, -3.0]
    sh[1] = [0.3, 0.0, 0.0]  # red varies with -y
    sh[2] = [0.0, 0.3, 0.0]  # green with z
    sh[3] = [0.0, 0.0, 0.3]  # blue with -x
    g = one_gaussian(mean, 0.05, 0.5, sh)
    image, alpha = peer.gsplat_render(g, camera)
    d = (mean - eye) / np.linalg.norm(mean - eye)
    expected = 0.5 + Y0 * sh[0] + C1 * (-d[1] * sh[1] + d[2] * sh[2] - d[0] * sh[3])
    assert expected[1] > 1.0 and expected[2] < 0.0  # no clamp above 1; the clamp at 0
    expected = np.maximum(expected, 0.0)
    peak = np.unravel_index(np.argmax(alpha), alpha.shape)
    np.testing.assert_allclose(image[peak] / alpha[peak], expected, rtol=1e-5, atol=1e-6)


# -- scene files and the stored references ------------------------------------------------


def test_reader_decodes_a_3dgs_ply(tmp_path):
    """Logit opacity, log scales, quaternion normalised, f_rest channel-major."""
    from plyfile import PlyData, PlyElement

    k = 4
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] \
        + [f"f_rest_{i}" for i in range(3 * (k - 1))] \
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
           "transform"]
    row = [1.0, 2.0, 3.0, 0, 0, 0, 0.1, 0.2, 0.3] + [10.0 + i for i in range(9)] \
        + [0.0, np.log(0.5), np.log(0.25), np.log(2.0), 2.0, 0.0, 0.0, 0.0, 7.0]
    vertex = np.array([tuple(row)], dtype=[(n, "f4") for n in names])
    path = tmp_path / "one.ply"
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))
    g = peer.read_3dgs_ply(path)
    assert g.sh_degree == 1
    np.testing.assert_allclose(g.positions[0], [1, 2, 3])
    np.testing.assert_allclose(g.opacity[0], 0.5)
    np.testing.assert_allclose(g.scales[0], [0.5, 0.25, 2.0], rtol=1e-6)
    np.testing.assert_allclose(g.rotations[0], [1, 0, 0, 0])
    np.testing.assert_allclose(g.sh[0, 0], [0.1, 0.2, 0.3], rtol=1e-6)
    # coefficient 1 of red, green, blue: f_rest_0, f_rest_3, f_rest_6
    np.testing.assert_allclose(g.sh[0, 1:], [[10, 13, 16], [11, 14, 17], [12, 15, 18]])


@pytest.mark.parametrize("reference", ["gsplat_fruit_drops.npz", "gsplat_donut.npz"])
def test_stored_reference_renders_again(reference):
    """The stored 160 x 120 references come back from their recorded cameras, to the
    float16 storage's rounding (half an ulp at 1: 5e-4, with the peer's own float32
    rounding: 1e-3)."""
    stored = np.load(DATA / reference)
    meta = json.loads(str(stored["meta"]))
    scene = {"fruit_drops_minimal.ply": "gaussian_scenes", "fused.ply": "gaussian_donut"}
    path = SHARED_DATA / scene[meta["scene"]] / meta["scene"]
    if not path.exists():
        pytest.skip(f"shared data not found: {path}")
    assert meta["gsplat"] == peer.GSPLAT_VERSION
    c = meta["camera"]
    camera = Camera(eye=tuple(c["eye"]), target=tuple(c["target"]), up=tuple(c["up"]),
                    width=c["width"], height=c["height"], fov_y=c["fov_y"], near=c["near"])
    viewmat, K = peer.camera_to_gsplat(camera)
    np.testing.assert_allclose(viewmat, meta["viewmat"], atol=1e-12)
    np.testing.assert_allclose(K, meta["K"], atol=1e-12)
    gaussians = peer.read_3dgs_ply(path)
    assert len(gaussians) == meta["gaussians"]
    image, alpha = peer.gsplat_render(gaussians, camera, eps2d=meta["eps2d"],
                                      antialiased=meta["antialiased"],
                                      background=meta["background"])
    assert stored["image"].shape == (c["height"], c["width"], 3)
    np.testing.assert_allclose(image, stored["image"].astype(np.float32), atol=1e-3)
    np.testing.assert_allclose(alpha, stored["alpha"].astype(np.float32), atol=1e-3)
    assert 0.2 < alpha.mean() < 0.9  # the scene fills the frame, not a speck in it


def test_cameras_json_view_gives_the_same_camera(tmp_path):
    """A view of the 3DGS trainer's cameras.json (``position``: the camera centre;
    ``rotation``: camera-to-world, rows; OpenCV axes) comes back as the camera it was
    written from, and is the default camera of a scene beside it."""
    camera = Camera(eye=(0.3, -0.2, 2.5), target=(0.1, 0.05, 0.0), up=(0.2, -1.0, 0.1),
                    width=64, height=48, fov_y=35.0)
    viewmat, K = peer.camera_to_gsplat(camera)
    world_from_camera = np.linalg.inv(viewmat)
    view = {"id": 0, "img_name": "x", "width": 640, "height": 480,
            "position": world_from_camera[:3, 3].tolist(),
            "rotation": world_from_camera[:3, :3].tolist(),
            "fx": K[0, 0] * 10, "fy": K[1, 1] * 10}
    (tmp_path / "cameras.json").write_text(json.dumps([view]))
    g = one_gaussian((0.0, 0.0, 0.0), 0.1, 0.5, np.zeros(3))
    again = peer.default_camera(g, 64, 48, scene_path=tmp_path / "point_cloud.ply")
    viewmat2, K2 = peer.camera_to_gsplat(again)
    np.testing.assert_allclose(viewmat2, viewmat, atol=1e-12)
    np.testing.assert_allclose(K2, K, rtol=1e-12)
