"""Sequences: focus pulls, aperture changes and camera moves, rendered frame by frame.

A sequence is a list of keyframes, each at a time t in [0, 1] (0 the first frame, 1 the
last) and each giving some of: ``eye``, ``target``, ``up`` (world units), ``fov`` (degrees),
``focus`` (the focus distance, world units), ``focus_at`` (a pixel [x, y] to autofocus on,
turned into a distance before interpolation), ``aperture`` (the lens diameter, world
units) and ``orbit`` (degrees about the target, around the up axis). A value a keyframe
leaves out is interpolated between the keyframes that give it (held before the first and
after the last); one no keyframe gives is the base camera's or lens's. Between two
keyframes the local time is eased (``smooth``: smoothstep, a focus pull that starts and
stops gently; or ``linear``).

Frame k is ``render(surfels, camera_k, lens_k, settings)``: exactly what ``dofsplat render``
draws for that frame's camera and lens, whichever process renders it. With a
``dask.distributed`` client the frames are tasks: the model (with its LOD hierarchy) is
scattered to every worker once, not shipped per task; each worker renders with
cores / workers numba threads.

Frames are written as they finish (atomically: a frame file is whole or absent), so an
interrupted sequence into a folder resumes where it stopped: the folder records the
model's content hash and the frames' cameras, lenses and settings, and a run of another
model or other arguments into it is refused rather than mixed (``_claim``). A video
(.mp4, H.264 through PyAV, FFmpeg's bindings; or .gif through Pillow) is assembled at the
end from those frames, in order, into a temporary file renamed into place.
"""

from __future__ import annotations

import contextlib
import json
import math
import numbers
import os
import shutil
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .camera import Camera, EyeLens, ThinLens
from .errors import DofsplatError
from .frame import RenderSettings
from .surfels import Surfels

FIELDS = {"eye": 3, "target": 3, "up": 3, "fov": 1, "focus": 1, "focus_at": 2, "aperture": 1,
          "orbit": 1}
RANGES = {"focus": (lambda v: v > 0, "> 0"), "aperture": (lambda v: v >= 0, ">= 0"),
          "fov": (lambda v: 0 < v < 180, "in (0, 180) degrees")}  # what a lens or camera takes
EASINGS = ("smooth", "linear")
FRAME_FORMATS = ("png", "npy", "exr")
VIDEO_SUFFIXES = (".mp4", ".gif")
MANIFEST = ".dofsplat-sequence.json"  # in a frame folder: which sequence its frames are
MANIFEST_VERSION = 2  # 2: the model's whole content hash (1: its count and a sample)


@dataclass(frozen=True)
class Keyframe:
    """Some of a frame's camera and lens values at time t in [0, 1] (module docstring).

    Checked when made: a field FIELDS names, with as many finite numbers as it takes (a
    bare number for a one-number field), a focus > 0, an aperture >= 0 and a fov in
    (0, 180); DofsplatError otherwise."""

    t: float
    values: dict  # field name -> tuple of floats (FIELDS gives each one's length)

    def __post_init__(self):
        t = _numbers(self.t, 1, "t")[0]
        if not 0.0 <= t <= 1.0:
            raise DofsplatError(f"t must be in 0..1, got {t:g}")
        if not isinstance(self.values, dict):
            raise DofsplatError(f"values must be a dict of field name -> numbers, got "
                                f"{type(self.values).__name__}")
        unknown = sorted(set(self.values) - set(FIELDS), key=str)
        if unknown:
            raise DofsplatError(f"unknown field {unknown[0]!r} (known: {', '.join(FIELDS)})")
        values = {name: _numbers(v, FIELDS[name], name) for name, v in self.values.items()}
        if "focus" in values and "focus_at" in values:
            raise DofsplatError("gives both focus and focus_at: give one")
        for name, (valid, text) in RANGES.items():
            if name in values and not valid(values[name][0]):
                raise DofsplatError(f"{name} must be {text}, got {values[name][0]:g}")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "values", values)


@dataclass(frozen=True)
class FrameSpec:
    """One frame's camera and lens: what ``render`` takes."""

    index: int
    camera: Camera
    lens: ThinLens | EyeLens | None


