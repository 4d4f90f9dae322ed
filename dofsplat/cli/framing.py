"""From a command's arguments to a written frame: camera, lens and settings from the options,
the checks that run before any loading, the render, the outputs, the summary line.

``render``, ``demo`` and ``reference`` run through :func:`render_and_write`; ``view`` and
``animate`` build their cameras, lenses and settings with the same functions, so that every
command reads an option the same way.
"""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path

from ..errors import DofsplatError
from .options import DEFAULT_FOV_DEG, DEFAULT_SIZE, EXIT_OK


def render_and_write(args, outputs, surfels, camera, default_focus: float,
                      default_aperture: float) -> int:
    """The part both commands share: lens, settings, autofocus, render, outputs."""
    import numpy as np

    from ..io import nonfinite_pixels, write_depth, write_image
    from ..render import focus_distance_at

    settings = settings_from_args(args)
    from ..backends import resolve_device

    if not args.quiet and resolve_device(settings.device, "--device") == "cpu":
        from ..backends.cpu import COMPILE_SECONDS, kernels_compiled

        if not kernels_compiled():
            print(f"dofsplat: compiling the rendering kernels, once (about {COMPILE_SECONDS} s "
                  "on 2 cores; numba keeps them for later runs)", file=sys.stderr, flush=True)
    lens, focus_source = None, None
    if settings.dof:
        if args.focus is not None:
            focus, focus_source = args.focus, "--focus"
        elif args.focus_at is not None:
            focus = focus_distance_at(surfels, camera, *args.focus_at, settings=settings)
            focus_source = "--focus-at"
        else:
            focus, focus_source = default_focus, "default"
        lens = lens_from_args(args, focus, default_aperture)

    result = render_by_method(args, surfels, camera, lens, settings)
    bad = nonfinite_pixels(result.image)
    if bad:
        # (write_image would refuse them without a cause: coordinates float32 cannot
        # square, such as a model at 1e30, are the one seen)
        reach = float(np.abs(surfels.positions).max(initial=0.0))
        raise DofsplatError(f"the frame came out with {bad:,} pixels of NaN or inf: the model's "
                            f"coordinates reach {reach:.3g}; rescale it (a flat test model "
                            f"rendered at +-1e20 and failed at +-1e22)")
    if result.stats.get("fragments", 1) == 0:
        import warnings

        warnings.warn("no surfel of the model reaches the image: it is the background alone "
                      "(the camera looks past the model? see --eye, --target, --fov)")
    info = getattr(args, "load_info", None)
    if info is not None:  # the model's loading and preparation, before the frame
        result.stats["load_ms"] = info["seconds"] * 1000.0
        result.stats["load_from_cache"] = bool(info["from_cache"])

    # what this run creates (a file that was there before is replaced: it cannot come back)
    created = [path for path in outputs.values() if not path.exists()]
    written = []
    try:
        write_image(outputs["image"], result.image, depth=result.depth)
        written.append(outputs["image"])
        if "depth" in outputs:
            write_depth(outputs["depth"], result.depth)
            written.append(outputs["depth"])
        if "stats" in outputs:
            write_stats(outputs["stats"], args, outputs, result, camera, lens, focus_source,
                         settings)
    except BaseException:
        # one output failed (a disk filled up since check_outputs): none that this run
        # created is left behind
        for path in written:
            if path in created:
                path.unlink(missing_ok=True)
        raise
    if not args.quiet:
        print(summary(list(outputs.values()), result.stats), file=sys.stderr)
    return EXIT_OK


