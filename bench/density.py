"""Where a model's rendered weight density comes from (docs/maths.md, "More on μ").

A blurred surface's coverage is min(1, w), w its accumulated splat weight, so a model whose
weights sum to 0.98 over its interior renders 2 % too transparent when blurred. The lion
scan did (Figure 6, bench/RESULTS.md) before the normalisation's level was calibrated
(``prep.normalise.rendered_level``). This prints the median (and 5th / 25th / 75th / 95th
percentiles) of the pinhole frame's weight over interior pixels (alpha > 0.999, eroded by
6 px), no LOD, 512 x 512, and its mean over the interior that does not select pixels by
their weight (``prep.normalise.interior_mask``, ``edge_margin`` inside every edge: the
measure the calibration uses; the alpha mask keeps pixels whose weight is 0.9 or more and
drops the surroundings of the dips, so its median leans high where a sampling dips):

* the lion (bench/table1.py's view) as loaded, and with one setting changed at a time:
  no back-face culling, ``z_thickness`` 8, cutoff 4, the "render" normalisation; the
  object normalisation without its calibration;
* synthetic flat squares of 120,000 random points (radii the 8th neighbour's distance,
  object normalisation): irregular, with depth noise, seen at 30 and 15 degrees, in rows
  four times denser along than across, and with noisy normals;
* the lion's normals against their 16 neighbours' mean, and the convergence of its object
  normalisation (the smoothed sums at its centres; the weights a fresh run from 1 gives);
* ``--psnr``: Figure 6's lion with its weights scaled so that the pinhole median reads 1,
  against a 200-sample reference of the scaled model (ours, no LOD, post-filter; minutes).

    python bench/density.py                  # about half a minute
    python bench/density.py --uncalibrated   # every normalisation without its calibration
    python bench/density.py --level          # and the measures behind the calibration
    python bench/density.py --psnr           # and the scaled lion against its reference

``--uncalibrated`` gives the figures docs/maths.md's "More on μ" quotes (written before the
calibration).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_erosion

import dofsplat as ds

sys.path.insert(0, str(Path(__file__).resolve().parent))

PERCENTILES = (5, 25, 50, 75, 95)
SETTINGS = ds.RenderSettings(lod=False)
N_SYNTHETIC = 120_000
CALIBRATE = [True]  # --uncalibrated sets it False


def interior_weights(result) -> np.ndarray:
    """The frame's weights over its interior: alpha > 0.999, eroded by 6 px."""
    inner = binary_erosion(result.image[..., 3] > 0.999, iterations=6)
    return result.weight[inner]


def interior_mean(result, surfels, camera) -> float:
    """The frame's mean weight over prep.normalise.interior_mask, edge_margin inside, each
    pixel read as at most LEVEL_MAX_READING: as rendered_level reads it."""
    from dofsplat.prep.normalise import LEVEL_MAX_READING, edge_margin, interior_mask

    mask = interior_mask(result, camera, erode=edge_margin(surfels, camera, SETTINGS.cutoff))
    reading = np.minimum(result.weight[mask], LEVEL_MAX_READING)
    return float(reading.mean()) if mask.any() else float("nan")


def row(label: str, result, surfels, camera) -> str:
    w = interior_weights(result)
    mean = interior_mean(result, surfels, camera)
    if w.size == 0:
        return f"| {label} | 0 | | | {mean:.3f} |"
    pct = " / ".join(f"{v:.3f}" for v in np.percentile(w, PERCENTILES))
    return f"| {label} | {w.size:,} | {np.median(w):.3f} | {pct} | {mean:.3f} |"


def normalised(surfels: ds.Surfels, method: str = "object") -> ds.Surfels:
    from dofsplat.prep.normalise import normalise

    return normalise(surfels, method, calibrate=CALIBRATE[0], progress=False)


def lion_rows(scene) -> tuple[list[str], str, ds.Surfels]:
    """The lion's table rows, a line on what culling removes, and the model measured."""
    from dofsplat.io import load
    from table1 import LION

    camera = scene.camera
    raw = load(LION, normalise="none")
    surfels = normalised(raw) if not CALIBRATE[0] else scene.surfels
    pinhole = ds.render(surfels, camera, None, SETTINGS)
    rows = [row("lion, as loaded", pinhole, surfels, camera)]
    for label, changed in (("no back-face culling", {"cull_backfaces": False}),
                           ("z_thickness 8", {"z_thickness": 8.0}),
                           ("cutoff 4", {"cutoff": 4.0})):
        settings = dataclasses.replace(SETTINGS, **changed)
        rows.append(row(f"lion, {label}", ds.render(surfels, camera, None, settings),
                        surfels, camera))
    unculled = ds.render(surfels, camera, None, dataclasses.replace(SETTINGS,
                                                                    cull_backfaces=False))
    gain = float(unculled.image[..., 3].sum() / pinhole.image[..., 3].sum())
    rendered = normalised(raw, "render")
    rows.append(row("lion, the render normalisation", ds.render(rendered, camera, None,
                                                                SETTINGS), rendered, camera))
    if CALIBRATE[0]:
        from dofsplat.prep.normalise import normalise

        plain = normalise(raw, "object", calibrate=False, progress=False)
        rows.append(row("lion, object normalisation, not calibrated",
                        ds.render(plain, camera, None, SETTINGS), plain, camera))
    return rows, f"Without culling the lion's pinhole sum of alpha is {gain:.3f} x.", surfels


