"""The preparation's rules that the in-memory steps (``pointcloud``) and the chunks
(``chunks``, which joins what the chunks decided alone) both apply."""

from __future__ import annotations

import numpy as np

OUTLIER_RADIUS_FACTOR = 4.0  # radius <= this x the median radius of the cloud
TIE_FRACTION = 0.05  # a vote under this fraction of its votes' total |n . d| is a tie


def sheet_votes(mean: np.ndarray) -> np.ndarray:
    """The vote of a component whose views tie (``outward_votes``): its mean normal's
    (n_comp, 3) (y, z, x) first component over 0.1 in size (up, else +z, else +x)."""
    mean = mean / np.maximum(np.linalg.norm(mean, axis=1), 1e-300)[:, None]
    first = np.argmax(np.abs(mean) > 0.1, axis=1)
    return mean[np.arange(len(mean)), first]



def outlier_cap(r_area: np.ndarray) -> float:
    """The radii's cap for lone fliers: ``OUTLIER_RADIUS_FACTOR`` x the median of the
    cloud's r_area (:func:`area_radii`)."""
    return OUTLIER_RADIUS_FACTOR * np.median(r_area)
