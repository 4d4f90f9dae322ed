"""The peer benchmark's pixel filter (bench/peer_mitsuba.py, ``--filter ewa``)."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from peer_mitsuba import ewa_blur  # noqa: E402


def test_ewa_blur_adds_the_prefilter_less_the_box():
    """A box-filtered point, blurred, has the paper's prefilter's variance, 1 px² per axis:
    the blur's 1 - 1/12 and the box's 1/12 (a uniform square of side 1). The blur of a
    discrete delta is scipy's sampled Gaussian, truncated at 4 sigma: its second moment
    differs from sigma² by under 1e-3 (mass beyond 4 sigma: 6e-5), hence the bound."""
    image = np.zeros((33, 33, 3))
    image[16, 16, :] = 1.0
    out = ewa_blur(image)[:, :, 1]
    x = np.arange(33) - 16.0
    assert abs(out.sum() - 1.0) < 1e-9
    var_x = (out.sum(axis=0) * x * x).sum()
    var_y = (out.sum(axis=1) * x * x).sum()
    for var in (var_x, var_y):
        assert abs(var + 1.0 / 12.0 - 1.0) < 1e-3
    assert np.allclose(ewa_blur(image)[:, :, 0], out)  # channels blurred alike, not mixed
