"""Frame times of several commits, paired: each checked out beside this one, alternating (issue 15).

    git worktree add -f ../old 12450ad --detach
    python bench/paired_frames.py old=../old new=.                # plane, lion, demo
    python bench/paired_frames.py old=../old new=. --runs 3 --repeat 9 --images
    python bench/paired_frames.py old=../old new=. --scenes g-guitar g-biker-hd   # 3DGS captures
    git worktree remove --force ../old

Each LABEL=PATH is a checkout of the package. A run starts one process per checkout, in
turn (each with its own numba cache under the system's temporary folder), and each process
renders every scene of ``bench/profile.py`` (this checkout's; "g-NAME" and "g-NAME-hd" are
``bench/gaussians.py``'s 3DGS captures at 320 x 240 and 1920 x 1080 with a 35 px lens)
pinhole and at its largest aperture with the default settings: a warm-up frame, then the median of ``--repeat`` frames,
timed whole. After ``--runs`` rounds the table gives the median of the runs' medians per
checkout, and each one's ratio to the first. ``--images`` also compares every frame's image
and depth map with the first checkout's, bit for bit, and gives those that differ their
largest difference and PSNR (the issue's bound: 60 dB). Alternating rounds spread this
machine's drift over all checkouts; the spread between rounds is the noise to quote.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent


def difference(a: np.ndarray, b: np.ndarray) -> str:
    """How far image b is from a: the largest difference and the PSNR over a's range (the
    issue's bound is 60 dB; a depth map's range is its finite depths')."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    both = np.isfinite(a) & np.isfinite(b)
    if not np.array_equal(np.isfinite(a), np.isfinite(b)):
        return f"{int((np.isfinite(a) != np.isfinite(b)).sum())} pixels finite in one only"
    err = np.abs(a[both] - b[both])
    peak = max(float(a[both].max() - min(a[both].min(), 0.0)), 1e-30) if both.any() else 1.0
    mse = float(np.mean(err ** 2)) if err.size else 0.0
    psnr = "inf" if mse == 0.0 else f"{10.0 * np.log10(peak * peak / mse):.1f}"
    return f"largest difference {err.max() if err.size else 0.0:.3g}, PSNR {psnr} dB"


def frames(root: str, scenes: list[str], repeat: int, out: str) -> None:
    """In a child process: the frames of ``root``'s package; times to out.json, images to
    out.npz."""
    sys.path.insert(0, str(Path(root).resolve()))
    import dofsplat as ds

    assert Path(ds.__file__).resolve().is_relative_to(Path(root).resolve()), ds.__file__
    sys.path.insert(1, str(BENCH))
    from profile import APERTURES, scene  # this checkout's scenes, the package under test

    times, images = {}, {}
    for name in scenes:
        surfels, camera, lens = scene(name)
        # (a Gaussian scene, "g-NAME": pinhole and its own 35 px lens, profile.gaussian_scene)
        apertures = APERTURES.get(name, (0.0, lens.aperture))
        for aperture in sorted({apertures[0], apertures[-1]}):
            thin = dataclasses.replace(lens, aperture=aperture) if aperture > 0 else None
            ds.render(surfels, camera, thin)
            ms, result = [], None
            for _ in range(repeat):
                t = time.perf_counter()
                result = ds.render(surfels, camera, thin)
                ms.append((time.perf_counter() - t) * 1000.0)
            key = f"{name}, A = {aperture:g}"
            times[key] = statistics.median(ms)
            images[key + " image"] = np.asarray(result.image)
            images[key + " depth"] = np.asarray(result.depth)
    Path(out + ".json").write_text(json.dumps(times))
    np.savez(out + ".npz", **images)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkouts", nargs="*", metavar="LABEL=PATH")
    ap.add_argument("--scenes", nargs="+", default=["plane", "lion", "demo"])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--images", action="store_true", help="compare images with the first")
    ap.add_argument("--child", nargs=2, metavar=("ROOT", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        frames(args.child[0], args.scenes, args.repeat, args.child[1])
        return 0
    pairs = [c.split("=", 1) for c in args.checkouts]
    if not pairs or any(len(p) != 2 or not Path(p[1], "dofsplat").is_dir() for p in pairs):
        ap.error("give checkouts as LABEL=PATH, each PATH holding the dofsplat package")
    pairs = [(label, str(Path(root).resolve())) for label, root in pairs]
    tmp = Path(tempfile.mkdtemp(prefix="dofsplat-pairs-"))
    results = {label: [] for label, _ in pairs}
    for run in range(args.runs):
        for label, root in pairs:
            out = str(tmp / f"{label}-{run}")
            env = dict(os.environ, PYTHONPATH=root,
                       NUMBA_CACHE_DIR=str(tmp / f"numba-{label}"))
            subprocess.run([sys.executable, __file__, "--child", root, out, "--repeat",
                            str(args.repeat), "--scenes", *args.scenes], check=True, env=env,
                           cwd=tmp)
            results[label].append(json.loads(Path(out + ".json").read_text()))
            print(f"run {run + 1}/{args.runs}: {label} done", file=sys.stderr, flush=True)
    labels = [label for label, _ in pairs]
    print("| frame | " + " | ".join(labels) + " | "
          + " | ".join(f"{b} / {labels[0]}" for b in labels[1:]) + " |")
    print("|---|" + "---:|" * (2 * len(labels) - 1))
    for key in results[labels[0]][0]:
        med = [statistics.median(r[key] for r in results[label]) for label in labels]
        print(f"| {key} | " + " | ".join(f"{m:.1f}" for m in med) + " | "
              + " | ".join(f"{m / med[0]:.3f}" for m in med[1:]) + " |")
    if args.images:
        first = np.load(tmp / f"{labels[0]}-0.npz")
        for label in labels[1:]:
            other = np.load(tmp / f"{label}-0.npz")
            same = [k for k in first.files if np.array_equal(first[k], other[k])]
            print(f"{label}: {len(same)} of {len(first.files)} images and depth maps equal "
                  f"to {labels[0]}'s bit for bit"
                  + ("" if len(same) == len(first.files)
                     else "; differ: " + ", ".join(sorted(set(first.files) - set(same)))))
            for key in sorted(set(first.files) - set(same)):
                print(f"  {key}: {difference(first[key], other[key])}")
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
