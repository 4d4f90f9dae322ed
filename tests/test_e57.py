"""E57 scans (io/e57.py, issue 18 item 7): several scans merged with their poses, colour,
intensity as grey, normals facing the scanner, z-up turned y-up; files written by pye57."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dofsplat import cli
from dofsplat.errors import DofsplatError
from dofsplat.io import load

pye57 = pytest.importorskip("pye57", reason="pye57 (the e57 extra) is not installed")


def grid(n=30, size=1.0):
    g = (np.arange(n) + 0.5) / n * size - size / 2
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    return x, y


def quaternion_about_z(deg):
    """(w, x, y, z) of a turn about z."""
    h = math.radians(deg) / 2
    return np.array([math.cos(h), 0.0, 0.0, math.sin(h)])


@pytest.fixture
def two_scans(tmp_path):
    """Two scans of the floor z = 0 (1 m squares, 900 points each), from scanners 2 m above
    their squares. Scan 0: red, in the file's frame, at x in [-0.5, 0.5]. Scan 1: intensity
    only (0..1000: a ramp along its own x), its frame turned 90 degrees about z and moved
    by (2, 0, 0), so its square lies at x in [1.5, 2.5]. The floor's normals must face up,
    towards the scanners (+z, which is +y once turned y-up)."""
    path = tmp_path / "site.e57"
    e57 = pye57.E57(str(path), mode="w")
    x, y = grid()
    n = x.size
    e57.write_scan_raw({"cartesianX": x, "cartesianY": y, "cartesianZ": np.full(n, -2.0),
                        "colorRed": np.full(n, 200, np.uint8),
                        "colorGreen": np.full(n, 30, np.uint8),
                        "colorBlue": np.full(n, 30, np.uint8)},
                       rotation=np.array([1.0, 0.0, 0.0, 0.0]),
                       translation=np.array([0.0, 0.0, 2.0]))
    e57.write_scan_raw({"cartesianX": x, "cartesianY": y, "cartesianZ": np.full(n, -2.0),
                        "intensity": (x + 0.5) * 1000.0},
                       rotation=quaternion_about_z(90.0),
                       translation=np.array([2.0, 0.0, 2.0]))
    e57.close()
    return path


def test_scans_merge_with_their_poses(two_scans):
    s = load(two_scans, normalise="none")
    assert len(s) == 1800
    p = s.positions.astype(np.float64)
    # y-up: the floor z = 0 is y = 0; the file's y is -z here
    np.testing.assert_allclose(p[:, 1], 0.0, atol=1e-3)
    first, second = p[:, 0] < 1.0, p[:, 0] > 1.0
    assert first.sum() == 900 and second.sum() == 900
    np.testing.assert_allclose([p[first, 0].min(), p[first, 0].max()], [-0.483, 0.483], atol=1e-3)
    np.testing.assert_allclose([p[second, 0].min(), p[second, 0].max()], [1.517, 2.483], atol=1e-3)
    # every normal faces its scanner, above the floor (+y)
    assert np.all(s.normals[:, 1] > 0.99)
    # scan 0 is red; scan 1 is grey from its intensity, which ramps along its own x axis,
    # the file's y after the 90-degree turn (the file's -z once y-up)
    red = s.colors[first]
    assert np.all(red[:, 0] > 0.5) and np.all(red[:, 1] < 0.05)
    grey = s.colors[second]
    np.testing.assert_allclose(grey[:, 0], grey[:, 1], atol=1e-6)
    np.testing.assert_allclose(grey[:, 1], grey[:, 2], atol=1e-6)
    along = -p[second, 2]  # the file's y
    assert np.corrcoef(along, grey[:, 0])[0, 1] > 0.95


def test_e57_renders_from_the_cli(two_scans, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["render", str(two_scans), "--size", "64x48", "--eye", "1", "3", "0.01",
                     "--target", "1", "0", "0"]) == 0
    assert (tmp_path / "site.png").exists()
    assert "1,800 points" in capsys.readouterr().err


def test_a_damaged_e57_is_one_error(tmp_path):
    bad = tmp_path / "bad.e57"
    bad.write_bytes(b"ASTM-E57" + bytes(200))
    with pytest.raises(DofsplatError, match="corrupt or truncated E57 file"):
        load(bad)
