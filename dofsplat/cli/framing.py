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
from .options import DEFAULT_FOV_DEG, DEFAULT_SENSOR_WIDTH_MM, DEFAULT_SIZE, EXIT_OK


def render_and_write(args, outputs, surfels, camera, default_focus: float,
                      default_aperture: float) -> int:
    """The part both commands share: lens, settings, autofocus, render, outputs."""
    import numpy as np

    from ..io import nonfinite_pixels, write_depth, write_image
    from ..render import focus_distance_at

    settings = settings_from_args(args)
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
        camera = photographic_camera(args, camera, focus)

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
        print(summary(list(outputs.values()), result.stats, focus_note(args, lens, focus_source)),
              file=sys.stderr)
    return EXIT_OK


def focus_note(args, lens, focus_source) -> str:
    """The summary's words naming the focus distance where dofsplat chose it (--focus-at,
    or render's default: ``focused at 1.93 (the surface at the image centre)``); nothing
    where the user gave it, the scene's own (the demo's middle sphere) or no lens."""
    if lens is None or focus_source == "--focus":
        return ""
    if focus_source == "--focus-at":
        x, y = args.focus_at
        where = f"--focus-at {x:g} {y:g}"
    else:
        where = getattr(args, "default_focus_source", None)
        if where is None:
            return ""
    return f"focused at {lens.focus_distance:.4g} ({where})"


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

        return render(surfels, camera, lens, dataclasses.replace(
            settings, gaussian_blur="viewers", gaussian_lens_samples=1,
            gaussian_lod=False))  # (as the viewers ship it: one pass, every Gaussian)
    if args.method == "postfilter":
        from ..postfilter import render_postfilter

        return render_postfilter(surfels, camera, lens, settings)
    if args.method == "reference":
        from ..reference import render_reference

        if args.samples >= ESTIMATE_FROM and not args.quiet:
            estimate_reference_time(surfels, camera, settings, args.samples)
        return render_reference(surfels, camera, lens, settings, samples=args.samples,
                                progress=not args.quiet)
    return render(surfels, camera, lens, settings)


ESTIMATE_FROM = 1000  # lens samples from which ``reference`` first says how long it will take


def estimate_reference_time(surfels, camera, settings, samples: int) -> None:
    """Print how long ``samples`` lens samples will take, from the time of one pinhole frame
    (the reference's samples are pinhole frames of the full model)."""
    import time

    from ..render import warm_up

    if settings.device == "cpu":
        warm_up()  # (loading the kernels is no sample's time)
    t0 = time.perf_counter()
    probe_render(surfels, camera, dataclass_replace(settings, dof=False, lens_samples=1))
    seconds = (time.perf_counter() - t0) * samples
    print(f"dofsplat: {samples:,} lens samples at about {seconds / samples:.2f} s each: about "
          f"{format_duration(seconds)} (Ctrl-C stops it)", file=sys.stderr, flush=True)


def format_duration(seconds: float) -> str:
    """``45 s``, ``12 min``, ``3.4 h``, ``2.1 days``."""
    for limit, scale, unit in ((120, 1, "s"), (7200, 60, "min"), (172800, 3600, "h")):
        if seconds < limit:
            return f"{seconds / scale:.0f} {unit}" if unit != "h" else f"{seconds / scale:.1f} h"
    return f"{seconds / 86400:.1f} days"


# -- camera, lens, settings --------------------------------------------------------------


def view_fov(args, width: int, height: int) -> float:
    """The vertical field of view (degrees) the options ask for: --fov, --frustum's, the
    lens's of --focal-length-mm on a --sensor-width-mm sensor focused at infinity (the
    final frame's narrows by focus breathing: ``photographic_frustum``), or the default."""
    if args.frustum is not None:
        left, right, bottom, top, near = args.frustum
        return math.degrees(2.0 * math.atan((top - bottom) / (2.0 * near)))
    if getattr(args, "focal_length_mm", None) is not None:
        sensor_height = args.sensor_width_mm * height / width
        return math.degrees(2.0 * math.atan(sensor_height / (2.0 * args.focal_length_mm)))
    return args.fov or DEFAULT_FOV_DEG


