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
(geometry and opacity as before). Printed: PSNR over black / white against the lens
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


def exposed_tree(scene, colour_weight: np.ndarray) -> L.GaussianTree:
    """``lod.build_tree`` with each pair's colour merged by colour_weight (N,) (in the
    scene's order) summed up the tree, its geometry and opacity as ``merge_pairs`` gives."""
    order = L.morton_order(scene.positions)
    mu = scene.positions[order].astype(np.float64)
    scales = scene.scales[order].astype(np.float64)
    rotations = scene.rotations[order]
    opacity = scene.opacity[order].astype(np.float64)
    sh = scene.sh[order].astype(np.float64)
    cov = L.covariances(scales, rotations)
    weight = opacity * L.cross_section(scales)
    cw = weight * colour_weight[order] + 1e-12 * weight
    levels = [(mu, scales, rotations.astype(np.float64), opacity, sh)]
    while len(mu) > 1:
        n = len(mu)
        m = n // 2
        a, b = slice(0, 2 * m, 2), slice(1, 2 * m, 2)
        pair = cw[a] + cw[b]
        f = np.where(pair > 0, cw[a] / np.where(pair > 0, pair, 1.0), 0.5)
        colour = f[:, None, None] * sh[a] + (1.0 - f)[:, None, None] * sh[b]
        if n % 2:
            colour = np.concatenate([colour, sh[-1:]])
            pair = np.concatenate([pair, cw[-1:]])
        mu, cov, weight, _ = L.merge_pairs(mu, cov, weight, sh)
        sh, cw = colour, pair
        s, q = L.scales_rotations(cov)
        levels.append((mu, s, q, weight / np.maximum(L.cross_section(s), 1e-300), sh))
    offsets = np.zeros(len(levels) + 1, np.int64)
    offsets[1:] = np.cumsum([len(lv[0]) for lv in levels])
    cat = lambda i: np.concatenate([lv[i] for lv in levels]).astype(np.float32)  # noqa: E731
    all_scales = cat(1)
    return L.GaussianTree(positions=cat(0), scales=all_scales, rotations=cat(2), opacity=cat(3),
                          sh=cat(4), extent=all_scales.max(axis=1), offsets=offsets,
                          fingerprint=L.fingerprint(scene, cached=True))


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
        trees = {"usual": L.build_tree(scene), "exposed": exposed_tree(scene, seen ** args.power)}
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
