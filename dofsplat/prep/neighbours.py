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


def nearest_neighbours(positions: np.ndarray, k: int, *, progress: bool = False,
                       desc: str = "neighbours"):
    """The k nearest neighbours of every point, the point itself first.

    positions: (N, 3) float64. Returns (dist (N, k+1) float64, idx (N, k+1) int64): column
    0 is the point itself (distance 0), columns 1..k its neighbours by increasing distance.
    """
    from scipy.spatial import cKDTree

    n = len(positions)
    tree = cKDTree(positions)
    dist = np.empty((n, k + 1), np.float64)
    idx = np.empty((n, k + 1), np.int64)
    with _progress_bar(n, desc, progress) as bar:
        for start in range(0, n, QUERY_CHUNK):
            stop = min(n, start + QUERY_CHUNK)
            with interrupt_after():  # (its threads write into d and i: parallel.py)
                d, i = tree.query(positions[start:stop], k + 1, workers=-1)
            dist[start:stop], idx[start:stop] = d, i
            bar.update(stop - start)
    return dist, idx


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
