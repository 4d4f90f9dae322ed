"""Tests of the model loaders (issue 4, items 1, 2 and 5): every format on small files that
the tests write, on the real files in ../shared/data (skipped when absent), mesh sampling,
and the one-line errors of bad input.
"""

from __future__ import annotations

import dataclasses
import gzip
import math
import struct
import warnings

import numpy as np
import pytest
from conftest import SHARED_DATA, front_camera, gaussian_ply_columns
from PIL import Image
from plyfile import PlyData, PlyElement

import dofsplat as ds
from dofsplat import cli
from dofsplat.errors import DofsplatError
from dofsplat.gaussians import Gaussians
from dofsplat.io import LOADERS, load, save_surfels, srgb_to_linear
from dofsplat.io.gaussians import SH_C0, gaussians_to_surfels, quaternion_matrices
from dofsplat.io.las import read_las_points
from dofsplat.io.pcd import parse_pcd_header, read_pcd_columns
from dofsplat.io.ply import parse_ply_header, ply_kind, read_ply_header, triangulate
from dofsplat.prep.meshes import (
    RADIUS_SCALE,
    MeshPart,
    mesh_to_surfels,
    mip,
    poisson_eliminate,
    sample_texture,
)
from dofsplat.prep.normalise import normalise, object_sums
from dofsplat.surfels import Surfels

U8 = 1.0 / 255.0  # one step of an 8-bit value


def assert_rows(a, row, atol=1e-6):
    """Every row of a equals row (numpy's assert_allclose does not broadcast)."""
    a = np.asarray(a, np.float64)
    assert len(a) > 0
    np.testing.assert_allclose(a, np.broadcast_to(np.asarray(row, np.float64), a.shape),
                               atol=atol, rtol=0)


def shared(relative: str):
    """The path of a real model in ../shared/data, or skip the test with the reason."""
    path = SHARED_DATA / relative
    if not path.is_file():
        pytest.skip(f"real model {relative} not found in {SHARED_DATA} (the shared data "
                    "folder is absent on this machine)")
    return path


@pytest.fixture
def captured_points(monkeypatch):
    """Replace points_to_surfels with a recorder of its arguments (it still runs)."""
    import dofsplat.prep.pointcloud as pc

    calls = []
    real = pc.points_to_surfels

    def spy(positions, colors=None, normals=None, **kw):
        calls.append(dict(positions=np.array(positions), colors=None if colors is None
                          else np.array(colors), normals=None if normals is None
                          else np.array(normals), **kw))
        return real(positions, colors, normals, **kw)

    monkeypatch.setattr(pc, "points_to_surfels", spy)
    return calls


# ---------------------------------------------------------------------------------------
# small files the tests write


def grid_points(n=12, spacing=0.1):
    """n x n points on the z = 0 plane: a well-posed cloud for PCA normals."""
    g = np.arange(n) * spacing
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    return np.stack([x, y, np.zeros(n * n)], axis=1)


def write_vertex_ply(path, columns: dict, text=False, faces=None, comments=()):
    n = len(next(iter(columns.values())))
    records = np.empty(n, dtype=[(k, np.asarray(v).dtype) for k, v in columns.items()])
    for k, v in columns.items():
        records[k] = v
    elements = [PlyElement.describe(records, "vertex")]
    if faces is not None:
        face = np.empty(len(faces), dtype=[("vertex_indices", "O")])
        face["vertex_indices"] = [np.asarray(f, np.int32) for f in faces]
        elements.append(PlyElement.describe(face, "face",
                                            val_types={"vertex_indices": "i4"}))
    ply = PlyData(elements, text=text, comments=list(comments))
    if str(path).endswith(".gz"):
        with gzip.open(path, "wb") as f:
            ply.write(f)
    else:
        ply.write(str(path))
    return path


def xyz_columns(points, dtype=np.float32):
    return {"x": points[:, 0].astype(dtype), "y": points[:, 1].astype(dtype),
            "z": points[:, 2].astype(dtype)}