def render_by_method(args, surfels, camera, lens, settings):
    """Our DOF render, the post-process baseline, or the multisample reference."""
    from ..gaussians import Gaussians
    from ..render import render

    gaussian = isinstance(surfels, Gaussians)
    if (args.method == "viewers") != gaussian and args.method in ("viewers", "postfilter"):
        raise DofsplatError(f"--method {args.method} is for "
                            f"{'surfel models' if args.method == 'postfilter' else 'Gaussian scenes'}"
                            f"; this model is {'a Gaussian scene' if gaussian else 'surfels'} "
                            f"(--method ours, the default, draws both)")
    if args.method == "viewers":
        import dataclasses

        return render(surfels, camera, lens, dataclasses.replace(settings, gaussian_blur="viewers"))
    if args.method == "postfilter":
        from ..postfilter import render_postfilter

        return render_postfilter(surfels, camera, lens, settings)
    if args.method == "reference":
        from ..reference import render_reference

        return render_reference(surfels, camera, lens, settings, samples=args.samples,
                                progress=not args.quiet)
    return render(surfels, camera, lens, settings)


# -- camera, lens, settings --------------------------------------------------------------


def framing_camera(args, lo, hi, width: int, height: int, up_hint=None):
    """``render``'s default camera: its bounding box in view, from the +z side of the model,
    or, when the up axis (--up, else the loader's hint: a z-up scan, ``prep.pointcloud.
    ground_up``) is (nearly) the z axis, from the -y side (a z-up scan seen from the front)."""
    from ..camera import Camera

    fov = args.fov or DEFAULT_FOV_DEG
    if args.frustum is not None:
        left, right, bottom, top, near = args.frustum
        fov = math.degrees(2.0 * math.atan((top - bottom) / (2.0 * near)))
    up = tuple(args.up or up_hint or (0.0, 1.0, 0.0))
    direction = (0.0, 0.0, 1.0)
    if abs(up[2]) > 0.9 * math.hypot(*up):
        direction = (0.0, -1.0, 0.0)
    return Camera.framing(lo, hi, width, height, fov, direction=direction, up=up)


def capture_camera(capture: dict, size):
    """The sensor's camera of a depth capture (``io.pcd.capture_camera``), at the capture's
    pixel size or ``size``, the frustum widened or narrowed about its centre to that aspect."""
    from ..camera import Camera

    w0, h0 = (int(v) for v in capture["size"])
    width, height = size or (w0, h0)
    left, right, bottom, top, near = (float(v) for v in capture["frustum"])
    centre, half = 0.5 * (left + right), 0.5 * (top - bottom) * width / height
    return Camera(eye=tuple(capture["eye"]), target=tuple(capture["target"]),
                  up=tuple(capture["up"]), width=width, height=height, fov_y=None,
                  frustum=(centre - half, centre + half, bottom, top, near))


def median_depth(surfels, camera) -> float:
    """The median camera depth of the surfels in front of the camera: a capture's default
    focus (its middle distance)."""
    import numpy as np

    forward = np.subtract(camera.target, camera.eye)
    forward = forward / np.linalg.norm(forward)
    depth = (surfels.positions.astype(np.float64) - camera.eye) @ forward
    depth = depth[depth > 0]
    return float(np.median(depth)) if depth.size else math.dist(camera.eye, camera.target)


def camera_from_args(args, base):
    """``base`` (the framing or the scene's camera) with the user's options applied."""
    from ..camera import Camera

    # the base's own frustum (a capture's) holds unless the user gives a view
    frustum = args.frustum if args.frustum is not None else (None if args.fov else base.frustum)
    return Camera(eye=args.eye or base.eye, target=args.target or base.target,
                  up=args.up or base.up, width=base.width, height=base.height,
                  fov_y=args.fov or base.fov_y or DEFAULT_FOV_DEG,
                  frustum=frustum, near=base.near)


def lens_from_args(args, focus: float, default_aperture: float):
    """The thin lens from --aperture, or --focal-length with --f-number, or the default."""
    from ..camera import ThinLens

    shape = {"bokeh": getattr(args, "bokeh", "disc"), "blades": getattr(args, "blades", 0),
             "blade_rotation": getattr(args, "blade_rotation", 0.0)}
    if args.f_number is not None:
        return ThinLens(focus_distance=focus, focal_length=args.focal_length,
                        f_number=args.f_number, **shape)
    aperture = args.aperture if args.aperture is not None else default_aperture
    return ThinLens(focus_distance=focus, aperture=aperture, focal_length=args.focal_length,
                    **shape)


