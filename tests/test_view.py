"""The browser viewer (dofsplat.viewer, ``dofsplat view``): its camera mapping, the depth
under a click, the low/high resolution states, and one end-to-end run in headless Chromium
driven by Playwright (skipped where no browser is installed)."""

from __future__ import annotations

import math
import shutil
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import dofsplat as ds
from dofsplat import cli
from dofsplat.viewer import (FOCUS_PULL_S, SETTLE_S, FocusPull, Refinement, camera_from_pose,
                             depth_at, pose_from_camera, render_options)

pytest.importorskip("viser")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def test_camera_mapping_round_trip():
    """dofsplat's look-at camera -> viser's pose -> camera: the same eye, view direction, up
    (made orthogonal to the view) and field of view, to 1e-9."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        eye, target = rng.normal(size=3) * 5, rng.normal(size=3)
        up = rng.normal(size=3)
        cam = ds.Camera(eye=tuple(eye), target=tuple(target), up=tuple(up), width=64,
                        height=48, fov_y=35.0)
        position, wxyz = pose_from_camera(cam)
        assert np.linalg.norm(wxyz) == pytest.approx(1.0)
        back = camera_from_pose(position, wxyz, math.radians(35.0), 64, 48)
        f0 = (target - eye) / np.linalg.norm(target - eye)
        f1 = np.subtract(back.target, back.eye)
        np.testing.assert_allclose(back.eye, eye, atol=1e-9)
        np.testing.assert_allclose(f1 / np.linalg.norm(f1), f0, atol=1e-9)
        u0 = up - (up @ f0) * f0
        np.testing.assert_allclose(np.asarray(back.up) / np.linalg.norm(back.up),
                                   u0 / np.linalg.norm(u0), atol=1e-9)
        assert back.fov_y == pytest.approx(35.0)


def test_viser_identity_pose_looks_along_z_with_y_down():
    """OpenCV's camera frame: the identity rotation looks along +z, image y down."""
    cam = camera_from_pose((1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0), math.radians(50.0), 32, 32)
    np.testing.assert_allclose(np.subtract(cam.target, cam.eye), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(cam.up, [0, -1, 0], atol=1e-12)


def test_depth_at_a_click_is_the_surface_depth():
    """A wall of surfels 3 units in front of the camera: a click on it reads 3 (to 0.5 %,
    the depth buffer of the rendered frame); a click beside it reads None (background)."""
    g = (np.arange(40) + 0.5) / 40 - 0.5
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    wall = ds.Surfels(positions=np.stack([x, y, np.full(x.size, -3.0)], 1),
                      normals=np.tile([0.0, 0.0, 1.0], (x.size, 1)),
                      radius=np.full(x.size, 1 / 40), colors=np.full((x.size, 3), 0.5))
    cam = ds.Camera(eye=(0, 0, 0), target=(0, 0, -1), width=64, height=48, fov_y=40.0)
    depth = ds.render(wall, cam, None, ds.RenderSettings(lod=False)).depth
    assert depth_at(depth, (0.5, 0.5)) == pytest.approx(3.0, rel=5e-3)
    assert depth_at(depth, (0.45, 0.6)) == pytest.approx(3.0, rel=5e-3)
    assert depth_at(depth, (0.02, 0.02)) is None  # the wall spans 0.5 x 0.5 of a 3-unit view
    assert depth_at(depth, (1.0, 1.0)) is None  # the edge clamps into the image


def test_refinement_low_while_moving_high_when_still():
    s = Refinement()
    assert s.next(0.0) == "high"  # the first frame
    s.done("high")
    assert s.next(0.1) is None
    s.moved(1.0)
    assert s.next(1.0) == "low"
    s.done("low")
    assert s.next(1.0 + SETTLE_S / 2) is None  # still moving, maybe: wait
    s.moved(1.2)  # moved again: low again, the settle clock restarts
    assert s.next(1.2) == "low"
    s.done("low")
    assert s.next(1.2 + SETTLE_S * 0.99) is None
    assert s.next(1.2 + SETTLE_S) == "high"
    s.done("high")
    assert s.next(5.0) is None


def test_focus_pull_eases_to_the_clicked_depth():
    pull = FocusPull(2.0, 4.0, 10.0)
    assert pull.value(10.0) == 2.0 and pull.value(10.0 + FOCUS_PULL_S) == 4.0
    assert pull.value(10.0 + FOCUS_PULL_S / 2) == pytest.approx(3.0)  # smoothstep's middle
    assert pull.value(9.0) == 2.0 and pull.value(11.0) == 4.0
    assert not pull.finished(10.1) and pull.finished(10.0 + FOCUS_PULL_S)


def test_saved_options_reproduce_the_camera():
    cam = ds.Camera(eye=(1, 2, 3), target=(0, 0, 0), width=64, height=48, fov_y=30.0)
    lens = ds.ThinLens(focus_distance=2.5, aperture=0.2)
    opts = render_options(cam, lens, ds.RenderSettings(lod=False))
    assert opts == ("--size 64x48 --eye 1 2 3 --target 0 0 0 --up 0 1 0 --fov 30 --focus 2.5 "
                    "--aperture 0.2 --bokeh disc --no-lod")


@pytest.mark.parametrize("argv, message", [
    (["view", "missing.ply", "--no-browser"], "no such file"),
    (["view", "--demo", "--port", "70000", "--no-browser"], "--port must be"),
    (["view", "--no-browser"], "give a model file to view"),
])
def test_mistakes_fail_before_the_server_starts(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium: apt-get install chromium (Debian)")
def test_click_to_focus_in_a_browser(tmp_path):
    """``dofsplat view --demo`` driven by headless Chromium: a frame arrives, a click on the
    floor sets the panel's "Focus distance" to the depth there. The viewer renders the
    demo's camera at the page's 800 x 600, so the expected depth is that of a pinhole frame
    of the demo at the clicked pixel (to 2 %: ours is the depth of the surface that
    contributes most to a blurred pixel)."""
    playwright = pytest.importorskip("playwright.sync_api")
    from dofsplat.demo import demo_scene

    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "dofsplat", "view", "--demo", "--port",
                             str(port), "--host", "127.0.0.1", "--no-browser"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path)
    lines = []
    threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True).start()

    def wait_for(text, timeout=120.0):
        t0 = time.monotonic()
        while not any(text in line for line in lines):
            assert proc.poll() is None, "".join(lines)
            assert time.monotonic() - t0 < timeout, f"no {text!r}: " + "".join(lines)
            time.sleep(0.1)

    try:
        wait_for("viewer at")
        with playwright.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=[
                "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update",
                "--disable-sync"])
            other = browser.new_page(viewport={"width": 320, "height": 240})
            other.goto(f"http://127.0.0.1:{port}")  # a second tab, with its own session
            wait_for("frame 320x240 sent")
            page = browser.new_page(viewport={"width": 800, "height": 600})
            page.goto(f"http://127.0.0.1:{port}")
            wait_for("frame 800x600 sent")  # a full-resolution frame is on the page
            field = page.get_by_label("Focus distance")
            before = float(field.input_value(timeout=10000))
            page.mouse.click(400, 360)  # the floor below the yellow sphere
            wait_for("focus on the surface")
            said = next(line for line in lines if "focus on the surface" in line)
            clicked = float(said.split(": ")[2].split()[0])  # the depth the server read
            t0 = time.monotonic()  # the panel eases there over FOCUS_PULL_S
            while (abs(float(field.input_value()) - clicked) > 1e-4 * clicked
                   and time.monotonic() - t0 < 10):
                time.sleep(0.1)
            after = float(field.input_value())
            page.get_by_role("button", name="Save image").click()
            wait_for(f"wrote {tmp_path.resolve()}/view-")  # the full path
            browser.close()
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    surfels, camera, _ = demo_scene(800, 600)
    expected = ds.focus_distance_at(surfels, camera, 400.5, 360.5)
    assert after != before
    assert after == pytest.approx(expected, rel=0.02)
    # "Save image": the PNG, and the JSON whose options make `dofsplat demo` draw it again
    import json

    saved = json.loads(next(tmp_path.glob("view-*.json")).read_text())
    assert saved["camera"]["width"] == 800 and saved["lens"]["focus_distance"] == pytest.approx(after, rel=1e-4)
    again = tmp_path / "again.png"
    assert cli.main(["demo", *saved["render_options"].split(), "-o", str(again), "-q"]) == 0
    from dofsplat.io import read_image
    from dofsplat.metrics import compare

    score = compare(read_image(next(tmp_path.glob("view-*.png"))), read_image(again))
    assert score["psnr"] > 50  # the same frame: 8-bit PNGs from options printed to 9 digits


