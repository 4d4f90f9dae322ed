"""The viewer as a newcomer meets it (issue 51, items 3-7): it orbits about the model, its
page says what the first frame waits for, its moving frames are cheap, its panel shows
the lens rendered and refuses what cannot be rendered, it listens on 127.0.0.1 and a port
check prints nothing; and it serves Gaussian scenes. A closed tab ends its session, and a
frame that cannot be rendered is said on the page (issue 52). Most tests drive the
viewer's own session with a stand-in for viser's page (``FakeClient``: viser's own
CameraHandle, fake GUI elements), or a server in process with websocket "tabs" that speak
viser's protocol (``_Tab``); the browser tests skip where Debian's chromium is absent."""

from __future__ import annotations

import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import dofsplat as ds
from dofsplat import cli
from dofsplat.errors import DofsplatError

viser = pytest.importorskip("viser")
from dofsplat.viewer import (MOVING_PIXEL_THRESHOLD, LensFields, Startup,  # noqa: E402
                             _ProbeFilter, _Session, camera_from_pose, default_scene,
                             edit_lens, orbit_point, render_frame,
                             saved_paths)

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
DONUT = DATA / "gaussian_donut" / "fused.ply"


# -- a stand-in for one viser page -----------------------------------------------------------


class FakeHandle:
    """A GUI element as viser's: assigning ``value`` calls the update callbacks at once."""

    def __init__(self, label, value):
        self.label, self._value, self.callbacks, self.removed = label, value, [], False
        self.content = value if isinstance(value, str) else None

    @property
    def value(self):
        return self._value

    @value.setter
    def value(self, v):
        if v == self._value:
            return
        self._value = type(self._value)(v) if not isinstance(self._value, str) else v
        for cb in list(self.callbacks):
            cb(None)

    def on_update(self, cb):
        self.callbacks.append(cb)
        return cb

    on_click = on_update

    def remove(self):
        self.removed = True


class FakeGui:
    def __init__(self):
        self.handles = {}

    def _add(self, label, value):
        h = self.handles[label] = FakeHandle(label, value)
        return h

    def add_number(self, label, initial_value, **_):
        return self._add(label, float(initial_value))

    def add_dropdown(self, label, options, initial_value=None, **_):
        return self._add(label, initial_value or options[0])

    def add_checkbox(self, label, initial_value, **_):
        return self._add(label, bool(initial_value))

    def add_slider(self, label, min, max, step, initial_value, **_):
        return self._add(label, float(initial_value))

    def add_button(self, label, **_):
        return self._add(label, False)

    def add_markdown(self, content, **_):
        h = FakeHandle("markdown", content)
        self.handles[f"markdown{len(self.handles)}"] = h
        return h


class FakeClient:
    """A viser client without a browser: viser's own CameraHandle (its look-at and
    orientation maths) on a connection that sends nothing, at viser's start-up pose."""

    def __init__(self, width=400, height=300):
        self.client_id = 0
        self.gui = FakeGui()
        self.notifications = []
        self.frames = []
        self._websock_connection = SimpleNamespace(queue_message=lambda m: None)
        self.camera = viser.CameraHandle(self)
        state = self.camera._state
        # what a fresh page reports: viser's default camera (3, 3, 3) looking at the origin
        state.position, state.look_at = np.array([3.0, 3.0, 3.0]), np.zeros(3)
        state.up_direction, state.fov = np.array([0.0, 0.0, 1.0]), math.radians(75.0)
        state.image_width, state.image_height = width, height
        state.update_timestamp = 1.0
        state.wxyz = np.array([1.0, 0.0, 0.0, 0.0])
        state.up_direction = np.array([0.0, 0.0, 1.0])
        self.camera._update_wxyz()
        self.scene = SimpleNamespace(on_click=lambda: (lambda cb: cb),
                                     set_background_image=lambda rgb, **kw: self.frames.append(rgb))

    @contextmanager
    def atomic(self):
        yield

    def add_notification(self, title, body, **kw):
        self.notifications.append((title, body, kw))


