"""Tests of the 3D Gaussian Splatting readers and writer (issue 48, item 1): the trainers'
PLY, PlayCanvas's compressed PLY, Niantic's SPZ and PlayCanvas's SOG, on tiny files that the
tests encode themselves (so the decoded values are known), and on the real scenes in
../shared/data (skipped when absent).
"""

from __future__ import annotations

import gzip
import io
import json
import math
import struct
import warnings
import zipfile

import numpy as np
import pytest
from conftest import SHARED_DATA, gaussian_ply_columns
from PIL import Image
from plyfile import PlyData, PlyElement

from dofsplat import cli
from dofsplat.errors import DofsplatError
from dofsplat.gaussians import Gaussians
from dofsplat.io import LOADERS, load, model_options, save_surfels
from dofsplat.io.gaussians import SH_C0, gaussians_to_surfels, quaternion_matrices
from dofsplat.io.spz import mirror_axes
from dofsplat.surfels import Surfels

SCENES = SHARED_DATA / "gaussian_scenes"


def shared(relative: str):
    """The path of a real scene in ../shared/data, or skip the test with the reason."""
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"real scene {relative} not found in {SHARED_DATA} (the shared data "
                    "folder is absent on this machine)")
    return path


def random_scene(n, k=16, seed=0):
    """Raw arrays of n Gaussians as a trainer stores them: log-scales, logits, quaternions
    not normalised, SH (n, k, 3)."""
    rng = np.random.default_rng(seed)
    f = lambda *shape: rng.normal(size=shape).astype(np.float32)  # noqa: E731
    return dict(positions=f(n, 3), log_scales=rng.uniform(-9, 1, (n, 3)).astype(np.float32),
                rotations=f(n, 4) * 3, logits=rng.uniform(-8, 12, n).astype(np.float32),
                sh=f(n, k, 3))


def write_3dgs_ply(path, scene, extra=None, text=False):
    """A trainers' PLY of the scene (``gaussian_ply_columns``), with extra float columns."""
    cols = gaussian_ply_columns(**scene)
    cols.update(extra or {})
    rec = np.empty(len(cols["x"]), dtype=[(name, "<f4") for name in cols])
    for name, v in cols.items():
        rec[name] = v
    PlyData([PlyElement.describe(rec, "vertex")], text=text).write(str(path))
    return path


# -- the trainers' PLY ---------------------------------------------------------------------


def test_3dgs_ply_decodes_every_column(tmp_path):
    scene = random_scene(7)
    path = write_3dgs_ply(tmp_path / "g.ply", scene, extra={"transform": np.ones(7, np.float32)})
    with pytest.warns(UserWarning, match=r"ignored vertex properties transform"):
        g = load(path)
    assert isinstance(g, Gaussians) and len(g) == 7 and g.sh_degree == 3
    np.testing.assert_array_equal(g.positions, scene["positions"])
    np.testing.assert_allclose(g.scales, np.exp(scene["log_scales"].astype(np.float64)),
                               rtol=1e-6)
    np.testing.assert_allclose(g.opacity, 1 / (1 + np.exp(-scene["logits"].astype(np.float64))),
                               rtol=1e-6)
    q = scene["rotations"] / np.linalg.norm(scene["rotations"], axis=1, keepdims=True)
    np.testing.assert_allclose(g.rotations, q, atol=1e-6)  # w first, normalised
    # channel-major f_rest: sh[:, 1:, c] = f_rest[c (K - 1):(c + 1) (K - 1)]
    np.testing.assert_array_equal(g.sh, scene["sh"])


def test_3dgs_ply_by_hand_one_gaussian(tmp_path):
    # degree 1: f_rest_0..2 are red's three coefficients, 3..5 green's, 6..8 blue's
    scene = dict(positions=np.array([[1, 2, 3]], np.float32),
                 log_scales=np.log(np.array([[0.1, 0.02, 0.3]], np.float32)),
                 rotations=np.array([[2.0, 0, 0, 0]], np.float32), logits=np.zeros(1, np.float32),
                 sh=np.arange(12, dtype=np.float32).reshape(1, 4, 3))
    path = write_3dgs_ply(tmp_path / "one.ply", scene)
    header = PlyData.read(str(path))["vertex"]
    assert header["f_rest_0"][0] == 3 and header["f_rest_3"][0] == 4 and header["f_rest_8"][0] == 11
    g = load(path)
    np.testing.assert_array_equal(g.sh[0, :, 0], [0, 3, 6, 9])  # red: f_dc_0, f_rest_0..2
    np.testing.assert_array_equal(g.rotations[0], [1, 0, 0, 0])
    assert g.opacity[0] == 0.5
    np.testing.assert_allclose(g.scales[0], [0.1, 0.02, 0.3], rtol=1e-6)


def test_3dgs_ply_ascii_and_damaged_rows(tmp_path):
    scene = random_scene(10, k=1)
    scene["rotations"][2] = 0.0  # a zero quaternion
    scene["log_scales"][5, 1] = 500.0  # absurd
    scene["positions"][7, 0] = np.nan
    with pytest.warns(UserWarning, match=r"dropped 3 of 10 Gaussians"):
        g = load(write_3dgs_ply(tmp_path / "a.ply", scene, text=True))
    assert len(g) == 7 and g.sh.shape == (7, 1, 3)


def test_3dgs_ply_bad_files(tmp_path):
    scene = random_scene(3, k=4)
    bad = write_3dgs_ply(tmp_path / "rest.ply", scene,
                         extra={"f_rest_9": np.zeros(3, np.float32)})
    with pytest.raises(DofsplatError, match=r"10 f_rest_\* properties"):
        load(bad)
    scene["positions"][:] = np.nan
    with pytest.raises(DofsplatError, match=r"no valid Gaussians"):
        load(write_3dgs_ply(tmp_path / "nan.ply", scene))
    with pytest.raises(DofsplatError, match=r"option\(s\) normalise do not apply"):
        load(write_3dgs_ply(tmp_path / "ok.ply", random_scene(3)), normalise="object")


