"""Regenerate the paper's results (Section 7): Figure 6 pairs with PSNR/SSIM, and the timing
of the multisample reference against ours.

DRAFT (issue 5): the plane is done; the lion scan (Figure 6's second model) and Figure 1
(a semi-transparent surface in front of an opaque model) are stubs that say so, to be
filled in when the lion loader lands. Each piece is one function; a scene is one entry in
SCENES.

    python bench/paper.py                             # everything, N = 200, 512 x 512
    python bench/paper.py --size 128 --samples 16     # a quick look (seconds)
    python bench/paper.py --scenes plane --apertures 0.1 0.2

Writes under --out (default bench/paper/): per scene and aperture the images ours, ours
without LOD, the reference, the post-filter, and a difference image (10 x |ours - ref|);
one montage per scene; results.json with every number. Prints markdown tables for
bench/RESULTS.md. Timings exclude JIT compilation (one warm-up frame first).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import dofsplat as ds
from dofsplat.io import write_image
from dofsplat.metrics import compare, write_difference
from dofsplat.postfilter import render_postfilter
from dofsplat.reference import DEFAULT_SAMPLES, render_reference

OUT_DIR = Path(__file__).resolve().parent / "paper"
PLANE_APERTURES = (0.1, 0.2, 0.4)  # world units; as bench_plane.py: max CoC 10, 20, 40 px at 512^2
QUALITY_GOAL_DB = {"plane": 35.0, "lion": 30.0}  # issue 5's aims against the 200-sample reference
TIMING_REPEAT = 5  # frames of ours per timing (median)


@dataclass
class Scene:
    """A model, a view and the lens diameters of its Figure 6 row."""

    name: str
    surfels: ds.Surfels
    camera: ds.Camera
    focus_distance: float  # P, world units
    apertures: tuple[float, ...]  # lens diameters A, world units
    note: str = ""


# -- scenes --------------------------------------------------------------------------------


def plane(size: int, apertures=None) -> Scene:
    """The paper's Plane: 262,144 textured surfels at a grazing angle, focus mid-plane."""
    from dofsplat.demo import plane_scene

    surfels, camera, lens = plane_scene(size, size)
    return Scene("plane", surfels, camera, lens.focus_distance,
                 tuple(apertures or PLANE_APERTURES),
                 note="dofsplat.demo.plane_scene: 512 x 512 surfels on a 4-unit square")


def lion(size: int, apertures=None) -> Scene | None:
    """The paper's scanned lion: ../shared/data/lion_takanawa (a Potree scan, not the
    paper's 81,458-point model). Not yet: needs the point-cloud loader (normals, radii)."""
    return None


SCENES = {"plane": plane, "lion": lion}


# -- Figure 6: ours beside the reference, with PSNR and SSIM -------------------------------


@dataclass
class Row:
    scene: str
    aperture: float
    max_coc_px: float
    ours: dict  # compare() against the reference: psnr, ssim, mse, space
    ours_no_lod: dict
    postfilter: dict
    ours_ms: float  # median of TIMING_REPEAT frames
    reference_s: float
    samples: int


def figure6(scene: Scene, samples: int, out: Path, progress: bool) -> list[Row]:
    rows = []
    lod, no_lod = ds.RenderSettings(), ds.RenderSettings(lod=False)
    for a in scene.apertures:
        lens = ds.ThinLens(focus_distance=scene.focus_distance, aperture=a)
        tag = f"{scene.name}_A{a:g}"

        ours_ms, ours = time_ours(scene, lens, lod)
        ours_nl = ds.render(scene.surfels, scene.camera, lens, no_lod)
        post = render_postfilter(scene.surfels, scene.camera, lens, no_lod)
        ref = render_reference(scene.surfels, scene.camera, lens, no_lod, samples=samples,
                               progress=progress)

        images = {"ours": ours.image, "ours_nolod": ours_nl.image, "postfilter": post.image,
                  "reference": ref.image}
        for kind, image in images.items():
            write_image(out / f"{tag}_{kind}.png", image)
        write_difference(out / f"{tag}_diff.png", ours.image, ref.image)
        write_difference(out / f"{tag}_diff_postfilter.png", post.image, ref.image)

        rows.append(Row(scene.name, a, max_coc(scene, lens), compare(ours.image, ref.image),
                        compare(ours_nl.image, ref.image), compare(post.image, ref.image),
                        ours_ms, ref.stats["total_ms"] / 1000.0, ref.stats["samples"]))
        print(f"  {tag}: ours {rows[-1].ours['psnr']:.2f} dB, reference "
              f"{rows[-1].reference_s:.1f} s", file=sys.stderr)
    montage(scene, rows, out)
    return rows


def time_ours(scene: Scene, lens, settings):
    ds.render(scene.surfels, scene.camera, lens, settings)  # warm-up: JIT, LOD hierarchy
    runs, result = [], None
    for _ in range(TIMING_REPEAT):
        t = time.perf_counter()
        result = ds.render(scene.surfels, scene.camera, lens, settings)
        runs.append((time.perf_counter() - t) * 1000.0)
    return statistics.median(runs), result