def make_session(model=None, lens=None, tmp_path=".", camera=None, **scene):
    model = model if model is not None else _sphere()
    sc = default_scene(model, camera=camera, lens=lens, **scene)
    client = FakeClient()
    return _Session(client, sc, lambda m: None, Path(tmp_path), start=False), client, sc


def _sphere(n=4000, radius=1.0, centre=(0.5, -0.2, 0.3)):
    """Surfels on a sphere (a Fibonacci lattice), off the origin."""
    i = np.arange(n) + 0.5
    phi, z = np.pi * (1 + 5 ** 0.5) * i, 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    nrm = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    return ds.Surfels(positions=np.asarray(centre) + radius * nrm, normals=nrm,
                      radius=np.full(n, 2.2 * radius / math.sqrt(n)),
                      colors=np.full((n, 3), 0.6))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# -- item 3: the orbit turns about the model -------------------------------------------------


def test_page_camera_orbits_about_the_model_centre():
    """After the viewer places a page's camera, viser's look-at point (the orbit's centre)
    is the model's centre (the default view's target, where the focus lies), not viser's
    start-up point; and the view is still the viewer's camera (same eye and axes, 1e-9)."""
    session, client, scene = make_session()
    lo, hi = scene.model.view_bounds()
    np.testing.assert_allclose(client.camera.look_at, (lo + hi) / 2, atol=1e-9)
    np.testing.assert_allclose(client.camera.position, scene.camera.eye, atol=1e-9)
    back = camera_from_pose(client.camera.position, client.camera.wxyz, client.camera.fov,
                            64, 48)
    f0 = np.subtract(scene.camera.target, scene.camera.eye)
    f1 = np.subtract(back.target, back.eye)
    np.testing.assert_allclose(f1 / np.linalg.norm(f1), f0 / np.linalg.norm(f0), atol=1e-9)
    np.testing.assert_allclose(back.up, scene.camera.up, atol=1e-9)


def test_orbit_point_is_the_focused_surface_or_the_centre():
    cam = ds.Camera(eye=(0, 0, 10), target=(0, 0, 0), width=64, height=48)
    lo, hi = np.array([-1.0, -1, -1]), np.array([1.0, 1, 1])
    np.testing.assert_allclose(orbit_point(cam, 9.5, lo, hi), [0, 0, 0.5])  # in the box
    np.testing.assert_allclose(orbit_point(cam, 3.0, lo, hi), [0, 0, 0])  # far from it
    # a focus given on the command line: the orbit turns about the focused surface
    session, client, _ = make_session(lens=ds.ThinLens(focus_distance=5.0, aperture=0.1),
                                      camera=ds.Camera(eye=(0.5, -0.2, 5.6),
                                                       target=(0.5, -0.2, 0.3)))
    np.testing.assert_allclose(client.camera.look_at, [0.5, -0.2, 0.6], atol=1e-9)


def test_a_click_moves_the_orbit_to_the_clicked_depth():
    session, client, scene = make_session()
    camera, lens, settings = session.current("high")
    _, depth, _ = render_frame(scene.model, camera, lens, settings)
    session.depth = depth
    session.clicked(SimpleNamespace(screen_pos=(0.5, 0.5)))
    d = float(depth[depth.shape[0] // 2, depth.shape[1] // 2])
    forward = np.subtract(scene.camera.target, scene.camera.eye)
    forward /= np.linalg.norm(forward)
    np.testing.assert_allclose(client.camera.look_at, np.asarray(scene.camera.eye) + d * forward,
                               atol=1e-6)
    assert session.pull is not None and session.pull.end == pytest.approx(d)


# -- item 4: the page says what it waits for -------------------------------------------------


def test_a_page_opened_while_waiting_says_what_for():
    said = []
    startup = Startup(said.append)
    startup.begin("kernels", "compiling the rendering kernels (once, about 60 s)…")
    page = FakeClient()
    startup.greet(page)
    note = next(h for k, h in page.gui.handles.items() if k.startswith("markdown"))
    assert "compiling the rendering kernels" in note.content
    startup.begin("model", "loading the model…")
    assert "compiling" in note.content and "loading the model" in note.content
    startup.end("kernels")
    assert "compiling" not in note.content and "loading the model" in note.content
    assert said == ["compiling the rendering kernels (once, about 60 s)…", "loading the model…"]
    startup.clear()
    assert note.removed


def _lines_of(proc):
    lines = []
    threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True).start()
    return lines


def _wait_for(lines, proc, text, timeout):
    t0 = time.monotonic()
    while not any(text in line for line in lines):
        assert proc.poll() is None, "".join(lines)
        assert time.monotonic() - t0 < timeout, f"no {text!r} in {timeout} s: " + "".join(lines)
        time.sleep(0.05)
    return time.monotonic() - t0


def _open_page(pw, port: int):
    """An 800 x 600 page of headless Chromium on the viewer at port."""
    browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True,
                                 args=["--no-sandbox", "--disable-gpu"])
    page = browser.new_page(viewport={"width": 800, "height": 600})
    page.goto(f"http://127.0.0.1:{port}")
    return page


