"""The fidelity suite (issue 13, "Occlusion without seams"): our depth of field against the
multisample reference on scenes made of occlusions, contacts and transparency.

    python bench/fidelity.py                       # every scene, 512 x 512, N = 200 (long)
    python bench/fidelity.py --scenes contact      # one scene
    python bench/fidelity.py --quick               # 128 x 128, N = 16: a smoke test

Each scene stresses the A-buffer's merge/separate decisions (docs/maths.md, "Surface
reconstruction") under blur:

* demo:                ``dofsplat.demo.demo_scene``: spheres on the textured plane, focus on
                       the yellow one;
* contact:             ``dofsplat.demo.contact_scene``: spheres resting on a checkered floor
                       (near, at the focus, far), focus on the middle one's contact point;
* intersect:           ``dofsplat.demo.intersecting_planes_scene``: two textured planes
                       crossing at 12 degrees along a diagonal through the frame, focus on the
                       line at the frame's centre;
* lion_leaves:         the Takanawa lion scan (``bench/table1.py``'s ``lion_scene``) seen from
                       behind, as in the README's picture, with the leaves of the bush in front
                       of the statue; focus on the statue's mane (pixel LION_FOCUS_PX of the
                       512 x 512 frame, about 7.1 units away), so the leaves (about 5.1-5.5
                       units) are the blurred foreground over a sharp statue: the partial
                       occlusion a post-filter cannot do (``bench/paper.py``'s "lion, behind"
                       row is the other way round: leaves behind a blurred statue);
* pane:                ``bench/paper.py``'s Figure 1: a semi-transparent pane in front of the
                       dragon, focus on the dragon (the pane blurred over it), unlit as there;
* transparent_contact: ``dofsplat.demo.transparent_contact_scene``: a sphere and a leaning
                       pane of opacity 0.5 resting on the textured floor, focus on the
                       sphere's contact point.

Each at three lens diameters, chosen so that the largest circle of confusion over the
surfels in the frame is TARGET_COC_PX (10, 20, 40 px); the CoC is linear in the diameter,
so one projection finds it (``aperture_for_coc``). Each frame is rendered by

* ours:         ``dofsplat.render`` with the scene's settings (``RenderSettings()``; the pane
                unlit), so LOD on;
* ours, no LOD: the same with ``lod=False``;
* post-filter:  ``dofsplat.postfilter.render_postfilter`` with the lens's CoC, over a
                pinhole render without LOD (as ``bench/paper.py`` calls it);

and compared with ``dofsplat.reference.render_reference`` (N = --samples lens samples) by
``dofsplat.metrics.compare`` (sRGB display values): whole-frame PSNR and SSIM, and the
worst-tile PSNR: the WORST_TILE_PERCENTILE-th percentile (numpy's linear interpolation)
of the PSNR over the TILE x TILE tiles of the frame. Every tile counts, background too; a
tile's MSE is over its pixels and colour channels, as metrics.py's; its PSNR is capped at
TILE_PSNR_CAP_DB, which an identical tile (MSE 0) gets. Whole-frame numbers hide a seam a
few pixels wide along a contact; the worst tiles show it.

Times are medians of --repeat frames after a warm-up frame (JIT and the LOD hierarchy's
build excluded), the post-filter's including its pinhole render; the pinhole frame (the
scene's settings, no lens) is timed too, so "largest aperture / pinhole" can be quoted.

References are cached in ``$XDG_CACHE_HOME/dofsplat/fidelity`` (``~/.cache/...``; or
--cache DIR) as .npy, named by a hash of the scene name, the image size, the lens, the
samples, the settings that the pinhole renders use, the surfels themselves,
REFERENCE_VERSION and the bytes of one pinhole frame rendered as the reference renders its
samples: the renderer is deterministic, so a change to it that alters what a pinhole
frame draws changes the key, and a stale reference is not used (--no-cache renders them
all again). Writes --out/fidelity.json (every number) and --out/fidelity/<scene>.png: the
worst tile of ours at the largest aperture, cropped from the reference, ours, ours without
LOD and the post-filter, enlarged ZOOM x (nearest), beside the reference frame with the
tile marked. Default --out: bench/ (bench/fidelity/quick/ with --quick).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import dofsplat as ds  # noqa: E402
from bench_plane import machine  # noqa: E402
from dofsplat import demo  # noqa: E402
from dofsplat.metrics import compare, display_values  # noqa: E402
from dofsplat.postfilter import render_postfilter  # noqa: E402
from dofsplat.reference import DEFAULT_SAMPLES, render_reference  # noqa: E402

BENCH = Path(__file__).resolve().parent
TARGET_COC_PX = (10.0, 20.0, 40.0)  # the largest CoC radius over the frame, per row
TILE = 32  # px, the side of the tiles of the worst-tile PSNR
WORST_TILE_PERCENTILE = 2.0  # of the tiles' PSNR: 256 tiles at 512^2, between the 6th and 7th worst
TILE_PSNR_CAP_DB = 100.0  # a tile with MSE 0 (or nearly) counts as this
ZOOM = 4  # the montage's enlargement of the tile crops (nearest neighbour)
REFERENCE_VERSION = "1"  # bump to render every cached reference again
QUICK = {"size": (128, 128), "samples": 16, "repeat": 1}
FULL = {"size": (512, 512), "samples": DEFAULT_SAMPLES, "repeat": 3}
METHODS = ("ours", "ours_nolod", "postfilter")
METHOD_NAMES = {"ours": "ours", "ours_nolod": "ours, no LOD", "postfilter": "post-filter"}
LION_VIEW = {  # the README's lion picture; its y-up (X, Y, Z) is (X, -Z, Y) in the PLY's z-up
    "eye": (-3.4, 11.5, 0.2), "target": (-2.89, 3.88, -1.1), "up": (0.0, 0.0, 1.0), "fov_y": 38.0}
LION_FOCUS_PX = (220, 150)  # the statue's mane, behind the leaves, in the 512 x 512 frame


# -- scenes --------------------------------------------------------------------------------


@dataclass
class FidelityScene:
    """A model, a camera, where the lens focuses and how ours renders it."""

    name: str
    surfels: ds.Surfels
    camera: ds.Camera
    focus_distance: float  # P, world units
    settings: ds.RenderSettings  # ours' settings; no LOD and the post-filter derive from them
    note: str  # one line for the progress output

    def lens(self, aperture: float) -> ds.ThinLens:
        return ds.ThinLens(focus_distance=self.focus_distance, aperture=aperture)


def _demo_module_scene(name: str, make: Callable, note: str) -> Callable:
    def build(width: int, height: int) -> FidelityScene:
        surfels, camera, lens = make(width, height)
        return FidelityScene(name, surfels, camera, lens.focus_distance, ds.RenderSettings(),
                             note)
    return build


def lion_leaves_scene(width: int, height: int) -> FidelityScene | None:
    """The lion scan from behind, leaves in front of the statue, focus on the statue."""
    from table1 import LION, lion_scene

    if not LION.exists():
        print(f"lion_leaves: {LION} not found, skipped", file=sys.stderr)
        return None
    surfels, _, _ = lion_scene(None, width, height)
    camera = ds.Camera(width=width, height=height, **LION_VIEW)
    focus = ds.focus_distance_at(surfels, camera, LION_FOCUS_PX[0] * width / 512,
                                 LION_FOCUS_PX[1] * height / 512, ds.RenderSettings(lod=False))
    return FidelityScene("lion_leaves", surfels, camera, focus, ds.RenderSettings(),
                         "the lion scan from behind, the leaves in front of it blurred, "
                         f"focus on the statue's mane ({focus:.2f})")


def pane_scene(width: int, height: int) -> FidelityScene | None:
    """Figure 1's semi-transparent pane in front of the dragon, focus on the dragon."""
    from paper import DRAGON, PANE_OPACITY, figure1_scene

    if not DRAGON.exists():
        print(f"pane: {DRAGON} not found, skipped", file=sys.stderr)
        return None
    surfels, camera, _, dragon_depth = figure1_scene(width)
    if height != width:  # figure1_scene makes square frames; the same view, other height
        camera = dataclasses.replace(camera, height=height)
    # the dragon's colours are shaded already and the pane is unlit (bench/paper.py)
    return FidelityScene("pane", surfels, camera, dragon_depth,
                         ds.RenderSettings(shading="none"),
                         f"Figure 1: a pane of opacity {PANE_OPACITY:g} before the dragon, "
                         "focus on the dragon, unlit")


