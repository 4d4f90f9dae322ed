"""Tests of the I/O layer: sRGB curves, surfel PLY files, image files, atomic writes."""

from __future__ import annotations

import gzip
import importlib.util
import os
import subprocess
import sys

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from dofsplat.errors import DofsplatError
from dofsplat.io import (LOADERS, SUPPORTED_IMAGE_EXTENSIONS, atomic_write,
                         check_output_path, linear_to_srgb, load, read_image,
                         read_surfel_ply, save_surfels, srgb_to_linear, write_depth,
                         write_image, write_surfel_ply)
from dofsplat.surfels import Surfels

SURFEL_ARRAYS = ("positions", "normals", "radius", "colors", "opacity", "tangent",
                 "radius_v", "weight")
U8_STEP = 1.0 / 255.0
HAVE_OPENEXR = importlib.util.find_spec("OpenEXR") is not None


# ---------------------------------------------------------------------------------------
# helpers


def make_surfels(n=50, elliptical=False, weights=False, seed=0) -> Surfels:
    rng = np.random.default_rng(seed)
    return Surfels(
        positions=rng.normal(size=(n, 3)) * 10.0,
        normals=rng.normal(size=(n, 3)),
        radius=rng.uniform(0.01, 1.0, n),
        colors=rng.uniform(0.0, 1.0, (n, 3)),
        opacity=rng.uniform(0.0, 1.0, n),
        tangent=rng.normal(size=(n, 3)) if elliptical else None,
        radius_v=rng.uniform(0.01, 1.0, n) if elliptical else None,
        weight=rng.uniform(0.0, 2.0, n) if weights else None)


def write_raw_ply(path, columns: dict, text=False):
    """A PLY with one vertex element whose properties are the given (N,) arrays."""
    n = len(next(iter(columns.values())))
    records = np.empty(n, dtype=[(k, np.asarray(v).dtype) for k, v in columns.items()])
    for k, v in columns.items():
        records[k] = v
    PlyData([PlyElement.describe(records, "vertex")], text=text).write(str(path))
    return path


def surfel_columns(n=5, **extra):
    """Float32 columns of n valid circular surfels facing +z, plus extra columns."""
    cols = {"x": np.arange(n, dtype=np.float32), "y": np.zeros(n, np.float32),
            "z": np.zeros(n, np.float32), "nx": np.zeros(n, np.float32),
            "ny": np.zeros(n, np.float32), "nz": np.ones(n, np.float32),
            "radius": np.full(n, 0.5, np.float32)}
    cols.update(extra)
    return cols


def test_srgb_known_values():
    assert srgb_to_linear(0.5) == pytest.approx(0.21404114, abs=1e-6)
    assert linear_to_srgb(0.21404114) == pytest.approx(0.5, abs=1e-6)
    assert srgb_to_linear(128 / 255) == pytest.approx(0.2158605, abs=1e-6)
    np.testing.assert_allclose(srgb_to_linear([0.0, 1.0]), [0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(linear_to_srgb([0.0, 1.0]), [0.0, 1.0], atol=1e-12)
    # linear segment below the knee: 0.02 / 12.92
    assert srgb_to_linear(0.02) == pytest.approx(0.02 / 12.92, rel=1e-12)
    assert linear_to_srgb(0.001) == pytest.approx(0.01292, rel=1e-12)


def test_the_kernels_srgb_decode_is_the_arrays():
    """gauss.composite.decode (one value, for the Gaussian kernels and their CUDA twins: linear
    between DECODE_STEPS + 1 steps of the curve) against srgb_to_linear at 100,001 values and
    either side of the knee: within 8e-8 (the chord's gap, h^2 / 8 x the curve's largest
    second derivative, 2.3e-8 where it is smooth; 7.4e-8 measured at the knee), under
    float32's own step near 1 (6e-8), and exact at 0 and 1."""
    from dofsplat.gauss.composite import DECODE, decode

    x = np.concatenate([np.linspace(0.0, 1.0, 100_001), [0.04045, np.nextafter(0.04045, 1.0)]])
    got = np.array([decode(v, DECODE) for v in x])
    np.testing.assert_allclose(got, srgb_to_linear(x), rtol=0, atol=8e-8)
    assert got[0] == 0.0 and got[100_000] == 1.0


def test_srgb_round_trip():
    x = np.linspace(0.0, 1.0, 10001)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, rtol=0, atol=1e-6)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, rtol=0, atol=1e-6)
    x32 = x.astype(np.float32)
    assert srgb_to_linear(x32).dtype == np.float32
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x32)), x32, rtol=0, atol=1e-6)