def square_mesh(n=4, size=1.0):
    """An n x n grid of squares (2 triangles each) on [0, size]^2, z = 0, facing +z."""
    g = np.linspace(0.0, size, n + 1)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    vertices = np.stack([x, y, np.zeros_like(x)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return vertices, faces


def test_registry_covers_every_format():
    for ext in (".ply", ".ply.gz", ".obj", ".gltf", ".glb", ".stl", ".off", ".las", ".laz",
                ".pcd"):
        assert ext in LOADERS


# -- PLY: header and dispatch ------------------------------------------------------------


def test_ply_header_parsing():
    head = (b"ply\nformat binary_little_endian 1.0\ncomment TextureFile tex.png\n"
            b"element vertex 3\nproperty float x\nproperty uchar red\n"
            b"element face 1\nproperty list uchar int vertex_indices\nend_header\r\nDATA")
    h = parse_ply_header(head)
    assert h.format == "binary_little_endian"
    assert h.comments == ("TextureFile tex.png",)
    assert [(e.name, e.count) for e in h.elements] == [("vertex", 3), ("face", 1)]
    assert h.element("vertex").names == ("x", "red")
    face = h.element("face").properties[0]
    assert (face.dtype, face.count_dtype) == ("i4", "u1")
    assert head[h.body_offset:] == b"DATA"
    for bad, why in [(b"plx\n", "not a PLY file"), (b"ply\nformat ascii 1.0\n", "end_header"),
                     (b"ply\nformat ascii 9\nend_header\n", "format line"),
                     (b"ply\nformat ascii 1.0\nelement v x\nend_header\n", "element line"),
                     (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "before any"),
                     (b"ply\nformat ascii 1.0\nelement v 1\nproperty quad x\nend_header\n",
                      "property line"),
                     (b"ply\nelement v 1\nend_header\n", "no format")]:
        with pytest.raises(DofsplatError, match=why):
            parse_ply_header(bad, "f.ply")


@pytest.mark.parametrize("names, faces, kind", [
    (("x", "y", "z", "f_dc_0", "scale_0", "rot_0", "nx", "ny", "nz"), 0, "gaussians"),
    (("x", "y", "z", "nx", "ny", "nz", "radius"), 5, "surfels"),
    (("x", "y", "z", "nx"), 0, "surfels"),  # half a normal: a damaged surfel file
    (("x", "y", "z"), 4, "mesh"),
    (("x", "y", "z", "red", "green", "blue"), 0, "points"),
    (("x", "y", "z", "nx", "ny", "nz"), 0, "points"),
])
def test_ply_kind(names, faces, kind):
    props = "".join(f"property float {n}\n" for n in names)
    face = f"element face {faces}\nproperty list uchar int vertex_indices\n"
    head = f"ply\nformat ascii 1.0\nelement vertex 1\n{props}{face}end_header\n".encode()
    assert ply_kind(parse_ply_header(head)) == kind


def test_surfel_ply_still_loads_exactly(tmp_path):
    rng = np.random.default_rng(3)
    s = Surfels(positions=rng.normal(size=(40, 3)), normals=rng.normal(size=(40, 3)),
                radius=rng.uniform(0.1, 1, 40), colors=rng.uniform(0, 1, (40, 3)))
    path = save_surfels(tmp_path / "s.ply.gz", s)
    back = load(path)
    np.testing.assert_array_equal(back.positions, s.positions)
    np.testing.assert_array_equal(back.radius, s.radius)
    with pytest.raises(DofsplatError, match=r"a surfel PLY: option\(s\) k do not apply"):
        load(path, k=8)


# -- PLY: bare points --------------------------------------------------------------------


def test_points_are_smoothed_unless_asked_not_to(tmp_path, capsys):
    # a plane z = 0 with noise of +-1 mm across it at 1 cm spacing: smoothing takes most of
    # the noise out (measured rms 0.55 -> 0.12 mm); smooth=False and --no-smooth keep it
    rng = np.random.default_rng(8)
    g = (np.arange(30) - 14.5) * 0.01
    x, y = np.meshgrid(g, g)
    xyz = np.stack([x.ravel(), y.ravel(), rng.uniform(-1e-3, 1e-3, 900)], axis=1)
    path = write_vertex_ply(tmp_path / "noisy.ply", xyz_columns(xyz.astype(np.float32)))
    raw = load(path, smooth=False)
    np.testing.assert_array_equal(raw.positions, xyz.astype(np.float32))
    smooth = load(path)
    assert np.sqrt(np.mean(smooth.positions[:, 2] ** 2)) < 0.5 * np.sqrt(np.mean(xyz[:, 2] ** 2))
    np.testing.assert_allclose(smooth.positions[:, :2], xyz[:, :2], atol=2e-4)  # across only
    out = tmp_path / "noisy.png"
    status, err = run_cli(["render", path, "-o", out, "--size", "32x32", "--no-smooth",
                           "--no-dof"], capsys)
    assert status == 0, err
    surfel_file = save_surfels(tmp_path / "surfels.ply", raw)
    with pytest.raises(DofsplatError, match=r"option\(s\) smooth do not apply"):
        load(surfel_file, smooth=False)


@pytest.mark.parametrize("text", [False, True])
def test_ply_points_uchar_colours(tmp_path, text, captured_points):
    pts = grid_points()
    n = len(pts)
    red = np.arange(n, dtype=np.uint8)
    cols = dict(xyz_columns(pts), red=red, green=np.full(n, 255, np.uint8),
                blue=np.zeros(n, np.uint8))
    path = write_vertex_ply(tmp_path / "p.ply", cols, text=text)
    s = load(path, k=8)
    call = captured_points[-1]
    np.testing.assert_allclose(call["positions"], pts, atol=1e-7)
    assert call["normals"] is None and call["k"] == 8
    np.testing.assert_allclose(call["colors"][:, 0], srgb_to_linear(red / 255.0), atol=1e-6)
    np.testing.assert_allclose(call["colors"][:, 1], 1.0, atol=1e-6)
    assert len(s) == n
    # PCA on a plane: every normal is +-z
    np.testing.assert_allclose(np.abs(s.normals[:, 2]), 1.0, atol=1e-4)
    lo, hi = s.bounds()
    np.testing.assert_allclose(lo, pts.min(0), atol=1e-6)
    np.testing.assert_allclose(hi, pts.max(0), atol=1e-6)


def test_ply_points_other_colour_types_normals_and_alpha(tmp_path, captured_points):
    pts = grid_points(6)
    n = len(pts)
    cols = dict(xyz_columns(pts), nx=np.zeros(n, np.float32), ny=np.zeros(n, np.float32),
                nz=np.ones(n, np.float32), red=np.full(n, 65535, np.uint16),
                green=np.full(n, 32768, np.uint16), blue=np.zeros(n, np.uint16),
                alpha=np.full(n, 128, np.uint8))
    s = load(write_vertex_ply(tmp_path / "p16.ply", cols))
    call = captured_points[-1]
    np.testing.assert_allclose(call["normals"], np.tile([0, 0, 1.0], (n, 1)))
    np.testing.assert_allclose(call["colors"][0], [1.0, srgb_to_linear(32768 / 65535), 0.0],
                               atol=1e-6)
    np.testing.assert_allclose(s.opacity, 128 / 255, atol=1e-6)
    np.testing.assert_allclose(s.normals[:, 2], 1.0, atol=1e-6)  # given normals kept
    floats = dict(xyz_columns(pts), red=np.full(n, 0.25, np.float32),
                  green=np.full(n, 0.5, np.float32), blue=np.full(n, 1.0, np.float32))
    load(write_vertex_ply(tmp_path / "pf.ply", floats))
    np.testing.assert_allclose(captured_points[-1]["colors"][0], [0.25, 0.5, 1.0])  # linear


def test_ply_points_nan_rows_dropped_and_all_nan_is_an_error(tmp_path):
    pts = grid_points(6)
    x = pts[:, 0].astype(np.float32)
    x[[3, 7]] = np.nan
    path = write_vertex_ply(tmp_path / "nan.ply", dict(xyz_columns(pts), x=x))
    with pytest.warns(UserWarning, match=r"dropped 2 of 36 points with NaN"):
        s = load(path)
    assert len(s) == 34
    path = write_vertex_ply(tmp_path / "allnan.ply",
                            {k: np.full(4, np.nan, np.float32) for k in "xyz"})
    with pytest.raises(DofsplatError, match=r"no valid points \(all 4 have NaN"):
        load(path)


def test_ply_points_options_that_do_not_apply(tmp_path):
    path = write_vertex_ply(tmp_path / "p.ply", xyz_columns(grid_points(4)))
    with pytest.raises(DofsplatError, match=r"a point cloud .*option\(s\) points, texture"):
        load(path, points=10, texture="t.png")


# -- PLY: meshes -------------------------------------------------------------------------


@pytest.mark.parametrize("text, suffix", [(True, ".ply"), (False, ".ply"), (True, ".ply.gz"),
                                          (False, ".ply.gz")])
def test_ply_mesh_sampled(tmp_path, text, suffix):
    v, f = square_mesh(4, 2.0)
    path = write_vertex_ply(tmp_path / f"m{suffix}", xyz_columns(v), text=text, faces=f)
    s = load(path, points=500, normalise="none")
    assert len(s) == 500
    lo, hi = s.bounds()
    assert np.all(lo[:2] >= -1e-6) and np.all(hi[:2] <= 2 + 1e-6)
    assert np.all(hi[:2] > 1.9) and np.all(lo[:2] < 0.1)  # the samples reach the corners
    np.testing.assert_allclose(s.normals, np.tile([0, 0, 1.0], (500, 1)), atol=1e-6)
    # radii: the samples share the area 4 equally, r^2 x weight averages to 4 / 500, and
    # the disks are RADIUS_SCALE wider than that area's radius
    area = s.radius.astype(np.float64) ** 2 * s.weight
    assert np.mean(area) == pytest.approx(4.0 / 500, rel=1e-5)
    np.testing.assert_allclose(s.weight, 1 / RADIUS_SCALE**2, rtol=1e-6)
    np.testing.assert_allclose(s.colors, 0.8, atol=1e-6)
    # by default the loader normalises: the object-space sums at the surfels come near 1
    # (measured away from the edges: mean |S - 1| 0.073 before, 0.009 after, max 0.23, 0.046)
    normalised = load(path, points=500)
    np.testing.assert_array_equal(normalised.positions, s.positions)
    inner = np.all((s.positions[:, :2] > 0.3) & (s.positions[:, :2] < 1.7), axis=1)
    before, after = (np.abs(object_sums(m)[inner] - 1) for m in (s, normalised))
    assert after.mean() < 0.02 and after.max() < 0.08
    assert before.mean() > 3 * after.mean()


def test_ply_mesh_polygons_colours_and_texture(tmp_path):
    # one quad and one pentagon (ragged: plyfile's reader), vertex colours in uchar sRGB
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0],
                  [1.5, 1.5, 0]], np.float32)
    faces = [[0, 1, 2, 3], [1, 4, 5, 6, 2]]
    red = np.array([255, 255, 255, 255, 0, 0, 0], np.uint8)
    cols = dict(xyz_columns(v), red=red, green=np.zeros(7, np.uint8),
                blue=np.zeros(7, np.uint8))
    for text in (True, False):
        s = load(write_vertex_ply(tmp_path / f"poly{text}.ply", cols, text=text, faces=faces),
                 points=400)
        assert len(s) == 400
        left = s.positions[:, 0] < 0.999
        assert_rows(s.colors[left], [1, 0, 0])
        assert s.colors[~left, 0].min() < 0.5  # the pentagon fades to black
    tris = triangulate(np.array([[0, 1, 2, 3]]), 4)
    np.testing.assert_array_equal(tris, [[0, 1, 2], [0, 2, 3]])
    # per-vertex uv and the texture that a comment names
    v, f = square_mesh(1, 1.0)
    image = np.zeros((2, 2, 3), np.uint8)
    image[:, 0] = (255, 0, 0)  # left column red, right column blue
    image[:, 1] = (0, 0, 255)
    Image.fromarray(image).save(tmp_path / "tex.png")
    cols = dict(xyz_columns(v), s=v[:, 0].astype(np.float32), t=v[:, 1].astype(np.float32))
    path = write_vertex_ply(tmp_path / "tex.ply", cols, faces=f,
                            comments=["TextureFile tex.png"])
    s = load(path, points=2000)
    far_left, far_right = s.positions[:, 0] < 0.2, s.positions[:, 0] > 0.8
    # bilinear with REPEAT wrapping: x < 0.25 blends with the right column through the wrap
    assert np.all(s.colors[far_left, 0] > s.colors[far_left, 2])
    assert np.all(s.colors[far_right, 2] > s.colors[far_right, 0])
    with pytest.raises(DofsplatError, match=r"needs texture coordinates"):
        load(write_vertex_ply(tmp_path / "nouv.ply", xyz_columns(v), faces=f),
             texture=tmp_path / "tex.png")