def settings_from_args(args):
    """The RenderSettings that the rendering options ask for."""
    from ..io import srgb_to_linear
    from ..frame import RenderSettings

    background = (0.0, 0.0, 0.0)
    if args.background is not None:
        background = tuple(float(c) for c in srgb_to_linear(args.background))
    if args.show_lod and not args.lod:
        raise DofsplatError("--show-lod needs the hierarchy: drop --no-lod")
    return RenderSettings(cutoff=args.cutoff, dof=not args.no_dof,
                          shading=args.shading or "phong",
                          background=background, cull_backfaces=not args.no_cull,
                          lod=args.lod, lod_pixel_threshold=args.lod_threshold,
                          lod_blur_fraction=args.lod_blur_fraction,
                          lod_color_tolerance=getattr(args, "lod_color_tolerance",
                                                      RenderSettings.lod_color_tolerance),
                          lod_min_node=getattr(args, "lod_min_node", RenderSettings.lod_min_node),
                          show_lod=args.show_lod,
                          device=getattr(args, "device", "cpu"),
                          reconstruction=getattr(args, "reconstruction", "soft"),
                          taper=getattr(args, "taper", False),
                          lens_samples=getattr(args, "lens_samples", 1),
                          sharp_visibility=getattr(args, "sharp_visibility", False))


def check_arguments(args) -> None:
    """Mistakes in combinations of options, found before any loading or rendering."""
    if args.f_number is not None and args.focal_length is None:
        raise DofsplatError("--f-number needs --focal-length (the lens diameter is F / n)")
    if (args.focal_length is not None and args.f_number is None and args.aperture is None
            and not args.no_dof):
        raise DofsplatError("--focal-length needs --f-number (or give the lens diameter "
                            "with --aperture)")
    if (args.focus is not None and args.focal_length is not None
            and args.focus <= args.focal_length):
        raise DofsplatError(f"the focus distance {args.focus:g} must exceed the focal length "
                            f"{args.focal_length:g} (a lens cannot focus nearer than F)")
    if args.frustum is not None:
        left, right, bottom, top, near = args.frustum
        if not (left < right and bottom < top and near > 0):
            raise DofsplatError(f"--frustum needs L < R, B < T and N > 0, got "
                                f"{' '.join(f'{v:g}' for v in args.frustum)}")
    if args.focus_at is not None:
        scene = "demo" if args.command == "demo" or getattr(args, "demo", False) else "render"
        width, height = args.size or DEFAULT_SIZE[scene]
        x, y = args.focus_at
        if not (0 <= x < width and 0 <= y < height):
            raise DofsplatError(f"--focus-at pixel ({x:g}, {y:g}) lies outside the "
                                f"{width}x{height} image")
    if getattr(args, "device", "cpu") != "cpu":
        from ..backends import resolve_device

        # --device cuda without a working GPU stops here, before any loading or writing;
        # auto falls back to the CPU with one warning
        args.device = resolve_device(args.device, flag="--device")


# -- outputs -----------------------------------------------------------------------------


def check_outputs(args) -> dict[str, Path]:
    """The output paths by role ("image", "depth", "stats"), checked before any work."""
    from ..io import check_output_path, check_writable_path

    outputs = {"image": check_output_path(args.output)}
    if args.depth is not None:
        outputs["depth"] = check_output_path(args.depth)
    if args.stats is not None:
        outputs["stats"] = check_writable_path(args.stats, "a file name for --stats")
    seen = {}
    for role, path in outputs.items():
        key = path.resolve()
        if key in seen:
            raise DofsplatError(f"the {role} output and the {seen[key]} output are the same "
                                f"file: {path}")
        seen[key] = role
    return outputs