# ---------------------------------------------------------------------------------------
# surfel PLY


@pytest.mark.parametrize("suffix, binary", [(".ply", True), (".ply", False),
                                            (".ply.gz", True), (".ply.gz", False)])
@pytest.mark.parametrize("elliptical, weights", [(False, False), (True, True)])
def test_ply_round_trip_is_exact(tmp_path, suffix, binary, elliptical, weights):
    surfels = make_surfels(elliptical=elliptical, weights=weights)
    path = save_surfels(tmp_path / f"model{suffix}", surfels, binary=binary)
    back = load(path)
    assert len(back) == len(surfels)
    for name in SURFEL_ARRAYS:
        a, b = getattr(surfels, name), getattr(back, name)
        if a is None:
            assert b is None, name
            continue
        assert b.dtype == np.float32, name
        np.testing.assert_array_equal(b, a, err_msg=name)  # bit for bit
    assert os.listdir(tmp_path) == [path.name]  # no temp file left behind
    if suffix == ".ply.gz":
        with gzip.open(path, "rb") as f:
            assert f.read(3) == b"ply"


def test_ply_uchar_colours_are_srgb(tmp_path):
    cols = surfel_columns(3, red=np.array([255, 128, 0], np.uint8),
                          green=np.array([0, 255, 128], np.uint8),
                          blue=np.array([128, 0, 255], np.uint8),
                          alpha=np.array([255, 51, 0], np.uint8))
    s = read_surfel_ply(write_raw_ply(tmp_path / "u8.ply", cols))
    np.testing.assert_allclose(s.colors[:, 0], [1.0, 0.2158605, 0.0], atol=1e-6)
    np.testing.assert_allclose(s.colors[:, 1], [0.0, 1.0, 0.2158605], atol=1e-6)
    np.testing.assert_allclose(s.opacity, [1.0, 0.2, 0.0], atol=1e-7)  # alpha is linear


def test_ply_other_colour_types(tmp_path):
    u16 = surfel_columns(2, **{c: np.array([65535, 32768], np.uint16)
                               for c in ("red", "green", "blue")})
    s = read_surfel_ply(write_raw_ply(tmp_path / "u16.ply", u16))
    np.testing.assert_allclose(s.colors[:, 0], [1.0, srgb_to_linear(32768 / 65535)],
                               atol=1e-6)
    f64 = surfel_columns(2, **{c: np.array([0.25, 0.75]) for c in ("red", "green", "blue")},
                         opacity=np.array([0.5, 1.0]))
    s = read_surfel_ply(write_raw_ply(tmp_path / "f64.ply", f64, text=True))
    np.testing.assert_array_equal(s.colors[:, 2], [0.25, 0.75])  # float is linear already
    np.testing.assert_array_equal(s.opacity, [0.5, 1.0])
    s = read_surfel_ply(write_raw_ply(tmp_path / "grey.ply", surfel_columns(2)))
    np.testing.assert_allclose(s.colors, 0.8, atol=1e-7)
    np.testing.assert_array_equal(s.opacity, 1.0)


def test_ply_nan_rows_dropped_with_count(tmp_path):
    x = np.arange(5, dtype=np.float32)
    x[1] = np.nan
    radius = np.full(5, 0.5, np.float32)
    radius[3] = np.inf
    path = write_raw_ply(tmp_path / "nan.ply", surfel_columns(5, x=x, radius=radius))
    with pytest.warns(UserWarning, match=r"dropped 2 of 5 surfels"):
        s = load(path)
    np.testing.assert_array_equal(s.positions[:, 0], [0.0, 2.0, 4.0])


def test_ply_zero_normal_and_bad_radius_raise_with_count(tmp_path):
    nz = np.array([1, 0, 1, 0, 1], np.float32)
    path = write_raw_ply(tmp_path / "zero_n.ply", surfel_columns(5, nz=nz))
    with pytest.raises(DofsplatError, match=r"2 of 5 surfels have a zero-length normal"):
        load(path)
    radius = np.array([0.5, 0.0, -1.0, -2.0, 0.5], np.float32)
    path = write_raw_ply(tmp_path / "bad_r.ply", surfel_columns(5, radius=radius))
    with pytest.raises(DofsplatError, match=r"3 of 5 surfels have a radius <= 0"):
        load(path)


