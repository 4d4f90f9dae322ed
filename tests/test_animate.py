"""Sequences (dofsplat.sequence, ``dofsplat animate``): each frame is a render, the
keyframes interpolate as documented, videos decode, runs resume, mistakes cost nothing."""

from __future__ import annotations

import json
import math
import os
import re

import numpy as np
import pytest

import dofsplat as ds
from dofsplat import cli, sequence
from dofsplat.demo import demo_scene
from dofsplat.errors import DofsplatError

from conftest import grid_surfels

W, H = 64, 48


@pytest.fixture(scope="module")
def scene():
    return demo_scene(W, H)


def run(argv, capsys):
    status = cli.main([str(a) for a in argv])
    out = capsys.readouterr()
    return status, out.err


def test_keyframe_interpolation_is_eased_between_keys():
    keys, easing = sequence.keyframes_from_json(
        {"keyframes": [{"t": 0.0, "focus": 2.0}, {"t": 0.5, "focus": 4.0, "aperture": 0.1},
                       {"t": 1.0, "focus": 3.0}]})
    assert easing == "smooth"
    f = lambda t: sequence.interpolate(keys, "focus", t)[0]  # noqa: E731
    assert f(0.0) == 2.0 and f(0.5) == 4.0 and f(1.0) == 3.0  # keys are met exactly
    assert f(0.25) == pytest.approx(3.0)  # smoothstep is 1/2 at the middle
    assert f(0.125) == pytest.approx(2.0 + 2.0 * (3 * 0.25**2 - 2 * 0.25**3))
    values = [f(t) for t in np.linspace(0, 0.5, 21)]
    assert all(b >= a for a, b in zip(values, values[1:]))  # monotone between two keys
    # a value given by one key is held everywhere; one given by none is None
    assert sequence.interpolate(keys, "aperture", 0.9) == (0.1,)
    assert sequence.interpolate(keys, "eye", 0.3) is None
    lin = sequence.interpolate(keys, "focus", 0.125, "linear")[0]
    assert lin == pytest.approx(2.5)


def test_keyframes_are_checked_when_made():
    """A Keyframe built in Python is checked as a keyframe file's are (a bare number for a
    one-number field; a mistake is a DofsplatError naming the field), and a value no lens
    or camera takes is refused at its keyframe, which a file's error names."""
    assert sequence.Keyframe(0, {"focus": 2}).values == {"focus": (2.0,)}
    for t, values, message in [
            (0.0, {"zoom": (2.0,)}, "unknown field 'zoom'"),
            (1.5, {"focus": (2.0,)}, r"t must be in 0\.\.1, got 1\.5"),
            ("0", {"focus": (2.0,)}, "t must be a number, got '0'"),
            (0.0, {"eye": (0.0, 1.0)}, "eye must be 3 numbers"),
            (0.0, [("focus", 2.0)], "values must be a dict"),
            (0.0, {"focus": (-2.0,)}, "focus must be > 0, got -2"),
            (0.0, {"aperture": (-0.1,)}, "aperture must be >= 0, got -0.1"),
            (0.0, {"fov": (200.0,)}, r"fov must be in \(0, 180\) degrees, got 200")]:
        with pytest.raises(DofsplatError, match=message):
            sequence.Keyframe(t, values)
    with pytest.raises(DofsplatError, match=r"^moves\.json: keyframe 1: focus must be > 0, got 0$"):
        sequence.keyframes_from_json([{"t": 0, "focus": 2}, {"t": 1, "focus": 0}], "moves.json")


def test_frame_specs_take_keyframes_in_any_order(scene):
    """Keyframes made in Python may come in any order (a file's are sorted on reading):
    given last-first they pulled the focus to the last key's value in every frame."""
    _, camera, lens = scene
    keys = [sequence.Keyframe(1.0, {"focus": (4.0,)}), sequence.Keyframe(0.0, {"focus": (2.0,)})]
    specs = sequence.frame_specs(keys, 3, camera, lens, "linear")
    assert [s.lens.focus_distance for s in specs] == pytest.approx([2.0, 3.0, 4.0])
    for n_frames in (0, 2.5, "3", None):
        with pytest.raises(DofsplatError, match="n_frames must be an integer >= 1"):
            sequence.frame_specs(keys, n_frames, camera, lens)
    with pytest.raises(DofsplatError, match="keyframes must be a list of Keyframe"):
        sequence.frame_specs({"keyframes": []}, 3, camera, lens)


