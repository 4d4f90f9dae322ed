"""A peer: how many samples, and how long, a path tracer needs for our frame's quality (issue 15).

    pip install mitsuba          # not a dependency of dofsplat, and not run in CI
    python bench/peer_mitsuba.py [--aperture 0.1] [--converged 4096] [--filter ewa|gaussian|box]

The scene is the paper's textured plane (``dofsplat.demo.plane_scene``: 4 x 4 units seen at
a grazing angle, 512 x 512, focused mid-plane), made emissive so that neither renderer
shades it (ours with ``shading="none"``; Mitsuba's ``area`` emitter with the texture our
surfels carry, 512 x 512 texels read bilinearly, and a black BSDF): what remains is the
depth of field itself. Mitsuba 3
renders it through its ``thinlens`` sensor (the same eye, target, field of view, lens radius
and focus distance) with the CPU variant ``llvm_ad_rgb`` at 1, 2, 4, ... samples per pixel.

The pixel's filter (``--filter``). Ours is the paper's: every splat is convolved with a
Gaussian of variance 1 px² (Section 6's prefilter I) and the image is read at the pixel
centres. Mitsuba's box filter integrates a pixel's square instead, a sharper image: against
it, our frame and our own converged reference both stop near 37 dB, whatever the depth of
field. ``--filter ewa`` (the default) asks Mitsuba for our image: its box-filtered samples
are blurred by a Gaussian of variance 1 - 1/12 px² (with the box's 1/12, the prefilter's
variance), the blur counted in its time. ``--filter gaussian`` asks for the same image
through Mitsuba's own ``gaussian`` film filter (stddev 1 px), a slower way to it
(bench/RESULTS.md). ``--filter box`` compares with Mitsuba's box filter as it is.

Both are measured against Mitsuba's converged image (``--converged`` samples per pixel):
our default frame (LOD, the aperture's disc), and Mitsuba at each sample count. The script
finds the first sample count whose PSNR reaches ours (doubling, then bisecting the last
step to within an eighth), and prints Mitsuba's time there over
our frame's time (both medians of 3 runs after a warm-up that includes Mitsuba's JIT
compilation). Our 200-sample reference against the same image says how far the two
renderers' scenes agree (the surfels' reconstruction of the texture, the pixel filters).

Mitsuba's LLVM variant loads the system's libLLVM. With Debian 12's default, libllvm15,
Mitsuba 3.9.1 stops with "LLVM ERROR: Cannot select: fminimum"; Debian 12's libllvm19 works:

    apt-get install libllvm19
    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 python bench/peer_mitsuba.py
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import dofsplat as ds  # noqa: E402
from dofsplat.demo import PLANE_SIZE, plane_scene, plane_texture  # noqa: E402
from dofsplat.metrics import compare  # noqa: E402
from dofsplat.reference import render_reference  # noqa: E402

TEXELS = 512  # as textured_plane's grid
FLIP = -1


def ours(aperture: float, samples: int):
    """(our frame (H, W, 4), our reference, our frame's median time in ms, camera, lens)."""
    surfels, camera, lens = plane_scene(512, 512)
    lens = dataclasses.replace(lens, aperture=aperture)
    st = ds.RenderSettings(shading="none")
    ds.render(surfels, camera, lens, st)
    runs, image = [], None
    for _ in range(3):
        t = time.perf_counter()
        image = ds.render(surfels, camera, lens, st).image
        runs.append((time.perf_counter() - t) * 1000.0)
    ref = render_reference(surfels, camera, lens, st, samples=samples,
                           progress=sys.stderr.isatty()).image
    return image, ref, statistics.median(runs), camera, lens


def mitsuba_scene(camera, lens, spp: int, rfilter: str = "box"):
    import mitsuba as mi

    # the texture our surfels carry (textured_plane: 512 x 512 samples of plane_texture,
    # u along x, v along z), read bilinearly: the same scene. The rectangle's v runs along
    # -z once turned, so the rows are reversed
    g = (np.arange(TEXELS) + 0.5) / TEXELS
    u, v = np.meshgrid(g, g)
    texture = plane_texture(u.ravel(), v.ravel()).reshape(TEXELS, TEXELS, 3)[::FLIP]
    # Mitsuba's rectangle spans [-1, 1]^2 in x-y facing +z; turned -90 degrees about x it
    # lies in y = 0 facing +y (our plane), scaled to its side
    plane = (mi.ScalarTransform4f.rotate([1, 0, 0], -90)
             @ mi.ScalarTransform4f.scale([PLANE_SIZE / 2, PLANE_SIZE / 2, 1]))
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 1},  # the emitter seen through the lens
        "sensor": {
            "type": "thinlens", "fov": camera.fov_y, "fov_axis": "y",
            "aperture_radius": lens.diameter / 2, "focus_distance": lens.focus_distance,
            "to_world": mi.ScalarTransform4f.look_at(origin=list(camera.eye),
                                                     target=list(camera.target),
                                                     up=list(camera.up)),
            "film": {"type": "hdrfilm", "width": camera.width, "height": camera.height,
                     "rfilter": ({"type": "gaussian", "stddev": 1.0} if rfilter == "gaussian"
                                 else {"type": "box"}),
                     "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "plane": {"type": "rectangle", "to_world": plane,
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
                  "emitter": {"type": "area",
                              "radiance": {"type": "bitmap", "raw": True,
                                           "data": mi.TensorXf(texture.astype(np.float32))}}},
    })


