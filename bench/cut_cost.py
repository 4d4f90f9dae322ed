"""The blurred frame's cost against the pinhole frame: today's LOD cut and the paper's (issue 13).

    python bench/cut_cost.py                          # the fidelity suite's six scenes
    python bench/cut_cost.py --scenes lion_leaves pane --rounds 3 --repeat 5

Issue 13 asks that the default frame at the suite's largest aperture (a CoC of up to 40 px)
cost at most 2 x the pinhole frame of the same run. This times, per scene of
``bench/fidelity.py`` (its camera, focus and settings), three frames in one process,
alternating, ``--rounds`` rounds of ``--repeat`` frames each after a warm-up:

* the pinhole frame (LOD's pixel stop alone);
* the blurred frame with the renderer's default cut (``RenderSettings``: the stop's margin
  ``lod_blur_fraction`` 0.35, ``lod_min_node`` 4, ``lod_color_tolerance`` 0.02);
* the same with the paper's cut (Section 6.2: ``lod_blur_fraction`` 1, any node,
  ``lod_color_tolerance`` inf), the coarsest the renderer draws.

It prints each frame's median over the rounds (the median of each round's frames), the
rounds' spread, and both blurred frames against the pinhole frame. What each cut costs in
quality is ``python bench/fidelity.py`` with the same settings (bench/RESULTS.md, "The
paper's cut against the budget").
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import dofsplat as ds  # noqa: E402
from fidelity import SCENES, TARGET_COC_PX, aperture_for_coc, machine  # noqa: E402

PAPER = "paper's cut"
PAPER_CUT = {"lod_blur_fraction": 1.0, "lod_min_node": 2, "lod_color_tolerance": float("inf")}


def frame_ms(render, repeat: int) -> float:
    """The median milliseconds of ``repeat`` frames."""
    ms = []
    for _ in range(repeat):
        t = time.perf_counter()
        render()
        ms.append((time.perf_counter() - t) * 1000.0)
    return statistics.median(ms)


def scene_costs(name: str, rounds: int, repeat: int, size=(512, 512)) -> dict | None:
    """{frame: [each round's median ms]} for the pinhole, default and paper-cut frames."""
    scene = SCENES[name](*size)
    if scene is None:
        return None
    lens = scene.lens(aperture_for_coc(scene, max(TARGET_COC_PX)))
    frames = {"pinhole": (None, scene.settings),
              "default cut": (lens, scene.settings),
              PAPER: (lens, dataclasses.replace(scene.settings, **PAPER_CUT))}
    for lens_, settings in frames.values():  # the JIT, the hierarchy
        ds.render(scene.surfels, scene.camera, lens_, settings)
    times = {key: [] for key in frames}
    for _ in range(rounds):
        for key, (lens_, settings) in frames.items():
            times[key].append(frame_ms(
                lambda: ds.render(scene.surfels, scene.camera, lens_, settings), repeat))
    return times


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", choices=list(SCENES), default=list(SCENES))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    print(f"Machine: {machine()}; 512 x 512, the largest CoC {max(TARGET_COC_PX):g} px; "
          f"median of {args.rounds} rounds of {args.repeat} frames, alternating\n")
    print("| scene | pinhole (ms) | default cut (ms) | paper's cut (ms) | default / pinhole "
          "| paper's / pinhole |")
    print("|---|---:|---:|---:|---:|---:|")
    for name in args.scenes:
        times = scene_costs(name, args.rounds, args.repeat)
        if times is None:
            continue
        med = {key: statistics.median(v) for key, v in times.items()}
        cells = [f"{med[k]:.1f} ({min(v):.0f}–{max(v):.0f})" for k, v in times.items()]
        print(f"| {name} | " + " | ".join(cells)
              + f" | {med['default cut'] / med['pinhole']:.2f} x"
              + f" | {med[PAPER] / med['pinhole']:.2f} x |",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
