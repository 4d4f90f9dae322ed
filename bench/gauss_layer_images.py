"""A prototype of the blurred Gaussian frame's next step (issue 48; docs/maths.md, "Gaussian
scenes", item 2, "Next"): the renderer's own frame with two stages replaced from outside, in
numpy and scipy, scored against the lens reference over a black and a white background. Not
the renderer: its times mean nothing.

    python bench/gauss_layer_images.py --size 320x240 --samples 64
    python bench/gauss_layer_images.py --size 1920x1080 --scenes playbot-500k guitar biker
    python bench/gauss_layer_images.py --variants today joins images --image-scales 2 4

Variants (each the default frame, ``ds.render``, otherwise):

* ``today``: the default frame as it is.
* ``joins``: the summed layers' pixels (``mark_summed``) decoded (their unpremultiplied
  colour) and joined "over" in linear light, the other layers' in the trainer's encoded
  values, back to front (``join_parts``, in numpy: a layer's blend of its own Gaussians is
  the trainers' in either case). Today every layer is joined in encoded values and the part
  decoded after: where a blurred layer half covers what is behind it, that mixes the two in
  encoded values, darker than the lens reference's mean of decoded views. (All layers joined
  in linear light overshoots where one view's Gaussians mix: the biker at 10 px lost 11 dB
  over black, a development measurement.)
* ``images``: ``joins``, with each summed layer's image replaced by the layer drawn alone
  and sharp (low-pass ``--eps``, 0.04 px^2) from its part's camera at 1/r the resolution
  (``--image-scales``), decoded (its unpremultiplied colour), blurred by a Gaussian of the
  layer's median residual blur (a part's sigma over its Gaussians; ``--sigma``) and sampled
  onto the layer's image: the layer's colour and coverage come from its own sharp view, as
  the reference's do, not from weighted blurred footprints whose sum is clamped at 1 and
  whose colours mix in encoded values.

Printed per scene and CoC (a lens whose largest circle of confusion over the frame's depths
is that many pixels at --size, ``bench/gaussians.py``'s ``lens_for``): PSNR (dB) against
--samples pinhole frames through the lens, over black and over white, and the frame's alpha
and linear colour summed over the reference's.
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gaussians as G  # noqa: E402  (bench/gaussians.py: scenes, camera, lens)

import dofsplat as ds  # noqa: E402
from dofsplat.backends import cpu_gauss as cg  # noqa: E402
from dofsplat.camera import effective_diameter, lens_camera  # noqa: E402
from dofsplat.colors import linear_to_srgb, srgb_to_linear  # noqa: E402
from dofsplat.gauss.composite import TILE, bin_tiles, composite_tiles, depth_order  # noqa: E402
from dofsplat.gauss.layers import (IM_HEIGHT, IM_MARGIN, IM_PIXEL0, IM_SCALE,  # noqa: E402
                                   IM_SUM, IM_TILE0, IM_WIDTH)
from dofsplat.gauss.lod import GaussianArrays  # noqa: E402
from dofsplat.gauss.project import view_matrix  # noqa: E402
from dofsplat.io import load  # noqa: E402
from dofsplat.metrics import psnr  # noqa: E402
from dofsplat.reference import render_reference  # noqa: E402

SCENES = dict(G.SCENES, **{"playbot-500k": G.DATA / "gaussian_scenes" / "playbot" / "0_0" /
                           "meta.json"})
ORIGINAL = {name: getattr(cg, name) for name in ("in_layers", "layer_plan",
                                                 "composite_images", "combine_layers")}
MODE = {"joins": False, "images": False, "scale": 2, "eps": 0.04, "sigma": "median"}
FRAME = {}  # what the frame's stages saw: its Gaussians, layers, camera, lens, parts


def in_layers(*args, **kwargs):
    arrays, layers = ORIGINAL["in_layers"](*args, **kwargs)
    FRAME["arrays"] = arrays
    return arrays, layers


def layer_plan(n, layers, camera, lens, parts, settings):
    """The renderer's plan, and which (part, layer) each image of it is, read from its
    part_layers (each part's images, one per layer with any Gaussian, front to back)."""
    plan = ORIGINAL["layer_plan"](n, layers, camera, lens, parts, settings)
    part_layers = plan[-1]
    filled = [j for j in range(len(layers.scales)) if layers.spans[j, 1] > layers.spans[j, 0]]
    which = {int(part_layers[p, col]): (p, j) for p in range(len(part_layers))
             for col, j in enumerate(filled) if j != layers.sharp}
    FRAME.update(which=which, layers=layers, camera=camera, lens=lens, parts=parts,
                 settings=settings)
    return plan


def unpremultiplied(color, coverage):
    out = np.zeros_like(color)
    ok = coverage > 1e-7
    out[ok] = color[ok] / coverage[ok, None]
    return out


def layer_view(p: int, j: int, r: int):
    """Layer j drawn alone and sharp from part p's camera at 1/r the resolution, decoded and
    blurred by its median residual blur: (linear colour premultiplied (h, w, 3), coverage (h,
    w)) float64."""
    arrays, layers, camera, lens, parts, settings = (FRAME[k] for k in (
        "arrays", "layers", "camera", "lens", "parts", "settings"))
    a, b = layers.spans[j]
    sub = GaussianArrays(positions=arrays.positions[a:b], scales=arrays.scales[a:b],
                         rotations=arrays.rotations[a:b], opacity=arrays.opacity[a:b],
                         sh=arrays.sh[a:b], level=arrays.level[a:b])
    small = replace(camera, width=camera.width // r, height=camera.height // r)
    cam = lens_camera(small, 0.5 * effective_diameter(small, lens) * parts.offsets[p],
                      float(lens.focus_distance))
    rows, boxes, visible = cg.project(sub, cam, None, settings, eps2d=MODE["eps"])
    n_tx, n_ty = -(-cam.width // TILE), -(-cam.height // TILE)
    offsets, ids = bin_tiles(depth_order(rows, visible), boxes, n_tx, n_ty)
    color = np.empty((cam.height, cam.width, 3), np.float32)
    trans = np.empty((cam.height, cam.width), np.float32)
    composite_tiles(rows, boxes, offsets, ids, n_tx, cam.width, cam.height, color, trans,
                    np.empty((cam.height, cam.width), np.float32), np.zeros((0, 0), np.float32))
    coverage = 1.0 - trans.astype(np.float64)
    linear = srgb_to_linear(np.clip(unpremultiplied(color.astype(np.float64), coverage), 0.0,
                                    None)) * coverage[..., None]
    view = view_matrix(camera)
    z = np.asarray(sub.positions, np.float64) @ view[2, :3] + view[2, 3]
    coc_k, inv_focus = lens.coc_coefficients(camera)
    sigma = parts.rho * math.sqrt(cg.blur_variance(lens)) * coc_k * np.abs(1.0 / z[z > 0]
                                                                            - inv_focus)
    s = {"median": np.median, "mean": np.mean, "rms": lambda x: np.sqrt(np.mean(x * x)),
         "min": np.min}[MODE["sigma"]](sigma) / r
    blur = [ndimage.gaussian_filter(linear[..., c], s, mode="constant") for c in range(3)]
    return np.stack(blur, -1), ndimage.gaussian_filter(coverage, s, mode="constant")


def replace_summed(table, color, trans):
    """Each summed image of the frame replaced by ``layer_view`` sampled onto its pixels
    (linear colour, premultiplied, as ``join_parts`` joins a summed layer)."""
    for i, (p, j) in FRAME["which"].items():
        if not table[i, IM_SUM]:
            continue
        w, h, s, m, q0 = (int(table[i, c]) for c in (IM_WIDTH, IM_HEIGHT, IM_SCALE,
                                                      IM_MARGIN, IM_PIXEL0))
        linear, coverage = layer_view(p, j, MODE["scale"])
        iy, ix = np.mgrid[0:h, 0:w]
        at = [((iy - m + 0.5) * s / MODE["scale"] - 0.5).ravel(),
              ((ix - m + 0.5) * s / MODE["scale"] - 0.5).ravel()]
        cov = np.clip(ndimage.map_coordinates(coverage, at, order=1, mode="constant"), 0, 1)
        lin = np.stack([ndimage.map_coordinates(linear[..., c], at, order=1, mode="constant")
                        for c in range(3)], -1)
        color[q0:q0 + w * h] = lin
        trans[q0:q0 + w * h] = 1.0 - cov


def composite_images(rows, boxes, offsets, ids, tile_image, table, live, color, trans, depth,
                     seen):
    ORIGINAL["composite_images"](rows, boxes, offsets, ids, tile_image, table, live, color,
                                 trans, depth, seen)
    if seen.shape[0] or not MODE["joins"]:
        return  # the lens visibility's views, or today's frame
    FRAME["offsets"] = offsets
    if MODE["images"]:
        replace_summed(table, color, trans)
        return
    for i in np.flatnonzero(table[:, IM_SUM]):  # decoded (linear, premultiplied)
        q0, n = table[i, IM_PIXEL0], table[i, IM_WIDTH] * table[i, IM_HEIGHT]
        with np.errstate(all="ignore"):  # (the tiles never written hold anything)
            coverage = 1.0 - trans[q0:q0 + n].astype(np.float64)
            color[q0:q0 + n] = srgb_to_linear(np.clip(unpremultiplied(
                color[q0:q0 + n].astype(np.float64), coverage), 0, None)) * coverage[:, None]


def sampled(table, i, color, trans, h, w):
    """Image i's colour and transmittance at the frame's pixels (bilinear where coarse, as
    ``over_pixel`` samples it), (h, w, 3) and (h, w); a tile that lists no Gaussian is empty
    (``composite_images`` writes only the tiles that ``combine_layers`` reads)."""
    iw, ih, s, m, q0 = (int(table[i, c]) for c in (IM_WIDTH, IM_HEIGHT, IM_SCALE, IM_MARGIN,
                                                    IM_PIXEL0))
    with np.errstate(all="ignore"):  # (the tiles never written hold anything)
        c = color[q0:q0 + iw * ih].reshape(ih, iw, 3).astype(np.float64)
        t = trans[q0:q0 + iw * ih].reshape(ih, iw).astype(np.float64)
    ty, tx = np.mgrid[0:ih, 0:iw]
    tile = table[i, IM_TILE0] + (ty // TILE) * -(-iw // TILE) + tx // TILE
    empty = FRAME["offsets"][tile + 1] == FRAME["offsets"][tile]
    c[empty], t[empty] = 0.0, 1.0
    if s == 1:
        return c, t
    y, x = np.mgrid[0:h, 0:w]
    at = [((y + 0.5) / s + m - 0.5).ravel(), ((x + 0.5) / s + m - 0.5).ravel()]
    return (np.stack([ndimage.map_coordinates(c[..., k], at, order=1, mode="nearest")
                      for k in range(3)], -1).reshape(h, w, 3),
            ndimage.map_coordinates(t, at, order=1, mode="nearest").reshape(h, w))


def join_parts(table, part_layers, color, trans, background, image):
    """Each part's layers joined back to front, a summed layer in linear light, the others in
    the trainer's encoded values (C + T encode(behind), decoded), over the background; the
    parts averaged: image (H, W, 4), as ``combine_layers`` writes it. background: (3,) in
    the trainer's encoded values, as ``combine_layers`` takes it."""
    h, w = image.shape[:2]
    total, t_total = np.zeros((h, w, 3)), np.zeros((h, w))
    for p in range(len(part_layers)):
        behind = np.broadcast_to(srgb_to_linear(np.asarray(background, np.float64)),
                                 (h, w, 3)).copy()
        t_part = np.ones((h, w))
        for i in reversed([i for i in part_layers[p] if i >= 0]):
            c, t = sampled(table, i, color, trans, h, w)
            if table[i, IM_SUM]:
                behind = c + t[..., None] * behind
            else:
                behind = srgb_to_linear(np.clip(c + t[..., None] * linear_to_srgb(
                    np.clip(behind, 0.0, 1.0)), 0.0, 1.0))
            t_part *= t
        total += np.clip(behind, 0.0, 1.0)
        t_total += t_part
    image[..., :3] = total / len(part_layers)
    image[..., 3] = 1.0 - t_total / len(part_layers)


def combine_layers(table, offsets, part_layers, color, trans, depth, background, lut, *rest):
    out = ORIGINAL["combine_layers"](table, offsets, part_layers, color, trans, depth,
                                     background, lut, *rest)
    if MODE["joins"]:  # (the depth map stays combine_layers')
        join_parts(table, part_layers, color, trans, background, rest[-1])
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--scenes", nargs="+", default=["donut", "fruit", "guitar", "biker",
                                                        "playbot"], choices=list(SCENES))
    parser.add_argument("--cocs", nargs="+", type=float, default=[10.0, 35.0])
    parser.add_argument("--variants", nargs="+", default=["today", "joins", "images"],
                        choices=["today", "joins", "images"])
    parser.add_argument("--image-scales", nargs="+", type=int, default=[2])
    parser.add_argument("--eps", type=float, default=0.04,
                        help="the sharp views' low-pass, px^2 of their pixels")
    parser.add_argument("--sigma", default="median", choices=["median", "mean", "rms", "min"],
                        help="a layer's blur from its Gaussians'")
    args = parser.parse_args(argv)
    MODE.update(eps=args.eps, sigma=args.sigma)
    size = tuple(int(v) for v in args.size.split("x"))
    for name, fn in (("in_layers", in_layers), ("layer_plan", layer_plan),
                     ("composite_images", composite_images), ("combine_layers", combine_layers)):
        setattr(cg, name, fn)
    variants = [(v, r) for v in args.variants for r in (args.image_scales if v == "images"
                                                         else [None])]
    print(f"{args.size}, {args.samples}-sample references; PSNR dB over black / white, "
          "alpha and colour summed over the reference's (over black)")
    for name in args.scenes:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = load(SCENES[name])
        camera = G.default_camera(scene, *size)
        depth = ds.render(scene, camera, None).depth
        for coc in args.cocs:
            lens = G.lens_for(scene, camera, coc, depth)
            scores = {v: [] for v in variants}
            for bg in (0.0, 1.0):
                settings = ds.RenderSettings(background=(bg,) * 3)
                ref = render_reference(scene, camera, lens, settings, samples=args.samples,
                                       progress=False).image
                for v, r in variants:
                    MODE.update(joins=v != "today", images=v == "images", scale=r or 2)
                    frame = ds.render(scene, camera, lens, settings).image
                    scores[(v, r)].append(psnr(frame, ref))
                    if bg == 0.0:
                        scores[(v, r)] += [frame[..., 3].sum() / ref[..., 3].sum(),
                                           frame[..., :3].sum() / ref[..., :3].sum()]
            cells = [f"{v}{'' if r is None else f' 1/{r}'} {s[0]:.2f} / {s[3]:.2f} "
                     f"(alpha {s[1]:.3f}, colour {s[2]:.3f})" for (v, r), s in scores.items()]
            print(f"{name} {coc:g} px: " + " | ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