def keyframes_from_json(data, source: str = "keyframes") -> tuple[list[Keyframe], str]:
    """(keyframes, easing) from the parsed JSON of a keyframe file:
    ``{"easing": "smooth", "keyframes": [{"t": 0, "focus": 2.0}, {"t": 1, "focus": 5.0}]}``
    (or the list alone). DofsplatError naming the keyframe and field for a bad value."""
    easing = "smooth"
    if isinstance(data, dict):
        unknown = sorted(set(data) - {"easing", "keyframes"}, key=str)
        if unknown:  # a misspelt "easing" would be dropped without a word
            raise DofsplatError(f"{source}: unknown key {unknown[0]!r} (a keyframe file "
                                "holds \"easing\" and \"keyframes\")")
        easing = data.get("easing", "smooth")
        if easing not in EASINGS:
            raise DofsplatError(f"{source}: easing must be one of {', '.join(EASINGS)}, "
                                f"got {easing!r}")
        data = data.get("keyframes")
    if not isinstance(data, list) or not data:
        raise DofsplatError(f"{source}: expected a non-empty list of keyframes (objects with "
                            "\"t\" and camera or lens values)")
    keys = []
    for i, item in enumerate(data):
        where = f"{source}: keyframe {i}"
        if not isinstance(item, dict):
            raise DofsplatError(f"{where} is not an object")
        if "t" not in item:
            raise DofsplatError(f"{where} has no \"t\" (its time, 0 the first frame, 1 the "
                                "last)")
        try:
            keys.append(Keyframe(item["t"], {k: v for k, v in item.items() if k != "t"}))
        except DofsplatError as e:
            raise DofsplatError(f"{where}: {e}") from None
    keys.sort(key=lambda k: k.t)
    return keys, easing