SCENES: dict[str, Callable[[int, int], FidelityScene | None]] = {
    "demo": _demo_module_scene("demo", demo.demo_scene,
                               "the demo: spheres on the textured plane, focus on the yellow "
                               "one"),
    "contact": _demo_module_scene("contact", demo.contact_scene,
                                  "spheres resting on a checkered floor, focus on the middle "
                                  "one's contact"),
    "intersect": _demo_module_scene("intersect", demo.intersecting_planes_scene,
                                    f"two planes crossing at {demo.INTERSECT_ANGLE_DEG:g} "
                                    "degrees, focus on their line"),
    "lion_leaves": lion_leaves_scene,
    "pane": pane_scene,
    "transparent_contact": _demo_module_scene(
        "transparent_contact", demo.transparent_contact_scene,
        f"a sphere and a pane of opacity {demo.TRANSPARENT_OPACITY:g} on the textured floor, "
        "focus on the sphere's contact"),
}


# -- apertures -----------------------------------------------------------------------------


def max_coc(surfels: ds.Surfels, camera: ds.Camera, lens: ds.ThinLens) -> float:
    """The largest CoC radius (px) over the surfels that project into the frame."""
    xy, depth = camera.project(surfels.positions)
    seen = (depth > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < camera.width) & (xy[:, 1] >= 0) \
        & (xy[:, 1] < camera.height)
    return float(lens.coc_radius_px(depth[seen], camera).max()) if seen.any() else 0.0


