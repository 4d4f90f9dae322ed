"""The browser viewer (``dofsplat view``): our depth of field, live, in viser's web viewer.

viser (nerfstudio's viewer library) serves a 3-D page: the user orbits, pans and zooms its
camera, and this module renders that camera with dofsplat and sends the frame back as the
page's background image, with its depth so that viser's own overlays sit in it. Each
browser tab (a viser client) has its own controls and one render thread:

* the page opens at once and says what the first frame waits for (the kernels compiling,
  once, in a thread while the model loads: ``Startup``, ``serve``);
* viser's camera orbits about the model: its look-at point is the focused surface on the
  view axis, or the depth of the model's centre (``orbit_point``), and a click moves it to
  the clicked depth;
* while the camera moves, frames are rendered at a quarter of the resolution (and the LOD
  cut that goes with it, at the paper's coarser stop, ``MOVING_LOD_BLUR_FRACTION``, without
  the finer cut for textured nodes, with the pixel stop at ``MOVING_PIXEL_THRESHOLD``);
  when it has been still for ``SETTLE_S`` the full-resolution frame follows
  (``Refinement``); only the latest camera is ever rendered, never a queue;
* a click on the model sets "Focus distance" to the depth seen under the cursor in the last
  frame (``depth_at``), eased over ``FOCUS_PULL_S`` like a focus pull (``FocusPull``); a
  click on the background says so and changes nothing;
* the panel shows the lens rendered: setting the focal length and f-number sets the lens
  diameter (F / n), and a value that gives no lens (a negative diameter, 3 blades, a focus
  nearer than F) is refused with a message and the last good value shown (``edit_lens``);
* "Save image" writes the full-resolution frame (PNG) and a JSON of the camera and lens,
  with the ``dofsplat render`` command that draws the same picture, into the folder the
  panel names (``--save-dir``, default the folder the server started in), and shows the
  full paths;
* it listens on 127.0.0.1 unless told otherwise, and a port check (a connection that sends
  no HTTP request) prints nothing (``silence_probes``).

A Gaussian scene (``Gaussians``) is served the same way, without the LOD controls.

The camera mapping (``camera_from_pose``, ``pose_from_camera``): viser's camera is a
position and a rotation whose columns are the camera's x (right), y (down) and z (forward)
axes in world coordinates (OpenCV's convention), with a vertical field of view in radians;
dofsplat's is a look-at camera (eye, target, up).
"""

from __future__ import annotations

import json
import logging
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
from .gaussians import Gaussians
from .surfels import Surfels

SETTLE_S = 0.3  # the camera still this long: render the full-resolution frame
MOVING_LOD_BLUR_FRACTION = 1.0  # the LOD stop of the frames drawn while the camera moves
MOVING_SCALE = 0.25  # resolution while the camera moves, x the chosen scale
MOVING_PIXEL_THRESHOLD = 2.0  # the LOD pixel stop (px) of the frames drawn while the camera moves
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


# -- the panel's lens: what it shows is what is rendered ------------------------------------


@dataclass(frozen=True)
class LensFields:
    """The lens as the panel shows it, which is the lens rendered (``lens()``).

    focus:    P, "Focus distance", world units along the view axis
    diameter: A, "Lens diameter", world units (0: a pinhole); F / n while both are set
    focal:    F, "Focal length", world units (0: unset)
    f_number: n, "f-number" (0: unset; needs F)
    bokeh:    "disc" or "gaussian"
    blades:   0 (round) or 5..16 straight blades (disc bokeh only)
    """

    focus: float
    diameter: float
    focal: float = 0.0
    f_number: float = 0.0
    bokeh: str = "disc"
    blades: int = 0

    @classmethod
    def of(cls, lens: ThinLens) -> "LensFields":
        return cls(float(lens.focus_distance), float(lens.diameter),
                   float(lens.focal_length or 0.0), float(lens.f_number or 0.0),
                   lens.bokeh, int(lens.blades))

    def lens(self) -> ThinLens:
        """The ThinLens these fields describe (DofsplatError where there is none)."""
        return ThinLens(focus_distance=self.focus, aperture=self.diameter,
                        focal_length=self.focal or None, bokeh=self.bokeh, blades=self.blades)


PANEL_NAMES = {"focus": "Focus distance", "diameter": "Lens diameter", "focal": "Focal length",
               "f_number": "f-number", "bokeh": "Bokeh", "blades": "Blades"}


