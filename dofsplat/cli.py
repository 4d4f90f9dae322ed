"""The ``dofsplat`` command line: render a surfel model, or the built-in demo scene.

    dofsplat render MODEL.ply -o OUT.png [camera, lens and rendering options]
    dofsplat demo [-o demo.png] [the same options; the scene supplies the defaults]
    dofsplat reference (MODEL.ply | --demo) [-o reference.png] [--samples N] [the same options]
    dofsplat compare A B [--diff DIFF.png] [--json FILE.json]
    dofsplat convert INPUT -o OUT.ply [--k K] [--normalise object|render|none]

``render`` and ``demo`` take ``--method ours|postfilter`` (our DOF, or the post-process
baseline of :mod:`dofsplat.postfilter`); ``reference`` averages pinhole renders over the
lens (:mod:`dofsplat.reference`); ``compare`` prints PSNR and SSIM (:mod:`dofsplat.metrics`).

A command runs in this order, so that a user mistake costs no rendering time and leaves no
file behind: parse and check the arguments, check the output paths, load the model (or
build the demo scene), set up camera, lens and settings, autofocus (``--focus-at``),
render, write the outputs (atomically, by :mod:`dofsplat.io`), print one summary line.

:func:`main` returns the exit status: 0 on success, 2 for a user mistake (one line
``dofsplat: error: ...`` on stderr), 130 on Ctrl-C. Anything else is a bug and keeps its
traceback. numpy, numba and the renderer are imported only when a command runs.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import warnings
from pathlib import Path

from .errors import DofsplatError

EXIT_OK = 0
EXIT_USAGE = 2  # argparse's status for a usage error; every user mistake gets it
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for Ctrl-C

DEFAULT_SIZE = {"render": (512, 512), "demo": (800, 600)}  # pixels
DEFAULT_FOV_DEG = 40.0  # vertical field of view for ``render``
DEFAULT_CUTOFF = 2.5  # the paper's c
APERTURE_PER_HALF_DIAGONAL = 0.1  # ``render``'s default lens diameter, x bbox half diagonal

_EPILOG = """\
units:
  Lengths (--eye, --target, --focus, --aperture, --focal-length, --frustum) are in world
  units, the units of the model's coordinates. Image sizes and positions (--size,
  --focus-at) are in pixels, (0, 0) being the top-left corner of the image. Angles are in
  degrees. Colours are display (sRGB) values in 0..1.

examples:
  dofsplat demo
  dofsplat demo --size 1280x720 --aperture 0.3 -o wide.png
  dofsplat render scan.ply -o scan.png --focus-at 256 300
  dofsplat render scan.ply -o scan.exr --focal-length 0.05 --f-number 1.4 --focus 2.5
  dofsplat render scan.ply -o scan.png --depth scan-depth.npy --stats scan.json
  dofsplat demo --method postfilter -o postfilter.png
  dofsplat reference --demo -o reference.png --samples 200
  dofsplat compare demo.png reference.png --diff diff.png
  dofsplat convert scan.laz -o scan-surfels.ply
"""


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0, 2 for a user mistake, 130)."""
    parser = build_parser()
    try:
        try:
            args = parser.parse_args(argv)
        except SystemExit as e:  # --help and --version exit through here, status 0
            return e.code if isinstance(e.code, int) else EXIT_OK
        if getattr(args, "quiet", False):
            # every progress bar (loaders, hierarchy, reference) is tqdm's: one switch
            os.environ["TQDM_DISABLE"] = "1"
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            return args.run(args)
    except DofsplatError as e:
        _print_error(str(e))
        return EXIT_USAGE
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED


# -- the commands ------------------------------------------------------------------------


def run_render(args) -> int:
    """``dofsplat render``: load a model, frame it, render it, write the outputs."""
    from .io import load

    _check_arguments(args)
    if args.output is None:
        args.output = default_output(args.input)
    outputs = _check_outputs(args)
    surfels = load(args.input, cache=_prep_cache(args), **_loader_options(args))
    args.load_info = getattr(surfels, "load_info", None)
    if args.lod:
        from .lod.cache import cached_hierarchy

        log = None if args.quiet else (lambda m: print(f"dofsplat: {m}", file=sys.stderr))
        cached_hierarchy(surfels, args.lod_cache, progress=not args.quiet and sys.stderr.isatty(),
                         log=log)
    lo, hi = surfels.bounds()
    half_diagonal = 0.5 * math.dist(lo.tolist(), hi.tolist())
    capture = getattr(surfels, "capture", None)
    placed = any(getattr(args, a) is not None for a in ("eye", "target", "up", "fov", "frustum"))
    if capture is not None and not placed:
        # a depth camera's capture: seen from its sensor, through its own frustum
        base = _capture_camera(capture, args.size)
        camera = _camera(args, base)
        default_focus = _median_depth(surfels, camera)
    else:
        width, height = args.size or DEFAULT_SIZE["render"]
        base = _framing_camera(args, lo, hi, width, height, getattr(surfels, "up_hint", None))
        camera = _camera(args, base)
        default_focus = math.dist(camera.eye, camera.target)
    return _render_and_write(args, outputs, surfels, camera, default_focus,
                             default_aperture=APERTURE_PER_HALF_DIAGONAL * half_diagonal)


