"""Fuzzing the PLY, PCD and Gaussian-scene readers: a damaged file is a DofsplatError, never
anything else.

Seeds are small valid files of every kind the readers tell apart (surfels, bare points,
meshes and 3D Gaussian splats in PLY, ASCII / binary / gzip; PCD in its three data modes,
organised or not; Gaussian scenes as a compressed PLY with an sh element, SPZ versions 2, 3
and 4, and a zipped SOG). Each is mutated in two ways:

* a deterministic loop of byte mutations (flips, truncations, insertions, deletions,
  numbers in the header replaced by others): FUZZ_CASES files per reader;
* hypothesis, which picks a seed and a list of edits (max_examples per reader), with no
  example database so that a run leaves nothing behind.

A mutated file must load as surfels (or Gaussians) or raise DofsplatError: any other
exception, a hang (the suite's timeout) or a crash is a bug. Mesh sampling is capped at a few samples so that
the test stays at a few seconds. A longer run: DOFSPLAT_FUZZ_CASES=20000
DOFSPLAT_FUZZ_EXAMPLES=4000 python -m pytest tests/test_fuzz.py (passed when written).
"""

from __future__ import annotations

import functools
import os
import gzip
import io
import random
import re
import struct
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from plyfile import PlyData, PlyElement

from dofsplat.errors import DofsplatError
from dofsplat.gaussians import Gaussians
from dofsplat.io import load
from dofsplat.surfels import Surfels

FUZZ_CASES = int(os.environ.get("DOFSPLAT_FUZZ_CASES", 1000))  # deterministic mutations per reader
HYPOTHESIS_EXAMPLES = int(os.environ.get("DOFSPLAT_FUZZ_EXAMPLES", 200))  # per reader
_NUMBER = re.compile(rb"-?\d+(\.\d+)?")
_ODD_NUMBERS = [b"0", b"1", b"-1", b"3", b"255", b"65536", b"4294967295", b"99999999999",
                b"nan", b"1e300", b"2.5"]


# -- seeds ---------------------------------------------------------------------------------


def _ply(elements, text=False, gz=False) -> bytes:
    buf = io.BytesIO()
    PlyData(elements, text=text).write(buf)
    data = buf.getvalue()
    return gzip.compress(data, mtime=0) if gz else data


def _vertex(columns: dict) -> PlyElement:
    n = len(next(iter(columns.values())))
    rec = np.empty(n, dtype=[(k, np.asarray(v).dtype) for k, v in columns.items()])
    for k, v in columns.items():
        rec[k] = v
    return PlyElement.describe(rec, "vertex")


def _faces(faces) -> PlyElement:
    face = np.empty(len(faces), dtype=[("vertex_indices", "O")])
    face["vertex_indices"] = [np.asarray(f, np.int32) for f in faces]
    return PlyElement.describe(face, "face", val_types={"vertex_indices": "i4"})


@functools.lru_cache(maxsize=None)
def ply_seeds() -> list[tuple[str, bytes]]:
    rng = np.random.default_rng(0)
    n = 12
    xyz = {k: rng.uniform(-1, 1, n).astype(np.float32) for k in "xyz"}
    surfel = dict(xyz, nx=np.zeros(n, np.float32), ny=np.zeros(n, np.float32),
                  nz=np.ones(n, np.float32), radius=np.full(n, 0.2, np.float32))
    points = dict(xyz, red=rng.integers(0, 256, n).astype(np.uint8),
                  green=np.zeros(n, np.uint8), blue=np.full(n, 9, np.uint8))
    gauss = dict(xyz, f_dc_0=rng.normal(size=n).astype(np.float32),
                 f_dc_1=np.zeros(n, np.float32), f_dc_2=np.zeros(n, np.float32),
                 opacity=np.ones(n, np.float32),
                 **{f"scale_{i}": np.full(n, -3.0, np.float32) for i in range(3)},
                 **{f"rot_{i}": rng.normal(size=n).astype(np.float32) for i in range(4)})
    mesh_v = {"x": np.array([0, 1, 1, 0, 2], np.float32),
              "y": np.array([0, 0, 1, 1, 0.5], np.float32), "z": np.zeros(5, np.float32)}
    tris, polys = [[0, 1, 2], [0, 2, 3], [1, 4, 2]], [[0, 1, 2, 3], [1, 4, 2]]
    return [
        ("surfels.ply", _ply([_vertex(surfel)])),
        ("surfels_ascii.ply", _ply([_vertex(surfel)], text=True)),
        ("points.ply", _ply([_vertex(points)])),
        ("points_ascii.ply", _ply([_vertex(points)], text=True)),
        ("gauss.ply", _ply([_vertex(gauss)])),
        ("mesh.ply", _ply([_vertex(mesh_v), _faces(tris)])),
        ("mesh_ascii.ply", _ply([_vertex(mesh_v), _faces(tris)], text=True)),
        ("poly_ascii.ply", _ply([_vertex(mesh_v), _faces(polys)], text=True)),
        ("poly.ply", _ply([_vertex(mesh_v), _faces(polys)])),
        ("mesh_ascii.ply.gz", _ply([_vertex(mesh_v), _faces(tris)], text=True, gz=True)),
    ]


