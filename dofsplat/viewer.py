"""The browser viewer (``dofsplat view``): our depth of field, live, in viser's web viewer.

viser (nerfstudio's viewer library) serves a 3-D page: the user orbits, pans and zooms its
camera, and this module renders that camera with dofsplat and sends the frame back as the
page's background image, with its depth so that viser's own overlays sit in it. Each
browser tab (a viser client) has its own controls and one render thread:

* while the camera moves, frames are rendered at a quarter of the resolution (and the LOD
  cut that goes with it, at the paper's coarser stop, ``MOVING_LOD_BLUR_FRACTION``, without
  the finer cut for textured nodes); when
  it has been still for ``SETTLE_S`` the full-resolution
  frame follows (``Refinement``); only the latest camera is ever rendered, never a queue;
* a click on the model sets "Focus distance" to the depth seen under the cursor in the last
  frame (``depth_at``), eased over ``FOCUS_PULL_S`` like a focus pull (``FocusPull``); a
  click on the background says so and changes nothing;
* "Save image" writes the full-resolution frame (PNG) and a JSON of the camera and lens,
  with the ``dofsplat render`` command that draws the same picture.

The camera mapping (``camera_from_pose``, ``pose_from_camera``): viser's camera is a
position and a rotation whose columns are the camera's x (right), y (down) and z (forward)
axes in world coordinates (OpenCV's convention), with a vertical field of view in radians;
dofsplat's is a look-at camera (eye, target, up).
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .camera import Camera, ThinLens
from .errors import DofsplatError
from .frame import RenderSettings
from .surfels import Surfels

SETTLE_S = 0.3  # the camera still this long: render the full-resolution frame
MOVING_LOD_BLUR_FRACTION = 1.0  # the LOD stop of the frames drawn while the camera moves
MOVING_SCALE = 0.25  # resolution while the camera moves, x the chosen scale
FOCUS_PULL_S = 0.15  # a click's focus change is eased over this long
MAX_WIDTH = 1920  # frames wider than this (a large window) are rendered at this width
FAR_DEPTH = 1e6  # empty pixels' depth for viser (its depth map has no infinity)


# -- the camera mapping ----------------------------------------------------------------------


def camera_from_pose(position, wxyz, fov_y: float, width: int, height: int,
                     near: float = 1e-3) -> Camera:
    """dofsplat's look-at camera for viser's pose: ``position`` (3,), ``wxyz`` the unit
    quaternion of the camera's rotation (columns: right, down, forward), ``fov_y`` the
    vertical field of view in radians; the image is ``width`` x ``height`` pixels."""
    rot = _matrix(wxyz)
    forward, down = rot[:, 2], rot[:, 1]
    eye = np.asarray(position, np.float64)
    return Camera(eye=tuple(eye), target=tuple(eye + forward), up=tuple(-down), width=width,
                  height=height, fov_y=math.degrees(fov_y), near=near)


def pose_from_camera(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(position, wxyz) of viser's camera that sees what ``camera`` sees."""
    eye = np.asarray(camera.eye, np.float64)
    forward = np.subtract(camera.target, eye)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, camera.up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return eye, _quaternion(np.stack([right, down, forward], axis=1))


def depth_at(depth: np.ndarray, screen_pos) -> float | None:
    """The depth (H, W; camera depth along the view axis, inf where empty) under a click at
    ``screen_pos`` (x, y in 0..1 from the top-left corner, viser's), or None on background."""
    h, w = depth.shape
    x = min(max(int(screen_pos[0] * w), 0), w - 1)
    y = min(max(int(screen_pos[1] * h), 0), h - 1)
    d = float(depth[y, x])
    return d if math.isfinite(d) and d > 0 else None


# -- the state of one tab, without threads -----------------------------------------------


class Refinement:
    """Which frame to render next: low resolution while the camera moves, the full one once
    it has been still for SETTLE_S, nothing when the latest is on screen. ``moved(t)`` on a
    camera or control change, ``next(t)`` -> "low", "high" or None, ``done(kind)`` after."""

    def __init__(self):
        self.last_change = -math.inf
        self.pending = "high"  # the first frame: full resolution
        self.shown = None

    def moved(self, t: float) -> None:
        self.last_change = t
        self.pending = "low"

    def next(self, t: float):
        if self.pending == "low":
            return "low"
        if self.pending == "high":
            return "high"
        if self.shown == "low" and t - self.last_change >= SETTLE_S:
            return "high"
        return None

    def done(self, kind: str) -> None:
        self.shown = kind
        if self.pending == kind or kind == "high":
            self.pending = None


