"""Sequences on a Dask cluster (issue 17): a 48-frame focus pull on the lion at 1280 x 720.

    python bench/animate.py [--frames 48] [--repeat 1]

Renders the same focus pull (the lion's LAZ scan, default view, focus from 9 to 17 world
units, lens diameter 1) with ``dofsplat.sequence.animate`` into a fresh folder of PNG
frames: in this process (2 numba threads), then on a LocalCluster of 1 worker process and
of 2 worker processes (cores / workers numba threads each). The model is loaded (from the
cache of prepared models) before the clock starts; the cluster's start is timed apart.
Prints seconds, frames per second and the speed-up against 1 worker. Frames are
independent, so on a machine with more cores (or a cluster) the rate grows with the workers
until the model's transfer or the disk dominates; on 2 cores numba's own threads already
use both, and the workers can only trade one for the other.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import dofsplat as ds
from dofsplat import sequence

LION = Path(__file__).resolve().parents[1].parent / "shared/data/lion_takanawa/lion_takanawa.copc.laz"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--size", default="1280x720")
    args = ap.parse_args(argv)
    if not LION.exists():
        print(f"no {LION}: the lion scan is in ../shared/data", file=sys.stderr)
        return 1
    from dask.distributed import Client, LocalCluster

    from dofsplat.cli.options import image_size
    from dofsplat.io import load

    width, height = image_size(args.size)
    surfels = load(LION)
    lo, hi = surfels.bounds()
    up = getattr(surfels, "up_hint", None) or (0.0, 1.0, 0.0)  # `dofsplat render`'s view
    camera = ds.Camera.framing(lo, hi, width, height, 40.0, up=up,
                               direction=(0.0, -1.0, 0.0) if up[2] else (0.0, 0.0, 1.0))
    lens = ds.ThinLens(focus_distance=13.0, aperture=1.0)
    keys = [sequence.Keyframe(0.0, {"focus": (9.0,)}), sequence.Keyframe(1.0, {"focus": (17.0,)})]
    settings = ds.RenderSettings()
    ds.render(surfels, camera, lens, settings)  # compile (or load) the kernels, the LOD tree
    print(f"{args.frames} frames of {width}x{height}, lion ({len(surfels):,} surfels), "
          f"{os.cpu_count()} cores")
    results = {}
    for workers in (0, 1, 2):
        with tempfile.TemporaryDirectory() as tmp:
            client = cluster = None
            t_start = time.perf_counter()
            if workers:
                threads = max(1, (os.cpu_count() or 1) // workers)
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1,
                                       processes=True, dashboard_address=None,
                                       env={"NUMBA_NUM_THREADS": str(threads)})
                client = Client(cluster)
            start_s = time.perf_counter() - t_start
            t = time.perf_counter()
            sequence.animate(surfels, keys, args.frames, camera, lens, settings,
                             output=Path(tmp) / "frames", client=client)
            seconds = time.perf_counter() - t
            if client is not None:
                client.close()
                cluster.close()
        results[workers] = seconds
        name = "in process" if workers == 0 else f"{workers} worker{'s' * (workers > 1)}"
        print(f"{name:12s} {seconds:6.1f} s  {args.frames / seconds:5.2f} frames/s"
              + (f"  (cluster start {start_s:.1f} s)" if workers else ""), flush=True)
    print(f"speed-up, 2 workers against 1: {results[1] / results[2]:.2f} x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