def max_coc(scene: Scene, lens) -> float:
    xy, depth = scene.camera.project(scene.surfels.positions)
    w, h = scene.camera.width, scene.camera.height
    seen = (depth > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
    return float(lens.coc_radius_px(depth[seen], scene.camera).max()) if seen.any() else 0.0


def montage(scene: Scene, rows: list[Row], out: Path) -> None:
    """One picture per scene: a row per aperture, ours | reference | post-filter | diff."""
    from PIL import Image, ImageDraw, ImageFont

    kinds = ("ours", "reference", "postfilter", "diff")
    w, h = scene.camera.width, scene.camera.height
    caption = 28
    sheet = Image.new("RGB", (w * len(kinds), (h + caption) * len(rows)), "white")
    draw = ImageDraw.Draw(sheet)
    try:
        font = ImageFont.load_default(size=max(9, min(16, w // 32)))  # Pillow >= 10.1
    except TypeError:
        font = ImageFont.load_default()
    for r, row in enumerate(rows):
        tag = f"{scene.name}_A{row.aperture:g}"
        y = r * (h + caption)
        for k, kind in enumerate(kinds):
            with Image.open(out / f"{tag}_{kind}.png") as im:
                sheet.paste(im.convert("RGB"), (k * w, y))
        labels = (f"ours  {row.ours['psnr']:.1f} dB  SSIM {row.ours['ssim']:.3f}",
                  f"reference, N = {row.samples}, A = {row.aperture:g}",
                  f"post-filter  {row.postfilter['psnr']:.1f} dB  "
                  f"SSIM {row.postfilter['ssim']:.3f}",
                  "10 x |ours - reference|")
        for k, text in enumerate(labels):
            draw.text((k * w + 6, y + h + 6), text, fill="black", font=font)
    sheet.save(out / f"figure6_{scene.name}.png")


# -- Figure 1 ------------------------------------------------------------------------------


def figure1(size: int, out: Path) -> None:
    """A semi-transparent surface in front of an opaque model, focused on each in turn.
    Not yet: waits for the model loaders (issue 4); the renderer supports it already."""
    print("figure 1: not yet (needs a model from ../shared/data)", file=sys.stderr)


# -- tables --------------------------------------------------------------------------------


def fmt(m: dict) -> str:
    return f"{m['psnr']:.2f} / {m['ssim']:.4f}" if math.isfinite(m["psnr"]) else "inf / 1"


def print_tables(rows: list[Row], samples: int, size: int) -> None:
    print(f"Figure 6 at {size} x {size}, reference N = {samples}; PSNR (dB) / SSIM against "
          "the reference, on sRGB values (dofsplat.metrics)")
    print()
    print("| scene | A | max CoC (px) | ours | ours, no LOD | post-filter | goal |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        goal = QUALITY_GOAL_DB.get(r.scene)
        met = "" if goal is None else f"{goal:g} dB " + ("met" if r.ours["psnr"] >= goal
                                                           else "MISSED")
        print(f"| {r.scene} | {r.aperture:g} | {r.max_coc_px:.1f} | {fmt(r.ours)} | "
              f"{fmt(r.ours_no_lod)} | {fmt(r.postfilter)} | {met} |")
    print()
    print("Time of the reference against ours (the paper: 147 s against 0.97 s for the plane)")
    print()
    print("| scene | A | ours (ms, median of 5) | reference (s) | ratio |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r.scene} | {r.aperture:g} | {r.ours_ms:.0f} | {r.reference_s:.1f} | "
              f"{r.reference_s * 1000.0 / r.ours_ms:,.0f} x |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", choices=sorted(SCENES), default=sorted(SCENES))
    ap.add_argument("--size", type=int, default=512, help="image width and height (default 512)")
    ap.add_argument("--samples", type=int, default=DEFAULT_SAMPLES,
                    help=f"lens samples of the reference (default {DEFAULT_SAMPLES})")
    ap.add_argument("--apertures", type=float, nargs="+",
                    help="lens diameters, world units (default: each scene's own)")
    ap.add_argument("--out", type=Path, default=OUT_DIR)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    rows = []
    for name in args.scenes:
        scene = SCENES[name](args.size, args.apertures)
        if scene is None:
            print(f"{name}: not yet available, skipped", file=sys.stderr)
            continue
        print(f"{name}: {len(scene.surfels):,} surfels, {scene.note}", file=sys.stderr)
        rows += figure6(scene, args.samples, args.out, progress=True)
    figure1(args.size, args.out)

    record = {"size": args.size, "samples": args.samples,
              "rows": [dataclasses.asdict(r) for r in rows]}
    text = json.dumps(record, indent=2, default=_json_number) + "\n"
    (args.out / "results.json").write_text(text)
    print_tables(rows, args.samples, args.size)
    return 0


def _json_number(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(type(x))


if __name__ == "__main__":
    sys.exit(main())