# the blur that turns the box filter's image into the paper's: a Gaussian of variance 1 px²
# in all, less the box's own 1/12
EWA_BLUR_SIGMA = (1.0 - 1.0 / 12.0) ** 0.5


def ewa_blur(image):
    """The box-filtered image (H, W, 3) as the paper's prefilter draws it (``--filter ewa``)."""
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(image, (EWA_BLUR_SIGMA, EWA_BLUR_SIGMA, 0.0), mode="nearest")


def mitsuba_render(camera, lens, spp: int, repeat: int = 3, pixel_filter: str = "box"):
    """(image (H, W, 3) linear, median seconds) at spp samples per pixel, with the pixel's
    filter ``pixel_filter`` (box, ewa or gaussian: the module notes)."""
    import mitsuba as mi

    scene = mitsuba_scene(camera, lens, spp, rfilter=pixel_filter)
    mi.render(scene, spp=spp)  # the JIT
    runs, image = [], None
    for seed in range(repeat):
        t = time.perf_counter()
        image = np.array(mi.render(scene, spp=spp, seed=seed + 1))
        if pixel_filter == "ewa":
            image = ewa_blur(image)
        runs.append(time.perf_counter() - t)
    return image, statistics.median(runs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--aperture", type=float, default=0.1, help="lens diameter (default 0.1)")
    ap.add_argument("--samples", type=int, default=200, help="our reference's lens samples")
    ap.add_argument("--converged", type=int, default=4096,
                    help="Mitsuba's samples per pixel for its converged image")
    ap.add_argument("--max-spp", type=int, default=1024)
    ap.add_argument("--filter", choices=("ewa", "gaussian", "box"), default="ewa",
                    help="the pixel's filter both images are held to (module notes; "
                         "default ewa, the paper's)")
    args = ap.parse_args(argv)
    try:
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
    except Exception as e:  # noqa: BLE001 - not installed, or no libLLVM
        print(f"Mitsuba 3's llvm_ad_rgb variant is not available: {e}", file=sys.stderr)
        return 1
    frame, ref, ms_ours, camera, lens = ours(args.aperture, args.samples)
    converged, secs = mitsuba_render(camera, lens, args.converged, repeat=1,
                                     pixel_filter=args.filter)
    print(f"Mitsuba {mi.__version__} llvm_ad_rgb, pixel filter {args.filter}: converged image "
          f"at {args.converged} spp in {secs:.1f} s")
    rgba = np.concatenate([converged, np.ones(converged.shape[:2] + (1,))], axis=-1)
    psnr_ours = compare(frame, rgba)["psnr"]
    print(f"ours: {psnr_ours:.2f} dB against Mitsuba's converged image, {ms_ours:.0f} ms per "
          f"frame (our {args.samples}-sample reference: {compare(ref, rgba)['psnr']:.2f} dB; "
          f"our frame against it: {compare(frame, ref)['psnr']:.2f} dB)")
    print("| spp | PSNR (dB) | time (ms) | Mitsuba time / ours |")
    print("|---:|---:|---:|---:|")
    runs = {}

    def reaches(spp: int) -> bool:
        image, secs = mitsuba_render(camera, lens, spp, pixel_filter=args.filter)
        img = np.concatenate([image, np.ones(image.shape[:2] + (1,))], axis=-1)
        psnr = compare(img, rgba)["psnr"]
        runs[spp] = secs * 1000.0
        print(f"| {spp} | {psnr:.2f} | {secs * 1000:.0f} | {secs * 1000 / ms_ours:.1f} |",
              flush=True)
        return psnr >= psnr_ours

    # doubling until Mitsuba reaches our PSNR, then halving the last step until it is an
    # eighth of the count at most: the samples it needs, to within 1/8
    spp = 1
    while not reaches(spp):
        spp *= 2
        if spp > args.max_spp:
            print(f"Mitsuba does not reach our {psnr_ours:.2f} dB by {args.max_spp} spp")
            return 0
    lo, hi = spp // 2, spp
    while hi - lo > max(1, hi // 8):
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if reaches(mid) else (mid, hi)
    print(f"Mitsuba reaches our {psnr_ours:.2f} dB at {hi} spp: "
          f"{runs[hi] / ms_ours:.1f} x our frame's time")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
