"""Exact duplicate positions merged (issue 4; issue 50's memory): the first point of each
position kept, in the input's order, with the mean colour of its copies. The in-memory
preparation (``pointcloud.points_to_surfels``) merges a cloud's, the cloud on disk
(``cloudfile.write_cloud``) each chunk's."""

from __future__ import annotations

from ..jit import numba
import numpy as np


def first_rows(pts: np.ndarray):
    """(first (N,) int64, duplicates): each row's first row of the same (x, y, z), bit for
    bit, and how many rows are not their own first. A 64-bit hash of each row, sorted
    (stable: equal hashes keep the rows' order), then the rows compared within each run of
    equal hashes: 16 bytes a point beside the result, where np.unique's sort of the rows
    as bytes, with its inverse, took about 60 (issue 50)."""
    u = np.ascontiguousarray(pts, np.float64).view(np.uint64)
    h = np.empty(len(u), np.uint64)
    _row_hashes(u, h)
    perm = np.argsort(h, kind="stable")
    first = np.empty(len(u), np.int64)
    duplicates = _first_of_runs(u, h, perm, first)
    return first, duplicates


@numba.njit(cache=True, nogil=True, parallel=True)
def _row_hashes(u, h):
    """h[i]: a 64-bit hash of row i's three words (splitmix64's finaliser, chained)."""
    for i in numba.prange(u.shape[0]):
        x = np.uint64(0x9E3779B97F4A7C15)
        for c in range(3):
            x ^= u[i, c]
            x *= np.uint64(0xBF58476D1CE4E5B9)
            x ^= x >> np.uint64(31)
            x *= np.uint64(0x94D049BB133111EB)
            x ^= x >> np.uint64(29)
        h[i] = x


@numba.njit(cache=True, nogil=True)
def _first_of_runs(u, h, perm, first):
    """``first_rows``' walk: first[i] for every row, from the rows sorted by hash (perm,
    stable); returns the number of rows that are not their own first."""
    n = perm.shape[0]
    reps = np.empty(n, np.int64)  # a run's distinct rows so far (usually one)
    duplicates = 0
    a = 0
    while a < n:
        b = a + 1
        while b < n and h[perm[b]] == h[perm[a]]:
            b += 1
        n_reps = 0
        for j in range(a, b):  # in the rows' order: a first row comes before its copies
            i = perm[j]
            first[i] = i
            for q in range(n_reps):
                r = reps[q]
                if u[r, 0] == u[i, 0] and u[r, 1] == u[i, 1] and u[r, 2] == u[i, 2]:
                    first[i] = r
                    duplicates += 1
                    break
            if first[i] == i:
                reps[n_reps] = i
                n_reps += 1
        a = b
    return duplicates


def merge_duplicates(pts, cols, nrm, source):
    """Merge points at exactly the same position: first normal, mean colour. Returns the
    points, colours, normals and the input rows kept (None when none were merged), in the
    input order of the first of each position."""
    first, duplicates = first_rows(pts)
    if not duplicates:
        return pts, cols, nrm, None
    own = first == np.arange(len(first))
    order = np.flatnonzero(own)  # the rows kept, in the input order
    group = np.cumsum(own) - 1  # the new index of each input point (its first's)
    del own
    group = group[first]
    del first
    out_pts = pts[order]
    out_cols = None
    if cols is not None:
        counts = np.bincount(group, minlength=len(order)).astype(np.float64)
        out_cols = np.empty((len(order), 3), np.float32)
        for c in range(3):
            out_cols[:, c] = np.bincount(group, cols[:, c], len(order)) / counts
    out_nrm = None if nrm is None else nrm[order]
    return out_pts, out_cols, out_nrm, order
