"""The viewer's moving frames against its full frame (issue 51, item 5).

    python bench/viewer_frames.py [--repeat 6]

The lion scan (../shared/data/lion_takanawa, the LAZ), framed whole at 1280 x 800 with the
viewer's default lens: the full frame with the default settings, and the moving frames the
viewer draws (``viewer.MOVING_*``: the paper's coarser LOD stop, every node drawn, no finer
cut for textured nodes) at a quarter (640 x 400) and a sixteenth (320 x 200) of the pixels,
with the pixel stop at 1 and at 2 px. Medians and minima of --repeat frames after a warm-up,
alternating the cases, and each case's ratio to the full frame of the same run.
"""

from __future__ import annotations

import argparse
import math
import platform
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

LION = Path(__file__).resolve().parents[2] / "shared" / "data" / "lion_takanawa" / "lion_takanawa.copc.laz"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=6)
    args = parser.parse_args(argv)
    import dofsplat as ds
    from dofsplat.io import load
    from dofsplat.render import render, warm_up

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lion = load(LION)
    lo, hi = lion.view_bounds()
    camera = ds.Camera.framing(lo, hi, 1280, 800, 40.0)
    lens = ds.ThinLens(focus_distance=math.dist(camera.eye, camera.target),
                       aperture=0.1 * 0.5 * float(np.linalg.norm(hi - lo)))
    settings = ds.RenderSettings()
    moving = replace(settings, lod_blur_fraction=1.0, lod_color_tolerance=math.inf, lod_min_node=2)
    cases = [("full", 1280, 800, settings)] + [
        (f"moving {w}x{h}, {t:g} px stop", w, h, replace(moving, lod_pixel_threshold=t))
        for (w, h) in ((640, 400), (320, 200)) for t in (1.0, 2.0)]
    warm_up()
    times = {name: [] for name, *_ in cases}
    for name, w, h, st in cases:  # the model's tree and every kernel, before timing
        render(lion, replace(camera, width=w, height=h), lens, st)
    for _ in range(args.repeat):
        for name, w, h, st in cases:
            t0 = time.perf_counter()
            render(lion, replace(camera, width=w, height=h), lens, st)
            times[name].append(time.perf_counter() - t0)
    full = np.median(times["full"])
    print(f"{platform.machine()}, {platform.processor() or '?'}; {len(lion):,} surfels; "
          f"{args.repeat} frames each, alternating")
    for name, ts in times.items():
        print(f"  {name:28s} min {1e3 * min(ts):6.0f} ms  median {1e3 * np.median(ts):6.0f} ms"
              f"  {np.median(ts) / full:.2f} x the full frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
