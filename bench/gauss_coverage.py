"""Prototypes of a blurred Gaussian frame's coverage (issue 48; docs/maths.md, "Gaussian
scenes", item 2): slow numpy/numba drafts, not the renderer, scored against the lens
reference over a black and a white background. The renderer has summed its blurred layers
since stop 59 (``cpu_gauss.mark_summed``, ``layer_shares``): "today" below is that frame,
and the drafts are kept for their variants.

    python bench/gaussians.py --backgrounds             # today's frames over both backgrounds
    python bench/gauss_coverage.py --scenes guitar donut --coc 35 [--samples 128]
    python bench/gauss_coverage.py --scenes guitar --share-scale 2 --share-eps 0.3
    python bench/gauss_coverage.py --cost --scenes guitar playbot --coc 10 35   # the shares' cost

Each prototype draws the lens in the default's 4 parts. Per part, the Gaussians are split by
their residual circle of confusion into an in-focus slab (composited as the trainers do, each
footprint blurred by the residual: "over") and blurred slabs: one near and one far (the
in-focus slab under 0.5 px), or slabs whose residual C_r doubles from ``--sharp`` px on, as the
renderer's layers do. Within a blurred slab each blurred
footprint is *added*, weighted by the Gaussian's seen share in the slab's own sharp
composite (alpha T summed over its pixels over its footprint's integral: a stack of
coincident Gaussians adds up to the front one's coverage, where "over" of their blurred
footprints compounds), the slab's coverage the sum clamped at 1; the slabs are joined
"over". Variants: the share from the part's centre alone or the largest over it and
``--part-views`` points of the part's rim; the parts averaged in the trainer's encoded
values (as the renderer does) or each decoded over the background first (linear light, as
the reference averages its views). Printed: PSNR over black / white, and the alpha
channel's. It draws ``(1 + part views) x 4 x 2`` sharp views at full resolution: tens of
times the default frame's cost.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gaussians as G  # noqa: E402  (bench/gaussians.py: scenes, camera, lens)

import dofsplat as ds  # noqa: E402
from dofsplat.backends.cpu_gauss import (draw_gaussians, lens_visibility_by_shifts,  # noqa: E402
                                        project, seen_in_view, to_linear_rgba)
from dofsplat.camera import effective_diameter, lens_camera  # noqa: E402
from dofsplat.colors import linear_to_srgb, srgb_to_linear  # noqa: E402
from dofsplat.frame import lens_parts  # noqa: E402
from dofsplat.gauss.composite import gaussian_alpha, seen_shares  # noqa: E402
from dofsplat.gauss.project import (EPS2D, F_B, F_CA, F_CB, F_CC, F_CUT, F_G,  # noqa: E402
                                    F_OPACITY, F_R, F_X, F_Y, view_matrix)
from dofsplat.jit import numba  # noqa: E402
from dofsplat.metrics import psnr  # noqa: E402
from dofsplat.reference import render_reference  # noqa: E402


@numba.njit(cache=False)
def add_footprints(rows, boxes, visible, weight, color, alpha):
    """color += w alpha c, alpha += w alpha over each visible row's box (no order, no "over")."""
    for i in range(rows.shape[0]):
        if not visible[i] or weight[i] <= 0.0:
            continue
        for y in range(boxes[i, 2], boxes[i, 3]):
            for x in range(boxes[i, 0], boxes[i, 1]):
                a = gaussian_alpha(rows[i, F_X], rows[i, F_Y], rows[i, F_CA], rows[i, F_CB],
                                   rows[i, F_CC], rows[i, F_OPACITY], rows[i, F_CUT], x, y)
                if a > 0.0:
                    a *= weight[i]
                    alpha[y, x] += a
                    color[y, x, 0] += a * rows[i, F_R]
                    color[y, x, 1] += a * rows[i, F_G]
                    color[y, x, 2] += a * rows[i, F_B]


def view_shares(scene, camera, settings, eps2d=None) -> np.ndarray:
    """(N,) each Gaussian's seen share in this sharp view, at most 1; eps2d: the view's
    low-pass (px^2 of its pixels), the trainers' 0.3 where None."""
    rows, visible, seen = seen_in_view(scene, camera, settings,
                                       EPS2D if eps2d is None else eps2d)
    out = np.empty(len(scene), np.float32)
    seen_shares(rows, visible, seen, out)
    return out