def edit_lens(fields: LensFields, name: str, value) -> LensFields:
    """The panel's fields after the user sets field ``name`` to ``value``, with the fields
    that depend on it updated (A = F / n while F and n are set); DofsplatError, with the
    message to show, for a value that gives no lens to render (the caller keeps ``fields``)."""
    label = PANEL_NAMES[name]
    if name == "bokeh":
        new = replace(fields, bokeh=str(value))
    elif name == "blades":
        x = float(value)
        if not (math.isfinite(x) and x == round(x)):
            raise DofsplatError(f"Blades must be a whole number: 0 (round) or 5 to 16, got {value}")
        new = replace(fields, blades=int(x))
    else:
        x = float(value)
        if not math.isfinite(x):
            raise DofsplatError(f"{label} must be a number, got {value}")
        if name == "focus":
            if x <= 0:
                raise DofsplatError(f"Focus distance must be > 0, got {x:g}")
            new = replace(fields, focus=x)
        elif name == "diameter":
            if x < 0:
                raise DofsplatError(f"Lens diameter must be >= 0 (0 is a pinhole), got {x:g}")
            new = replace(fields, diameter=x)
            if fields.focal > 0 and fields.f_number > 0:  # n follows: n = F / A
                new = replace(new, f_number=fields.focal / x if x > 0 else 0.0)
        elif name == "focal":
            if x < 0:
                raise DofsplatError(f"Focal length must be >= 0 (0: unset), got {x:g}")
            new = replace(fields, focal=x, f_number=fields.f_number if x > 0 else 0.0)
            if x > 0 and fields.f_number > 0:
                new = replace(new, diameter=x / fields.f_number)
        else:  # f_number
            if x < 0:
                raise DofsplatError(f"f-number must be >= 0 (0: unset), got {x:g}")
            if x > 0 and fields.focal <= 0:
                raise DofsplatError("f-number needs a Focal length: set it first (the lens "
                                    "diameter is then F / n)")
            new = replace(fields, f_number=x)
            if x > 0:
                new = replace(new, diameter=fields.focal / x)
    new.lens()  # the lens's own checks: P > F, blades 0 or 5..16 with the disc bokeh
    return new


# -- the server ------------------------------------------------------------------------------


@dataclass
class Scene:
    """What the viewer serves: the model and the first view, lens and settings."""

    model: Surfels | Gaussians
    camera: Camera
    lens: ThinLens
    settings: RenderSettings


def default_scene(model, camera: Camera | None = None, lens: ThinLens | None = None,
                  settings: RenderSettings | None = None) -> Scene:
    """``model`` with the first view framed from +z, focused on its centre, and a lens
    diameter of 0.1 x its half diagonal, where not given."""
    lo, hi = model.view_bounds()
    half_diagonal = 0.5 * float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    camera = camera or Camera.framing(lo, hi, 800, 600, 40.0,
                                      up=getattr(model, "up_hint", None) or (0.0, 1.0, 0.0))
    lens = lens or ThinLens(focus_distance=math.dist(camera.eye, camera.target),
                            aperture=0.1 * half_diagonal)
    return Scene(model, camera, lens, settings or RenderSettings())


def orbit_point(camera: Camera, focus_distance: float, lo, hi) -> np.ndarray:
    """The point viser's camera orbits about (its look-at point): on the view axis at the
    focus distance where that lies in the model's box [lo, hi] (the focused surface), else
    at the depth of the box's centre, so that an orbit turns about the model (nerfstudio's
    viewer does the same); on the view axis, so that setting it keeps the view."""
    eye = np.asarray(camera.eye, np.float64)
    forward = np.subtract(camera.target, eye)
    forward /= np.linalg.norm(forward)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    margin = 0.05 * (hi - lo) + 1e-9
    focused = eye + forward * focus_distance
    if np.all(focused >= lo - margin) and np.all(focused <= hi + margin):
        return focused
    depth = float((0.5 * (lo + hi) - eye) @ forward)
    return eye + forward * (depth if depth > 0 else focus_distance)


def is_local(host: str) -> bool:
    """Whether ``host`` is a loopback address (only this machine can connect)."""
    return host in ("localhost", "::1") or host.startswith("127.")


