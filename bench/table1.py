"""The paper's Table 1: #FRAG, #PTS and time per frame, with and without LOD.

Scenes at 512x512, cutoff c = 2.5 (as in the paper):

* plane: the 512 x 512 = 262,144-surfel textured plane (``dofsplat.demo.plane_scene``);
* lion:  the Takanawa lion scan (../shared/data/lion_takanawa, 341,989 points; Potree),
         turned into surfels (PCA normals, neighbour radii), and the same scan randomly
         subsampled to 81,458 points like the paper's lion.

For each scene: aperture 0 without LOD (the paper's first row), then a small and a large
aperture with and without LOD, plus aperture 0 with LOD. Times are medians of --repeat
frames after a warm-up frame, all in one run, so the ratios compare like with like.
``--plot FILE.png`` also sweeps the aperture and plots time and #FRAG against it.

    python bench/table1.py                      # markdown tables on stdout
    python bench/table1.py --plot bench/table1.png --json bench/table1.json
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import dofsplat as ds  # noqa: E402
from bench_plane import machine  # noqa: E402
from dofsplat.demo import plane_scene  # noqa: E402
from dofsplat.lod import build_hierarchy  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
LION = SHARED / "lion_takanawa" / "lion_takanawa_xyzrgb.ply"
DRAGON = SHARED / "stanford_dragon" / "dragon_vrip.ply.gz"
PAPER_LION_POINTS = 81_458

# lens diameters, world units: (small, large). The plane is 4 units wide and 3.4 from the
# eye; the lion is about 5.7 units tall, seen from 9 units. Both pairs give a largest CoC of
# about 10 and 40 pixels, like the paper's two apertures.
APERTURES = {"plane": (0.1, 0.4), "lion": (0.5, 2.0)}
SWEEP = (0.0, 0.025, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4)  # x (large / 0.4)


def lion_scene(n_points: int | None, width=512, height=512, seed=0):
    """The lion scan as surfels, seen from the front (its scan's z is up), focused on its face."""
    from dofsplat.io import load

    surfels = load(LION)
    if n_points is not None and n_points < len(surfels):
        # a sparser scan: subsample the points, then estimate normals and radii again
        from plyfile import PlyData

        from dofsplat.io import srgb_to_linear
        from dofsplat.prep.pointcloud import points_to_surfels

        v = PlyData.read(str(LION))["vertex"]
        pos = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
        rgb = np.stack([v["red"], v["green"], v["blue"]], axis=1) / 255.0
        pick = np.random.default_rng(seed).choice(len(pos), n_points, replace=False)
        surfels = points_to_surfels(pos[pick], srgb_to_linear(rgb[pick]), progress=False)
    lo, hi = surfels.bounds()
    center = (lo + hi) / 2
    direction = np.array([math.cos(math.radians(300)), math.sin(math.radians(300)), 0.35])
    eye = center + 9.0 * direction / np.linalg.norm(direction)
    camera = ds.Camera(eye=tuple(eye), target=tuple(center + [0.0, 0.0, 0.3]), up=(0, 0, 1),
                       width=width, height=height, fov_y=40)
    # focus on the lion's face (what pixel (215, 185) of the 512 x 512 frame shows)
    focus = ds.focus_distance_at(surfels, camera, 215 * width / 512, 185 * height / 512,
                                 ds.RenderSettings(lod=False))
    lens = ds.ThinLens(focus_distance=focus, aperture=0.0)
    return surfels, camera, lens


def time_frames(surfels, camera, lens, settings, hierarchy, repeat):
    ds.render(surfels, camera, lens, settings, hierarchy)  # warm-up
    runs, stats = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        res = ds.render(surfels, camera, lens, settings, hierarchy)
        runs.append((time.perf_counter() - t) * 1000)
        stats = res.stats
    return statistics.median(runs), stats, res


def max_coc(surfels, camera, lens) -> float:
    xy, depth = camera.project(surfels.positions)
    inside = (depth > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < camera.width) & (xy[:, 1] >= 0) \
        & (xy[:, 1] < camera.height)
    return float(lens.coc_radius_px(depth[inside], camera).max()) if lens.diameter else 0.0


def psnr(a, b) -> float:
    mse = float(np.mean((a[..., :3].astype(np.float64) - b[..., :3]) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(1 / mse)


def table(name, surfels, camera, lens, repeat, records, lod_options):
    small, large = APERTURES["lion" if name.startswith("lion") else "plane"]
    t = time.perf_counter()
    tree = build_hierarchy(surfels)
    build_s = time.perf_counter() - t
    print(f"\n### {name}: {len(surfels):,} surfels, hierarchy of {len(tree):,} nodes built in "
          f"{build_s:.2f} s\n")
    print("| aperture | max CoC (px) | LOD | #FRAG (k) | #PTS | time (ms) | x pinhole | PSNR vs no LOD (dB) |")
    print("|---:|---:|:---:|---:|---:|---:|---:|---:|")
    rows = [(0.0, False), (0.0, True), (small, True), (large, True), (small, False), (large, False)]
    results = {}
    for aperture, lod in rows:
        this = ds.ThinLens(focus_distance=lens.focus_distance, aperture=aperture) if aperture else None
        settings = ds.RenderSettings(cutoff=2.5, lod=lod, **lod_options)
        ms, st, res = time_frames(surfels, camera, this, settings, tree if lod else None, repeat)
        results[(aperture, lod)] = (ms, st, res)
    base = results[(0.0, False)][0]
    for aperture, lod in rows:
        ms, st, res = results[(aperture, lod)]
        q = psnr(res.image, results[(aperture, False)][2].image) if lod else None
        this = ds.ThinLens(focus_distance=lens.focus_distance, aperture=aperture)
        coc = max_coc(surfels, camera, this)
        print(f"| {aperture:g} | {coc:.1f} | {'yes' if lod else '-' if aperture == 0 else 'no'} | "
              f"{st['fragments'] / 1000:,.0f} | {st['splats_rendered']:,} | {ms:.0f} | "
              f"{ms / base:.2f} | {'' if q is None else f'{q:.1f}'} |")
        records.append({"scene": name, "surfels": len(surfels), "aperture": aperture, "lod": lod,
                        "max_coc_px": coc, "fragments": st["fragments"],
                        "splats": st["splats_rendered"], "ms": ms, "psnr_vs_no_lod": q})
    lod_large = results[(large, True)][0]
    print(f"\nLOD at the large aperture: {lod_large / base:.2f} x the pinhole frame "
          f"(paper: 0.99 x plane, 1.30 x lion); {results[(large, False)][0] / lod_large:.1f} x "
          f"faster than without LOD (paper: 27 x plane, 16 x lion)")
    return tree


def sweep(name, surfels, camera, lens, tree, repeat, scale, lod_options):
    out = []
    for a in SWEEP:
        aperture = a * scale
        this = ds.ThinLens(focus_distance=lens.focus_distance, aperture=aperture) if aperture else None
        for lod in (True, False):
            ms, st, _ = time_frames(surfels, camera, this, ds.RenderSettings(lod=lod, **lod_options),
                                    tree if lod else None, repeat)
            out.append({"scene": name, "aperture": aperture, "lod": lod, "ms": ms,
                        "fragments": st["fragments"], "splats": st["splats_rendered"]})
            print(f"  sweep {name} A={aperture:g} lod={lod}: {ms:.0f} ms", file=sys.stderr)
    return out


def plot(path, sweeps):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted({r["scene"] for r in sweeps}, key=lambda n: [r["scene"] for r in sweeps].index(n))
    fig, axes = plt.subplots(2, len(names), figsize=(4.2 * len(names), 6.4), squeeze=False)
    for col, name in enumerate(names):
        for lod, style in ((True, "o-"), (False, "s--")):
            rs = [r for r in sweeps if r["scene"] == name and r["lod"] == lod]
            a = [r["aperture"] for r in rs]
            label = "with LOD" if lod else "without LOD"
            axes[0, col].plot(a, [r["ms"] for r in rs], style, label=label)
            axes[1, col].plot(a, [r["fragments"] / 1e6 for r in rs], style, label=label)
        axes[0, col].set_title(name)
        axes[0, col].set_ylabel("time per frame (ms)")
        axes[1, col].set_ylabel("#FRAG (millions)")
        axes[1, col].set_xlabel("lens diameter A (world units)")
        for ax in axes[:, col]:
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend()
    fig.suptitle("512 x 512, c = 2.5: with LOD the cost hardly depends on the aperture")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def hierarchy_costs(path: Path):
    """Build, save and load (with its fingerprint check) the hierarchy of a large model."""
    import tempfile

    from dofsplat.io import load
    from dofsplat.lod import Hierarchy

    surfels = load(path)
    build_hierarchy(surfels.subset(slice(0, 100)))  # compile outside the timing
    t = time.perf_counter()
    tree = build_hierarchy(surfels)
    build_s = time.perf_counter() - t
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        saved = tree.save(Path(tmp) / "tree.lod.npz")
        save_s = time.perf_counter() - t
        t = time.perf_counter()
        assert Hierarchy.load(saved, surfels) is not None
        load_s = time.perf_counter() - t
    print(f"\n### hierarchy of {path.name}: {len(surfels):,} surfels, {len(tree):,} nodes, "
          f"{tree.nbytes() / 1e6:.0f} MB; build {build_s:.2f} s, save {save_s:.2f} s, "
          f"load with the fingerprint check {load_s:.2f} s")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--plot", metavar="FILE.png", help="also sweep the aperture and plot")
    ap.add_argument("--json", metavar="FILE.json", help="write every number measured")
    ap.add_argument("--scenes", default="plane,lion,lion81k,dragon-tree",
                    help="comma-separated: plane, lion, lion81k; dragon-tree times the "
                         "hierarchy of the full dragon (build, save, load)")
    ap.add_argument("--lod-blur-fraction", type=float,
                    default=ds.RenderSettings.lod_blur_fraction,
                    help="LOD's stop (RenderSettings.lod_blur_fraction; default the "
                         "renderer's, 0.35; 1 is the paper's rule)")
    ap.add_argument("--lod-color-tolerance", type=float,
                    default=ds.RenderSettings.lod_color_tolerance,
                    help="the finer cut for textured nodes (RenderSettings."
                         "lod_color_tolerance; default the renderer's, 0.02; inf: off)")
    ap.add_argument("--lod-min-node", type=int, default=ds.RenderSettings.lod_min_node,
                    help="the smallest node the blur's stop draws (RenderSettings."
                         "lod_min_node; default the renderer's, 4; 2 is the paper's rule)")
    args = ap.parse_args(argv)
    lod_options = {"lod_blur_fraction": args.lod_blur_fraction,
                   "lod_color_tolerance": args.lod_color_tolerance,
                   "lod_min_node": args.lod_min_node}
    print(f"LOD stop: lod_blur_fraction = {args.lod_blur_fraction:g}, "
          f"lod_color_tolerance = {args.lod_color_tolerance:g}, "
          f"lod_min_node = {args.lod_min_node}")
    print(f"machine: {machine()}")
    scenes = []
    names = args.scenes.split(",")
    for name in names:
        if name == "dragon-tree":
            continue
        if name == "plane":
            scenes.append((name, *plane_scene(512, 512), 1.0))
        elif name in ("lion", "lion81k"):
            if not LION.exists():
                print(f"\n(skipping {name}: {LION} not found)")
                continue
            n = PAPER_LION_POINTS if name == "lion81k" else None
            scenes.append((name, *lion_scene(n), APERTURES["lion"][1] / 0.4))
        else:
            ap.error(f"unknown scene {name}")
    records, sweeps = [], []
    for name, surfels, camera, lens, scale in scenes:
        tree = table(name, surfels, camera, lens, args.repeat, records, lod_options)
        if args.plot:
            sweeps += sweep(name, surfels, camera, lens, tree, max(1, args.repeat // 2), scale,
                            lod_options)
    if "dragon-tree" in names:
        if DRAGON.exists():
            hierarchy_costs(DRAGON)
        else:
            print(f"\n(skipping dragon-tree: {DRAGON} not found)")
    if args.plot:
        plot(args.plot, sweeps)
        print(f"\nplot: {args.plot}")
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine(),
                                               "lod_blur_fraction": args.lod_blur_fraction,
                                               "lod_color_tolerance": (
                                                   None if math.isinf(args.lod_color_tolerance)
                                                   else args.lod_color_tolerance),
                                               "lod_min_node": args.lod_min_node,
                                               "table": records, "sweep": sweeps}, indent=1))


if __name__ == "__main__":
    main()
