"""Niantic's SPZ files (``.spz``): quantised 3D Gaussian Splatting scenes, read as Gaussians.

The format (nianticlabs/spz, README "File Format"): a header, then per Gaussian and
attribute by attribute (all of one attribute, then the next):

* positions: 3 signed 24-bit fixed-point numbers, ``fractionalBits`` of fraction
  (version 1: 3 float16);
* alphas: 1 byte, the opacity times 255 (the sigmoid, not the logit);
* colours: 3 bytes b, the SH degree-0 coefficient f_dc = (b / 255 - 0.5) / 0.15;
* scales: 3 bytes b, the log standard deviation b / 16 - 10;
* rotations: version 3 and 4, a uint32 with the index of the largest of (x, y, z, w) in the
  top 2 bits and the other three as 10 bits each (sign, then 9 bits of magnitude in units
  of 1/(511 sqrt 2)), the last of them in the low bits; version 1 and 2, x y z as bytes
  b / 127.5 - 1 and w = sqrt(1 - x^2 - y^2 - z^2);
* spherical harmonics: (degree + 1)^2 - 1 coefficients per channel, colour the inner axis,
  each byte b the value (b - 128) / 128.

Versions 1 to 3 are one gzip stream of a 16-byte header (magic "NGSP", version, count,
degree, fractional bits, flags, a reserved byte) and the attributes. Version 4 is a 32-byte
plain header (the same fields, then the stream count, the byte offset of the table of
contents, 12 reserved bytes), optional extension records, a table of contents (compressed
and decompressed size of each stream, uint64) and each attribute a Zstandard stream of its
own (zstandard decompresses them).

Coordinates: SPZ stores RUB (x right, y up, z back: OpenGL's), the 3DGS PLY RDF (x right,
y down, z forward: OpenCV's). The Gaussians are turned into the PLY's axes, so that an SPZ
and a PLY of one scene load alike: y and z change sign, and with them the quaternions' y and
z and the SH coefficients whose basis function is odd in y or z. An
``SPZ_ADOBE_coordinate_system`` extension record naming another of the eight axis-flip
systems is honoured the same way; the rotated ones are refused. An antialiased scene (flag
0x1, mip-splatting) is read as ordinary Gaussians, with a warning. SH degree 4 is cut to 3.
"""

from __future__ import annotations

import gzip
import io
import math
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np

from ..errors import DofsplatError
from ..gaussians import Gaussians
from .gaussians import _float32

MAGIC = b"NGSP"
COLOUR_SCALE = 0.15  # SPZ's colour byte scale (the f_dc value of one step is 1/(255 0.15))
FLAG_ANTIALIASED = 0x1
FLAG_EXTENSIONS = 0x2
COORDINATE_EXTENSION = 0xADBE0003  # SPZ_ADOBE_coordinate_system: a uint32 system number
# the axis-flip systems (SPZ's CoordinateSystem 1 to 8); 0 (unspecified) reads as RUB
SYSTEMS = {1: "LDB", 2: "RDB", 3: "LUB", 4: "RUB", 5: "LDF", 6: "RDF", 7: "LUF", 8: "RUF"}
DEFAULT_SYSTEM = "RUB"
# which of x, y, z each of 3DGS's real SH basis functions 1..15 is odd in (their
# polynomials: y, z, x; xy, yz, 3z^2 - 1, xz, x^2 - y^2; y(3x^2 - y^2), xyz, y(5z^2 - 1),
# z(5z^2 - 3), x(5z^2 - 1), z(x^2 - y^2), x(x^2 - 3y^2)): a mirror of those axes flips them
SH_ODD = np.array([(0, 1, 0), (0, 0, 1), (1, 0, 0), (1, 1, 0), (0, 1, 1), (0, 0, 0),
                   (1, 0, 1), (0, 0, 0), (0, 1, 0), (1, 1, 1), (0, 1, 0), (0, 0, 1),
                   (1, 0, 0), (0, 0, 1), (1, 0, 0)])