def test_the_surfels_checks_read_blocks_of_rows(monkeypatch):
    """``Surfels._validate`` reads ``VALIDATE_ROWS`` rows at a time (a model of memory maps
    is never read whole): in blocks of 2 rows the rows it mends (normals and tangents made
    unit, colours and opacities clipped) are those of one block, and its counts are over
    all the blocks."""
    import dofsplat.surfels as surfels_module

    rng = np.random.default_rng(3)
    arrays = dict(positions=rng.normal(size=(7, 3)), normals=3.0 * rng.normal(size=(7, 3)),
                  radius=0.1, colors=rng.uniform(-0.5, 1.0, (7, 3)),
                  opacity=rng.uniform(-0.5, 1.5, 7), tangent=rng.normal(size=(7, 3)),
                  radius_v=0.2)
    whole = Surfels(**arrays)
    monkeypatch.setattr(surfels_module, "VALIDATE_ROWS", 2)
    blocks = Surfels(**arrays)
    for name in ("normals", "tangent", "colors", "opacity"):
        np.testing.assert_array_equal(getattr(blocks, name), getattr(whole, name))
    normals = arrays["normals"].copy()
    normals[[1, 4]] = 0.0
    with pytest.raises(DofsplatError, match=r"2 of 7 surfels have a zero-length normal"):
        Surfels(**(arrays | {"normals": normals}))
    with pytest.raises(DofsplatError, match=r"3 of 7 surfels have a radius <= 0"):
        Surfels(**(arrays | {"radius": np.array([0.1, 0, 0.1, -1, 0.1, 0.1, 0])}))


def test_surfels_take_one_value_for_every_surfel_and_name_what_is_not_numbers():
    """A scalar radius, opacity or weight is every surfel's (Surfels meant to broadcast it,
    but refused it as "shape (3,), got (1,)"; from_arrays failed with an IndexError); an
    array of strings, or a material that is not a Material, is named."""
    positions, normals = np.zeros((3, 3)), np.tile([0.0, 0.0, 1.0], (3, 1))
    s = Surfels(positions, normals, radius=0.1, colors=np.ones((3, 3)), opacity=0.5)
    np.testing.assert_array_equal(s.radius, np.full(3, 0.1, np.float32))
    np.testing.assert_array_equal(s.opacity, np.full(3, 0.5, np.float32))
    s = Surfels.from_arrays(positions, normals, 0.1, np.ones((3, 3)), weight=1.0)
    np.testing.assert_array_equal(s.radius, np.full(3, 0.1, np.float32))
    np.testing.assert_array_equal(s.weight, np.ones(3, np.float32))
    with pytest.raises(DofsplatError, match="colors must be numbers, got 'red'"):
        Surfels(positions, normals, radius=0.1, colors="red")
    with pytest.raises(DofsplatError, match="material must be a Material, got str"):
        Surfels(positions, normals, radius=0.1, colors=np.ones((3, 3)), material="shiny")


@pytest.mark.parametrize("suffix, binary", [(".ply", True), (".ply", False),
                                            (".ply.gz", True)])
def test_ply_truncated_file(tmp_path, suffix, binary):
    path = save_surfels(tmp_path / f"full{suffix}", make_surfels(200), binary=binary)
    data = path.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(DofsplatError, match=r"cut\.ply.*(truncated|corrupt)") as info:
        load(cut)
    assert "\n" not in str(info.value)


def test_ply_garbage_and_header_errors(tmp_path):
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(DofsplatError, match=r"garbage\.ply: not a PLY file"):
        load(garbage)
    fake_gz = tmp_path / "fake.ply.gz"
    fake_gz.write_bytes(b"\x1f\x8b" + b"not really gzip" * 10)
    with pytest.raises(DofsplatError, match=r"fake\.ply\.gz"):
        load(fake_gz)
    other = tmp_path / "faces.ply"
    face = np.zeros(2, dtype=[("a", "f4")])
    PlyData([PlyElement.describe(face, "face")]).write(str(other))
    with pytest.raises(DofsplatError, match=r"no 'vertex' element.*'face'"):
        load(other)
    empty = write_raw_ply(tmp_path / "empty.ply",
                          {k: v[:0] for k, v in surfel_columns(1).items()})
    with pytest.raises(DofsplatError, match=r"empty"):
        load(empty)


