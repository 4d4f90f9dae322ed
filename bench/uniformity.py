"""Uniformity of the accumulated splat weights before and after per-point normalisation.

For the Stanford dragon (its 437,645 mesh vertices as bare points), the lion scan (341,989
points) and the demo plane (``dofsplat.demo.textured_plane``, 512 x 512 surfels on a grid,
and the same plane as jittered bare points), prints the fraction of interior surface
pixels whose accumulated weight lies in 1 +- 0.1 (the paper's measure, Section 6.3;
``dofsplat.normalise.uniformity``) with no normalisation, the object-space method and the
paper's render-capture method, and how long each preprocessing step takes.

Each model is rendered pinhole, unlit, c = 2.5, no LOD, from two directions, at 512 x 512
and at a "close-up" size where the median surfel radius is about 2 pixels (the kernels
are then resolved, not averaged by the pixel filter: the hard case). Each cell gives the
measure with interior pixels at least ``edge_margin`` pixels from an edge (the width over
which splats fade out there: 4 px at 512 x 512, 5 px in close-up), and in brackets with
the fixed 2 px band of ``uniformity``'s default.

    python bench/uniformity.py                 # all models, both methods (a few minutes)
    python bench/uniformity.py --quick         # 512 x 512 only, object method only
    python bench/uniformity.py --models plane  # one model
    python bench/uniformity.py --quick --models lion --k 16 --no-smooth  # other preprocessing
"""

from __future__ import annotations

import argparse
import dataclasses
import gzip
import math
import sys
import time
from pathlib import Path

import numpy as np

import dofsplat as ds
from dofsplat.demo import textured_plane
from dofsplat.io import srgb_to_linear
from dofsplat.normalise import edge_margin, normalise, uniformity
from dofsplat.pointcloud import points_to_surfels
from dofsplat.render import RenderSettings, render

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_plane import machine  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
MODELS = ("dragon", "lion", "plane", "plane-jittered")
CLOSE_UP_PX_PER_RADIUS = 2.0


def read_ply_points(path: Path):
    """(positions (N, 3) float64, colours (N, 3) linear or None) of a PLY's vertices."""
    from plyfile import PlyData

    opener = gzip.open if path.name.endswith(".gz") else open
    with opener(path, "rb") as f:
        v = PlyData.read(f)["vertex"]
    pos = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    names = v.data.dtype.names
    col = None
    if "red" in names:
        col = srgb_to_linear(np.stack([v["red"], v["green"], v["blue"]], axis=1) / 255.0)
    return pos, col


def model(name: str, **options):
    """(surfels, view directions, up vector, preprocessing seconds) for a model name;
    options (k, smooth) go to points_to_surfels."""
    t0 = time.perf_counter()
    if name == "dragon":
        pos, col = read_ply_points(DATA / "stanford_dragon" / "dragon_vrip.ply.gz")
        t0 = time.perf_counter()
        surfels = points_to_surfels(pos, col, progress=False, source="dragon", **options)
        return surfels, [(0, 0, 1), (1, 0.3, 0.2)], (0, 1, 0), time.perf_counter() - t0
    if name == "lion":
        pos, col = read_ply_points(DATA / "lion_takanawa" / "lion_takanawa_xyzrgb.ply")
        t0 = time.perf_counter()
        surfels = points_to_surfels(pos, col, progress=False, source="lion", **options)
        return surfels, [(0, -1, 0.3), (1, 0, 0.3)], (0, 0, 1), time.perf_counter() - t0
    if name == "plane":
        return textured_plane(512), [(0, 1, 0.3), (0, 1, 1.2)], (0, 1, 0), 0.0
    if name == "plane-jittered":
        plane = textured_plane(512)
        h = 4.0 / 512
        rng = np.random.default_rng(1)
        pos = plane.positions.astype(np.float64)
        pos[:, [0, 2]] += rng.uniform(-0.5, 0.5, (len(pos), 2)) * h  # within its grid cell
        t0 = time.perf_counter()
        surfels = points_to_surfels(pos, plane.colors, progress=False, source="plane", **options)
        return surfels, [(0, 1, 0.3), (0, 1, 1.2)], (0, 1, 0), time.perf_counter() - t0
    raise SystemExit(f"unknown model {name!r}; choose from {', '.join(MODELS)}")


def cameras(surfels, directions, up, size):
    """One framing camera per direction; size None: the close-up size (radius ~2 px)."""
    lo, hi = surfels.bounds()
    out = []
    for d in directions:
        cam = ds.Camera.framing(lo, hi, 512, 512, 30.0, direction=d, up=up)
        if size is None:
            dist = math.dist(cam.eye, cam.target)
            px = float(np.median(surfels.radius)) * cam.pixels_per_unit_at_unit_depth / dist
            side = int(min(4096, max(512, round(512 * CLOSE_UP_PX_PER_RADIUS / px))))
            cam = ds.Camera.framing(lo, hi, side, side, 30.0, direction=d, up=up)
        out.append(cam)
    return out


def settings() -> RenderSettings:
    wanted = {"shading": "none", "lod": False}
    names = {f.name for f in dataclasses.fields(RenderSettings)}
    return RenderSettings(**{k: v for k, v in wanted.items() if k in names})


def measure(surfels, cams) -> list[tuple[float, float]]:
    """(uniformity with the edge margin, with the fixed 2 px band) for each camera."""
    out = []
    for c in cams:
        result = render(surfels, c, None, settings())
        margin = edge_margin(surfels, c, settings().cutoff)
        out.append((uniformity(result, c, erode=margin), uniformity(result, c, erode=2)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument("--quick", action="store_true",
                    help="512 x 512 only, object method only")
    ap.add_argument("--k", type=int, default=None,
                    help="neighbours for points_to_surfels (default: its DEFAULT_K)")
    ap.add_argument("--no-smooth", dest="smooth", action="store_false",
                    help="keep the points' measured positions (points_to_surfels)")
    args = ap.parse_args(argv)
    methods = ("none", "object") if args.quick else ("none", "object", "render")
    sizes = (512,) if args.quick else (512, None)

    print(f"machine: {machine()}")
    print()
    head = "| model | points | preprocess (s) | normalisation | time (s) |"
    rule = "|---|---:|---:|---|---:|"
    for size in sizes:
        head += f" {'512²' if size else 'close-up'} view 1 | view 2 |"
        rule += "---:|---:|"
    print(head)
    print(rule)
    for name in args.models:
        if name in ("dragon", "lion") and not DATA.is_dir():
            print(f"| {name} | (skipped: {DATA} not found) |", file=sys.stderr)
            continue
        surfels, directions, up, t_pre = model(name, k=args.k, smooth=args.smooth)
        views = {size: cameras(surfels, directions, up, size) for size in sizes}
        size_note = ", ".join(f"{views[None][0].width}²" for _ in [0]) if None in views else ""
        for method in methods:
            t0 = time.perf_counter()
            normalised = normalise(surfels, method, progress=False)
            t_norm = time.perf_counter() - t0
            row = (f"| {name} | {len(surfels):,} | {t_pre:.1f} | {method} | "
                   f"{t_norm:.1f} |")
            for size in sizes:
                row += "".join(f" {u:.3f} ({u2:.3f}) |"
                               for u, u2 in measure(normalised, views[size]))
            print(row, flush=True)
        if size_note:
            print(f"<!-- {name}: close-up size {size_note} -->", flush=True)


if __name__ == "__main__":
    main()