def framing_camera(args, lo, hi, width: int, height: int, up_hint=None, surfels=None):
    """``render``'s default camera. Its up axis is --up, else the loader's hint (a z-up scan,
    ``prep.pointcloud.ground_up``; a Gaussian scene's y down), else y. It looks from the
    model's most visible side among the four axis directions across the up axis
    (``most_visible_direction``: a surfel model's; a Gaussian scene, without a
    cameras.json, is seen from +z), and stands where the model's projection fills the
    frame (``fit_camera``); without ``surfels``, from +z (or -y when up is z) at a distance
    that keeps the bounding sphere [lo, hi] in view."""
    from ..camera import Camera
    from ..surfels import Surfels

    fov = view_fov(args, width, height)
    up = tuple(args.up or up_hint or (0.0, 1.0, 0.0))
    direction = default_direction(up)
    if surfels is None:
        return Camera.framing(lo, hi, width, height, fov, direction=direction, up=up)
    if not isinstance(surfels, Surfels):  # a Gaussian scene: its robust box's corners
        import itertools

        corners = [[(lo, hi)[k][axis] for axis, k in enumerate(c)]
                   for c in itertools.product((0, 1), repeat=3)]
        return fit_camera(corners, [0.0] * 8, lo, hi, width, height, fov, direction, up)
    direction = most_visible_direction(surfels, lo, hi, fov, width, height, up, direction)
    return fit_camera(surfels.positions, surfels.radius, lo, hi, width, height, fov,
                      direction, up)


def default_direction(up) -> tuple:
    """Where the camera stands, seen from the model, before any choice: +z, or -y when up
    is (nearly) the z axis (a z-up scan seen from the front)."""
    if abs(up[2]) > 0.9 * math.hypot(*up):
        return (0.0, -1.0, 0.0)
    return (0.0, 0.0, 1.0)


# the direction choice renders at most surfels.VIEW_SAMPLE surfels (a random sample, each
# disk widened to keep the area they cover) into a frame of VISIBILITY_SIZE pixels
VISIBILITY_SIZE = 64
VISIBILITY_MARGIN = 1.05  # another side must show 5 % more surface to replace the default


def most_visible_direction(surfels, lo, hi, fov: float, width: int, height: int, up,
                           default) -> tuple:
    """Of the four directions across ``up`` (``default`` first, then turned by 90 degrees
    about up), the one from which a small pinhole render of the model, backfaces culled,
    covers the most pixels: its most visible side (a cow from its flank, a scan from the side
    it was scanned from). All four are framed alike (the bounding sphere), so that covered
    pixels compare areas; another side must cover VISIBILITY_MARGIN times the default's."""
    import numpy as np

    from ..camera import Camera
    from ..frame import RenderSettings

    u = np.asarray(up, float) / np.linalg.norm(up)
    d0 = np.asarray(default, float) - np.dot(default, u) * u
    if np.linalg.norm(d0) < 1e-6:  # --up along the default direction: any other across it
        d0 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    d0 /= np.linalg.norm(d0)
    d1 = np.cross(u, d0)
    candidates = [d0, d1, -d0, -d1]
    sample = visibility_sample(surfels)
    w = VISIBILITY_SIZE
    h = max(8, round(w * height / width))
    settings = RenderSettings(dof=False, lod=False, shading="none", cull_backfaces=True)
    covered = []
    for d in candidates:
        camera = Camera.framing(lo, hi, w, h, fov, direction=tuple(d), up=tuple(u))
        result = probe_render(sample, camera, settings)
        covered.append(int(np.count_nonzero(np.isfinite(result.depth))))
    best = int(np.argmax(covered))
    if covered[best] <= VISIBILITY_MARGIN * covered[0]:
        best = 0
    return tuple(float(v) for v in candidates[best])