def test_write_gaussian_ply_round_trip_is_exact(tmp_path):
    scene = random_scene(2000)
    scene["logits"][:4] = [-200.0, 200.0, 30.0, -30.0]  # opacities 0 and 1 and next to them
    g = load(write_3dgs_ply(tmp_path / "in.ply", scene))
    for name in ("out.ply", "out.ply.gz"):
        out = save_surfels(tmp_path / name, g)  # Gaussians: a 3DGS PLY
        back = load(out)
        for field in ("positions", "scales", "rotations", "opacity", "sh"):
            np.testing.assert_array_equal(getattr(back, field), getattr(g, field), err_msg=field)
    names = [p.name for p in PlyData.read(str(tmp_path / "out.ply"))["vertex"].properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2",
                          "rot_0", "rot_1", "rot_2", "rot_3"]
    assert not list(tmp_path.glob(".*"))  # no temporary file left (atomic write)


def test_gaussians_to_surfels_from_gaussians_and_columns(tmp_path):
    # one Gaussian turned 90 degrees about z, scales (0.1, 0.02, 0.3) along its x, y, z
    q = np.array([[math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]])
    g = Gaussians(positions=[[1.0, 2.0, 3.0]], scales=[[0.1, 0.02, 0.3]], rotations=q,
                  opacity=[0.5], sh=[[[1.0, 0.0, -5.0]]])
    s = gaussians_to_surfels(g)
    assert isinstance(s, Surfels) and s.is_elliptical
    np.testing.assert_allclose(np.abs(s.normals[0]), [1, 0, 0], atol=1e-6)  # local y
    np.testing.assert_allclose(np.abs(s.tangent[0]), [0, 0, 1], atol=1e-6)  # local z
    assert s.radius[0] == pytest.approx(0.6, rel=1e-5)
    assert s.radius_v[0] == pytest.approx(0.2, rel=1e-5)
    np.testing.assert_allclose(quaternion_matrices(q)[0] @ [0, 1, 0], [-1, 0, 0], atol=1e-12)
    faint = Gaussians(positions=[[0.0, 0, 0]], scales=[[1.0, 1, 1]], rotations=[[1.0, 0, 0, 0]],
                      opacity=[0.001], sh=np.zeros((1, 1, 3)))
    with pytest.raises(DofsplatError, match=r"every Gaussian has opacity below"):
        gaussians_to_surfels(faint)


# -- PlayCanvas compressed PLY -------------------------------------------------------------


