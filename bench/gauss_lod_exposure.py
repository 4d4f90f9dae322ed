"""A prototype for the Gaussian LOD's colour (issue 48; docs/maths.md, "Gaussian scenes", item
4): the tree's colour merges weighted by each Gaussian's *exposure*, not the renderer.

    python bench/gauss_lod_exposure.py --scenes guitar biker donut playbot --power 4
    python bench/gauss_lod_exposure.py --scenes playbot --power 4 --hemisphere

The LOD cut's loss on the guitar is the colour of hidden children: a node's colour is its
children's mean weighted by o A (``gauss/lod.py``), so the Gaussians under a surface tint it.
Here each Gaussian's exposure is its largest seen share (``composite.seen_share``: alpha T
over its footprint's integral) over ``--views`` pinhole views from a sphere around the scene
(2.5 x its radius, ``--size`` px square; with ``--hemisphere`` the half that faces the
default camera), and the tree is built again with colours merged by o A exposure^power
(``lod.build_tree(colour_weight=...)``, plus 1e-12 so that a pair nobody sees keeps its
o A mean; geometry and opacity as before). Printed: PSNR over black / white against the lens
reference (``--samples``) for the default frame from the usual tree and from this one, and
no LOD's, at the bench's 10 and 35 px lenses (``bench/gaussians.py``), 320 x 240.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gaussians as G  # noqa: E402  (bench/gaussians.py: scenes, camera, lens)

import dofsplat as ds  # noqa: E402
from dofsplat.backends.cpu_gauss import seen_in_view  # noqa: E402
from dofsplat.gauss import lod as L  # noqa: E402
from dofsplat.gauss.composite import seen_shares  # noqa: E402
from dofsplat.metrics import psnr  # noqa: E402
from dofsplat.reference import render_reference  # noqa: E402


def exposure(scene, views: int, size: int, facing=None) -> np.ndarray:
    """(N,) each Gaussian's largest seen share over views from a Fibonacci sphere around the
    scene (its 2-98 % box's centre, 2.5 x the box's half-diagonal away), or its half whose
    directions have a positive dot product with facing (3,)."""
    p = scene.positions.astype(np.float64)
    lo, hi = np.quantile(p, 0.02, axis=0), np.quantile(p, 0.98, axis=0)
    centre, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo)
    k = np.arange(views) + 0.5
    polar = np.arccos(1.0 - 2.0 * k / views)
    azimuth = np.pi * (1.0 + 5.0 ** 0.5) * k
    dirs = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar),
                     np.cos(polar)], 1)
    if facing is not None:
        dirs = np.where((dirs @ facing)[:, None] < 0.0, -dirs, dirs)
    best = np.zeros(len(scene), np.float32)
    share = np.empty(len(scene), np.float32)
    settings = ds.RenderSettings()
    for d in dirs:
        up = (0.0, 1.0, 0.0) if abs(d[1]) < 0.9 else (1.0, 0.0, 0.0)
        cam = ds.Camera(eye=tuple(centre + 2.5 * radius * d), target=tuple(centre), up=up,
                        width=size, height=size, fov_y=50.0, near=0.01 * radius)
        rows, visible, seen = seen_in_view(scene, cam, settings)
        seen_shares(rows, visible, seen, share)
        np.maximum(best, share, out=best)
    return best


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["guitar", "biker", "donut", "playbot"],
                        choices=list(G.SCENES))
    parser.add_argument("--power", type=float, default=4.0)
    parser.add_argument("--views", type=int, default=14)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--hemisphere", action="store_true")
    args = parser.parse_args(argv)
    for name in args.scenes:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = ds.io.load(G.SCENES[name])
        camera = G.default_camera(scene, 320, 240)
        pinhole = ds.render(scene, camera, None, ds.RenderSettings())
        facing = None
        if args.hemisphere:
            d = np.asarray(camera.eye) - np.asarray(camera.target)
            facing = d / np.linalg.norm(d)
        t = time.perf_counter()
        seen = exposure(scene, args.views, args.size, facing)
        seconds = time.perf_counter() - t
        trees = {"usual": L.build_tree(scene),
                 "exposed": L.build_tree(scene, colour_weight=seen ** args.power + 1e-12)}
        for coc in (10.0, 35.0):
            lens = G.lens_for(scene, camera, coc, pinhole.depth)
            cells = {}
            for bg in (0.0, 1.0):
                st = ds.RenderSettings(background=(bg,) * 3)
                ref = render_reference(scene, camera, lens, st, samples=args.samples,
                                       progress=False).image
                for label, tree in trees.items():
                    scene._gaussian_tree = tree
                    image = ds.render(scene, camera, lens, st).image
                    cells.setdefault(label, []).append(f"{psnr(image, ref):.2f}")
                image = ds.render(scene, camera, lens, ds.RenderSettings(
                    background=(bg,) * 3, gaussian_lod=False)).image
                cells.setdefault("no LOD", []).append(f"{psnr(image, ref):.2f}")
            scene._gaussian_tree = None
            print(f"  {name} {coc:.0f} px (exposure {seconds:.1f} s, median "
                  f"{np.median(seen):.3f}): " + " | ".join(
                      f"{k} {' / '.join(v)}" for k, v in cells.items()), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
