"""How long the first render compiles, stage by stage (issue 18: the first run's notice).

    python bench/compile_time.py

Runs the CPU pipeline's stages once on a two-surfel frame (LOD, the aperture's disc, soft
reconstruction: what ``dofsplat demo`` needs) in a subprocess whose numba cache is a fresh,
empty folder (NUMBA_CACHE_DIR), so that every kernel compiles and the user's cache is left
alone, then once more from that cache. Prints the seconds per stage. Then the first frame
as a user meets it: ``import dofsplat`` and one small demo frame in a fresh cache, where
``backends.cpu.warm_up`` compiles the rasteriser in a second process beside the rest, and
the same with that second process turned off (``warm_up`` without it, the old way).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile

STAGES = r'''
import time
import dofsplat as ds
from dofsplat.backends import cpu
from dofsplat.frame import merge_parameters
s = ds.Surfels(positions=[[0, 0, 0], [0.1, 0, 0]], normals=[[0, 0, 1], [0, 0, 1]],
               radius=[0.1, 0.1], colors=[[1, 1, 1], [1, 1, 1]])
cam = ds.Camera(eye=(0, 0, 1), target=(0, 0, 0), width=8, height=8)
lens = ds.ThinLens(focus_distance=0.5, aperture=0.1)
st = ds.RenderSettings()
def timed(name, f):
    t = time.perf_counter(); r = f(); print(f"{name:40s} {time.perf_counter() - t:5.1f} s", flush=True); return r
t0 = time.perf_counter()
src = timed("select (LOD hierarchy and cut)", lambda: cpu.select(s, cam, lens, st))
rgb = timed("shade", lambda: cpu.shade_surfels(src, cam, st))
sp, bb, vis = timed("project", lambda: cpu.project(src, rgb, cam, lens, st))
bands = timed("plan bands", lambda: cpu.plan_bands(bb, vis, cam, st))
timed("rasterise (front pass, bins, A-buffer)", lambda: cpu.rasterize(
    sp, bb, vis, bands, cam, st, merge_parameters(cam, lens, st), lens))
print(f"{'total':40s} {time.perf_counter() - t0:5.1f} s")
'''


FIRST_FRAME = r'''
import sys, time
t0 = time.perf_counter()
import dofsplat as ds
from dofsplat.backends import cpu
from dofsplat.demo import demo_scene
if sys.argv[1] == "serial":
    cpu._start_rasteriser_compile = lambda: None  # every kernel in this process
s, cam, lens = demo_scene(160, 120)
ds.render(s, cam, lens, ds.RenderSettings())
print(f"first frame, {sys.argv[1]:8s} (import, compile, render) {time.perf_counter() - t0:5.1f} s")
'''


def main() -> int:
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for what in ("cold: every kernel compiles", "warm: loaded from numba's cache"):
            print(f"-- {what}")
            subprocess.run([sys.executable, "-c", STAGES], env=env, check=True)
    print("-- the first frame in a fresh cache")
    for mode in ("serial", "parallel", "serial", "parallel"):
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, NUMBA_CACHE_DIR=cache)
            subprocess.run([sys.executable, "-c", FIRST_FRAME, mode], env=env, check=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