def flat_square(rng, *, depth_noise=0.0, normal_noise=0.0, rows=0.0) -> ds.Surfels:
    """N_SYNTHETIC points on the square |x|, |z| <= 1 of y = 0: random, or in rows ``rows``
    times denser along than across (jittered by a tenth of the spacing); depth noise and
    normal noise (radians per axis) as given; object-normalised."""
    from dofsplat.prep.neighbours import nearest_neighbours

    n = N_SYNTHETIC
    if rows:
        n_rows = int(round((n / rows) ** 0.5))
        n_cols = n // n_rows
        gx, gz = np.meshgrid(np.linspace(-1, 1, n_cols), np.linspace(-1, 1, n_rows))
        xz = np.c_[gx.ravel(), gz.ravel()] + rng.normal(0, 0.2 / n_cols, (n_rows * n_cols, 2))
    else:
        xz = rng.uniform(-1, 1, (n, 2))
    n = len(xz)
    positions = np.c_[xz[:, 0], rng.normal(0, depth_noise, n) if depth_noise else np.zeros(n),
                      xz[:, 1]]
    normals = np.tile([0.0, 1.0, 0.0], (n, 1))
    if normal_noise:
        normals[:, [0, 2]] += rng.normal(0, normal_noise, (n, 2))
        normals /= np.linalg.norm(normals, axis=1)[:, None]
    dist, _ = nearest_neighbours(positions, 8)
    surfels = ds.Surfels(positions=positions, normals=normals, radius=dist[:, -1],
                         colors=np.full((n, 3), 0.5))
    return normalised(surfels)


def synthetic_rows() -> list[str]:
    spacing = 2.0 / math.sqrt(N_SYNTHETIC)

    def camera(elevation_deg: float) -> ds.Camera:
        e = math.radians(elevation_deg)
        eye = (0.0, 3.0 * math.sin(e), 3.0 * math.cos(e) + 1e-3)
        return ds.Camera(eye=eye, target=(0.0, 0.0, 0.0), width=512, height=512, fov_y=30,
                         near=0.01)

    cases = (("random", {}, 90), ("depth noise of 1/6 spacing",
                                  {"depth_noise": spacing / 6}, 90),
             ("random, seen at 30 degrees", {}, 30), ("random, seen at 15 degrees", {}, 15),
             ("rows, 4 x denser along them", {"rows": 4.0}, 90),
             ("normal noise 0.14 rad per axis", {"normal_noise": 0.14}, 90))
    out = []
    for label, options, elevation in cases:
        surfels = flat_square(np.random.default_rng(1), **options)
        cam = camera(elevation)
        out.append(row(f"flat square, {label}", ds.render(surfels, cam, None, SETTINGS),
                       surfels, cam))
    return out


def lion_normalisation(surfels) -> list[str]:
    from dofsplat.prep.neighbours import nearest_neighbours
    from dofsplat.prep.normalise import object_sums

    p, n = surfels.positions.astype(np.float64), surfels.normals.astype(np.float64)
    _, idx = nearest_neighbours(p, 16)
    mean = n[idx].sum(1)
    mean /= np.linalg.norm(mean, axis=1)[:, None]
    agree = np.median(np.abs(np.sum(n * mean, axis=1)))
    sums = np.median(object_sums(surfels))
    fresh = normalised(dataclasses.replace(surfels, weight=None))
    ratio = np.median(fresh.weight / surfels.weight)
    return [f"lion: normals against their 16 neighbours' mean, median cos {agree:.4f} "
            f"({math.degrees(math.acos(min(agree, 1.0))):.1f} degrees)",
            f"lion: object sums at the centres (smoothed), median {sums:.4f}; a fresh "
            f"normalisation from weights of 1 ends at {ratio:.4f} x the loaded weights"]


def level_rows(scene) -> list[str]:
    """--level: the measures behind the level's calibration (docs/maths.md, "The level,
    calibrated"), on models normalised without it: the mean interior weight against the
    resolution, a jittered grid, the lion's capture views, and where on the lion it is low."""
    from dofsplat.io import load
    from dofsplat.prep.neighbours import fibonacci_directions, nearest_neighbours
    from dofsplat.prep.normalise import (LEVEL_VIEWS, normalisation_cameras, normalise,
                                         rendered_level)
    from dofsplat.prep.pointcloud import points_to_surfels
    from scipy.ndimage import gaussian_filter
    from table1 import DRAGON, LION

    def plain(surfels):
        return normalise(surfels, "object", calibrate=False, progress=False)

    def mean_at(surfels, camera):
        return interior_mean(ds.render(surfels, camera, None, SETTINGS), surfels, camera)

    out = ["mean interior weight (interior_mask, edge_margin inside), object normalisation "
           "without the calibration:"]
    rng = np.random.default_rng(1)
    square = plain(dataclasses.replace(flat_square(rng), weight=None))
    xz = np.random.default_rng(1).uniform(-1, 1, (N_SYNTHETIC, 2))
    piped = points_to_surfels(np.c_[xz[:, 0], np.zeros(N_SYNTHETIC), xz[:, 1]],
                              normalise="none", progress=False)
    piped = plain(piped)
    cells = {"flat square (8th-neighbour radii, exact normals)": [],
             "the same points through points_to_surfels": []}
    for size in (128, 256, 512, 1024):
        cam = ds.Camera(eye=(0, 3, 1e-3), target=(0, 0, 0), width=size, height=size,
                        fov_y=30, near=0.01)
        cells["flat square (8th-neighbour radii, exact normals)"].append(
            f"{size}: {mean_at(square, cam):.3f}")
        cells["the same points through points_to_surfels"].append(
            f"{size}: {mean_at(piped, cam):.3f}")
    raw = load(LION, normalise="none")
    lion = plain(raw)
    cells["lion (Table 1's view)"] = [
        f"{size}: {mean_at(lion, dataclasses.replace(scene.camera, width=size, height=size)):.3f}"
        for size in (256, 512, 1024, 2048)]
    out += [f"  {name}: " + ", ".join(v) for name, v in cells.items()]

    # a jittered grid: each point random within its cell, 80 x 80, spacing 0.02
    n, h = 80, 0.02
    g = (np.arange(n) - (n - 1) / 2) * h
    gx, gy = np.meshgrid(g, g)
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(n * n)], axis=1)
    pts[:, :2] += np.random.default_rng(7).uniform(-0.5, 0.5, (n * n, 2)) * h
    jitter = points_to_surfels(pts, normalise="none", progress=False)
    jp = plain(jitter)
    jc = normalise(jitter, "object", progress=False)
    face = ds.Camera(eye=(0, 0, 2.4), target=(0, 0, 0), width=160, height=160, fov_y=30)
    tilt = ds.Camera(eye=(0, 1.5, 1.9), target=(0, 0, 0), width=160, height=160, fov_y=30)
    out.append(f"  jittered grid: face-on {mean_at(jp, face):.3f}, 38 degrees "
               f"{mean_at(jp, tilt):.3f}; calibrated {mean_at(jc, face):.3f} / "
               f"{mean_at(jc, tilt):.3f} (level {rendered_level(jp):.4f})")

    # the lion's capture views
    views = []
    for d, cam in zip(fibonacci_directions(LEVEL_VIEWS), normalisation_cameras(lion,
                                                                                LEVEL_VIEWS)):
        views.append(f"{mean_at(lion, cam):.3f}")
    out.append(f"  the lion's {LEVEL_VIEWS} capture views ({cam.width} px): "
               f"{', '.join(views)}; pooled level {rendered_level(lion):.4f}; the dragon's "
               f"level {rendered_level(plain(load(DRAGON, normalise='none'))):.4f}")

    # where on the lion: the frame's weight smoothed by 2 px, read at each visible surfel
    result = ds.render(lion, scene.camera, None, SETTINGS)
    inner = binary_erosion(result.image[..., 3] > 0.5, iterations=6)
    num = gaussian_filter(np.where(inner, result.weight, 0.0), 2.0)
    den = gaussian_filter(inner.astype(np.float64), 2.0)
    local = num / np.maximum(den, 1e-9)
    p = lion.positions.astype(np.float64)
    nrm = lion.normals.astype(np.float64)
    xy, depth = scene.camera.project(p)
    to_eye = np.asarray(scene.camera.eye) - p
    cos = np.sum(nrm * to_eye, 1) / np.linalg.norm(to_eye, axis=1)
    hgt, wid = result.weight.shape
    jx = np.clip(np.floor(xy[:, 0]).astype(int), 0, wid - 1)
    iy = np.clip(np.floor(xy[:, 1]).astype(int), 0, hgt - 1)
    seen = (cos > 0.5) & (xy[:, 0] >= 0) & (xy[:, 0] < wid) & (xy[:, 1] >= 0)
    seen &= (xy[:, 1] < hgt) & inner[iy, jx] & (den[iy, jx] > 0.95)
    seen &= np.abs(result.depth[iy, jx] - depth) < 0.01 * depth
    read = local[iy, jx]
    dist, idx = nearest_neighbours(p, 16)
    r = lion.radius.astype(np.float64)
    d = p[idx[:, 1:9]] - p[:, None]
    dn = nrm[idx[:, 1:9]] - nrm[:, None]
    features = {
        "radius / 6th neighbour's distance": r / dist[:, 6],
        "weight": lion.weight.astype(np.float64),
        "radius x curvature (> 0 convex)": r * np.mean(np.sum(dn * d, 2)
                                                       / np.maximum(np.sum(d * d, 2), 1e-300), 1),
        "neighbours' distance off the plane / radius":
            np.mean(np.abs(np.sum(d * nrm[:, None], 2)), 1) / r,
        "cos of the viewing angle": cos,
    }
    out.append(f"  the lion's {int(seen.sum()):,} visible surfels, the frame's weight smoothed "
               f"by 2 px at each (median {np.median(read[seen]):.3f}), by deciles of:")
    for name, f in features.items():
        f, rd = f[seen], read[seen]
        qs = np.percentile(f, [0, 10, 30, 50, 70, 90, 100])
        bands = [f"{np.median(rd[(f >= lo) & (f <= hi)]):.3f}" for lo, hi in zip(qs[:-1], qs[1:])]
        out.append(f"    {name} (bands 0-10-30-50-70-90-100 %): {' / '.join(bands)}")
    return out


