#!/usr/bin/env bash
# The tests as CI runs them (.ci/run, the README's test command), from the project root:
#  1. the suite. Without a GPU the CUDA backend's tests skip here; DOFSPLAT_MAX_SKIPS, where
#     set (.ci/run sets it), fails the run when more of the others skip (tests/skip_guard.py).
#  2. the CUDA backend's tests on numba's CUDA simulator, which needs no GPU (numba's own
#     numba.cuda; NUMBA_ENABLE_CUDASIM is process-wide, hence a second pytest). Every CUDA
#     thread is a Python thread there, so the whole-frame tests run at one lens only (4 lens
#     parts, LOD): with the stage tests they launch every kernel of dofsplat/backends/cuda.py,
#     which the module's last test checks. No skips allowed, nor a simulator that fails to load.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pytest -q
DOFSPLAT_TEST_CUDASIM=1 NUMBA_ENABLE_CUDASIM=1 DOFSPLAT_REQUIRE_CUDA=1 DOFSPLAT_MAX_SKIPS=0 \
    python3 -m pytest -q tests/test_cuda.py -m cuda -k "not test_frame_matches_cpu or A2-lod"
