"""Mesh files (OBJ, glTF, GLB, STL, OFF) to surfels, parsed by trimesh.

trimesh reads the file and its materials; each mesh of the scene (with its node's
transform applied) becomes one :class:`dofsplat.prep.meshes.MeshPart`, and all parts are sampled
together by :func:`dofsplat.prep.meshes.mesh_to_surfels`, so the sample density is the same
over the whole scene. Materials:

* glTF / GLB (PBR): baseColorTexture times baseColorFactor, alphaMode (OPAQUE, MASK with
  alphaCutoff, BLEND) and doubleSided;
* OBJ (MTL): map_Kd (the texture; Kd is then ignored, as most viewers do), else Kd;
  ``d`` / ``Tr`` are not read. An OBJ that names no material file but has texture
  coordinates (``vt``) takes its image from the ``texture`` option (``--texture``);
* vertex or face colours where the file has them (uchar: sRGB);
* nothing: grey 0.8.

PLY meshes are read by :mod:`dofsplat.io.ply` (faster for large ASCII files).
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np

from ..errors import DofsplatError, library_message
from ..surfels import Material, Surfels

MESH_EXTENSIONS = (".obj", ".gltf", ".glb", ".stl", ".off")


def read_mesh(path, *, material: Material | None = None, points: int | str | None = None,
              texture=None, smooth: bool = True, normalise: str = "object") -> Surfels:
    """Load a mesh file as surfels.

    points: samples over the whole mesh (None: the default of ``mesh_to_surfels``;
    "vertices": one surfel per vertex). texture: an image file applied through the mesh's
    texture coordinates to every part that has them, replacing the file's own textures.
    smooth: samples on the Phong tessellation of the faces (False: on the flat faces).
    normalise: the per-surfel normalisation, "object", "render" or "none".
    Raises DofsplatError for an unreadable file, a file without triangles, or a texture
    for a mesh without texture coordinates.
    """
    from ..prep.meshes import mesh_to_surfels
    from ..prep.normalise import check_method

    check_method(normalise)
    path = Path(path)
    if not path.is_file():
        raise DofsplatError(f"no such file: {path}")
    if path.stat().st_size == 0:
        raise DofsplatError(f"{path}: the file is empty (0 bytes)")
    image = load_texture(texture) if texture is not None else None
    scene = _load_scene(path)
    try:
        parts, skipped = scene_parts(scene, str(path))
    except (OSError, ValueError, SyntaxError) as e:
        # Pillow decodes an embedded texture only here, and a damaged one raises OSError
        # ("broken data stream when reading image file") or ValueError
        raise DofsplatError(f"{path}: an embedded texture image is damaged: "
                            f"{library_message(e)}") from e
    if not parts:
        what = f" (it holds {', '.join(skipped)})" if skipped else ""
        raise DofsplatError(f"{path}: no triangle mesh in the file{what}: a mesh without "
                            "faces cannot be sampled (save bare points as PLY to render them "
                            "as a point cloud)")
    if image is not None:
        textured = [p for p in parts if p.uv is not None]
        if not textured:
            raise DofsplatError(f"{path}: a texture image needs texture coordinates (vt in "
                                "an OBJ), and the mesh has none")
        for p in textured:
            # the given image replaces the part's own texture and colours
            p.texture, p.vertex_colors, p.base_color = image, None, (1.0, 1.0, 1.0, 1.0)
    elif any(p.uv is not None and p.texture is None and p.vertex_colors is None
             for p in parts):
        warnings.warn(f"{path}: the mesh has texture coordinates but no texture image; "
                      "give one (--texture FILE; texture= in dofsplat.io.load)", stacklevel=2)
    return mesh_to_surfels(parts, points, material=material, smooth=smooth,
                           normalise=normalise, source=str(path))


def _load_scene(path: Path):
    import trimesh

    # trimesh reports missing textures and the like through logging: make them warnings
    logger = logging.getLogger("trimesh")
    handler = _WarningHandler(str(path))
    logger.addHandler(handler)
    try:
        load = getattr(trimesh, "load_scene", None)
        if load is not None:
            return load(str(path), process=False)
        return trimesh.load(str(path), force="scene", process=False)
    except DofsplatError:
        raise
    except PermissionError as e:
        raise DofsplatError(f"{path}: cannot read: {e.strerror}") from e
    except Exception as e:  # trimesh, numpy, json and zip raise many types for bad files
        raise DofsplatError(f"{path}: cannot read the mesh: {library_message(e)}") from e
    finally:
        logger.removeHandler(handler)


class _WarningHandler(logging.Handler):
    def __init__(self, source: str):
        super().__init__(level=logging.WARNING)
        self.source = source

    def emit(self, record):
        warnings.warn(f"{self.source}: {record.getMessage()}", stacklevel=2)


def scene_parts(scene, source: str = "mesh"):
    """(parts, skipped): a MeshPart per mesh instance of a trimesh Scene, in world space,
    and the names of the kinds of geometry that are not triangle meshes."""
    import trimesh

    parts, skipped = [], set()
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geometry = scene.geometry.get(name)
        if isinstance(geometry, trimesh.Trimesh) and len(geometry.faces):
            parts.extend(_mesh_parts(geometry, np.asarray(transform, dtype=np.float64), name))
        elif geometry is not None:
            skipped.add("a mesh without faces" if isinstance(geometry, trimesh.Trimesh)
                        else type(geometry).__name__)
    return parts, sorted(skipped)


def _mesh_parts(mesh, transform: np.ndarray, name: str):
    """One MeshPart (a list of one) from a trimesh.Trimesh and its node transform."""
    from ..prep.meshes import MeshPart

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    vertices = vertices @ transform[:3, :3].T + transform[:3, 3]
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if np.linalg.det(transform[:3, :3]) < 0:
        faces = faces[:, ::-1]  # a mirroring transform turns the faces inside out
    visual = mesh.visual
    kw = {}
    if getattr(visual, "kind", None) == "texture":
        uv = getattr(visual, "uv", None)
        if uv is not None and len(uv) == len(vertices):
            kw["uv"] = np.asarray(uv, dtype=np.float64)
        kw.update(_material(visual.material))
    elif getattr(visual, "kind", None) == "vertex":
        kw["vertex_colors"] = _rgba8_to_linear(visual.vertex_colors)
    elif getattr(visual, "kind", None) == "face":
        # unshare the vertices so that each face keeps its own colour
        vertices = vertices[faces].reshape(-1, 3)
        colors = np.repeat(_rgba8_to_linear(visual.face_colors), 3, axis=0)
        faces = np.arange(len(vertices)).reshape(-1, 3)
        kw["vertex_colors"] = colors
    if "vertex_colors" in kw and np.any(kw["vertex_colors"][:, 3] < 1.0):
        kw["alpha_mode"] = "BLEND"
    return [MeshPart(vertices, faces, name=str(name), **kw)]


def _material(material) -> dict:
    """MeshPart fields from a trimesh PBRMaterial (glTF) or SimpleMaterial (OBJ)."""
    from ..prep.meshes import texture_from_image

    out = {}
    if material is None:
        return out
    if hasattr(material, "baseColorTexture"):  # PBR
        image, factor = material.baseColorTexture, material.baseColorFactor
        if factor is not None:  # trimesh keeps it as uint8 RGBA of the linear factor
            out["base_color"] = tuple(np.asarray(factor, dtype=np.float64) / 255.0)
        if image is not None:
            out["texture"] = texture_from_image(image)
        out["alpha_mode"] = (material.alphaMode or "OPAQUE").upper()
        if material.alphaCutoff is not None:
            out["alpha_cutoff"] = float(material.alphaCutoff)
        out["double_sided"] = bool(material.doubleSided)
    else:  # OBJ's SimpleMaterial: map_Kd, else Kd (trimesh's placeholder: neither)
        image = getattr(material, "image", None)
        if image is not None and not _is_placeholder(image):
            out["texture"] = texture_from_image(image)
        elif image is None and getattr(material, "diffuse", None) is not None:
            rgba = np.asarray(material.diffuse, dtype=np.float64) / 255.0
            out["base_color"] = (rgba[0], rgba[1], rgba[2], 1.0)
    return out


def _is_placeholder(image) -> bool:
    """trimesh gives an OBJ without a material file a tiny one-colour image: not a texture."""
    if image.size[0] * image.size[1] > 4:
        return False
    pixels = np.asarray(image.convert("RGBA")).reshape(-1, 4)
    return bool(np.all(pixels == pixels[0]))


def _rgba8_to_linear(rgba) -> np.ndarray:
    from ..colors import srgb_to_linear

    rgba = np.asarray(rgba, dtype=np.float64) / 255.0
    out = np.ones((len(rgba), 4), np.float32)
    out[:, :3] = srgb_to_linear(rgba[:, :3])
    if rgba.shape[1] == 4:
        out[:, 3] = rgba[:, 3]
    return out


def load_texture(path) -> np.ndarray:
    """(H, W, 4) float32 linear RGBA from an image file (sRGB colour, linear alpha)."""
    from ..prep.meshes import texture_from_image

    path = Path(path)
    if not path.is_file():
        raise DofsplatError(f"no such texture file: {path}")
    try:
        from PIL import Image

        with Image.open(path) as image:
            image.load()
            return texture_from_image(image)
    except DofsplatError:
        raise
    except Exception as e:  # Pillow raises many types for a damaged image
        raise DofsplatError(f"{path}: cannot read the texture image: "
                            f"{library_message(e)}") from e
