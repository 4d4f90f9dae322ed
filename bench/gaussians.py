"""Gaussian scenes through a lens (issue 48): dofsplat against gsplat and against the truth.

    python bench/gaussians.py [--size 640x480] [--samples 256] [--scenes donut fruit ...]
        [--out bench/gaussians.json]
    python bench/gaussians.py --visibility --size 960x720 --samples 64   # its resolution
    python bench/gaussians.py --backgrounds --size 320x240   # black and white backgrounds

For each shared 3DGS scene, seen by the default camera of ``dofsplat render`` (the scene's
``view_bounds`` framed from +z, up = the scene's ``up_hint``):

* **pinhole**: dofsplat's frame against gsplat 1.5.3's image of the same Gaussians and
  camera (``bench/gsplat_peer.py``; skipped where torch and gsplat are not installed:
  ``pip install -e ".[gsplat-peer]"``), PSNR on the displayed values;
* **depth of field**, focused on the surface at the image centre, at apertures whose largest
  circle of confusion over the frame's depths (its 2nd and 98th percentiles) is 10, 20 and
  35 px: the default frame (``default``: the lens in 4 parts drawn in layers, LOD), the
  parts drawn whole (``whole``: the default frame of 2026-11-28, ``cpu_gauss.LAYERS`` off),
  the default without LOD (``no_lod``), one pass (``one_pass``), the viewers' blur as they
  ship it (``viewers``: PlayCanvas splat-transform's and Spark's; one pass, every Gaussian)
  and the pinhole image, each against the truth, the average of ``--samples`` pinhole
  frames through points of the lens (``dofsplat reference``): whole-frame PSNR and the
  worst 2 % of 32 x 32 tiles;
* **time**: each variant once, then the pinhole, default and whole frames in turn
  ``--repeat`` times (medians; the ratios to the pinhole frame are of the same turns, so
  that a shared machine's load falls on all three alike; the machine is named).

The figures go to ``--out`` (JSON) and a table on stdout; bench/RESULTS.md quotes them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
SCENES = {
    "donut": DATA / "gaussian_donut" / "fused.ply",
    "fruit": DATA / "gaussian_scenes" / "fruit_drops_minimal.ply",
    "guitar": DATA / "gaussian_scenes" / "guitar.compressed.ply",
    "biker": DATA / "gaussian_scenes" / "biker.spz",
    "playbot": DATA / "gaussian_scenes" / "playbot" / "1_0" / "meta.json",
}
COCS = (10.0, 20.0, 35.0)
TILE = 32


def default_camera(scene, width, height):
    import dofsplat as ds

    lo, hi = scene.view_bounds()
    return ds.Camera.framing(lo, hi, width, height, 40.0, direction=(0.0, 0.0, 1.0),
                             up=tuple(getattr(scene, "up_hint", (0.0, 1.0, 0.0))))


def worst_tiles(a, b, fraction=0.02):
    """The mean PSNR of the worst ``fraction`` of 32 x 32 tiles (displayed values)."""
    from dofsplat.metrics import display_values

    x, y = display_values(a), display_values(b)
    h, w = x.shape[:2]
    scores = []
    for ty in range(0, h - TILE + 1, TILE):
        for tx in range(0, w - TILE + 1, TILE):
            mse = float(np.mean((x[ty:ty + TILE, tx:tx + TILE] - y[ty:ty + TILE, tx:tx + TILE]) ** 2))
            scores.append(10 * np.log10(1.0 / max(mse, 1e-12)))
    scores = np.sort(scores)
    k = max(1, int(round(fraction * len(scores))))
    return float(np.mean(scores[:k]))


def lens_for(scene, camera, coc_px, depth):
    """The thin lens focused at the image centre's depth whose largest CoC over the frame's
    depths (2nd-98th percentile) is coc_px."""
    import dofsplat as ds

    d = depth[np.isfinite(depth)]
    focus = float(np.median(depth[camera.height // 2 - 2:camera.height // 2 + 3,
                                  camera.width // 2 - 2:camera.width // 2 + 3]))
    if not np.isfinite(focus):
        focus = float(np.median(d))
    near, far = np.percentile(d, 2), np.percentile(d, 98)
    worst = max(abs(1 / near - 1 / focus), abs(1 / far - 1 / focus))
    aperture = 2 * coc_px / (camera.pixels_per_unit_at_unit_depth * worst)
    return ds.ThinLens(focus_distance=focus, aperture=aperture)


def gsplat_image(scene, camera):
    try:
        sys.path.insert(0, str(ROOT / "bench"))
        import gsplat_peer
    except ImportError as e:
        return None, f"gsplat peer unavailable ({e})"
    try:
        image, _ = gsplat_peer.gsplat_render(scene, camera)
    except ImportError as e:
        return None, f"gsplat peer unavailable ({e})"
    return np.asarray(image, np.float64), None


def whole_parts(render):
    """``render`` with the lens's parts drawn whole (``cpu_gauss.LAYERS`` off)."""
    from dofsplat.backends import cpu_gauss

    def run(*args):
        layers = cpu_gauss.LAYERS
        cpu_gauss.LAYERS = dataclasses.replace(layers, enabled=False)
        try:
            return render(*args)
        finally:
            cpu_gauss.LAYERS = layers
    return run


