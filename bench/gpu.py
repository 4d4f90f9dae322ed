"""The CUDA backend against the CPU backend: milliseconds per frame (issue 6).

Scenes (cutoff c = 2.5):

* plane:  the paper's 262,144-surfel textured plane (``dofsplat.demo.plane_scene``);
* lion:   the Takanawa lion scan (341,989 points; Potree), as in ``bench/table1.py``;
* dragon: the Stanford dragon's 437k vertices as surfels (Stanford 3D Scanning Repository);
* synth10m: a 3,163 x 3,163 = 10,004,569-surfel textured plane, seen like the plane;

at 512x512 and 1920x1080 (the dragon at 1920x1080, synth10m at 1920x1080), three apertures
(0 and the scene's small and large: a largest CoC of about 10 and 40 pixels at 512x512), with
and without LOD. GPU: ``dofsplat.backends.cuda.render_frame`` (the frame stays on the GPU)
timed with CUDA events after --warmup frames, the median of --repeat; "with copy" adds
the image's copy to the host (``render(..., device="cuda")``, wall clock). CPU: the same
frame through ``render`` (device cpu), median of --cpu-repeat. Each row also checks the
two images against each other (mean and max absolute difference; the issue's bounds are
1e-3 and 1e-2).

    python bench/gpu.py                                  # everything, markdown on stdout
    python bench/gpu.py --scenes plane --sizes 512x512   # one scene at one size
    python bench/gpu.py --json bench/gpu.json --no-cpu

The lion and dragon files are read from --data (default ../shared/data, as the tests do;
a folder holding the two files directly also works): on the GPU machine, copy
lion_takanawa/lion_takanawa_xyzrgb.ply and stanford_dragon/dragon_vrip.ply.gz into a
folder of the repository that git ignores and carry it. Needs a CUDA GPU and numba-cuda
(``pip install 'dofsplat[cuda]'``).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import dofsplat as ds  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SIZES = {"plane": ("512x512", "1920x1080"), "lion": ("512x512", "1920x1080"),
         "dragon": ("1920x1080",), "synth10m": ("1920x1080",)}
# lens diameters (world units), small and large: a largest CoC of about 10 and 40 pixels at
# 512x512 (bench/table1.py's for the plane and the lion); the dragon's, 0.2 units long and
# seen from 0.54, give about 20 and 80 pixels at 1920x1080, the same blur for its height
APERTURES = {"plane": (0.1, 0.4), "lion": (0.5, 2.0), "dragon": (0.1, 0.4),
             "synth10m": (0.1, 0.4)}
SYNTH_SIDE = 3163  # 3163^2 = 10,004,569 surfels


def _find(data: Path, relpath: str) -> Path:
    for path in (data / relpath, data / Path(relpath).name):
        if path.exists():
            return path
    raise SystemExit(f"bench/gpu.py: {relpath} not found under {data} (see --data)")


def load_scene(name: str, width: int, height: int, data: Path):
    """(surfels, camera, focus distance) for a scene at a size."""
    from dofsplat.demo import PLANE_SIZE, plane_scene, textured_plane

    if name == "plane":
        surfels, camera, lens = plane_scene(width, height)
        return surfels, camera, lens.focus_distance
    if name == "synth10m":
        _, camera, lens = plane_scene(width, height)
        return textured_plane(SYNTH_SIDE, PLANE_SIZE), camera, lens.focus_distance
    if name == "lion":
        import table1

        table1.LION = _find(data, "lion_takanawa/lion_takanawa_xyzrgb.ply")
        surfels, camera, lens = table1.lion_scene(None, width, height)
        return surfels, camera, lens.focus_distance
    if name == "dragon":
        from dofsplat.io import load

        surfels = load(_find(data, "stanford_dragon/dragon_vrip.ply.gz"), points="vertices")
        lo, hi = surfels.bounds()
        camera = ds.Camera.framing(lo, hi, width, height, 30.0, direction=(0.3, 0.2, 1.0),
                                   up=(0, 1, 0))
        focus = float(np.linalg.norm(np.subtract(camera.eye, camera.target)))
        return surfels, camera, focus
    raise SystemExit(f"unknown scene {name!r}")


def gpu_frame_ms(surfels, camera, lens, settings, tree, warmup: int, repeat: int):
    """Median and all CUDA-event times of render_frame; the stats of the last frame."""
    from numba import cuda

    from dofsplat.backends.cuda import render_frame

    for _ in range(warmup):
        render_frame(surfels, camera, lens, settings, tree)
    cuda.synchronize()
    times, stats = [], {}
    for _ in range(repeat):
        start, end = cuda.event(), cuda.event()
        start.record()
        frame = render_frame(surfels, camera, lens, settings, tree)
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end))
        stats = frame.stats
    return statistics.median(times), times, stats


def wall_ms(fn, repeat: int):
    times, result = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        result = fn()
        times.append((time.perf_counter() - t) * 1000.0)
    return statistics.median(times), result


def gpu_name() -> str:
    from numba import cuda

    dev = cuda.get_current_device()
    name = dev.name.decode() if isinstance(dev.name, bytes) else str(dev.name)
    cc = ".".join(map(str, dev.compute_capability))
    try:
        driver = ".".join(map(str, cuda.cudadrv.driver.driver.get_version()))
    except Exception:  # noqa: BLE001 - the version is only printed
        driver = "?"
    return f"{name} (compute {cc}, CUDA driver API {driver})"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--sizes", nargs="+", metavar="WxH",
                    help="render every scene at these sizes instead (e.g. 512x512)")
    ap.add_argument("--repeat", type=int, default=50, help="GPU frames timed (median)")
    ap.add_argument("--warmup", type=int, default=3, help="GPU frames before timing")
    ap.add_argument("--cpu-repeat", type=int, default=3, help="CPU frames timed (median)")
    ap.add_argument("--no-cpu", action="store_true", help="skip the CPU backend")
    ap.add_argument("--data", type=Path, default=SHARED, help="folder of the real models")
    ap.add_argument("--json", type=Path, help="also write every measurement here")
    args = ap.parse_args(argv)

    from dofsplat.backends import cuda_problem
    from dofsplat.lod import build_hierarchy

    problem = cuda_problem()
    if problem is not None:
        raise SystemExit(f"bench/gpu.py needs a CUDA GPU: {problem}")
    from bench_plane import machine

    print(f"GPU: {gpu_name()}")
    print(f"CPU: {machine()}, Python {platform.python_version()}")
    print()
    print("| scene | size | splats in | aperture | LOD | GPU ms (median) | min | with copy | CPU ms "
          "| CPU / GPU | select | shade | project | bin | raster | #FRAG (k) | mean / max diff |")
    print("|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    rows = []
    for name in args.scenes:
        for size in args.sizes or SIZES[name]:
            width, height = (int(v) for v in size.split("x"))
            surfels, camera, focus = load_scene(name, width, height, args.data)
            t = time.perf_counter()
            tree = build_hierarchy(surfels)
            build_s = time.perf_counter() - t
            print(f"<!-- {name} {size}: {len(surfels):,} surfels, hierarchy built in {build_s:.1f} s -->",
                  flush=True)
            for aperture in (0.0, *APERTURES[name]):
                lens = ds.ThinLens(focus_distance=focus, aperture=aperture)
                for lod in (False, True):
                    settings = ds.RenderSettings(lod=lod, device="cuda")
                    gpu_ms, gpu_all, stats = gpu_frame_ms(surfels, camera, lens, settings, tree,
                                                          args.warmup, args.repeat)
                    frame_args = (surfels, camera, lens, settings, tree)
                    copy_ms, gpu_result = wall_ms(lambda a=frame_args: ds.render(*a), 5)
                    cpu_ms, diff = None, (None, None)
                    if not args.no_cpu:
                        cpu_settings = replace(settings, device="cpu")
                        ds.render(surfels, camera, lens, cpu_settings, tree)  # warm-up
                        cpu_args = (surfels, camera, lens, cpu_settings, tree)
                        cpu_ms, cpu_result = wall_ms(lambda a=cpu_args: ds.render(*a),
                                                     args.cpu_repeat)
                        d = np.abs(cpu_result.image.astype(np.float64) - gpu_result.image)
                        diff = (float(d.mean()), float(d.max()))
                    row = {"scene": name, "size": size, "surfels": len(surfels),
                           "aperture": aperture, "lod": lod, "gpu_ms": gpu_ms,
                           "gpu_min_ms": min(gpu_all), "gpu_with_copy_ms": copy_ms,
                           "cpu_ms": cpu_ms, "mean_abs_diff": diff[0], "max_abs_diff": diff[1],
                           "stats": stats}
                    rows.append(row)
                    ratio = f"{cpu_ms / gpu_ms:.0f}x" if cpu_ms else "-"
                    cpu_text = f"{cpu_ms:.1f}" if cpu_ms else "-"
                    diff_text = f"{diff[0]:.1e} / {diff[1]:.1e}" if diff[0] is not None else "-"
                    stages = " | ".join(f"{stats.get(k, 0.0):.2f}" for k in
                                        ("select_ms", "shade_ms", "project_ms", "bin_ms", "raster_ms"))
                    print(f"| {name} | {size} | {len(surfels):,} | {aperture:g} | {'on' if lod else 'off'} "
                          f"| {gpu_ms:.2f} | {min(gpu_all):.2f} | {copy_ms:.1f} | {cpu_text} | {ratio} "
                          f"| {stages} | {stats['fragments'] / 1000:.0f} | {diff_text} |", flush=True)
                    if args.json:  # after every row: a run cut short keeps what it measured
                        args.json.write_text(json.dumps(
                            {"gpu": gpu_name(), "cpu": machine(), "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
