#!/usr/bin/env bash
# The check for a session that is lent a GPU machine (the developers' brief): the CUDA parity
# tests (surfels and Gaussian scenes), then bench/gpu.py and bench/gpu_gauss.py, in one call;
# what they print goes to $OUT (default ./gpu-check).
#
# The GPU machine has numba and numba-cuda but not this package's other needs, and cannot
# reach a package registry, so prepare two ignored folders here and carry them:
#
#   printf '/.whl/\n/.gpudata/\n' >> .git/info/exclude
#   mkdir -p .gpudata && cp ../shared/data/lion_takanawa/lion_takanawa_xyzrgb.ply \
#       ../shared/data/stanford_dragon/dragon_vrip.ply.gz ../shared/data/gaussian_donut/fused.ply \
#       ../shared/data/gaussian_scenes/{guitar.compressed.ply,biker.spz} .gpudata/ &&
#   cp -r ../shared/data/gaussian_scenes/playbot/0_0 .gpudata/
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
#       --implementation cp --platform manylinux_2_28_x86_64 -d .whl plyfile==1.1.5 numpy==2.4.6
#
# numpy 2.4: the machine's numpy 2.5.2 broke numba-cuda 0.30.4 ("module 'numpy' has no
# attribute 'row_stack'" in the first kernel). Then, on the machine: bash bench/gpu_check.sh
# (about 7 min on an H100 with 16 CPU threads; TEST_S, BENCH_S and GAUSS_S cap the three
# steps, 0 skips one; TEST_K selects tests (pytest -k); BENCH_ARGS and GAUSS_ARGS pass
# options to bench/gpu.py and bench/gpu_gauss.py, e.g. "--scenes plane lion").
set -u
cd "$(dirname "$0")/.."
OUT=${OUT:-gpu-check}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/numba-cache}
if compgen -G ".whl/*.whl" >/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site:$PWD
fi
{
    date -u; nvidia-smi; lscpu | grep -E "Model name|^CPU\(s\)"
    python3 -c "import importlib.metadata as m; print({p: m.version(p) for p in ('numba', 'numba-cuda', 'llvmlite', 'numpy', 'scipy')})"
    python3 -c "from dofsplat.backends import cuda_problem; print('cuda_problem:', cuda_problem())"
} 2>&1 | tee "$OUT/env.txt"
t0=$(date +%s)
if [ "${TEST_S:-170}" != 0 ]; then
    DOFSPLAT_REQUIRE_CUDA=1 timeout "${TEST_S:-170}" python3 -m pytest -q -p no:cacheprovider \
        --durations=8 ${TEST_K:+-k "$TEST_K"} tests/test_cuda.py 2>&1 | tee "$OUT/test_cuda.txt"
    echo "tests took $(( $(date +%s) - t0 )) s" | tee -a "$OUT/test_cuda.txt"
fi
t0=$(date +%s)
data=../shared/data
[ -d .gpudata ] && data=.gpudata
if [ "${BENCH_S:-330}" != 0 ]; then
    # shellcheck disable=SC2086 - BENCH_ARGS is a list of options
    timeout "${BENCH_S:-330}" python3 -W ignore::Warning bench/gpu.py --data "$data" --repeat 20 \
        --cpu-repeat 2 ${BENCH_ARGS:-} --json "$OUT/gpu.json" 2>&1 | tee "$OUT/gpu.md"
    echo "bench took $(( $(date +%s) - t0 )) s" | tee -a "$OUT/gpu.md"
fi
t0=$(date +%s)
if [ "${GAUSS_S:-240}" != 0 ]; then
    # shellcheck disable=SC2086 - GAUSS_ARGS is a list of options
    timeout "${GAUSS_S:-240}" python3 -W ignore::Warning bench/gpu_gauss.py --data "$data" \
        ${GAUSS_ARGS:-} --json "$OUT/gpu_gauss.json" 2>&1 | tee "$OUT/gpu_gauss.md"
    echo "Gaussian bench took $(( $(date +%s) - t0 )) s" | tee -a "$OUT/gpu_gauss.md"
fi