def read_spz(path) -> Gaussians:
    """Load the Gaussians of an ``.spz`` file (module docstring), in the 3DGS PLY's axes.

    DofsplatError naming the file for anything damaged: a bad magic number or version, a
    header whose sizes do not fit the data, a broken gzip or Zstandard stream.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise DofsplatError(f"{path}: cannot read: {e.strerror or e}") from e
    if data[:2] == b"\x1f\x8b":
        try:
            data = gzip.decompress(data)
        except (OSError, EOFError, zlib.error) as e:  # gzip.BadGzipFile is an OSError
            raise DofsplatError(f"{path}: corrupt SPZ file: its gzip stream is damaged "
                                f"({type(e).__name__})") from e
    return decode_spz(data, str(path))


def decode_spz(data: bytes, source: str = "SPZ") -> Gaussians:
    """The Gaussians of an SPZ file's bytes (gzip already undone for versions 1 to 3)."""
    if len(data) < 16 or data[:4] != MAGIC:
        raise DofsplatError(f"{source}: not an SPZ file (no 'NGSP' magic number)")
    version, n, degree, fraction_bits, flags = struct.unpack_from("<IIBBB", data, 4)
    if not 1 <= version <= 4:
        raise DofsplatError(f"{source}: SPZ version {version} is not supported (1 to 4 are)")
    if n == 0:
        raise DofsplatError(f"{source}: the SPZ file holds no Gaussians")
    if degree > 4:
        raise DofsplatError(f"{source}: SPZ SH degree {degree}; the format has 0 to 4")
    if fraction_bits > 23:
        raise DofsplatError(f"{source}: SPZ fractional bits {fraction_bits}; at most 23 fit "
                            "a 24-bit position")
    rest = (degree + 1) ** 2 - 1
    sizes = [n * (6 if version == 1 else 9), n, 3 * n, 3 * n,
             n * (4 if version >= 3 else 3), 3 * rest * n]
    if version >= 4:
        streams, extensions = _zstd_streams(data, sizes if rest else sizes[:5], flags, source)
    else:
        streams, extensions = _plain_streams(data, sizes, flags, source)
    positions, alphas, colours, scales, rotations = streams[:5]

    if version == 1:
        xyz = np.frombuffer(positions, "<f2").reshape(n, 3).astype(np.float64)
    else:
        b = np.frombuffer(positions, np.uint8).reshape(n, 3, 3).astype(np.int64)
        fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
        xyz = np.where(fixed & 0x800000, fixed - (1 << 24), fixed) / float(1 << fraction_bits)
    log_scales = np.frombuffer(scales, np.uint8).reshape(n, 3) / 16.0 - 10.0
    if version >= 3:
        xyzw = _smallest_three(np.frombuffer(rotations, "<u4").astype(np.int64))
    else:
        first = np.frombuffer(rotations, np.uint8).reshape(n, 3) / 127.5 - 1.0
        w = np.sqrt(np.maximum(0.0, 1.0 - np.sum(first * first, axis=1)))
        xyzw = np.concatenate([first, w[:, None]], axis=1)
    sh = np.empty((n, min(rest, 15) + 1, 3), np.float64)
    sh[:, 0] = (np.frombuffer(colours, np.uint8).reshape(n, 3) / 255.0 - 0.5) / COLOUR_SCALE
    if rest:
        coeffs = (np.frombuffer(streams[5], np.uint8).reshape(n, rest, 3) - 128.0) / 128.0
        sh[:, 1:] = coeffs[:, :15]
    if degree == 4:
        warnings.warn(f"{source}: SH degree 4 is cut to degree 3 (its 9 highest coefficients "
                      "per channel are dropped)", stacklevel=3)
    if flags & FLAG_ANTIALIASED:
        warnings.warn(f"{source}: the scene was trained with antialiasing (mip-splatting); it "
                      "is drawn as ordinary Gaussians", stacklevel=3)

    signs = _axis_signs(_coordinate_system(extensions, source))
    rotations_wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    xyz, rotations_wxyz, sh = mirror_axes(xyz, rotations_wxyz, sh, signs)
    with np.errstate(over="ignore"):
        scales_linear = np.exp(log_scales)
    return Gaussians.from_arrays(_float32(xyz), _float32(scales_linear),
                                 _float32(rotations_wxyz),
                                 _float32(np.frombuffer(alphas, np.uint8) / 255.0),
                                 _float32(sh), source=source)


def _plain_streams(data: bytes, sizes: list[int], flags: int, source: str):
    """Versions 1-3: the attributes one after the other from byte 16; extension records, if
    flagged, after them."""
    end = 16 + sum(sizes)
    if len(data) < end:
        raise DofsplatError(f"{source}: truncated SPZ file: the header promises "
                            f"{end:,} bytes of data, the file holds {len(data):,}")
    streams, at = [], 16
    for size in sizes:
        streams.append(data[at:at + size])
        at += size
    extensions = _extension_records(data[end:], source) if flags & FLAG_EXTENSIONS else {}
    return streams, extensions