def write_stats(path: Path, args, outputs, result, camera, lens, focus_source,
                 settings) -> None:
    """result.stats, plus the camera, lens and settings used, as JSON."""
    import json

    from ..io import atomic_write

    left, right, bottom, top, near = camera.frustum_lrbtn()
    record = dict(result.stats)
    record["method"] = args.method  # ours, postfilter or reference
    record["camera"] = {
        "eye": list(camera.eye), "target": list(camera.target), "up": list(camera.up),
        "width": camera.width, "height": camera.height,
        "fov_y_deg": camera.fov_y,  # None when the projection was given as a frustum
        "frustum_lrbtn": [left, right, bottom, top, near],
    }
    record["lens"] = None if lens is None else {
        "focus_distance": float(lens.focus_distance),
        "aperture": lens.diameter,
        "focal_length": None if lens.focal_length is None else float(lens.focal_length),
        "f_number": None if lens.f_number is None else float(lens.f_number),
        "bokeh": lens.bokeh, "blades": int(lens.blades),
        "blade_rotation": float(lens.blade_rotation),
        "focus_source": focus_source,
        "focus_at_px": None if args.focus_at is None else list(args.focus_at),
    }
    record["settings"] = {
        "cutoff": settings.cutoff, "dof": settings.dof, "shading": settings.shading,
        "background_linear": list(settings.background),
        "cull_backfaces": settings.cull_backfaces,
        "lod": settings.lod, "lod_pixel_threshold": settings.lod_pixel_threshold,
        "lod_blur_fraction": settings.lod_blur_fraction,
        # JSON has no infinity: null is the tolerance turned off
        "lod_color_tolerance": (None if math.isinf(settings.lod_color_tolerance)
                                else settings.lod_color_tolerance),
        "lod_min_node": settings.lod_min_node, "show_lod": settings.show_lod,
        "device": settings.device, "reconstruction": settings.reconstruction,
        "taper": settings.taper, "lens_samples": settings.lens_samples,
        "sharp_visibility": settings.sharp_visibility,
    }
    record["files"] = {"input": getattr(args, "input", None),
                       **{role: str(p) for role, p in outputs.items()}}
    # one line per key; lists of numbers stay on one line
    text = re.sub(r"\[\s+([^\[\]{}]*?)\s+\]",
                  lambda m: "[" + " ".join(m[1].split()) + "]",
                  json.dumps(record, indent=2)) + "\n"
    atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def summary(paths: list[Path], stats: dict) -> str:
    """``wrote demo.png (800x600, 337,807 points, 261,301 splats, 30.9M fragments, 0.90 s)``,
    and for a model file how long loading took: ``...; model loaded in 6.1 s`` or
    ``...; model from the cache in 0.02 s``."""
    samples = (f"{stats['samples']} lens sample{'s' * (stats['samples'] != 1)}, "
               if "samples" in stats else "")
    load = ""
    if "load_ms" in stats:
        how = "from the cache in" if stats["load_from_cache"] else "loaded in"
        load = f"; model {how} {stats['load_ms'] / 1000:.2f} s"
    return (f"wrote {', '.join(str(p) for p in paths)} ({stats['width']}x{stats['height']}, "
            f"{stats['points_in']:,} points, {stats['splats_rendered']:,} splats, "
            f"{samples}{format_count(stats['fragments'])} fragments, "
            f"{stats['total_ms'] / 1000:.2f} s{load})")


def format_count(n: int) -> str:
    """A count for the summary line: 9,999 as is, then 10.0k, 466.3k, 20.9M, 6.2G."""
    for threshold, scale, suffix in ((1e9, 1e9, "G"), (1e6, 1e6, "M"), (1e4, 1e3, "k")):
        if n >= threshold:
            return f"{n / scale:.1f}{suffix}"
    return f"{n:,}"
