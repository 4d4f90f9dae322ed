"""The memory of a point cloud's preparation (issue 50): int32 neighbour lists, distances only
where needed, (rows, k+1) temporaries a block of rows at a time, and the same surfels bit
for bit as the whole-array computation they replaced (bench/prep_memory.py measures it on
a large scan)."""

import math
import tracemalloc

import numpy as np
import pytest
from scipy.spatial import cKDTree

import dofsplat as ds
from dofsplat.prep import neighbours, normalise
from dofsplat.prep import pointcloud as pc
from dofsplat.prep.neighbours import nearest_neighbours

K = 24  # pc.DEFAULT_K


def scan(n, seed=0):
    """A small terrain scan: a wavy height field sampled at random (x, y), coordinates at
    millimetres (ties and a few duplicates, as in a LAS file), with a sphere of 2,000 points
    above it (a second component for the orientation) and colours."""
    rng = np.random.default_rng(seed)
    m = n - 2000
    xy = rng.uniform(0.0, 40.0, (m, 2))
    z = 1.5 * np.sin(xy[:, 0] / 6.0) * np.cos(xy[:, 1] / 9.0) + 0.02 * rng.standard_normal(m)
    ground = np.column_stack([xy[:, 0], z, xy[:, 1]])
    d = rng.standard_normal((2000, 3))
    ball = (20.0, 6.0, 20.0) + 2.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    pts = np.round(np.concatenate([ground, ball]), 3)
    return pts, rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)


def whole_array_surfels(positions, colors, k=K, smooth=True):
    """points_to_surfels(..., normalise="none") as it was computed before issue 50: int64
    lists and float64 distances of all points at once, the (N, k+1, 3) differences whole,
    the density's formula over the whole (N, k+1) matrix (the slow twin)."""
    pts, cols, _ = pc._check_inputs(positions, colors, None, "twin")
    pts, cols, _, _ = pc.merge_duplicates(pts, cols, None, "twin")
    dist, idx = cKDTree(pts).query(pts, k + 1)
    assert idx.dtype == np.int64
    normals, centroids = pc.pca_planes(pts, idx)
    if smooth:
        pts = pc.project_to_planes(pts, normals, centroids)
        dist = np.linalg.norm(pts[idx] - pts[:, None, :], axis=2)
        order = np.argsort(dist, axis=1, kind="stable")
        dist, idx = np.take_along_axis(dist, order, 1), np.take_along_axis(idx, order, 1)
    normals = pc.orient_normals(pts, normals, idx[:, 1:pc.ORIENT_K + 1],
                                fixed=np.zeros(len(pts), bool))
    reach = dist[:, -1:]
    s2 = (reach / pc.DENSITY_BANDWIDTH) ** 2
    phi = np.exp(-dist * dist / (2 * s2)) - np.exp(-reach * reach / (2 * s2))
    q = 0.5 * pc.DENSITY_BANDWIDTH ** 2
    integral = 2 * math.pi * s2[:, 0] * (1 - math.exp(-q) * (1 + q))
    r_area = 1.0 / np.sqrt(np.clip(phi, 0, None).sum(axis=1) / integral)
    limit = np.minimum(pc.CLUSTER_RADIUS_FACTOR * dist[:, 4],
                       pc.OUTLIER_RADIUS_FACTOR * np.median(r_area))
    radius, weight = pc.surfel_radii(pts, normals, idx, r_area, limit)  # all k+1 columns
    return ds.Surfels(positions=pts, normals=normals, radius=radius, colors=cols,
                      weight=weight)