def aperture_for_coc(scene: FidelityScene, target_px: float) -> float:
    """The lens diameter (world units, 4 significant digits) whose largest CoC over the
    frame is ``target_px``: C_r is proportional to the diameter (eq. 3), so one unit-lens
    projection gives it."""
    unit = max_coc(scene.surfels, scene.camera, scene.lens(1.0))
    if unit <= 0.0:
        raise ValueError(f"{scene.name}: nothing in the frame is out of focus")
    return float(f"{target_px / unit:.4g}")


# -- metrics -------------------------------------------------------------------------------


def tile_psnr(image: np.ndarray, reference: np.ndarray, tile: int = TILE) -> np.ndarray:
    """(rows, cols) PSNR in dB per ``tile`` x ``tile`` tile (the last row and column may be
    narrower), on sRGB display values as ``metrics.compare``; capped at TILE_PSNR_CAP_DB."""
    sq = (display_values(image) - display_values(reference)) ** 2  # (H, W, C)
    h, w, c = sq.shape
    rows, cols = -(-h // tile), -(-w // tile)
    padded = np.zeros((rows * tile, cols * tile, c))
    padded[:h, :w] = sq
    sums = padded.reshape(rows, tile, cols, tile, c).sum(axis=(1, 3, 4))
    heights = np.minimum(tile, h - tile * np.arange(rows))
    widths = np.minimum(tile, w - tile * np.arange(cols))
    mse = sums / (heights[:, None] * widths[None, :] * c)
    with np.errstate(divide="ignore"):
        db = 10.0 * np.log10(1.0 / mse)  # data range 1; MSE 0 gives inf
    return np.minimum(db, TILE_PSNR_CAP_DB)


def scores(image: np.ndarray, reference: np.ndarray) -> tuple[dict, np.ndarray]:
    """PSNR, SSIM (``compare``) and the worst-tile PSNR; and the tiles' PSNR."""
    m = compare(image, reference)
    tiles = tile_psnr(image, reference)
    return {"psnr": m["psnr"], "ssim": m["ssim"],
            "worst_tile_psnr": float(np.percentile(tiles, WORST_TILE_PERCENTILE))}, tiles


# -- the reference, cached -----------------------------------------------------------------


def cache_folder() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or (Path.home() / ".cache")
    return Path(base) / "dofsplat" / "fidelity"


def reference_key(scene: FidelityScene, lens: ds.ThinLens, samples: int) -> str:
    """A hash of everything the reference image depends on (module notes)."""
    digest = hashlib.sha256()
    s = scene.surfels
    for a in (s.positions, s.normals, s.radius, s.colors, s.opacity, s.tangent, s.radius_v,
              s.weight):
        digest.update(b"-" if a is None else np.ascontiguousarray(a).tobytes())
    # the settings a pinhole sample uses: not the LOD's nor the device's
    skip = {"lod", "lod_pixel_threshold", "lod_blur_fraction", "lod_min_node",
            "lod_color_tolerance", "show_lod", "device", "max_tile_pairs", "lens_samples",
            "coarse_blur_px"}  # a pinhole sample has no blur to sample coarsely
    settings = {k: v for k, v in dataclasses.asdict(scene.settings).items() if k not in skip}
    meta = {"version": REFERENCE_VERSION, "scene": scene.name,
            "size": [scene.camera.width, scene.camera.height], "camera": repr(scene.camera),
            "focus_distance": lens.focus_distance, "aperture": lens.diameter,
            "samples": samples, "settings": repr(sorted(settings.items())),
            "material": repr(s.material)}
    digest.update(json.dumps(meta, sort_keys=True).encode())
    # the frame from the lens centre, made as the reference makes its samples: the renderer
    # is deterministic (bit for bit), so a pinhole renderer that draws anything differently
    # gives a new key, and a stale reference is never compared with
    probe = render_reference(s, scene.camera, None, scene.settings, progress=False)
    digest.update(np.ascontiguousarray(probe.image).tobytes())
    return digest.hexdigest()[:20]


def reference_frame(scene: FidelityScene, lens: ds.ThinLens, samples: int,
                    cache: Path | None, progress: bool = False) -> tuple[np.ndarray, dict]:
    """The reference image (H, W, 4) float32 and {"cached": bool, "s": seconds to render
    it, when it was rendered}; read from ``cache`` if there, else rendered (and kept)."""
    cam = scene.camera
    path = None
    if cache is not None:
        key = reference_key(scene, lens, samples)
        path = cache / f"{scene.name}_{cam.width}x{cam.height}_N{samples}_{key}.npy"
        if path.exists():
            info = path.with_suffix(".json")
            seconds = json.loads(info.read_text()).get("s") if info.exists() else None
            return np.load(path), {"cached": True, "s": seconds}
    ref = render_reference(scene.surfels, cam, lens, scene.settings, samples=samples,
                           progress=progress)
    info = {"cached": False, "s": ref.stats["total_ms"] / 1000.0}
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.stem + f".tmp{os.getpid()}.npy")
        np.save(tmp, ref.image)
        os.replace(tmp, path)  # atomic: an interrupted run leaves no half a reference
        path.with_suffix(".json").write_text(json.dumps(
            {"scene": scene.name, "size": [cam.width, cam.height], "samples": samples,
             "focus_distance": lens.focus_distance, "aperture": lens.diameter,
             "version": REFERENCE_VERSION, "s": info["s"]}) + "\n")
    return ref.image, info