def test_frame_specs_with_the_eye_model(scene):
    """An EyeLens (eq. 4) animates too: a focus keyframe moves its fixation, an aperture
    keyframe its pupil (it failed with an AttributeError, looking for an f-number)."""
    _, camera, _ = scene
    eye = ds.EyeLens(focus_distance=2.0, screen_distance=0.5, pixels_per_unit=2000.0)
    keys = [sequence.Keyframe(0.0, {"focus": (2.0,), "aperture": (0.002,)}),
            sequence.Keyframe(1.0, {"focus": (4.0,), "aperture": (0.006,)})]
    specs = sequence.frame_specs(keys, 3, camera, eye, "linear")
    assert all(isinstance(s.lens, ds.EyeLens) for s in specs)
    assert [s.lens.focus_distance for s in specs] == pytest.approx([2.0, 3.0, 4.0])
    assert [s.lens.pupil_diameter for s in specs] == pytest.approx([0.002, 0.004, 0.006])
    assert specs[1].lens.screen_distance == 0.5


def test_fps_is_any_real_number(scene):
    """numpy's numbers are numbers (np.float32(24) was refused as not one); a bool is not."""
    surfels, camera, lens = scene
    keys = [sequence.Keyframe(0.0, {"focus": 2.0})]
    assert len(sequence.animate(surfels, keys, 1, camera, lens, fps=np.float32(24))) == 1
    for fps in (True, 0, float("nan"), "24"):
        with pytest.raises(DofsplatError, match="fps must be a positive number"):
            sequence.animate(surfels, keys, 1, camera, lens, fps=fps)


def test_frame_specs_focus_pull_and_orbit(scene):
    surfels, camera, lens = scene
    keys = [sequence.Keyframe(0.0, {"focus": (1.5,), "orbit": (0.0,)}),
            sequence.Keyframe(1.0, {"focus": (4.0,), "orbit": (90.0,)})]
    specs = sequence.frame_specs(keys, 5, camera, lens, "linear")
    assert [s.lens.focus_distance for s in specs] == pytest.approx([1.5, 2.125, 2.75, 3.375, 4.0])
    assert all(s.lens.diameter == lens.diameter for s in specs)
    # the last eye is the first turned by 90 degrees about the target, around up
    e0 = np.subtract(camera.eye, camera.target)
    e1 = np.subtract(specs[-1].camera.eye, camera.target)
    up = np.asarray(camera.up) / np.linalg.norm(camera.up)
    assert float(e1 @ up) == pytest.approx(float(e0 @ up))  # the height stays
    h0, h1 = e0 - (e0 @ up) * up, e1 - (e1 @ up) * up
    assert float(h0 @ h1) == pytest.approx(0.0, abs=1e-9)  # a quarter turn
    assert np.linalg.norm(h1) == pytest.approx(np.linalg.norm(h0))


def test_every_frame_equals_a_single_render(scene):
    """In this process and on two Dask worker processes (one numba thread each): frame k is
    ``render`` of frame k's camera and lens, bit for bit (the renderer does not depend on
    the thread count)."""
    pytest.importorskip("dask.distributed")
    from dask.distributed import Client, LocalCluster

    surfels, camera, lens = scene
    keys = [sequence.Keyframe(0.0, {"focus": (1.5,), "aperture": (0.05,)}),
            sequence.Keyframe(1.0, {"focus": (4.0,), "aperture": (0.2,)})]
    settings = ds.RenderSettings()
    frames = sequence.animate(surfels, keys, 3, camera, lens, settings)
    specs = sequence.frame_specs(keys, 3, camera, lens)
    for frame, spec in zip(frames, specs):
        np.testing.assert_array_equal(frame, ds.render(surfels, spec.camera, spec.lens,
                                                       settings).image)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        distributed = sequence.animate(surfels, keys, 3, camera, lens, settings,
                                       client=client)
    for a, b in zip(frames, distributed):
        np.testing.assert_array_equal(a, b)