@dataclass
class FocusPull:
    """The focus distance eased from ``start`` to ``end`` over FOCUS_PULL_S (smoothstep)."""

    start: float
    end: float
    t0: float

    def value(self, t: float) -> float:
        u = min(max((t - self.t0) / FOCUS_PULL_S, 0.0), 1.0)
        return self.start + (self.end - self.start) * u * u * (3.0 - 2.0 * u)

    def finished(self, t: float) -> bool:
        return t - self.t0 >= FOCUS_PULL_S


# -- the server ------------------------------------------------------------------------------


def view(surfels: Surfels, camera: Camera | None = None, lens: ThinLens | None = None,
         settings: RenderSettings | None = None, port: int = 8080, host: str = "0.0.0.0",
         open_browser: bool = True, log=None, block: bool = True):
    """Serve ``surfels`` in the browser viewer (module docstring) until Ctrl-C (or return the
    server at once with ``block=False``). camera: the first view (default: the model framed
    from +z); lens: the first lens (default: focused on the target, diameter 0.1 x the
    model's half diagonal); settings: the rendering settings (LOD, bokeh, device)."""
    try:
        import viser
    except ImportError:
        raise DofsplatError("the viewer needs viser: pip install 'dofsplat[view]'") from None
    lo, hi = surfels.view_bounds()
    half_diagonal = 0.5 * float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    camera = camera or Camera.framing(lo, hi, 800, 600, 40.0)
    lens = lens or ThinLens(focus_distance=math.dist(camera.eye, camera.target),
                            aperture=0.1 * half_diagonal)
    settings = settings or RenderSettings()
    log = log or (lambda m: print(f"dofsplat: {m}", file=sys.stderr, flush=True))
    try:
        server = viser.ViserServer(host=host, port=port, verbose=False)
    except OSError as e:
        raise DofsplatError(f"cannot serve on {host}:{port}: {e}") from None
    server.scene.set_up_direction(tuple(camera.up))
    sessions = {}

    @server.on_client_connect
    def _(client) -> None:
        sessions[client.client_id] = _Session(client, surfels, camera, lens, settings,
                                              half_diagonal, log)

    @server.on_client_disconnect
    def _(client) -> None:
        session = sessions.pop(client.client_id, None)
        if session is not None:
            session.stop()

    address = f"http://{'localhost' if host in ('0.0.0.0', '::') else host}:{server.get_port()}"
    print(f"dofsplat: viewer at {address} (Ctrl-C stops it)", file=sys.stderr, flush=True)
    if open_browser:
        import webbrowser

        webbrowser.open(address)
    if not block:
        return server
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        for session in list(sessions.values()):
            session.stop()
        server.stop()
    return server