# -- one scene -----------------------------------------------------------------------------


def time_frames(render_once: Callable[[], ds.RenderResult], repeat: int):
    """Median milliseconds of ``repeat`` frames after a warm-up frame, and the last result."""
    result = render_once()  # JIT, the LOD hierarchy
    runs = []
    for _ in range(repeat):
        t = time.perf_counter()
        result = render_once()
        runs.append((time.perf_counter() - t) * 1000.0)
    return statistics.median(runs), result


def measure_scene(scene: FidelityScene, samples: int = DEFAULT_SAMPLES, repeat: int = 3,
                  targets=TARGET_COC_PX, cache: Path | None = None,
                  progress: bool = False) -> tuple[list[dict], dict]:
    """One row per target CoC (every number in a dict), and the frames of the largest one
    (method -> (H, W, 4) image, "reference" too) with its tiles' PSNR (``"tiles"``)."""
    surfels, camera = scene.surfels, scene.camera
    settings = {"ours": scene.settings,
                "ours_nolod": dataclasses.replace(scene.settings, lod=False)}
    pinhole_ms, _ = time_frames(lambda: ds.render(surfels, camera, None, scene.settings), repeat)
    rows, largest = [], {}
    for target in sorted(targets):
        lens = scene.lens(aperture_for_coc(scene, target))
        t = time.perf_counter()
        reference, ref_info = reference_frame(scene, lens, samples, cache, progress)
        ref_s = time.perf_counter() - t
        images, ms, stats = {}, {}, {}
        for name, s in settings.items():
            ms[name], result = time_frames(lambda s=s: ds.render(surfels, camera, lens, s),
                                           repeat)
            images[name], stats[name] = result.image, result.stats
        ms["postfilter"], post = time_frames(
            lambda: render_postfilter(surfels, camera, lens, settings["ours_nolod"]), repeat)
        images["postfilter"] = post.image
        row = {"scene": scene.name, "width": camera.width, "height": camera.height,
               "target_coc_px": target, "aperture": lens.diameter,
               "focus_distance": scene.focus_distance,
               "max_coc_px": max_coc(surfels, camera, lens), "samples": samples,
               "reference": ref_info, "pinhole_ms": pinhole_ms}
        tiles = {}
        for name in METHODS:
            row[name], tiles[name] = scores(images[name], reference)
            row[name]["ms"] = ms[name]
        for name in settings:
            row[name].update({k: stats[name].get(k) for k in
                              ("splats_rendered", "fragments", "abuffer_overflows")})
        worst = np.unravel_index(int(np.argmin(tiles["ours"])), tiles["ours"].shape)
        row["worst_tile_ours"] = {"x": int(worst[1] * TILE), "y": int(worst[0] * TILE),
                                  "psnr": float(tiles["ours"][worst])}
        rows.append(row)
        largest = {**images, "reference": reference, "tiles": tiles}
        print(f"  {scene.name} A = {lens.diameter:g} (max CoC {row['max_coc_px']:.1f} px): "
              + ", ".join(f"{METHOD_NAMES[k]} {row[k]['psnr']:.2f} dB "
                          f"(worst tiles {row[k]['worst_tile_psnr']:.1f})" for k in METHODS)
              + ("; reference cached" if ref_info["cached"]
                 else f"; reference {ref_s:.1f} s"), file=sys.stderr)
    return rows, largest