def test_cli_frame_equals_render(tmp_path, capsys):
    out = tmp_path / "frames"
    status, err = run(["animate", "--demo", "-o", out, "--frames", 3, "--size", f"{W}x{H}",
                       "--focus-from", 1.5, "--focus-to", 4, "--frame-format", "npy"], capsys)
    assert status == 0 and "wrote" in err
    assert sorted(p.name for p in out.iterdir()) == ([".dofsplat-sequence.json"]
                                                     + [f"frame_000{i}.npy" for i in range(3)])
    assert run(["demo", "--size", f"{W}x{H}", "--focus", 2.75, "-o", tmp_path / "mid.npy",
                "-q"], capsys)[0] == 0
    np.testing.assert_array_equal(np.load(out / "frame_0001.npy"), np.load(tmp_path / "mid.npy"))


def test_mp4_and_gif_decode_to_the_frames(tmp_path, capsys):
    av = pytest.importorskip("av")
    from PIL import Image

    mp4, gif, folder = tmp_path / "pull.mp4", tmp_path / "pull.gif", tmp_path / "frames"
    for out in (mp4, gif, folder):
        status, _ = run(["animate", "--demo", "-o", out, "--frames", 5, "--size", "63x47",
                         "--aperture-from", 0, "--aperture-to", 3, "-q"], capsys)
        assert status == 0
    with av.open(str(mp4)) as box:
        frames = list(box.decode(video=0))
    assert len(frames) == 5
    assert (frames[0].width, frames[0].height) == (64, 48)  # H.264 wants even sizes
    # the video's frames are the rendered ones, in order: each decoded frame (less the
    # repeated last row and column) against every frame the same command writes as PNG.
    # H.264 is lossy (crf 18, colour at half resolution: on a 63 x 47 frame of texture
    # edges 32.0-34.7 dB measured), so each is within 30 dB of its own frame and 1 dB
    # nearer it than any other (the next frame, 0.75 more aperture, lies 29.4-31.6 dB
    # from it); a frame out of order, or the wrong frame, fails
    decoded = [f.to_ndarray(format="rgb24")[:47, :63] / 255.0 for f in frames]
    rendered = [np.asarray(Image.open(p).convert("RGB")) / 255.0
                for p in sorted(folder.glob("frame_*.png"))]
    assert len(rendered) == 5
    # (PSNR of the 8-bit sRGB values, as encoded: metrics.psnr reads linear RGBA)
    score = np.array([[-10 * np.log10(np.mean((d - r) ** 2)) for r in rendered]
                      for d in decoded])
    for k in range(5):
        assert score[k, k] > 30.0, score.round(1)
        assert score[k, k] > np.delete(score[k], k).max() + 1.0, score.round(1)
    assert Image.open(gif).n_frames == 5 and Image.open(gif).size == (63, 47)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no leftovers
    # readable as any new file is (the umask's), not private as a temporary file (0600,
    # until 2026-11-27)
    umask = os.umask(0)
    os.umask(umask)
    for out in (mp4, gif):
        assert out.stat().st_mode & 0o777 == 0o666 & ~umask


def test_a_rerun_skips_the_frames_that_exist(tmp_path, capsys, monkeypatch):
    out = tmp_path / "frames"
    argv = ["animate", "--demo", "-o", out, "--frames", 3, "--size", f"{W}x{H}",
            "--focus-from", 1.5, "--focus-to", 4, "-q"]
    assert run(argv, capsys)[0] == 0
    (out / "frame_0001.png").unlink()
    rendered = []
    original = sequence.render_frame
    monkeypatch.setattr(sequence, "render_frame",
                        lambda s, spec, *a: rendered.append(spec.index) or original(s, spec, *a))
    assert run(argv, capsys)[0] == 0
    assert rendered == [1] and (out / "frame_0001.png").exists()
    # other arguments into the same folder: refused, the frames left alone
    status, err = run(argv[:-1] + ["--focus-to", 5, "-q"], capsys)
    assert status == 2 and "holds the frames of another sequence" in err