def coverage_frame(scene, camera, lens, settings, sharp_px=0.5, part_views=0,
                   linear_parts=True, doubling=False, shared_views=False, scale=1,
                   eps2d=None, shifts=False) -> np.ndarray:
    """The prototype's frame, (H, W, 4) linear RGBA over settings.background. shared_views:
    one share per Gaussian for every part, the largest over the lens centre and 8 points at
    0.7 of its radius (else each part's centre and part_views points of its rim); scale,
    eps2d: the share views at 1/scale the resolution with that low-pass; shifts: those views
    drawn as the lens visibility draws its own (``lens_visibility_by_shifts``: one
    projection, moved)."""
    parts = lens_parts(camera, lens, dataclasses.replace(settings, lens_samples=4))
    view = view_matrix(camera)
    z = scene.positions.astype(np.float64) @ view[2, :3] + view[2, 3]
    k, inv_focus = parts.residual.coc_coefficients(camera)
    r = k * (1.0 / np.maximum(z, 1e-9) - inv_focus)  # signed residual C_r, px (+: near)
    a = np.abs(r)
    if doubling:  # slabs of residual C_r doubling from sharp_px on, as the renderer's layers
        level = 1 + np.floor(np.log2(np.maximum(a, sharp_px) / sharp_px)).astype(int)
        slab = np.where(a < sharp_px, 0, np.sign(r).astype(int) * level)
    else:  # one near and one far slab
        slab = np.where(a < sharp_px, 0, np.sign(r)).astype(int)
    diameter = effective_diameter(camera, lens)
    bg = linear_to_srgb(np.asarray(settings.background, np.float64))
    h, w = camera.height, camera.width
    small = dataclasses.replace(camera, width=max(1, w // scale), height=max(1, h // scale))
    shared = {}
    color_sum, trans_sum, linear_sum = np.zeros((h, w, 3)), np.zeros((h, w)), np.zeros((h, w, 3))
    for k_part, cam in enumerate(parts.cameras):
        color, trans = np.zeros((h, w, 3)), np.ones((h, w))
        for key in sorted(set(slab.tolist()), reverse=True):  # near to far
            sub = scene.subset(np.flatnonzero(slab == key))
            if key == 0:
                c, t, _, _ = draw_gaussians(sub, cam, parts.residual, settings, "ours", None)
                color += trans[..., None] * c
                trans *= t
                continue
            if shared_views:
                points = [np.zeros(2)] + [0.7 * np.array([math.cos(a), math.sin(a)])
                                          for a in np.arange(8) * math.pi / 4.0]
            else:
                u0 = np.asarray(parts.offsets[k_part], np.float64)
                points = [u0] + [u0 + parts.rho * np.array([math.cos(a), math.sin(a)])
                                 for a in np.arange(part_views) * 2.0 * math.pi / max(part_views, 1)]
            if key not in shared and shifts:
                # one projection from the centre, moved to the 8 views (the mean exactly, the
                # shape the centre's), as the renderer's lens visibility draws its views
                shared[key] = lens_visibility_by_shifts(sub, camera, lens, settings, views=8,
                                                        scale=scale, radius=0.7, eps2d=eps2d,
                                                        raw=True)
            if key not in shared:
                shared[key] = np.max([view_shares(sub, lens_camera(
                    small, 0.5 * diameter * p, float(lens.focus_distance)), settings, eps2d)
                    for p in points], axis=0)
            share = shared[key]
            if not shared_views:
                del shared[key]
            rows, boxes, visible = project(sub, cam, parts.residual, settings)
            c, a = np.zeros((h, w, 3)), np.zeros((h, w))
            add_footprints(rows, boxes, visible, share, c, a)
            over = a > 1.0
            c[over] /= a[over][:, None]
            a = np.minimum(a, 1.0)
            color += trans[..., None] * c
            trans *= 1.0 - a
        color_sum += color
        trans_sum += trans
        linear_sum += srgb_to_linear(np.clip(color + trans[..., None] * bg, 0.0, 1.0))
    n = len(parts.cameras)
    if not linear_parts:
        return to_linear_rgba(color_sum, trans_sum, settings.background, 1.0 / n)
    return np.concatenate([linear_sum / n, 1.0 - trans_sum[..., None] / n], -1).astype(np.float32)


def share_cost(names, cocs, size, sharp=1.5, repeat=5) -> None:
    """The shares' cost as the renderer would draw them (one shifted-views projection per
    blurred slab, 8 views at 1/4 resolution) against today's lens visibility on the same
    Gaussians and today's frame, no LOD: medians of ``repeat`` turns of the three."""
    import time

    from dofsplat.backends.cpu_gauss import visibility_scale_for

    settings = ds.RenderSettings(gaussian_lod=False)
    for name in names:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = ds.io.load(G.SCENES[name])
        camera = G.default_camera(scene, *size)
        depth = ds.render(scene, camera, None, settings).depth
        for coc in cocs:
            lens = G.lens_for(scene, camera, coc, depth)
            parts = lens_parts(camera, lens, dataclasses.replace(settings, lens_samples=4))
            view = view_matrix(camera)
            z = scene.positions.astype(np.float64) @ view[2, :3] + view[2, 3]
            k, inv_focus = parts.residual.coc_coefficients(camera)
            r = k * (1.0 / np.maximum(z, 1e-9) - inv_focus)
            a = np.abs(r)
            level = 1 + np.floor(np.log2(np.maximum(a, sharp) / sharp)).astype(int)
            slab = np.where(a < sharp, 0, np.sign(r).astype(int) * level)
            subs = [scene.subset(np.flatnonzero(slab == key)) for key in set(slab.tolist())
                    if key != 0]
            scale = visibility_scale_for(scene.positions, camera, lens, settings)
            turns = {
                "today's lens visibility": lambda: lens_visibility_by_shifts(
                    scene, camera, lens, settings, scale=scale),
                "the slabs' shares": lambda: [lens_visibility_by_shifts(
                    sub, camera, lens, settings, views=8, scale=4, radius=0.7, eps2d=0.04,
                    raw=True) for sub in subs],
                "today's frame": lambda: ds.render(scene, camera, lens, settings),
            }
            times = {key: [] for key in turns}
            for turn in range(repeat + 1):
                for key, run in turns.items():
                    t = time.perf_counter()
                    run()
                    if turn:  # the first turn warms up
                        times[key].append(time.perf_counter() - t)
            print(f"  {name} {coc:.0f} px, {len(subs)} blurred slabs: " + ", ".join(
                f"{key} {1000 * np.median(v):.1f} ms" for key, v in times.items()), flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["guitar", "biker", "donut", "fruit"],
                        choices=list(G.SCENES))
    parser.add_argument("--coc", type=float, nargs="+", default=[35.0])
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--samples", type=int, default=128)
    parser.add_argument("--sharp", type=float, default=1.5,
                        help="the doubling slabs' in-focus slab: residual C_r under this, px "
                             "(composited as the trainers do, its footprints blurred)")
    parser.add_argument("--part-views", type=int, default=4,
                        help="points of each part's rim besides its centre for the seen share")
    parser.add_argument("--share-scale", type=int, default=4,
                        help="the last variant's share views at 1/this the resolution")
    parser.add_argument("--share-eps", type=float, default=1.0 / 12.0,
                        help="the last variant's share views' low-pass, px^2 of their pixels "
                             "(the trainers' 0.3; the lens visibility's 1/12)")
    parser.add_argument("--cost", action="store_true",
                        help="only the shares' cost against today's lens visibility and frame")
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    if args.cost:
        share_cost(args.scenes, args.coc, size, args.sharp)
        return 0
    settings = ds.RenderSettings(gaussian_lod=False)
    for name in args.scenes:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = ds.io.load(G.SCENES[name])
        camera = G.default_camera(scene, *size)
        pinhole = ds.render(scene, camera, None, settings)
        for coc in args.coc:
            lens = G.lens_for(scene, camera, coc, pinhole.depth)
            cells = {}
            for bg in (0.0, 1.0):
                st = dataclasses.replace(settings, background=(bg,) * 3)
                ref = render_reference(scene, camera, lens, st, samples=args.samples,
                                       progress=False).image
                frames = {
                    "today (no LOD)": ds.render(scene, camera, lens, st).image,
                    "2 slabs, centre share, encoded mean": coverage_frame(
                        scene, camera, lens, st, 0.5, 0, False),
                    f"2 slabs, {args.part_views + 1}-view share, linear mean": coverage_frame(
                        scene, camera, lens, st, 0.5, args.part_views, True),
                    f"doubling slabs from {args.sharp} px, {args.part_views + 1}-view share, "
                    "linear mean": coverage_frame(scene, camera, lens, st, args.sharp,
                                                  args.part_views, True, doubling=True),
                    f"the same, 9 shared views at 1/{args.share_scale} resolution, low-pass "
                    f"{args.share_eps:.3g} px^2": coverage_frame(
                        scene, camera, lens, st, args.sharp, 0, True, doubling=True,
                        shared_views=True, scale=args.share_scale, eps2d=args.share_eps),
                    "the same, its views moved from one projection": coverage_frame(
                        scene, camera, lens, st, args.sharp, 0, True, doubling=True,
                        shared_views=True, scale=args.share_scale, eps2d=args.share_eps,
                        shifts=True),
                }
                for key, image in frames.items():
                    cells.setdefault(key, []).append(f"{psnr(image, ref):.2f}")
                    if bg:
                        cells[key].append(f"alpha {psnr(image[..., 3], ref[..., 3], 'linear'):.1f}")
            print(f"  {name} {coc:.0f} px: " + " | ".join(
                f"{k} {' / '.join(v)}" for k, v in cells.items()), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