def fidelity_rows(scene: str | FidelityScene, size=(512, 512), samples: int = DEFAULT_SAMPLES,
                  repeat: int = 3, targets=TARGET_COC_PX, cache: Path | None = None,
                  progress: bool = False) -> list[dict]:
    """The rows of one scene (a name in SCENES, or a FidelityScene): importable, e.g.
    ``fidelity_rows("contact", (64, 64), samples=4, repeat=1)`` for a quick test.
    cache: a folder for the references, None to render them every time. [] if the
    scene's data is missing."""
    if isinstance(scene, str):
        scene = SCENES[scene](*size)
        if scene is None:
            return []
    return measure_scene(scene, samples, repeat, targets, cache, progress)[0]


# -- montage -------------------------------------------------------------------------------


def montage(scene: FidelityScene, row: dict, frames: dict, path: Path) -> None:
    """The worst tile of ours at the largest aperture: the reference frame with the tile
    marked, then the tile from the reference, ours, ours without LOD, the post-filter."""
    from PIL import Image, ImageDraw

    from paper import sheet

    x, y = row["worst_tile_ours"]["x"], row["worst_tile_ours"]["y"]
    cell = (slice(y, y + TILE), slice(x, x + TILE))
    i, j = y // TILE, x // TILE

    def picture(image):
        rgb = display_values(image)
        return Image.fromarray((rgb * 255.0 + 0.5).astype(np.uint8))

    def crop(image):
        pic = picture(np.asarray(image)[cell])
        return pic.resize((pic.width * ZOOM, pic.height * ZOOM), Image.NEAREST)

    side = TILE * ZOOM
    context = picture(frames["reference"])
    scale = side / max(context.width, context.height)
    context = context.resize((max(1, round(context.width * scale)),
                              max(1, round(context.height * scale))), Image.LANCZOS)
    draw = ImageDraw.Draw(context)
    draw.rectangle([x * scale, y * scale, (x + TILE) * scale - 1, (y + TILE) * scale - 1],
                   outline=(255, 40, 40))
    grid = [[context, crop(frames["reference"])]
            + [crop(frames[name]) for name in METHODS]]
    captions = [[f"reference, tile ({x}, {y})", f"reference\nN = {row['samples']}"]
                + [f"{METHOD_NAMES[name]}\ntile {frames['tiles'][name][i, j]:.1f} dB"
                   for name in METHODS]]
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet(grid, captions, path,
          f"{scene.name}: the worst {TILE}x{TILE} tile of ours at A = {row['aperture']:g} "
          f"(max CoC {row['max_coc_px']:.0f} px), x{ZOOM}")


