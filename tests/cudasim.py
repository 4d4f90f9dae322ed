"""``pytest --cudasim``: the CUDA backend's tests on numba's CUDA simulator (hooks that
tests/conftest.py imports).

The README's test command runs the suite, where without a GPU the CUDA tests skip, then
``python3 -m pytest -q --cudasim``: numba's own ``numba.cuda`` simulates the kernels on the
CPU (no GPU, no numba-cuda). NUMBA_ENABLE_CUDASIM is read when numba is first imported and
holds for the process, hence a second pytest; the option sets it (and
DOFSPLAT_TEST_CUDASIM, DOFSPLAT_REQUIRE_CUDA: the simulator must load; DOFSPLAT_MAX_SKIPS=0:
nothing may skip) before any test module imports numba. Every CUDA thread is a Python thread
there, so of the whole-frame tests only the surfels' one with the lens in parts (2 on the
simulator) and LOD, the wide blurs' one-pass frame and the Gaussians' default and pinhole
frames run:
with the stage tests they launch every kernel of
dofsplat/backends/cuda.py and cuda_gauss.py, which the module's last parity test checks.
"""

from __future__ import annotations

import os
from pathlib import Path

SIMULATED_FILE = "test_cuda.py"
# the parity cases left out on the simulator (test name: the cases kept): they launch no
# kernel that the kept cases (or, for the whole lens's visibility views, the frame with
# LAYERS off) do not; the Gaussians' pinhole frame is the one to launch ``_finish``, the
# frames through the lens averaging their parts in linear light
LEFT_OUT = {"test_frame_matches_cpu": ("A2-lod",),
            "test_gaussian_frame_matches_cpu": ("default", "pinhole"),
            "test_gaussian_lens_visibility_matches_cpu": ("by-shifts",)}


def add_option(parser) -> None:
    parser.addoption("--cudasim", action="store_true",
                     help="run the CUDA backend's tests on numba's CUDA simulator only")


def configure(config) -> None:
    if config.getoption("--cudasim"):
        os.environ.update(DOFSPLAT_TEST_CUDASIM="1", NUMBA_ENABLE_CUDASIM="1",
                          DOFSPLAT_REQUIRE_CUDA="1", DOFSPLAT_MAX_SKIPS="0")


def ignore_collect(collection_path: Path, config) -> bool | None:
    if config.getoption("--cudasim") and collection_path.suffix == ".py" \
            and collection_path.name != SIMULATED_FILE:
        return True
    return None


def select(config, items) -> None:
    if not config.getoption("--cudasim"):
        return
    keep, drop = [], []
    for item in items:
        name, _, case = item.name.partition("[")
        whole_frame = name in LEFT_OUT and case.rstrip("]") not in LEFT_OUT[name]
        (drop if whole_frame or item.get_closest_marker("cuda") is None else keep).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep
