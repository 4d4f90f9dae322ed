"""Where a model's rendered weight density comes from (docs/maths.md, "More on μ").

A blurred surface's coverage is min(1, w), w its accumulated splat weight, so a model whose
weights sum to 0.98 over its interior renders 2 % too transparent when blurred. The lion
scan does (Figure 6, bench/RESULTS.md). This prints the median (and 5th / 25th / 75th /
95th percentiles) of the pinhole frame's weight over interior pixels (alpha > 0.999,
eroded by 6 px), no LOD, 512 x 512:

* the lion (bench/table1.py's view) as loaded, and with one setting changed at a time:
  no back-face culling, ``z_thickness`` 8, cutoff 4, the "render" normalisation;
* synthetic flat squares of 120,000 random points (radii the 8th neighbour's distance,
  object normalisation): irregular, with depth noise, seen at 30 and 15 degrees, in rows
  four times denser along than across, and with noisy normals;
* the lion's normals against their 16 neighbours' mean, and the convergence of its object
  normalisation (the smoothed sums at its centres; the weights a fresh run from 1 gives);
* ``--psnr``: Figure 6's lion with its weights scaled so that the pinhole median reads 1,
  against a 200-sample reference of the scaled model (ours, no LOD, post-filter; minutes).

    python bench/density.py            # about a minute
    python bench/density.py --psnr     # and the scaled lion against its reference
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


def interior_weights(result) -> np.ndarray:
    """The frame's weights over its interior: alpha > 0.999, eroded by 6 px."""
    inner = binary_erosion(result.image[..., 3] > 0.999, iterations=6)
    return result.weight[inner]


def row(label: str, result) -> str:
    w = interior_weights(result)
    if w.size == 0:
        return f"| {label} | 0 | | |"
    pct = " / ".join(f"{v:.3f}" for v in np.percentile(w, PERCENTILES))
    return f"| {label} | {w.size:,} | {np.median(w):.3f} | {pct} |"


def lion_rows(scene) -> tuple[list[str], str]:
    """The lion's table rows, and a line on what culling removes."""
    from dofsplat.io import load
    from table1 import LION

    surfels, camera = scene.surfels, scene.camera
    pinhole = ds.render(surfels, camera, None, SETTINGS)
    rows = [row("lion, as loaded", pinhole)]
    for label, changed in (("no back-face culling", {"cull_backfaces": False}),
                           ("z_thickness 8", {"z_thickness": 8.0}),
                           ("cutoff 4", {"cutoff": 4.0})):
        rows.append(row(f"lion, {label}", ds.render(surfels, camera, None,
                                                    dataclasses.replace(SETTINGS, **changed))))
    unculled = ds.render(surfels, camera, None, dataclasses.replace(SETTINGS,
                                                                    cull_backfaces=False))
    gain = float(unculled.image[..., 3].sum() / pinhole.image[..., 3].sum())
    rendered = load(LION, normalise="render")
    rows.append(row("lion, the render normalisation", ds.render(rendered, camera, None,
                                                                SETTINGS)))
    return rows, f"Without culling the lion's pinhole sum of alpha is {gain:.3f} x."


def flat_square(rng, *, depth_noise=0.0, normal_noise=0.0, rows=0.0) -> ds.Surfels:
    """N_SYNTHETIC points on the square |x|, |z| <= 1 of y = 0: random, or in rows ``rows``
    times denser along than across (jittered by a tenth of the spacing); depth noise and
    normal noise (radians per axis) as given; object-normalised."""
    from dofsplat.prep.neighbours import nearest_neighbours
    from dofsplat.prep.normalise import normalise

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
    return normalise(surfels, "object", progress=False)


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
        out.append(row(f"flat square, {label}", ds.render(surfels, camera(elevation), None,
                                                           SETTINGS)))
    return out


def lion_normalisation(surfels) -> list[str]:
    from dofsplat.prep.neighbours import nearest_neighbours
    from dofsplat.prep.normalise import normalise, object_sums

    p, n = surfels.positions.astype(np.float64), surfels.normals.astype(np.float64)
    _, idx = nearest_neighbours(p, 16)
    mean = n[idx].sum(1)
    mean /= np.linalg.norm(mean, axis=1)[:, None]
    agree = np.median(np.abs(np.sum(n * mean, axis=1)))
    sums = np.median(object_sums(surfels))
    fresh = normalise(dataclasses.replace(surfels, weight=None), "object", progress=False)
    ratio = np.median(fresh.weight / surfels.weight)
    return [f"lion: normals against their 16 neighbours' mean, median cos {agree:.4f} "
            f"({math.degrees(math.acos(min(agree, 1.0))):.1f} degrees)",
            f"lion: object sums at the centres (smoothed), median {sums:.4f}; a fresh "
            f"normalisation from weights of 1 ends at {ratio:.4f} x the loaded weights"]


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
    args = ap.parse_args(argv)

    from paper import lion

    scene = lion(512)
    print("| frame (pinhole, no LOD, 512 x 512) | interior px | median weight | "
          "percentiles 5 / 25 / 50 / 75 / 95 |")
    print("|---|---:|---:|---|")
    note = None
    if scene is not None:
        rows, note = lion_rows(scene)
        for line in rows:
            print(line, flush=True)
    for line in synthetic_rows():
        print(line, flush=True)
    if scene is not None:
        print()
        print(note)
        for line in lion_normalisation(scene.surfels):
            print(line)
        if args.psnr:
            print()
            for line in scaled_lion_psnr(scene, args.samples):
                print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