def run_scene(name, path, size, samples, settings, repeat=3):
    import dofsplat as ds
    from dofsplat.io import linear_to_srgb, load
    from dofsplat.metrics import psnr
    from dofsplat.reference import render_reference

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = load(path)
    camera = default_camera(scene, *size)
    out = {"scene": str(path.relative_to(DATA)), "gaussians": len(scene),
           "sh_degree": scene.sh_degree, "size": list(size)}
    t = time.perf_counter()
    pinhole = ds.render(scene, camera, None, settings)
    out["pinhole_s"] = time.perf_counter() - t
    peer, why = gsplat_image(scene, camera)
    if peer is not None:
        ours = linear_to_srgb(pinhole.rgb.astype(np.float64))
        mse = float(np.mean((ours - np.clip(peer, 0, 1)) ** 2))
        out["pinhole_vs_gsplat_db"] = 10 * np.log10(1 / max(mse, 1e-20))
    else:
        out["pinhole_vs_gsplat_db"] = why
    out["dof"] = []
    for coc in COCS:
        lens = lens_for(scene, camera, coc, pinhole.depth)
        t = time.perf_counter()
        ref = render_reference(scene, camera, lens, settings, samples=samples, progress=False)
        ref_s = time.perf_counter() - t
        row = {"coc_px": coc, "focus": lens.focus_distance, "aperture": lens.aperture,
               "reference_s": ref_s}
        variants = {
            "default": (ds.render, settings),
            "whole": (whole_parts(ds.render), settings),
            "no_lod": (ds.render, dataclasses.replace(settings, gaussian_lod=False)),
            "one_pass": (ds.render, dataclasses.replace(settings, gaussian_lens_samples=1)),
            # the viewers' blur as they ship it: one pass, every Gaussian
            "viewers": (ds.render, dataclasses.replace(settings, gaussian_blur="viewers",
                                                       gaussian_lens_samples=1,
                                                       gaussian_lod=False)),
        }
        frames = {}
        for key, (render, st) in variants.items():
            t = time.perf_counter()
            frames[key] = render(scene, camera, lens, st)
            row[f"{key}_s"] = time.perf_counter() - t
        # the ratios to the pinhole frame, from turns of the three
        turns = {"pinhole": (ds.render, None, settings), "default": (ds.render, lens, settings),
                 "whole": (whole_parts(ds.render), lens, settings)}
        seconds = {key: [] for key in turns}
        for _ in range(repeat):
            for key, (render, turn_lens, st) in turns.items():
                t = time.perf_counter()
                render(scene, camera, turn_lens, st)
                seconds[key].append(time.perf_counter() - t)
        for key in turns:
            row[f"{key}_median_s"] = float(np.median(seconds[key]))
        for key in ("default", "whole"):
            row[f"{key}_x_pinhole"] = row[f"{key}_median_s"] / row["pinhole_median_s"]
        frames["pinhole"] = pinhole
        for key, frame in frames.items():
            row[key] = {"psnr": psnr(frame.image, ref.image),
                        "worst_2pct_tiles": worst_tiles(frame.image, ref.image)}
        out["dof"].append(row)
        print(f"  {name} CoC {coc:4.0f} px: " + "  ".join(
            f"{k} {row[k]['psnr']:.2f} ({row[k]['worst_2pct_tiles']:.2f})" for k in frames)
            + f"  default {row['default_median_s']:.2f} s = {row['default_x_pinhole']:.2f} x "
              f"pinhole, whole {row['whole_median_s']:.2f} s = {row['whole_x_pinhole']:.2f} x, "
              f"pinhole {row['pinhole_median_s']:.2f} s; no LOD {row['no_lod_s']:.2f} s (once)",
            flush=True)
    return out


