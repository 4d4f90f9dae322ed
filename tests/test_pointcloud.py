"""Bare points to surfels (dofsplat.prep.pointcloud): normals, orientation, radii, bad input."""

import dataclasses
import math
import re
import warnings

import numpy as np
import pytest
from conftest import SHARED_DATA, lion_points

import dofsplat as ds
from dofsplat.errors import DofsplatError
from dofsplat.prep.pointcloud import (
    MID_GREY,
    nearest_neighbours,
    neighbour_distances,
    orient_normals,
    pca_normals,
    pca_normals_slow,
    pca_planes,
    points_to_surfels,
    project_to_planes,
)
from dofsplat.render import RenderSettings, render


def fibonacci_sphere(n, radius=1.0):
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    return radius * np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def grid_points(n, h, rotation=None):
    """An n x n grid of spacing h in the z = 0 plane, optionally rotated in 3D."""
    g = (np.arange(n) - (n - 1) / 2) * h
    x, y = np.meshgrid(g, g)
    p = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    return p if rotation is None else p @ rotation.T


def rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def angles_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))


# -- normals ------------------------------------------------------------------------------


def test_pca_normals_on_a_sampled_sphere_within_2_degrees():
    # the requirement. A Fibonacci lattice of 5,000 points: the 16 neighbours of a
    # point span ~0.1 of the radius, where the sphere bends by a fraction of a degree
    pts = fibonacci_sphere(5000, radius=2.0)
    s = points_to_surfels(pts, progress=False)
    truth = s.positions / np.linalg.norm(s.positions, axis=1)[:, None]
    err = angles_deg(s.normals, truth)
    assert err.max() < 2.0, err.max()  # also checks the orientation: outward everywhere


def test_pca_normals_on_a_randomly_sampled_sphere_within_2_degrees():
    # random (Poisson) sampling makes lopsided neighbourhoods, which tilt the fitted plane
    # by up to ~2 degrees at 20,000 points; the tilt shrinks with the neighbourhood (as
    # 1 / sqrt(N)): at 40,000 points the worst measured is about 1.5 degrees
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(40000, 3))
    pts /= np.linalg.norm(pts, axis=1)[:, None]
    s = points_to_surfels(pts, progress=False)
    err = angles_deg(s.normals, s.positions / np.linalg.norm(s.positions, axis=1)[:, None])
    assert err.max() < 2.0, err.max()


def test_pca_normals_match_their_numpy_twin():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(2000, 3)) * [1.0, 0.5, 0.05]  # a noisy slab, and some blobs
    _, idx = nearest_neighbours(pts, 12)
    fast, slow = pca_normals(pts, idx), pca_normals_slow(pts, idx)
    # eigenvectors up to sign; the Jacobi sweeps converge to ~1e-15 off-diagonal
    assert np.all(np.abs(np.sum(fast * slow, axis=1)) > 1 - 1e-9)
    assert np.allclose(np.linalg.norm(fast, axis=1), 1.0, atol=1e-12)


def test_orientation_is_consistent_on_a_non_convex_closed_surface():
    # a torus: "outward from the centroid" would be wrong on the inner side; propagation
    # over the neighbour graph from the farthest point gets every normal outward
    n_u, n_v, big, small = 160, 60, 1.0, 0.35
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n_u, endpoint=False),
                       np.linspace(0, 2 * np.pi, n_v, endpoint=False))
    u, v = u.ravel(), v.ravel()
    centre = np.stack([big * np.cos(u), big * np.sin(u), np.zeros_like(u)], axis=1)
    normal = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    s = points_to_surfels(centre + small * normal, progress=False)
    assert np.all(np.sum(s.normals * normal, axis=1) > 0.95)


def test_orientation_towards_a_viewpoint():
    pts = grid_points(30, 0.1, rotation((1, 1, 0), 0.3))
    below = -5 * rotation((1, 1, 0), 0.3) @ np.array([0, 0, 1.0])
    s = points_to_surfels(pts, viewpoint=below, progress=False)
    assert np.all(np.sum(s.normals * (below - s.positions), axis=1) > 0)
    with pytest.raises(DofsplatError, match="viewpoint"):
        points_to_surfels(pts, viewpoint=(0, 0), progress=False)


