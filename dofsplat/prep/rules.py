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
    return OUTLIER_RADIUS_FACTOR * median(r_area)


MEDIAN_BLOCK = 1 << 20  # values that ``median`` reads at a time
MEDIAN_BITS = 20  # the leading bits of a value that name its bucket in ``median``'s count


def median(a: np.ndarray) -> float:
    """np.median of a (N,) float64 array, the same value, read ``MEDIAN_BLOCK`` values at a
    time where N is more (the radii of a cloud on disk, a memory map, are never copied
    whole). For values > 0 the bits of a float64 order as the values do: a first pass counts
    the values by their leading ``MEDIAN_BITS`` bits, a second gathers those of the one or
    two buckets that hold the middle ranks, and they are sorted. Anything else (a value
    <= 0 or not finite) is np.median's of the whole."""
    n = len(a)
    if n <= MEDIAN_BLOCK:
        return float(np.median(a))
    shift = np.uint64(64 - MEDIAN_BITS)
    counts = np.zeros(1 << MEDIAN_BITS, np.int64)
    for s in range(0, n, MEDIAN_BLOCK):
        part = np.ascontiguousarray(a[s:s + MEDIAN_BLOCK], np.float64)
        if not (np.all(part > 0.0) and np.all(np.isfinite(part))):
            return float(np.median(np.asarray(a)))
        counts += np.bincount(part.view(np.uint64) >> shift, minlength=len(counts))
    ranks = ((n - 1) // 2, n // 2)
    upto = np.cumsum(counts)
    buckets = np.searchsorted(upto, ranks, "right")
    first, last = int(buckets[0]), int(buckets[1])
    below = int(upto[first - 1]) if first else 0
    found = []
    for s in range(0, n, MEDIAN_BLOCK):
        part = np.ascontiguousarray(a[s:s + MEDIAN_BLOCK], np.float64)
        bucket = part.view(np.uint64) >> shift
        found.append(part[(bucket >= first) & (bucket <= last)])
    values = np.sort(np.concatenate(found))
    middle = values[[ranks[0] - below, ranks[1] - below]]
    return float(np.mean(middle)) if n % 2 == 0 else float(middle[0])