class _ProbeFilter(logging.Filter):
    """Drops websockets' "opening handshake failed" for a connection that sent no valid
    HTTP request (a port check, a browser's speculative pre-connection): a 30-line
    traceback for nothing. Every other record passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        try:
            from websockets.exceptions import InvalidMessage
        except ImportError:  # pragma: no cover - viser depends on websockets
            return True
        return not isinstance(exc, InvalidMessage)


PROBE_FILTER = _ProbeFilter()


def silence_probes() -> None:
    """Install ``_ProbeFilter`` on the websockets server's loggers (once)."""
    for name in ("websockets.server", "websockets.asyncio.server", "websockets"):
        logger = logging.getLogger(name)
        if PROBE_FILTER not in logger.filters:
            logger.addFilter(PROBE_FILTER)


class Startup:
    """What the server waits for before the first frame (compiling the kernels, loading the
    model), said on every page within a moment of its opening and in the terminal."""

    def __init__(self, log):
        self.log = log
        self.lock = threading.Lock()
        self.steps: dict[str, str] = {}
        self.notes = []  # the pages' markdown elements that say it

    def text(self) -> str:
        return "**Please wait:** " + "  \n".join(self.steps.values()) if self.steps else ""

    def begin(self, step: str, message: str, say: bool = True) -> None:
        with self.lock:
            self.steps[step] = message
            self._show()
        if say:
            self.log(message)

    def end(self, step: str) -> None:
        with self.lock:
            self.steps.pop(step, None)
            self._show()

    def greet(self, client) -> None:
        """A page opened while waiting: it says what for."""
        with self.lock:
            self.notes.append(client.gui.add_markdown(self.text()))

    def clear(self) -> None:
        with self.lock:
            for note in self.notes:
                note.remove()
            self.notes = []

    def _show(self) -> None:
        for note in self.notes:
            note.content = self.text()


def compile_kernels(startup: Startup, settings: RenderSettings | None = None,
                    say: bool = True, gaussian: bool = False):
    """Start compiling the CPU rendering kernels (a Gaussian scene's, for ``gaussian``) in a
    thread, where they are not compiled yet (a first run): (thread, errors list), or None.
    The page says so meanwhile."""
    from .backends import cpu, cpu_gauss

    kernels = cpu_gauss if gaussian else cpu  # (kernels_compiled, COMPILE_SECONDS, warm_up)
    if (settings is not None and settings.device == "cuda") or kernels.kernels_compiled():
        return None
    seconds = kernels.COMPILE_SECONDS
    startup.begin("kernels", f"compiling the rendering kernels (once, about {seconds} s)…",
                  say)
    errors = []

    def run():
        try:
            kernels.warm_up()
        except Exception as e:  # noqa: BLE001 - raised again by the server's thread
            errors.append(e)
        finally:
            startup.end("kernels")

    thread = threading.Thread(target=run, daemon=True, name="dofsplat-view-compile")
    thread.start()
    return thread, errors


def view(surfels, camera: Camera | None = None, lens: ThinLens | None = None,
         settings: RenderSettings | None = None, port: int = 8080, host: str = "127.0.0.1",
         open_browser: bool = True, log=None, block: bool = True, save_dir=None):
    """Serve ``surfels`` (``Surfels`` or ``Gaussians``) in the browser viewer (module
    docstring) until Ctrl-C (or return the server at once with ``block=False``). camera:
    the first view (default: the model framed from +z); lens: the first lens (default:
    focused on the target, diameter 0.1 x the model's half diagonal); settings: the
    rendering settings (LOD, bokeh, device); host: 127.0.0.1, this machine only ("0.0.0.0"
    shares the model with the network); save_dir: where "Save image" writes (default: the
    current folder)."""
    from .gaussians import Gaussians

    return serve(lambda: default_scene(surfels, camera, lens, settings), port=port, host=host,
                 open_browser=open_browser, log=log, block=block, save_dir=save_dir,
                 gaussian=isinstance(surfels, Gaussians))