def test_ply_mesh_vertices_mode_and_bad_faces(tmp_path):
    v, f = square_mesh(4, 2.0)
    s = load(write_vertex_ply(tmp_path / "m.ply", xyz_columns(v), faces=f), points="vertices",
             normalise="none")
    assert len(s) == 25
    interior = np.all((v[:, :2] > 0.1) & (v[:, :2] < 1.9), axis=1)
    order = np.lexsort((s.positions[:, 0], s.positions[:, 1]))
    # an interior vertex of a grid of spacing h stands for h^2 = r^2 x weight, h = 0.5
    area = s.radius.astype(np.float64) ** 2 * s.weight
    np.testing.assert_allclose(area[order][interior], 0.25, rtol=1e-6)
    np.testing.assert_allclose(s.radius[order][interior], 0.5 * RADIUS_SCALE, rtol=1e-6)
    bad = write_vertex_ply(tmp_path / "bad.ply", xyz_columns(v), faces=[[0, 1, 99]])
    with pytest.raises(DofsplatError, match=r"refers to vertex 99"):
        load(bad)
    flat = write_vertex_ply(tmp_path / "flat.ply", xyz_columns(v), faces=[[0, 1, 2]])
    with pytest.raises(DofsplatError, match=r"zero area"):
        load(flat)  # three collinear vertices of the grid's first row


# -- 3D Gaussian Splatting -------------------------------------------------------------


def gaussian_columns(n, rng=None, **overrides):
    """The 3DGS PLY columns (``gaussian_ply_columns``) of n random Gaussians of degree 0,
    sigmas e^-4 to e^-2, mostly opaque; the columns named in ``overrides`` replaced."""
    rng = rng or np.random.default_rng(0)

    def normal(k):
        return np.stack([rng.normal(size=n) for _ in range(k)], axis=1)

    positions, f_dc, logits = normal(3), normal(3), rng.normal(size=n) + 2
    log_scales = np.stack([rng.uniform(-4, -2, n) for _ in range(3)], axis=1)
    cols = gaussian_ply_columns(positions, log_scales, normal(4), logits, f_dc[:, None, :])
    cols.update({k: np.asarray(v, np.float32) for k, v in overrides.items()})
    return cols


