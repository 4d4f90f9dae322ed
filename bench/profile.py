"""Where a CPU frame's time goes, stage by stage, and a big frame's memory (issue 15).

    python bench/profile.py                      # plane, lion 1280x720, demo: a markdown table
    python bench/profile.py --scenes big         # 10 M surfels at 1920x1080, time and memory
    python bench/profile.py --scenes empty       # 1280x720 with nothing in view: per-pixel cost
    python bench/profile.py --scenes intersect   # two crossing planes: the front pass's worst case
    python bench/profile.py --scenes leaves pane # the fidelity suite's dearest blurred frames
    python bench/profile.py --no-exact           # the paper's analytic normalisation instead
    python bench/profile.py --sharp-visibility   # the front pass in the pinhole frames too
    python bench/profile.py --json out.json      # the figures as JSON too
    python bench/profile.py --scenes big --max-splat-rows 524288   # band by band (RESULTS)

Each scene is rendered pinhole and at two apertures with the default settings (LOD on, the
aperture's disc, soft reconstruction): one warm-up frame (the JIT, the LOD hierarchy), then
the median of ``--repeat`` frames per stage (``render().stats``): select (the LOD cut), shade,
project (EWA kernels, normalisation), bin, front (the front pass and the splats'
visibility), raster (rasterisation, A-buffer and resolve). "ns/frag" is the raster stage's
time per fragment per thread (raster_ms x threads / fragments).

The big scene (a 3,163 x 3,163 textured plane, 10,004,569 surfels, seen as the paper's plane)
runs in a subprocess per frame so that its peak memory is the frame's own: the peak resident
set is reset after the scene and its hierarchy are loaded (Linux /proc/self/clear_refs), and
"frame peak" is the peak minus the resident set before the frame, per surfel.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import numba

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import dofsplat as ds  # noqa: E402

STAGES = ("select_ms", "shade_ms", "project_ms", "bin_ms", "front_ms", "raster_ms", "total_ms")
APERTURES = {"plane": (0.0, 0.1, 0.4), "lion": (0.0, 0.5, 2.0), "demo": (0.0, 0.12, 0.3),
             "big": (0.0, 0.1, 0.4), "empty": (0.0,),
             # two planes crossing (the fidelity suite's): a CoC of up to 10 and 20 px, and
             # most of the rear plane behind the front one (the front pass's worst case)
             "intersect": (0.0, 0.1, 0.2),
             # the fidelity suite's two dearest blurred frames against their pinhole frame
             # (bench/fidelity.py: the lion's leaves and the pane at a CoC of 10 and 40 px)
             "leaves": (0.0, 0.4151, 1.66), "pane": (0.0, 0.02103, 0.08411)}
BIG_SIDE = 3163  # surfels per side of the big plane: 10,004,569


def gaussian_scene(name: str):
    """(scene, camera, lens) of a shared 3DGS capture as ``bench/gaussians.py`` sees it:
    "g-NAME" at 320 x 240, "g-NAME-hd" at 1920 x 1080, the lens whose largest CoC over the
    frame's depths is 35 px at that size (``bench/paired_frames.py``'s Gaussian frames)."""
    import warnings

    import dofsplat as ds
    import gaussians
    from dofsplat.io import load

    key = name[2:].removesuffix("-hd")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = load(gaussians.SCENES[key])
    size = (1920, 1080) if name.endswith("-hd") else (320, 240)
    camera = gaussians.default_camera(model, *size)
    pinhole = ds.render(model, camera, None)
    return model, camera, gaussians.lens_for(model, camera, 35.0, pinhole.depth)


def scene(name: str):
    from dofsplat.demo import PLANE_SIZE, demo_scene, plane_scene, textured_plane

    if name.startswith("g-"):
        return gaussian_scene(name)

    if name == "plane":
        return plane_scene(512, 512)
    if name == "demo":
        return demo_scene(800, 600)
    if name == "lion":
        from table1 import lion_scene

        return lion_scene(None, 1280, 720)
    if name == "intersect":
        from dofsplat.demo import intersecting_planes_scene

        return intersecting_planes_scene(512, 512)
    if name in ("leaves", "pane"):  # 512 x 512, their focus, the suite's settings aside
        import fidelity

        made = (fidelity.lion_leaves_scene if name == "leaves" else fidelity.pane_scene)(512, 512)
        if made is None:
            raise SystemExit(f"{name}: the model is not in ../shared/data")
        return made.surfels, made.camera, made.lens(1.0)
    if name == "empty":  # a 1280 x 720 frame with nothing in view: the cost per pixel alone
        _, camera, lens = plane_scene(1280, 720)
        far = ds.Surfels(positions=[[0.0, 0.0, 50.0]], normals=[[0.0, 0.0, 1.0]], radius=[0.01],
                         colors=[[1.0, 1.0, 1.0]])  # behind the camera
        return far, camera, lens
    _, camera, lens = plane_scene(1920, 1080)
    return textured_plane(BIG_SIDE, PLANE_SIZE), camera, lens


def frames(name: str, aperture: float, repeat: int, settings=None) -> dict:
    surfels, camera, lens = scene(name)
    lens = dataclasses.replace(lens, aperture=aperture) if aperture > 0 else None
    ds.render(surfels, camera, lens, settings)  # the JIT, the hierarchy
    runs = [ds.render(surfels, camera, lens, settings).stats for _ in range(repeat)]
    out = {k: statistics.median(r[k] for r in runs) for k in STAGES}
    out["fragments"] = runs[0]["fragments"]
    out["splats"] = runs[0]["splats_rendered"]
    out["ns_per_fragment_thread"] = (out["raster_ms"] * 1e6 * numba.get_num_threads()
                                     / max(out["fragments"], 1))
    return out


def big_frame(aperture: float, repeat: int, settings=None) -> dict:
    """One big frame in this process (called by the subprocess): times and memory."""
    surfels, camera, lens = scene("big")
    lens = dataclasses.replace(lens, aperture=aperture) if aperture > 0 else None
    from dofsplat.lod import hierarchy_for

    hierarchy_for(surfels)  # built or loaded before the frame, as a viewer holds it
    ds.render(surfels, camera, lens, settings)  # the JIT
    before = _status("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # reset the peak resident set
    runs = [ds.render(surfels, camera, lens, settings).stats for _ in range(repeat)]
    peak = _status("VmHWM")
    out = {k: statistics.median(r[k] for r in runs) for k in STAGES}
    out.update(fragments=runs[0]["fragments"], splats=runs[0]["splats_rendered"],
               surfels=len(surfels), rss_before_mb=before / 1024, peak_mb=peak / 1024,
               frame_peak_mb=(peak - before) / 1024,
               frame_bytes_per_surfel=(peak - before) * 1024 / len(surfels))
    return out


def _status(field: str) -> int:
    """A /proc/self/status figure in kB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"no {field} in /proc/self/status")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["plane", "lion", "demo"],
                    choices=list(APERTURES))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", help="write the figures here too")
    ap.add_argument("--no-exact", action="store_true",
                    help="RenderSettings(exact_normalization=False): what the pixel sum costs")
    ap.add_argument("--sharp-visibility", action="store_true",
                    help="RenderSettings(sharp_visibility=True): what the front pass costs in "
                         "a pinhole frame (its 'front' column)")
    ap.add_argument("--max-splat-rows", type=int,
                    help="RenderSettings(max_splat_rows=...): an LOD cut of more splats is "
                         "projected band by band (default: a quarter of the memory available)")
    ap.add_argument("--tree", choices=["auto", "full", "compact"], default="auto",
                    help="the LOD tree's layout: compact leaves out the nodes of 2 or 3 "
                         "surfels (default: compact from lod.hierarchy.COMPACT_FROM surfels)")
    ap.add_argument("--big-frame", type=float, help=argparse.SUPPRESS)  # the subprocess
    args = ap.parse_args(argv)
    if args.tree != "auto":  # every tree this process builds
        import dofsplat.lod.hierarchy as hierarchy
        hierarchy.COMPACT_FROM = 0 if args.tree == "compact" else 1 << 62
    settings = ds.RenderSettings(exact_normalization=not args.no_exact,
                                 sharp_visibility=args.sharp_visibility,
                                 max_splat_rows=args.max_splat_rows)
    if args.big_frame is not None:
        print(json.dumps(big_frame(args.big_frame, args.repeat, settings)))
        return 0
    print(f"{numba.get_num_threads()} threads, {os.cpu_count()} cores, numba {numba.__version__}")
    print("| scene | A | splats | fragments | select | shade | project | bin | front | raster "
          "| total (ms) | ns/frag/thread |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    records = []
    for name in args.scenes:
        for a in APERTURES[name]:
            if name == "big":
                done = subprocess.run([sys.executable, __file__, "--big-frame", str(a),
                                       "--repeat", str(min(args.repeat, 3)),
                                      ]
                                      + ["--max-splat-rows", str(args.max_splat_rows)] * (
                                          args.max_splat_rows is not None)
                                      + ["--tree", args.tree]
                                      + ["--no-exact"] * args.no_exact
                                      + ["--sharp-visibility"] * args.sharp_visibility,
                                      capture_output=True, text=True, check=True)
                r = json.loads(done.stdout.strip().splitlines()[-1])
                r["ns_per_fragment_thread"] = (r["raster_ms"] * 1e6 * numba.get_num_threads()
                                               / max(r["fragments"], 1))
            else:
                r = frames(name, a, args.repeat, settings)
            r.update(scene=name, aperture=a)
            records.append(r)
            print(f"| {name} | {a:g} | {r['splats']:,} | {r['fragments']:,} | "
                  + " | ".join(f"{r[k]:.0f}" for k in STAGES)
                  + f" | {r['ns_per_fragment_thread']:.1f} |", flush=True)
            if name == "big":
                print(f"|  | memory: {r['rss_before_mb']:.0f} MB before the frame, "
                      f"peak {r['peak_mb']:.0f} MB: the frame's {r['frame_peak_mb']:.0f} MB = "
                      f"{r['frame_bytes_per_surfel']:.0f} B per surfel |", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(records, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
