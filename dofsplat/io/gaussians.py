"""3D Gaussian Splatting scenes (Kerbl et al. 2023) in PLY files, read as ``Gaussians``.

Two PLY layouts hold a 3DGS scene; :func:`dofsplat.io.ply.read_ply` tells them apart by
the header (:func:`dofsplat.io.ply.ply_kind`) and hands the elements to
:func:`gaussians_from_columns` or :func:`decode_compressed_ply`.

**The trainers' PLY** (``point_cloud.ply``; recognised by f_dc_0, scale_0 and rot_0) has one
vertex per Gaussian with

* ``x y z``: the centre;
* ``f_dc_0..2``: the degree-0 spherical-harmonic coefficients of the colour;
* ``f_rest_*``, optional: 9, 24 or 45 higher coefficients (SH degree 1, 2, 3), stored
  channel-major: f_rest_0..K-2 are red's coefficients 1..K-1, then green's, then blue's;
* ``opacity``: a logit (the opacity is its sigmoid);
* ``scale_0..2``: the logarithms of the standard deviations along the Gaussian's axes;
* ``rot_0..3``: a quaternion (w, x, y, z), not normalised, rotating the axes into the world;
* ``nx ny nz`` (zeros in 3DGS output) are skipped; any other property is ignored with a
  one-line warning that names it.

**PlayCanvas's compressed PLY** (SuperSplat's ``*.compressed.ply``; recognised by a
``chunk`` element and ``packed_position`` in the vertex element): the Gaussians in chunks
of 256, each chunk with the min/max of its positions, log-scales and (optionally) colours;
per vertex four uint32s, each field a fraction of its chunk's range:

* ``packed_position``, ``packed_scale``: x 11 bits, y 10, z 11 (high to low bits);
* ``packed_rotation``: 2 bits naming the largest of (w, x, y, z) by index, then the other
  three in that order, 10 bits each, mapping [-1/sqrt 2, 1/sqrt 2]; the largest is
  sqrt(1 - the others' squares), positive;
* ``packed_color``: r g b opacity, 8 bits each (high to low): the colour is
  0.5 + C0 f_dc (the SH degree-0 colour, so f_dc = (c - 0.5) / C0), the opacity the
  sigmoid itself;
* an optional ``sh`` element of uchar ``f_rest_*`` (channel-major as above), each byte b
  the value 8 (b + 0.5) / 256 - 4 (0 and 255 stand for -4 and 4).

Decoding follows PlayCanvas splat-transform's reader (``decompress-ply.ts``).

Rows with NaN or inf, a scale that is absurd (|log| >= 60) or a zero quaternion are dropped
with one warning (:meth:`Gaussians.from_arrays`). :func:`write_gaussian_ply` writes the
trainers' layout back, and a read/write/read round trip gives the same float32 arrays.

:func:`gaussians_to_surfels` flattens Gaussians into elliptical surfels (the renderer's way
before it drew Gaussians): its two largest axes span the disk, the smallest is the normal, a
standard deviation s is a radius of 2s (a surfel's disk radius r is a Gaussian sigma of
r/2), the colour is the degree-0 term taken as sRGB. What that loses: the third axis, the
view-dependent colour and 3DGS's front-to-back blending of every Gaussian.
"""

from __future__ import annotations

import gzip
import math
import warnings
from pathlib import Path

import numpy as np

from ..colors import srgb_to_linear
from ..errors import DofsplatError
from ..gaussians import Gaussians, quaternion_matrices  # noqa: F401 - (re-exported)
from ..surfels import Material, Surfels
from .images import atomic_write

SH_C0 = 0.28209479177387814  # the degree-0 real spherical harmonic, 1 / (2 sqrt(pi))
REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
            "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
NORMAL = ("nx", "ny", "nz")  # written by 3DGS trainers, always zero: skipped without a word
REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # f_rest_* values per Gaussian -> SH degree
MIN_OPACITY = 1.0 / 255.0  # below this a Gaussian cannot change an 8-bit pixel
MIN_AXIS_RATIO = 1e-3  # the shorter disk axis is kept at least this fraction of the longer
_MAX_LOG_SCALE = 60.0  # exp(60) ~ 1e26: beyond this a scale is damage, not a Gaussian
_MAX_LOGIT = 1e4  # the logit written for opacity 0 or 1: its sigmoid is 0 or 1 in float64

CHUNK_SIZE = 256  # Gaussians per chunk of a compressed PLY
PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
CHUNK_RANGES = ("x", "y", "z", "scale_x", "scale_y", "scale_z")  # each as min_* and max_*
CHUNK_COLOURS = ("r", "g", "b")  # optional, as min_* and max_*


# ---------------------------------------------------------------------------------------
# Reading


