"""Uniformity of the accumulated splat weights before and after per-point normalisation.

For the Stanford dragon (its 437,645 mesh vertices as bare points), the lion scan (341,989
points) and the demo plane (``dofsplat.demo.textured_plane``, 512 x 512 surfels on a grid,
and the same plane as jittered bare points), and for meshes sampled by
``dofsplat.prep.meshes.mesh_to_surfels`` (a unit square, 40,000 samples; Spot, 200,000; the
full dragon mesh, 437,645), prints the fraction of interior surface pixels whose
accumulated weight lies in 1 +- 0.1 (the paper's measure, Section 6.3;
``dofsplat.prep.normalise.uniformity``) with no normalisation, the object-space method and the
paper's render-capture method, and how long each preprocessing step takes.

Each model is rendered pinhole, unlit, c = 2.5, no LOD, from two directions, at 512 x 512
and at a "close-up" size where the median surfel radius is about 2 pixels (``--close-up``;
the kernels are then resolved, not averaged by the pixel filter: the hard case). Each cell
gives the measure with interior pixels at least ``edge_margin`` pixels from an edge (the
width over which splats fade out there: 4 px at 512 x 512, 5 px in close-up), and in
brackets with the fixed 2 px band of ``uniformity``'s default.

    python bench/uniformity.py                 # the point models, all methods (minutes)
    python bench/uniformity.py --quick         # 512 x 512 only, object method only
    python bench/uniformity.py --models plane  # one model
    python bench/uniformity.py --quick --models lion --k 16 --no-smooth  # other preprocessing
    python bench/uniformity.py --models square-mesh spot dragon-mesh --close-up 2.6
    python bench/uniformity.py --models square-mesh spot dragon-mesh --radius-scale 1.0 \
        --close-up 2 --methods none object       # r = sqrt(area), the same zoom
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
from dofsplat.prep.normalise import edge_margin, normalise, uniformity
from dofsplat.prep.pointcloud import points_to_surfels
from dofsplat.render import RenderSettings, render

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_plane import machine  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
POINT_MODELS = ("dragon", "lion", "plane", "plane-jittered")
MESH_MODELS = ("square-mesh", "spot", "dragon-mesh")
MODELS = POINT_MODELS + MESH_MODELS
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
        surfels = points_to_surfels(pos, col, progress=False, source="dragon", normalise="none",
                                    **options)
        return surfels, [(0, 0, 1), (1, 0.3, 0.2)], (0, 1, 0), time.perf_counter() - t0
    if name == "lion":
        pos, col = read_ply_points(DATA / "lion_takanawa" / "lion_takanawa_xyzrgb.ply")
        t0 = time.perf_counter()
        surfels = points_to_surfels(pos, col, progress=False, source="lion", normalise="none",
                                    **options)
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
        surfels = points_to_surfels(pos, plane.colors, progress=False, source="plane",
                                    normalise="none", **options)
        return surfels, [(0, 1, 0.3), (0, 1, 1.2)], (0, 1, 0), time.perf_counter() - t0
    if name in MESH_MODELS:
        return mesh_model(name, options.get("smooth", True))
    raise SystemExit(f"unknown model {name!r}; choose from {', '.join(MODELS)}")


def mesh_model(name: str, smooth: bool = True):
    """A mesh sampled by mesh_to_surfels, not normalised (dofsplat.prep.meshes.RADIUS_SCALE as
    set by --radius-scale; smooth: samples on the Phong tessellation)."""
    from dofsplat.io import load
    from dofsplat.prep.meshes import MeshPart, mesh_to_surfels

    t0 = time.perf_counter()
    if name == "square-mesh":
        v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
        surfels = mesh_to_surfels(MeshPart(v, [[0, 1, 2], [0, 2, 3]]), 40_000,
                                  smooth=smooth, normalise="none", source="square")
        return surfels, [(0, 0, 1), (0, 0.8, 1)], (0, 1, 0), time.perf_counter() - t0
    if name == "spot":
        spot = DATA / "spot"
        surfels = load(spot / "spot_triangulated.obj", texture=spot / "spot_texture.png",
                       smooth=smooth, normalise="none")
        return surfels, [(0, 0, 1), (1, 0.3, 0.2)], (0, 1, 0), time.perf_counter() - t0
    surfels = load(DATA / "stanford_dragon" / "dragon_vrip.ply.gz", smooth=smooth,
                   normalise="none")
    return surfels, [(0, 0, 1), (1, 0.3, 0.2)], (0, 1, 0), time.perf_counter() - t0


def cameras(surfels, directions, up, size, close_up=CLOSE_UP_PX_PER_RADIUS):
    """One framing camera per direction; size None: the close-up size (the median radius
    ``close_up`` px)."""
    lo, hi = surfels.bounds()
    out = []
    for d in directions:
        cam = ds.Camera.framing(lo, hi, 512, 512, 30.0, direction=d, up=up)
        if size is None:
            dist = math.dist(cam.eye, cam.target)
            px = float(np.median(surfels.radius)) * cam.pixels_per_unit_at_unit_depth / dist
            side = int(min(4096, max(512, round(512 * close_up / px))))
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
    ap.add_argument("--models", nargs="+", default=list(POINT_MODELS), choices=MODELS,
                    help=f"default: the point models; meshes: {', '.join(MESH_MODELS)}")
    ap.add_argument("--methods", nargs="+", choices=("none", "object", "render"),
                    help="normalisations to measure (default: all; with --quick none, object)")
    ap.add_argument("--close-up", type=float, default=CLOSE_UP_PX_PER_RADIUS,
                    help="pixels per median surfel radius in the close-up views")
    ap.add_argument("--radius-scale", type=float, default=None,
                    help="meshes: disk radius over the radius of the area a sample stands "
                         "for (default: dofsplat.prep.meshes.RADIUS_SCALE)")
    ap.add_argument("--quick", action="store_true",
                    help="512 x 512 only, object method only")
    ap.add_argument("--k", type=int, default=None,
                    help="neighbours for points_to_surfels (default: its DEFAULT_K)")
    ap.add_argument("--no-smooth", dest="smooth", action="store_false",
                    help="keep the points' measured positions (points_to_surfels), meshes' "
                         "samples on the flat faces")
    args = ap.parse_args(argv)
    if args.radius_scale is not None:
        import dofsplat.prep.meshes

        dofsplat.prep.meshes.RADIUS_SCALE = args.radius_scale
    methods = ("none", "object") if args.quick else ("none", "object", "render")
    methods = args.methods or methods
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
        if name in ("dragon", "lion", "spot", "dragon-mesh") and not DATA.is_dir():
            print(f"| {name} | (skipped: {DATA} not found) |", file=sys.stderr)
            continue
        surfels, directions, up, t_pre = model(name, k=args.k, smooth=args.smooth)
        views = {size: cameras(surfels, directions, up, size, args.close_up) for size in sizes}
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