def run_demo(args) -> int:
    """``dofsplat demo``: the built-in scene (a textured plane and three spheres)."""
    from .demo import demo_scene

    _check_arguments(args)
    outputs = _check_outputs(args)
    width, height = args.size or DEFAULT_SIZE["demo"]
    surfels, base, scene_lens = demo_scene(width, height)
    camera = _camera(args, base)
    # The scene focuses on its middle sphere; a camera moved by the user focuses on its target.
    moved = args.eye is not None or args.target is not None
    default_focus = math.dist(camera.eye, camera.target) if moved else scene_lens.focus_distance
    return _render_and_write(args, outputs, surfels, camera, default_focus,
                             default_aperture=scene_lens.diameter)


def run_reference(args) -> int:
    """``dofsplat reference``: the multisample reference of a model, or of the demo scene."""
    if (args.input is None) == (not args.demo):
        raise DofsplatError("give either a model file or --demo (the built-in scene), "
                            "not both" if args.demo else
                            "give a model file to render, or --demo for the built-in scene")
    # every lens sample is a full-resolution pinhole render: no LOD hierarchy to build (the
    # parser has no LOD options for this command; the shared code reads these, so any LOD
    # option added later gets RenderSettings' default here rather than an AttributeError)
    from .frame import RenderSettings

    lod_defaults = RenderSettings()
    args.lod, args.show_lod = False, False
    args.lod_threshold = getattr(args, "lod_threshold", lod_defaults.lod_pixel_threshold)
    args.lod_blur_fraction = getattr(args, "lod_blur_fraction", lod_defaults.lod_blur_fraction)
    return run_demo(args) if args.demo else run_render(args)