class _Session:
    """One browser tab: its controls, its camera and its render thread."""

    def __init__(self, client, surfels, camera, lens, settings, half_diagonal, log):
        self.client, self.surfels, self.settings, self.log = client, surfels, settings, log
        self.base_camera = camera
        self.lock = threading.Condition()
        self.state = Refinement()
        self.pull = None
        self.depth = None  # the last frame's depth, for clicks
        self.running = True
        gui = client.gui
        self.focus = gui.add_number("Focus distance", float(lens.focus_distance), min=1e-6,
                                    step=0.01 * half_diagonal,
                                    hint="scene units along the view axis; click the model "
                                         "to focus where you click")
        self.aperture = gui.add_number("Lens diameter", float(lens.diameter), min=0.0,
                                       step=0.01 * half_diagonal,
                                       hint="scene units; 0 is a pinhole")
        self.focal = gui.add_number("Focal length", float(lens.focal_length or 0.0), min=0.0,
                                    step=0.001 * half_diagonal,
                                    hint="with f-number: lens diameter = F / n (0: unused)")
        self.f_number = gui.add_number("f-number", 0.0, min=0.0, step=0.1,
                                       hint="with focal length, sets the lens diameter "
                                            "(0: use Lens diameter)")
        self.bokeh = gui.add_dropdown("Bokeh", ("disc", "gaussian"), initial_value=lens.bokeh)
        self.blades = gui.add_number("Blades", int(lens.blades), min=0, max=16, step=1)
        self.lod = gui.add_checkbox("LOD", settings.lod)
        self.show_lod = gui.add_checkbox("Show LOD", settings.show_lod)
        self.scale = gui.add_slider("Resolution scale", 0.25, 1.0, 0.05, 1.0)
        self.save = gui.add_button("Save image")
        self.status = gui.add_markdown("")
        for handle in (self.focus, self.aperture, self.focal, self.f_number, self.bokeh,
                       self.blades, self.lod, self.show_lod, self.scale):
            handle.on_update(lambda _: self.changed())
        self.save.on_click(lambda _: self.save_image())
        client.scene.on_click()(self.clicked)
        position, wxyz = pose_from_camera(camera)
        with client.atomic():  # the first view: the command line's camera
            client.camera.position = tuple(position)
            client.camera.wxyz = tuple(wxyz)
            client.camera.fov = math.radians(camera.fov_y or 40.0)
        client.camera.on_update(lambda _: self.changed())
        self.thread = threading.Thread(target=self.loop, daemon=True,
                                       name=f"dofsplat-view-{client.client_id}")
        self.thread.start()

    # the controls and the camera

    def changed(self) -> None:
        with self.lock:
            self.state.moved(time.monotonic())
            self.lock.notify()

    def clicked(self, event) -> None:
        depth = self.depth
        d = None if depth is None else depth_at(depth, event.screen_pos)
        if d is None:
            self.client.add_notification("Nothing here", "Click on the model to focus on it: "
                                         "there is only background under the cursor.",
                                         auto_close_seconds=3.0)
            return
        with self.lock:
            self.pull = FocusPull(float(self.focus.value), d, time.monotonic())
            self.lock.notify()
        self.log(f"focus on the surface under the click: {d:.6g} (pixel "
                 f"{event.screen_pos[0]:.3f}, {event.screen_pos[1]:.3f} of the frame)")

    def current(self, kind: str):
        """(camera, lens, settings) of the frame to render now."""
        cam = self.client.camera
        scale = float(self.scale.value) * (MOVING_SCALE if kind == "low" else 1.0)
        width = max(16, int(cam.image_width or 800))
        height = max(16, int(cam.image_height or 600))
        factor = min(scale, MAX_WIDTH / width)
        w, h = max(8, round(width * factor)), max(8, round(height * factor))
        camera = camera_from_pose(cam.position, cam.wxyz, cam.fov, w, h)
        focus = max(float(self.focus.value), 1e-6)
        shape = {"bokeh": self.bokeh.value, "blades": _blades(self.blades.value)}
        if float(self.f_number.value) > 0 and float(self.focal.value) > 0:
            lens = ThinLens(focus_distance=max(focus, 1.0001 * float(self.focal.value)),
                            focal_length=float(self.focal.value),
                            f_number=float(self.f_number.value), **shape)
        else:
            lens = ThinLens(focus_distance=focus, aperture=max(float(self.aperture.value), 0.0),
                            **shape)
        settings = replace(self.settings, lod=bool(self.lod.value),
                           show_lod=bool(self.show_lod.value) and bool(self.lod.value))
        if kind == "low":
            # while the camera moves: the paper's coarser LOD stop (docs/maths.md, "The
            # stop's margin"), every node drawn ("The smallest nodes") and no finer cut for
            # textured nodes ("A finer cut where the texture needs it"), together 1.6-1.8x
            # cheaper at Table 1's largest aperture (bench/RESULTS.md); the still frame
            # keeps the settings' own
            settings = replace(settings, lod_blur_fraction=max(settings.lod_blur_fraction,
                                                               MOVING_LOD_BLUR_FRACTION),
                               lod_color_tolerance=math.inf, lod_min_node=2)
        return camera, lens, settings

    # the render thread

    def loop(self) -> None:
        from .io import linear_to_srgb
        from .render import render

        while self.running:
            with self.lock:
                now = time.monotonic()
                if self.pull is not None:
                    self.focus.value = self.pull.value(now)
                    if self.pull.finished(now):
                        self.pull = None
                    self.state.moved(now)
                kind = self.state.next(now)
                if kind is None:
                    self.lock.wait(timeout=0.05)
                    continue
            try:
                camera, lens, settings = self.current(kind)
                result = render(self.surfels, camera, lens, settings)
            except Exception as e:  # noqa: BLE001 - said in the panel; the thread goes on
                self.status.content = f"**Cannot render:** {e}"
                if not isinstance(e, DofsplatError):
                    self.log(f"render failed: {type(e).__name__}: {e}")
                with self.lock:
                    self.state.done(kind)
                continue
            rgb = (np.clip(linear_to_srgb(np.clip(result.image[..., :3], 0, 1)), 0, 1) * 255
                   ).astype(np.uint8)
            depth = np.where(np.isfinite(result.depth), result.depth, FAR_DEPTH)
            self.client.scene.set_background_image(rgb, format="png",
                                                   depth=depth.astype(np.float32))
            self.depth = result.depth
            self.status.content = (f"{camera.width}x{camera.height}, "
                                   f"{result.stats['total_ms']:.0f} ms"
                                   + (" (moving: reduced)" if kind == "low" else ""))
            with self.lock:
                self.state.done(kind)
            if kind == "high":
                self.log(f"frame {camera.width}x{camera.height} sent, focus "
                         f"{lens.focus_distance:.6g}")

    def stop(self) -> None:
        self.running = False
        with self.lock:
            self.lock.notify()

    def save_image(self) -> None:
        from .io import write_image
        from .render import render

        camera, lens, settings = self.current("high")
        stamp = time.strftime("%Y%m%d-%H%M%S")
        png, meta = Path(f"view-{stamp}.png"), Path(f"view-{stamp}.json")
        result = render(self.surfels, camera, lens, settings)
        write_image(png, result.image)
        record = {"camera": {"eye": list(camera.eye), "target": list(camera.target),
                             "up": list(camera.up), "width": camera.width,
                             "height": camera.height, "fov_y_deg": camera.fov_y},
                  "lens": {"focus_distance": lens.focus_distance, "aperture": lens.diameter,
                           "bokeh": lens.bokeh, "blades": lens.blades},
                  "settings": {"lod": settings.lod, "show_lod": settings.show_lod},
                  "render_options": render_options(camera, lens, settings)}
        meta.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
        self.client.add_notification("Saved", f"{png} and {meta}", auto_close_seconds=4.0)
        self.log(f"wrote {png}, {meta}")