def load_keyframes(path) -> tuple[list[Keyframe], str]:
    """``keyframes_from_json`` of a JSON file; DofsplatError if it cannot be read."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DofsplatError(f"no such keyframe file: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DofsplatError(f"{path}: not a readable JSON keyframe file ({e})") from None
    return keyframes_from_json(data, str(path))


def ease(u: float, easing: str = "smooth") -> float:
    """Eased local time: smoothstep 3u^2 - 2u^3 (0 and 1 fixed, slope 0 at both), or u."""
    u = min(max(u, 0.0), 1.0)
    return u * u * (3.0 - 2.0 * u) if easing == "smooth" else u


def interpolate(keys: list[Keyframe], name: str, t: float, easing: str = "smooth"):
    """The value of ``name`` at time t (a tuple), or None when no keyframe gives it."""
    have = [k for k in keys if name in k.values]
    if not have:
        return None
    if t <= have[0].t:
        return have[0].values[name]
    for a, b in zip(have, have[1:]):
        if t <= b.t:
            u = ease((t - a.t) / (b.t - a.t) if b.t > a.t else 1.0, easing)
            return tuple(x + (y - x) * u for x, y in zip(a.values[name], b.values[name]))
    return have[-1].values[name]


def frame_specs(keys: list[Keyframe], n_frames: int, camera: Camera,
                lens: ThinLens | EyeLens | None, easing: str = "smooth", surfels: Surfels | None = None,
                settings: RenderSettings | None = None) -> list[FrameSpec]:
    """Each frame's camera and lens: the base ``camera`` and ``lens`` with the keyframes'
    values at t = k / (n_frames - 1). A ``focus_at`` pixel is focused on (a pinhole frame of
    ``surfels`` from that keyframe's camera) and interpolated as a distance."""
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise DofsplatError(f"n_frames must be an integer >= 1, got {n_frames!r}")
    if not isinstance(keys, (list, tuple)) or not all(isinstance(k, Keyframe) for k in keys):
        raise DofsplatError("keyframes must be a list of Keyframe (keyframes_from_json reads "
                            "a file's)")
    keys = sorted(keys, key=lambda k: k.t)  # interpolate() walks them in time
    keys = _resolve_focus_at(keys, camera, surfels, settings, easing)
    specs = []
    for k in range(n_frames):
        t = k / (n_frames - 1) if n_frames > 1 else 0.0
        specs.append(FrameSpec(k, _camera_at(keys, t, camera, easing),
                               _lens_at(keys, t, lens, easing)))
    return specs


def render_frame(surfels: Surfels, spec: FrameSpec, settings: RenderSettings,
                 threads: int | None = None) -> np.ndarray:
    """Frame ``spec`` of ``surfels``: the (H, W, 4) float32 linear RGBA image of ``render``."""
    from .render import render

    if threads:
        import numba

        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    return render(surfels, spec.camera, spec.lens, settings).image


def frame_path(folder: Path, index: int, frame_format: str = "png") -> Path:
    return Path(folder) / f"frame_{index:04d}.{frame_format}"


def animate(surfels: Surfels, keyframes: list[Keyframe], n_frames: int, camera: Camera,
            lens: ThinLens | EyeLens | None = None, settings: RenderSettings | None = None, *,
            output=None, fps: float = 24.0, easing: str = "smooth",
            frame_format: str = "png", client=None, progress: bool = False, log=None):
    """Render a sequence; returns the ``n_frames`` frames, each an (H, W, 4) float32 linear
    RGBA image as ``render`` gives, when ``output`` is None; else writes ``output`` (a
    folder of frame_0000.png ..., an .mp4 or a .gif) and returns its path.

    keyframes: ``Keyframe`` list (``keyframes_from_json``, or built directly, e.g.
    ``Keyframe(0.0, {"focus": (2.0,)})``; distances in world units, angles in degrees);
    camera, lens: the base values the keyframes change (lens: a ThinLens, or an EyeLens,
    whose pupil an aperture keyframe sets; None: pinhole frames);
    fps: the video's frames per second; easing: "smooth" or "linear" between keyframes;
    frame_format: png, npy or exr, for a folder; client: a ``dask.distributed.Client``
    (None: render here, frame after frame); progress: a tqdm bar of frames done and the
    rate. Frames already in an output folder are kept, not rendered again (a video's
    frames wait in a hidden folder beside it until it is assembled), when the folder holds
    this sequence of this model: a folder of another model (any array or the material
    changed: recoloured, new weights, radii, opacities) or of other cameras, lenses or
    settings is refused with a DofsplatError naming it and what differs, its frames left
    alone; so is a folder of frames no dofsplat sequence wrote (``_claim``). log: where
    to say that a run resumes ("resuming: N of M frames already there") and, on Ctrl-C,
    what it kept ("interrupted: N of M frames kept in FOLDER; ..."); None says nothing.
    """
    if easing not in EASINGS:
        raise DofsplatError(f"easing must be one of {', '.join(EASINGS)}, got {easing!r}")
    if frame_format not in FRAME_FORMATS:
        raise DofsplatError(f"frame_format must be one of {', '.join(FRAME_FORMATS)}, got "
                            f"{frame_format!r}")
    if isinstance(fps, bool) or not (isinstance(fps, numbers.Real) and math.isfinite(fps)
                                     and fps > 0):
        raise DofsplatError(f"fps must be a positive number, got {fps!r}")
    settings = settings or RenderSettings()
    specs = frame_specs(keyframes, n_frames, camera, lens, easing, surfels, settings)
    if output is None:
        if client is not None:
            futures = _submit(client, surfels, settings, specs)
            try:
                return [_named(f.result, s.index) for f, s in zip(futures, _bar(specs, progress))]
            finally:
                for f in futures:
                    f.cancel()
        return [_checked(render_frame, surfels, s, settings) for s in _bar(specs, progress)]

    output = Path(output)
    video = output.suffix.lower() in VIDEO_SUFFIXES
    if output.suffix and not video:
        raise DofsplatError(f"{output}: a sequence is written as .mp4, .gif or a folder of "
                            "frames (a name without an extension)")
    folder = output.with_name(f".{output.name}.frames") if video else output
    frame_format = "png" if video else frame_format
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise DofsplatError(f"{output}: cannot write: {e.strerror or e}") from e
    _claim(folder, specs, settings, surfels, frame_format)
    todo = [s for s in specs if not frame_path(folder, s.index, frame_format).exists()]
    if log is not None and len(todo) < len(specs):
        log(f"resuming: {len(specs) - len(todo)} of {len(specs)} frames already there")
    try:
        _render_into(folder, todo, len(specs), surfels, settings, frame_format, client,
                     progress)
    except KeyboardInterrupt:
        if log is not None:
            kept = sum(frame_path(folder, s.index, frame_format).exists() for s in specs)
            log(f"interrupted: {kept} of {len(specs)} frames kept in {folder}; run the same "
                "command again to resume")
        raise
    if video:
        frames = [frame_path(folder, s.index) for s in specs]
        write_video(output, frames, fps)
        shutil.rmtree(folder, ignore_errors=True)
    return output


def write_video(path: Path, frames: list[Path], fps: float) -> None:
    """Assemble PNG frames, in order, into an .mp4 (H.264, yuv420p) or a .gif, atomically."""
    from PIL import Image

    from .io import atomic_write

    path = Path(path)

    def write(tmp: str) -> None:
        if path.suffix.lower() == ".gif":
            images = [Image.open(f).convert("RGB") for f in frames]
            images[0].save(tmp, save_all=True, append_images=images[1:],
                           duration=max(1, round(1000.0 / fps)), loop=0)
        else:
            _write_mp4(tmp, frames, fps)

    # (atomic_write: a temporary file renamed, with the permissions of any new file; the
    # video's own temporary file was private, 0600, until 2026-11-27)
    atomic_write(path, write)


# -- the parts ----------------------------------------------------------------------------


def _numbers(value, n: int, what: str) -> tuple:
    items = value if isinstance(value, (list, tuple)) else [value]
    if len(items) != n or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                  and math.isfinite(v) for v in items):
        raise DofsplatError(f"{what} must be {'a number' if n == 1 else f'{n} numbers'}, "
                            f"got {value!r}")
    return tuple(float(v) for v in items)