def convergence() -> None:
    """The lens in K parts against the reference as K grows, on a random scene of 300
    Gaussians (SH 3) at a 5-10 px blur, 96 x 72; and the plain pinhole frames from the 64
    parts' centroids, averaged (what the parts would give without their residual blur)."""
    import dofsplat as ds
    from dofsplat.frame import lens_parts
    from dofsplat.metrics import psnr
    from dofsplat.reference import render_reference

    rng = np.random.default_rng(3)
    n = 300
    scene = ds.Gaussians(positions=rng.uniform(-0.6, 0.6, (n, 3)),
                         scales=rng.uniform(0.01, 0.08, (n, 3)), rotations=rng.normal(size=(n, 4)),
                         opacity=rng.uniform(0.3, 1.0, n), sh=rng.normal(0, 0.4, (n, 16, 3)))
    camera = ds.Camera(eye=(0.3, -0.2, 2.5), target=(0, 0, 0), width=96, height=72,
                       fov_y=40.0, near=0.01)
    lens = ds.ThinLens(focus_distance=2.2, aperture=1.5)
    settings = ds.RenderSettings()
    ref = render_reference(scene, camera, lens, settings, samples=1024, progress=False)
    for k in (1, 4, 16, 64):
        frame = ds.render(scene, camera, lens, dataclasses.replace(settings, gaussian_lens_samples=k))
        print(f"  {k:2d} parts: {psnr(frame.image, ref.image):.2f} dB")
    parts = lens_parts(camera, lens, dataclasses.replace(settings, lens_samples=64))
    mean = sum(ds.render(scene, c, None, settings).image for c in parts.cameras) / 64
    print(f"  pinhole frames from the 64 parts' centroids: {psnr(mean, ref.image):.2f} dB")


def lenses(names, size, samples, settings, scaled=False):
    """(name, scene, camera, C_r px, lens, the lens reference) for each scene at the 10 and
    35 px lenses (``lens_for``); scaled: the lenses of a 320 px wide frame, whose C_r at
    --size is that x width / 320."""
    import dofsplat as ds
    from dofsplat.io import load
    from dofsplat.reference import render_reference

    for name in names:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = load(SCENES[name])
        camera = default_camera(scene, *size)
        pinhole = ds.render(scene, camera, None, settings)
        for coc in (10.0, 35.0):
            coc_px = coc * size[0] / 320 if scaled else coc
            lens = lens_for(scene, camera, coc_px, pinhole.depth)
            ref = render_reference(scene, camera, lens, settings, samples=samples, progress=False)
            yield name, scene, camera, coc_px, lens, ref


def lod(names, size, samples) -> None:
    """The Gaussian LOD cut (``gaussian_lod``) against no LOD, each against the reference,
    at stops (``lod_blur_fraction``) 0.35, 0.1 and 0.03, at 10 and 35 px; times of the
    second of two runs."""
    import dofsplat as ds
    from dofsplat.metrics import psnr

    settings = ds.RenderSettings()
    for name, scene, camera, coc, lens, ref in lenses(names, size, samples, settings):
        cells = []
        for label, fraction in (("no LOD", None), ("0.35", 0.35), ("0.1", 0.1), ("0.03", 0.03)):
            st = dataclasses.replace(settings, gaussian_lod=False) if fraction is None else \
                dataclasses.replace(settings, gaussian_lod=True, lod_blur_fraction=fraction)
            for _ in range(2):
                t = time.perf_counter()
                frame = ds.render(scene, camera, lens, st)
                seconds = time.perf_counter() - t
            cells.append(f"{label}: {psnr(frame.image, ref.image):.2f} dB {seconds:.2f} s "
                         f"{frame.stats['splats_rendered']:,} splats")
        print(f"  {name} {coc:.0f} px: " + " | ".join(cells), flush=True)


def visibility(names, size, samples) -> None:
    """The lens visibility's resolution (``cpu_gauss.LayerSettings.visibility_scale``, and the
    blur's rule ``visibility_scale_for``): the default frame with its visibility at 1/4,
    1/8 and 1/16 the resolution and by the rule, each against the reference, with the
    bench's 10 and 35 px lenses (the lens of a 320 px wide frame: at --size its C_r is
    that x width / 320); times of the second of two runs."""
    import dofsplat as ds
    from dofsplat.backends import cpu_gauss
    from dofsplat.metrics import psnr

    settings = ds.RenderSettings()
    saved = cpu_gauss.LAYERS
    for name, scene, camera, coc, lens, ref in lenses(names, size, samples, settings, True):
        rule = cpu_gauss.visibility_scale_for(scene.positions, camera, lens, settings)
        cells = []
        for label, scale in (("1/4", 4), ("1/8", 8), ("1/16", 16), (f"rule 1/{rule}", None)):
            cpu_gauss.LAYERS = saved if scale is None else dataclasses.replace(
                saved, visibility_scale=scale, visibility_max_scale=scale)
            try:
                for _ in range(2):
                    t = time.perf_counter()
                    frame = ds.render(scene, camera, lens, settings)
                    seconds = time.perf_counter() - t
            finally:
                cpu_gauss.LAYERS = saved
            cells.append(f"{label}: {psnr(frame.image, ref.image):.2f} dB {seconds:.2f} s")
        print(f"  {name} {coc:.0f} px: " + " | ".join(cells), flush=True)


