"""The training cameras of a 3D Gaussian Splatting scene (``cameras.json``), for its default view.

A 3DGS trainer (Kerbl et al. 2023's ``train.py``; gsplat's and nerfstudio's exporters write
the same) saves the scene as ``MODEL/point_cloud/iteration_N/point_cloud.ply`` and its
training cameras as ``MODEL/cameras.json``: a list of

    {"id", "img_name", "width", "height", "position": [x, y, z],
     "rotation": [[...], [...], [...]], "fx", "fy"}

where position is the camera's centre in the world and rotation its camera-to-world rotation,
columns the camera's x (right), y (down) and z (forward) axes, OpenCV's frame as COLMAP's; the
principal point is the image's centre. ``load`` looks for the file beside the scene, then in
the model folder above ``point_cloud/iteration_N/``, and gives the scene:

* ``capture``: the first camera as dofsplat's view (eye, target, up, frustum at the trainers'
  near plane 0.01, size), which ``dofsplat render`` and ``view`` start from, as they start a
  depth capture from its sensor: the scene as the trainer saw it, the right way up;
* ``up_hint``: the cameras' mean up direction (their -y), for views framed otherwise.

A file that is not such a list is ignored with one warning: the scene renders as it would
without it.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np

NAME = "cameras.json"
TRAINERS_NEAR = 0.01  # the near plane of the trainers' projection (3DGS's znear)


def find_cameras_json(path) -> Path | None:
    """``cameras.json`` beside the scene file, or in the model folder of a trainer's
    ``point_cloud/iteration_N/point_cloud.ply``; None if there is none."""
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    candidates = [folder / NAME]
    if folder.parent.name == "point_cloud":
        candidates.append(folder.parent.parent / NAME)
    return next((c for c in candidates if c.is_file()), None)


def read_cameras_json(path) -> list[dict]:
    """The cameras of a cameras.json, each {"eye", "target", "up", "frustum", "size"} in
    dofsplat's terms (see the module docstring). Raises ValueError naming what is wrong."""
    path = Path(path)
    try:
        entries = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as e:
        raise ValueError(f"not UTF-8 text ({e.reason})") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"not JSON ({e.msg}, line {e.lineno})") from None
    if not isinstance(entries, list) or not entries:
        raise ValueError("not a non-empty list of cameras")
    return [_camera(entry, k) for k, entry in enumerate(entries)]


def _camera(entry, k: int) -> dict:
    where = f"camera {k}"
    if not isinstance(entry, dict):
        raise ValueError(f"{where} is not an object")
    missing = [key for key in ("width", "height", "position", "rotation", "fx", "fy")
               if key not in entry]
    if missing:
        raise ValueError(f"{where} has no {', '.join(missing)}")
    try:
        eye = np.asarray(entry["position"], np.float64).reshape(3)
        rotation = np.asarray(entry["rotation"], np.float64).reshape(3, 3)
        width, height = float(entry["width"]), float(entry["height"])
        fx, fy = float(entry["fx"]), float(entry["fy"])
    except (TypeError, ValueError):
        raise ValueError(f"{where}: position, rotation, width, height, fx and fy must be "
                         f"numbers (3, 3 x 3, and one each)") from None
    if not (np.all(np.isfinite(eye)) and np.all(np.isfinite(rotation))
            and all(math.isfinite(v) and v > 0 for v in (width, height, fx, fy))):
        raise ValueError(f"{where}: values must be finite, and sizes and focal lengths > 0")
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3):
        raise ValueError(f"{where}: rotation is not a rotation matrix")
    forward, down = rotation[:, 2], rotation[:, 1]
    n = TRAINERS_NEAR
    half_w, half_h = n * 0.5 * width / fx, n * 0.5 * height / fy
    return {"eye": eye, "target": eye + forward, "up": -down,
            "frustum": np.array([-half_w, half_w, -half_h, half_h, n]),
            "size": np.array([round(width), round(height)], np.float64)}


def attach_cameras(scene, path) -> None:
    """Give a loaded Gaussian scene its trainer's view (``capture``, ``up_hint``) from the
    cameras.json found for path, if any; a file that cannot be read is said and ignored."""
    found = find_cameras_json(path)
    if found is None:
        return
    try:
        cameras = read_cameras_json(found)
    except (OSError, ValueError) as e:
        warnings.warn(f"{found}: ignored ({e}); the scene is framed without its cameras",
                      stacklevel=3)
        return
    up = np.mean([c["up"] for c in cameras], axis=0)
    if np.linalg.norm(up) > 1e-6:
        scene.up_hint = tuple(float(v) for v in up / np.linalg.norm(up))
    scene.capture = cameras[0]