def _resolve_focus_at(keys, camera, surfels, settings, easing):
    """Keyframes with each ``focus_at`` pixel replaced by the depth seen there."""
    from .render import focus_distance_at

    out = []
    for key in keys:
        if "focus_at" in key.values:
            if surfels is None:
                raise DofsplatError("a keyframe's focus_at needs the model to focus on")
            x, y = key.values["focus_at"]
            cam = _camera_at(keys, key.t, camera, easing)
            d = focus_distance_at(surfels, cam, x, y, settings=settings)
            values = {k: v for k, v in key.values.items() if k != "focus_at"}
            key = Keyframe(key.t, {**values, "focus": (d,)})
        out.append(key)
    return out


def _camera_at(keys, t, camera: Camera, easing) -> Camera:
    eye = np.asarray(interpolate(keys, "eye", t, easing) or camera.eye, np.float64)
    target = np.asarray(interpolate(keys, "target", t, easing) or camera.target, np.float64)
    up = np.asarray(interpolate(keys, "up", t, easing) or camera.up, np.float64)
    orbit = interpolate(keys, "orbit", t, easing)
    if orbit is not None and orbit[0] != 0.0:
        eye = target + _rotate(eye - target, up / np.linalg.norm(up), math.radians(orbit[0]))
    fov = interpolate(keys, "fov", t, easing)
    changed = fov is not None
    return replace(camera, eye=tuple(eye.tolist()), target=tuple(target.tolist()),
                   up=tuple(up.tolist()), fov_y=fov[0] if changed else camera.fov_y,
                   frustum=None if changed else camera.frustum)


def _lens_at(keys, t, lens: ThinLens | EyeLens | None, easing):
    focus = interpolate(keys, "focus", t, easing)
    aperture = interpolate(keys, "aperture", t, easing)
    if lens is None:
        return None
    if focus is None and aperture is None:
        return lens
    if isinstance(lens, EyeLens):  # the eye's aperture is its pupil
        return replace(lens, focus_distance=focus[0] if focus else lens.focus_distance,
                       pupil_diameter=aperture[0] if aperture else lens.pupil_diameter)
    kw = {"focus_distance": focus[0] if focus else lens.focus_distance,
          "focal_length": lens.focal_length, "bokeh": lens.bokeh, "blades": lens.blades,
          "blade_rotation": lens.blade_rotation}
    if aperture is not None or lens.f_number is None:
        kw["aperture"] = aperture[0] if aperture else lens.diameter
    else:
        kw["f_number"] = lens.f_number
    return ThinLens(**kw)