@functools.lru_cache(maxsize=None)
def pcd_seeds() -> list[tuple[str, bytes]]:
    import lzf

    rng = np.random.default_rng(1)
    n = 12
    x, y, z = (rng.uniform(-1, 1, n).astype(np.float32) for _ in range(3))
    rgb = rng.integers(0, 1 << 24, n).astype(np.uint32) | np.uint32(0xFF000000)

    def head(mode, fields="x y z rgb", size="4 4 4 4", typ="F F F U", width=n, height=1):
        return (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {typ}\n"
                f"COUNT {' '.join('1' for _ in fields.split())}\nWIDTH {width}\n"
                f"HEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {width * height}\n"
                f"DATA {mode}\n").encode()

    ascii_body = "".join(f"{x[i]} {y[i]} {z[i]} {rgb[i]}\n" for i in range(n)).encode()
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    rec["x"], rec["y"], rec["z"], rec["rgb"] = x, y, z, rgb
    raw = x.tobytes() + y.tobytes() + z.tobytes() + rgb.tobytes()
    packed = lzf.compress(raw, 2 * len(raw) + 64)  # room to grow: random data does not shrink
    organised_z = z.copy()
    organised_z[[1, 5]] = np.nan
    raw_org = x.tobytes() + y.tobytes() + organised_z.tobytes()
    packed_org = lzf.compress(raw_org, 2 * len(raw_org) + 64)
    return [
        ("ascii.pcd", head("ascii") + ascii_body),
        ("binary.pcd", head("binary") + rec.tobytes()),
        ("compressed.pcd", head("binary_compressed") + struct.pack("<II", len(packed), len(raw))
         + packed),
        ("organised.pcd", head("binary_compressed", "x y z", "4 4 4", "F F F", 4, 3)
         + struct.pack("<II", len(packed_org), len(raw_org)) + packed_org),
    ]


@functools.lru_cache(maxsize=None)
def gaussian_seeds() -> list[tuple[str, bytes]]:
    """Small Gaussian scenes, written by the encoders of tests/test_gaussian_io.py."""
    import tempfile
    import zipfile

    from test_gaussian_io import compressed_ply, sog_files, sog_scene, spz_bytes, spz_scene

    rng = np.random.default_rng(2)
    n = 12
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "c.ply")
        compressed_ply(path, rng.normal(size=(n, 3)), rng.uniform(-5, -1, (n, 3)),
                       rng.normal(size=(n, 4)), rng.uniform(0, 1, (n, 3)), rng.uniform(0, 1, n),
                       rest=rng.uniform(-1, 1, (n, 3, 3)))
        with open(path, "rb") as f:
            compressed = f.read()
    sog = io.BytesIO()
    with zipfile.ZipFile(sog, "w", zipfile.ZIP_STORED) as z:
        for name, data in sog_files(**sog_scene(n=n)).items():
            z.writestr(name, data)
    scene = spz_scene(n=n)
    return [
        ("scene.compressed.ply", compressed),
        ("v2.spz", spz_bytes(2, **scene)),
        ("v3.spz", spz_bytes(3, **scene)),
        ("v4.spz", spz_bytes(4, **scene)),
        ("scene.sog", sog.getvalue()),
    ]


SEEDS = {"ply": ply_seeds, "pcd": pcd_seeds, "gaussians": gaussian_seeds}


# -- mutations -----------------------------------------------------------------------------


def mutate(data: bytes, rng: random.Random) -> bytes:
    """One to three random edits of data."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 3)):
        op = rng.randrange(6)
        if op == 0 and b:  # flip bytes
            for _ in range(rng.randint(1, 4)):
                b[rng.randrange(len(b))] = rng.randrange(256)
        elif op == 1 and b:  # truncate
            del b[rng.randrange(len(b)):]
        elif op == 2:  # insert
            at = rng.randrange(len(b) + 1)
            b[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
        elif op == 3 and b:  # delete a slice
            at = rng.randrange(len(b))
            del b[at:at + rng.randint(1, 16)]
        elif op == 4:  # a number of the header replaced by an odd one
            head = bytes(b[:300])
            numbers = list(_NUMBER.finditer(head))
            if numbers:
                m = rng.choice(numbers)
                b[m.start():m.end()] = rng.choice(_ODD_NUMBERS)
        elif op == 5 and b:  # duplicate a line
            lines = bytes(b).split(b"\n")
            i = rng.randrange(len(lines))
            lines.insert(i, lines[i])
            b = bytearray(b"\n".join(lines))
    return bytes(b)


def load_or_error(path) -> None:
    """Load a (damaged) file: Surfels, Gaussians or DofsplatError, nothing else."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            result = load(path)
        except DofsplatError as e:
            assert str(e) and "\n" not in str(e), repr(str(e))
            return
    assert isinstance(result, (Surfels, Gaussians))


