"""The peer benchmark's pixel filter (bench/peer_mitsuba.py, ``--filter ewa``)."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from peer_mitsuba import ewa_blur  # noqa: E402


def test_ewa_blur_adds_the_prefilter_less_the_box():
    """Blurring adds the prefilter's variance less the box's: 1 - 1/12 px² per axis, so that
    with the box's own 1/12 (a uniform square of side 1) a point has the paper's 1 px². The
    blur of a discrete delta is scipy's sampled Gaussian, truncated at 4 sigma: its second
    moment differs from sigma² by under 1e-3 (mass beyond 4 sigma: 6e-5; measured 2.5e-5),
    hence the bound."""
    image = np.zeros((33, 33, 3))
    image[16, 16, 1] = 1.0  # one channel only: the blur must not spread it to the others
    blurred = ewa_blur(image)
    out = blurred[:, :, 1]
    x = np.arange(33) - 16.0
    assert abs(out.sum() - 1.0) < 1e-9
    var_x = (out.sum(axis=0) * x * x).sum()
    var_y = (out.sum(axis=1) * x * x).sum()
    for var in (var_x, var_y):
        assert abs(var + 1.0 / 12.0 - 1.0) < 1e-3
    assert not blurred[:, :, 0].any() and not blurred[:, :, 2].any()