def is_compressed_ply(header) -> bool:
    """Whether a PLY header is PlayCanvas's compressed layout (a chunk element and packed
    vertex attributes)."""
    vertex = header.element("vertex")
    return (header.element("chunk") is not None and vertex is not None
            and "packed_position" in vertex.names)


def gaussians_from_columns(columns: dict[str, np.ndarray], source: str = "3DGS") -> Gaussians:
    """Gaussians from the vertex columns of a trainers' 3DGS PLY (module docstring).

    columns: property name -> (N,) array. DofsplatError if a required property is missing,
    the f_rest_* count is not 0, 9, 24 or 45, or no valid row is left.
    """
    missing = [n for n in REQUIRED if n not in columns]
    if missing:
        raise DofsplatError(f"{source}: a 3D Gaussian Splatting PLY needs {' '.join(REQUIRED)}; "
                            f"this one lacks {' '.join(missing)}")
    rest = _rest_names(columns, source)
    ignored = sorted(set(columns) - set(REQUIRED) - set(NORMAL) - set(rest))
    if ignored:
        warnings.warn(f"{source}: ignored vertex properties {' '.join(ignored)} (not part of "
                      "a 3D Gaussian Splatting scene)", stacklevel=3)
    n = len(columns["x"])
    if n == 0:
        raise DofsplatError(f"{source}: no Gaussians in the file")
    col = lambda name: np.asarray(columns[name], np.float64)  # noqa: E731
    stack = lambda names: np.stack([col(c) for c in names], axis=1)  # noqa: E731
    k = 1 + len(rest) // 3  # coefficients per channel
    sh = np.empty((n, k, 3), np.float64)
    sh[:, 0] = stack(("f_dc_0", "f_dc_1", "f_dc_2"))
    for c in range(3):  # channel-major: red's k - 1 coefficients, then green's, then blue's
        if k > 1:
            sh[:, 1:, c] = stack(rest[c * (k - 1):(c + 1) * (k - 1)])
    return _gaussians(stack(("x", "y", "z")), log_scales=stack(("scale_0", "scale_1", "scale_2")),
                      rotations=stack(("rot_0", "rot_1", "rot_2", "rot_3")),
                      opacity=sigmoid(col("opacity")), sh=sh, source=source)


def _rest_names(columns, source: str) -> list[str]:
    """f_rest_0 .. f_rest_{M-1} in order; DofsplatError unless M is 0, 9, 24 or 45 and the
    names are those."""
    found = [n for n in columns if n.startswith("f_rest_")]
    names = [f"f_rest_{i}" for i in range(len(found))]
    if set(found) != set(names) or len(found) not in REST_COUNTS:
        raise DofsplatError(f"{source}: {len(found)} f_rest_* properties; a 3DGS PLY has "
                            "f_rest_0 to f_rest_8, _23 or _44 (SH degree 1, 2 or 3) or none")
    return names