@pytest.fixture(autouse=True)
def _few_samples(monkeypatch):
    """Meshes sample 40 points, not 200k, and the normalisation's level is read from one
    view, not six: the fuzzing is about parsing (the six renders were two thirds of a
    point cloud's load here: 1.6 of 2.4 s for 20 loads of the binary PCD, profiled)."""
    import functools

    import dofsplat.prep.meshes as meshes
    import dofsplat.prep.normalise as normalise

    monkeypatch.setattr(meshes, "DEFAULT_MIN_SAMPLES", 40)
    monkeypatch.setattr(normalise, "rendered_level",
                        functools.partial(normalise.rendered_level, views=1))


def _check_mutation(path, data: bytes, what: str) -> None:
    path.write_bytes(data)
    try:
        load_or_error(path)
    except AssertionError:
        raise
    except Exception as e:  # the bug the fuzzing looks for: report the input
        pytest.fail(f"{what}: {type(e).__name__}: {e}\ninput ({len(data)} bytes): {data!r}")


# -- the tests -----------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["ply", "pcd", "gaussians"])
def test_seeds_load(tmp_path, kind):
    for name, data in SEEDS[kind]():
        path = tmp_path / name
        path.write_bytes(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert len(load(path)) > 0, name


@pytest.mark.parametrize("kind", ["ply", "pcd", "gaussians"])
def test_byte_mutations_raise_only_dofsplat_errors(tmp_path, kind):
    seeds = SEEDS[kind]()
    rng = random.Random(f"dofsplat-{kind}")
    for i in range(FUZZ_CASES):
        name, data = seeds[i % len(seeds)]
        _check_mutation(tmp_path / name, mutate(data, rng), f"{kind} case {i} from {name}")


def _edits():
    return st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255),
                              st.sampled_from(["set", "insert", "delete"])),
                    min_size=1, max_size=6)


def _apply(data: bytes, edits, cut) -> bytes:
    b = bytearray(data)
    for at, value, op in edits:
        at = at % (len(b) + 1)
        if op == "set" and at < len(b):
            b[at] = value
        elif op == "insert":
            b[at:at] = bytes([value])
        elif op == "delete":
            del b[at:at + 1 + value % 8]
    return bytes(b[:cut] if cut is not None else b)


_HYPOTHESIS = settings(max_examples=HYPOTHESIS_EXAMPLES, deadline=None, database=None,
                       derandomize=True,
                       suppress_health_check=[HealthCheck.function_scoped_fixture,
                                              HealthCheck.too_slow])


@_HYPOTHESIS
@given(seed=st.integers(0, 9), edits=_edits(), cut=st.none() | st.integers(0, 2000))
def test_hypothesis_ply(tmp_path, seed, edits, cut):
    name, data = ply_seeds()[seed]
    _check_mutation(tmp_path / name, _apply(data, edits, cut), f"ply from {name}")


@_HYPOTHESIS
@given(seed=st.integers(0, 3), edits=_edits(), cut=st.none() | st.integers(0, 2000))
def test_hypothesis_pcd(tmp_path, seed, edits, cut):
    name, data = pcd_seeds()[seed]
    _check_mutation(tmp_path / name, _apply(data, edits, cut), f"pcd from {name}")


def test_sog_member_mutations_raise_only_dofsplat_errors(tmp_path):
    """A zip's checksums catch most flips in a .sog: here one member at a time (meta.json or
    an image) is damaged and the archive rebuilt, so that the JSON and WebP decoding see it."""
    import zipfile

    from test_gaussian_io import sog_files, sog_scene

    files = sog_files(**sog_scene(n=12))
    names = sorted(files)
    rng = random.Random("dofsplat-sog")
    for i in range(FUZZ_CASES // 4):
        name = names[i % len(names)]
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as z:
            for member, data in files.items():
                z.writestr(member, mutate(data, rng) if member == name else data)
        _check_mutation(tmp_path / "scene.sog", buf.getvalue(), f"sog case {i}, {name} damaged")


@_HYPOTHESIS
@given(seed=st.integers(0, 4), edits=_edits(), cut=st.none() | st.integers(0, 2000))
def test_hypothesis_gaussians(tmp_path, seed, edits, cut):
    name, data = gaussian_seeds()[seed]
    _check_mutation(tmp_path / name, _apply(data, edits, cut), f"gaussians from {name}")


@settings(max_examples=300, deadline=None, database=None, derandomize=True)
@given(text=st.binary(max_size=400))
def test_header_parsers_on_arbitrary_bytes(text):
    from dofsplat.io.pcd import parse_pcd_header
    from dofsplat.io.ply import parse_ply_header

    for parse, prefix in ((parse_ply_header, b"ply\nformat ascii 1.0\n"), (parse_pcd_header, b"")):
        for data in (text, prefix + text):
            try:
                parse(data, "fuzz")
            except DofsplatError:
                pass