def test_ctrl_c_leaves_whole_frames_and_no_video(tmp_path, capsys, monkeypatch):
    out = tmp_path / "pull.gif"
    original = sequence.render_frame

    def interrupted(s, spec, *a):
        if spec.index == 2:
            raise KeyboardInterrupt
        return original(s, spec, *a)

    monkeypatch.setattr(sequence, "render_frame", interrupted)
    argv = ["animate", "--demo", "-o", out, "--frames", 4, "--size", f"{W}x{H}", "-q",
            "--focus-from", 1.5, "--focus-to", 4]
    assert run(argv, capsys)[0] == 130
    assert not out.exists()
    waiting = tmp_path / ".pull.gif.frames"
    assert sorted(p.name for p in waiting.glob("frame_*")) == ["frame_0000.png",
                                                               "frame_0001.png"]
    monkeypatch.setattr(sequence, "render_frame", original)
    assert run(argv, capsys)[0] == 0  # resumes: frames 2 and 3, then the video
    assert out.exists() and not waiting.exists()


def test_a_failed_frame_is_named_and_stops_the_sequence(tmp_path, capsys, monkeypatch):
    """Frame 1 fails: one line naming it, exit 2, frame 0 kept whole, no video."""
    original = sequence.render_frame

    def failing(s, spec, *a):
        if spec.index == 1:
            raise DofsplatError("the lens is on fire")
        return original(s, spec, *a)

    monkeypatch.setattr(sequence, "render_frame", failing)
    out = tmp_path / "pull.mp4"
    status, err = run(["animate", "--demo", "-o", out, "--frames", 3, "--size", f"{W}x{H}",
                       "-q", "--focus-from", 1.5, "--focus-to", 4], capsys)
    assert status == 2 and err == "dofsplat: error: frame 1: the lens is on fire\n"
    assert not out.exists()
    assert [p.name for p in (tmp_path / ".pull.mp4.frames").glob("frame_*")] == ["frame_0000.png"]