def decode_compressed_ply(elements: dict[str, dict[str, np.ndarray]],
                          source: str = "compressed PLY") -> Gaussians:
    """Gaussians from the elements of a PlayCanvas compressed PLY (module docstring).

    elements: element name -> property name -> (rows,) array, with ``chunk``, ``vertex``
    and optionally ``sh``. DofsplatError when a property is missing or of the wrong type,
    or the chunk count does not fit the vertex count.
    """
    vertex, chunk = elements["vertex"], elements.get("chunk", {})
    need = [f"{m}_{a}" for a in CHUNK_RANGES for m in ("min", "max")]
    missing = [p for p in PACKED if p not in vertex] + [p for p in need if p not in chunk]
    if missing:
        raise DofsplatError(f"{source}: a compressed PLY needs vertex {' '.join(PACKED)} and "
                            f"chunk min/max_x/y/z/scale_x/y/z; this one lacks {' '.join(missing)}")
    colours = [f"{m}_{a}" for a in CHUNK_COLOURS for m in ("min", "max")]
    has_colours = [p in chunk for p in colours]
    if any(has_colours) and not all(has_colours):
        raise DofsplatError(f"{source}: the chunk element has some of "
                            f"{' '.join(colours)} but not all")
    if any(not np.issubdtype(np.asarray(vertex[p]).dtype, np.integer) for p in PACKED):
        raise DofsplatError(f"{source}: the packed vertex properties must be uint (32-bit)")
    n = len(vertex["packed_position"])
    if n == 0:
        raise DofsplatError(f"{source}: no Gaussians in the file")
    if len(chunk["min_x"]) != -(-n // CHUNK_SIZE):
        raise DofsplatError(f"{source}: {len(chunk['min_x']):,} chunks for {n:,} Gaussians; a "
                            f"compressed PLY has one chunk per {CHUNK_SIZE}")
    packed = {p: np.asarray(vertex[p]).astype(np.int64) & 0xFFFFFFFF for p in PACKED}
    in_chunk = np.arange(n) // CHUNK_SIZE

    def lerp(name: str, t: np.ndarray) -> np.ndarray:
        lo = np.asarray(chunk[f"min_{name}"], np.float64)[in_chunk]
        hi = np.asarray(chunk[f"max_{name}"], np.float64)[in_chunk]
        with np.errstate(invalid="ignore", over="ignore"):
            return lo * (1.0 - t) + hi * t  # as splat-transform computes it

    position = _unpack_11_10_11(packed["packed_position"])
    scale = _unpack_11_10_11(packed["packed_scale"])
    rgba = np.stack([_unorm(packed["packed_color"] >> s, 8) for s in (24, 16, 8, 0)], axis=1)
    if all(has_colours):
        rgb = np.stack([lerp(a, rgba[:, i]) for i, a in enumerate(CHUNK_COLOURS)], axis=1)
    else:
        rgb = rgba[:, :3]
    sh = ((rgb - 0.5) / SH_C0)[:, None, :]
    if "sh" in elements:
        sh = np.concatenate([sh, _compressed_rest(elements["sh"], n, source)], axis=1)
    return _gaussians(np.stack([lerp(a, position[:, i]) for i, a in enumerate("xyz")], axis=1),
                      log_scales=np.stack([lerp(f"scale_{a}", scale[:, i])
                                           for i, a in enumerate("xyz")], axis=1),
                      rotations=_unpack_rotation(packed["packed_rotation"]),
                      opacity=rgba[:, 3], sh=sh, source=source)


def _unorm(v: np.ndarray, bits: int) -> np.ndarray:
    """The low ``bits`` bits of v as a fraction in [0, 1]."""
    top = (1 << bits) - 1
    return (v & top) / top


def _unpack_11_10_11(v: np.ndarray) -> np.ndarray:
    """(N, 3) fractions from x (11 bits), y (10 bits), z (11 bits), high to low."""
    return np.stack([_unorm(v >> 21, 11), _unorm(v >> 11, 10), _unorm(v, 11)], axis=1)


def _unpack_rotation(v: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z) from the compressed PLY's smallest-three packing."""
    abc = np.stack([(_unorm(v >> s, 10) - 0.5) * math.sqrt(2.0) for s in (20, 10, 0)], axis=1)
    largest = np.sqrt(np.maximum(0.0, 1.0 - np.sum(abc * abc, axis=1)))
    which = (v >> 30) & 3  # the index (in w, x, y, z) of the component left out
    q = np.empty((len(v), 4), np.float64)
    rows = np.arange(len(v))
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[which]
    q[rows, which] = largest
    for i in range(3):
        q[rows, others[:, i]] = abc[:, i]
    return q


def _compressed_rest(sh: dict[str, np.ndarray], n: int, source: str) -> np.ndarray:
    """(N, K - 1, 3) SH coefficients 1.. from the compressed PLY's uchar sh element."""
    names = _rest_names(sh, source)
    if not names or len(sh[names[0]]) != n:
        raise DofsplatError(f"{source}: the sh element must have {n:,} rows of f_rest_0 to "
                            "f_rest_8, _23 or _44")
    b = np.stack([np.asarray(sh[name], np.float64) for name in names], axis=1)
    unit = np.where(b <= 0, 0.0, np.where(b >= 255, 1.0, (b + 0.5) / 256.0))
    values = (unit - 0.5) * 8.0
    k1 = len(names) // 3
    return values.reshape(n, 3, k1).transpose(0, 2, 1)  # channel-major to (N, K - 1, 3)


def _gaussians(positions, *, log_scales, rotations, opacity, sh, source) -> Gaussians:
    """Gaussians.from_arrays from float64 arrays, with log-scales made standard deviations
    (an absurd one, |log| >= 60, becomes NaN: damage, dropped there)."""
    with np.errstate(invalid="ignore", over="ignore"):
        sane = np.abs(log_scales) < _MAX_LOG_SCALE
        scales = np.where(sane, np.exp(np.where(sane, log_scales, 0.0)), np.nan)
        arrays = [_float32(a) for a in (positions, scales, rotations, opacity, sh)]
    return Gaussians.from_arrays(*arrays, source=source)


def _float32(a) -> np.ndarray:
    """a as float32; values beyond float32's range become inf (and their rows dropped)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return np.asarray(a, np.float64).astype(np.float32)


def sigmoid(x) -> np.ndarray:
    """The logistic function in float64, exactly 0 or 1 far out (no overflow warning)."""
    x = np.asarray(x, np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        return 1.0 / (1.0 + np.exp(-x))


# ---------------------------------------------------------------------------------------
# Writing


def write_gaussian_ply(path, gaussians: Gaussians) -> Path:
    """Write Gaussians as a trainers' 3DGS PLY (binary little endian, all float32): x y z,
    nx ny nz (zeros), f_dc_0..2, f_rest_* (channel-major), opacity (a logit), scale_0..2
    (logarithms), rot_0..3 (w, x, y, z), as 3DGS trainers write them; a name ending in
    ``.gz`` is gzip-compressed. Reading the file gives back the same float32 arrays: each
    logit and logarithm is the float32 whose sigmoid or exponential is the stored value.
    The write is atomic. Returns the path."""
    path = Path(path)
    g = gaussians
    n, k = len(g), g.sh.shape[1]
    rest = g.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1))  # channel-major
    columns = [g.positions, np.zeros((n, 3), np.float32), g.sh[:, 0, :], rest,
               _exact_inverse(g.opacity[:, None], sigmoid, _logit),
               _exact_inverse(g.scales, np.exp, np.log), g.rotations]
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(3 * (k - 1))]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    body = np.concatenate(columns, axis=1).astype("<f4")
    head = ("ply\nformat binary_little_endian 1.0\n"
            "comment dofsplat: 3D Gaussian Splatting scene\n"
            f"element vertex {n}\n" + "".join(f"property float {p}\n" for p in names)
            + "end_header\n").encode("ascii")

    def write(tmp):
        if path.name.lower().endswith(".gz"):
            # mtime=0: the same Gaussians give the same bytes
            with open(tmp, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as gz:
                gz.write(head)
                gz.write(body.tobytes())
        else:
            with open(tmp, "wb") as f:
                f.write(head)
                f.write(body.tobytes())

    return atomic_write(path, write)


def _logit(p: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.clip(np.log(p) - np.log1p(-p), -_MAX_LOGIT, _MAX_LOGIT)


def _exact_inverse(values: np.ndarray, forward, inverse, steps: int = 4) -> np.ndarray:
    """float32 x with float32(forward(float64(x))) == values, as the reader computes them.

    inverse(values) rounded to float32 can miss by a step or two where forward compresses
    (exp of a log-scale near -5: 1 ulp of the log is 8 ulps of the scale), so the float32
    neighbours within ``steps`` are tried too, and the one that maps closest is kept. Values
    that a file's float32 gave map back exactly; others (an opacity of k / 255 from a
    quantised format) to within a float32 step or two."""
    target = np.asarray(values, np.float32)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        error = lambda x: np.abs(  # noqa: E731
            forward(x.astype(np.float64)).astype(np.float32).astype(np.float64) - target)
        best = _float32(inverse(target.astype(np.float64)))
        best_error = error(best)
        lo = hi = best
        for _ in range(steps):
            lo = np.nextafter(lo, np.float32(-np.inf))
            hi = np.nextafter(hi, np.float32(np.inf))
            for x in (lo, hi):
                e = error(x)
                better = e < best_error
                best[better], best_error[better] = x[better], e[better]
    return best


# ---------------------------------------------------------------------------------------
# Flattening into surfels (the renderer's way before it drew Gaussians)


def gaussians_to_surfels(gaussians: Gaussians | dict, *, material: Material | None = None,
                         source: str = "3DGS") -> Surfels:
    """Elliptical surfels from Gaussians (see the module docstring), one per Gaussian of
    opacity 1/255 or more.

    gaussians: a :class:`Gaussians`, or the vertex columns of a 3DGS PLY (property name ->
    (N,) array, read by :func:`gaussians_from_columns`). DofsplatError when every Gaussian
    is below 1/255 opacity.
    """
    g = gaussians if isinstance(gaussians, Gaussians) else gaussians_from_columns(gaussians,
                                                                                   source)
    visible = g.opacity >= MIN_OPACITY
    if not visible.any():
        raise DofsplatError(f"{source}: every Gaussian has opacity below {MIN_OPACITY:.4f} "
                            "(nothing to render)")
    g = g.subset(visible)
    rotation = g.rotation_matrices()
    sigma = g.scales.astype(np.float64)
    # axes sorted by their standard deviation: smallest (the normal), middle, largest
    order = np.argsort(sigma, axis=1)
    rows = np.arange(len(g))
    axis = lambda i: rotation[rows, :, order[:, i]]  # noqa: E731 - the rotation's columns
    radius = 2.0 * sigma[rows, order[:, 2]]
    radius_v = np.maximum(2.0 * sigma[rows, order[:, 1]], MIN_AXIS_RATIO * radius)
    colors = srgb_to_linear(np.clip(0.5 + SH_C0 * g.sh[:, 0, :].astype(np.float64), 0.0, 1.0))
    return Surfels.from_arrays(g.positions, axis(0), radius, colors, g.opacity,
                               tangent=axis(2), radius_v=radius_v, material=material,
                               source=source)