def _rotate(v, axis, angle):
    """v turned by ``angle`` radians about the unit ``axis`` (Rodrigues)."""
    c, s = math.cos(angle), math.sin(angle)
    return v * c + np.cross(axis, v) * s + axis * float(axis @ v) * (1.0 - c)


def _bar(items, progress, total=None):
    from tqdm.auto import tqdm

    return tqdm(items, total=total, unit="frame", desc="frames", disable=not progress,
                leave=False)


def _submit(client, surfels, settings, specs):
    """One task per frame; the model scattered to every worker once. A frame renders with
    its machine's cores / the task threads of all the workers there numba threads, so
    that the frames running at once on a machine share its cores (a ``dask worker`` runs
    as many tasks at once as it has threads: its cores, by default)."""
    from collections import Counter

    workers = client.scheduler_info().get("workers", {})
    per_host = Counter()
    for info in workers.values():
        per_host[info.get("host")] += max(1, int(info.get("nthreads") or 1))
    per_host = dict(per_host)
    model = client.scatter(surfels, broadcast=True)
    return [client.submit(_render_on_worker, model, s, settings, per_host, pure=False,
                          key=f"dofsplat-frame-{s.index}-{os.getpid()}-{id(specs)}")
            for s in specs]


def _render_on_worker(surfels, spec, settings, per_host):
    """``render_frame`` in a Dask worker, sharing its machine's cores with its neighbours
    (``per_host``: host -> the task threads of the workers there)."""
    from distributed import get_worker
    from distributed.comm import get_address_host

    host = get_address_host(get_worker().address)  # as the scheduler names it
    threads = max(1, (os.cpu_count() or 1) // max(1, per_host.get(host, 1)))
    with _frame_lock():
        return render_frame(surfels, spec, settings, threads)


_WORKQUEUE_LOCK = threading.Lock()


def _frame_lock():
    """Frames in one worker process run at once (one per task thread) under numba's tbb
    and omp threading layers; its workqueue layer (where neither is installed) aborts the
    process on concurrent parallel regions, so there they take turns. Until a frame has
    run, the layer is not chosen yet: the first frames take turns too."""
    import numba

    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel region has run in this process yet
        layer = None
    return _WORKQUEUE_LOCK if layer in (None, "workqueue") else contextlib.nullcontext()


def _claim(folder: Path, specs, settings, surfels, frame_format) -> None:
    """Mark ``folder`` as this sequence's, or refuse it, so that a resumed run never mixes
    the frames of two sequences nor keeps the frames of a model since changed.

    The manifest (MANIFEST) records two hashes: the model's content hash (every array and
    the material, ``dofsplat.fingerprint``: recoloured, with new weights, radii or
    opacities, it is another model) and the frames' (every frame's camera and lens, the
    settings, the frame format). A folder whose manifest differs in either is refused, not
    rendered over (as other arguments always were: no frame is deleted unasked): a
    DofsplatError names the folder and what differs, and its frames are left alone (delete
    them, or give another folder). So is a folder of frame files that
    no dofsplat sequence wrote (``frame_*`` without a manifest), and one of frames beside
    a damaged manifest; a damaged manifest beside no frames is written anew."""
    import hashlib

    from .fingerprint import content_hash
    from .io import atomic_write

    folder = Path(folder)
    mine = {"version": MANIFEST_VERSION, "model": content_hash(surfels),
            "sequence": hashlib.blake2b(repr((specs, settings, frame_format)).encode(),
                                        digest_size=16).hexdigest(),
            "frames": len(specs)}
    path = folder / MANIFEST
    have = _read_manifest(path)
    if isinstance(have, dict):
        if have.get("version") != MANIFEST_VERSION:
            raise DofsplatError(f"{folder} holds the frames of a sequence that an older "
                                "dofsplat wrote, which did not record the whole model: give "
                                "another folder, or delete it")
        differ = [text for key, text in (("model", "another model: its arrays or material "
                                                   "differ"),
                                         ("sequence", "other cameras, lenses or settings"))
                  if have.get(key) != mine[key]]
        if differ:
            raise DofsplatError(f"{folder} holds the frames of another sequence "
                                f"({'; '.join(differ)}): give another folder, or delete it")
        return
    if any(folder.glob("frame_*")):
        if have is None:
            raise DofsplatError(f"{folder} already holds frame files that no dofsplat "
                                "sequence wrote: give another folder")
        raise DofsplatError(f"{folder} holds frames whose record {MANIFEST} is damaged "
                            f"({have}), so which sequence they are is unknown: give another "
                            "folder, or delete it")

    def write(tmp: str) -> None:
        Path(tmp).write_text(json.dumps(mine) + "\n", encoding="utf-8")

    atomic_write(path, write)


def _read_manifest(path: Path):
    """A folder's manifest: its dict, None where there is none, or why it is damaged (str)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, ValueError) as e:
        return f"not readable JSON: {e}"
    if not isinstance(data, dict) or not isinstance(data.get("sequence"), str):
        return "not a dofsplat sequence record"
    return data


def _write_frame(folder: Path, index: int, image: np.ndarray, frame_format: str) -> None:
    from .io import write_image

    write_image(frame_path(folder, index, frame_format), image)  # atomic


def _render_into(folder, todo, total, surfels, settings, frame_format, client, progress):
    """Render ``todo`` into ``folder``, writing each frame as it finishes; a frame that
    fails is named and stops the sequence (the frames written so far stay)."""
    bar = _bar([], progress, total=total)
    bar.update(total - len(todo))
    try:
        if client is None:
            for spec in todo:
                _write_frame(folder, spec.index, _checked(render_frame, surfels, spec,
                                                          settings), frame_format)
                bar.update()
            return
        if not todo:
            return  # nothing to render: the model is not sent
        from dask.distributed import as_completed
        from distributed.scheduler import KilledWorker

        futures = _submit(client, surfels, settings, todo)
        index = {f.key: s.index for f, s in zip(futures, todo)}
        try:
            for future in as_completed(futures):
                k = index[future.key]
                try:
                    image = _named(future.result, k)
                except KilledWorker:
                    raise DofsplatError(f"frame {k}: the workers rendering it died (out of "
                                        "memory? the workers' logs tell)") from None
                _write_frame(folder, k, image, frame_format)
                bar.update()
        finally:
            for f in futures:
                f.cancel()
    finally:
        bar.close()


def _checked(fn, surfels, spec, settings):
    return _named(lambda: fn(surfels, spec, settings), spec.index)


def _named(call, index: int):
    """``call()``, its failure naming frame ``index``: a DofsplatError (a user's mistake) and
    running out of memory as one line; any other error (a bug) keeps its traceback, with
    the frame added as a note."""
    try:
        return call()
    except DofsplatError as e:
        raise DofsplatError(f"frame {index}: {e}") from None
    except MemoryError:
        raise DofsplatError(f"frame {index}: out of memory") from None
    except Exception as e:
        if hasattr(e, "add_note"):  # Python >= 3.11
            e.add_note(f"(dofsplat animate: while rendering frame {index})")
        raise


def _write_mp4(path, frames, fps):
    import av
    from fractions import Fraction
    from PIL import Image

    with av.open(str(path), mode="w", format="mp4") as box:
        stream = None
        for f in frames:
            rgb = np.asarray(Image.open(f).convert("RGB"))
            if stream is None:
                stream = box.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
                # H.264 in yuv420p wants even sizes: the last row or column is repeated
                height, width = rgb.shape[0] + rgb.shape[0] % 2, rgb.shape[1] + rgb.shape[1] % 2
                stream.height, stream.width = height, width
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": "18"}
            pad = ((0, height - rgb.shape[0]), (0, width - rgb.shape[1]), (0, 0))
            rgb = np.pad(rgb, pad, mode="edge")
            for packet in stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                box.mux(packet)
        for packet in stream.encode():
            box.mux(packet)