def compressed_ply(path, positions, log_scales, rotations, rgb, opacity, rest=None,
                   chunk_colours=True):
    """A compressed PLY as SuperSplat writes one (PlayCanvas splat-transform's layout)."""
    n = len(positions)
    chunks = -(-n // 256)
    ranges = {}
    fields = [("x", positions[:, 0]), ("y", positions[:, 1]), ("z", positions[:, 2]),
              ("scale_x", log_scales[:, 0]), ("scale_y", log_scales[:, 1]),
              ("scale_z", log_scales[:, 2])]
    if chunk_colours:
        fields += [("r", rgb[:, 0]), ("g", rgb[:, 1]), ("b", rgb[:, 2])]
    for name, v in fields:
        lo = np.array([v[c * 256:(c + 1) * 256].min() for c in range(chunks)], np.float32)
        hi = np.array([v[c * 256:(c + 1) * 256].max() for c in range(chunks)], np.float32)
        ranges[name] = (lo, hi)
    in_chunk = np.arange(n) // 256

    def frac(name, v, bits):
        lo, hi = (a[in_chunk].astype(np.float64) for a in ranges[name])
        t = np.where(hi > lo, (v - lo) / np.where(hi > lo, hi - lo, 1), 0)
        return np.round(t * ((1 << bits) - 1)).astype(np.uint32)

    def pack(names, v):
        return (frac(names[0], v[:, 0], 11) << 21) | (frac(names[1], v[:, 1], 10) << 11) \
            | frac(names[2], v[:, 2], 11)

    q = rotations / np.linalg.norm(rotations, axis=1, keepdims=True)
    largest = np.argmax(np.abs(q), axis=1)
    q = q * np.sign(q[np.arange(n), largest])[:, None]
    packed_rot = largest.astype(np.uint32) << 30
    # the three others, in (w, x, y, z) order, the last in the low bits
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    for i in range(3):
        v = q[np.arange(n), others[:, i]] / math.sqrt(2) + 0.5
        packed_rot |= np.round(v * 1023).astype(np.uint32) << np.uint32(20 - 10 * i)
    if chunk_colours:
        colour = [frac(c, rgb[:, i], 8) for i, c in enumerate("rgb")]
    else:
        colour = [np.round(np.clip(rgb[:, i], 0, 1) * 255).astype(np.uint32) for i in range(3)]
    alpha = np.round(opacity * 255).astype(np.uint32)
    packed_colour = (colour[0] << 24) | (colour[1] << 16) | (colour[2] << 8) | alpha

    chunk = np.empty(chunks, dtype=[(f"{m}_{name}", "<f4") for name, _ in fields
                                    for m in ("min", "max")])
    for name, (lo, hi) in ranges.items():
        chunk[f"min_{name}"], chunk[f"max_{name}"] = lo, hi
    vertex = np.empty(n, dtype=[(p, "<u4") for p in ("packed_position", "packed_rotation",
                                                     "packed_scale", "packed_color")])
    vertex["packed_position"] = pack("xyz", positions)
    vertex["packed_rotation"] = packed_rot
    vertex["packed_scale"] = pack(("scale_x", "scale_y", "scale_z"), log_scales)
    vertex["packed_color"] = packed_colour
    elements = [PlyElement.describe(chunk, "chunk"), PlyElement.describe(vertex, "vertex")]
    if rest is not None:  # (n, K - 1, 3) -> uchar f_rest, channel-major
        flat = rest.transpose(0, 2, 1).reshape(n, -1)
        sh = np.empty(n, dtype=[(f"f_rest_{i}", "u1") for i in range(flat.shape[1])])
        for i in range(flat.shape[1]):
            sh[f"f_rest_{i}"] = np.clip(np.trunc((flat[:, i] / 8 + 0.5) * 256), 0, 255)
        elements.append(PlyElement.describe(sh, "sh"))
    PlyData(elements, byte_order="<").write(str(path))
    return path


@pytest.mark.parametrize("chunk_colours", [True, False])
def test_compressed_ply_decodes_within_its_quantisation(tmp_path, chunk_colours):
    rng = np.random.default_rng(4)
    n = 300  # two chunks
    positions = rng.uniform(-2, 2, (n, 3))
    log_scales = rng.uniform(-6, -1, (n, 3))
    rotations = rng.normal(size=(n, 4))
    rgb = rng.uniform(0.1, 0.9, (n, 3))
    opacity = rng.uniform(0, 1, n)
    rest = rng.uniform(-1, 1, (n, 3, 3))  # SH degree 1
    path = compressed_ply(tmp_path / "c.compressed.ply", positions, log_scales, rotations, rgb,
                          opacity, rest, chunk_colours)
    g = load(path)
    assert isinstance(g, Gaussians) and len(g) == n and g.sh_degree == 1
    np.testing.assert_allclose(g.positions, positions, atol=4.0 / 1023 / 2 + 1e-6)
    np.testing.assert_allclose(np.log(g.scales), log_scales, atol=5.0 / 1023 / 2 + 1e-5)
    r_file, r_back = quaternion_matrices(rotations), g.rotation_matrices()
    np.testing.assert_allclose(r_back, r_file, atol=5e-3)  # 10 bits a component
    np.testing.assert_allclose(0.5 + SH_C0 * g.sh[:, 0], rgb, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(g.opacity, opacity, atol=0.5 / 255 + 1e-7)
    np.testing.assert_allclose(g.sh[:, 1:], rest, atol=8 / 256 + 1e-6)  # 8 bits over [-4, 4]


def test_compressed_ply_by_hand(tmp_path):
    # one Gaussian, its chunk spanning [0, 2] in x y z and [-4, -2] in log-scale, no colour range
    chunk = np.zeros(1, dtype=[(f"{m}_{a}", "<f4") for a in ("x", "y", "z", "scale_x",
                                                             "scale_y", "scale_z")
                               for m in ("min", "max")])
    for a in "xyz":
        chunk[f"max_{a}"] = 2.0
        chunk[f"min_scale_{a}"], chunk[f"max_scale_{a}"] = -4.0, -2.0
    vertex = np.zeros(1, dtype=[(p, "<u4") for p in ("packed_position", "packed_rotation",
                                                     "packed_scale", "packed_color")])
    vertex["packed_position"] = (2047 << 21) | (0 << 11) | 1023  # x = 2, y = 0, z = 1023/2047 * 2
    vertex["packed_scale"] = (0 << 21) | (1023 << 11) | 2047  # log-scales -4, -2, -2
    vertex["packed_rotation"] = (1 << 30) | (512 << 20) | (512 << 10) | 512  # x is the largest
    vertex["packed_color"] = 0xFF8000FF  # r = 1, g = 128/255, b = 0, opacity 1
    path = tmp_path / "one.compressed.ply"
    PlyData([PlyElement.describe(chunk, "chunk"), PlyElement.describe(vertex, "vertex")],
            byte_order="<").write(str(path))
    g = load(path)
    np.testing.assert_allclose(g.positions[0], [2, 0, 2 * 1023 / 2047], rtol=1e-6)
    np.testing.assert_allclose(g.scales[0], np.exp([-4, -2, -2]), rtol=1e-6)
    small = (512 / 1023 - 0.5) * math.sqrt(2)
    expected = np.array([small, math.sqrt(1 - 3 * small ** 2), small, small])
    np.testing.assert_allclose(g.rotations[0], expected, atol=1e-7)
    np.testing.assert_allclose(g.sh[0, 0], (np.array([1, 128 / 255, 0]) - 0.5) / SH_C0,
                               rtol=1e-6)
    assert g.opacity[0] == 1.0


def test_compressed_ply_bad_chunks(tmp_path):
    rng = np.random.default_rng(0)
    path = compressed_ply(tmp_path / "c.ply", rng.normal(size=(300, 3)),
                          rng.uniform(-5, -1, (300, 3)), rng.normal(size=(300, 4)),
                          rng.uniform(0, 1, (300, 3)), rng.uniform(0, 1, 300))
    ply = PlyData.read(str(path))
    short = PlyElement.describe(ply["chunk"].data[:1], "chunk")
    PlyData([short, ply["vertex"]], byte_order="<").write(str(tmp_path / "short.ply"))
    with pytest.raises(DofsplatError, match=r"1 chunks for 300 Gaussians"):
        load(tmp_path / "short.ply")


# -- Niantic SPZ ---------------------------------------------------------------------------


def spz_bytes(version, positions, log_scales, rotations_xyzw, alpha, f_dc, rest=None,
              fraction_bits=12, flags=0, extensions=b""):
    """An SPZ file as nianticlabs/spz writes one (positions etc. in SPZ's own axes)."""
    n = len(positions)
    rest = np.zeros((n, 0, 3)) if rest is None else rest
    degree = {0: 0, 3: 1, 8: 2, 15: 3, 24: 4}[rest.shape[1]]
    if version == 1:
        pos = positions.astype("<f2").tobytes()
    else:
        fixed = np.round(positions * (1 << fraction_bits)).astype(np.int64) & 0xFFFFFF
        pos = np.stack([fixed & 255, (fixed >> 8) & 255, fixed >> 16], axis=-1).astype(
            np.uint8).tobytes()
    byte = lambda v: np.clip(np.round(v), 0, 255).astype(np.uint8).tobytes()  # noqa: E731
    q = rotations_xyzw / np.linalg.norm(rotations_xyzw, axis=1, keepdims=True)
    if version >= 3:
        largest = np.argmax(np.abs(q), axis=1)
        q = q * np.sign(q[np.arange(n), largest])[:, None]
        packed = np.zeros(n, np.uint32)
        for j in range(4):
            here = largest != j
            bits = (np.round(np.abs(q[:, j]) * math.sqrt(2) * 511).astype(np.uint32)
                    | ((q[:, j] < 0).astype(np.uint32) << 9))
            packed = np.where(here, (packed << 10) | bits, packed)
        rot = (packed | (largest.astype(np.uint32) << 30)).astype("<u4").tobytes()
    else:
        q = q * np.where(q[:, 3:] < 0, -1, 1)
        rot = byte((q[:, :3] + 1) * 127.5)
    streams = [pos, byte(alpha * 255), byte((f_dc * 0.15 + 0.5) * 255),
               byte((log_scales + 10) * 16), rot]
    if degree:
        streams.append(byte(rest * 128 + 128))
    if version <= 3:
        head = struct.pack("<4sIIBBBB", b"NGSP", version, n, degree, fraction_bits, flags, 0)
        return gzip.compress(head + b"".join(streams) + extensions, mtime=0)
    import zstandard

    packed_streams = [zstandard.ZstdCompressor().compress(s) for s in streams]
    toc_at = 32 + len(extensions)
    head = struct.pack("<4sIIBBBBI12x", b"NGSP", 4, n, degree, fraction_bits, flags,
                       len(streams), toc_at)
    toc = b"".join(struct.pack("<QQ", len(p), len(s)) for p, s in zip(packed_streams, streams))
    return head + extensions + toc + b"".join(packed_streams)


def spz_scene(n=50, k1=3, seed=5):
    rng = np.random.default_rng(seed)
    return dict(positions=rng.uniform(-3, 3, (n, 3)), log_scales=rng.uniform(-8, 2, (n, 3)),
                rotations_xyzw=rng.normal(size=(n, 4)), alpha=rng.uniform(0, 1, n),
                f_dc=rng.uniform(-3, 3, (n, 3)), rest=rng.uniform(-1, 1, (n, k1, 3)))


FLIP = np.array([1.0, -1.0, -1.0])  # RUB (SPZ) to RDF (the 3DGS PLY)


@pytest.mark.parametrize("version", [2, 3, 4])
def test_spz_decodes_within_its_quantisation_in_ply_axes(tmp_path, version):
    s = spz_scene()
    path = tmp_path / "s.spz"
    path.write_bytes(spz_bytes(version, **s))
    g = load(path)
    assert isinstance(g, Gaussians) and len(g) == 50 and g.sh_degree == 1
    np.testing.assert_allclose(g.positions, s["positions"] * FLIP, atol=0.5 / 4096 + 1e-6)
    np.testing.assert_allclose(np.log(g.scales), s["log_scales"], atol=1 / 32 + 1e-5)
    np.testing.assert_allclose(g.opacity, s["alpha"], atol=0.5 / 255 + 1e-7)
    np.testing.assert_allclose(g.sh[:, 0], s["f_dc"], atol=0.5 / 255 / 0.15 + 1e-6)
    # SH degree 1: basis y, z, x; mirroring y and z flips the first two, keeps the third
    np.testing.assert_allclose(g.sh[:, 1:], s["rest"] * [[-1], [-1], [1]], atol=1 / 128 + 1e-6)
    # rotations: F R F with F = diag(1, -1, -1)
    xyzw = s["rotations_xyzw"]
    r_spz = quaternion_matrices(np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1))
    f = np.diag(FLIP)
    # version 2 stores x y z in 8 bits and derives w, which is coarse where w is small
    tolerance = 6e-2 if version == 2 else 5e-3
    np.testing.assert_allclose(g.rotation_matrices(), f @ r_spz @ f, atol=tolerance)


def test_spz_by_hand_and_coordinate_extension(tmp_path):
    one = dict(positions=np.array([[1.0, 2.0, 3.0]]), log_scales=np.array([[-2.0, -3.0, -4.0]]),
               rotations_xyzw=np.array([[0.0, 0.0, 0.0, 1.0]]), alpha=np.array([1.0]),
               f_dc=np.array([[0.0, 1.0, -1.0]]))
    path = tmp_path / "one.spz"
    path.write_bytes(spz_bytes(4, **one))
    g = load(path)
    np.testing.assert_array_equal(g.positions[0], [1, -2, -3])  # exact in 12 fraction bits
    np.testing.assert_allclose(g.scales[0], np.exp([-2, -3, -4]), rtol=1e-6)
    np.testing.assert_array_equal(g.rotations[0], [1, 0, 0, 0])
    np.testing.assert_allclose(g.sh[0, 0], (np.round((np.array([0, 1, -1]) * 0.15 + 0.5)
                                                     * 255) / 255 - 0.5) / 0.15, rtol=1e-6)
    # an SPZ_ADOBE_coordinate_system record saying RDF (6): no flip
    record = struct.pack("<III", 0xADBE0003, 4, 6)
    path.write_bytes(spz_bytes(4, **one, flags=0x2, extensions=record))
    np.testing.assert_array_equal(load(path).positions[0], [1, 2, 3])
    path.write_bytes(spz_bytes(3, **one, flags=0x2, extensions=record))  # legacy: at the end
    np.testing.assert_array_equal(load(path).positions[0], [1, 2, 3])
    path.write_bytes(spz_bytes(4, **one, flags=0x2, extensions=struct.pack("<III", 0xADBE0003,
                                                                           4, 12)))
    with pytest.raises(DofsplatError, match=r"coordinate system 12 is not supported"):
        load(path)


def test_spz_degree_4_is_cut_and_flags_warn(tmp_path):
    s = spz_scene(n=5, k1=24)
    path = tmp_path / "d4.spz"
    path.write_bytes(spz_bytes(4, **s, flags=0x1))
    with pytest.warns(UserWarning) as record:
        g = load(path)
    text = " ".join(str(w.message) for w in record)
    assert "SH degree 4 is cut" in text and "antialiasing" in text
    assert g.sh.shape == (5, 16, 3)


def test_spz_bad_files(tmp_path):
    path = tmp_path / "bad.spz"
    good = spz_bytes(4, **spz_scene(n=8))
    for data, why in [(b"NGSX" + good[4:], "not an SPZ file"),
                      (good[:4] + struct.pack("<I", 9) + good[8:], "version 9"),
                      (good[:-10], "stream 5"),
                      (good[:20], "header needs 32 bytes"),
                      (good[:40], "table of contents"),
                      (gzip.compress(b"NGSP" + struct.pack("<IIBBBB", 2, 10**6, 0, 12, 0, 0)),
                       "truncated SPZ file"),
                      (b"\x1f\x8b\x08\x00garbage", "gzip stream is damaged")]:
        path.write_bytes(data)
        with pytest.raises(DofsplatError, match=why) as e:
            load(path)
        assert str(path) in str(e.value) and "\n" not in str(e.value)


# 3DGS's real SH basis (its sh_utils.eval_sh), to check the mirror's signs physically
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def eval_sh(sh, d):
    """Colour of (N, 16, 3) SH seen along unit directions d (N, 3), as 3DGS evaluates it."""
    x, y, z = (d[:, i:i + 1] for i in range(3))
    xx, yy, zz = x * x, y * y, z * z
    basis = [np.full_like(x, SH_C0), -C1 * y, C1 * z, -C1 * x,
             C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z,
             C2[4] * (xx - yy),
             C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
             C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
             C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    return sum(b * sh[:, i] for i, b in enumerate(basis))


@pytest.mark.parametrize("signs", [(1, -1, -1), (-1, 1, 1), (-1, -1, -1), (1, 1, -1)])
def test_mirror_axes_keeps_what_is_seen(signs):
    """The colour seen along d in one frame is the colour seen along F d in the mirrored
    one, and the mirrored covariance is F Sigma F."""
    rng = np.random.default_rng(1)
    n = 200
    sh = rng.normal(size=(n, 16, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    q = rng.normal(size=(n, 4))
    f = np.asarray(signs, np.float64)
    p2, q2, sh2 = mirror_axes(rng.normal(size=(n, 3)), q, sh, f)
    np.testing.assert_allclose(eval_sh(sh2, d * f), eval_sh(sh, d), atol=1e-12)
    r, r2 = quaternion_matrices(q), quaternion_matrices(q2)
    np.testing.assert_allclose(r2, np.diag(f) @ r @ np.diag(f), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r2), 1.0, atol=1e-12)


# -- PlayCanvas SOG ------------------------------------------------------------------------


def _webp(pixels: np.ndarray, width: int) -> bytes:
    rows = -(-len(pixels) // width)
    full = np.zeros((rows * width, 4), np.uint8)
    full[:len(pixels)] = pixels
    buf = io.BytesIO()
    Image.fromarray(full.reshape(rows, width, 4), "RGBA").save(buf, "WEBP", lossless=True,
                                                               exact=True)
    return buf.getvalue()


def sog_files(positions, log_scales, quats_wxyz, f_dc, opacity, rest=None) -> dict[str, bytes]:
    """meta.json and the WebP images of a SOG v2 scene, as splat-transform writes them."""
    n = len(positions)
    width = max(4, math.ceil(math.sqrt(n) / 4) * 4)
    u = np.sign(positions) * np.log1p(np.abs(positions))
    mins, maxs = u.min(axis=0), u.max(axis=0)
    v = np.round(65535 * (u - mins) / (maxs - mins)).astype(np.int64)
    opaque = np.full((n, 1), 255)
    low = np.concatenate([v & 255, opaque], axis=1)
    high = np.concatenate([v >> 8, opaque], axis=1)
    q = quats_wxyz / np.linalg.norm(quats_wxyz, axis=1, keepdims=True)
    largest = np.argmax(np.abs(q), axis=1)
    q = q * np.sign(q[np.arange(n), largest])[:, None] * math.sqrt(2)
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    quats = np.stack([np.round(255 * (q[np.arange(n), others[:, i]] * 0.5 + 0.5))
                      for i in range(3)] + [252 + largest], axis=1)
    scale_book = np.linspace(log_scales.min(), log_scales.max(), 256)
    colour_book = np.linspace(f_dc.min(), f_dc.max(), 256)
    nearest = lambda book, x: np.abs(x[..., None] - book).argmin(axis=-1)  # noqa: E731
    scales = np.concatenate([nearest(scale_book, log_scales), opaque], axis=1)
    sh0 = np.concatenate([nearest(colour_book, f_dc), np.round(opacity * 255)[:, None]], axis=1)
    meta = {"version": 2, "count": n,
            "means": {"mins": mins.tolist(), "maxs": maxs.tolist(),
                      "files": ["means_l.webp", "means_u.webp"]},
            "scales": {"codebook": scale_book.tolist(), "files": ["scales.webp"]},
            "quats": {"files": ["quats.webp"]},
            "sh0": {"codebook": colour_book.tolist(), "files": ["sh0.webp"]}}
    files = {"means_l.webp": _webp(low, width), "means_u.webp": _webp(high, width),
             "quats.webp": _webp(quats, width), "scales.webp": _webp(scales, width),
             "sh0.webp": _webp(sh0, width)}
    if rest is not None:  # a palette with one entry per Gaussian, in order
        k1 = rest.shape[1]
        book = np.linspace(-1, 1, 256)
        centroids = np.concatenate([nearest(book, rest).reshape(n * k1, 3),
                                    np.full((n * k1, 1), 255)], axis=1)
        labels = np.stack([np.arange(n) & 255, np.arange(n) >> 8, np.zeros(n), opaque[:, 0]],
                          axis=1)
        meta["shN"] = {"count": n, "bands": {3: 1, 8: 2, 15: 3}[k1], "codebook": book.tolist(),
                       "files": ["shN_centroids.webp", "shN_labels.webp"]}
        files["shN_centroids.webp"] = _webp(centroids, 64 * k1)
        files["shN_labels.webp"] = _webp(labels, width)
    files["meta.json"] = json.dumps(meta).encode()
    return files


def sog_scene(n=40, seed=6):
    rng = np.random.default_rng(seed)
    return dict(positions=rng.uniform(-2, 2, (n, 3)), log_scales=rng.uniform(-7, -1, (n, 3)),
                quats_wxyz=rng.normal(size=(n, 4)), f_dc=rng.uniform(-2, 2, (n, 3)),
                opacity=rng.uniform(0, 1, n), rest=rng.uniform(-1, 1, (n, 8, 3)))


def write_folder(folder, files):
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return folder


def check_sog(g, s):
    assert isinstance(g, Gaussians) and len(g) == len(s["positions"]) and g.sh_degree == 2
    np.testing.assert_allclose(g.positions, s["positions"], atol=3 * 2.2 / 65535)
    np.testing.assert_allclose(np.log(g.scales), s["log_scales"], atol=6.0 / 255 / 2 + 1e-5)
    np.testing.assert_allclose(g.rotation_matrices(), quaternion_matrices(s["quats_wxyz"]),
                               atol=2e-2)  # 8 bits a component
    np.testing.assert_allclose(g.sh[:, 0], s["f_dc"], atol=4.0 / 255 / 2 + 1e-5)
    np.testing.assert_allclose(g.opacity, s["opacity"], atol=0.5 / 255 + 1e-7)
    np.testing.assert_allclose(g.sh[:, 1:], s["rest"], atol=1.0 / 255 + 1e-6)


def test_sog_folder_meta_and_zip(tmp_path):
    s = sog_scene()
    files = sog_files(**s)
    folder = write_folder(tmp_path / "scene", files)
    check_sog(load(folder), s)
    check_sog(load(folder / "meta.json"), s)
    archive = tmp_path / "scene.sog"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in files.items():
            z.writestr(name, data)
    g = load(archive)
    check_sog(g, s)
    np.testing.assert_array_equal(g.positions, load(folder).positions)
    assert model_options(folder) == ("a SOG scene (3D Gaussian Splatting)", ("level",))
    with pytest.raises(DofsplatError, match=r"level must be a whole number from 0 to 0"):
        load(archive, level=1)


def test_sog_lod_chain_levels(tmp_path):
    fine, coarse = sog_scene(n=40, seed=1), sog_scene(n=6, seed=2)
    write_folder(tmp_path / "chain" / "0_0", sog_files(**fine))
    write_folder(tmp_path / "chain" / "1_0", sog_files(**coarse))
    lod = {"lodLevels": 2, "environment": None,
           "filenames": ["0_0/meta.json", "1_0/meta.json"],
           "tree": {"children": [
               {"lods": {"0": {"file": 0, "offset": 25, "count": 15},
                         "1": {"file": 1, "offset": 0, "count": 2}}},
               {"lods": {"0": {"file": 0, "offset": 0, "count": 25},
                         "1": {"file": 1, "offset": 2, "count": 4}}}]}}
    (tmp_path / "chain" / "lod-meta.json").write_text(json.dumps(lod))
    level0 = load(tmp_path / "chain")  # the folder: its lod-meta.json, level 0
    whole = load(tmp_path / "chain" / "0_0")
    order = np.r_[25:40, 0:25]  # the tree's order
    np.testing.assert_array_equal(level0.positions, whole.positions[order])
    np.testing.assert_array_equal(level0.sh, whole.sh[order])
    assert len(load(tmp_path / "chain" / "lod-meta.json", level=1)) == 6
    assert len(load(tmp_path / "chain", level=-1)) == 6
    with pytest.raises(DofsplatError, match=r"level must be a whole number from 0 to 1"):
        load(tmp_path / "chain", level=2)
    lod["tree"]["children"][0]["lods"]["0"]["count"] = 30  # rows 25..55 of 40
    (tmp_path / "chain" / "lod-meta.json").write_text(json.dumps(lod))
    with pytest.raises(DofsplatError, match=r"rows 25 to 55 of 0_0/meta.json, which has 40"):
        load(tmp_path / "chain")


def test_sog_bad_input(tmp_path):
    s = sog_scene(n=10)
    files = sog_files(**s)
    meta = json.loads(files["meta.json"])
    cases = [({"meta.json": b"{not json"}, "bad JSON"),
             ({"meta.json": json.dumps({**meta, "version": 3}).encode()}, "version 3"),
             ({"meta.json": json.dumps({k: v for k, v in meta.items()
                                        if k != "version"}).encode()}, "version 1"),
             ({"meta.json": json.dumps({**meta, "count": 10**6}).encode()},
              "pixels for 1,000,000 Gaussians"),
             ({"meta.json": json.dumps({**meta, "means": {"mins": [0, 0]}}).encode()},
              "means.mins must be 3 numbers"),
             ({"quats.webp": b"RIFF0000WEBPjunk"}, "quats.webp is not a readable image")]
    for i, (change, why) in enumerate(cases):
        folder = write_folder(tmp_path / f"case{i}", {**files, **change})
        with pytest.raises(DofsplatError, match=why) as e:
            load(folder)
        assert "\n" not in str(e.value)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DofsplatError, match=r"a folder, not a model file"):
        load(empty)
    (tmp_path / "x.sog").write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(DofsplatError, match=r"corrupt .sog \(zip\) file"):
        load(tmp_path / "x.sog")


# -- the registry, the cache and the command line -----------------------------------------


def test_registry_and_no_cache_for_gaussians(tmp_path, monkeypatch):
    from dofsplat import cache
    from dofsplat.io import prepared

    assert {".spz", ".sog", "meta.json", "lod-meta.json"} <= set(LOADERS)
    monkeypatch.setattr(prepared, "MIN_SECONDS", 0.0)
    monkeypatch.setenv("DOFSPLAT_CACHE_MAX", str(1 << 30))
    path = tmp_path / "s.spz"
    path.write_bytes(spz_bytes(4, **spz_scene()))
    g = load(path, cache="auto")
    assert isinstance(g, Gaussians) and g.load_info["from_cache"] is False
    folder = cache.cache_folder("surfels")
    assert not folder.exists() or not list(folder.iterdir())
    with pytest.raises(DofsplatError, match=r"unknown option\(s\) k"):
        load(path, k=8)


def test_convert_writes_a_3dgs_ply(tmp_path):
    s = spz_scene()
    src = tmp_path / "s.spz"
    src.write_bytes(spz_bytes(3, **s))
    out = tmp_path / "s.ply"
    assert cli.main(["convert", str(src), "-o", str(out), "-q"]) == 0
    a, b = load(src), load(out)
    for field in ("positions", "scales", "rotations", "sh"):
        np.testing.assert_array_equal(getattr(b, field), getattr(a, field), err_msg=field)
    # an 8-bit opacity k / 255 has no float32 logit that maps back exactly: the nearest
    np.testing.assert_allclose(b.opacity, a.opacity, rtol=0, atol=3e-8)
    assert cli.main(["convert", str(src), "-o", str(tmp_path / "t.ply"), "--k", "8"]) == 2


# -- the real scenes -----------------------------------------------------------------------


def test_real_gaussian_donut():
    g = load(shared("gaussian_donut/fused.ply"))
    assert isinstance(g, Gaussians) and len(g) == 45_624 and g.sh_degree == 0
    lo, hi = g.bounds()
    assert np.all(hi - lo < 0.25) and np.all(hi - lo > 0.05)
    assert 0.3 < g.opacity.mean() < 0.9


def test_real_fruit_drops_sh3():
    with pytest.warns(UserWarning, match=r"ignored vertex properties transform"):
        g = load(shared("gaussian_scenes/fruit_drops_minimal.ply"))
    assert len(g) == 4_721 and g.sh.shape == (4_721, 16, 3)
    assert np.abs(g.sh[:, 1:]).max() > 0.05  # view-dependent colour is there


@pytest.mark.parametrize("name, count", [("biker", 152_746), ("guitar", 90_854)])
def test_real_compressed_plys(name, count):
    g = load(shared(f"gaussian_scenes/{name}.compressed.ply"))
    assert len(g) == count and g.sh_degree == 0
    lo, hi = g.bounds()
    assert np.all(hi - lo > 0.5) and np.all(hi - lo < 6)
    assert 0 < g.opacity.min() <= g.opacity.max() <= 1


def test_real_biker_spz_agrees_with_its_compressed_ply():
    """The same scene in two formats: SPZ (RUB, 12 fraction bits) and the compressed PLY
    (RDF, 11/10/11 bits per chunk), row for row."""
    a = load(shared("gaussian_scenes/biker.spz"))
    b = load(shared("gaussian_scenes/biker.compressed.ply"))
    assert len(a) == len(b) == 152_746
    # positions: within half an SPZ step (1/4096) plus the PLY's own (found 1.22e-4)
    np.testing.assert_allclose(a.positions, b.positions, atol=0.5 / 4096 + 1e-6)
    np.testing.assert_array_equal(a.opacity, b.opacity)  # both 8-bit, found identical
    # log-scales within SPZ's 1/16 step where SPZ's -10 floor does not clamp (median 1/64)
    log_a, log_b = np.log(a.scales), np.log(b.scales)
    free = np.all(log_b > -9.9, axis=1)
    assert free.mean() > 0.9
    assert np.abs(log_a - log_b)[free].max() < 1 / 32 + 0.01
    # colours within SPZ's step 1 / (255 x 0.15) = 0.026 (found at most 0.013)
    np.testing.assert_allclose(a.sh[:, 0], b.sh[:, 0], atol=0.5 / 255 / 0.15 + 1e-4)
    # orientations within a fraction of a degree (found at most 0.15 degrees)
    turn = np.einsum("nij,nik->njk", a.rotation_matrices(), b.rotation_matrices())
    angle = np.degrees(np.arccos(np.clip((np.trace(turn, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angle.max() < 0.5


def test_real_playbot_sog_levels():
    folder = shared("gaussian_scenes/playbot")
    chain = json.loads((folder / "lod-meta.json").read_text())
    g = load(folder)
    assert len(g) == 500_000 and g.sh_degree == 2
    bound = chain["tree"]["bound"]
    lo, hi = g.positions.min(axis=0), g.positions.max(axis=0)
    assert np.all(lo >= np.array(bound["min"]) - 1e-3)
    assert np.all(hi <= np.array(bound["max"]) + 1e-3)
    assert 0.3 < g.opacity.mean() < 0.9
    assert len(load(folder, level=1)) == 250_000
    coarsest = load(folder / "lod-meta.json", level=6)
    assert len(coarsest) == sum(child["lods"]["6"]["count"]
                                for child in chain["tree"]["children"])


def test_real_scenes_flatten_to_surfels():
    g = load(shared("gaussian_donut/fused.ply"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = gaussians_to_surfels(g, source="donut")
    assert s.is_elliptical and 40_000 < len(s) <= 45_624
    assert np.all(s.radius_v <= s.radius + 1e-9)


# -- a trainer's cameras.json ------------------------------------------------------------

def trainer_layout(tmp_path, cameras):
    """A trainer's output folder: MODEL/point_cloud/iteration_7000/point_cloud.ply (a white
    Gaussian at (2, 1, 0) and a red one 0.3 along +x from it) and MODEL/cameras.json
    (cameras: the JSON to write, or a string written as it is). Returns the PLY's path."""
    ply = tmp_path / "model" / "point_cloud" / "iteration_7000" / "point_cloud.ply"
    ply.parent.mkdir(parents=True)
    positions = np.array([[2.0, 1.0, 0.0], [2.3, 1.0, 0.0]])
    sh = np.zeros((2, 1, 3))
    sh[0, 0] = (1.0 - 0.5) / SH_C0  # white
    sh[1, 0] = (np.array([1.0, 0.0, 0.0]) - 0.5) / SH_C0  # red
    cols = gaussian_ply_columns(positions, np.log(np.full((2, 3), 0.04)),
                                np.tile([1.0, 0, 0, 0], (2, 1)), np.full(2, 6.0), sh)
    PlyData([PlyElement.describe(np.rec.fromarrays(list(cols.values()), names=list(cols)),
                                 "vertex")]).write(str(ply))
    text = cameras if isinstance(cameras, str) else json.dumps(cameras)
    (tmp_path / "model" / "cameras.json").write_text(text)
    return ply


# a camera 3 units from the white Gaussian, looking along -z, with the world's +x up: its
# rotation's columns are its right (-y), down (-x) and forward (-z) axes, as 3DGS writes them
TRAINER_CAMERA = {"id": 0, "img_name": "0001", "width": 800, "height": 600,
                  "position": [2.0, 1.0, 3.0],
                  "rotation": [[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]],
                  "fx": 700.0, "fy": 700.0}


def test_a_trainers_cameras_json_gives_the_default_view(tmp_path):
    """``dofsplat render`` of a trainer's point_cloud.ply starts from the first camera of
    MODEL/cameras.json: the white Gaussian it looks at lands on the image centre, the red
    one (0.3 along the camera's up, +x) above it, and the view's width is fx's: 2 atan(400 /
    700) across, so the red one is 0.3 / 3 x 700 / 800 x 80 = 7 px above the centre at 80 px
    wide (aspect kept: 80 x 60)."""
    ply = trainer_layout(tmp_path, [TRAINER_CAMERA, {**TRAINER_CAMERA, "position": [9, 9, 9]}])
    scene = load(ply)
    np.testing.assert_allclose(scene.capture["eye"], [2.0, 1.0, 3.0])
    np.testing.assert_allclose(scene.capture["target"], [2.0, 1.0, 2.0])
    np.testing.assert_allclose(scene.up_hint, [1.0, 0.0, 0.0])
    out = tmp_path / "view.png"
    assert cli.main(["render", str(ply), "-o", str(out), "--no-dof", "-q", "--size",
                     "80x60"]) == 0
    image = np.asarray(Image.open(out).convert("RGB"), np.float64)
    white = image.sum(axis=2) - 2 * np.abs(image[..., 0] - image[..., 1])
    row, col = np.unravel_index(np.argmax(white), white.shape)
    assert abs(row - 29.5) <= 1 and abs(col - 39.5) <= 1, (row, col)
    red = image[..., 0] - image[..., 1]
    r_row, r_col = np.unravel_index(np.argmax(red), red.shape)
    assert abs((row - r_row) - 7) <= 1 and abs(r_col - col) <= 1, (r_row, r_col)


@pytest.mark.parametrize("text, why", [
    ("{not json", "not JSON"),
    ("[]", "not a non-empty list of cameras"),
    (json.dumps([{"id": 0}]), "camera 0 has no width, height, position, rotation, fx, fy"),
    (json.dumps([{**TRAINER_CAMERA, "fx": -1}]), "sizes and focal lengths > 0"),
    (json.dumps([{**TRAINER_CAMERA, "rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}]),
     "camera 0: rotation is not a rotation matrix"),
    (json.dumps([{**TRAINER_CAMERA, "position": [1, 2]}]), "must be numbers"),
])
def test_a_damaged_cameras_json_is_said_and_ignored(tmp_path, text, why):
    """A cameras.json that cannot be read is named in one warning, with the reason, and the
    scene loads without it (framed as any scene: y down)."""
    ply = trainer_layout(tmp_path, text)
    with pytest.warns(UserWarning, match="cameras.json: ignored") as said:
        scene = load(ply)
    assert why in str(said[0].message)
    assert scene.capture is None and scene.up_hint == (0.0, -1.0, 0.0)
