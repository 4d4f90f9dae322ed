import os
from pathlib import Path

import numpy as np
import pytest

import dofsplat as ds

import cudasim
import skip_guard
# DOFSPLAT_MAX_SKIPS: more skips than that fail the run (tests/skip_guard.py)
from skip_guard import pytest_sessionfinish, pytest_terminal_summary  # noqa: F401


def pytest_addoption(parser):
    cudasim.add_option(parser)  # --cudasim: the CUDA tests on numba's simulator


def pytest_configure(config):
    cudasim.configure(config)  # (before any test module imports numba)
    skip_guard.pytest_configure(config)


def pytest_ignore_collect(collection_path, config):
    return cudasim.ignore_collect(collection_path, config)


def pytest_collection_modifyitems(config, items):
    cudasim.select(config, items)

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session", autouse=True)
def _private_cache(tmp_path_factory):
    """Keep what the CLI caches out of the user's ~/.cache, and cache nothing unless a test
    asks (a prepared model read back would skip the preparation a test is about). The
    compiled kernels stay in the user's kernel folder (``dofsplat.jit``), for this process
    and the CLI's subprocesses: a fresh folder would compile them again in every run."""
    from dofsplat.jit import kernel_cache_folder

    os.environ.setdefault("DOFSPLAT_KERNEL_DIR", str(kernel_cache_folder()))
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("xdg-cache"))
    os.environ["DOFSPLAT_CACHE_MAX"] = "0"


@pytest.fixture(scope="session", autouse=True)
def _compiled():
    """Compile (or load from cache) the kernels once per session."""
    ds.render.__module__  # noqa: B018 - keep the import
    from dofsplat.render import warm_up
    warm_up()


def grid_surfels(n=32, spacing=1.0 / 32, z=0.0, color=(0.6, 0.3, 0.2), opacity=1.0,
                 center=(0.0, 0.0)):
    """An n x n square grid of disks in the plane z, facing +z, radius = spacing."""
    g = (np.arange(n) - (n - 1) / 2) * spacing
    x, y = np.meshgrid(g + center[0], g + center[1])
    pos = np.stack([x.ravel(), y.ravel(), np.full(n * n, z)], axis=1)
    return ds.Surfels(positions=pos, normals=np.tile([0.0, 0.0, 1.0], (n * n, 1)),
                      radius=np.full(n * n, spacing), colors=np.tile(color, (n * n, 1)),
                      opacity=np.full(n * n, opacity))


def front_camera(width=64, height=64, distance=2.0, fov=40.0):
    return ds.Camera(eye=(0.0, 0.0, distance), target=(0.0, 0.0, 0.0), width=width,
                     height=height, fov_y=fov, near=0.01)


def gaussian_ply_columns(positions, log_scales, rotations, logits, sh):
    """The vertex columns of a 3DGS PLY as the trainers write them, float32 copies in their
    order: x y z, nx ny nz (zeros), f_dc_0..2, f_rest_* (channel-major: red's K - 1
    coefficients, then green's, then blue's), opacity, scale_0..2, rot_0..3. positions
    (N, 3); log_scales (N, 3), log sigma; rotations (N, 4), w first, not normalised;
    logits (N,), the opacity before its sigmoid; sh (N, K, 3), K = (degree + 1)^2."""
    positions, log_scales, rotations, sh = (np.asarray(a) for a in (positions, log_scales,
                                                                   rotations, sh))
    n, k = sh.shape[:2]
    cols = {a: positions[:, i] for i, a in enumerate("xyz")}
    cols.update({a: np.zeros(n) for a in ("nx", "ny", "nz")})
    cols.update({f"f_dc_{c}": sh[:, 0, c] for c in range(3)})
    for c in range(3):
        for j in range(1, k):
            cols[f"f_rest_{c * (k - 1) + j - 1}"] = sh[:, j, c]
    cols["opacity"] = logits
    cols.update({f"scale_{i}": log_scales[:, i] for i in range(3)})
    cols.update({f"rot_{i}": rotations[:, i] for i in range(4)})
    return {name: np.array(v, np.float32) for name, v in cols.items()}


os.environ.setdefault("NUMBA_NUM_THREADS", "2")


def lion_points():
    """(positions (N, 3) float64, linear colours) of the lion scan, z up; skips without it."""
    path = SHARED_DATA / "lion_takanawa" / "lion_takanawa_xyzrgb.ply"
    if not path.exists():
        pytest.skip(f"shared data not found: {path}")
    from plyfile import PlyData

    from dofsplat.io import srgb_to_linear

    v = PlyData.read(str(path))["vertex"]
    pos = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    rgb = np.stack([v["red"], v["green"], v["blue"]], axis=1) / 255.0
    return pos, srgb_to_linear(rgb)
