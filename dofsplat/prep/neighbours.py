"""Neighbours and directions: the geometric queries that the surfel preparation shares.

``nearest_neighbours`` (scipy's k-d tree, in chunks with a progress bar) serves the normal
and radius estimation (``pointcloud``) and the per-point normalisation (``normalise``);
``fibonacci_directions`` spreads directions over the sphere for both.
"""

from __future__ import annotations

import math
import sys

import numpy as np

from ..parallel import interrupt_after

QUERY_CHUNK = 1 << 16  # points per k-d tree query, the unit of the progress bar


def nearest_neighbours(positions: np.ndarray, k: int, *, distances: bool = True,
                       progress: bool = False, desc: str = "neighbours"):
    """The k nearest neighbours of every point, the point itself first.

    positions: (N, 3) float64. Returns (dist (N, k+1) float64, idx (N, k+1) int32, or
    int64 for 2^31 points or more): column 0 is the point itself (distance 0), columns
    1..k its neighbours by increasing distance. distances=False returns (None, idx), for
    callers that need only the lists.

    The lists are the largest arrays of a preparation (issue 50): int32 indices, and no
    distances where none are needed, make them 12 or 4 bytes a neighbour and a point
    instead of 16.
    """
    from scipy.spatial import cKDTree

    n = len(positions)
    tree = cKDTree(positions)
    dist = np.empty((n, k + 1), np.float64) if distances else None
    idx = np.empty((n, k + 1), index_dtype(n))
    with _progress_bar(n, desc, progress) as bar:
        for start in range(0, n, QUERY_CHUNK):
            stop = min(n, start + QUERY_CHUNK)
            with interrupt_after():  # (its threads write into d and i: parallel.py)
                d, i = tree.query(positions[start:stop], k + 1, workers=-1)
            idx[start:stop] = i
            if distances:
                dist[start:stop] = d
            bar.update(stop - start)
    return dist, idx


def index_dtype(n: int) -> type:
    """The integer type of neighbour indices into n points: int32 while they fit."""
    return np.int32 if n <= np.iinfo(np.int32).max else np.int64


def as_index_array(idx: np.ndarray) -> np.ndarray:
    """Neighbour indices as the kernels take them: int32 or int64, as they come (an
    int64 copy of int32 lists would double their memory), other integers as int64."""
    idx = np.asarray(idx)
    return idx if idx.dtype in (np.int32, np.int64) else idx.astype(np.int64)


def _progress_bar(total: int, desc: str, enabled: bool):
    from tqdm import tqdm

    show = enabled and total > QUERY_CHUNK and sys.stderr.isatty()
    return tqdm(total=total, desc=desc, unit="pt", unit_scale=True, file=sys.stderr,
                disable=not show, leave=False)


def fibonacci_directions(n: int) -> np.ndarray:
    """n unit vectors spread evenly over the sphere, (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), z, r * np.sin(phi)], axis=1)