def test_the_readme_keyframes_are_docs_moves_json():
    """The README's keyframe example is docs/moves.json (which its command runs) and reads."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    shown = re.search(r"```json\n(.*?)```", (root / "README.md").read_text(), re.S).group(1)
    assert json.loads(shown) == json.loads((root / "docs/moves.json").read_text())
    keys, easing = sequence.load_keyframes(root / "docs/moves.json")
    assert easing == "smooth" and [k.t for k in keys] == [0.0, 0.6, 1.0]


@pytest.mark.parametrize("extra, message", [
    (["--frames", "0"], "--frames must be at least 1"),
    (["--frames", "3", "-o", "x.avi"], "write a sequence as .mp4, .gif or a folder"),
    (["--frames", "3", "--focus-from", "2"], "go together"),
    (["--frames", "3", "--keyframes", "KEYS"], "keyframe 1 has no \"t\""),
    (["--frames", "3", "--keyframes", "BADFIELD"], "unknown field 'zoom'"),
    (["--frames", "3", "--focus-at", "5", "5", "--focus-from", "2", "--focus-to", "3"],
     "give it or --focus-from"),
    (["--frames", "3", "--depth", "d.npy"], "describe one frame"),
    (["--frames", "3", "--scheduler", "no-port"], "cannot reach the Dask scheduler"),
    (["--frames", "3", "--scheduler", ""], "--scheduler needs the Dask scheduler's address"),
    (["--frames", "3", "--keyframes", "FOLDER"], "FOLDER: a folder, not a keyframe file"),
    # a misspelt "easing" was dropped without a word
    (["--frames", "3", "--keyframes", "TYPO"], "TYPO: unknown key 'easeing'"),
    (["--frames", "3", "--frame-format", "exr"], "is for a folder of frames"),
])
def test_mistakes_are_one_line_and_write_nothing(tmp_path, capsys, monkeypatch, extra, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "KEYS").write_text(json.dumps([{"t": 0, "focus": 2}, {"focus": 3}]))
    (tmp_path / "BADFIELD").write_text(json.dumps({"keyframes": [{"t": 0, "zoom": 2}]}))
    (tmp_path / "TYPO").write_text(json.dumps({"easeing": "linear",
                                               "keyframes": [{"t": 0, "focus": 2}]}))
    (tmp_path / "FOLDER").mkdir()
    before = sorted(p.name for p in tmp_path.iterdir())
    argv = ["animate", "--demo", "--size", f"{W}x{H}"]
    argv += extra if "-o" in extra else extra + ["-o", "seq.mp4"]
    status, err = run(argv, capsys)
    assert status == 2
    assert err.count("\n") == 1 and message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_keyframe_focus_at_a_pixel(scene):
    """A keyframe may focus on a pixel: it becomes the depth seen there."""
    surfels, camera, lens = scene
    keys = [sequence.Keyframe(0.0, {"focus_at": (W / 2, H / 2)}),
            sequence.Keyframe(1.0, {"focus": (5.0,)})]
    specs = sequence.frame_specs(keys, 2, camera, lens, surfels=surfels)
    seen = ds.focus_distance_at(surfels, camera, W / 2, H / 2)
    assert specs[0].lens.focus_distance == pytest.approx(seen)
    assert specs[1].lens.focus_distance == 5.0
    with pytest.raises(DofsplatError, match="focus and focus_at"):
        sequence.keyframes_from_json([{"t": 0, "focus": 1, "focus_at": [1, 1]}])
    assert math.isfinite(seen)


def test_cli_on_an_existing_scheduler(tmp_path, capsys):
    """--scheduler ADDRESS sends the frames to a running cluster (here a LocalCluster's
    scheduler, one worker with two task threads, as ``dask worker`` runs several frames at
    once): the frames are the in-process ones."""
    pytest.importorskip("dask.distributed")
    from dask.distributed import LocalCluster

    argv = ["animate", "--demo", "--frames", 2, "--size", f"{W}x{H}", "--frame-format", "npy",
            "--focus-from", 1.5, "--focus-to", 4, "-q"]
    assert run(argv + ["-o", tmp_path / "here"], capsys)[0] == 0
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True,
                      dashboard_address=None) as cluster:
        assert run(argv + ["-o", tmp_path / "there", "--scheduler",
                           cluster.scheduler_address], capsys)[0] == 0
    for k in range(2):
        np.testing.assert_array_equal(np.load(tmp_path / "here" / f"frame_000{k}.npy"),
                                      np.load(tmp_path / "there" / f"frame_000{k}.npy"))
    status, err = run(argv + ["-o", tmp_path / "x", "--scheduler", "tcp://127.0.0.1:9"],
                      capsys)
    assert status == 2 and "cannot reach the Dask scheduler" in err


def _edited(surfels, edit):
    """A copy of the model with one thing changed, as a user changes it between two runs."""
    from dataclasses import replace

    n = len(surfels)
    if edit == "recoloured":
        colors = surfels.colors.copy()
        colors[n // 2] = (0.9, 0.1, 0.1)  # one surfel: the old sample of positions saw none
        return replace(surfels, colors=colors)
    if edit == "reweighted":  # what --normalise gives
        weight = np.ones(n, np.float32) if surfels.weight is None else surfels.weight.copy()
        weight[::7] *= 1.05
        return replace(surfels, weight=weight)
    if edit == "radii":
        return replace(surfels, radius=surfels.radius * np.float32(1.01))
    if edit == "opacities":
        opacity = surfels.opacity.copy()
        opacity[n // 3] = 0.5
        return replace(surfels, opacity=opacity)
    if edit == "material":
        return replace(surfels, material=ds.Material(specular=0.5))
    raise AssertionError(edit)


FOCUS_PULL = [sequence.Keyframe(0.0, {"focus": (1.5,)}), sequence.Keyframe(1.0, {"focus": (4.0,)})]


@pytest.mark.parametrize("edit", ["recoloured", "reweighted", "radii", "opacities", "material"])
def test_a_folder_of_another_model_is_refused(tmp_path, scene, edit):
    """Two frames into a folder, the model changed, the same sequence again: refused, one
    line naming the folder and the model, the frames left alone (the old fingerprint, the
    count and a sample of positions, kept the stale frames without a word); the model
    itself still resumes."""
    surfels, camera, lens = scene
    out = tmp_path / "frames"
    sequence.animate(surfels, FOCUS_PULL, 3, camera, lens, output=out, frame_format="npy")
    (out / "frame_0001.npy").unlink()  # an interrupted run
    first = (out / "frame_0000.npy").read_bytes()
    with pytest.raises(DofsplatError) as error:
        sequence.animate(_edited(surfels, edit), FOCUS_PULL, 3, camera, lens, output=out,
                         frame_format="npy")
    assert str(error.value) == (f"{out} holds the frames of another sequence (another model: "
                                "its arrays or material differ): give another folder, or "
                                "delete it")
    assert not (out / "frame_0001.npy").exists()
    assert (out / "frame_0000.npy").read_bytes() == first
    sequence.animate(surfels, FOCUS_PULL, 3, camera, lens, output=out, frame_format="npy")
    assert (out / "frame_0001.npy").exists() and (out / "frame_0000.npy").read_bytes() == first


def test_a_model_edited_in_place_is_another_model(tmp_path):
    """A notebook recolours the same ``Surfels`` in place between two runs: the folder's
    hash is computed afresh each run (a hash kept on the object would not see it)."""
    surfels = grid_surfels(n=32)
    camera = ds.Camera(eye=(0, 0, 2), target=(0, 0, 0), width=32, height=24, fov_y=40)
    lens = ds.ThinLens(focus_distance=2.0, aperture=0.05)
    out = tmp_path / "frames"
    sequence.animate(surfels, FOCUS_PULL, 2, camera, lens, output=out, frame_format="npy")
    surfels.colors[5] = (0.0, 1.0, 0.0)
    with pytest.raises(DofsplatError, match=r"\(another model: its arrays or material differ\)"):
        sequence.animate(surfels, FOCUS_PULL, 2, camera, lens, output=out, frame_format="npy")


def test_other_arguments_and_model_are_both_named(tmp_path, scene):
    surfels, camera, lens = scene
    out = tmp_path / "frames"
    sequence.animate(surfels, FOCUS_PULL, 1, camera, lens, output=out, frame_format="npy")
    with pytest.raises(DofsplatError, match=r"\(other cameras, lenses or settings\)"):
        sequence.animate(surfels, FOCUS_PULL, 1, camera, lens, ds.RenderSettings(cutoff=2.0),
                         output=out, frame_format="npy")
    with pytest.raises(DofsplatError, match=r"\(another model: its arrays or material differ; "
                                            r"other cameras, lenses or settings\)"):
        sequence.animate(_edited(surfels, "radii"), FOCUS_PULL, 2, camera, lens, output=out,
                         frame_format="npy")


@pytest.mark.parametrize("damage", ["{\"sequence\": ", "[]", "{\"frames\": 3}", "\xff\xfe"])
def test_a_damaged_manifest(tmp_path, scene, damage):
    """A folder of frames whose record is damaged (cut short, not an object, no hash, not
    text) is refused, naming the damage (a list crashed with an AttributeError; the rest
    were called another sequence); with no frames beside it, it is written anew."""
    surfels, camera, lens = scene
    out = tmp_path / "frames"
    sequence.animate(surfels, FOCUS_PULL, 1, camera, lens, output=out, frame_format="npy")
    manifest = out / sequence.MANIFEST
    manifest.write_bytes(damage.encode("latin-1"))
    with pytest.raises(DofsplatError, match=rf"^{re.escape(str(out))} holds frames whose record "
                                            r"\.dofsplat-sequence\.json is damaged \((not "
                                            r"readable JSON|not a dofsplat sequence record)"):
        sequence.animate(surfels, FOCUS_PULL, 1, camera, lens, output=out, frame_format="npy")
    assert manifest.read_bytes() == damage.encode("latin-1")
    (out / "frame_0000.npy").unlink()
    sequence.animate(surfels, FOCUS_PULL, 1, camera, lens, output=out, frame_format="npy")
    assert json.loads(manifest.read_text())["version"] == sequence.MANIFEST_VERSION
    assert (out / "frame_0000.npy").exists()


def test_a_folder_of_an_older_dofsplat_is_refused(tmp_path, scene):
    """A record written before the model's whole hash was kept (its count and a sample of
    positions) cannot tell a recoloured model: its frames are not trusted."""
    surfels, camera, lens = scene
    out = tmp_path / "frames"
    sequence.animate(surfels, FOCUS_PULL, 1, camera, lens, output=out, frame_format="npy")
    (out / sequence.MANIFEST).write_text(json.dumps({"sequence": "0123456789abcdef0123",
                                                     "frames": 1}))
    with pytest.raises(DofsplatError, match=rf"^{re.escape(str(out))} holds the frames of a "
                                            "sequence that an older dofsplat wrote"):
        sequence.animate(surfels, FOCUS_PULL, 1, camera, lens, output=out, frame_format="npy")


def test_a_folder_of_foreign_frames_is_refused(tmp_path, scene):
    """PNG frames that no dofsplat sequence wrote (no record beside them): refused, one line
    naming the folder, the files untouched; other files in a folder are no frames."""
    from PIL import Image

    surfels, camera, lens = scene
    out = tmp_path / "shots"
    out.mkdir()
    for k in range(2):
        Image.new("RGB", (W, H), (k * 100, 0, 0)).save(out / f"frame_{k:04d}.png")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(DofsplatError) as error:
        sequence.animate(surfels, FOCUS_PULL, 2, camera, lens, output=out)
    assert str(error.value) == (f"{out} already holds frame files that no dofsplat sequence "
                                "wrote: give another folder")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    other = tmp_path / "other"
    other.mkdir()
    Image.new("RGB", (W, H)).save(other / "photo.png")
    sequence.animate(surfels, FOCUS_PULL, 1, camera, lens, output=other)
    assert sorted(p.name for p in other.iterdir()) == [".dofsplat-sequence.json",
                                                       "frame_0000.png", "photo.png"]


def test_a_resume_on_a_dask_scheduler(tmp_path, scene):
    """A folder begun here resumes on a Dask scheduler (a Client by its address, as
    ``--scheduler`` makes): only the missing frame is rendered, there, equal to the one
    rendered here; the model changed is refused there as here, before anything is sent."""
    pytest.importorskip("dask.distributed")
    from dask.distributed import Client, LocalCluster

    surfels, camera, lens = scene
    out = tmp_path / "frames"
    sequence.animate(surfels, FOCUS_PULL, 3, camera, lens, output=out, frame_format="npy")
    middle = np.load(out / "frame_0001.npy")
    (out / "frame_0001.npy").unlink()
    kept = {k: (out / f"frame_000{k}.npy").stat().st_mtime_ns for k in (0, 2)}
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster, \
            Client(cluster.scheduler_address) as client:
        with pytest.raises(DofsplatError, match="another model: its arrays or material differ"):
            sequence.animate(_edited(surfels, "recoloured"), FOCUS_PULL, 3, camera, lens,
                             output=out, frame_format="npy", client=client)
        assert not (out / "frame_0001.npy").exists()
        sequence.animate(surfels, FOCUS_PULL, 3, camera, lens, output=out, frame_format="npy",
                         client=client)
    np.testing.assert_array_equal(np.load(out / "frame_0001.npy"), middle)
    assert {k: (out / f"frame_000{k}.npy").stat().st_mtime_ns for k in (0, 2)} == kept
