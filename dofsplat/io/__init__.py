"""Model and image I/O: one module per format, chosen by file extension.

``LOADERS`` maps a lower-case extension to a function ``loader(path, **options) ->
Surfels | Gaussians``; a new format registers itself by adding an entry (as trimesh's
exchange modules do). :func:`load` picks the loader of the longest extension the file name
ends with, so ``.ply.gz`` wins over ``.gz``. 3D Gaussian Splatting scenes (a 3DGS or
compressed PLY, ``.spz``, PlayCanvas SOG: ``.sog``, ``meta.json``, ``lod-meta.json`` or a
folder holding one of those) load as :class:`dofsplat.Gaussians`, everything else as
surfels.

Importing this package imports numpy only; each format imports its library (plyfile,
Pillow, OpenEXR, zstandard) when first used.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Callable

from ..errors import DofsplatError
from ..gaussians import Gaussians
from ..surfels import Surfels
from ..colors import linear_to_srgb, srgb_to_linear
from .images import (SUPPORTED_IMAGE_EXTENSIONS, atomic_write, check_output_path,
                     check_writable_path, nonfinite_pixels, read_image, write_depth,
                     write_image)
from .e57 import E57_EXTENSIONS, read_e57
from .las import LAS_EXTENSIONS, read_las
from .mesh import MESH_EXTENSIONS, read_mesh
from .model_file import EXTENSION as MODEL_FILE_EXTENSION, read_model_file
from . import prepared
from .pcd import PCD_EXTENSIONS, read_pcd
from .cameras_json import attach_cameras
from .gaussians import write_gaussian_ply
from .ply import (ply_kind, ply_options, read_ply, read_ply_header, read_surfel_ply,
                  write_surfel_ply)
from .sog import LOD_META, META, read_sog
from .spz import read_spz

LOADERS: dict[str, Callable[..., Surfels | Gaussians]] = {
    # any PLY: surfels, 3DGS (the trainers' or PlayCanvas's compressed one), a mesh or bare
    # points, told apart by its header
    ".ply": read_ply,
    ".ply.gz": read_ply,
    **{ext: read_mesh for ext in MESH_EXTENSIONS},
    **{ext: read_las for ext in LAS_EXTENSIONS},
    **{ext: read_e57 for ext in E57_EXTENSIONS},
    **{ext: read_pcd for ext in PCD_EXTENSIONS},
    # Gaussian scenes: Niantic's SPZ; PlayCanvas SOG, zipped, or its meta file (a folder
    # holding meta.json or lod-meta.json is read by read_sog too: see load)
    ".spz": read_spz,
    ".sog": read_sog,
    # a prepared model: surfels and their LOD tree, read through memory maps (model_file)
    MODEL_FILE_EXTENSION: read_model_file,
    META: read_sog,
    LOD_META: read_sog,
}
GAUSSIAN_LOADERS = (read_spz, read_sog)  # always Gaussians (read_ply: when the header says)

SAVERS: dict[str, Callable[..., object]] = {
    ".ply": write_surfel_ply,
    ".ply.gz": write_surfel_ply,
}

__all__ = ["LOADERS", "SAVERS", "SUPPORTED_IMAGE_EXTENSIONS", "atomic_write",
           "check_output_path", "check_writable_path", "linear_to_srgb", "load", "model_options",
           "nonfinite_pixels",
           "read_image",
           "read_e57", "read_las", "read_mesh", "read_model_file", "read_pcd", "read_ply",
           "read_surfel_ply",
           "read_sog", "read_spz", "save_surfels", "srgb_to_linear", "write_depth",
           "write_gaussian_ply", "write_image", "write_surfel_ply"]


def load(path, cache: str = "auto", **options) -> Surfels | Gaussians:
    """Load a model, choosing the loader by the file's extension: surfels, or for a 3D
    Gaussian Splatting scene :class:`dofsplat.Gaussians` (a 3DGS or compressed PLY, ``.spz``,
    a SOG ``.sog``, ``meta.json``, ``lod-meta.json`` or a folder holding one of those two).

    cache: "auto" keeps a model that took ``prepared.MIN_SECONDS`` or more to load (the
    normals, radii and normalisation of a point cloud, a mesh's sampling) in the user's
    cache folder and reads it from there next time, keyed by the file's content, the
    options and the preparation code (``dofsplat.cache``); "off" always prepares it.
    ``surfels.load_info`` says how long loading took and whether it came from the cache.

    options are passed to the loader: ``material`` for all; ``points`` (sample count or
    "vertices") and ``texture`` (an image file) for meshes; ``k`` (neighbours for normals
    and radii) and ``smooth`` (False keeps the measured positions) for point clouds;
    ``normalise`` ("object", the default for points and meshes, "render" or "none": the
    per-surfel normalisation of Section 6.3; a surfel or 3DGS PLY is taken as it is unless
    given one) for all (docs/formats.md lists them). Gaussian scenes take no options but a
    SOG LOD chain's ``level`` (0, the full scene, by default), and are never cached: they
    need no preparation, and decode in a second or two; a trainer's ``cameras.json`` beside
    one (or above its ``point_cloud/iteration_N/``) gives it its default view
    (:mod:`dofsplat.io.cameras_json`). Raises DofsplatError for a missing
    file, an unsupported extension, an option the loader does not take, or whatever the
    loader finds wrong with the file.
    """
    path = _model_file(path)
    loader = _loader(path)
    _check_options(loader, path, options)
    if cache not in ("auto", "off"):
        raise DofsplatError(f"cache must be 'auto' or 'off', got {cache!r}")
    use_cache = (cache == "auto" and not _holds_gaussians(path, loader)
                 and loader is not read_model_file)  # (prepared already)
    model = prepared.load_prepared(path, loader, options, use_cache=use_cache)
    if isinstance(model, Gaussians):
        attach_cameras(model, path)  # a trainer's cameras.json: the default view
    return model


def model_options(path) -> tuple[str, tuple[str, ...]]:
    """What :func:`load` makes of the model file at path, from its extension (and a PLY's
    header): (the kind of model in words, such as "a triangle mesh" or "a .laz file"; the
    options that apply to it besides ``material``, which applies to all). The command line
    checks its input options against these before loading, so that its message names them
    as the user typed them. Raises DofsplatError as :func:`load` does for a missing file or
    an unsupported extension."""
    path = _model_file(path)
    loader = _loader(path)
    if loader is read_ply:
        return ply_options(read_ply_header(path))
    if loader is read_sog:
        return "a SOG scene (3D Gaussian Splatting)", ("level",)
    if loader is read_spz:
        return "an SPZ scene (3D Gaussian Splatting)", ()
    names = list(inspect.signature(loader).parameters)[1:]
    ext = _extension(path, LOADERS, "model")
    return f"a {ext} file", tuple(n for n in names if n != "material")


def save_surfels(path, surfels: Surfels | Gaussians, **options) -> Path:
    """Save a model; the extension picks the format (``.ply`` or ``.ply.gz``): surfels as a
    surfel PLY (options are passed to the writer: ``binary=True``), Gaussians as a 3DGS
    PLY (:func:`write_gaussian_ply`, no options). Atomic; returns the path.
    """
    path = Path(path)
    saver = SAVERS[_extension(path, SAVERS, "model")]
    if isinstance(surfels, Gaussians):
        saver = write_gaussian_ply
    _check_options(saver, path, options, skip=2)
    return saver(path, surfels, **options)


def _model_file(path) -> Path:
    """path as a Path, or DofsplatError when it is missing, or is neither a file nor a
    folder holding a SOG scene (meta.json or lod-meta.json)."""
    path = Path(path)
    if not path.exists():
        raise DofsplatError(f"no such file: {path}")
    if path.is_dir():
        if not any((path / name).is_file() for name in (LOD_META, META)):
            raise DofsplatError(f"{path}: a folder, not a model file (a folder is read only "
                                f"as a SOG scene, with a {LOD_META} or {META} in it)")
        return path
    if not path.is_file():
        raise DofsplatError(f"not a file: {path}")
    return path


def _loader(path: Path) -> Callable[..., Surfels | Gaussians]:
    """The loader for a model file (by its extension) or a SOG folder."""
    if path.is_dir():
        return read_sog
    return LOADERS[_extension(path, LOADERS, "model")]


def _holds_gaussians(path: Path, loader) -> bool:
    """Whether the loader gives Gaussians (a PLY says so in its header)."""
    if loader in GAUSSIAN_LOADERS:
        return True
    return loader is read_ply and ply_kind(read_ply_header(path)) == "gaussians"


def _extension(path: Path, registry: dict, what: str) -> str:
    """The longest registered extension that the file name ends with (any case)."""
    name = path.name.lower()
    for ext in sorted(registry, key=len, reverse=True):
        if name.endswith(ext):
            return ext
    raise DofsplatError(f"{path}: unsupported {what} format; supported extensions: "
                        f"{', '.join(sorted(registry))}")


def _check_options(fn, path: Path, options: dict, skip: int = 1) -> None:
    # a typo in an option should be a clear error, not a TypeError from inside the loader
    params = list(inspect.signature(fn).parameters.values())[skip:]
    if any(p.kind is p.VAR_KEYWORD for p in params):
        return
    unknown = sorted(set(options) - {p.name for p in params})
    if unknown:
        known = ", ".join(p.name for p in params) or "none"
        raise DofsplatError(f"{path}: unknown option(s) {', '.join(unknown)} for this format "
                            f"(options: {known})")