def test_ply_missing_properties_are_named(tmp_path):
    points = {k: np.zeros(3, np.float32) for k in ("x", "y", "z", "nx")}
    path = write_raw_ply(tmp_path / "points.ply", points)
    with pytest.raises(DofsplatError, match=r"lacks required properties ny nz radius;.*"
                                            r"not a surfel file"):
        load(path)
    half_ellipse = surfel_columns(3, tx=np.ones(3, np.float32), ty=np.zeros(3, np.float32))
    path = write_raw_ply(tmp_path / "half.ply", half_ellipse)
    with pytest.raises(DofsplatError, match=r"lacks tz radius_v"):
        load(path)


def test_load_dispatch_errors(tmp_path):
    assert {".ply", ".ply.gz"} <= set(LOADERS)
    with pytest.raises(DofsplatError, match=r"no such file: .*nothere\.ply"):
        load(tmp_path / "nothere.ply")
    xyz = tmp_path / "model.xyz"
    xyz.write_text("0 0 0\n")
    with pytest.raises(DofsplatError, match=r"unsupported model format.*\.ply, \.ply\.gz"):
        load(xyz)
    path = save_surfels(tmp_path / "UPPER.PLY", make_surfels(4))
    assert len(load(path)) == 4  # extensions match in any case
    with pytest.raises(DofsplatError, match=r"unknown option\(s\) scale"):
        load(path, scale=2.0)
    with pytest.raises(DofsplatError, match=r"unsupported model format"):
        save_surfels(tmp_path / "model.obj", make_surfels(4))


# ---------------------------------------------------------------------------------------
# images


def make_rgba(h=7, w=5, seed=1) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 1.0, (h, w, 4)).astype(np.float32)


def test_png_round_trip_within_one_step(tmp_path):
    from PIL import Image

    rgba = make_rgba()
    path = write_image(tmp_path / "out.png", rgba)
    with Image.open(path) as im:
        assert im.mode == "RGB" and im.size == (5, 7)
    back = read_image(path)
    assert back.shape == (7, 5, 3) and back.dtype == np.float32
    # compared where the 8 bits live, in sRGB: rounding is off by at most half a step
    err = np.abs(linear_to_srgb(back.astype(np.float64)) - linear_to_srgb(rgba[..., :3]))
    assert err.max() <= 0.5 * U8_STEP + 1e-6


def test_png_clips_out_of_range(tmp_path):
    rgba = np.zeros((2, 2, 4), np.float32)
    rgba[0, 0, :3] = [2.0, -1.0, 0.5]
    back = read_image(write_image(tmp_path / "clip.png", rgba))
    np.testing.assert_allclose(back[0, 0], [1.0, 0.0, srgb_to_linear(188 / 255)], atol=1e-6)


def test_npy_round_trip_exact(tmp_path):
    rgba = make_rgba()
    back = read_image(write_image(tmp_path / "out.npy", rgba))
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, rgba)


def test_exr_round_trip_exact(tmp_path):
    OpenEXR = pytest.importorskip("OpenEXR")
    rgba = make_rgba()
    depth = np.random.default_rng(2).uniform(1.0, 50.0, rgba.shape[:2]).astype(np.float32)
    depth[0, 0] = np.inf
    path = write_image(tmp_path / "out.exr", rgba, depth=depth)
    np.testing.assert_array_equal(read_image(path), rgba)
    channels = OpenEXR.File(str(path), separate_channels=True).channels()
    assert set(channels) == {"R", "G", "B", "A", "Z"}
    np.testing.assert_array_equal(channels["Z"].pixels, depth)


def test_exr_without_openexr_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "OpenEXR", None)  # makes `import OpenEXR` fail
    with pytest.raises(DofsplatError, match=r"pip install 'dofsplat\[exr\]'"):
        write_image(tmp_path / "out.exr", make_rgba())
    with pytest.raises(DofsplatError, match=r"OpenEXR"):
        check_output_path(tmp_path / "out.exr")
    assert not any(tmp_path.iterdir())