def backgrounds(names, size, samples) -> None:
    """The default frame, no LOD, one pass, the viewers' blur and the pinhole image against the
    lens reference over a black background (the bench's) and a white one, whole-frame PSNR,
    and the alpha channel's PSNR and sum (the same on both): a black background hides a
    frame's excess coverage where that coverage is dark, a white one shows it."""
    import dofsplat as ds
    from dofsplat.metrics import psnr

    variants = {"default": {}, "no LOD": {"gaussian_lod": False},
                "one pass": {"gaussian_lens_samples": 1},
                "viewers": {"gaussian_blur": "viewers", "gaussian_lens_samples": 1,
                            "gaussian_lod": False}}
    for bg in ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)):
        settings = ds.RenderSettings(background=bg)
        for name, scene, camera, coc, lens, ref in lenses(names, size, samples, settings):
            frames = {k: ds.render(scene, camera, lens, dataclasses.replace(settings, **v))
                      for k, v in variants.items()}
            frames["pinhole"] = ds.render(scene, camera, None, settings)
            cells = [f"{k} {psnr(f.image, ref.image):.2f} (alpha "
                     f"{psnr(f.image[..., 3], ref.image[..., 3], 'linear'):.1f}, summed "
                     f"{f.image[..., 3].sum():,.0f})" for k, f in frames.items()]
            cells.append(f"reference's alpha summed {ref.image[..., 3].sum():,.0f}")
            print(f"  {name} {coc:.0f} px, background {bg[0]:.0f}: " + " | ".join(cells),
                  flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--samples", type=int, default=256)
    parser.add_argument("--repeat", type=int, default=3,
                        help="turns of the pinhole, default and whole frames timed (medians)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "gaussians.json")
    parser.add_argument("--convergence", action="store_true",
                        help="only the lens in 1-64 parts against the reference (a random scene)")
    parser.add_argument("--lod", action="store_true",
                        help="only the Gaussian LOD cut against no LOD (--scenes, --size, --samples)")
    parser.add_argument("--visibility", action="store_true",
                        help="only the lens visibility at 1/4, 1/8, 1/16 the resolution and by "
                             "the blur's rule (--scenes, --size, --samples)")
    parser.add_argument("--backgrounds", action="store_true",
                        help="only the frames against the reference over a black and a white "
                             "background, with the alpha channel's PSNR (--scenes, --size, "
                             "--samples)")
    args = parser.parse_args(argv)
    if args.backgrounds:
        backgrounds(args.scenes, tuple(int(v) for v in args.size.lower().split("x")),
                    args.samples)
        return 0
    if args.visibility:
        visibility(args.scenes, tuple(int(v) for v in args.size.lower().split("x")),
                   args.samples)
        return 0
    if args.convergence:
        convergence()
        return 0
    if args.lod:
        lod(args.scenes, tuple(int(v) for v in args.size.lower().split("x")), args.samples)
        return 0
    size = tuple(int(v) for v in args.size.lower().split("x"))
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # torch beside numba on 2 cores
    import dofsplat as ds
    from dofsplat.render import warm_up

    warm_up()
    settings = ds.RenderSettings()
    results = {"machine": f"{platform.machine()} {os.cpu_count()} cores, {platform.node()}",
               "samples": args.samples, "scenes": {}}
    for name in args.scenes:
        if not SCENES[name].exists():
            print(f"  {name}: not found ({SCENES[name]})")
            continue
        results["scenes"][name] = run_scene(name, SCENES[name], size, args.samples, settings,
                                            args.repeat)
        if isinstance(results["scenes"][name]["pinhole_vs_gsplat_db"], float):
            print(f"  {name}: pinhole against gsplat "
                  f"{results['scenes'][name]['pinhole_vs_gsplat_db']:.2f} dB", flush=True)
        args.out.write_text(json.dumps(results, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