def run_compare(args) -> int:
    """``dofsplat compare``: PSNR and SSIM between two images; a difference image on request."""
    import json

    from .io import atomic_write, check_output_path, check_writable_path, read_image
    from .metrics import compare, write_difference

    outputs = {}
    if args.diff is not None:
        outputs["diff"] = check_output_path(args.diff)
    if args.json is not None:
        outputs["json"] = check_writable_path(args.json, "a file name for --json")
    inputs = {Path(args.a).resolve(), Path(args.b).resolve()}
    for role, path in outputs.items():
        if path.resolve() in inputs:
            raise DofsplatError(f"the --{role} output {path} would overwrite an input image")
    if "diff" in outputs and "json" in outputs and outputs["diff"].resolve() == outputs["json"].resolve():
        raise DofsplatError(f"--diff and --json name the same file: {outputs['diff']}")

    a, b = read_image(args.a), read_image(args.b)
    if a.shape[:2] != b.shape[:2]:
        raise DofsplatError(f"the images differ in size: {args.a} is {a.shape[1]}x{a.shape[0]} "
                            f"pixels, {args.b} is {b.shape[1]}x{b.shape[0]}")
    result = compare(a, b, space=args.space)

    if "diff" in outputs:
        write_difference(outputs["diff"], a, b, gain=args.gain, space=args.space)
    if "json" in outputs:
        identical = math.isinf(result["psnr"])
        record = {"a": str(args.a), "b": str(args.b), "width": int(a.shape[1]),
                  "height": int(a.shape[0]), "space": result["space"],
                  "psnr_db": None if identical else result["psnr"],  # null: identical, PSNR inf
                  "identical": identical, "ssim": result["ssim"], "mse": result["mse"]}
        text = json.dumps(record, indent=2) + "\n"
        atomic_write(outputs["json"], lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
    print(f"PSNR {result['psnr']:.2f} dB  SSIM {result['ssim']:.4f}")
    if outputs and not args.quiet:
        print(f"wrote {', '.join(str(p) for p in outputs.values())}", file=sys.stderr)
    return EXIT_OK


def run_convert(args) -> int:
    """``dofsplat convert``: any model file to a normalised surfel PLY, done once."""
    import time

    from .io import SAVERS, check_writable_path, load, save_surfels

    out = Path(args.output)
    if not any(out.name.lower().endswith(ext) for ext in SAVERS):
        raise DofsplatError(f"{out}: a converted model is saved as a surfel PLY; give a name "
                            f"ending in {' or '.join(sorted(SAVERS))}")
    check_writable_path(out, "a surfel file name")
    if Path(args.input).exists() and out.resolve() == Path(args.input).resolve():
        raise DofsplatError(f"the output {out} would overwrite the input")
    t0 = time.perf_counter()
    surfels = load(args.input, cache=_prep_cache(args), **_loader_options(args))
    save_surfels(out, surfels)
    if not args.quiet:
        how = args.normalise or _default_normalisation(Path(args.input))
        print(f"wrote {out} ({len(surfels):,} surfels, normalisation: {how}, "
              f"{time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    return EXIT_OK


def _render_and_write(args, outputs, surfels, camera, default_focus: float,
                      default_aperture: float) -> int:
    """The part both commands share: lens, settings, autofocus, render, outputs."""
    from .io import write_depth, write_image
    from .render import focus_distance_at

    settings = _settings(args)
    from .backends import resolve_device

    if not args.quiet and resolve_device(settings.device, "--device") == "cpu":
        from .backends.cpu import COMPILE_SECONDS, kernels_compiled

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
        lens = _lens(args, focus, default_aperture)

    result = _render_by_method(args, surfels, camera, lens, settings)
    info = getattr(args, "load_info", None)
    if info is not None:  # the model's loading and preparation, before the frame
        result.stats["load_ms"] = info["seconds"] * 1000.0
        result.stats["load_from_cache"] = bool(info["from_cache"])

    write_image(outputs["image"], result.image, depth=result.depth)
    if "depth" in outputs:
        write_depth(outputs["depth"], result.depth)
    if "stats" in outputs:
        _write_stats(outputs["stats"], args, outputs, result, camera, lens, focus_source,
                     settings)
    if not args.quiet:
        print(_summary(list(outputs.values()), result.stats), file=sys.stderr)
    return EXIT_OK


def _render_by_method(args, surfels, camera, lens, settings):
    """Our DOF render, the post-process baseline, or the multisample reference."""
    from .render import render

    if args.method == "postfilter":
        from .postfilter import render_postfilter

        return render_postfilter(surfels, camera, lens, settings)
    if args.method == "reference":
        from .reference import render_reference

        return render_reference(surfels, camera, lens, settings, samples=args.samples,
                                progress=not args.quiet)
    return render(surfels, camera, lens, settings)


# -- camera, lens, settings --------------------------------------------------------------


def _framing_camera(args, lo, hi, width: int, height: int, up_hint=None):
    """``render``'s default camera: its bounding box in view, from the +z side of the model,
    or, when the up axis (--up, else the loader's hint: a z-up scan, ``prep.pointcloud.
    ground_up``) is (nearly) the z axis, from the -y side (a z-up scan seen from the front)."""
    from .camera import Camera

    fov = args.fov or DEFAULT_FOV_DEG
    if args.frustum is not None:
        left, right, bottom, top, near = args.frustum
        fov = math.degrees(2.0 * math.atan((top - bottom) / (2.0 * near)))
    up = tuple(args.up or up_hint or (0.0, 1.0, 0.0))
    direction = (0.0, 0.0, 1.0)
    if abs(up[2]) > 0.9 * math.hypot(*up):
        direction = (0.0, -1.0, 0.0)
    return Camera.framing(lo, hi, width, height, fov, direction=direction, up=up)


def _capture_camera(capture: dict, size):
    """The sensor's camera of a depth capture (``io.pcd.capture_camera``), at the capture's
    pixel size or ``size``, the frustum widened or narrowed about its centre to that aspect."""
    from .camera import Camera

    w0, h0 = (int(v) for v in capture["size"])
    width, height = size or (w0, h0)
    left, right, bottom, top, near = (float(v) for v in capture["frustum"])
    centre, half = 0.5 * (left + right), 0.5 * (top - bottom) * width / height
    return Camera(eye=tuple(capture["eye"]), target=tuple(capture["target"]),
                  up=tuple(capture["up"]), width=width, height=height, fov_y=None,
                  frustum=(centre - half, centre + half, bottom, top, near))


def _median_depth(surfels, camera) -> float:
    """The median camera depth of the surfels in front of the camera: a capture's default
    focus (its middle distance)."""
    import numpy as np

    forward = np.subtract(camera.target, camera.eye)
    forward = forward / np.linalg.norm(forward)
    depth = (surfels.positions.astype(np.float64) - camera.eye) @ forward
    depth = depth[depth > 0]
    return float(np.median(depth)) if depth.size else math.dist(camera.eye, camera.target)


def _camera(args, base):
    """``base`` (the framing or the scene's camera) with the user's options applied."""
    from .camera import Camera

    # the base's own frustum (a capture's) holds unless the user gives a view
    frustum = args.frustum if args.frustum is not None else (None if args.fov else base.frustum)
    return Camera(eye=args.eye or base.eye, target=args.target or base.target,
                  up=args.up or base.up, width=base.width, height=base.height,
                  fov_y=args.fov or base.fov_y or DEFAULT_FOV_DEG,
                  frustum=frustum, near=base.near)


def _lens(args, focus: float, default_aperture: float):
    """The thin lens from --aperture, or --focal-length with --f-number, or the default."""
    from .camera import ThinLens

    shape = {"bokeh": getattr(args, "bokeh", "disc"), "blades": getattr(args, "blades", 0),
             "blade_rotation": getattr(args, "blade_rotation", 0.0)}
    if args.f_number is not None:
        return ThinLens(focus_distance=focus, focal_length=args.focal_length,
                        f_number=args.f_number, **shape)
    aperture = args.aperture if args.aperture is not None else default_aperture
    return ThinLens(focus_distance=focus, aperture=aperture, focal_length=args.focal_length,
                    **shape)


def _settings(args):
    from .io import srgb_to_linear
    from .frame import RenderSettings

    background = (0.0, 0.0, 0.0)
    if args.background is not None:
        background = tuple(float(c) for c in srgb_to_linear(args.background))
    if args.show_lod and not args.lod:
        raise DofsplatError("--show-lod needs the hierarchy: drop --no-lod")
    return RenderSettings(cutoff=args.cutoff, dof=not args.no_dof, shading=args.shading,
                          background=background, cull_backfaces=not args.no_cull,
                          lod=args.lod, lod_pixel_threshold=args.lod_threshold,
                          lod_blur_fraction=args.lod_blur_fraction, show_lod=args.show_lod,
                          device=getattr(args, "device", "cpu"),
                          reconstruction=getattr(args, "reconstruction", "soft"),
                          taper=getattr(args, "taper", False))


def _check_arguments(args) -> None:
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
        from .backends import resolve_device

        # --device cuda without a working GPU stops here, before any loading or writing;
        # auto falls back to the CPU with one warning
        args.device = resolve_device(args.device, flag="--device")


# -- outputs -----------------------------------------------------------------------------


def _check_outputs(args) -> dict[str, Path]:
    """The output paths by role ("image", "depth", "stats"), checked before any work."""
    from .io import check_output_path, check_writable_path

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


def _write_stats(path: Path, args, outputs, result, camera, lens, focus_source,
                 settings) -> None:
    """result.stats, plus the camera, lens and settings used, as JSON."""
    import json

    from .io import atomic_write

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
        "lod_blur_fraction": settings.lod_blur_fraction, "show_lod": settings.show_lod,
        "device": settings.device, "reconstruction": settings.reconstruction,
        "taper": settings.taper,
    }
    record["files"] = {"input": getattr(args, "input", None),
                       **{role: str(p) for role, p in outputs.items()}}
    # one line per key; lists of numbers stay on one line
    text = re.sub(r"\[\s+([^\[\]{}]*?)\s+\]",
                  lambda m: "[" + " ".join(m[1].split()) + "]",
                  json.dumps(record, indent=2)) + "\n"
    atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def _summary(paths: list[Path], stats: dict) -> str:
    """``wrote demo.png (800x600, 337,807 points, 261,301 splats, 30.9M fragments, 0.90 s)``,
    and for a model file how long loading took: ``...; model loaded in 6.1 s`` or
    ``...; model from the cache in 0.02 s``."""
    samples = f"{stats['samples']} lens samples, " if "samples" in stats else ""
    load = ""
    if "load_ms" in stats:
        how = "from the cache in" if stats["load_from_cache"] else "loaded in"
        load = f"; model {how} {stats['load_ms'] / 1000:.2f} s"
    return (f"wrote {', '.join(str(p) for p in paths)} ({stats['width']}x{stats['height']}, "
            f"{stats['points_in']:,} points, {stats['splats_rendered']:,} splats, "
            f"{samples}{_count(stats['fragments'])} fragments, "
            f"{stats['total_ms'] / 1000:.2f} s{load})")


def _count(n: int) -> str:
    """A count for the summary line: 9,999 as is, then 10.0k, 466.3k, 20.9M, 6.2G."""
    for threshold, scale, suffix in ((1e9, 1e9, "G"), (1e6, 1e6, "M"), (1e4, 1e3, "k")):
        if n >= threshold:
            return f"{n / scale:.1f}{suffix}"
    return f"{n:,}"


# -- the parser --------------------------------------------------------------------------


class _HelpFormatter(argparse.HelpFormatter):
    """Wraps prose paragraphs; keeps indented blocks (the examples) as written."""

    def _fill_text(self, text, width, indent):
        paragraphs = []
        for block in text.strip("\n").split("\n\n"):
            lines = block.splitlines()
            if any(line.startswith(" ") for line in lines[1:]):
                paragraphs.append("\n".join(indent + line for line in lines))
            else:
                paragraphs.append(super()._fill_text(block, width, indent))
        return "\n\n".join(paragraphs)


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage mistake is one line on stderr (raised, printed by main)."""

    def error(self, message):
        raise DofsplatError(message)


def build_parser() -> argparse.ArgumentParser:
    from . import __version__
    from .demo import DEMO_APERTURE, DEMO_FOV_DEG, PLANE_SIZE

    parser = _Parser(
        prog="dofsplat", allow_abbrev=False, epilog=_EPILOG,
        formatter_class=_HelpFormatter,
        description="Render surfel models (points with normals and radii) with depth of "
                    "field, by EWA surface splatting (Krivanek & Zara 2003).")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND",
                                     parser_class=_Parser)

    render = commands.add_parser(
        "render", allow_abbrev=False, epilog=_EPILOG,
        formatter_class=_HelpFormatter,
        help="render a model file: surfels, points, a mesh or Gaussian splats",
        description="Render a model with depth of field. Without camera options the "
                    "model is framed from its +z side, focused on its centre, with a lens "
                    f"diameter of {APERTURE_PER_HALF_DIAGONAL:g} x the half diagonal of its "
                    "bounding box.")
    render.add_argument("input", metavar="INPUT",
                        help="model file: surfels, points, a mesh or 3D Gaussian splats: "
                             + ", ".join(_MODEL_EXTENSIONS) + " (docs/formats.md)")
    render.add_argument("-o", "--output", metavar="OUTPUT",
                        help="image to write: .png (8-bit sRGB), .npy (float32 linear RGBA, "
                             "H x W x 4) or .exr (float32 linear RGBA + Z) (default: the "
                             "model's name with .png, in the current folder)")
    _add_input_options(render)
    _add_view_options(render, "render")
    render.set_defaults(run=run_render)

    demo = commands.add_parser(
        "demo", allow_abbrev=False, epilog=_EPILOG,
        formatter_class=_HelpFormatter,
        help="render the built-in scene: a textured plane and three spheres",
        description="Render the built-in demo scene: a textured plane with three spheres, "
                    "the middle one in focus. The scene brings its own camera (vertical field "
                    f"of view {DEMO_FOV_DEG:g} degrees) and lens (diameter {DEMO_APERTURE:g} "
                    f"world units; the plane is {PLANE_SIZE:g} world units wide); the options "
                    "below override them.")
    demo.add_argument("-o", "--output", metavar="OUTPUT", default="demo.png",
                      help="image to write: .png, .npy or .exr (default: demo.png)")
    _add_view_options(demo, "demo")
    demo.set_defaults(run=run_demo)

    reference = commands.add_parser(
        "reference", allow_abbrev=False, epilog=_EPILOG,
        formatter_class=_HelpFormatter,
        help="the multisample reference: pinhole renders over the lens, averaged",
        description="Render the ground truth that depth of field approximates: N pinhole "
                    "images seen from points spread over the lens, each with its frustum "
                    "sheared so that the focal plane stays fixed, averaged (the paper's "
                    "multisampling reference; it takes N times as long as a pinhole render). "
                    "Takes a model file like 'render', or --demo for the built-in scene, and "
                    "the same camera and lens options, so that 'dofsplat compare' can set "
                    "the two images side by side.")
    reference.add_argument("input", metavar="INPUT", nargs="?",
                           help="model file, as for 'render' (or give --demo)")
    reference.add_argument("--demo", action="store_true",
                           help="render the built-in demo scene, with its camera and lens")
    reference.add_argument("-o", "--output", metavar="OUTPUT", default="reference.png",
                           help="image to write: .png, .npy or .exr (default: reference.png)")
    reference.add_argument("--samples", metavar="N", type=_positive_int, default=200,
                           help="number of lens samples (default: 200, as in the paper)")
    _add_input_options(reference)
    _add_view_options(reference, "reference")
    reference.set_defaults(run=run_reference, method="reference")

    compare = commands.add_parser(
        "compare", allow_abbrev=False, formatter_class=_HelpFormatter,
        help="PSNR and SSIM between two images",
        description="Print the PSNR (dB; inf for identical images) and the SSIM of two "
                    "images of the same size, measured on the displayed values: linear "
                    "colour clipped to 0..1 and sRGB-encoded (alpha is ignored).",
        epilog="example:\n  dofsplat compare demo.png reference.png --diff diff.png")
    compare.add_argument("a", metavar="A", help="first image: .png, .npy or .exr")
    compare.add_argument("b", metavar="B", help="second image, the same size")
    compare.add_argument("--diff", metavar="OUT",
                         help="also write the difference image, GAIN x |A - B| per channel "
                              "(.png, .npy or .exr)")
    compare.add_argument("--gain", metavar="GAIN", type=_positive, default=10.0,
                         help="amplification of the difference image (default: 10)")
    compare.add_argument("--json", metavar="FILE.json",
                         help="also write the numbers as JSON (psnr_db is null for "
                              "identical images)")
    compare.add_argument("--space", choices=("srgb", "linear"), default="srgb",
                         help="compare the displayed sRGB values (default) or the linear ones")
    compare.add_argument("-q", "--quiet", action="store_true",
                         help="do not say which files were written")
    compare.set_defaults(run=run_compare)

    convert = commands.add_parser(
        "convert", allow_abbrev=False, formatter_class=_HelpFormatter,
        help="turn a model file into normalised surfels, saved as a surfel PLY",
        description="Load any model file as 'render' does (points get normals and radii, "
                    "meshes and Gaussian splats become surfels, points and meshes get the "
                    "per-surfel normalisation so that splats sum to 1 over the surface, paper "
                    "Section 6.3), and save the surfels, so that this is done once.",
        epilog="examples:\n  dofsplat convert scan.laz -o scan-surfels.ply\n"
               "  dofsplat convert dragon.ply.gz -o dragon.ply --points vertices "
               "--normalise render")
    convert.add_argument("input", metavar="INPUT",
                         help="model file: " + ", ".join(_MODEL_EXTENSIONS))
    convert.add_argument("-o", "--output", metavar="OUT.ply", required=True,
                         help="surfel PLY to write (.ply, binary, or .ply.gz)")
    convert.add_argument("-q", "--quiet", action="store_true",
                         help="no progress bars, no summary line")
    _add_input_options(convert)
    convert.set_defaults(run=run_convert)

    cache = commands.add_parser(
        "cache", allow_abbrev=False, formatter_class=_HelpFormatter,
        help="show or clear the cache of prepared models and LOD hierarchies",
        description="Show where dofsplat keeps prepared models (point clouds and meshes "
                    "made into surfels) and LOD hierarchies, and how much room they take; "
                    "or clear it. The cache holds at most 2 GB unless DOFSPLAT_CACHE_MAX says "
                    "otherwise (e.g. 500M, 10G; 0 turns it off); the least recently used "
                    "files go first.",
        epilog="examples:\n  dofsplat cache\n  dofsplat cache --clear\n"
               "  dofsplat cache --clear lod")
    cache.add_argument("--info", action="store_true",
                       help="show the folder, the files and their size (the default)")
    cache.add_argument("--clear", nargs="?", const="all", choices=("all", "surfels", "lod"),
                       help="delete the cached files: all (the default), or one kind")
    cache.set_defaults(run=run_cache)

    parser.set_defaults(run=_no_command)
    return parser


def run_cache(args) -> int:
    """``dofsplat cache``: the cache's folder and size; --clear empties it."""
    from . import cache

    root = cache.cache_root()
    if args.clear is not None:
        kind = None if args.clear == "all" else args.clear
        n, size = cache.clear_cache(kind)
        print(f"removed {n:,} file{'s' * (n != 1)} ({cache.format_bytes(size)}) from {root}")
        return EXIT_OK
    info = cache.cache_info()
    limit = cache.max_bytes()
    print(f"cache folder: {root}")
    for kind, what in cache.KINDS.items():
        n, size = info[kind]
        print(f"  {kind + '/':10s}{what}: {n:,} file{'s' * (n != 1)}, {cache.format_bytes(size)}")
    n, size = info["total"]
    cap = "off (DOFSPLAT_CACHE_MAX=0)" if limit == 0 else cache.format_bytes(limit)
    print(f"  total: {cache.format_bytes(size)} of at most {cap}; least recently used files "
          "go first (DOFSPLAT_CACHE_MAX sets the cap, DOFSPLAT_CACHE_DIR the folder)")
    print("  'dofsplat cache --clear' empties it (or --clear surfels, --clear lod)")
    return EXIT_OK


def _no_command(args) -> int:
    raise DofsplatError("no command given: use 'dofsplat render INPUT -o OUTPUT' or "
                        "'dofsplat demo' (dofsplat --help tells more)")


# what ``render`` reads, for the help texts (dofsplat.io.LOADERS holds the loaders)
_MODEL_EXTENSIONS = (".ply", ".ply.gz", ".obj", ".gltf", ".glb", ".stl", ".off", ".las", ".laz",
                     ".e57", ".pcd")


def _add_input_options(p: argparse.ArgumentParser) -> None:
    """How a model file becomes surfels: the loader options (dofsplat.io.load's keywords)."""
    group = p.add_argument_group(
        "input", "How a file that is not a surfel file becomes surfels (docs/formats.md).")
    group.add_argument("--points", metavar="N", type=_sample_count,
                       help="meshes: the number of surfels sampled over the surface "
                            "(default: the vertex count, at least 200000), or 'vertices' "
                            "for one surfel per vertex")
    group.add_argument("--texture", metavar="FILE",
                       help="meshes: an image applied through the texture coordinates "
                            "(for an OBJ that names no material file)")
    group.add_argument("--k", metavar="K", type=_positive_int,
                       help="point clouds (PLY without faces, LAS/LAZ, E57, PCD): neighbours for "
                            "the normals, smoothing and radii (default: 24)")
    group.add_argument("--no-smooth", dest="smooth", action="store_false", default=None,
                       help="point clouds: keep the positions as measured (default: each "
                            "point is moved along its normal onto the plane of its K "
                            "neighbours, which removes scanner noise and quantisation); "
                            "meshes: samples on the flat triangles (default: on the Phong "
                            "tessellation that the vertex normals describe)")
    group.add_argument("--normalise", choices=("object", "render", "none"),
                       help="per-surfel normalisation, so that splats sum to 1 over the "
                            "surface (paper Section 6.3): object (neighbours' basis functions "
                            "summed in each surfel's tangent plane, seconds), render (the "
                            "paper's: weights read back from renders, slower) or none. "
                            "Default: object for points and meshes; a surfel or 3DGS file is "
                            "taken as it is")
    group.add_argument("--no-cache", action="store_true",
                       help="prepare the model again: neither read nor keep it in the cache "
                            "of prepared models (a point cloud or mesh that took over "
                            "0.5 s to prepare is kept there, keyed by the file's content and "
                            "these options; 'dofsplat cache' shows and clears it)")


def _prep_cache(args) -> str:
    """load()'s cache: "off" with --no-cache."""
    return "off" if getattr(args, "no_cache", False) else "auto"


def default_output(model: str) -> str:
    """``render``'s output without -o: the model's name with .png, in the current folder
    (``scans/lion.laz`` -> ``lion.png``, ``dragon.ply.gz`` -> ``dragon.png``)."""
    name = Path(model).name
    for ext in sorted(_MODEL_EXTENSIONS, key=len, reverse=True):
        if name.lower().endswith(ext):
            name = name[:-len(ext)]
            break
    return (name or "render") + ".png"


def _loader_options(args) -> dict:
    """The input options the user gave, as keywords for dofsplat.io.load."""
    names = ("points", "texture", "k", "smooth", "normalise")
    return {n: getattr(args, n) for n in names if getattr(args, n, None) is not None}


def _default_normalisation(path: Path) -> str:
    """What the loaders do without --normalise: "object" for points and meshes, "none" for
    a surfel or 3DGS PLY (taken as it is)."""
    from .io.ply import ply_kind, read_ply_header

    ply = path.name.lower().endswith((".ply", ".ply.gz"))
    if ply and ply_kind(read_ply_header(path)) in ("surfels", "gaussians"):
        return "none (as stored)"
    return "object"


def _sample_count(text: str):
    if text.strip().lower() == "vertices":
        return "vertices"
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number or 'vertices', got "
                                         f"{text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text!r}")
    return value