# -- output --------------------------------------------------------------------------------


def _cell(m: dict) -> str:
    psnr = "inf" if not math.isfinite(m["psnr"]) else f"{m['psnr']:.2f}"
    return f"{psnr} / {m['ssim']:.3f} / {m['worst_tile_psnr']:.1f} / {m['ms']:,.0f}"


def print_table(record: dict) -> None:
    w, h = record["size"]
    print(f"Machine: {record['machine']}\n")
    print(f"### Against the reference (N = {record['samples']}), {w} x {h}\n")
    print(f"Each cell: PSNR (dB) / SSIM / worst-tile PSNR (dB; the "
          f"{_ordinal(WORST_TILE_PERCENTILE)} percentile of the {TILE}x{TILE} tiles' PSNR) / "
          f"ms per frame (median of {record['repeat']} after a warm-up; the post-filter's "
          "with its pinhole render).\n")
    print("| scene | A | max CoC (px) | " + " | ".join(METHOD_NAMES[k] for k in METHODS)
          + " | pinhole (ms) |")
    print("|---|---:|---:|" + "---:|" * len(METHODS) + "---:|")
    for r in record["rows"]:
        print(f"| {r['scene']} | {r['aperture']:g} | {r['max_coc_px']:.1f} | "
              + " | ".join(_cell(r[k]) for k in METHODS) + f" | {r['pinhole_ms']:,.0f} |")
    print("\nLargest aperture, ours (default settings) against the pinhole frame: "
          + "; ".join(f"{r['scene']} {r['ours']['ms'] / r['pinhole_ms']:.2f} x"
                      for r in _largest_rows(record["rows"])))
    load = record["load_average"]
    print(f"\nLoad average {load['start']:.1f} at the start, {load['end']:.1f} at the end "
          f"({os.cpu_count()} cores; other work may share the machine). Run: "
          + ", ".join(f"{k} {v:.0f} s" for k, v in record["scene_s"].items()) + ".")


def _ordinal(p: float) -> str:
    if p != int(p):
        return f"{p:g}th"
    n = int(p)
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def _largest_rows(rows: list[dict]) -> list[dict]:
    by = {}
    for r in rows:
        if r["scene"] not in by or r["aperture"] > by[r["scene"]]["aperture"]:
            by[r["scene"]] = r
    return list(by.values())


def _size(text: str) -> tuple[int, int]:
    try:
        parts = [int(v) for v in text.lower().split("x")]
    except ValueError:
        parts = []
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2 or min(parts) < 16:
        raise argparse.ArgumentTypeError(f"expected WxH of at least 16 px, got {text!r}")
    return parts[0], parts[1]


