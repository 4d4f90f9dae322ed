"""E57 point clouds (ASTM E2807), the exchange format of terrestrial laser scanners, read by
pye57 (the ``e57`` extra: ``pip install "dofsplat[e57]"``; libE57Format's Python bindings).

An E57 file holds one or more scans, each in its scanner's own frame with a pose (a
rotation and a translation) into the file's common frame. Every scan is read with its pose
applied (pye57's ``read_scan(..., transform=True)``, which also turns spherical coordinates
into Cartesian ones) and the scans are merged into one cloud:

* colour: a scan's ``colorRed/Green/Blue`` (8-bit sRGB, or 16-bit where a value passes 255,
  as for LAS); a scan without colour is grey from its ``intensity``, scaled by the scan's
  intensity limits (or the range of its values), as sRGB; with neither, mid grey;
* normals: estimated by PCA over the merged cloud (``prep.pointcloud.points_to_surfels``)
  and turned towards the scanner that saw each point (the pose's translation), so that
  every surface faces the position it was scanned from, whichever scan it came from.

E57 frames are z-up (levelled scanners, georeferenced sites), like LAS: the points are
turned into dofsplat's y-up frame, (x, y, z) -> (x, z, -y), and shifted near the origin
when float32 would lose their precision (``io.las``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DofsplatError, library_message
from ..surfels import Material, Surfels

E57_EXTENSIONS = (".e57",)


def read_e57(path, *, material: Material | None = None, k: int | None = None,
             smooth: bool = True, normalise: str = "object") -> Surfels:
    """Load an .e57 file (all its scans, merged with their poses) as surfels; k, smooth
    and normalise as for LAS (``points_to_surfels``)."""
    from dataclasses import replace

    from ..prep.normalise import check_method
    from ..prep.pointcloud import points_to_surfels
    from .las import _recentre, z_up_to_y_up
    from .ply import finite_rows

    check_method(normalise)
    path = Path(path)
    positions, colors, sensors = read_e57_points(path)
    keep = finite_rows(positions, colors, source=str(path))
    positions, colors, sensors = positions[keep], colors[keep], sensors[keep]
    first = positions[:1].copy()
    positions = _recentre(positions, 1e-4, str(path))  # E57 stores doubles: 0.1 mm (in place)
    sensors = sensors + (positions[:1] - first)
    positions = z_up_to_y_up(positions)
    sensors = z_up_to_y_up(sensors)
    surfels = points_to_surfels(positions, colors, None, k=k, viewpoint=sensors,
                                smooth=smooth, normalise=normalise, source=str(path))
    return surfels if material is None else replace(surfels, material=material)


def read_e57_points(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions (N, 3) float64 in the file's frame, colours (N, 3) float32 linear, the
    position of the scanner that saw each point (N, 3) float64) of every scan."""
    try:
        import pye57
    except ImportError as e:
        raise DofsplatError(f"{path}: reading E57 needs pye57: pip install 'dofsplat[e57]'") from e
    from ..colors import srgb_to_linear

    parts = []
    try:
        with open(path, "rb") as f:
            signature = f.read(8)
    except OSError:
        signature = None  # (the reader below says why)
    if signature is not None and signature != b"ASTM-E57":
        raise DofsplatError(f"{path}: " + ("the file is empty (0 bytes)" if not signature else
                                           "not an E57 file (it does not start with the "
                                           "ASTM-E57 signature)"))
    try:
        e57 = pye57.E57(str(path), mode="r")
        try:
            for i in range(e57.scan_count):
                data = e57.read_scan(i, intensity=True, colors=True,
                                     ignore_missing_fields=True, transform=True)
                xyz = np.stack([np.asarray(data[c], np.float64) for c in
                                ("cartesianX", "cartesianY", "cartesianZ")], axis=1)
                if len(xyz) == 0:
                    continue
                grey = _scan_colors(data, e57.get_header(i), len(xyz))
                sensor = np.asarray(e57.scan_position(i), np.float64).reshape(3)
                parts.append((xyz, grey, np.broadcast_to(sensor, xyz.shape)))
        finally:
            e57.close()
    except DofsplatError:
        raise
    except PermissionError as e:
        raise DofsplatError(f"{path}: cannot read: {e.strerror}") from e
    except Exception as e:  # libE57Format raises its own types for damaged files
        raise DofsplatError(f"{path}: corrupt or truncated E57 file: "
                            f"{library_message(e)}") from e
    if not parts:
        raise DofsplatError(f"{path}: the file holds no points")
    positions = np.concatenate([p[0] for p in parts])
    colors = srgb_to_linear(np.concatenate([p[1] for p in parts]).astype(np.float32))
    sensors = np.concatenate([p[2] for p in parts])
    return positions, colors, sensors


def _scan_colors(data: dict, header, n: int) -> np.ndarray:
    """(n, 3) sRGB in [0, 1]: the scan's colour, else its intensity as grey, else mid grey."""
    rgb = [data.get(c) for c in ("colorRed", "colorGreen", "colorBlue")]
    if all(c is not None and len(c) == n for c in rgb):
        rgb = np.stack([np.asarray(c, np.float64) for c in rgb], axis=1)
        top = 255.0 if rgb.size == 0 or rgb.max() <= 255 else 65535.0
        return np.clip(rgb / top, 0.0, 1.0)
    intensity = data.get("intensity")
    if intensity is not None and len(intensity) == n:
        intensity = np.asarray(intensity, np.float64)
        lo, hi = _intensity_limits(header, intensity)
        grey = np.clip((intensity - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.full(n, 0.5)
        return np.repeat(grey[:, None], 3, axis=1)
    return np.full((n, 3), 0.5)


def _intensity_limits(header, intensity: np.ndarray) -> tuple[float, float]:
    """The scan's declared intensity limits, else the range of its values."""
    try:
        limits = header.node["intensityLimits"]
        return float(limits["intensityMinimum"].value()), float(limits["intensityMaximum"].value())
    except Exception:  # noqa: BLE001 - optional in the standard
        return float(intensity.min()), float(intensity.max())
