"""The aperture's disc against the paper's Gaussian (issue 14): quality and cost in one run.

    python bench/bokeh.py [--scenes plane lion demo] [--samples 200] [--repeat 3]

For the paper's plane and lion at Table 1's apertures and the demo at two apertures, each
frame (512 x 512, LOD on and off) is rendered with ``bokeh="disc"`` (the default) and
``bokeh="gaussian"`` (the paper's) and compared with the multisample reference of the same
round lens (``--samples`` lens samples, cached in ~/.cache/dofsplat/bokeh). Times are the
median of ``--repeat`` frames after a warm-up, and the disc / Gaussian ratio is taken within
the run. Writes bench/bokeh.json and prints a markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import dofsplat as ds  # noqa: E402
from dofsplat.demo import demo_scene, plane_scene  # noqa: E402
from dofsplat.metrics import compare  # noqa: E402
from dofsplat.reference import render_reference  # noqa: E402

APERTURES = {"plane": (0.1, 0.4), "lion": (0.5, 2.0), "demo": (0.12, 0.3)}
CACHE = Path.home() / ".cache" / "dofsplat" / "bokeh"


def scene(name: str):
    if name == "plane":
        return plane_scene(512, 512)
    if name == "demo":
        return demo_scene(512, 512)
    from table1 import lion_scene

    return lion_scene(None)


def reference(name, surfels, camera, lens, samples, progress):
    """The reference of the round lens, cached by scene, lens, samples and a pinhole frame."""
    pin = ds.render(surfels, camera, None, ds.RenderSettings(lod=False)).image
    key = hashlib.blake2b(f"{name}{camera}{lens.focus_distance}{lens.diameter}{samples}".encode()
                          + pin.tobytes(), digest_size=10).hexdigest()
    path = CACHE / f"{name}_{key}.npy"
    if path.exists():
        return np.load(path)
    img = render_reference(surfels, camera, lens, samples=samples, progress=progress).image
    CACHE.mkdir(parents=True, exist_ok=True)
    np.save(path, img)
    return img


def timed(surfels, camera, lens, settings, repeat):
    ds.render(surfels, camera, lens, settings)
    runs = []
    for _ in range(repeat):
        t = time.perf_counter()
        res = ds.render(surfels, camera, lens, settings)
        runs.append((time.perf_counter() - t) * 1000.0)
    return res, statistics.median(runs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(APERTURES), choices=list(APERTURES))
    ap.add_argument("--samples", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=str(Path(__file__).with_name("bokeh.json")))
    args = ap.parse_args(argv)
    records = []
    print("| scene | A | LOD | disc: PSNR / SSIM | Gaussian: PSNR / SSIM | disc (ms) | Gaussian (ms) | disc / Gaussian |")
    print("|---|---:|:---:|---:|---:|---:|---:|---:|")
    for name in args.scenes:
        surfels, camera, lens = scene(name)
        for a in APERTURES[name]:
            disc = dataclasses.replace(lens, aperture=a, bokeh="disc")
            gauss = dataclasses.replace(disc, bokeh="gaussian")
            ref = reference(name, surfels, camera, disc, args.samples, sys.stderr.isatty())
            for lod in (True, False):
                st = ds.RenderSettings(lod=lod)
                d_res, d_ms = timed(surfels, camera, disc, st, args.repeat)
                g_res, g_ms = timed(surfels, camera, gauss, st, args.repeat)
                d_q, g_q = compare(d_res.image, ref), compare(g_res.image, ref)
                records.append({"scene": name, "aperture": a, "lod": lod, "disc": d_q,
                                "gaussian": g_q, "disc_ms": d_ms, "gaussian_ms": g_ms,
                                "disc_fragments": d_res.stats["fragments"],
                                "gaussian_fragments": g_res.stats["fragments"]})
                print(f"| {name} | {a:g} | {'yes' if lod else 'no'} | {d_q['psnr']:.2f} / "
                      f"{d_q['ssim']:.3f} | {g_q['psnr']:.2f} / {g_q['ssim']:.3f} | {d_ms:.0f} | "
                      f"{g_ms:.0f} | {d_ms / g_ms:.2f} |", flush=True)
    Path(args.out).write_text(json.dumps({"samples": args.samples, "records": records}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
