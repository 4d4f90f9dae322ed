"""What an LOD cut is made of, and what the back-facing rule adds to it (issue 50).

    python bench/cut_census.py MODEL [--size 320x240] [--cocs 0 10 40] [--repeat 3] [--samples 32]

For a frame of a big scan to read little of it, its cut must stay near a few nodes a pixel.
The walk (``lod.select.visit_node``) descended wherever a node's mean normal faces away from
the eye ("let the children decide"), so a scan with mixed normals (foliage, noise, both
sides of thin walls) was cut down to single surfels there, which the projection then culls;
in a blurred region it now drops such a node where the blur's stop would draw it.
This counts it, per frame of the model's default camera (``dofsplat render``'s, focused on
the surface at the image centre; a CoC of about ``--cocs`` px at the model's far side:
``bench/model_file.py``'s ``frame_view``):

* the cut's nodes, how many are single surfels, and how many of those face away from the
  eye (drawn as nothing), with back faces culled (``cull_backfaces``, the default), the walk
  descending a back-facing node (``lod_backface_drop=False``, the rule until 2026-11-28) and
  dropping one that the blur's stop would draw (the default; docs/maths.md, "A back-facing
  node under the blur");
* the same frame two-sided (``cull_backfaces=False``: the walk then stops on size alone and
  every splat is drawn from both sides): its nodes and single surfels;
* each frame's splats drawn, its time (median of ``--repeat``, after a warm-up), its PSNR
  against the descending walk's frame and, with ``--samples N``, against the lens reference
  of N samples (``dofsplat reference``; the pinhole frame against the frame of every surfel).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--cocs", type=float, nargs="+", default=[0.0, 10.0, 40.0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--samples", type=int, default=0,
                        help="also each frame against the lens reference of this many samples")
    args = parser.parse_args(argv)
    import dofsplat as ds
    from bokeh import timed  # (a warm-up frame, then the median of repeat frames, ms)
    from dofsplat.io import load
    from dofsplat.metrics import psnr
    from dofsplat.reference import render_reference
    from model_file import frame_view  # (bench/model_file.py's frames)

    width, height = (int(v) for v in args.size.lower().split("x"))
    model = load(args.model)
    print(f"{args.model.name}: {len(model):,} surfels, {width}x{height}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    print("| CoC px | walk | nodes | single surfels | of them facing away | splats | s "
          "| PSNR against descending | against the reference |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    walks = {"descending": ds.RenderSettings(lod_backface_drop=False),
             "dropping": ds.RenderSettings(),
             "two-sided": ds.RenderSettings(cull_backfaces=False)}
    for coc in args.cocs:
        camera, lens = frame_view(model, args.model, width, height, coc)
        truth = None
        if args.samples and lens is not None:
            truth = render_reference(model, camera, lens, ds.RenderSettings(),
                                     samples=args.samples, progress=False).image
        elif args.samples:
            truth = ds.render(model, camera, None, ds.RenderSettings(lod=False)).image
        first = None
        for label, settings in walks.items():
            frame, ms = timed(model, camera, lens, settings, args.repeat)
            c = census(model, camera, lens, settings)
            first = frame.image if first is None else first
            away = "" if label == "two-sided" else \
                f"{c['single_away']:,} ({c['single_away'] / max(c['single'], 1):.0%})"
            print(f"| {coc:g} | {label} | {c['nodes']:,} | {c['single']:,} "
                  f"({c['single'] / c['nodes']:.0%}) | {away} | "
                  f"{frame.stats['splats_rendered']:,} | {ms / 1000:.2f} | "
                  f"{psnr(frame.image, first):.1f} | "
                  f"{'' if truth is None else format(psnr(frame.image, truth), '.2f')} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
