"""Where does the lens need its parts? (issue 49, item 1: a measurement before the feature.)

    python bench/parts_where.py [--size 256] [--samples 64] [--scenes contact intersect ...]
        [--margin 0.05] [--json FILE]

The lens drawn in K = 4 parts (``--lens-samples 4``) is 6 dB closer to the reference than one
pass on the fidelity suite, at 6-10 x a pinhole frame's cost. The parts can only differ from
the one pass where surfaces at different depths meet within a circle of confusion; elsewhere
one surface covers the pixel's whole circle and both draw it alike. This script asks how
much of a frame that is, and whether a test on the one pass's own output finds it:

* **the test**: an occlusion edge is a pair of neighbouring pixels of the one-pass frame
  whose depths (``RenderResult.depth``, the depth of the surface that contributes most;
  inf for the background) differ by more than ``--margin`` of the nearer one; each edge
  pixel marks the pixels within the larger of the two depths' CoC radii (+1 px); a 16 x 16
  tile with a marked pixel needs the parts;
* **the oracle**: the tiles where the 4-part frame and the one pass differ by more than
  a tile PSNR of 45 dB between themselves;
* **the hybrid**: the 4-part frame on the tiles the test marks, the one pass elsewhere (a
  composite of the two whole frames: the quality a tile-restricted drawing of the parts
  would give, before any blending at the boundary).

For each fidelity scene (``bench/fidelity.py``'s, at --size) at the three apertures whose
largest CoC is 10, 20 and 40 px at 512 x 512 (scaled with the size), against a reference of
--samples lens samples: the share of tiles the test marks and the oracle needs, the test's
recall of the oracle's tiles, and the whole-frame and worst-2 %-tile PSNR of the one pass,
the 4 parts and the hybrid.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))

import dofsplat as ds  # noqa: E402
from dofsplat.frame import coc_coefficients  # noqa: E402
from fidelity import (SCENES, TARGET_COC_PX, aperture_for_coc, reference_frame, scores,  # noqa: E402
                      tile_psnr, time_frames)

TILE = 16  # the raster's tiles
ORACLE_DB = 45.0  # a tile where parts and one pass agree to this is one the parts do not change


def doubt_mask(depth: np.ndarray, coc_k: float, inv_focus: float, margin: float) -> np.ndarray:
    """(H, W) bool: the pixels within a CoC of an occlusion edge of the depth map (the
    module docstring's test)."""
    d = np.where(np.isfinite(depth), depth, np.inf).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        coc = np.where(np.isfinite(d), coc_k * np.abs(1.0 / d - inv_focus), 0.0)
    radius = np.zeros(d.shape)
    for axis in (0, 1):
        a = d
        b = np.roll(d, -1, axis=axis)
        near = np.minimum(a, b)
        far = np.maximum(a, b)
        with np.errstate(invalid="ignore"):
            jump = (far > near * (1.0 + margin)) & np.isfinite(near)
        if axis == 0:
            jump[-1, :] = False
        else:
            jump[:, -1] = False
        r = np.maximum(coc, np.roll(coc, -1, axis=axis)) + 1.0
        radius = np.maximum(radius, np.where(jump, r, 0.0))
    # each edge pixel marks a disc of its radius: dilate by classes of radius (powers of 2)
    mask = np.zeros(d.shape, bool)
    top = max(1.0, float(radius.max()))
    lo = 0.0
    r = 1.0
    while lo < top:
        hi = r
        cls = (radius > lo) & (radius <= hi)
        if cls.any():
            size = int(np.ceil(hi))
            yy, xx = np.mgrid[-size:size + 1, -size:size + 1]
            mask |= ndimage.binary_dilation(cls, structure=(xx * xx + yy * yy) <= hi * hi)
        lo, r = hi, 2.0 * r
    return mask


LAYERS: list = []  # the one pass's most surfaces a pixel held, per tile (backends.cpu.draw)


def _keep_layers() -> None:
    """Note each drawn frame's per-tile surface counts (``rasterize``'s stats) in LAYERS."""
    from dofsplat.backends import cpu

    def noting(draw):
        def drawn(*args, **kwargs):
            out = draw(*args, **kwargs)
            LAYERS.append(out[3]["tile_layers"].copy())
            return out
        return drawn

    cpu.draw_cut, cpu.draw = noting(cpu.draw_cut), noting(cpu.draw)


def tiles_of(mask: np.ndarray) -> np.ndarray:
    h, w = mask.shape
    rows, cols = -(-h // TILE), -(-w // TILE)
    padded = np.zeros((rows * TILE, cols * TILE), bool)
    padded[:h, :w] = mask
    return padded.reshape(rows, TILE, cols, TILE).any(axis=(1, 3))


def expand(tiles: np.ndarray, shape) -> np.ndarray:
    h, w = shape
    return np.repeat(np.repeat(tiles, TILE, axis=0), TILE, axis=1)[:h, :w]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--margin", type=float, default=0.05)
    ap.add_argument("--test", choices=("layers", "edges"), default="layers")
    ap.add_argument("--repeat", type=int, default=3, help="frames timed (median)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    _keep_layers()
    scale = args.size / 512.0
    print("| scene | CoC px | tiles marked | oracle | recall | one pass | 4 parts | hybrid | "
          "needed | ms: pinhole, one pass, 4 parts, needed |")
    print("|---|---:|---:|---:|---:|---|---|---|---|---|")
    rows = []
    for name in args.scenes:
        scene = SCENES[name](args.size, args.size)
        if scene is None:
            print(f"<!-- {name}: data missing -->")
            continue
        for target in TARGET_COC_PX:
            coc = target * scale
            lens = scene.lens(aperture_for_coc(scene, coc))
            ref, _ = reference_frame(scene, lens, args.samples, cache=None)
            def frame(lens_, **kw):
                st = dataclasses.replace(scene.settings, **kw)
                return lambda: ds.render(scene.surfels, scene.camera, lens_, st)

            ms = {}
            ms["pinhole"], _ = time_frames(frame(None), args.repeat)
            ms["one"], one = time_frames(frame(lens, lens_samples=1), args.repeat)
            layers = LAYERS[-1]
            ms["parts"], parts = time_frames(frame(lens, lens_samples=4), args.repeat)
            ms["needed"], needed = time_frames(frame(lens, lens_samples=4, lens_parts="needed"),
                                               args.repeat)
            k, inv_focus = coc_coefficients(scene.camera, lens, scene.settings)
            edges = tiles_of(doubt_mask(one.depth, k, inv_focus, args.margin))
            marked = layers >= 2 if args.test == "layers" else edges
            oracle = tile_psnr(parts.image, one.image, TILE) < ORACLE_DB
            pick = expand(marked, one.depth.shape)[..., None]
            hybrid = np.where(pick, parts.image, one.image)
            s = {key: scores(img, ref)[0] for key, img in
                 (("one", one.image), ("parts", parts.image), ("hybrid", hybrid),
                  ("needed", needed.image))}
            recall = float((marked & oracle).sum() / max(1, oracle.sum()))
            row = {"scene": name, "coc_px": coc, "marked": float(marked.mean()), "ms": ms,
                   "needed_tiles": needed.stats.get("parts_tiles"),
                   "oracle": float(oracle.mean()), "recall": recall,
                   **{f"{key}_{m}": s[key][m] for key in s for m in ("psnr", "worst_tile_psnr")}}
            rows.append(row)
            cells = [f"{s[key]['psnr']:.2f} ({s[key]['worst_tile_psnr']:.2f})"
                     for key in ("one", "parts", "hybrid", "needed")]
            times = ", ".join(f"{ms[key]:.0f}" for key in ("pinhole", "one", "parts", "needed"))
            print(f"| {name} | {coc:.0f} | {row['marked']:.0%} | {row['oracle']:.0%} | "
                  f"{recall:.0%} | " + " | ".join(cells) + f" | {times} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