def visibility_sample(surfels):
    """At most VIEW_SAMPLE of the surfels, drawn at random (seeded; ``Surfels.sample``),
    their disks widened by sqrt(N / n) so that the sample covers the surface the model does."""
    import numpy as np

    from ..surfels import VIEW_SAMPLE

    n = len(surfels)
    sample = surfels.sample(VIEW_SAMPLE)
    if len(sample) == n:
        return sample
    grow = np.float32(math.sqrt(n / VIEW_SAMPLE))
    from dataclasses import replace

    return replace(sample, radius=sample.radius * grow,
                   radius_v=None if sample.radius_v is None else sample.radius_v * grow)


FILL = 0.92  # the model's projection spans this fraction of the frame's limiting side
FIT_CHUNK = 1 << 20  # fit_camera reads the disks this many at a time


def fit_camera(positions, radius, lo, hi, width: int, height: int, fov: float, direction,
               up):
    """A camera looking along -``direction`` with vertical field of view ``fov``, placed so
    that the projection of the disks (``positions`` (N, 3), ``radius`` (N,)) spans FILL of
    the frame on its tighter side, centred: the eye's lateral offset and distance are the
    smallest that keep every disk in the frustum (each disk a point of depth z, lateral
    x +- r, must satisfy |x - c_x| + r <= tan(fov_x / 2) FILL (E - z), a max of linear
    functions, minimised in closed form). Its target is on the view axis, at the depth of
    the bounding box's centre (what --orbit turns about)."""
    import numpy as np

    from ..camera import Camera
    from ..io.model_file import read_rows

    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    right = np.cross(-d, np.asarray(up, float))
    right /= np.linalg.norm(right)
    true_up = np.cross(right, -d)
    centre = 0.5 * (np.asarray(lo, np.float64) + np.asarray(hi, np.float64))
    ty = math.tan(math.radians(fov) / 2.0) * FILL
    tx = ty * width / height
    # the maxima over the disks, a chunk of rows at a time (a stored model's positions are a
    # memory map: read once through its file, never held as float64 copies)
    top = np.full(6, -np.inf)  # far_x, near_x, far_y, near_y, z, r
    for i in range(0, max(len(positions), 1), FIT_CHUNK):
        p = np.asarray(read_rows(positions, i, i + FIT_CHUNK), np.float64) - centre
        r = np.asarray(read_rows(radius, i, i + FIT_CHUNK), np.float64)
        if not len(p):
            continue
        x, y, z = p @ right, p @ true_up, p @ d
        top = np.maximum(top, [np.max(z + (x + r) / tx), np.max(z + (r - x) / tx),
                               np.max(z + (y + r) / ty), np.max(z + (r - y) / ty),
                               z.max(), r.max()])

    def side(far, near, t):  # (lateral centre, eye distance) that fit the coordinates
        return 0.5 * t * (far - near), 0.5 * (far + near)

    cx, ex = side(top[0], top[1], tx)
    cy, ey = side(top[2], top[3], ty)
    extent = max(float(np.linalg.norm(np.asarray(hi, float) - lo)), float(max(top[5], 0.0)),
                 1e-9)
    eye_z = max(ex, ey, float(top[4]) + 0.05 * extent)  # nothing at the eye
    lateral = centre + cx * right + cy * true_up
    eye = lateral + eye_z * d
    target = lateral  # depth 0: the box's centre
    return Camera(eye=tuple(float(v) for v in eye), target=tuple(float(v) for v in target),
                  up=tuple(float(v) for v in up), width=width, height=height, fov_y=fov,
                  near=eye_z * 1e-4)


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
    """The median camera depth of the surfels in front of the camera."""
    import numpy as np

    forward = np.subtract(camera.target, camera.eye)
    forward = forward / np.linalg.norm(forward)
    depth = (surfels.positions.astype(np.float64) - camera.eye) @ forward
    depth = depth[depth > 0]
    return float(np.median(depth)) if depth.size else math.dist(camera.eye, camera.target)