def assert_same_surfels(a, b):
    for name in ("positions", "normals", "radius", "colors", "opacity", "weight"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def small_blocks(monkeypatch):
    """Blocks of a few hundred rows, so that a small cloud crosses many block edges."""
    monkeypatch.setattr(pc, "ROW_CHUNK", 300)
    monkeypatch.setattr(neighbours, "QUERY_CHUNK", 1000)


def test_neighbour_lists_are_int32_and_the_distances_optional():
    pts, _ = scan(6000)
    dist, idx = nearest_neighbours(pts, 12)
    d_ref, i_ref = cKDTree(pts).query(pts, 13)
    assert idx.dtype == np.int32  # 4 bytes a neighbour, not 8
    assert np.array_equal(idx, i_ref) and np.array_equal(dist, d_ref)
    none, idx_only = nearest_neighbours(pts, 12, distances=False)
    assert none is None and np.array_equal(idx_only, idx)
    assert neighbours.index_dtype(2 ** 31 - 1) == np.int32
    assert neighbours.index_dtype(2 ** 31) == np.int64


@pytest.mark.parametrize("smooth", [True, False])
def test_the_preparation_equals_its_whole_array_twin_bit_for_bit(monkeypatch, smooth):
    pts, colors = scan(30_000)
    twin = whole_array_surfels(pts, colors, smooth=smooth)
    fast = pc.points_to_surfels(pts, colors, k=K, smooth=smooth, normalise="none",
                                progress=False)
    assert_same_surfels(fast, twin)
    small_blocks(monkeypatch)  # the blocks' edges change nothing either
    blocks = pc.points_to_surfels(pts, colors, k=K, smooth=smooth, normalise="none",
                                  progress=False)
    assert_same_surfels(blocks, twin)


def test_the_object_weights_of_int32_lists_equal_int64_ones(monkeypatch):
    pts, colors = scan(20_000, seed=1)
    surfels = pc.points_to_surfels(pts, colors, k=K, normalise="none", progress=False)
    fast = normalise.object_weights(surfels, progress=False)

    def int64_lists(positions, k, **options):
        return None, cKDTree(positions).query(positions, k + 1)[1]

    monkeypatch.setattr(normalise, "nearest_neighbours", int64_lists)
    assert np.array_equal(fast, normalise.object_weights(surfels, progress=False))


def test_the_extreme_point_vote_equals_its_formula():
    """outward_votes' fallback, one (N, 8) array at a time, against its one-line formula."""
    rng = np.random.default_rng(2)
    n, n_comp = 5000, 7
    label = np.sort(rng.integers(0, n_comp, n)).astype(np.int32)
    p, nrm = rng.standard_normal((n, 3)), rng.standard_normal((n, 3))
    d = neighbours.fibonacci_directions(8)
    starts = np.r_[0, np.nonzero(np.diff(label))[0] + 1]
    reach = p @ d.T
    top = np.maximum.reduceat(reach, starts, axis=0)
    formula = np.bincount(label, np.where(reach >= top[label], nrm @ d.T, 0.0).sum(axis=1),
                          n_comp)
    assert np.array_equal(pc._extreme_support(p, nrm, label, starts, d, n_comp), formula)


def test_the_preparation_peaks_under_800_bytes_a_point(monkeypatch):
    """numpy's peak during points_to_surfels (tracemalloc; normalise="none"), in small
    blocks so that the fixed-size buffers do not count. The whole-array preparation peaked
    at 2.4 kB a point (the (N, k+1, 3) differences of the smoothed points, beside both
    queries' int64 lists and float64 distances); today's peak is the orientation's sparse
    graph, about 500 (k = 24): 800 leaves room for numpy's and scipy's versions."""
    pts, colors = scan(30_000, seed=3)
    small_blocks(monkeypatch)
    pc.points_to_surfels(pts, colors, k=K, normalise="none", progress=False)  # (compiled)
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        pc.points_to_surfels(pts, colors, k=K, normalise="none", progress=False)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert peak / len(pts) < 800, f"{peak / len(pts):.0f} bytes a point"


def unique_rows_twin(pts, cols, nrm):
    """merge_duplicates as it was (np.unique of the rows as bytes, with its inverse)."""
    keys = np.ascontiguousarray(pts).view(np.dtype((np.void, 24))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    order = np.sort(first)
    remap = np.empty(len(first), np.int64)
    remap[np.argsort(first)] = np.arange(len(first))
    group = remap[inverse]
    counts = np.bincount(group, minlength=len(order)).astype(np.float64)
    out_cols = np.stack([np.bincount(group, cols[:, c], len(order)) / counts
                         for c in range(3)], axis=1).astype(np.float32)
    return pts[order], out_cols, nrm[order], order


def test_merging_duplicates_by_hash_equals_np_unique():
    """merge_duplicates (a hash per row, sorted, rows compared within equal hashes: issue
    50) against the np.unique of the rows it replaced: many copies of a few rows, -0.0 and
    0.0 apart (different bytes), and a run of equal hashes forced by a bad hash."""
    rng = np.random.default_rng(5)
    base = np.round(rng.uniform(-1.0, 1.0, (3000, 3)), 2)
    pts = base[rng.integers(0, 3000, 20_000)]
    pts[:50] = 0.0
    pts[50:60] = -0.0
    cols = rng.uniform(0.0, 1.0, (20_000, 3)).astype(np.float32)
    nrm = rng.standard_normal((20_000, 3))
    fast = pc.merge_duplicates(pts, cols, nrm, "test")
    for a, b in zip(fast, unique_rows_twin(pts, cols, nrm)):
        assert np.array_equal(a, b)
    first, duplicates = pc.first_rows(pts)
    assert duplicates == 20_000 - len(fast[3])
    # every row in one run of equal hashes: the rows themselves decide
    first_all = np.empty(len(pts), np.int64)
    u = pts.view(np.uint64)
    same = np.zeros(len(pts), np.uint64)
    assert pc._first_of_runs(u, same, np.arange(len(pts)), first_all) == duplicates
    assert np.array_equal(first_all, first)
    assert pc.merge_duplicates(base, cols[:3000], nrm[:3000], "test")[3] is None