def test_gaussians_axes_colour_opacity(tmp_path):
    # one Gaussian turned 90 degrees about z (quaternion not normalised: x3), scales
    # (0.1, 0.02, 0.3) along its local x, y, z
    q = 3.0 * np.array([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    cols = gaussian_columns(1, x=[1.0], y=[2.0], z=[3.0], f_dc_0=[1.0], f_dc_1=[0.0],
                            f_dc_2=[-5.0], opacity=[0.0], scale_0=[math.log(0.1)],
                            scale_1=[math.log(0.02)], scale_2=[math.log(0.3)],
                            rot_0=[q[0]], rot_1=[q[1]], rot_2=[q[2]], rot_3=[q[3]])
    path = write_vertex_ply(tmp_path / "g.ply", cols)
    g = load(path)  # a 3DGS PLY loads as Gaussians (tests/test_gaussian_io.py); as surfels:
    s = gaussians_to_surfels(g)
    assert s.is_elliptical and len(s) == 1
    # local y (the smallest axis) turned by 90 degrees about z is world -x: the normal
    np.testing.assert_allclose(np.abs(s.normals[0]), [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(np.abs(s.tangent[0]), [0, 0, 1], atol=1e-6)  # local z
    assert s.radius[0] == pytest.approx(0.6, rel=1e-5)  # 2 sigma of the largest axis
    assert s.radius_v[0] == pytest.approx(0.2, rel=1e-5)  # local x, sigma 0.1
    expected = srgb_to_linear(np.clip(0.5 + SH_C0 * np.array([1.0, 0.0, -5.0]), 0, 1))
    np.testing.assert_allclose(s.colors[0], expected, atol=1e-6)
    assert s.opacity[0] == pytest.approx(0.5)
    np.testing.assert_allclose(s.positions[0], [1, 2, 3])


def test_gaussians_rotation_matrices_are_rotations():
    q = np.random.default_rng(1).normal(size=(100, 4)) * 5
    r = quaternion_matrices(q)
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.tile(np.eye(3), (100, 1, 1)),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    assert np.all(np.isnan(quaternion_matrices(np.zeros((1, 4)))))


def test_gaussians_bad_rows_and_invisible_ones():
    cols = gaussian_columns(10)
    cols["rot_0"][:] = 1.0
    for i in range(1, 4):
        cols[f"rot_{i}"][2] = 0.0
    cols["rot_0"][2] = 0.0  # a zero quaternion
    cols["scale_1"][5] = 500.0  # absurd
    cols["opacity"][7] = -20.0  # invisible: dropped silently
    with pytest.warns(UserWarning, match=r"dropped 2 of 10 Gaussians"):
        s = gaussians_to_surfels(cols, source="g")
    assert len(s) == 7
    cols["opacity"][:] = -20.0
    with pytest.raises(DofsplatError, match=r"every Gaussian has opacity below"), \
            pytest.warns(UserWarning, match=r"dropped 2 of 10 Gaussians"):
        gaussians_to_surfels(cols, source="g")
    with pytest.raises(DofsplatError, match=r"lacks rot_3"):
        gaussians_to_surfels({k: v for k, v in cols.items() if k != "rot_3"})


def test_gaussian_scene_renders_without_holes_and_blended(tmp_path):
    """A red half-transparent layer of Gaussians in front of an opaque blue one: the
    interior shows no background, and both colours mix."""
    rng = np.random.default_rng(2)
    g = np.linspace(-0.6, 0.6, 25)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    n = len(x)
    sigma = 0.05  # spacing 0.05: sigma = spacing, like trained 3DGS splats overlap
    layers = []
    for z, dc, logit in ((0.0, (-1.8, -1.8, 1.8), 6.0), (0.3, (1.8, -1.8, -1.8), 0.0)):
        jitter = rng.uniform(-0.01, 0.01, (n, 2))
        layers.append(gaussian_columns(
            n, rng, x=x + jitter[:, 0], y=y + jitter[:, 1], z=np.full(n, z),
            f_dc_0=np.full(n, dc[0]), f_dc_1=np.full(n, dc[1]), f_dc_2=np.full(n, dc[2]),
            opacity=np.full(n, logit), scale_0=np.full(n, math.log(sigma)),
            scale_1=np.full(n, math.log(sigma)), scale_2=np.full(n, math.log(0.002)),
            rot_0=np.ones(n), rot_1=np.zeros(n), rot_2=np.zeros(n), rot_3=np.zeros(n)))
    cols = {k: np.concatenate([layer[k] for layer in layers]) for k in layers[0]}
    s = gaussians_to_surfels(load(write_vertex_ply(tmp_path / "layers.ply", cols)))
    result = ds.render(s, front_camera(64, 64, distance=2.0), None,
                       ds.RenderSettings(shading="none"))
    inner = result.image[24:40, 24:40]
    assert inner[..., 3].min() > 0.99  # no holes: opaque everywhere inside
    red, blue = inner[..., 0].mean(), inner[..., 2].mean()
    # half-transparent red over blue: both show, neither wins outright
    assert 0.25 < red < 0.75 and 0.2 < blue < 0.75, (red, blue)


# -- OBJ, glTF, STL, OFF (trimesh) -------------------------------------------------------


def write_textured_obj(tmp_path, with_mtl=True):
    # top half green (v > 0.5), bottom half black; 64 rows, so that the bilinear blend
    # across the wrap at v = 0 (REPEAT) stays within v < 1/128
    image = np.zeros((64, 64, 3), np.uint8)
    image[:32, :] = (0, 255, 0)
    Image.fromarray(image).save(tmp_path / "tex.png")
    lines = ["v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0",
             "vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1"]
    if with_mtl:
        (tmp_path / "quad.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd tex.png\n")
        lines = ["mtllib quad.mtl", "usemtl m"] + lines
    lines += ["f 1/1 2/2 3/3", "f 1/1 3/3 4/4"]
    path = tmp_path / "quad.obj"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("with_mtl", [True, False])
def test_obj_texture_through_uv(tmp_path, with_mtl):
    path = write_textured_obj(tmp_path, with_mtl)
    options = {} if with_mtl else {"texture": tmp_path / "tex.png"}
    s = load(path, points=1000, **options)
    assert len(s) == 1000
    y = s.positions[:, 1]
    top, bottom = (y > 0.55) & (y < 0.98), (y > 0.02) & (y < 0.45)
    assert_rows(s.colors[top], [0, 1, 0])
    assert_rows(s.colors[bottom], [0, 0, 0])
    np.testing.assert_allclose(s.normals[:, 2], 1.0, atol=1e-6)
    if not with_mtl:
        with pytest.warns(UserWarning, match=r"texture coordinates but no texture"):
            s = load(path, points=100)
        np.testing.assert_allclose(s.colors, 0.8, atol=1e-6)


def test_obj_stl_off_and_meshes_without_faces(tmp_path):
    (tmp_path / "t.stl").write_text(
        "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n"
        "vertex 0 1 0\nendloop\nendfacet\nendsolid t\n")
    (tmp_path / "t.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    for name in ("t.stl", "t.off"):
        s = load(tmp_path / name, points=300)
        assert len(s) == 300
        assert np.all(s.positions[:, 0] + s.positions[:, 1] <= 1 + 1e-6)
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(DofsplatError, match=r"no triangle mesh in the file.*without faces"):
        load(tmp_path / "points.obj")
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(DofsplatError, match=r"zero area"):
        load(tmp_path / "flat.obj")
    with pytest.raises(DofsplatError, match=r"no such texture file"):
        load(tmp_path / "t.off", texture=tmp_path / "missing.png")
    with pytest.raises(DofsplatError, match=r"unknown option\(s\) k"):
        load(tmp_path / "t.off", k=8)


def test_glb_alpha_modes_round_trip_through_trimesh(tmp_path):
    """A GLB written by trimesh with an OPAQUE, a MASK and a BLEND quad."""
    import trimesh
    from trimesh.visual.material import PBRMaterial
    from trimesh.visual.texture import TextureVisuals

    # alpha rises from 0 at the bottom of the texture to 1 at its top
    alpha = np.repeat(np.linspace(255, 0, 16).astype(np.uint8)[:, None], 16, axis=1)
    rgba = np.dstack([np.full((16, 16, 3), 200, np.uint8), alpha])
    image = Image.fromarray(rgba, "RGBA")
    scene = trimesh.Scene()
    for i, mode in enumerate(("OPAQUE", "MASK", "BLEND")):
        v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float) + [2.0 * i, 0, 0]
        uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
        material = PBRMaterial(baseColorTexture=image, alphaMode=mode, alphaCutoff=0.5,
                               doubleSided=(mode == "BLEND"))
        mesh = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False,
                               visual=TextureVisuals(uv=uv, material=material))
        scene.add_geometry(mesh, geom_name=mode)
    path = tmp_path / "modes.glb"
    path.write_bytes(scene.export(file_type="glb"))
    s = load(path, points=3000)
    opaque, mask, blend = (np.abs(s.positions[:, 0] - (2 * i + 0.5)) < 0.51 for i in range(3))
    np.testing.assert_allclose(s.opacity[opaque], 1.0)
    assert opaque.sum() == pytest.approx(1000, abs=25)  # one third of the area
    # MASK keeps the upper half (alpha >= 0.5) only, fully opaque
    assert s.positions[mask, 1].min() > 0.4 and mask.sum() == pytest.approx(500, rel=0.1)
    np.testing.assert_allclose(s.opacity[mask], 1.0)
    # BLEND: opacity follows alpha (up the quad), twins face both ways (double-sided)
    lo, hi = s.opacity[blend].min(), s.opacity[blend].max()
    assert lo < 0.1 and hi > 0.9
    assert np.corrcoef(s.positions[blend, 1], s.opacity[blend])[0, 1] > 0.95
    assert np.sum(s.normals[blend, 2] > 0) == np.sum(s.normals[blend, 2] < 0)
    # colour 200 / 255 is sRGB
    assert_rows(s.colors[opaque], [srgb_to_linear(200 / 255)] * 3, atol=2e-3)


# -- LAS / LAZ ---------------------------------------------------------------------------


def write_las(path, points, rgb=None, scale=0.001):
    import laspy

    header = laspy.LasHeader(point_format=3 if rgb is not None else 0, version="1.2")
    header.scales = [scale] * 3
    header.offsets = np.floor(points.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    if rgb is not None:
        las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    las.write(str(path))
    return path


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_colours_and_y_up(tmp_path, suffix, captured_points):
    pts = grid_points(8)[:, [0, 2, 1]]  # a vertical wall in LAS's z-up frame
    n = len(pts)
    rgb = np.stack([np.full(n, 65535), np.full(n, 32768), np.zeros(n)], 1).astype(np.uint16)
    s = load(write_las(tmp_path / f"wall{suffix}", pts, rgb), k=6)
    call = captured_points[-1]
    # (x, y, z) -> (x, z, -y): the wall stands up in y
    np.testing.assert_allclose(call["positions"], pts[:, [0, 2, 1]] * [1, 1, -1], atol=1e-3)
    np.testing.assert_allclose(call["colors"][0], [1.0, srgb_to_linear(32768 / 65535), 0],
                               atol=1e-6)
    assert len(s) == n and call["k"] == 6
    # 8-bit values in the 16-bit fields are recognised
    rgb8 = np.stack([np.full(n, 255), np.full(n, 128), np.zeros(n)], 1).astype(np.uint16)
    _, colors, _ = read_las_points(write_las(tmp_path / f"w8{suffix}", pts, rgb8))
    np.testing.assert_allclose(colors[0], [1.0, srgb_to_linear(128 / 255), 0], atol=1e-6)


def test_las_far_from_origin_is_recentred(tmp_path, captured_points):
    pts = grid_points(8) + [512_345.0, 5_432_100.0, 250.0]  # UTM-like
    with pytest.warns(UserWarning, match=r"beyond float32 precision; shifted"):
        s = load(write_las(tmp_path / "utm.las", pts))
    lo, hi = s.bounds()
    assert np.all(np.abs(lo) < 10) and np.all(np.abs(hi) < 10)
    # the grid spacing survives (float32 at 5e6 would round it to 0.5)
    d = np.diff(np.unique(np.round(captured_points[-1]["positions"][:, 0], 4)))
    np.testing.assert_allclose(d, 0.1, atol=2e-3)


def test_las_bad_files(tmp_path):
    bad = tmp_path / "bad.las"
    bad.write_bytes(b"LASF" + bytes(300))
    with pytest.raises(DofsplatError, match=r"bad\.las: corrupt or truncated LAS/LAZ"):
        load(bad)
    good = write_las(tmp_path / "g.laz", grid_points(8))
    cut = tmp_path / "cut.laz"
    cut.write_bytes(good.read_bytes()[:-40])
    with pytest.raises(DofsplatError, match=r"cut\.laz"):
        load(cut)


# -- PCD ---------------------------------------------------------------------------------


def pcd_bytes(fields, types, sizes, columns, mode="ascii", width=None, height=1,
              viewpoint="0 0 0 1 0 0 0"):
    """A PCD file with the given (POINTS,) columns."""
    import lzf

    n = len(columns[0])
    width = n if width is None else width
    head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {' '.join(fields)}\n"
            f"SIZE {' '.join(map(str, sizes))}\nTYPE {' '.join(types)}\n"
            f"COUNT {' '.join('1' for _ in fields)}\nWIDTH {width}\nHEIGHT {height}\n"
            f"VIEWPOINT {viewpoint}\nPOINTS {n}\nDATA {mode}\n").encode()
    dts = [np.dtype(f"<{t.lower() if t != 'F' else 'f'}{s}") for t, s in zip(types, sizes)]
    cols = [np.asarray(c).astype(d) for c, d in zip(columns, dts)]
    if mode == "ascii":
        # a float-packed colour: its uint32 integer, as PCL writes it (the float is a NaN)
        cols = [c.view(np.uint32) if f in ("rgb", "rgba") and c.dtype == np.float32 else c
                for f, c in zip(fields, cols)]
        rows = [" ".join(repr(c[i].item()) for c in cols) for i in range(n)]
        return head + ("\n".join(rows) + "\n").encode()
    if mode == "binary":
        rec = np.empty(n, dtype=[(f"f{i}", d) for i, d in enumerate(dts)])
        for i, c in enumerate(cols):
            rec[f"f{i}"] = c
        return head + rec.tobytes()
    raw = b"".join(c.tobytes() for c in cols)
    packed = lzf.compress(raw, 2 * len(raw) + 64)  # room to grow: random data does not shrink
    return head + struct.pack("<II", len(packed), len(raw)) + packed


def packed_rgb(r, g, b) -> np.ndarray:
    return ((np.asarray(r, np.uint32) << 16) | (np.asarray(g, np.uint32) << 8)
            | np.asarray(b, np.uint32) | np.uint32(0xFF000000)).astype(np.uint32)


@pytest.mark.parametrize("mode", ["ascii", "binary", "binary_compressed"])
@pytest.mark.parametrize("rgb_type", ["U", "F"])
def test_pcd_modes_and_packed_colour(tmp_path, mode, rgb_type, captured_points):
    pts = grid_points(6)
    n = len(pts)
    rgb = packed_rgb(np.full(n, 255), np.arange(n), np.zeros(n))
    if rgb_type == "F":
        rgb = rgb.view(np.float32)  # PCL's float-packed rgb
    path = tmp_path / "c.pcd"
    path.write_bytes(pcd_bytes(["x", "y", "z", "rgb"], ["F", "F", "F", rgb_type], [4] * 4,
                               [pts[:, 0], pts[:, 1], pts[:, 2], rgb], mode=mode))
    header, columns = read_pcd_columns(path)
    assert header.points == n and header.data == mode
    s = load(path)
    call = captured_points[-1]
    np.testing.assert_allclose(call["positions"], pts, atol=1e-6)
    np.testing.assert_allclose(call["colors"][:, 1], srgb_to_linear(np.arange(n) / 255),
                               atol=1e-6)
    assert call["viewpoint"] is None  # PCL's default VIEWPOINT says nothing
    assert len(s) == n


def test_pcd_ascii_colour_printed_as_a_float(tmp_path):
    """Old writers printed the float whose bits are the colour (alpha 0: a denormal)."""
    bits = np.array([0x00FF8000, 0x000000FF], np.uint32)
    rows = [f"{0.1 * i} 0 1 {bits[i].view(np.float32).item()!r}" for i in range(2)]
    data = (b"FIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\nWIDTH 2\nPOINTS 2\nDATA ascii\n"
            + "\n".join(rows).encode())
    (tmp_path / "old.pcd").write_bytes(data)
    _, columns = read_pcd_columns(tmp_path / "old.pcd")
    np.testing.assert_array_equal(columns["rgb"][:, 0], bits)


def test_pcd_organised_cloud_with_nan_and_normals(tmp_path, captured_points):
    w, h = 6, 4
    g = np.arange(w * h, dtype=np.float64)
    x, y, z = (g % w) * 0.1, (g // w) * 0.1, np.full(w * h, 2.0)
    x[[0, 5]] = np.nan  # pixels without depth
    normals = [np.zeros(w * h), np.zeros(w * h), -np.ones(w * h)]
    path = tmp_path / "org.pcd"
    path.write_bytes(pcd_bytes(["x", "y", "z", "normal_x", "normal_y", "normal_z"],
                               ["F"] * 6, [4] * 6, [x, y, z, *normals],
                               mode="binary_compressed", width=w, height=h,
                               viewpoint="0 0 0.5 1 0 0 0"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # NaN pixels of an organised cloud: no warning
        s = load(path)
    call = captured_points[-1]
    assert len(call["positions"]) == w * h - 2
    # turned from the optical frame: (x, -y, -z), the sensor too
    np.testing.assert_allclose(call["positions"][:, 2], -2.0)
    np.testing.assert_allclose(call["viewpoint"], [0, 0, -0.5])
    np.testing.assert_allclose(call["normals"], [[0, 0, 1]] * (w * h - 2))
    np.testing.assert_allclose(s.normals[:, 2], 1.0, atol=1e-6)  # towards the sensor


def test_pcd_capture_is_seen_from_its_sensor(tmp_path, capsys):
    """An organised cloud (a 64 x 48 depth capture with an off-centre principal point:
    a wall 2 m away with a box in front, some pixels without depth): the intrinsics are
    recovered from the grid, and ``dofsplat render`` without camera options sees it from
    the sensor, pixel for pixel: the depth drawn at every pixel with depth is the capture's
    (to 0.5 %: splats overlap their neighbours by the prefilter), the size is the grid's."""
    from dofsplat import cli

    w, h, fx, fy, cx, cy = 64, 48, 60.0, 58.0, 30.0, 21.0
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = np.full((h, w), 2.0)
    z[14:30, 20:40] = 1.5  # the box
    z[::7, ::11] = np.nan  # pixels without depth
    x, y = (u - cx) / fx * z, (v - cy) / fy * z
    path = tmp_path / "capture.pcd"
    path.write_bytes(pcd_bytes(["x", "y", "z"], ["F"] * 3, [4] * 3,
                               [x.ravel(), y.ravel(), z.ravel()], width=w, height=h))
    s = load(path, normalise="none")
    cam = s.capture
    np.testing.assert_allclose(cam["size"], [w, h])
    near = cam["frustum"][4]
    np.testing.assert_allclose(cam["frustum"][:4] / near,
                               [(-0.5 - cx) / fx, (w - 0.5 - cx) / fx, -(h - 0.5 - cy) / fy,
                                (0.5 + cy) / fy], rtol=1e-4)
    status = cli.main(["render", str(path), "-o", str(tmp_path / "c.png"), "--no-dof",
                       "--depth", str(tmp_path / "d.npy"), "-q"])
    assert status == 0
    depth = np.load(tmp_path / "d.npy")
    assert depth.shape == (h, w)
    valid = np.isfinite(z)
    # inside the box and on the wall above it: away from the box's outline, where a pixel
    # may show the nearer surface's splat
    interior = np.zeros_like(valid)
    interior[16:28, 22:38] = True
    interior[:10, :] = True
    np.testing.assert_allclose(depth[interior & valid], z[interior & valid], rtol=5e-3)


def test_a_converted_capture_keeps_its_view(tmp_path, capsys):
    """``dofsplat convert`` keeps a depth capture's sensor view and its unlit default in
    the surfel PLY's header (``comment dofsplat view ...``): rendering the PLY is rendering
    the capture, to the bit. Until 2026-11-27 both were lost, and the converted model of
    the shared data's five_people.pcd rendered lit, from a framing camera, 8 dB from the
    capture's own frame."""
    from dofsplat import cli

    w, h, fx, cx, cy = 32, 24, 30.0, 15.0, 11.0
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = np.full((h, w), 2.0)
    z[8:16, 10:20] = 1.5
    x, y = (u - cx) / fx * z, (v - cy) / fx * z
    path = tmp_path / "capture.pcd"
    rgb = np.full(w * h, float(np.frombuffer(np.array([0x00C08040], "<u4").tobytes(), "<f4")[0]))
    path.write_bytes(pcd_bytes(["x", "y", "z", "rgb"], ["F"] * 4, [4] * 4,
                               [x.ravel(), y.ravel(), z.ravel(), rgb], width=w, height=h))
    ply = tmp_path / "capture.ply"
    assert cli.main(["convert", str(path), "-o", str(ply), "-q"]) == 0
    kept = load(ply)
    original = load(path)
    assert kept.shading_hint == "none"
    for key in ("eye", "target", "up", "size", "frustum"):
        np.testing.assert_allclose(kept.capture[key], original.capture[key], rtol=1e-15)
    for name, src in (("a.npy", path), ("b.npy", ply)):
        assert cli.main(["render", str(src), "-o", str(tmp_path / name), "-q"]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "a.npy"), np.load(tmp_path / "b.npy"))


def test_pcd_header_errors():
    ok = b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\n"
    assert parse_pcd_header(ok + b"DATA ascii\n").points == 2
    for bad, why in [(b"hello\n", "unexpected line"), (ok, "no DATA"),
                     (ok + b"DATA zip\n", "DATA must be"),
                     (ok.replace(b"TYPE F F F", b"TYPE F F Q") + b"DATA ascii\n", "TYPE Q"),
                     (ok.replace(b"SIZE 4 4 4", b"SIZE 4 4") + b"DATA ascii\n",
                      "one entry per field"),
                     (ok.replace(b"POINTS 2", b"POINTS 3") + b"DATA ascii\n", "is not POINTS"),
                     (ok.replace(b"WIDTH 2", b"WIDTH -2") + b"DATA ascii\n", "whole numbers"),
                     (ok + b"VIEWPOINT 0 0\nDATA ascii\n", "VIEWPOINT needs 7")]:
        with pytest.raises(DofsplatError, match=why):
            parse_pcd_header(bad, "f.pcd")


def test_pcd_truncated_and_corrupt_data(tmp_path):
    pts = grid_points(5)
    cols = [pts[:, 0], pts[:, 1], pts[:, 2]]
    for mode, why in [("ascii", "truncated"), ("binary", "truncated"),
                      ("binary_compressed", "truncated|corrupt")]:
        data = pcd_bytes(["x", "y", "z"], ["F"] * 3, [4] * 3, cols, mode=mode)
        path = tmp_path / f"{mode}.pcd"
        path.write_bytes(data[:-30])
        with pytest.raises(DofsplatError, match=why):
            load(path)
    data = bytearray(pcd_bytes(["x", "y", "z"], ["F"] * 3, [4] * 3, cols,
                               mode="binary_compressed"))
    data[-20:] = b"\xff" * 20
    (tmp_path / "lzf.pcd").write_bytes(bytes(data))
    with pytest.raises(DofsplatError, match=r"corrupt PCD file"):
        load(tmp_path / "lzf.pcd")
    empty = pcd_bytes(["x", "y", "z"], ["F"] * 3, [4] * 3, [[], [], []])
    (tmp_path / "empty.pcd").write_bytes(empty)
    with pytest.raises(DofsplatError, match=r"holds no points"):
        load(tmp_path / "empty.pcd")


# ---------------------------------------------------------------------------------------
# mesh sampling (dofsplat.prep.meshes)


def test_sampling_is_area_uniform_and_deterministic():
    # a 4 x 1 strip cut into triangles of very different sizes at x = 0.1, 1, 2.6
    xs = np.array([0.0, 0.1, 1.0, 2.6, 4.0])
    v = np.array([[x, y, 0.0] for x in xs for y in (0.0, 1.0)])
    faces = [f for i in range(4) for f in ([2 * i, 2 * i + 2, 2 * i + 3],
                                           [2 * i, 2 * i + 3, 2 * i + 1])]
    part = MeshPart(v, faces)
    s = mesh_to_surfels(part, 4000)
    # equal areas get equal counts, across faces of any size, within 5 % (the blue-noise
    # elimination keeps a few % more samples near the strip's boundary: windows stay off
    # it, and hold a little less than their share of the count)
    windows = [(0.3, 1.3), (1.5, 2.5), (2.7, 3.7)]
    counts = [np.count_nonzero((s.positions[:, 0] >= lo) & (s.positions[:, 0] < hi)
                               & (s.positions[:, 1] > 0.1) & (s.positions[:, 1] < 0.9))
              for lo, hi in windows]
    for c in counts:
        assert c == pytest.approx(np.mean(counts), rel=0.05), counts
        assert c == pytest.approx(4000 * 0.8 / 4.0, rel=0.08), counts
    # the candidates before the elimination: every face gets its share to one sample
    import dofsplat.prep.meshes as meshes

    geo = meshes._face_geometry(part)
    face = meshes._candidates([part], [geo], 8000, 4.0)[1]
    share = 8000 * geo.area / 4.0
    assert np.abs(np.bincount(face, minlength=len(share)) - share).max() <= 1.0
    again = mesh_to_surfels(part, 4000)
    np.testing.assert_array_equal(s.positions, again.positions)


def test_sphere_normals_and_radii():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    s = mesh_to_surfels(MeshPart(sphere.vertices, sphere.faces), 6000, normalise="none")
    radial = s.positions / np.linalg.norm(s.positions, axis=1)[:, None]
    angle = np.degrees(np.arccos(np.clip(np.sum(radial * s.normals, 1), -1, 1)))
    # interpolated vertex normals of a 642-vertex icosphere: within 2 degrees of the truth
    assert angle.max() < 2.0, angle.max()
    area = sphere.area
    assert np.sum(s.radius.astype(np.float64) ** 2 * s.weight) == pytest.approx(area, rel=1e-4)
    # the radii follow the local spacing: no point is far from its neighbours' scale
    assert s.radius.max() / s.radius.min() < 2.5


def test_phong_positions():
    import trimesh

    from dofsplat.prep.meshes import phong_positions

    # a coarse icosphere (42 vertices): samples on the Phong tessellation lie nearer the
    # sphere than on the flat faces (measured: mean | |p| - 1 | 0.044 flat, 0.017 smooth)
    ico = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    part = MeshPart(ico.vertices, ico.faces)
    err = {}
    for smooth in (False, True):
        s = mesh_to_surfels(part, 5000, smooth=smooth, normalise="none")
        err[smooth] = np.mean(np.abs(np.linalg.norm(s.positions, axis=1) - 1))
    assert err[True] < err[False] / 2
    # through the vertices; a flat face (vertex normals = face normal) stays flat; at a
    # crease (a cube's corners: 54.7 degrees from every face) the face stays flat too
    rng = np.random.default_rng(3)
    v = rng.normal(size=(50, 3, 3))
    n = rng.normal(size=(50, 3, 3))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    for k in range(3):
        corner = np.zeros((50, 3))
        corner[:, k] = 1
        np.testing.assert_allclose(phong_positions(v, n, corner), v[:, k], atol=1e-12)
    bary = rng.dirichlet((1, 1, 1), 50)
    flat = np.einsum("nk,nkd->nd", bary, v)
    np.testing.assert_allclose(phong_positions(v, np.repeat(fn[:, None], 3, 1), bary),
                               flat, atol=1e-12)
    cube = trimesh.creation.box()  # 8 shared vertices: hard corners, flat faces, flat normals
    on_faces = mesh_to_surfels(MeshPart(cube.vertices, cube.faces), 3000, normalise="none")
    assert np.all(np.abs(np.abs(on_faces.positions).max(axis=1) - 0.5) < 1e-6)
    assert np.all(np.abs(on_faces.normals).max(axis=1) > 1 - 1e-6)


def test_sampled_plane_covers_without_holes():
    """A sampled square rendered head on: no holes, and most of the surface near 1.

    A regular grid sums to 1 +- 6 % here; irregular samples cannot, and the per-surfel
    normalisation (dofsplat.prep.normalise) is the remedy: this is the state before it.
    """
    v, f = square_mesh(20, 2.0)
    s = mesh_to_surfels(MeshPart(v - [1, 1, 0], f), 5000, normalise="none")
    cam = ds.Camera(eye=(0, 0, 3), target=(0, 0, 0), width=128, height=128, fov_y=30)
    w = ds.render(s, cam, None, ds.RenderSettings(shading="none")).weight[32:96, 32:96]
    assert w.min() > 0.2  # no holes
    assert np.mean(np.abs(w - 1) < 0.1) > 0.4
    assert np.mean(w) == pytest.approx(1.0, abs=0.05)


def test_sampled_plane_close_up_sums_to_1():
    """Seen close up (6 px per sample spacing, the kernels resolved), a sampled square sums
    to 1 +- 0.1 almost everywhere with the defaults: disks RADIUS_SCALE wider than the
    area they stand for, then the object-space normalisation. With disks of that area's
    radius (r = h) the same normalisation cannot flatten the dips between blue-noise
    samples. Measured: 0.978 against 0.78 (bench/RESULTS.md has the whole square)."""
    from dofsplat.prep.normalise import uniformity

    v, f = square_mesh(4, 1.0)
    s = mesh_to_surfels(MeshPart(v, f), 40_000)
    narrow = normalise(dataclasses.replace(s, radius=s.radius / RADIUS_SCALE, weight=None),
                       "object", progress=False)
    h = math.sqrt(1.0 / 40_000)
    side = int(round(6 * 0.4 / h))  # the middle 0.4 x 0.4 at 6 px per spacing
    cam = ds.Camera(eye=(0.5, 0.5, 2.0), target=(0.5, 0.5, 0.0), width=side, height=side,
                    fov_y=2 * math.degrees(math.atan(0.2 / 2.0)))
    settings = ds.RenderSettings(shading="none", lod=False)
    wide_u = uniformity(ds.render(s, cam, None, settings), cam)
    narrow_u = uniformity(ds.render(narrow, cam, None, settings), cam)
    assert wide_u > 0.97
    assert narrow_u < 0.9


def eliminate_slow(points, area, n_keep):
    """The weighted sample elimination by brute force: drop the argmax weight each time."""
    m = len(points)
    r_max = math.sqrt(area / (2 * math.sqrt(3) * n_keep))
    r_min = r_max * (1 - (n_keep / m) ** 1.5) * 0.65
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    w = np.where(d < 2 * r_max, (1 - np.maximum(d, r_min) / (2 * r_max)) ** 8, 0.0)
    np.fill_diagonal(w, 0.0)
    alive = np.ones(m, bool)
    weight = w.sum(1)
    for _ in range(m - n_keep):
        i = int(np.argmax(np.where(alive, weight, -np.inf)))
        alive[i] = False
        weight -= w[i]
    return alive


def test_elimination_matches_its_slow_twin():
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(0, 1, (600, 2)), np.zeros(600)])
    fast = poisson_eliminate(points, 1.0, 200)
    np.testing.assert_array_equal(fast, eliminate_slow(points, 1.0, 200))
    # blue noise: the closest pair is far apart compared with random picks
    from scipy.spatial import cKDTree

    kept = points[fast]
    nearest = cKDTree(kept).query(kept, k=2)[0][:, 1]
    assert nearest.min() > 0.5 * math.sqrt(1.0 / (2 * math.sqrt(3) * 200))


def test_texture_lookup_and_mip():
    t = np.arange(16, dtype=np.float64).reshape(4, 4, 1)
    # texel centres: u = (j + 0.5) / 4, v = 1 - (i + 0.5) / 4
    np.testing.assert_allclose(sample_texture(t, [[0.125, 0.875]]), [[0.0]])
    np.testing.assert_allclose(sample_texture(t, [[0.25, 0.875]]), [[0.5]])  # halfway
    np.testing.assert_allclose(sample_texture(t, [[1.125, -0.125]]), [[0.0]])  # REPEAT
    np.testing.assert_allclose(sample_texture(t, [[0.0, 0.875]]), [[1.5]])  # wraps to 3
    np.testing.assert_allclose(mip(t, 1)[..., 0], [[2.5, 4.5], [10.5, 12.5]])
    assert mip(t, 5).shape == (1, 1, 1)


def test_mask_blend_and_double_sided_parts():
    v, f = square_mesh(1, 1.0)
    rgba = np.ones((len(v), 4), np.float32)
    rgba[:, 3] = v[:, 1]  # alpha 0 at the bottom, 1 at the top
    mask = mesh_to_surfels(MeshPart(v, f, vertex_colors=rgba, alpha_mode="MASK",
                                    alpha_cutoff=0.5), 1000)
    assert mask.positions[:, 1].min() >= 0.49 and np.all(mask.opacity == 1)
    blend = mesh_to_surfels(MeshPart(v, f, vertex_colors=rgba, alpha_mode="BLEND",
                                     double_sided=True), 1000)
    np.testing.assert_allclose(blend.opacity, blend.positions[:, 1], atol=1e-5)
    assert len(blend) == 2 * np.count_nonzero(blend.normals[:, 2] > 0)
    with pytest.raises(DofsplatError, match=r"alpha mode must be"):
        MeshPart(v, f, alpha_mode="GLASS")
    with pytest.raises(DofsplatError, match=r"sample count must be"):
        mesh_to_surfels(MeshPart(v, f), 0)


# ---------------------------------------------------------------------------------------
# the real files in ../shared/data


def test_real_dragon_res4_mesh():
    path = shared("stanford_dragon/dragon_vrip_res4.ply")
    header = read_ply_header(path)
    assert ply_kind(header) == "mesh" and header.element("vertex").count == 5205
    s = load(path, points=20000)
    assert len(s) == 20000
    lo, hi = s.bounds()
    np.testing.assert_allclose(lo, [-0.108, 0.053, -0.050], atol=2e-3)
    np.testing.assert_allclose(hi, [0.096, 0.196, 0.041], atol=2e-3)
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-5)
    v = load(path, points="vertices")
    assert 5000 < len(v) <= 5205


def test_real_dragon_full_gz_vertices(tmp_path):
    """The 437k-vertex ASCII dragon (gzip): parsed by the fast reader in a few seconds."""
    path = shared("stanford_dragon/dragon_vrip.ply.gz")
    s = load(path, points="vertices")
    assert 430_000 < len(s) <= 437_645
    lo, hi = s.bounds()
    assert hi[1] - lo[1] == pytest.approx(0.144, abs=0.003)


def test_real_lion_laz_and_ply_agree():
    laz = shared("lion_takanawa/lion_takanawa.copc.laz")
    ply = shared("lion_takanawa/lion_takanawa_xyzrgb.ply")
    positions, colors, scale = read_las_points(laz)
    assert len(positions) == 341_989 and scale == pytest.approx(0.01)
    assert colors.min() >= 0 and colors.max() <= 1
    vertex = PlyData.read(str(ply))["vertex"]
    np.testing.assert_allclose(vertex["x"], positions[:, 0], atol=1e-5)
    # the PLY's uchar colours are the LAS's 16-bit ones >> 8
    from dofsplat.io import linear_to_srgb

    red16 = np.round(linear_to_srgb(colors[:, 0].astype(np.float64)) * 65535)
    assert np.abs(np.floor(red16 / 256) - np.asarray(vertex["red"], np.float64)).max() <= 1


def test_real_lion_laz_loads():
    s = load(shared("lion_takanawa/lion_takanawa.copc.laz"))
    assert 250_000 < len(s) <= 341_989  # duplicates (1 cm quantisation) are merged
    lo, hi = s.bounds()
    # y-up: the statue's height (LAS z, -3.45 .. 1.12) is now y
    np.testing.assert_allclose([lo[1], hi[1]], [-3.45, 1.12], atol=0.02)
    assert 0.2 < float(np.mean(s.colors)) < 0.35


@pytest.mark.parametrize("name, valid", [("table_scene_mug_stereo_textured.pcd", 209_280),
                                         ("five_people.pcd", 239_075)])
def test_real_pcd_scenes(name, valid):
    header, columns = read_pcd_columns(shared(f"pcl_scenes/{name}"))
    assert (header.width, header.height, header.data) == (640, 480, "binary_compressed")
    z = columns["z"][:, 0]
    assert np.count_nonzero(np.isfinite(z)) == valid
    assert np.nanmin(z) > 0.6  # depth in metres in front of the sensor


def test_real_mug_scene_loads_facing_the_sensor():
    s = load(shared("pcl_scenes/table_scene_mug_stereo_textured.pcd"))
    assert len(s) == 209_280
    lo, hi = s.bounds()
    assert hi[2] < -0.6 and lo[2] > -2.7  # in front of the sensor, which looks along -z
    # oriented towards the sensor at the origin
    assert np.mean(np.sum(s.normals * -s.positions, axis=1) > 0) > 0.999


def test_real_gaussian_donut():
    g = load(shared("gaussian_donut/fused.ply"))
    assert isinstance(g, Gaussians) and len(g) == 45_624
    s = gaussians_to_surfels(g)  # the flattening a surfel renderer used
    assert s.is_elliptical and 40_000 < len(s) <= 45_624
    assert s.opacity.min() >= 1 / 255 and s.opacity.max() <= 1
    assert np.all(s.radius_v <= s.radius + 1e-9)
    lo, hi = s.bounds()
    assert np.all(hi - lo < 0.25) and np.all(hi - lo > 0.05)


def test_real_spot_with_texture():
    s = load(shared("spot/spot_triangulated.obj"), points=20000,
             texture=shared("spot/spot_texture.png"))
    assert len(s) == 20000
    luma = s.colors.mean(axis=1)
    # a white cow with dark patches (linear 0.05, sRGB 0.25): both extremes are common
    assert np.mean(luma < 0.1) > 0.05 and np.mean(luma > 0.5) > 0.3


def test_real_alpha_blend_sample():
    s = load(shared("alpha_blend_test/AlphaBlendModeTest.glb"), points=50000)
    partial = (s.opacity > 0.05) & (s.opacity < 0.95)
    assert np.count_nonzero(partial) > 500  # the BLEND panel and decal
    assert np.mean(s.opacity == 1.0) > 0.8


@pytest.mark.parametrize("name", ["stanford_bunny/stanford-bunny.obj", "armadillo/armadillo.obj"])
def test_real_obj_meshes(name):
    s = load(shared(name), points=10000)
    assert len(s) == 10000
    assert np.all(np.isfinite(s.positions)) and s.radius.min() > 0


# ---------------------------------------------------------------------------------------
# bad input through the command line: one line, exit status 2, nothing written


def run_cli(argv, capsys):
    status = cli.main([str(a) for a in argv])
    _, err = capsys.readouterr()
    return status, err


@pytest.mark.parametrize("case", ["truncated", "corrupt", "extension", "empty", "nan",
                                  "no_faces", "pcd_garbage", "option"])
def test_cli_bad_input_one_line(tmp_path, capsys, case):
    v, f = square_mesh(2)
    if case == "truncated":
        path = write_vertex_ply(tmp_path / "m.ply", xyz_columns(v), faces=f)
        path.write_bytes(path.read_bytes()[:-10])
    elif case == "corrupt":
        path = tmp_path / "c.ply"
        path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                         b"property float y\nproperty float z\nend_header\n0 0 zero\n1 1 1\n")
    elif case == "extension":
        path = tmp_path / "model.xyz"
        path.write_text("0 0 0\n")
    elif case == "empty":
        path = tmp_path / "e.ply"
        path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                         b"property float y\nproperty float z\nend_header\n")
    elif case == "nan":
        path = write_vertex_ply(tmp_path / "n.ply", {k: np.full(5, np.nan, np.float32)
                                                     for k in "xyz"})
    elif case == "no_faces":
        path = tmp_path / "p.obj"
        path.write_text("v 0 0 0\nv 1 0 0\n")
    elif case == "pcd_garbage":
        path = tmp_path / "g.pcd"
        path.write_bytes(bytes(range(256)))
    else:
        path = write_vertex_ply(tmp_path / "o.ply", xyz_columns(v), faces=f)
    out = tmp_path / "out.png"
    extra = ["--k", "5"] if case == "option" else []
    status, err = run_cli(["render", path, "-o", out, "--size", "32x32", *extra], capsys)
    assert status == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("dofsplat: error: "), err
    assert str(path.name) in lines[0]
    assert not out.exists()