def test_given_normals_are_kept_and_seed_the_orientation_of_missing_ones():
    pts = fibonacci_sphere(3000)
    inward = -pts
    s = points_to_surfels(pts, normals=inward, progress=False)
    assert np.allclose(s.normals, inward, atol=1e-6)  # kept, sign included
    partial = inward.copy()
    partial[::3] = 0.0  # unknown: estimated, then oriented like their given neighbours
    partial[1::7] = np.nan
    s = points_to_surfels(pts, normals=partial, progress=False)
    assert np.all(np.sum(s.normals * inward, axis=1) > 0.99)


def test_orient_normals_flips_a_scrambled_plane_back():
    rng = np.random.default_rng(3)
    pts = grid_points(40, 1.0)
    normals = np.tile([0.0, 0.0, 1.0], (len(pts), 1)) * rng.choice([-1.0, 1.0], (len(pts), 1))
    _, idx = nearest_neighbours(pts, 8)
    out = orient_normals(pts, normals, idx[:, 1:])
    assert abs(out[:, 2].sum()) == len(pts)  # all one way


def dome_on_terrain(seed=3, h=0.04):
    """An open scan: a concave terrain z = 0.05 (x^2 + y^2) on [-2, 2]^2 with a unit
    hemisphere standing on it (no samples under the dome), and the true outward normals."""
    rng = np.random.default_rng(seed)
    g = np.arange(-2, 2 + 1e-9, h)
    x, y = np.meshgrid(g, g)
    x = x.ravel() + rng.uniform(-0.3, 0.3, x.size) * h
    y = y.ravel() + rng.uniform(-0.3, 0.3, y.size) * h
    outside = x * x + y * y > 1.0
    x, y = x[outside], y[outside]
    ground = np.stack([x, y, 0.05 * (x * x + y * y)], axis=1)
    up = np.stack([-0.1 * x, -0.1 * y, np.ones_like(x)], axis=1)
    up /= np.linalg.norm(up, axis=1)[:, None]
    m = int(2 * np.pi / h ** 2)
    v = rng.normal(size=(3 * m, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    v = v[v[:, 2] > 0.05][:m]
    return np.concatenate([ground, v]), np.concatenate([up, v])


def test_orientation_of_an_open_scan_with_ground():
    # Hoppe's root, the point farthest from the centroid, is a corner of the terrain whose
    # normal leans towards the centroid: "away from the centroid" turned every normal
    # inward. Seen from around, the dome faces out and the terrain cancels out.
    pts, truth = dome_on_terrain()
    far = np.argmax(np.sum((pts - pts.mean(axis=0)) ** 2, axis=1))
    assert np.dot(truth[far], pts[far] - pts.mean(axis=0)) < 0  # the old rule fails here
    s = points_to_surfels(pts, progress=False, smooth=False)
    assert len(s) == len(pts)  # same order: no duplicates
    assert np.mean(np.sum(s.normals * truth, axis=1) > 0) > 0.99


@pytest.mark.parametrize("k", [16, None])
def test_lion_scan_ground_and_statue_face_out(k):
    # the lion's ground (z up) is a one-sided sheet; the old single-root rule turned the
    # whole scan inside out at k = 20, 24 and 32 (4 - 6 % of normals agreeing with the
    # default's). With the vote, of the flat surfels in the lowest tenth 90 / 89 / 88 %
    # face up at k = 16 / 24 / 32 (the rest are patches the propagation flips, across
    # the plants' stems and the base's undercut), and 97 / 99 / 91 % of the crown
    pos, _ = lion_points()
    s = points_to_surfels(pos, k=k, progress=False)
    z, nz = s.positions[:, 2], s.normals[:, 2]
    ground = (z < np.quantile(z, 0.1)) & (np.abs(nz) > 0.9)
    assert ground.sum() > 1000
    assert np.mean(nz[ground] > 0) > 0.8
    top = z > np.quantile(z, 0.999)  # the crown of the head
    assert np.mean(nz[top] > 0) > 0.85


# -- smoothing ----------------------------------------------------------------------------


def test_smoothing_puts_quantised_points_back_on_the_surface():
    # a sphere sampled at spacing ~0.025 with coordinates rounded to 0.02 (like the lion
    # scan's 1 cm at 1.4 cm spacing): the points move onto the surface along the normal,
    # and only along it, so the sampling density is kept
    pts = np.round(fibonacci_sphere(20000) / 0.02) * 0.02
    pts = np.unique(pts, axis=0)
    raw = points_to_surfels(pts, progress=False, smooth=False)
    smooth = points_to_surfels(pts, progress=False)
    assert np.array_equal(raw.positions, pts.astype(np.float32))  # smooth=False: as given
    err_raw = np.abs(np.linalg.norm(raw.positions, axis=1) - 1)
    err_smooth = np.abs(np.linalg.norm(smooth.positions, axis=1) - 1)
    # measured: mean 2.8e-3 -> 1.0e-3 (a plane fit over 24 neighbours of a curved surface
    # sits 1e-3 inside it: R^2 / 6 r); rms of the normal error 3.9 -> 1.7 degrees
    assert np.mean(err_smooth) < 0.5 * np.mean(err_raw)
    moved = smooth.positions.astype(np.float64) - pts
    along = np.sum(moved * smooth.normals, axis=1)
    across = np.linalg.norm(moved - along[:, None] * smooth.normals, axis=1)
    assert np.max(across) < 1e-6 + 1e-3 * np.max(np.abs(along))
    assert np.max(np.abs(along)) < 0.02


def test_projection_never_makes_two_points_one():
    pts = np.array([[0.0, 0.0, 0.1], [0.0, 0.0, -0.1], [1.0, 0.0, 0.0]])
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    centroids = np.zeros((3, 3))
    out = project_to_planes(pts, normals, centroids)
    assert np.array_equal(out[0], [0, 0, 0]) and np.array_equal(out[2], [1, 0, 0])
    assert np.array_equal(out[1], pts[1])  # would land on point 0: keeps its position
    assert len(np.unique(out, axis=0)) == 3


def test_pca_planes_and_neighbour_distances():
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(500, 3)) * [1.0, 1.0, 0.01]
    _, idx = nearest_neighbours(pts, 10)
    normals, centroids = pca_planes(pts, idx)
    assert np.allclose(normals, pca_normals(pts, idx))
    assert np.allclose(centroids, pts[idx].mean(axis=1))
    assert np.allclose(np.abs(normals[:, 2]), 1, atol=0.05)  # the flat cloud's z
    dist, idx2 = neighbour_distances(pts, idx[:, ::-1].copy())  # any order in, sorted out
    d_ref, i_ref = nearest_neighbours(pts, 10)
    assert np.allclose(dist, d_ref) and np.array_equal(idx2[:, 0], np.arange(500))


# -- radii and areas ---------------------------------------------------------------------


@pytest.mark.parametrize("tilt", [None, ((1, 2, 3), 0.7)])
def test_radii_on_a_regular_grid_equal_the_spacing(tilt):
    # the requirement: within 5 % (the density kernel gives 1.5 % on a square grid)
    h = 0.01
    rot = None if tilt is None else rotation(*tilt)
    pts = grid_points(60, h, rot)
    s = points_to_surfels(pts, progress=False)
    flat = pts if rot is None else pts @ rot  # back in the grid's plane
    inner = np.all(np.abs(flat[:, :2]) < 0.3 - 4 * h, axis=1)  # away from the edges
    assert np.allclose(s.radius[inner], h, rtol=0.05), (s.radius[inner].min(), s.radius[inner].max())
    # and each surfel stands for the area h^2: weight r^2 w = h^2 within 5 %
    assert np.allclose(s.radius[inner] ** 2 * s.weight[inner], h * h, rtol=0.05)


def test_irregular_samples_get_covering_disks_and_their_area():
    # a jittered grid: the disks widen to cover the gaps, the area per surfel stays right
    rng = np.random.default_rng(4)
    h = 0.02
    pts = grid_points(80, h)
    pts[:, :2] += rng.uniform(-0.5, 0.5, (len(pts), 2)) * h
    s = points_to_surfels(pts, normalise="none", progress=False)
    inner = np.all(np.abs(pts[:, :2]) < 0.8 - 5 * h, axis=1)
    area = s.radius ** 2 * s.weight
    assert abs(np.mean(area[inner]) / h ** 2 - 1) < 0.05  # the density estimate
    assert np.median(s.radius[inner]) > 1.1 * h  # wider than sqrt(area): coverage
    assert np.all(s.weight <= 1.0 + 1e-6)
    # no holes: face-on, with the kernels resolved (r ~ 6 px), every interior pixel is
    # covered, and better than by disks of radius sqrt(area) (measured minima 0.36, 0.20)
    from dofsplat.prep.normalise import interior_mask

    cam = ds.Camera(eye=(0, 0, 2.4), target=(0, 0, 0), width=320, height=320, fov_y=30)
    area_only = dataclasses.replace(s, radius=np.sqrt(area), weight=None)
    minima = []
    for model in (s, area_only):
        res = render(model, cam, None, RenderSettings(shading="none", lod=False))
        mask = interior_mask(res, cam)
        assert mask.sum() > 40000
        minima.append(res.weight[mask].min())
    assert minima[0] > 0.3  # a hole reads ~0
    assert minima[0] > minima[1] + 0.1


def test_outliers_do_not_become_giant_disks():
    pts = grid_points(40, 0.01)
    pts = np.vstack([pts, [[5.0, 5.0, 5.0], [5.01, 5.0, 5.0], [-4, 3, 1]]])
    s = points_to_surfels(pts, progress=False)
    assert s.radius.max() <= 4.0 * 0.01 * 1.05


# -- colours, duplicates, bad input ------------------------------------------------------


def test_colours_default_to_mid_grey_and_duplicates_merge():
    pts = grid_points(20, 0.1)
    s = points_to_surfels(pts, progress=False)
    assert np.allclose(s.colors, MID_GREY)
    from dofsplat.io import linear_to_srgb

    assert abs(linear_to_srgb(np.float32(MID_GREY)) - 0.5) < 2e-3
    cols = np.random.default_rng(5).uniform(0, 1, (len(pts), 3))
    doubled = np.vstack([pts, pts[:10]])
    doubled_cols = np.vstack([cols, 1 - cols[:10]])
    s = points_to_surfels(doubled, doubled_cols, progress=False)
    assert len(s) == len(pts)
    assert np.allclose(s.colors[:10], 0.5, atol=1e-6)  # mean of c and 1 - c
    assert np.allclose(s.colors[10:], cols[10:], atol=1e-6)


def test_nan_rows_are_dropped_with_a_warning():
    pts = grid_points(20, 0.1)
    pts[[3, 7]] = np.nan
    with pytest.warns(UserWarning, match="dropped 2 of 400"):
        s = points_to_surfels(pts, progress=False, source="scan.ply")
    assert len(s) == 398


@pytest.mark.parametrize("positions, message", [
    (np.zeros((0, 3)), "empty"),
    (np.zeros((5, 2)), r"shape \(N, 3\)"),
    (np.full((4, 3), np.nan), "no valid points"),
    (np.zeros((10, 3)), "at least 3 distinct points"),
])
def test_bad_point_clouds_are_one_clear_error(positions, message):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(DofsplatError, match=message):
            points_to_surfels(positions, progress=False)


def test_bad_k_and_shapes():
    pts = grid_points(10, 0.1)
    for k in (0, 3, 2.5, True, "8", 257, 10**6):
        # the whole message, the value as given (match="k" matched any message with a k)
        with pytest.raises(DofsplatError, match=re.escape(
                f"k (neighbours) must be an integer from 4 to 256, got {k!r}")):
            points_to_surfels(pts, k=k, progress=False)
    with pytest.raises(DofsplatError, match="colors"):
        points_to_surfels(pts, np.zeros((5, 3)), progress=False)
    with pytest.raises(DofsplatError, match="normals"):
        points_to_surfels(pts, normals=np.zeros((len(pts), 2)), progress=False)
    assert len(points_to_surfels(pts[:3], progress=False)) == 3  # k shrinks to fit


# -- the real dragon ---------------------------------------------------------------------


def test_dragon_vertices_normals_agree_with_the_mesh():
    path = SHARED_DATA / "stanford_dragon" / "dragon_vrip_res4.ply"
    if not path.exists():
        pytest.skip(f"shared data not found: {path}")
    from plyfile import PlyData

    from dofsplat.prep.meshes import vertex_normals

    ply = PlyData.read(str(path))
    v = ply["vertex"]
    pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    vert_n = vertex_normals(pts, np.vstack(ply["face"]["vertex_indices"]))
    used = np.linalg.norm(vert_n, axis=1) > 0  # 69: no face (2) or back-to-back faces
    s = points_to_surfels(pts, progress=False)
    assert len(s) == len(pts)  # no duplicate vertices in this file
    dots = np.sum(s.normals * vert_n, axis=1)[used]
    # orientation: this 5,205-vertex dragon is so coarse that its horns and claws are one
    # or two samples thick, where a sign can jump sheets. Measured 92.2 % right with the
    # defaults (k = 24, smoothing), 96.4 % with k = 16 and no smoothing: the plane fits
    # span both sides of those features and smoothing pulls the sides together. The full
    # dragon: 99.4 % with the defaults, 99.6 % with the old ones
    assert np.mean(dots > 0) > 0.9
    assert np.median(np.degrees(np.arccos(np.clip(np.abs(dots), 0, 1)))) < 10


def scene_points(up_axis: int, n=40, seed=0):
    """A scan of a ground (2 x 2, n x n points) with a box (0.5 high) standing on it, up
    along axis ``up_axis`` (1: y, 2: z)."""
    rng = np.random.default_rng(seed)
    g = np.linspace(-1, 1, n)
    a, b = (v.ravel() for v in np.meshgrid(g, g))
    ground = np.stack([a, b, np.zeros_like(a)], axis=1)
    ground = ground[(np.abs(a) > 0.3) | (np.abs(b) > 0.3)]
    h = np.linspace(0, 0.5, 12)
    s = np.linspace(-0.3, 0.3, 15)
    ws, wh = (v.ravel() for v in np.meshgrid(s, h))
    walls = [np.stack([np.full(ws.size, x), ws, wh], axis=1) for x in (-0.3, 0.3)]
    walls += [w[:, [1, 0, 2]] for w in walls]
    ta, tb = (v.ravel() for v in np.meshgrid(s, s))
    top = np.stack([ta, tb, np.full(ta.size, 0.5)], axis=1)
    pts = np.concatenate([ground, *walls, top]) + rng.normal(0, 1e-4, (1, 3))
    if up_axis == 1:  # z-up -> y-up
        pts = pts[:, [0, 2, 1]] * [1, 1, -1]
    return pts


@pytest.mark.parametrize("up_axis", [2, 1])
def test_the_ground_is_summed_a_block_at_a_time(up_axis, monkeypatch):
    """``ground_up`` reads a model ``ROW_BLOCK`` surfels at a time (a cloud prepared on disk
    is memory maps): in blocks of 500 its fractions, and so its hint, are one block's."""
    import dofsplat.prep.pointcloud as pc
    from dofsplat.prep.pointcloud import ground_up

    s = points_to_surfels(scene_points(up_axis), progress=False, normalise="none")
    whole = ground_up(s)
    monkeypatch.setattr(pc, "ROW_BLOCK", 500)
    assert len(s) > 4 * 500 and ground_up(s) == whole


@pytest.mark.parametrize("up_axis, expected", [(2, (0.0, 0.0, 1.0)), (1, None)])
def test_a_z_up_scan_is_recognised_by_its_ground(up_axis, expected, tmp_path):
    """Issue 18 item 3: a bare-point scan whose ground faces +z gets the hint z-up (the
    default camera then sees it upright from -y, like the same points read from LAS); a
    y-up one gets none (y-up is the default)."""
    from plyfile import PlyData, PlyElement

    from dofsplat.io import load
    from dofsplat.prep.pointcloud import ground_up

    pts = scene_points(up_axis)
    s = points_to_surfels(pts, progress=False, normalise="none")
    assert ground_up(s) == expected
    v = np.zeros(len(pts), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    v["x"], v["y"], v["z"] = pts.T
    path = tmp_path / "scan.ply"
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))
    assert load(path).up_hint == expected
    from dofsplat import cli

    stats = tmp_path / "s.json"
    assert cli.main(["render", str(path), "-o", str(tmp_path / "x.png"), "--size", "48x36",
                     "--stats", str(stats), "-q"]) == 0
    import json

    cam = json.loads(stats.read_text())["camera"]
    if expected is None:
        assert cam["up"] == [0.0, 1.0, 0.0] and cam["eye"][2] > cam["target"][2]
    else:
        assert cam["up"] == [0.0, 0.0, 1.0] and cam["eye"][1] < cam["target"][1]