def _stop(proc):
    """Ends the server and what it started (the kernel compile's helper process)."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        pass
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium: apt-get install chromium (Debian)")
def test_fresh_install_page_says_compiling_within_2_s(tmp_path):
    """On fresh kernel caches (an empty DOFSPLAT_KERNEL_DIR), the page, opened as soon as
    the server answers, says that the kernels compile within seconds of loading (before:
    a blank page until the first frame, after the compile); the terminal said it too."""
    playwright = pytest.importorskip("playwright.sync_api")
    port = _free_port()
    env = dict(os.environ, DOFSPLAT_KERNEL_DIR=str(tmp_path / "kernels"))
    proc = subprocess.Popen([sys.executable, "-m", "dofsplat", "view", "--demo", "--port",
                             str(port), "--no-browser"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
                            start_new_session=True)
    lines = _lines_of(proc)
    try:
        _wait_for(lines, proc, "viewer at", 60)
        with playwright.sync_playwright() as pw:
            page = _open_page(pw, port)
            t0 = time.monotonic()
            page.get_by_text("compiling the rendering kernels").first.wait_for(timeout=10000)
            # the target is 2 s; 1.8 s measured here, most of it headless Chromium starting
            # viser's page (WebGL in software) on 2 busy cores: 4 s keeps the test steady
            assert time.monotonic() - t0 < 4.0
            page.context.browser.close()
        assert any("compiling the rendering kernels" in line for line in lines), lines
    finally:
        _stop(proc)


# -- item 5: moving frames cost in proportion ------------------------------------------------


def test_moving_frames_use_a_coarser_pixel_stop():
    session, _, _ = make_session()
    _, _, moving = session.current("low")
    camera, _, still = session.current("high")
    assert moving.lod_pixel_threshold == MOVING_PIXEL_THRESHOLD == 2.0
    assert still.lod_pixel_threshold == ds.RenderSettings().lod_pixel_threshold == 1.0
    low_camera, _, _ = session.current("low")
    assert (low_camera.width, low_camera.height) == (100, 75)  # a sixteenth of the pixels


def test_moving_frame_draws_a_fraction_of_the_full_frames_splats():
    """The cost of a frame is that of its cut: a dense model (160,000 surfels on a sphere
    filling the view) draws at most 0.3 x the full frame's splats in a moving frame (0.16
    measured; with the pixel stop at 1 px, as before, the sixteenth of the pixels kept 0.48
    x them)."""
    session, client, scene = make_session(model=_sphere(160000))
    client.camera._state.image_width, client.camera._state.image_height = 1280, 800
    full = render_frame(scene.model, *session.current("high"))[2].stats["splats_selected"]
    low = render_frame(scene.model, *session.current("low"))[2].stats["splats_selected"]
    assert low <= 0.3 * full, (low, full)


# -- item 6: the panel shows what is rendered, refuses what cannot be -------------------------


def test_focal_length_and_f_number_set_the_lens_diameter():
    fields = LensFields(focus=2.0, diameter=0.42)
    fields = edit_lens(fields, "focal", 0.05)
    assert fields.diameter == 0.42  # F alone changes nothing rendered
    fields = edit_lens(fields, "f_number", 1.4)
    assert fields.diameter == pytest.approx(0.05 / 1.4) and fields.lens().diameter == fields.diameter
    fields = edit_lens(fields, "diameter", 0.01)  # A with F set: n follows
    assert fields.f_number == pytest.approx(5.0)
    fields = edit_lens(fields, "focal", 0.1)
    assert fields.diameter == pytest.approx(0.02)
    fields = edit_lens(fields, "focal", 0.0)  # F unset: n is unset, A stays
    assert (fields.f_number, fields.diameter) == (0.0, pytest.approx(0.02))


@pytest.mark.parametrize("start, name, value, message", [
    (dict(focal=0.05, f_number=1.4), "focus", 0.01, "must exceed the focal length"),
    ({}, "diameter", -5, "Lens diameter must be >= 0"),
    ({}, "blades", 3, "blades must be 0 (round) or 5 to 16"),
    ({}, "blades", 6.5, "whole number"),
    ({}, "focus", 0.0, "Focus distance must be > 0"),
    ({}, "f_number", 2.0, "needs a Focal length"),
    (dict(focal=0.05), "f_number", -1, "f-number must be >= 0"),
    (dict(focus=0.04), "focal", 0.05, "must exceed the focal length"),
    (dict(blades=6), "bokeh", "gaussian", "need the disc bokeh"),
])
def test_what_cannot_be_rendered_is_refused(start, name, value, message):
    fields = LensFields(**{"focus": 2.0, "diameter": 0.42, **start})
    with pytest.raises(DofsplatError, match=message.replace("(", r"\(").replace(")", r"\)")):
        edit_lens(fields, name, value)


def test_the_panel_shows_the_lens_rendered_and_restores_refused_values():
    session, client, _ = make_session(lens=ds.ThinLens(focus_distance=3.0, aperture=0.42))
    h = session.handles
    h["focal"].value = 0.05
    h["f_number"].value = 1.4
    assert h["diameter"].value == pytest.approx(0.05 / 1.4)
    assert session.current("high")[1].diameter == pytest.approx(h["diameter"].value)
    h["focus"].value = 0.01  # nearer than F: refused, the field shows the focus rendered
    assert h["focus"].value == 3.0 and session.current("high")[1].focus_distance == 3.0
    assert client.notifications[-1][0] == "Not applied"
    assert "focal length" in client.notifications[-1][1]
    h["diameter"].value = -5
    assert h["diameter"].value == pytest.approx(0.05 / 1.4)
    h["blades"].value = 3
    assert h["blades"].value == 0 and session.current("high")[1].blades == 0
    assert "Not applied" in session.status.content
    h["blades"].value = 6  # a good value is taken, and the notice goes
    assert session.current("high")[1].blades == 6 and session.notice == ""


def test_save_image_writes_into_the_named_folder_and_shows_the_full_path(tmp_path):
    session, client, scene = make_session(tmp_path=tmp_path)
    client.camera._state.image_width, client.camera._state.image_height = 64, 48
    session.save_image()
    session.save_image()  # the same second: a second name, nothing overwritten
    pngs = sorted(tmp_path.glob("view-*.png"))
    assert len(pngs) == 2 and len(list(tmp_path.glob("view-*.json"))) == 2
    title, body, _ = client.notifications[-1]
    assert title == "Saved" and str(tmp_path.resolve()) in body and body.startswith("/")
    assert str(tmp_path.resolve()) in session.save_note.content
    png, meta = saved_paths(tmp_path)
    assert png.is_absolute() and not png.exists()


@pytest.mark.parametrize("flag", ["--depth", "--stats"])
def test_view_refuses_outputs_it_does_not_write(flag, capsys, tmp_path):
    assert cli.main(["view", "--demo", flag, str(tmp_path / "x.npy"), "--no-browser"]) == 2
    err = capsys.readouterr().err
    assert f"view has no {flag[2:]} output" in err and err.count("\n") == 1, err
    assert not (tmp_path / "x.npy").exists()


# -- item 7: this machine only, and probes print nothing -------------------------------------


def test_the_server_listens_on_this_machine_by_default():
    import inspect

    from dofsplat.viewer import serve, view

    args = cli.build_parser().parse_args(["view", "--demo"])
    assert args.host == "127.0.0.1"
    assert inspect.signature(view).parameters["host"].default == "127.0.0.1"
    assert inspect.signature(serve).parameters["host"].default == "127.0.0.1"


def test_the_probe_filter_drops_only_a_missing_request():
    import logging

    from websockets.exceptions import InvalidMessage

    def record(exc):
        return logging.LogRecord("websockets.server", logging.ERROR, __file__, 1,
                                 "opening handshake failed", None,
                                 (type(exc), exc, None) if exc else None)

    f = _ProbeFilter()
    assert not f.filter(record(InvalidMessage("did not receive a valid HTTP request")))
    assert f.filter(record(RuntimeError("something else")))
    assert f.filter(record(None))


def test_a_port_check_prints_nothing_and_sharing_warns(tmp_path):
    """A TCP connection that sends no HTTP request (a port check), and one that sends
    garbage: nothing printed (viser 1.1.1 with websockets 15 printed a 30-line traceback
    for each). --host 0.0.0.0 says in one line that the model is shared."""
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "dofsplat", "view", "--demo", "--port",
                             str(port), "--host", "0.0.0.0", "--no-browser"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path, start_new_session=True)
    lines = _lines_of(proc)
    try:
        _wait_for(lines, proc, "viewer at", 60)
        time.sleep(0.5)
        before = len(lines)
        with socket.create_connection(("127.0.0.1", port)):
            pass
        with socket.create_connection(("127.0.0.1", port)) as s:
            s.sendall(b"garbage\r\n\r\n")
            time.sleep(0.3)
        time.sleep(1.5)
        after = "".join(lines[before:])
        assert "Traceback" not in after and "handshake" not in after, after
        warnings = [line for line in lines if "warning: listening on 0.0.0.0" in line]
        assert len(warnings) == 1
    finally:
        _stop(proc)


# -- Gaussian scenes -------------------------------------------------------------------------


@pytest.mark.skipif(not DONUT.exists(), reason="no ../shared/data/gaussian_donut/fused.ply")
def test_the_viewer_renders_a_gaussian_scene():
    """The donut (a 3DGS PLY) through the viewer's own session and render function: no LOD
    controls on its panel, a full frame and a moving frame with the model in them."""
    from dofsplat.io import load

    donut = load(str(DONUT))
    assert isinstance(donut, ds.Gaussians)
    session, client, scene = make_session(model=donut)
    assert session.lod is None and session.show_lod is None
    assert "LOD" not in client.gui.handles and "Show LOD" not in client.gui.handles
    for kind in ("high", "low"):
        camera, lens, settings = session.current(kind)
        rgb, depth, _ = render_frame(scene.model, camera, lens, settings)
        assert rgb.shape == (camera.height, camera.width, 3)
        covered = np.isfinite(depth).mean()
        assert 0.05 < covered < 1.0 and rgb.max() > 50, (kind, covered)


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium: apt-get install chromium (Debian)")
def test_a_200_px_drag_keeps_the_model_in_view():
    """A sphere 0.35 units across, served in process; headless Chromium drags the view
    200 px to the right: the camera turned (by more than 20 degrees) about the model, whose
    centre stays in the middle of the frame (within 5 % of its width), and the frame
    rendered for that camera is a third covered or more. Before, viser orbited about its
    start-up look-at point 5.2 units ahead, and the model left the frame."""
    playwright = pytest.importorskip("playwright.sync_api")
    from dofsplat.viewer import view

    model = _sphere(4000, radius=0.35)
    port = _free_port()
    server = view(model, port=port, open_browser=False, block=False, log=lambda m: None)
    try:
        with playwright.sync_playwright() as pw:
            page = _open_page(pw, port)
            t0 = time.monotonic()
            while not server.dofsplat_sessions or next(iter(
                    server.dofsplat_sessions.values())).depth is None:
                assert time.monotonic() - t0 < 60, "no frame"
                time.sleep(0.1)
            client = next(iter(server.get_clients().values()))
            before = _matrix_of(client.camera.wxyz)[:, 2].copy()
            page.mouse.move(200, 300)
            page.mouse.down()
            for i in range(1, 21):
                page.mouse.move(200 + 10 * i, 300)
                time.sleep(0.02)
            page.mouse.up()
            time.sleep(1.0)
            cam = client.camera
            after = _matrix_of(cam.wxyz)[:, 2]
            turned = math.degrees(math.acos(min(1.0, float(before @ after))))
            camera = camera_from_pose(cam.position, cam.wxyz, cam.fov, 800, 600)
            page.context.browser.close()
    finally:
        server.stop()
    assert turned > 20, turned
    centre = np.asarray(model.positions).mean(0)
    view_from_world = camera.camera_from_world()
    p = view_from_world[:3, :3] @ centre + view_from_world[:3, 3]
    assert p[2] < 0  # in front of the camera (looking down -z)
    ax, bx, ay, by = camera.screen_coefficients()
    x = ax * p[0] / -p[2] + bx
    assert abs(x - 400) < 40, (x, turned)
    depth = ds.render(model, camera, None, ds.RenderSettings(lod=False)).depth
    assert np.isfinite(depth).mean() > 0.1


def _matrix_of(wxyz):
    from dofsplat.viewer import _matrix

    return _matrix(wxyz)


# -- a page's session: a tab closed, a frame that cannot be rendered (issue 52) ---------------


def _until(condition, timeout, what):
    t0 = time.monotonic()
    while not condition():
        assert time.monotonic() - t0 < timeout, f"no {what} in {timeout} s"
        time.sleep(0.02)


class _Tab:
    """A browser tab without a browser: a websocket to the viewer speaking viser's own
    protocol (its version as the subprotocol, then the camera message its page sends on
    opening, which is when viser counts the client as connected); what the server sends
    is read and dropped."""

    def __init__(self, port: int):
        import msgspec
        from viser import _messages
        from websockets.sync.client import connect

        self._message, self._encode = _messages.ViewerCameraMessage, msgspec.msgpack.encode
        self.ws = connect(f"ws://127.0.0.1:{port}", max_size=None,
                          subprotocols=[f"viser-v{viser.__version__}"])
        threading.Thread(target=self._drain, daemon=True).start()

    def _drain(self):
        try:
            for _ in self.ws:
                pass
        except Exception:  # noqa: BLE001 - the tab closed
            pass

    def look(self, width: int, height: int) -> None:
        """The page's camera: 4 units before the sphere, at a width x height canvas."""
        message = self._message(wxyz=(0.0, 1.0, 0.0, 0.0), position=(0.5, -0.2, 4.3),
                                fov=math.radians(40.0), near=0.01, far=1000.0,
                                image_height=height, image_width=width,
                                look_at=(0.5, -0.2, 0.3), up_direction=(0.0, 1.0, 0.0))
        self.ws.send(self._encode(message.as_serializable_dict()))

    def close(self) -> None:
        self.ws.close()


