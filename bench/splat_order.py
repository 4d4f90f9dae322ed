"""The order in which a frame's splats are drawn: what it costs and what it changes (issue 15).

    python bench/splat_order.py                    # both tables, plane, demo and lion
    python bench/splat_order.py --orders --scenes lion --apertures 0 2
    python bench/splat_order.py --leaves

``--orders``: one default frame's splats (LOD on, as ``render`` projects them) are captured
and rasterised again (``backends.cpu.draw_splats``: binning, front pass, raster) in other
orders: the cut's own (the tree's preorder), by depth either way, by screen row, along a
Morton curve of the screen position, and two random ones. Per order: the raster stage's
median over ``--repeat`` draws, and the image against the cut's order (PSNR, the largest
difference of a channel, and the pixels that differ by more than 0.01). The A-buffer is
order-dependent (a fragment joins the first surface its depth range meets), so the images
differ a little where surfaces meet; the time differs by how the fragments fall on the tile's
accumulators.

``--leaves``: the pinhole frame with LOD against every surfel drawn without LOD, in the
LOD tree's leaf order (``Surfels.subset(tree.order)``), at the scenes' sizes and at a half
and a quarter of them (more sub-pixel surfels): median frame times, fragments and the PSNR
between the two. Where the pinhole cut is (nearly) all leaves, the leaves cost less than the
cut: no walk of the tree, no gather.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import dofsplat as ds  # noqa: E402
from bench_plane import machine  # noqa: E402
from profile import APERTURES, scene  # noqa: E402


def psnr(a, b) -> float:
    mse = float(np.mean((a[..., :3].astype(np.float64) - b[..., :3]) ** 2))
    return float("inf") if mse == 0.0 else 10.0 * np.log10(1.0 / mse)


def capture(surfels, camera, lens, tree):
    """The visible splats (and their boxes) that a default frame rasterises, and its image."""
    from dofsplat.backends import cpu

    held = {}
    draw = cpu.draw_splats

    def keep(splats, bbox, visible, *args, **kwargs):
        held["splats"] = (splats.copy(), bbox.copy(), visible.copy())
        return draw(splats, bbox, visible, *args, **kwargs)

    cpu.draw_splats = keep
    try:
        image = ds.render(surfels, camera, lens, ds.RenderSettings(), tree).image
    finally:
        cpu.draw_splats = draw
    splats, bbox, visible = held["splats"]
    keep_rows = np.nonzero(visible)[0]
    return splats[keep_rows], bbox[keep_rows], image


def morton(x, y):
    def spread(v):
        v = np.clip(v, 0, 65535).astype(np.uint64)
        for shift, mask in ((8, 0x00FF00FF), (4, 0x0F0F0F0F), (2, 0x33333333),
                            (1, 0x55555555)):
            v = (v | (v << np.uint64(shift))) & np.uint64(mask)
        return v
    return spread(x) | (spread(y) << np.uint64(1))


def orders_table(names, apertures, repeat):
    from dofsplat.backends.cpu import draw_splats
    from dofsplat.lod import build_hierarchy
    from dofsplat.splat.project import DEPTH, MX, MY

    print("| scene | A | splats | order | raster ms | PSNR against the cut's order | "
          "largest difference | pixels > 0.01 |")
    print("|---|---:|---:|---|---:|---:|---:|---:|")
    for name in names:
        surfels, camera, lens = scene(name)
        tree = build_hierarchy(surfels)
        for aperture in apertures or APERTURES[name]:
            thin = ds.ThinLens(focus_distance=lens.focus_distance, aperture=aperture)
            splats, bbox, image = capture(surfels, camera, thin, tree)
            mx, my, depth = splats[:, MX], splats[:, MY], splats[:, DEPTH]
            rng = np.random.default_rng
            orders = {"the cut's (tree preorder)": np.arange(len(splats)),
                      "depth, front first": np.argsort(depth, kind="stable"),
                      "depth, back first": np.argsort(-depth, kind="stable"),
                      "screen rows": np.lexsort((mx, np.floor(my))),
                      "Morton curve": np.argsort(morton(mx, my), kind="stable"),
                      "random (seed 0)": rng(0).permutation(len(splats)),
                      "random (seed 1)": rng(1).permutation(len(splats))}
            settings = ds.RenderSettings()
            for label, order in orders.items():
                times, out = [], None
                for _ in range(repeat):
                    visible = np.ones(len(order), np.bool_)
                    out = draw_splats(splats[order], bbox[order], visible, camera, thin,
                                      settings, 0.0)
                    times.append(out[3]["raster_ms"])
                diff = np.abs(out[0][..., :3].astype(np.float64) - image[..., :3])
                print(f"| {name} | {aperture:g} | {len(splats):,} | {label} "
                      f"| {statistics.median(times):.1f} | {psnr(out[0], image):.1f} "
                      f"| {diff.max():.3f} | {int((diff.max(-1) > 0.01).sum())} |", flush=True)


def frame_ms(surfels, camera, lens, settings, tree, repeat):
    ds.render(surfels, camera, lens, settings, tree)
    times, result = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        result = ds.render(surfels, camera, lens, settings, tree)
        times.append((time.perf_counter() - t) * 1000.0)
    return statistics.median(times), result


def leaves_table(names, repeat):
    from dofsplat.lod import build_hierarchy

    print("| scene | size | LOD: ms | fragments | leaves in tree order: ms | fragments "
          "| leaves / LOD | PSNR between them |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name in names:
        surfels, camera, lens = scene(name)
        tree = build_hierarchy(surfels)
        leaves = surfels.subset(tree.order)
        pinhole = ds.ThinLens(focus_distance=lens.focus_distance, aperture=0.0)
        for scale in (1, 2, 4):
            cam = dataclasses.replace(camera, width=camera.width // scale,
                                      height=camera.height // scale)
            lod_ms, lod = frame_ms(surfels, cam, pinhole, ds.RenderSettings(), tree, repeat)
            leaf_ms, leaf = frame_ms(leaves, cam, pinhole, ds.RenderSettings(lod=False), None,
                                     repeat)
            print(f"| {name} | {cam.width}x{cam.height} | {lod_ms:.1f} "
                  f"| {lod.stats['fragments']:,} | {leaf_ms:.1f} | {leaf.stats['fragments']:,} "
                  f"| {leaf_ms / lod_ms:.2f} | {psnr(lod.image, leaf.image):.1f} |", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["plane", "demo", "lion"],
                    choices=["plane", "demo", "lion", "intersect"])
    ap.add_argument("--apertures", nargs="+", type=float,
                    help="--orders: these lens diameters (default: the scene's three)")
    ap.add_argument("--orders", action="store_true", help="only the orders' table")
    ap.add_argument("--leaves", action="store_true", help="only the pinhole leaves' table")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    both = not (args.orders or args.leaves)
    print(f"{machine()}\n")
    if args.orders or both:
        orders_table(args.scenes, args.apertures, args.repeat)
        print()
    if args.leaves or both:
        leaves_table(args.scenes, args.repeat)


if __name__ == "__main__":
    main()
