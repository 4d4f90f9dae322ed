"""What an LOD cut is made of, and what the back-facing rule adds to it (issue 50).

    python bench/cut_census.py MODEL [--size 320x240] [--cocs 0 10 40] [--repeat 3]

For a frame of a big scan to read little of it, its cut must stay near a few nodes a pixel.
The walk (``lod.select.visit_node``) descends wherever a node's mean normal faces away from
the eye ("let the children decide"), so a scan with mixed normals (foliage, noise, both
sides of thin walls) is cut down to single surfels there, which the projection then culls.
This counts it, per frame of the model's default camera (``dofsplat render``'s, focused on
the surface at the image centre; a CoC of about ``--cocs`` px at the model's far side, as
``bench/model_file.py`` sets it):

* the cut's nodes, how many are single surfels, and how many of those face away from the
  eye (drawn as nothing), with back faces culled (``cull_backfaces``, the default);
* the same frame two-sided (``cull_backfaces=False``: the walk then stops on size alone and
  every splat is drawn from both sides): its nodes and single surfels, a bound on what a
  stop for mixed-normal nodes could save;
* each frame's splats drawn, its time (median of ``--repeat``, after a warm-up), and the
  two frames' PSNR against each other.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def frame_view(model, path, width, height, coc):
    """(camera, lens) of ``dofsplat render``'s default view of the model at this size, the
    lens (None for coc 0) focused on the surface at the image centre with a CoC of coc px
    at the model's far side (``bench/model_file.py``)."""
    from dofsplat import ThinLens
    from dofsplat.cli import build_parser
    from dofsplat.cli.render import model_view

    args = build_parser().parse_args(["render", str(path), "--size", f"{width}x{height}"])
    args.input = str(path)
    camera, focus, _ = model_view(args, model)
    if coc <= 0:
        return camera, None
    lo, hi = model.view_bounds()
    far = (float(np.linalg.norm(np.asarray(camera.eye) - 0.5 * (lo + hi)))
           + 0.5 * float(np.linalg.norm(hi - lo)))
    k_per_aperture = ThinLens(focus_distance=focus, aperture=1.0).coc_coefficients(camera)[0]
    return camera, ThinLens(focus_distance=focus,
                            aperture=coc / (k_per_aperture * abs(1 / far - 1 / focus)))


def census(model, camera, lens, settings) -> dict:
    """The cut's nodes, its single surfels and those of them that face away from the eye."""
    from dofsplat.backends.cpu import select_cut
    from dofsplat.frame import lod_tree

    nodes, start, count, row = select_cut(model, camera, lens, settings)
    single = count == 1
    surfel = np.asarray(lod_tree(model).order)[start[single]]  # leaf order to the surfels
    eye = np.asarray(camera.eye, np.float64)
    to_eye = eye - np.asarray(model.positions[surfel], np.float64)
    away = np.einsum("ij,ij->i", np.asarray(model.normals[surfel], np.float64), to_eye) < 0
    return {"nodes": len(nodes), "single": int(single.sum()), "single_away": int(away.sum())}


def timed(model, camera, lens, settings, repeat):
    import dofsplat as ds

    ds.render(model, camera, lens, settings)
    seconds = []
    for _ in range(repeat):
        t = time.perf_counter()
        frame = ds.render(model, camera, lens, settings)
        seconds.append(time.perf_counter() - t)
    return frame, float(np.median(seconds))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--cocs", type=float, nargs="+", default=[0.0, 10.0, 40.0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    import dofsplat as ds
    from dofsplat.io import load
    from dofsplat.metrics import psnr

    width, height = (int(v) for v in args.size.lower().split("x"))
    model = load(args.model)
    print(f"{args.model.name}: {len(model):,} surfels, {width}x{height}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    print("| CoC px | nodes | single surfels | of them facing away | splats | s "
          "| two-sided: nodes | single | splats | s | PSNR one- vs two-sided |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    one = ds.RenderSettings()
    two = dataclasses.replace(one, cull_backfaces=False)
    for coc in args.cocs:
        camera, lens = frame_view(model, args.model, width, height, coc)
        frame1, s1 = timed(model, camera, lens, one, args.repeat)
        frame2, s2 = timed(model, camera, lens, two, args.repeat)
        c1, c2 = census(model, camera, lens, one), census(model, camera, lens, two)
        print(f"| {coc:g} | {c1['nodes']:,} | {c1['single']:,} ({c1['single'] / c1['nodes']:.0%}) "
              f"| {c1['single_away']:,} ({c1['single_away'] / max(c1['single'], 1):.0%}) "
              f"| {frame1.stats['splats_rendered']:,} | {s1:.2f} | {c2['nodes']:,} "
              f"| {c2['single']:,} ({c2['single'] / c2['nodes']:.0%}) "
              f"| {frame2.stats['splats_rendered']:,} | {s2:.2f} "
              f"| {psnr(frame1.image, frame2.image):.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