def render_options(camera: Camera, lens: ThinLens, settings: RenderSettings) -> str:
    """The ``dofsplat render MODEL`` options that draw this camera and lens."""
    def num(x) -> str:  # no exponent: argparse reads "-1e-05" as an option
        text = f"{x:.9g}"
        return text if "e" not in text else f"{x:.12f}".rstrip("0").rstrip(".")

    def v(xs):
        return " ".join(num(x) for x in xs)

    opts = [f"--size {camera.width}x{camera.height}", f"--eye {v(camera.eye)}",
            f"--target {v(camera.target)}", f"--up {v(camera.up)}", f"--fov {num(camera.fov_y)}",
            f"--focus {num(lens.focus_distance)}", f"--aperture {num(lens.diameter)}",
            f"--bokeh {lens.bokeh}"]
    if lens.blades:
        opts.append(f"--blades {lens.blades}")
    if not settings.lod:
        opts.append("--no-lod")
    if settings.show_lod:
        opts.append("--show-lod")
    return " ".join(opts)


def _blades(value) -> int:
    n = int(round(float(value)))
    return n if n == 0 or 5 <= n <= 16 else (0 if n < 5 else 16)


def _matrix(wxyz) -> np.ndarray:
    w, x, y, z = (float(c) for c in wxyz)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _quaternion(m: np.ndarray) -> np.ndarray:
    """wxyz of a rotation matrix (Shepperd's method: the largest diagonal term)."""
    t = np.trace(m)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return q / np.linalg.norm(q)