def test_cli_renders_a_mesh_with_input_options(tmp_path, capsys):
    path = write_textured_obj(tmp_path, with_mtl=False)
    out = tmp_path / "quad.png"
    status, err = run_cli(["render", path, "-o", out, "--size", "48x48", "--points", "3000",
                           "--texture", tmp_path / "tex.png", "--no-dof", "--shading",
                           "none"], capsys)
    assert status == 0, err
    image = np.asarray(Image.open(out).convert("RGB"), np.float64)
    assert image[12, 24, 1] > 200 and image[12, 24, 0] < 30  # top half green
    assert image[34, 24].max() < 30  # bottom half black


def test_pcd_capture_has_no_holes_from_its_sensor(tmp_path):
    """A depth capture of a tilted textured wall (60 degrees from facing the sensor), its
    depth quantised in 1.5 % steps as a structured-light sensor's is: seen from the sensor,
    every pixel away from the image border is covered (alpha >= 0.99). Surfels sized by 3-D
    neighbours left 62 % of them below that (tilted surfaces are under-covered and depth
    steps split the surface into layers); sized by the sensor's pixels
    (``capture_footprints``) none is. The colours are rendered unshaded by default, so a
    grey wall is its own grey wherever its normals point."""
    from dofsplat import cli

    w, h, f = 64, 48, 60.0
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rx, ry = (u - (w - 1) / 2) / f, (v - (h - 1) / 2) / f
    # the plane z = 2 + tan(60 deg) x, seen along the rays (x, y, z) = z (rx, ry, 1)
    z = 2.0 / (1.0 - np.tan(np.radians(60.0)) * rx)
    z = np.where((z > 0) & (z < 8), z, np.nan)
    z = np.round(z / (0.015 * z)) * (0.015 * z)  # depth steps of 1.5 %
    x, y = rx * z, ry * z
    grey = np.full(w * h, 150)
    rgb = packed_rgb(grey, grey, grey)
    path = tmp_path / "wall.pcd"
    path.write_bytes(pcd_bytes(["x", "y", "z", "rgb"], ["F", "F", "F", "U"], [4] * 4,
                               [x.ravel(), y.ravel(), z.ravel(), rgb], width=w, height=h))
    s = load(path)
    assert s.tangent is not None and s.shading_hint == "none"
    assert cli.main(["render", str(path), "-o", str(tmp_path / "c.npy"), "--no-dof",
                     "--no-lod", "-q"]) == 0
    image = np.load(tmp_path / "c.npy")
    # away from the image border, and where the wall is seen within 75 degrees of face-on:
    # beyond that a footprint would stretch more than CAPTURE_MAX_STRETCH (4 ~ 1 / cos 75)
    n = np.array([-np.tan(np.radians(60.0)), 0.0, 1.0])
    rays = np.stack([rx, ry, np.ones_like(rx)], axis=-1)
    cos = np.abs(rays @ n) / (np.linalg.norm(rays, axis=-1) * np.linalg.norm(n))
    inside = np.isfinite(z) & (cos > np.cos(np.radians(75.0)))
    inside[:2], inside[-2:], inside[:, :2], inside[:, -2:] = False, False, False, False
    assert inside.sum() > 1500
    alpha = image[..., 3][inside]
    assert np.mean(alpha < 0.99) == 0.0, np.mean(alpha < 0.99)
    # unshaded: the wall's own colour, sRGB 150/255 -> linear 0.305, to 1 %
    np.testing.assert_allclose(image[..., 1][inside], srgb_to_linear(150 / 255), rtol=0.01)