def serve(load, port: int = 8080, host: str = "127.0.0.1", open_browser: bool = True,
          log=None, block: bool = True, save_dir=None, say_compiling: bool = True,
          gaussian: bool = False):
    """The server of ``view``, for a model still to be loaded: ``load()`` returns the
    ``Scene`` (a Gaussian scene's, with ``gaussian``: its own kernels compile). The page
    opens at once and says what it waits for (the kernels compiling,
    in a thread, while ``load`` runs here); the first frame follows. say_compiling: False
    where the caller has already said in the terminal that the kernels compile."""
    try:
        import viser
    except ImportError:
        raise DofsplatError("the viewer needs viser: pip install 'dofsplat[view]'") from None
    log = log or (lambda m: print(f"dofsplat: {m}", file=sys.stderr, flush=True))
    save_dir = Path(save_dir or ".").expanduser().resolve()
    if not save_dir.is_dir():
        raise DofsplatError(f"the folder for saved images does not exist: {save_dir}")
    silence_probes()
    try:
        server = viser.ViserServer(host=host, port=port, verbose=False)
    except OSError as e:
        raise DofsplatError(f"cannot serve on {host}:{port}: {e}") from None
    startup = Startup(log)
    sessions, ready = {}, []
    lock = threading.Lock()

    @server.on_client_connect
    def _(client) -> None:
        with lock:
            if not ready:
                startup.greet(client)
                return
            scene = ready[0]
        sessions[client.client_id] = _Session(client, scene, log, save_dir)

    @server.on_client_disconnect
    def _(client) -> None:
        session = sessions.pop(client.client_id, None)
        if session is not None:
            session.stop()

    shown = "localhost" if host in ("0.0.0.0", "::", "") else host
    address = f"http://{shown}:{server.get_port()}"
    print(f"dofsplat: viewer at {address} (Ctrl-C stops it)", file=sys.stderr, flush=True)
    if not is_local(host):
        print(f"dofsplat: warning: listening on {host or 'every interface'}: anyone who can "
              "reach this machine can open the model and use its CPU", file=sys.stderr,
              flush=True)
    if open_browser:
        import webbrowser

        webbrowser.open(address)
    try:
        compiling = compile_kernels(startup, say=say_compiling, gaussian=gaussian)
        startup.begin("model", "loading the model…")
        scene = load()
        startup.end("model")
        if compiling is not None:
            thread, errors = compiling
            thread.join()
            if errors:
                raise errors[0]
        lo, hi = scene.model.view_bounds()
        server.scene.set_up_direction(tuple(scene.camera.up))
        initial = server.initial_camera  # a page opened from now on starts there
        initial.position = tuple(scene.camera.eye)
        initial.look_at = tuple(orbit_point(scene.camera, scene.lens.focus_distance, lo, hi))
        initial.up = tuple(scene.camera.up)
        initial.fov = math.radians(scene.camera.fov_y or 40.0)
        with lock:
            ready.append(scene)
            waiting = [c for c in server.get_clients().values()
                       if c.client_id not in sessions]
        startup.clear()
        for client in waiting:
            sessions[client.client_id] = _Session(client, scene, log, save_dir)
        log("ready: the first frame is on its way to each page")
    except BaseException:
        server.stop()
        raise
    if not block:
        server.dofsplat_sessions = sessions  # for tests: each page's _Session
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


def render_frame(model, camera: Camera, lens, settings: RenderSettings):
    """One frame for the page: (rgb (H, W, 3) uint8 sRGB, depth (H, W) float32 with inf
    where empty, the RenderResult)."""
    from .io import linear_to_srgb
    from .render import render

    result = render(model, camera, lens, settings)
    rgb = (np.clip(linear_to_srgb(np.clip(result.image[..., :3], 0, 1)), 0, 1) * 255
           ).astype(np.uint8)
    return rgb, result.depth, result