def scaled_lion_psnr(scene, samples: int) -> list[str]:
    """Figure 6's lion with weights scaled to a pinhole median of 1, against its reference."""
    from paper import VARIANTS

    from dofsplat.metrics import compare
    from dofsplat.postfilter import render_postfilter
    from dofsplat.reference import render_reference

    pinhole = ds.render(scene.surfels, scene.camera, None, VARIANTS["ours_nolod"])
    scale = float(np.median(interior_weights(pinhole)))
    surfels = dataclasses.replace(scene.surfels, weight=scene.surfels.weight / scale)
    out = [f"weights / {scale:.4f}; PSNR (dB) against the reference of the scaled model",
           "| lens | ours | ours, no LOD | post-filter |", "|---|---:|---:|---:|"]
    for view in scene.lenses:
        ref = render_reference(surfels, scene.camera, view.lens, VARIANTS["ours_nolod"],
                               samples=samples).image
        cells = [compare(ds.render(surfels, scene.camera, view.lens, VARIANTS[v]).image,
                         ref)["psnr"] for v in ("ours", "ours_nolod")]
        cells.append(compare(render_postfilter(surfels, scene.camera, view.lens,
                                               VARIANTS["ours_nolod"]).image, ref)["psnr"])
        out.append(f"| {scene.tag(view)} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
        print(out[-1], file=sys.stderr)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--psnr", action="store_true",
                    help="also Figure 6's lion at unit density against its reference")
    ap.add_argument("--samples", type=int, default=200, help="the reference's lens samples")
    ap.add_argument("--level", action="store_true",
                    help="also the measures behind the level's calibration (a minute)")
    ap.add_argument("--uncalibrated", action="store_true",
                    help="normalise without the level's calibration (the lion, the squares)")
    args = ap.parse_args(argv)
    CALIBRATE[0] = not args.uncalibrated

    from paper import lion

    scene = lion(512)
    print("| frame (pinhole, no LOD, 512 x 512) | interior px | median weight | "
          "percentiles 5 / 25 / 50 / 75 / 95 | mean, interior_mask |")
    print("|---|---:|---:|---|---:|")
    note = None
    if scene is not None:
        rows, note, measured = lion_rows(scene)
        for line in rows:
            print(line, flush=True)
    for line in synthetic_rows():
        print(line, flush=True)
    if scene is not None:
        print()
        print(note)
        for line in lion_normalisation(measured):
            print(line)
        if args.level:
            print()
            for line in level_rows(scene):
                print(line, flush=True)
        if args.psnr:
            print()
            for line in scaled_lion_psnr(scene, args.samples):
                print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