def _zstd_streams(data: bytes, sizes: list[int], flags: int, source: str):
    """Version 4: a Zstandard stream per attribute, located by the table of contents."""
    if len(data) < 32:
        raise DofsplatError(f"{source}: truncated SPZ file: the header needs 32 bytes")
    count, toc = struct.unpack_from("<BI", data, 15)
    if count != len(sizes):
        raise DofsplatError(f"{source}: corrupt SPZ file: {count} streams, where its SH "
                            f"degree needs {len(sizes)}")
    at = toc + 16 * count
    if toc < 32 or at > len(data):
        raise DofsplatError(f"{source}: corrupt SPZ file: its table of contents (byte "
                            f"{toc:,}) lies outside the file ({len(data):,} bytes)")
    extensions = _extension_records(data[32:toc], source) if flags & FLAG_EXTENSIONS else {}
    try:
        import zstandard
    except ImportError:  # a declared dependency: only a broken installation lacks it
        raise DofsplatError(f"{source}: SPZ version 4 needs the zstandard package "
                            "(pip install zstandard)") from None
    streams = []
    for i, size in enumerate(sizes):
        packed, unpacked = struct.unpack_from("<QQ", data, toc + 16 * i)
        if unpacked != size or at + packed > len(data):
            raise DofsplatError(f"{source}: corrupt SPZ file: stream {i} has {unpacked:,} "
                                f"bytes ({packed:,} packed) where {size:,} are needed, or "
                                "runs past the end")
        try:
            # read through a bounded stream: a damaged frame header can claim any size,
            # which decompress() would allocate up front
            reader = zstandard.ZstdDecompressor().stream_reader(
                io.BytesIO(data[at:at + packed]), read_across_frames=True)
            stream = reader.read(size + 1)
        except zstandard.ZstdError as e:
            raise DofsplatError(f"{source}: corrupt SPZ file: stream {i} does not "
                                f"decompress ({' '.join(str(e).split())})") from e
        if len(stream) != size:
            raise DofsplatError(f"{source}: corrupt SPZ file: stream {i} decompresses to "
                                f"{len(stream):,} bytes, not {size:,}")
        streams.append(stream)
        at += packed
    return streams, extensions


def _extension_records(block: bytes, source: str) -> dict[int, bytes]:
    """Extension records ``[u32 type][u32 length][payload]``, type -> payload."""
    records, at = {}, 0
    while at + 8 <= len(block):
        kind, length = struct.unpack_from("<II", block, at)
        if at + 8 + length > len(block):
            raise DofsplatError(f"{source}: corrupt SPZ file: an extension record runs past "
                                "its block")
        records[kind] = block[at + 8:at + 8 + length]
        at += 8 + length
    return records


def _coordinate_system(extensions: dict[int, bytes], source: str) -> str:
    payload = extensions.get(COORDINATE_EXTENSION)
    if payload is None:
        return DEFAULT_SYSTEM
    value = struct.unpack_from("<I", payload)[0] if len(payload) >= 4 else -1
    if value == 0:
        return DEFAULT_SYSTEM
    if value not in SYSTEMS:
        raise DofsplatError(f"{source}: SPZ coordinate system {value} is not supported (only "
                            "the axis flips 1 to 8, such as RUB and RDF, are)")
    return SYSTEMS[value]


def _axis_signs(system: str) -> np.ndarray:
    """(3,) signs that take the axes of ``system`` (such as "RUB") to the PLY's RDF."""
    return np.array([1.0 if system[0] == "R" else -1.0, 1.0 if system[1] == "D" else -1.0,
                     1.0 if system[2] == "F" else -1.0])


def mirror_axes(positions: np.ndarray, rotations: np.ndarray, sh: np.ndarray,
                signs: np.ndarray):
    """Gaussians seen in axes mirrored by ``signs`` (3,) of +-1, F = diag(signs):
    positions F p, rotations F R F (the quaternion (w, x, y, z) times (1, sy sz, sx sz,
    sx sy), which is a rotation whatever the signs), and each SH coefficient times the sign
    its basis function takes under F (``SH_ODD``).

    positions (N, 3), rotations (N, 4) w first, sh (N, K, 3); returns new arrays."""
    sx, sy, sz = (float(s) for s in signs)
    q_signs = np.array([1.0, sy * sz, sx * sz, sx * sy])
    k = sh.shape[1]
    sh_signs = np.prod(np.where(SH_ODD[:k - 1] == 1, np.asarray(signs, np.float64), 1.0), axis=1)
    sh = sh.copy()
    sh[:, 1:] *= sh_signs[None, :, None]
    return positions * np.asarray(signs, np.float64), rotations * q_signs, sh


def _smallest_three(v: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w) from SPZ's smallest-three uint32s: the 2 top bits
    name the largest component; the others follow from the highest index down, the last
    in the low bits, each a sign bit over 9 bits of magnitude in units of 1/(511 sqrt 2)."""
    largest = (v >> 30) & 3
    q = np.zeros((len(v), 4), np.float64)
    rows = np.arange(len(v))
    rest = v.copy()
    for i in range(3, -1, -1):
        here = largest != i
        magnitude = (rest & 511) / 511.0 / math.sqrt(2.0)
        value = np.where((rest >> 9) & 1, -magnitude, magnitude)
        q[here, i] = value[here]
        rest = np.where(here, rest >> 10, rest)
    q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(q * q, axis=1)))
    return q