def test_a_closed_tab_ends_its_session(monkeypatch):
    """Two tabs on one server, each with its session (controls, render thread) and a
    frame. The first tab closes: its session leaves the server's table, its render thread
    ends within 5 s, nothing holds the session any more (collected), and a late camera
    update for it renders nothing; the other tab is still served (a new camera, a new
    frame, at its new size)."""
    import gc
    import weakref

    from dofsplat import viewer
    from dofsplat.viewer import view

    renders = []  # the render thread of each frame rendered
    real_render_frame = viewer.render_frame

    def counted(*args, **kwargs):
        renders.append(threading.current_thread())
        return real_render_frame(*args, **kwargs)

    monkeypatch.setattr(viewer, "render_frame", counted)
    server = view(_sphere(), port=_free_port(), open_browser=False, block=False,
                  log=lambda m: None)
    sessions = server.dofsplat_sessions
    try:
        closing, staying = _Tab(server.get_port()), _Tab(server.get_port())
        closing.look(64, 48)
        staying.look(64, 48)
        _until(lambda: len(sessions) == 2 and all(s.depth is not None
                                                  for s in list(sessions.values())),
               60, "first frame on both tabs")
        before = dict(sessions)
        assert all(s.thread in renders for s in before.values())

        closing.close()
        _until(lambda: len(sessions) == 1, 5, "session removed")
        (kept_id, kept), = sessions.items()
        (closed,) = (s for k, s in before.items() if k != kept_id)
        del before
        closed.thread.join(timeout=5)
        assert not closed.thread.is_alive() and not closed.running
        rendered_for_closed = renders.count(closed.thread)
        closed.changed()  # a camera update still in flight when the tab closed
        kept_before = renders.count(kept.thread)
        staying.look(80, 60)
        _until(lambda: kept.depth is not None and kept.depth.shape == (60, 80), 30,
               "new frame on the open tab")
        time.sleep(0.5)
        assert renders.count(closed.thread) == rendered_for_closed
        assert renders.count(kept.thread) > kept_before
        assert list(sessions) == [kept_id]

        gone = weakref.ref(closed)
        del closed
        gc.collect()
        assert gone() is None, gc.get_referrers(gone())
        staying.close()
        _until(lambda: not sessions, 5, "the last session removed")
    finally:
        server.stop()