FOCUS_PROBE_SIZE = 128  # pixels on the longer side of the default focus's pinhole render


def centre_focus(surfels, camera, settings) -> tuple[float, str]:
    """The default focus: (distance, where it came from). The depth of the surface seen at
    the image centre in a small pinhole render (the median of the centre's 3 x 3 pixels
    that see a surface), else the median depth of all the surface that render sees, else
    (an empty frame) the median depth of the model's points in front of the camera."""
    import numpy as np

    probe = small_camera(camera, FOCUS_PROBE_SIZE)
    pinhole = dataclass_replace(settings, dof=False, show_lod=False, lens_samples=1)
    # the centre's pixels first, through a window of the probe's frustum (its own pixels,
    # its LOD cut near the centre's rays: a large scan's whole probe frame read 1.5 GB of
    # its file), the whole probe frame only where they see nothing
    h, w = probe.height, probe.width
    x0, y0 = max(0, w // 2 - 1), max(0, h // 2 - 1)
    depth = probe_render(surfels, window_camera(probe, x0, y0, min(w, w // 2 + 2) - x0,
                                                min(h, h // 2 + 2) - y0), pinhole).depth
    centre = depth[np.isfinite(depth)]
    if centre.size:
        return float(np.median(centre)), "the surface at the image centre"
    depth = probe_render(surfels, probe, pinhole).depth
    seen = depth[np.isfinite(depth)]
    if seen.size:
        return float(np.median(seen)), "the median depth of the visible surface"
    return median_depth(surfels, camera), "the median depth of the model"


def probe_render(surfels, camera, settings):
    """A pinhole render that only chooses the view or the focus: its warnings (a model too
    large for float32, say) are the frame's own to give, once."""
    import warnings

    import numpy as np

    from ..render import render

    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        return render(surfels, camera, None, settings)


def dataclass_replace(obj, **changes):
    import dataclasses

    return dataclasses.replace(obj, **changes)


def small_camera(camera, longest: int):
    """``camera`` at most ``longest`` pixels on its longer side, seeing the same view (a
    frustum is widened about its centre to the small frame's aspect)."""
    scale = min(1.0, longest / max(camera.width, camera.height))
    if scale == 1.0:
        return camera
    width = max(1, round(camera.width * scale))
    height = max(1, round(camera.height * scale))
    frustum = camera.frustum
    if frustum is not None:
        left, right, bottom, top, near = frustum
        middle, half = 0.5 * (left + right), 0.5 * (top - bottom) * width / height
        frustum = (middle - half, middle + half, bottom, top, near)
    return dataclass_replace(camera, width=width, height=height, frustum=frustum)


def window_camera(camera, x0: int, y0: int, width: int, height: int):
    """The pixels [x0, x0 + width) x [y0, y0 + height) of ``camera``'s frame as a camera of
    their own: the same eye and view, the frustum cut to them (pixel (i, j) of it is pixel
    (x0 + i, y0 + j) of the frame, to float rounding)."""
    left, right, bottom, top, near = camera.frustum_lrbtn()
    sx, sy = (right - left) / camera.width, (top - bottom) / camera.height
    frustum = (left + x0 * sx, left + (x0 + width) * sx, top - (y0 + height) * sy,
               top - y0 * sy, near)
    return dataclass_replace(camera, width=width, height=height, frustum=frustum)


def camera_from_args(args, base):
    """``base`` (the framing or the scene's camera) with the user's options applied."""
    from ..camera import Camera

    # the base's own frustum (a capture's) holds unless the user gives a view
    new_view = args.fov or getattr(args, "focal_length_mm", None)
    frustum = args.frustum if args.frustum is not None else (None if new_view else base.frustum)
    fov = (view_fov(args, base.width, base.height) if new_view
           else base.fov_y or DEFAULT_FOV_DEG)
    return Camera(eye=args.eye or base.eye, target=args.target or base.target,
                  up=args.up or base.up, width=base.width, height=base.height,
                  fov_y=fov, frustum=frustum, near=base.near)


def focal_length(args) -> float | None:
    """The lens's focal length F in world units: --focal-length, or --focal-length-mm in
    metres over --scene-scale (metres per world unit), as ``camera.photographic`` takes it."""
    if getattr(args, "focal_length_mm", None) is not None:
        return args.focal_length_mm / 1000.0 / args.scene_scale
    return args.focal_length


def photographic_camera(args, camera, focus: float):
    """With --focal-length-mm: ``camera`` with the frustum of ``camera.photographic``, the
    sensor (--sensor-width-mm wide) at the image distance V_p = F P / (P - F) of the lens
    focused at P = ``focus`` (focus breathing: the field of view of a lens focused there, so
    that the CoC in pixels is the CoC on the sensor times W / sensor width). Else
    ``camera`` as it is."""
    if getattr(args, "focal_length_mm", None) is None:
        return camera
    f = focal_length(args)
    sensor = args.sensor_width_mm / 1000.0 / args.scene_scale
    v_p = f * focus / (focus - f)  # (the lens checked that P > F)
    near = camera.near if camera.frustum is None else camera.frustum[4]
    right = near * (sensor / 2.0) / v_p
    top = right * camera.height / camera.width
    return dataclass_replace(camera, frustum=(-right, right, -top, top, near))


def lens_from_args(args, focus: float, default_aperture: float):
    """The thin lens from --aperture, or a focal length (--focal-length, --focal-length-mm)
    with --f-number, or the default diameter."""
    from ..camera import ThinLens

    shape = {"bokeh": getattr(args, "bokeh", "disc"), "blades": getattr(args, "blades", 0),
             "blade_rotation": getattr(args, "blade_rotation", 0.0)}
    if args.f_number is not None:
        return ThinLens(focus_distance=focus, focal_length=focal_length(args),
                        f_number=args.f_number, **shape)
    aperture = args.aperture if args.aperture is not None else default_aperture
    return ThinLens(focus_distance=focus, aperture=aperture, focal_length=focal_length(args),
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
                          lens_parts=getattr(args, "lens_parts", "everywhere"),
                          coarse_blur_px=getattr(args, "coarse_blur", RenderSettings.coarse_blur_px),
                          sharp_visibility=getattr(args, "sharp_visibility", False))


def check_arguments(args) -> None:
    """Mistakes in combinations of options, found before any loading or rendering."""
    mm = getattr(args, "focal_length_mm", None)
    if mm is not None:
        for flag, given in (("--focal-length", args.focal_length), ("--fov", args.fov),
                            ("--frustum", args.frustum)):
            if given is not None:
                raise DofsplatError(f"--focal-length-mm sets the field of view and the focal "
                                    f"length: drop {flag}")
    else:
        for flag, name in (("--sensor-width-mm", "sensor_width_mm"),
                           ("--scene-scale", "scene_scale")):
            if getattr(args, name, None) is not None:
                raise DofsplatError(f"{flag} goes with --focal-length-mm")
    if mm is not None:
        args.sensor_width_mm = args.sensor_width_mm or DEFAULT_SENSOR_WIDTH_MM
        args.scene_scale = args.scene_scale or 1.0
    if args.f_number is not None and args.focal_length is None and mm is None:
        raise DofsplatError("--f-number needs --focal-length or --focal-length-mm (the lens "
                            "diameter is F / n)")
    if (args.focal_length is not None and args.f_number is None and args.aperture is None
            and not args.no_dof):
        raise DofsplatError("--focal-length needs --f-number (or give the lens diameter "
                            "with --aperture)")
    f = focal_length(args)
    if args.focus is not None and f is not None and args.focus <= f:
        raise DofsplatError(f"the focus distance {args.focus:g} must exceed the focal length "
                            f"{f:g} (a lens cannot focus nearer than F)")
    if args.frustum is not None:
        left, right, bottom, top, near = args.frustum
        if not (left < right and bottom < top and near > 0):
            raise DofsplatError(f"--frustum needs L < R, B < T and N > 0, got "
                                f"{' '.join(f'{v:g}' for v in args.frustum)}")
    if args.focus_at is not None:
        width, height = frame_size(args)
        x, y = args.focus_at
        if not (0 <= x < width and 0 <= y < height):
            raise DofsplatError(f"--focus-at pixel ({x:g}, {y:g}) lies outside the "
                                f"{width}x{height} image")
    if getattr(args, "device", "cpu") != "cpu":
        from ..backends import resolve_device

        # --device cuda without a working GPU stops here, before any loading or writing;
        # auto falls back to the CPU with one warning
        args.device = resolve_device(args.device, flag="--device")


def frame_size(args) -> tuple[int, int]:
    """The size the frame will have, known before loading: --size; the demo scene's; a depth
    capture's own (a PCD's organised WIDTH x HEIGHT, or a surfel PLY that recorded one),
    which ``render`` keeps unless a camera option frames the model instead
    (``render.model_view``); else ``render``'s default."""
    if args.size:
        return tuple(args.size)
    if args.command == "demo" or getattr(args, "demo", False):
        return DEFAULT_SIZE["demo"]
    placed = any(getattr(args, a, None) is not None
                 for a in ("eye", "target", "up", "fov", "frustum", "focal_length_mm"))
    if not placed and getattr(args, "input", None):
        size = capture_size(Path(args.input))
        if size is not None:
            return size
    return DEFAULT_SIZE["render"]


def capture_size(path: Path) -> tuple[int, int] | None:
    """A depth capture's pixel size from its header alone, or None (not a capture, or a
    file the loader will report on)."""
    name = path.name.lower()
    try:
        if name.endswith(".pcd"):
            from ..io.pcd import _HEADER_MAX, parse_pcd_header

            with open(path, "rb") as f:
                header = parse_pcd_header(f.read(_HEADER_MAX), str(path))
            return (header.width, header.height) if header.height > 1 else None
        if name.endswith((".ply", ".ply.gz")):
            from ..io.ply import VIEW_COMMENT, read_ply_header

            for line in read_ply_header(path).comments:
                words = line.split()
                if words[:3] == VIEW_COMMENT.split() + ["capture.size"] and len(words) == 5:
                    return int(float(words[3])), int(float(words[4]))
    except (DofsplatError, OSError, ValueError):
        return None
    return None


# -- the first run's compile notice ------------------------------------------------------

_ANNOUNCED = []  # once per process


def announce_compiling(args, model=None) -> None:
    """Say so before a command compiles numba kernels (a first run, or a new version), with
    the measured time: the renderer's (``backends.cpu.kernels_compiled``), and a point
    cloud's or a mesh's preparation kernels (``prep.kernels_compiled``) when ``model`` will
    be prepared rather than read from the cache of prepared models. Called before loading
    (``render.load_model``) or building the demo scene, so that the notice comes within a
    second or two of the start rather than after the preparation that compiles."""
    if getattr(args, "quiet", False) or _ANNOUNCED:
        return
    from .. import prep as preparation
    from ..backends import cpu, cpu_gauss

    names, seconds = [], 0
    prep = None if model is None else model_preparation(args, model)
    if model is not None and gaussian_scene(model):  # its own kernels, on the CPU
        if not cpu_gauss.kernels_compiled():
            names.append("Gaussian rendering")
            seconds += cpu_gauss.COMPILE_SECONDS
    # the preparation's normalisation renders on the CPU, whatever --device says
    elif ((getattr(args, "device", "cpu") == "cpu" or prep is not None)
            and not cpu.kernels_compiled()):
        names.append("rendering")
        seconds += cpu.COMPILE_SECONDS
    if prep is not None and not preparation.kernels_compiled(prep) \
            and not prepared_in_cache(args, model):
        names.append(prep)
        seconds += preparation.PREP_COMPILE_SECONDS[prep]
    if not names:
        return
    _ANNOUNCED.append(True)
    print(f"dofsplat: compiling the {' and '.join(names)} kernels, once (about {seconds} s "
          "on 2 cores; numba keeps them for later runs)", file=sys.stderr, flush=True)


def gaussian_scene(model) -> bool:
    """Whether the model file is a 3D Gaussian Splatting scene (``io.model_options``)."""
    from ..io import model_options

    return "Gaussian Splatting" in model_options(model)[0]


def model_preparation(args, model) -> str | None:
    """What loading ``model`` prepares: "point-cloud" (normals, radii), "mesh" (sampling),
    or None (a surfel file or a Gaussian scene, taken as stored). Raises the loader's
    DofsplatError for a missing file or an unknown format."""
    from ..io import model_options

    _, accepted = model_options(model)
    if "k" in accepted:
        return "point-cloud"
    if "points" in accepted:
        return "mesh"
    return None


def prepared_in_cache(args, model) -> bool:
    """Whether the cache of prepared models holds ``model`` with these options (then it is
    read back, and nothing is prepared)."""
    from .. import cache
    from ..io import LOADERS, prepared
    from .options import loader_options, prep_cache

    if prep_cache(args) == "off" or not cache.enabled():
        return False
    path = Path(model)
    name = path.name.lower()
    ext = max((e for e in LOADERS if name.endswith(e)), key=len, default=None)
    if ext is None:
        return False
    try:
        key = prepared.cache_key(path, LOADERS[ext], loader_options(args))
        return (cache.cache_folder("surfels") / f"{key}.npz").is_file()
    except (DofsplatError, OSError):
        return False


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
        "lens_parts": settings.lens_parts, "coarse_blur_px": settings.coarse_blur_px,
        "sharp_visibility": settings.sharp_visibility,
    }
    record["files"] = {"input": getattr(args, "input", None),
                       **{role: str(p) for role, p in outputs.items()}}
    # one line per key; lists of numbers stay on one line
    text = re.sub(r"\[\s+([^\[\]{}]*?)\s+\]",
                  lambda m: "[" + " ".join(m[1].split()) + "]",
                  json.dumps(record, indent=2)) + "\n"
    atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def summary(paths: list[Path], stats: dict, focus: str = "") -> str:
    """``wrote demo.png (800x600, 337,807 points, 261,301 splats, 30.9M fragments, 0.90 s)``,
    the lens's parts where a frame drew more than one (``..., 4 lens parts, ...``: a Gaussian
    scene's default, more under a lens wide against its focus distance), the focus where
    dofsplat chose it (``..., 0.90 s, focused at 1.93 (the surface at the image centre)``:
    ``focus_note``), and for a model file how long loading took: ``...; model loaded in
    6.1 s`` or ``...; model from the cache in 0.02 s``."""
    samples = (f"{stats['samples']} lens sample{'s' * (stats['samples'] != 1)}, "
               if "samples" in stats else "")
    if stats.get("lens_samples", 1) > 1:
        samples += f"{stats['lens_samples']} lens parts, "
    load = ""
    if "load_ms" in stats:
        how = "from the cache in" if stats["load_from_cache"] else "loaded in"
        load = f"; model {how} {stats['load_ms'] / 1000:.2f} s"
    return (f"wrote {', '.join(str(p) for p in paths)} ({stats['width']}x{stats['height']}, "
            f"{stats['points_in']:,} points, {stats['splats_rendered']:,} splats, "
            f"{samples}{format_count(stats['fragments'])} fragments, "
            f"{stats['total_ms'] / 1000:.2f} s{', ' + focus if focus else ''}{load})")


def format_count(n: int) -> str:
    """A count for the summary line: 9,999 as is, then 10.0k, 466.3k, 20.9M, 6.2G."""
    for threshold, scale, suffix in ((1e9, 1e9, "G"), (1e6, 1e6, "M"), (1e4, 1e3, "k")):
        if n >= threshold:
            return f"{n / scale:.1f}{suffix}"
    return f"{n:,}"