def test_ctrl_c_stops_the_server_cleanly():
    """SIGINT (Ctrl-C) after the server is up: exit status 0, no traceback."""
    import signal

    port = _free_port()
    # Ctrl-C's default in the child even where this run inherited it ignored (a shell's
    # background job): Python only installs its handler where SIGINT is not ignored
    proc = subprocess.Popen([sys.executable, "-m", "dofsplat", "view", "--demo", "--port",
                             str(port), "--host", "127.0.0.1", "--no-browser"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = []
    threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True).start()
    t0 = time.monotonic()
    while not any("ready:" in line for line in lines):  # the model loaded, pages served
        assert proc.poll() is None and time.monotonic() - t0 < 120, "".join(lines)
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=30) == 0
    time.sleep(0.2)
    assert "Traceback" not in "".join(lines)
    assert any("viewer stopped" in line for line in lines)


def test_moving_frames_use_the_papers_lod_stop():
    """While the camera moves the viewer draws a quarter-resolution frame at the paper's
    coarser LOD stop (kappa 1, every node drawn, no finer cut for textured nodes); the still
    frame keeps the settings' own (0.35, nodes of at least 4 surfels, 0.02 by default)."""
    from types import SimpleNamespace

    from dofsplat.viewer import MOVING_LOD_BLUR_FRACTION, LensFields, _Session

    session = object.__new__(_Session)  # the controls current() reads, without a browser
    cam = ds.Camera(eye=(0, 0, 3), target=(0, 0, 0), width=400, height=300)
    position, wxyz = pose_from_camera(cam)
    value = lambda v: SimpleNamespace(value=v)  # noqa: E731
    session.client = SimpleNamespace(camera=SimpleNamespace(
        position=position, wxyz=wxyz, fov=math.radians(cam.fov_y), image_width=400,
        image_height=300))
    session.scale, session.fields = value(1.0), LensFields(focus=3.0, diameter=0.1)
    session.lod, session.show_lod, session.gaussians = value(True), value(False), False
    session.settings = ds.RenderSettings()
    _, _, moving = session.current("low")
    camera, _, still = session.current("high")
    assert moving.lod_blur_fraction == MOVING_LOD_BLUR_FRACTION == 1.0
    assert still.lod_blur_fraction == ds.RenderSettings().lod_blur_fraction == 0.35
    assert moving.lod_color_tolerance == math.inf
    assert still.lod_color_tolerance == ds.RenderSettings().lod_color_tolerance == 0.02
    assert moving.lod_min_node == 2
    assert still.lod_min_node == ds.RenderSettings().lod_min_node == 4
    assert (camera.width, camera.height) == (400, 300)