def _add_view_options(p: argparse.ArgumentParser, command: str) -> None:
    """The options that ``render``, ``demo`` and ``reference`` share; help texts name each
    one's defaults (``reference`` has ``render``'s, or the demo scene's with --demo)."""
    from .demo import DEMO_APERTURE, DEMO_FOV_DEG

    is_demo = command == "demo"
    w, h = DEFAULT_SIZE.get(command, DEFAULT_SIZE["render"])
    demo_size = "; with --demo: {}x{}".format(*DEFAULT_SIZE["demo"]) if command == "reference" else ""

    out = p.add_argument_group("more outputs")
    out.add_argument("--depth", metavar="FILE",
                     help="also write the depth map: camera depth in world units, inf where "
                          "empty (.npy or .exr); .png gives a 16-bit picture of it, near is "
                          "dark, empty is black")
    out.add_argument("--stats", metavar="FILE.json",
                     help="also write statistics as JSON: points in, splats rendered, "
                          "fragments, milliseconds per stage and in total, and the camera, "
                          "lens and settings used")
    out.add_argument("-q", "--quiet", action="store_true",
                     help="do not print the summary line")

    cam = p.add_argument_group(
        "camera", "Where the camera is and what it sees. "
        + ("Default: the scene's camera." if is_demo else
           "Default: looking at the centre of the model's bounding box along -z, from far "
           "enough away that the whole box is in view."))
    cam.add_argument("--size", metavar="WxH", type=_size,
                     help=f"image size in pixels (default: {w}x{h}{demo_size})")
    cam.add_argument("--eye", nargs=3, type=_number, metavar=("X", "Y", "Z"),
                     help="camera position, world units")
    cam.add_argument("--target", nargs=3, type=_number, metavar=("X", "Y", "Z"),
                     help="point the camera looks at, world units"
                          + ("" if is_demo else " (default: the model's centre)"))
    cam.add_argument("--up", nargs=3, type=_number, metavar=("X", "Y", "Z"),
                     help="direction that appears upwards in the image (default: 0 1 0, or "
                          "0 0 1 for a point cloud whose ground faces +z)")
    view = cam.add_mutually_exclusive_group()
    view.add_argument("--fov", metavar="DEG", type=_fov,
                      help="vertical field of view in degrees (default: "
                           + (f"{DEMO_FOV_DEG:g})" if is_demo else f"{DEFAULT_FOV_DEG:g})"))
    view.add_argument("--frustum", nargs=5, type=_number, metavar=("L", "R", "B", "T", "N"),
                      help="the projection as glFrustum: the window [L, R] x [B, T] on the "
                           "near plane at distance N in front of the eye, world units; "
                           "(R-L)/(T-B) must equal W/H")

    lens = p.add_argument_group(
        "lens (depth of field)",
        "A thin lens: surfaces at the focus distance are sharp, nearer and farther ones blur "
        "the more, the wider the lens. Default: "
        + (f"the scene's lens, diameter {DEMO_APERTURE:g} world units, focused on the "
           "middle sphere."
           if is_demo else
           f"diameter {APERTURE_PER_HALF_DIAGONAL:g} x the half diagonal of the model's "
           "bounding box, focused on the target."))
    diameter = lens.add_mutually_exclusive_group()
    diameter.add_argument("--aperture", metavar="A", type=_non_negative,
                          help="lens diameter, world units; 0 is a pinhole (all sharp)")
    diameter.add_argument("--f-number", metavar="N", type=_positive,
                          help="f-number (f-stop) n, with --focal-length: the lens diameter "
                               "is F / n, so a smaller n blurs more")
    diameter.add_argument("--no-dof", action="store_true",
                          help="no depth of field: a pinhole camera, everything sharp")
    lens.add_argument("--focal-length", metavar="F", type=_positive,
                      help="focal length F, world units (e.g. 0.05 for a 50 mm lens in a "
                           "model measured in metres); with --f-number it sets the lens "
                           "diameter, and the focus distance must exceed it. The field of "
                           "view is set by --fov or --frustum, not by F")
    lens.add_argument("--bokeh", choices=("disc", "gaussian"), default="disc",
                      help="the blur's shape: disc (default), the aperture's own image, flat "
                           "with a crisp edge as in a photograph; gaussian, the paper's soft "
                           "blob of the same size (docs/maths.md)")
    lens.add_argument("--blades", metavar="N", type=_blades, default=0,
                      help="straight aperture blades, 5 to 16: defocused highlights become "
                           "N-gons (default 0: round)")
    lens.add_argument("--blade-rotation", metavar="DEG", type=_number, default=0.0,
                      help="turn the polygon of --blades by DEG degrees, counterclockwise")
    focus = lens.add_mutually_exclusive_group()
    focus.add_argument("--focus", metavar="P", type=_positive,
                       help="focus distance, world units, measured along the view axis "
                            "(default: "
                            + ("the middle sphere; with --eye or --target, the distance "
                               "from eye to target)" if is_demo else
                               "the distance from eye to target)"))
    focus.add_argument("--focus-at", nargs=2, type=_number, metavar=("X", "Y"),
                       help="focus on the surface seen at pixel (X, Y), counted from the "
                            "top-left corner of the image (costs one extra, sharp render)")

    ren = p.add_argument_group("rendering")
    ren.add_argument("--cutoff", metavar="C", type=_positive, default=DEFAULT_CUTOFF,
                     help="splat cutoff c: each Gaussian kernel is cut where its exponent "
                          f"reaches c; larger is smoother and slower (default: "
                          f"{DEFAULT_CUTOFF:g}, as in the paper)")
    ren.add_argument("--shading", choices=("phong", "none"), default="phong",
                     help="phong: lit by a light at the camera (default); none: the surfel "
                          "colours as they are")
    ren.add_argument("--background", nargs=3, type=_unit, metavar=("R", "G", "B"),
                     help="background colour, display (sRGB) values in 0..1 "
                          "(default: 0 0 0, black)")
    ren.add_argument("--no-cull", action="store_true",
                     help="keep surfels that face away from the camera and light both "
                          "sides (for models with inconsistent normals)")
    if command != "reference":
        ren.add_argument("--method", choices=("ours", "postfilter"), default="ours",
                         help="ours: each splat blurred by its circle of confusion before "
                              "visibility (default); postfilter: the common post-process "
                              "baseline, a pinhole image blurred by the CoC of its depth "
                              "buffer (for comparison: it leaks intensity and misses partial "
                              "occlusion)")
        ren.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu",
                         help="where to render: cpu (default); cuda, an NVIDIA GPU (pip install "
                              "'dofsplat[cuda]'; an error if none works); auto, the GPU if one "
                              "works, else the CPU")

    if command == "reference":
        return  # its lens samples are full-resolution pinhole renders: no LOD options
    p.add_argument("--reconstruction", choices=("soft", "paper"), default="soft",
                   help="how blurred surfaces meet: soft (default) merges surfaces whose "
                        "parallax is small against their blur and removes what such a "
                        "surface hides, so a blurred object touching another shows no seam; "
                        "paper is Section 6.4's z-range decision alone (docs/maths.md)")
    lod = p.add_argument_group(
        "level of detail",
        "Blurred surfaces are drawn from a coarser level of a hierarchy over the surfels, "
        "so the time per frame hardly depends on the aperture (the paper's Section 6.2). "
        "The picture stays the same (PSNR against --no-lod: 54-65 dB on the plane of the "
        "paper's Table 1, 46-55 dB on a scanned statue).")
    lod.add_argument("--lod", action=argparse.BooleanOptionalAction, default=True,
                     help="select splats from the hierarchy (default: on); --no-lod splats "
                          "every surfel")
    lod.add_argument("--lod-threshold", metavar="PX", type=_non_negative, default=1.0,
                     help="also draw a node whole when its disk projects to at most PX "
                          "pixels in radius, as QSplat does (default: 1; 0 keeps every "
                          "surfel that the blur does not merge)")
    lod.add_argument("--lod-blur-fraction", metavar="K", type=_fraction, default=1.0,
                     help="draw a node when its own blur is at most K times the depth-of-"
                          "field blur (variance): 1 (default) is the paper's rule; 0.5 goes "
                          "one level finer, closer to the exact picture, for ~1.5x the "
                          "fragments")
    lod.add_argument("--show-lod", action="store_true",
                     help="colour each splat by its level (grey: single surfels, then "
                          "blue, cyan, green, ... as nodes get coarser) and draw it without "
                          "the blur, to see which levels the depth of field selects")
    lod.add_argument("--taper", action="store_true",
                     help="with --bokeh gaussian: taper LOD nodes' Gaussians to 0 at the "
                          "cutoff, so that very large blurs show no hard-edged discs; it "
                          "also narrows them, so it is off by default (docs/maths.md). The "
                          "aperture's kernels (the default) are always tapered")
    if not is_demo:
        lod.add_argument("--lod-cache", metavar="FILE|auto|off", default="auto",
                         help="where the hierarchy is kept between runs: auto (default) "
                              "in ~/.cache/dofsplat/lod; a FILE.npz, e.g. next to the "
                              "model; off builds it each time. A changed model is detected "
                              "and its hierarchy rebuilt")