def test_a_frame_that_cannot_be_rendered_is_said_on_the_page(monkeypatch):
    """A render that raises a user's error (here a page set to the CUDA device on a
    machine without one: render() refuses) shows "Cannot render: <why>" in the page's
    status line and sends no frame; the session's render thread goes on, says nothing of
    a failure in the terminal (the error is the user's, not a bug), and draws the next
    frame once the cause is gone."""
    import dofsplat.backends

    problem = "no CUDA driver (a stand-in)"
    monkeypatch.setattr(dofsplat.backends, "cuda_problem", lambda: problem)
    said = []
    session, client, _ = make_session(settings=ds.RenderSettings(device="cuda"))
    session.log = said.append
    client.camera._state.image_width, client.camera._state.image_height = 64, 48
    session.thread.start()
    try:
        _until(lambda: session.status.content.startswith("**Cannot render:**"), 60,
               "'Cannot render' in the status line")
        assert session.status.content == (f"**Cannot render:** device cuda cannot run here: "
                                          f"{problem} (use device cpu or auto)")
        time.sleep(0.3)
        assert session.thread.is_alive() and client.frames == []
        assert not any("render failed" in line for line in said), said

        session.settings = replace(session.settings, device="cpu")
        session.changed()
        # a moving frame (a quarter of the size), then the still one
        _until(lambda: client.frames and client.frames[-1].shape == (48, 64, 3), 60,
               "full frame after the cause is gone")
        assert session.status.content.startswith("64x48, ")
    finally:
        session.stop()
        session.thread.join(timeout=5)
    assert not session.thread.is_alive()


def test_a_render_that_fails_by_a_bug_is_said_in_the_terminal_too(monkeypatch):
    """Not a user's error: the page's status line says "Cannot render", the terminal says
    which exception (to report), and the render thread goes on."""
    from dofsplat import viewer

    def broken(*args, **kwargs):
        raise RuntimeError("a bug")

    monkeypatch.setattr(viewer, "render_frame", broken)
    said = []
    session, client, _ = make_session()
    session.log = said.append
    session.thread.start()
    try:
        _until(lambda: said, 30, "line in the terminal")
        assert session.status.content == "**Cannot render:** a bug"
        assert said == ["render failed: RuntimeError: a bug"]
        assert session.thread.is_alive() and client.frames == []
    finally:
        session.stop()
        session.thread.join(timeout=5)
    assert not session.thread.is_alive()