def main(argv=None) -> int:
    from paper import _finite, _json_number

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", choices=list(SCENES), default=list(SCENES))
    ap.add_argument("--size", type=_size, help="WxH (default 512x512)")
    ap.add_argument("--samples", type=int,
                    help=f"lens samples of the reference (default {DEFAULT_SAMPLES})")
    ap.add_argument("--repeat", type=int, help=f"timed frames per render (default "
                                               f"{FULL['repeat']})")
    ap.add_argument("--quick", action="store_true",
                    help=f"a smoke test: {QUICK['size'][0]}x{QUICK['size'][1]}, "
                         f"N = {QUICK['samples']}, into bench/fidelity/quick unless --out")
    ap.add_argument("--out", type=Path, help="folder for fidelity.json and fidelity/*.png "
                                             "(default bench/)")
    ap.add_argument("--cache", type=Path, help=f"folder of the cached references (default "
                                               f"{cache_folder()})")
    ap.add_argument("--no-cache", action="store_true", help="render every reference again "
                                                            "(and keep none)")
    ap.add_argument("--lens-samples", type=int, default=1,
                    help="ours (with and without LOD) draws the aperture as this many parts "
                         "(RenderSettings.lens_samples; default 1, the single pass)")
    ap.add_argument("--lod-blur-fraction", type=float,
                    default=ds.RenderSettings.lod_blur_fraction,
                    help="ours' LOD stop (RenderSettings.lod_blur_fraction; default the "
                         "renderer's, 0.35; 1 is the paper's rule)")
    ap.add_argument("--lod-min-node", type=int, default=ds.RenderSettings.lod_min_node,
                    help="the smallest node ours' blur may draw (RenderSettings.lod_min_node; "
                         "default the renderer's, 4; 2: any node, the paper's)")
    ap.add_argument("--lod-color-tolerance", type=float,
                    default=ds.RenderSettings.lod_color_tolerance,
                    help="ours' finer cut for textured nodes (RenderSettings."
                         "lod_color_tolerance; default the renderer's, 0.02; inf: none, "
                         "the paper's)")
    ap.add_argument("--coarse-blur", type=float, default=ds.RenderSettings.coarse_blur_px,
                    help="ours' threshold for drawing a wide blur at every second pixel "
                         "(RenderSettings.coarse_blur_px; default the renderer's, 8 px; 0: "
                         "every pixel)")
    args = ap.parse_args(argv)
    defaults = QUICK if args.quick else FULL
    size = args.size or defaults["size"]
    samples = args.samples or defaults["samples"]
    repeat = args.repeat or defaults["repeat"]
    out = args.out or (BENCH / "fidelity" / "quick" if args.quick else BENCH)
    cache = None if args.no_cache else (args.cache or cache_folder())
    progress = sys.stderr.isatty()
    t_start = time.perf_counter()
    load = {"start": os.getloadavg()[0]}  # the machine may be shared: timings depend on it

    rows, scene_s = [], {}
    for name in args.scenes:
        t = time.perf_counter()
        scene = SCENES[name](*size)
        if scene is None:
            continue
        scene.settings = dataclasses.replace(scene.settings, lens_samples=args.lens_samples,
                                             lod_blur_fraction=args.lod_blur_fraction,
                                             lod_min_node=args.lod_min_node,
                                             lod_color_tolerance=args.lod_color_tolerance,
                                             coarse_blur_px=args.coarse_blur)
        print(f"{name}: {len(scene.surfels):,} surfels, {size[0]}x{size[1]}, N = {samples}; "
              f"{scene.note}", file=sys.stderr)
        scene_rows, frames = measure_scene(scene, samples, repeat, TARGET_COC_PX, cache,
                                           progress)
        montage(scene, scene_rows[-1], frames, out / "fidelity" / f"{name}.png")
        rows += scene_rows
        scene_s[name] = time.perf_counter() - t
        print(f"{name}: done in {scene_s[name]:.0f} s", file=sys.stderr)
    load["end"] = os.getloadavg()[0]

    record = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), "size": list(size),
              "samples": samples, "repeat": repeat, "targets_coc_px": list(TARGET_COC_PX),
              "tile": TILE, "worst_tile_percentile": WORST_TILE_PERCENTILE,
              "reference_version": REFERENCE_VERSION, "load_average": load,
              "lens_samples": args.lens_samples, "lod_blur_fraction": args.lod_blur_fraction,
              "lod_min_node": args.lod_min_node,
              "lod_color_tolerance": args.lod_color_tolerance, "coarse_blur_px": args.coarse_blur,
              "run_s": time.perf_counter() - t_start, "scene_s": scene_s, "rows": rows}
    out.mkdir(parents=True, exist_ok=True)
    text = json.dumps(_finite(record), indent=1, default=_json_number, allow_nan=False) + "\n"
    (out / "fidelity.json").write_text(text)
    if rows:
        print_table(record)
    print(f"\n(wrote {out / 'fidelity.json'} and {out / 'fidelity'}/; "
          f"{record['run_s'] / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