class _Session:
    """One browser tab: its controls, its camera and its render thread."""

    def __init__(self, client, scene: Scene, log, save_dir: Path, start: bool = True):
        self.client, self.model, self.log = client, scene.model, log
        self.settings, self.save_dir = scene.settings, save_dir
        self.gaussians = isinstance(scene.model, Gaussians)
        self.lock = threading.Condition()
        self.state = Refinement()
        self.pull = None
        self.depth = None  # the last frame's depth, for clicks
        self.notice = ""  # the last refusal, shown in the status line
        self.frame_text = ""
        self.running = True
        lo, hi = scene.model.view_bounds()
        self.bounds = (np.asarray(lo), np.asarray(hi))
        half_diagonal = 0.5 * float(np.linalg.norm(self.bounds[1] - self.bounds[0]))
        self.fields = LensFields.of(scene.lens)
        gui = client.gui
        step = 0.01 * half_diagonal
        self.handles = {
            "focus": gui.add_number("Focus distance", self.fields.focus, step=step,
                                    hint="scene units along the view axis; click the model "
                                         "to focus where you click"),
            "diameter": gui.add_number("Lens diameter", self.fields.diameter, step=step,
                                       hint="scene units; 0 is a pinhole; F / n while focal "
                                            "length and f-number are set"),
            "focal": gui.add_number("Focal length", self.fields.focal, step=0.1 * step,
                                    hint="scene units, with f-number: lens diameter = F / n "
                                         "(0: unset)"),
            "f_number": gui.add_number("f-number", self.fields.f_number, step=0.1,
                                       hint="with focal length, sets the lens diameter "
                                            "(0: unset, Lens diameter rules)"),
            "bokeh": gui.add_dropdown("Bokeh", ("disc", "gaussian"),
                                      initial_value=self.fields.bokeh),
            "blades": gui.add_number("Blades", self.fields.blades, step=1,
                                     hint="0 (round) or 5 to 16 straight blades (disc bokeh)"),
        }
        # a Gaussian scene has no surfel hierarchy: no LOD controls
        self.lod = None if self.gaussians else gui.add_checkbox("LOD", scene.settings.lod)
        self.show_lod = None if self.gaussians else gui.add_checkbox("Show LOD",
                                                                     scene.settings.show_lod)
        self.scale = gui.add_slider("Resolution scale", 0.25, 1.0, 0.05, 1.0)
        self.save = gui.add_button("Save image")
        self.save_note = gui.add_markdown(f"Saves to `{save_dir}`")
        self.status = gui.add_markdown("")
        for name, handle in self.handles.items():
            handle.on_update(lambda _, name=name: self.lens_edited(name))
        for handle in (self.lod, self.show_lod, self.scale):
            if handle is not None:
                handle.on_update(lambda _: self.changed())
        self.save.on_click(lambda _: self.save_image())
        client.scene.on_click()(self.clicked)
        self.place_camera(scene.camera)
        client.camera.on_update(lambda _: self.changed())
        self.thread = threading.Thread(target=self.loop, daemon=True,
                                       name=f"dofsplat-view-{client.client_id}")
        if start:
            self.thread.start()

    def place_camera(self, camera: Camera) -> None:
        """The page's camera at ``camera``, orbiting about ``orbit_point``: viser's look-at
        is set after the position (setting the position moves it along), so that the view
        is the camera's and a drag turns it about the model."""
        position, _ = pose_from_camera(camera)
        with self.client.atomic():
            cam = self.client.camera
            cam.up_direction = tuple(float(u) for u in camera.up)
            cam.position = tuple(position)
            cam.look_at = tuple(orbit_point(camera, self.fields.focus, *self.bounds))
            cam.fov = math.radians(camera.fov_y or 40.0)

    # the controls and the camera

    def changed(self) -> None:
        with self.lock:
            self.state.moved(time.monotonic())
            self.lock.notify()

    def lens_edited(self, name: str) -> None:
        """A lens field changed (by the user, a focus pull or ``show_fields``): take it with
        the fields that depend on it, or refuse it with a message and show the last good
        value again."""
        handle = self.handles[name]
        with self.lock:
            if handle.value == getattr(self.fields, name):
                return
            try:
                self.fields = edit_lens(self.fields, name, handle.value)
                refused = None
            except (DofsplatError, TypeError, ValueError) as e:
                refused = str(e)
        if refused is not None:
            self.refuse(refused)
            handle.value = getattr(self.fields, name)
            return
        self.notice = ""
        self.show_fields()
        self.changed()

    def show_fields(self) -> None:
        """Every lens field shows the lens rendered."""
        for name, handle in self.handles.items():
            value = getattr(self.fields, name)
            if handle.value != value:
                handle.value = value

    def refuse(self, message: str) -> None:
        self.notice = f"**Not applied:** {message}"
        self.status.content = self.notice + ("  \n" + self.frame_text if self.frame_text else "")
        self.client.add_notification("Not applied", message, color="red",
                                     auto_close_seconds=6.0)
        self.log(f"not applied: {message}")

    def clicked(self, event) -> None:
        depth = self.depth
        d = None if depth is None else depth_at(depth, event.screen_pos)
        if d is None:
            self.client.add_notification("Nothing here", "Click on the model to focus on it: "
                                         "there is only background under the cursor.",
                                         auto_close_seconds=3.0)
            return
        if self.fields.focal > 0 and d <= self.fields.focal:
            self.refuse(f"the surface there is {d:.6g} away, nearer than the focal length "
                        f"F = {self.fields.focal:g}: a lens cannot focus nearer than F")
            return
        with self.lock:
            self.pull = FocusPull(self.fields.focus, d, time.monotonic())
            self.lock.notify()
        # the orbit turns about the newly focused surface (on the view axis, at its depth)
        cam = self.client.camera
        forward = _matrix(cam.wxyz)[:, 2]
        try:
            cam.look_at = tuple(np.asarray(cam.position, np.float64) + d * forward)
        except ValueError:  # pragma: no cover - viser refuses a degenerate camera
            pass
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
        lens = self.fields.lens()
        if self.gaussians:
            settings = replace(self.settings, show_lod=False)
        else:
            lod = bool(self.lod.value)
            settings = replace(self.settings, lod=lod, show_lod=bool(self.show_lod.value) and lod)
        if kind == "low" and not self.gaussians:
            # while the camera moves: the paper's coarser LOD stop (docs/maths.md, "The
            # stop's margin"), every node drawn ("The smallest nodes"), no finer cut for
            # textured nodes ("A finer cut where the texture needs it"), and the pixel stop
            # at MOVING_PIXEL_THRESHOLD: the cut of a small frame is not much smaller than
            # a large one's at 1 px (the surfels of the nodes under it), and its cost is
            # the cut's; the still frame keeps the settings' own
            settings = replace(settings, lod_blur_fraction=max(settings.lod_blur_fraction,
                                                               MOVING_LOD_BLUR_FRACTION),
                               lod_color_tolerance=math.inf, lod_min_node=2,
                               lod_pixel_threshold=max(settings.lod_pixel_threshold,
                                                       MOVING_PIXEL_THRESHOLD))
        return camera, lens, settings

    # the render thread

    def loop(self) -> None:
        while self.running:
            with self.lock:
                now = time.monotonic()
                pull = self.pull
                if pull is not None and pull.finished(now):
                    self.pull = None
                kind = self.state.next(now)
            if pull is not None:  # outside the lock: the field's callback takes it
                self.handles["focus"].value = pull.value(now)
                with self.lock:
                    self.state.moved(now)
                    kind = self.state.next(now)
            if kind is None:
                with self.lock:
                    self.lock.wait(timeout=0.05)
                continue
            try:
                camera, lens, settings = self.current(kind)
                rgb, depth, result = render_frame(self.model, camera, lens, settings)
            except Exception as e:  # noqa: BLE001 - said in the panel; the thread goes on
                self.status.content = f"**Cannot render:** {e}"
                if not isinstance(e, DofsplatError):
                    self.log(f"render failed: {type(e).__name__}: {e}")
                with self.lock:
                    self.state.done(kind)
                continue
            far = np.where(np.isfinite(depth), depth, FAR_DEPTH).astype(np.float32)
            self.client.scene.set_background_image(rgb, format="png", depth=far)
            self.depth = depth
            self.frame_text = (f"{camera.width}x{camera.height}, "
                               f"{result.stats['total_ms']:.0f} ms"
                               + (" (moving: reduced)" if kind == "low" else ""))
            self.status.content = (self.notice + "  \n" if self.notice else "") + self.frame_text
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
        png, meta = saved_paths(self.save_dir)
        result = render(self.model, camera, lens, settings)
        write_image(png, result.image)
        record = {"camera": {"eye": list(camera.eye), "target": list(camera.target),
                             "up": list(camera.up), "width": camera.width,
                             "height": camera.height, "fov_y_deg": camera.fov_y},
                  "lens": {"focus_distance": lens.focus_distance, "aperture": lens.diameter,
                           "focal_length": lens.focal_length,
                           "f_number": self.fields.f_number or None,
                           "bokeh": lens.bokeh, "blades": lens.blades},
                  "settings": {"lod": settings.lod, "show_lod": settings.show_lod},
                  "render_options": render_options(camera, lens, settings)}
        meta.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
        self.client.add_notification("Saved", f"{png}\n{meta}", auto_close_seconds=8.0)
        self.save_note.content = f"Saved `{png}`"
        self.log(f"wrote {png}, {meta}")


def saved_paths(folder: Path) -> tuple[Path, Path]:
    """(PNG, JSON) absolute paths for a saved frame in ``folder``: view-DATE-TIME, with -2,
    -3, ... where a file of that name exists (two saves in one second)."""
    stem = f"view-{time.strftime('%Y%m%d-%H%M%S')}"
    folder = Path(folder).resolve()
    for i in range(1, 10000):
        name = stem if i == 1 else f"{stem}-{i}"
        png, meta = folder / f"{name}.png", folder / f"{name}.json"
        if not png.exists() and not meta.exists():
            return png, meta
    raise DofsplatError(f"too many saved images named {stem} in {folder}")


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