def test_write_depth_formats(tmp_path):
    depth = np.array([[2.0, 4.0], [np.inf, 6.0]], np.float32)
    back = np.load(write_depth(tmp_path / "d.npy", depth))
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, depth)

    from PIL import Image

    with Image.open(write_depth(tmp_path / "d.png", depth)) as im:
        grey = np.asarray(im).astype(np.int64)
        assert (float(im.info["near"]), float(im.info["far"])) == (2.0, 6.0)
    # near -> 1, far -> 65535, halfway -> 32768, empty -> 0
    np.testing.assert_array_equal(grey, [[1, 32768], [0, 65535]])

    if HAVE_OPENEXR:
        z = read_image(write_depth(tmp_path / "d.exr", depth))
        np.testing.assert_array_equal(z[..., 0], depth)


def test_write_image_rejects_bad_input(tmp_path):
    with pytest.raises(DofsplatError, match=r"\.png, \.npy, \.exr"):
        write_image(tmp_path / "out.jpg", make_rgba())
    with pytest.raises(DofsplatError, match=r"shape \(H, W, 4\)"):
        write_image(tmp_path / "out.png", np.zeros((4, 4)))
    bad = make_rgba()
    bad[1, 1, 0] = np.nan
    with pytest.raises(DofsplatError, match=r"1 pixels with NaN"):
        write_image(tmp_path / "out.npy", bad)
    with pytest.raises(DofsplatError, match=r"depth has shape"):
        write_image(tmp_path / "out.exr", make_rgba(), depth=np.ones((3, 3)))
    assert not any(tmp_path.iterdir())


# ---------------------------------------------------------------------------------------
# atomic writes and output paths


def test_atomic_write_leaves_nothing_on_error(tmp_path):
    def fail(tmp):
        with open(tmp, "wb") as f:
            f.write(b"half an image")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        atomic_write(tmp_path / "out.png", fail)
    assert list(tmp_path.iterdir()) == []

    # an existing file is left as it was
    old = tmp_path / "old.npy"
    old.write_bytes(b"previous")
    with pytest.raises(RuntimeError):
        atomic_write(old, fail)
    assert [p.name for p in tmp_path.iterdir()] == ["old.npy"]
    assert old.read_bytes() == b"previous"


def test_atomic_write_replaces_and_keeps_suffix(tmp_path):
    seen = []

    def write(tmp):
        seen.append(tmp)
        with open(tmp, "wb") as f:
            f.write(b"new")

    out = tmp_path / "img.exr"
    out.write_bytes(b"old")
    atomic_write(out, write)
    assert out.read_bytes() == b"new"
    assert seen[0].endswith(".exr") and os.path.dirname(seen[0]) == str(tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["img.exr"]
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(out).st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's private 0600
    with pytest.raises(DofsplatError, match=r"does not exist"):
        atomic_write(tmp_path / "missing" / "img.png", write)


def test_check_output_path(tmp_path):
    assert SUPPORTED_IMAGE_EXTENSIONS == (".png", ".npy", ".exr")
    assert check_output_path(tmp_path / "a.png") == tmp_path / "a.png"
    assert check_output_path(tmp_path / "A.NPY") == tmp_path / "A.NPY"
    with pytest.raises(DofsplatError, match=r"unsupported image format '\.jpg'.*\.png"):
        check_output_path(tmp_path / "a.jpg")
    with pytest.raises(DofsplatError, match=r"no extension"):
        check_output_path(tmp_path / "image")
    with pytest.raises(DofsplatError, match=r"'.*nodir' does not exist"):
        check_output_path(tmp_path / "nodir" / "a.png")
    (tmp_path / "dir.png").mkdir()
    with pytest.raises(DofsplatError, match=r"is a directory"):
        check_output_path(tmp_path / "dir.png")


def test_ply_write_is_atomic(tmp_path, monkeypatch):
    def broken(self, stream, text, byte_order):
        stream.write(b"1 2 3")  # the header is out already: a half-written file
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(PlyElement, "_write", broken)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_surfel_ply(tmp_path / "m.ply", make_surfels(3))
    assert list(tmp_path.iterdir()) == []


def test_importing_io_stays_light():
    code = ("import sys, dofsplat.io; "
            "print(sorted(m for m in ('plyfile', 'PIL', 'OpenEXR', 'scipy', 'numba') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=os.path.dirname(os.path.dirname(__file__)))
    assert out.stdout.strip() == "[]"
