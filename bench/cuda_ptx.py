"""Compile every CUDA kernel to PTX without a GPU: a typing check for the CUDA backend.

numba's CUDA simulator runs kernels as Python, so it never types them: a kernel that the
simulator runs can still fail to compile for a GPU. This script

1. renders a few tiny frames under the simulator (in a child process) and records the
   numba argument types of every kernel launch (a kernel that none of them launches fails);
2. compiles each kernel for those types to PTX with numba-cuda's NVVM (``cuda.compile_ptx``;
   nested device functions are compiled for --cc, since there is no device to ask).

Needs numba-cuda with its NVVM (``pip install 'dofsplat[cuda]'``), no GPU and no driver.

    python bench/cuda_ptx.py            # prints one line per kernel and signature
    python bench/cuda_ptx.py --cc 8 6
"""

from __future__ import annotations

import argparse
import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def record(path: Path) -> None:
    """(Under the simulator.) Render tiny frames; pickle ({kernel name: [argument types]},
    every kernel's name)."""
    import numba
    import numpy as np

    import dofsplat as ds
    from dofsplat.backends import cuda as bc
    from dofsplat.backends import cuda_gauss as bg

    sigs: dict[str, set] = {}
    kernels: list[str] = []

    class Recorder:
        def __init__(self, name, kernel):
            self.name, self.kernel = name, kernel

        def __getitem__(self, config):
            launch = self.kernel[config]

            def call(*args):
                types = tuple(numba.typeof(getattr(a, "_ary", a)) for a in args)
                sigs.setdefault(self.name, set()).add(types)
                return launch(*args)
            return call

    for module in (bc, bg):
        for name in dir(module):
            obj = getattr(module, name)
            if type(obj).__name__ == "FakeCUDAKernel" and not getattr(obj, "_device", False) \
                    and obj.fn.__module__ == module.__name__:
                setattr(module, name, Recorder(f"{module.__name__}.{name}", obj))
                kernels.append(f"{module.__name__}.{name}")

    n = 6
    g = (np.arange(n) - (n - 1) / 2) / n
    x, y = np.meshgrid(g, g)
    pos = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    disks = ds.Surfels(positions=pos, normals=np.tile([0.0, 0.0, 1.0], (n * n, 1)),
                       radius=np.full(n * n, 1.0 / n), colors=np.full((n * n, 3), 0.5))
    ellipses = ds.Surfels(positions=pos, normals=disks.normals, radius=disks.radius,
                          colors=disks.colors, tangent=np.tile([1.0, 0.0, 0.0], (n * n, 1)),
                          radius_v=disks.radius / 2, weight=np.ones(n * n))
    camera = ds.Camera(eye=(0, 0, 2), target=(0, 0, 0), width=16, height=16, fov_y=40)
    lens = ds.ThinLens(focus_distance=1.0, aperture=0.3)
    for model in (disks, ellipses):
        for settings in (ds.RenderSettings(lod=False), ds.RenderSettings(show_lod=True),
                         ds.RenderSettings(shading="none")):
            bc.render_frame(model, camera, lens, settings)
    bc.render_frame(disks, camera, lens, ds.RenderSettings(lens_samples=4))  # _accumulate
    x = np.arange(3000, dtype=np.uint8)  # a scan deep enough for _scan_add
    bc.exclusive_scan(bc._upload(x), x.size, bc.cuda.device_array(x.size + 1, np.int64))
    # a Gaussian scene: the pinhole, the default frame (the lens in layers, coarse ones too:
    # a blur of up to 5 px), and the parts drawn whole (cpu_gauss.LAYERS off)
    from dataclasses import replace

    from dofsplat.backends import cpu_gauss

    rng = np.random.default_rng(1)
    gaussians = ds.Gaussians(positions=rng.uniform(-0.5, 0.5, (20, 3)),
                             scales=rng.uniform(0.02, 0.1, (20, 3)),
                             rotations=rng.normal(size=(20, 4)), opacity=np.full(20, 0.8),
                             sh=rng.normal(0, 0.3, (20, 4, 3)))
    g_lens = ds.ThinLens(focus_distance=2.0, aperture=3.0)
    for frame_lens in (None, g_lens):
        bg.render_gaussians_cuda(gaussians, camera, frame_lens, ds.RenderSettings(device="cuda"))
    cpu_gauss.LAYERS = replace(cpu_gauss.LAYERS, enabled=False)
    bg.render_gaussians_cuda(gaussians, camera, g_lens, ds.RenderSettings(device="cuda"))
    with open(path, "wb") as f:
        pickle.dump(({k: sorted(v, key=str) for k, v in sigs.items()}, kernels), f)


def compile_all(path: Path, cc: tuple[int, int]) -> int:
    """Compile the recorded signatures (and the probe kernel) to PTX. Returns failures."""
    import numba
    import numba.cuda.dispatcher as dispatcher
    from numba import cuda

    class Device:  # what compile_device asks the (absent) current device for
        compute_capability = cc

    dispatcher.get_current_device = lambda: Device()
    import importlib

    with open(path, "rb") as f:
        sigs, kernels = pickle.load(f)
    sigs["dofsplat.backends.cuda.probe_kernel"] = [(numba.types.Array(numba.float64, 1, "C"),)]
    failures = 0
    for name in sorted(set(kernels) - set(sigs)):
        failures += 1
        print(f"FAIL  {name}: no frame of --record launched it (add one)")
    for name in sorted(sigs):
        module, _, kernel = name.rpartition(".")
        for types in sigs[name]:
            try:
                fn = getattr(importlib.import_module(module), kernel).py_func
                ptx, _ = cuda.compile_ptx(fn, types, cc=cc)
                print(f"ok    {name}: {len(ptx):,} characters of PTX")
            except Exception as e:  # noqa: BLE001 - report every kernel, then fail
                failures += 1
                print(f"FAIL  {name}{types}: {type(e).__name__}: {e}")
    return failures


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cc", nargs=2, type=int, default=(9, 0), metavar=("MAJOR", "MINOR"),
                    help="compute capability to compile for (default: 9 0, Hopper)")
    ap.add_argument("--record", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.record:
        record(args.record)
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "signatures.pkl"
        env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
        subprocess.run([sys.executable, __file__, "--record", str(path)], env=env, check=True,
                       cwd=ROOT)
        failures = compile_all(path, tuple(args.cc))
    print(f"{failures} kernel(s) failed to compile" if failures else "every kernel compiled")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