# -- argument types: each raises ArgumentTypeError, which argparse reports on one line ---


def _blades(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of blades, got {text!r}") from None
    if n != 0 and not 5 <= n <= 16:
        raise argparse.ArgumentTypeError(f"blades must be 0 (round) or 5 to 16, got {n}")
    return n


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels such as 640x480, "
                                         f"got {text!r}")
    width, height = int(m[1]), int(m[2])
    if width < 1 or height < 1:
        raise argparse.ArgumentTypeError(f"the image needs at least 1x1 pixels, got {text!r}")
    return width, height


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _positive(text: str) -> float:
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text!r}")
    return value


def _non_negative(text: str) -> float:
    value = _number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return value


def _fraction(text: str) -> float:
    value = _number(text)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], got {text!r}")
    return value


def _unit(text: str) -> float:
    value = _number(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in 0..1, got {text!r}")
    return value


def _fov(text: str) -> float:
    value = _number(text)
    if not 0.0 < value < 180.0:
        raise argparse.ArgumentTypeError(f"must be between 0 and 180 degrees, got {text!r}")
    return value


# -- messages ----------------------------------------------------------------------------


def _print_error(message: str) -> None:
    print(f"dofsplat: error: {_one_line(message)}", file=sys.stderr)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"dofsplat: warning: {_one_line(str(message))}", file=sys.stderr)


def _one_line(message: str) -> str:
    return " ".join(part.strip() for part in message.splitlines() if part.strip()) or "failed"
