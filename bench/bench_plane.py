"""Benchmark: the paper's Plane (262,144 surfels) at 512x512, c = 2.5, three apertures.

Reports #FRAG (thousands), #PTS (splats rendered) and milliseconds per frame (median of
--repeat frames after a warm-up frame, so JIT compilation is excluded), plus the time per
stage. Without LOD (``RenderSettings(lod=False)``): the fragment count, and the time, grow
with the aperture; ``bench/table1.py`` compares with LOD.

    python bench/bench_plane.py            # prints a markdown table
    python bench/bench_plane.py --repeat 9
    python bench/bench_plane.py --analytic  # the paper's 1 - e^-c normalisation
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numba

import dofsplat as ds
from dofsplat.demo import plane_scene

APERTURES = (0.0, 0.1, 0.4)  # world units; the plane is 4 units wide, the eye 3.4 away


def machine() -> str:
    cpu = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{cpu}, {os.cpu_count()} cores, numba {numba.__version__} with {numba.get_num_threads()} threads"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--analytic", action="store_true",
                    help="normalise kernels by 1 - e^-c (the paper) instead of their pixel sums")
    args = ap.parse_args(argv)
    surfels, camera, lens = plane_scene(512, 512)
    settings = ds.RenderSettings(cutoff=2.5, exact_normalization=not args.analytic, lod=False)
    xy, depth = camera.project(surfels.positions)
    in_view = (depth > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < 512) & (xy[:, 1] >= 0) & (xy[:, 1] < 512)
    depth_in_view = depth[in_view]
    print(f"machine: {machine()}")
    print()
    print("| aperture A | max CoC (px) | #FRAG (k) | #PTS | tile pairs (k) | ms / frame | project | bin | raster |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for a in APERTURES:
        this = ds.ThinLens(focus_distance=lens.focus_distance, aperture=a)
        ds.render(surfels, camera, this, settings)  # warm-up (JIT, caches)
        runs = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            res = ds.render(surfels, camera, this, settings)
            runs.append((time.perf_counter() - t) * 1000)
            last = res.stats
        coc = float(this.coc_radius_px(depth_in_view, camera).max())
        print(f"| {a:g} | {coc:.1f} | {last['fragments'] / 1000:,.0f} | {last['splats_rendered']:,} | "
              f"{last['tile_pairs'] / 1000:,.0f} | "
              f"{statistics.median(runs):.0f} | {last['project_ms']:.0f} | {last['bin_ms']:.0f} | "
              f"{last['raster_ms']:.0f} |")


if __name__ == "__main__":
    main()
