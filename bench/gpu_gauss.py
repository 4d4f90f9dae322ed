"""Gaussian scenes on the GPU against the CPU: milliseconds per frame (issue 48).

    python bench/gpu_gauss.py [--scenes donut guitar biker playbot] [--size 1920x1080]
        [--cocs 10 35] [--repeat 10] [--cpu-repeat 2] [--no-gpu] [--data DIR] [--json FILE]
    python bench/gpu_gauss.py --no-gpu --cocs --cpu-repeat 5   # the CPU's pinhole frames

Each shared 3DGS scene (playbot: its finest level, 500,000 Gaussians), seen by the default
camera of ``dofsplat render`` (bench/gaussians.py's ``default_camera``), focused on the
surface at the image centre: the pinhole frame and, at apertures whose largest circle of
confusion over the frame's depths is 10 and 35 px (``lens_for``), the default frame (the lens
in 4 parts drawn in layers, LOD, lens visibility), the default without LOD, and the default
with each part drawn whole (``whole``: ``cpu_gauss.LAYERS`` off, on both devices). GPU: ``render(...,
device="cuda")`` by the wall clock (the LOD cut on the host and the image's copy to it
included), the median of --repeat after one warm frame, with its stages' times (select: the
LOD cut, on the host, and the upload; visibility: the lens visibility's 7 small views; draw:
the K lens parts' passes; copy: the final colour conversion and the copy to the host); CPU: the
same frame on the CPU backend with all of numba's threads, the median of --cpu-repeat. Each
row checks the two images against each other (mean and largest absolute difference; the
parity tests' bounds are 1e-3 and 1e-2).
--no-gpu times the CPU alone (the 2-core machine's figures for issue 48's 1.5 s target).

The scenes are read from --data (default ../shared/data; a folder holding the files
directly, as bench/gpu_check.sh carries them, also works).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import dofsplat as ds  # noqa: E402
from dofsplat.backends import cpu_gauss  # noqa: E402
from dofsplat.io import load  # noqa: E402
from gaussians import default_camera, lens_for  # noqa: E402
from gpu import SHARED, gpu_name, wall_ms  # noqa: E402

SCENES = {
    "donut": "gaussian_donut/fused.ply",
    "guitar": "gaussian_scenes/guitar.compressed.ply",
    "biker": "gaussian_scenes/biker.spz",
    "playbot": "gaussian_scenes/playbot/0_0/meta.json",
}
COCS = (10.0, 35.0)


def find(data: Path, relpath: str) -> Path:
    """relpath under data, or (a carried flat folder) its last part, or for a SOG level its
    folder's name."""
    for p in (data / relpath, data / Path(relpath).name, data / Path(relpath).parent.name /
              Path(relpath).name):
        if p.exists():
            return p
    raise SystemExit(f"bench/gpu_gauss.py: {relpath} is not under {data}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--size", default="1920x1080", metavar="WxH")
    ap.add_argument("--cocs", nargs="*", type=float, default=list(COCS), metavar="PX",
                    help="largest circles of confusion of the blurred frames (none: the "
                         "pinhole frame only)")
    ap.add_argument("--repeat", type=int, default=10, help="GPU frames timed (median)")
    ap.add_argument("--cpu-repeat", type=int, default=2, help="CPU frames timed (median)")
    ap.add_argument("--no-gpu", action="store_true", help="time the CPU backend alone")
    ap.add_argument("--no-cpu", action="store_true", help="time the GPU backend alone")
    ap.add_argument("--data", type=Path, default=SHARED, help="folder of the scenes")
    ap.add_argument("--json", type=Path, help="also write every measurement here")
    args = ap.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    import numba

    gpu = not args.no_gpu
    print(f"{'GPU: ' + gpu_name() + ', ' if gpu else ''}CPU: {platform.processor() or platform.machine()}, "
          f"numba {numba.__version__} with {numba.get_num_threads()} threads, "
          f"Python {platform.python_version()}\n")
    cols = ["scene", "Gaussians", "CoC px", "frame", "CPU ms"]
    if gpu:
        cols += ["GPU ms", "CPU / GPU", "select", "visibility", "draw", "copy",
                 "mean / max diff"]
    print("| " + " | ".join(cols) + " |")
    print("|" + "|".join("---" if c in ("scene", "frame", "mean / max diff") else "---:"
                         for c in cols) + "|", flush=True)
    rows = []
    for name in args.scenes:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                scene = load(find(args.data, SCENES[name]))
        except (ds.DofsplatError, SystemExit) as e:
            print(f"<!-- {name}: not loaded: {e} -->", flush=True)
            continue
        camera = default_camera(scene, width, height)
        cpu_settings = ds.RenderSettings()
        pinhole = ds.render(scene, camera, None, cpu_settings)  # compiles; its depth focuses
        cases = [(0.0, "pinhole", None, cpu_settings)]
        for coc in args.cocs:
            lens = lens_for(scene, camera, coc, pinhole.depth)
            cases += [(coc, "default", lens, cpu_settings),
                      (coc, "no LOD", lens, replace(cpu_settings, gaussian_lod=False)),
                      (coc, "whole", lens, cpu_settings)]
        layered = cpu_gauss.LAYERS
        for coc, label, lens, settings in cases:
            cpu_gauss.LAYERS = replace(layered, enabled=label != "whole")
            row = {"scene": name, "gaussians": len(scene), "size": [width, height],
                   "coc_px": coc, "frame": label}
            cpu_frame = None
            if not args.no_cpu:
                row["cpu_ms"], cpu_frame = wall_ms(lambda: ds.render(scene, camera, lens,
                                                                     settings), args.cpu_repeat)
            cells = [name, f"{len(scene):,}", f"{coc:.0f}", label,
                     f"{row.get('cpu_ms', float('nan')):.0f}"]
            if gpu:
                gs = replace(settings, device="cuda")
                ds.render(scene, camera, lens, gs)  # warm: compiles, uploads the scene
                row["gpu_ms"], frame = wall_ms(lambda: ds.render(scene, camera, lens, gs),
                                               args.repeat)
                for key in ("select_ms", "visibility_ms", "draw_ms", "copy_ms"):
                    row[key] = frame.stats.get(key, 0.0)
                diff = "-"
                if cpu_frame is not None:
                    d = np.abs(cpu_frame.image.astype(np.float64) - frame.image)
                    row["mean_diff"], row["max_diff"] = float(d.mean()), float(d.max())
                    diff = f"{d.mean():.1e} / {d.max():.1e}"
                ratio = row.get("cpu_ms", float("nan")) / row["gpu_ms"]
                cells += [f"{row['gpu_ms']:.1f}", f"{ratio:.0f}x", f"{row['select_ms']:.1f}",
                          f"{row['visibility_ms']:.1f}", f"{row['draw_ms']:.1f}",
                          f"{row['copy_ms']:.1f}", diff]
            rows.append(row)
            print("| " + " | ".join(cells) + " |", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "threads": numba.get_num_threads(),
                                         "gpu": gpu_name() if gpu else None}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
