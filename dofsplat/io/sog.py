"""PlayCanvas SOG scenes (version 2): 3D Gaussian Splatting in WebP images, read as Gaussians.

A SOG scene is a ``meta.json`` and lossless WebP images, as a folder or zipped into one
``.sog`` file. Gaussian i is pixel i of every image (row-major, RGBA); meta.json gives the
count, the ranges and the codebooks (PlayCanvas splat-transform's ``read-sog.ts`` and
``write-sog.ts`` are the reference):

* ``means``: means_l and means_u, the low and high bytes of 16-bit x y z fractions v of
  [mins, maxs] of log-transformed positions: p = sign(u) (e^|u| - 1), u = min + v (max - min);
* ``quats``: the largest component's index in (w, x, y, z) as 252 + index in alpha, the other
  three in order in r g b, each b mapping (b / 255 * 2 - 1) / sqrt 2; the largest is
  sqrt(1 - the others' squares), positive;
* ``scales``: r g b index a codebook of 256 log standard deviations;
* ``sh0``: r g b index a codebook of 256 SH degree-0 coefficients (f_dc), alpha is the
  opacity times 255;
* ``shN``, optional (SH degree 1 to 3, ``bands``): shN_labels' r + 256 g is an index into a
  palette of ``count`` entries, shN_centroids, 64 entries a row, each entry (K - 1) pixels
  whose r g b index a codebook of 256 coefficients.

A LOD chain (``lod-meta.json``, splat-transform's streamed output) names SOG files in
``filenames`` and, in a tree of nodes, which rows of which file make each level
(``lods``: {level: {file, offset, count}}). :func:`read_sog` loads one level, 0 (the full
one) by default, as the concatenation of its nodes' rows in tree order. An
``environment`` scene that the chain names is not read (a warning says so). SOG version 1
(a meta.json without "version", per-channel ranges) is refused.

Pillow decodes the WebP images (its wheels carry libwebp).
"""

from __future__ import annotations

import io
import json
import math
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import DofsplatError
from ..gaussians import Gaussians
from .gaussians import _float32

META = "meta.json"
LOD_META = "lod-meta.json"
SH_REST = {0: 0, 1: 3, 2: 8, 3: 15}  # SH bands -> coefficients per channel besides the DC
PALETTE_ROW = 64  # shN palette entries per row of shN_centroids
_MAX_META_BYTES = 64 << 20  # a meta.json is kilobytes; more is not one


def read_sog(path, *, level: int = 0) -> Gaussians:
    """Load a SOG scene: a folder holding ``lod-meta.json`` or ``meta.json`` (a LOD chain
    first), either file itself, or a zipped ``.sog``.

    level: for a LOD chain, which level (0: the full scene, the default; 1 has about half
    as many Gaussians, ...; -1 the coarsest); a single scene has only level 0.
    DofsplatError naming the file for anything missing or damaged.
    """
    path = Path(path)
    if path.is_dir():
        found = [path / name for name in (LOD_META, META) if (path / name).is_file()]
        if not found:
            raise DofsplatError(f"{path}: a folder is read as a SOG scene, but it holds no "
                                f"{LOD_META} or {META}")
        path = found[0]
    if path.name.lower().endswith(LOD_META):
        return _read_lod_chain(path, level)
    _check_level(level, 1, path)
    if path.suffix.lower() == ".sog":
        return _read_zipped(path)
    return decode_sog(_read_json(path), _folder_files(path.parent), str(path))


def _check_level(level, levels: int, source) -> int:
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)) \
            or not -levels <= level < levels:
        raise DofsplatError(f"{source}: level must be a whole number from 0 to {levels - 1} "
                            f"(or -1 for the coarsest), got {level!r}")
    return int(level) % levels


def _read_json(path: Path) -> dict:
    try:
        if path.stat().st_size > _MAX_META_BYTES:
            raise DofsplatError(f"{path}: {path.stat().st_size:,} bytes is too large for a "
                                "SOG meta file")
        meta = json.loads(path.read_bytes())
    except OSError as e:
        raise DofsplatError(f"{path}: cannot read: {e.strerror or e}") from e
    except (ValueError, RecursionError) as e:  # JSONDecodeError, UnicodeDecodeError
        raise DofsplatError(f"{path}: not a SOG meta file: bad JSON ({_one_line(e)})") from e
    if not isinstance(meta, dict):
        raise DofsplatError(f"{path}: not a SOG meta file: the JSON is not an object")
    return meta


def _folder_files(folder: Path) -> Callable[[str], bytes]:
    def read(name: str) -> bytes:
        try:
            return (folder / name).read_bytes()
        except OSError as e:
            raise DofsplatError(f"{folder / name}: cannot read: {e.strerror or e}") from e
    return read


def _read_zipped(path: Path) -> Gaussians:
    """A ``.sog``: meta.json and the images in a zip archive."""
    try:
        with zipfile.ZipFile(path) as archive:
            def read(name: str) -> bytes:
                try:
                    return archive.read(name)
                except KeyError:
                    raise DofsplatError(f"{path}: the archive has no {name}") from None
            try:
                meta = json.loads(read(META))
            except (ValueError, RecursionError) as e:
                raise DofsplatError(f"{path}: its meta.json is not JSON ({_one_line(e)})") from e
            if not isinstance(meta, dict):
                raise DofsplatError(f"{path}: its meta.json is not a JSON object")
            return decode_sog(meta, read, str(path))
    except DofsplatError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, ValueError,
            NotImplementedError, RuntimeError, zlib.error) as e:
        raise DofsplatError(f"{path}: corrupt .sog (zip) file: {_one_line(e)}") from e


def _read_lod_chain(path: Path, level: int) -> Gaussians:
    """Level ``level`` of a lod-meta.json chain: its nodes' rows, in tree order."""
    meta = _read_json(path)
    levels, names, tree = meta.get("lodLevels"), meta.get("filenames"), meta.get("tree")
    if not (isinstance(levels, int) and levels > 0 and isinstance(names, list)
            and all(isinstance(n, str) for n in names) and isinstance(tree, dict)):
        raise DofsplatError(f"{path}: not a SOG LOD chain: lod-meta.json needs lodLevels (a "
                            "positive whole number), filenames (names) and tree (an object)")
    level = _check_level(level, levels, path)
    if meta.get("environment"):
        warnings.warn(f"{path}: the environment scene {meta['environment']!r} is not read",
                      stacklevel=3)
    parts = []  # (file index, offset, count) in tree order
    stack = [tree]
    while stack:
        node = stack.pop()
        if not isinstance(node, dict):
            raise DofsplatError(f"{path}: corrupt lod-meta.json: a tree node is not an object")
        ref = (node.get("lods") or {}).get(str(level)) if isinstance(node.get("lods"),
                                                                      dict) else None
        if ref is not None:
            values = [ref.get(k) if isinstance(ref, dict) else None
                      for k in ("file", "offset", "count")]
            if not all(isinstance(v, int) and v >= 0 for v in values) or values[0] >= len(names):
                raise DofsplatError(f"{path}: corrupt lod-meta.json: a level {level} "
                                    f"reference {ref!r} is not a file index, offset and count")
            parts.append(tuple(values))
        children = node.get("children") or []
        if not isinstance(children, list):
            raise DofsplatError(f"{path}: corrupt lod-meta.json: children is not a list")
        stack.extend(reversed(children))
    parts = [p for p in parts if p[2] > 0]
    if not parts:
        raise DofsplatError(f"{path}: level {level} of the LOD chain has no Gaussians")
    scenes: dict[int, Gaussians] = {}
    pieces = []
    for file, offset, count in parts:
        if file not in scenes:
            unit = path.parent / names[file]
            if unit.name.lower().endswith(LOD_META) or unit.resolve() == path.resolve():
                raise DofsplatError(f"{path}: a LOD chain names another chain ({unit.name})")
            if not unit.exists():
                raise DofsplatError(f"{unit}: no such file (named by the LOD chain {path})")
            scenes[file] = read_sog(unit)
        scene = scenes[file]
        if offset + count > len(scene):
            raise DofsplatError(f"{path}: level {level} asks for rows {offset:,} to "
                                f"{offset + count:,} of {names[file]}, which has {len(scene):,}")
        pieces.append(scene.subset(slice(offset, offset + count)))
    if len(pieces) == 1:
        return pieces[0]
    return Gaussians(*(np.concatenate([getattr(p, f) for p in pieces])
                       for f in ("positions", "scales", "rotations", "opacity", "sh")))


def decode_sog(meta: dict, read: Callable[[str], bytes], source: str = "SOG") -> Gaussians:
    """Gaussians from a SOG version 2 meta.json (a dict) and ``read(name) -> bytes`` for
    the images it names (module docstring)."""
    if "version" not in meta:
        raise DofsplatError(f"{source}: SOG version 1 (a meta.json without 'version') is not "
                            "supported; convert it with PlayCanvas splat-transform")
    if meta["version"] != 2:
        raise DofsplatError(f"{source}: SOG version {meta['version']!r} is not supported (2 is)")
    n = meta.get("count")
    if not isinstance(n, int) or n <= 0:
        raise DofsplatError(f"{source}: bad SOG meta.json: count must be a positive whole "
                            f"number, got {n!r}")
    field = _Fields(meta, source)
    mins, maxs = field.numbers("means", "mins", 3), field.numbers("means", "maxs", 3)
    images = lambda part, count: [_image(read, name, n, source)  # noqa: E731
                                  for name in field.files(part, count)]

    # positions: 16-bit fractions of the log-transformed range
    low, high = images("means", 2)
    v = (low[:, :3].astype(np.int64) | (high[:, :3].astype(np.int64) << 8)) / 65535.0
    span = np.where(maxs - mins == 0, 1.0, maxs - mins)
    u = mins + span * v
    with np.errstate(over="ignore"):
        positions = np.sign(u) * np.expm1(np.abs(u))

    (quats,) = images("quats", 1)
    rotations = _smallest_three(quats)
    (scale_index,) = images("scales", 1)
    with np.errstate(over="ignore"):
        scales = np.exp(field.codebook("scales")[scale_index[:, :3]])
    (sh0,) = images("sh0", 1)
    sh = field.codebook("sh0")[sh0[:, :3]][:, None, :]
    opacity = sh0[:, 3] / 255.0

    if meta.get("shN") is not None:
        bands = field.get("shN", "bands")
        if bands not in (1, 2, 3):
            raise DofsplatError(f"{source}: bad SOG meta.json: shN.bands must be 1, 2 or 3, "
                                f"got {bands!r}")
        sh = np.concatenate([sh, _palette_sh(field, read, n, SH_REST[bands], source)], axis=1)
    return Gaussians.from_arrays(_float32(positions), _float32(scales), _float32(rotations),
                                 _float32(opacity), _float32(sh), source=source)


def _palette_sh(field: "_Fields", read, n: int, k1: int, source: str) -> np.ndarray:
    """(N, k1, 3) SH coefficients 1.. from the shN palette."""
    codebook = field.codebook("shN")
    size = field.get("shN", "count")
    if not isinstance(size, int) or size < 0:
        raise DofsplatError(f"{source}: bad SOG meta.json: shN.count must be a whole number")
    centroids_name, labels_name = field.files("shN", 2)
    centroids, width = _image(read, centroids_name, 0, source, shape=True)
    if width != PALETTE_ROW * k1:
        raise DofsplatError(f"{source}: {centroids_name} is {width} pixels wide; "
                            f"{PALETTE_ROW} entries of {k1} coefficients need "
                            f"{PALETTE_ROW * k1}")
    labels = _image(read, labels_name, n, source)
    label = labels[:, 0].astype(np.int64) | (labels[:, 1].astype(np.int64) << 8)
    # entry e's coefficients are pixels e k1 .. e k1 + k1 - 1 (rows of 64 entries)
    entries = min(size, len(centroids) // k1)
    palette = codebook[centroids[:entries * k1, :3]].reshape(entries, k1, 3).astype(np.float32)
    valid = label < entries
    coeffs = palette[np.where(valid, label, 0)] if entries else np.zeros((n, k1, 3), np.float32)
    coeffs[~valid] = 0.0  # a label past the palette: no view-dependent colour
    return coeffs


class _Fields:
    """Checked access to a SOG meta.json's fields: a DofsplatError naming the field."""

    def __init__(self, meta: dict, source: str):
        self.meta, self.source = meta, source

    def get(self, part: str, key: str):
        section = self.meta.get(part)
        if not isinstance(section, dict) or key not in section:
            raise DofsplatError(f"{self.source}: bad SOG meta.json: no {part}.{key}")
        return section[key]

    def numbers(self, part: str, key: str, count: int | None = None) -> np.ndarray:
        value = self.get(part, key)
        ok = isinstance(value, list) and all(isinstance(v, (int, float))
                                             and not isinstance(v, bool) for v in value)
        if not ok or (count is not None and len(value) != count):
            what = f"{count} numbers" if count else "a list of numbers"
            raise DofsplatError(f"{self.source}: bad SOG meta.json: {part}.{key} must be {what}")
        return np.array(value, np.float64)

    def codebook(self, part: str) -> np.ndarray:
        """A 256-entry codebook (shorter ones are padded with NaN: an index past the end
        is damage, and its row is dropped)."""
        book = self.numbers(part, "codebook")
        if not 0 < len(book) <= 256:
            raise DofsplatError(f"{self.source}: bad SOG meta.json: {part}.codebook has "
                                f"{len(book)} entries; 1 to 256 fit a byte")
        return np.concatenate([book, np.full(256 - len(book), np.nan)])

    def files(self, part: str, count: int) -> list[str]:
        names = self.get(part, "files")
        if not (isinstance(names, list) and len(names) >= count
                and all(isinstance(s, str) for s in names[:count])):
            raise DofsplatError(f"{self.source}: bad SOG meta.json: {part}.files must name "
                                f"{count} image(s)")
        return names[:count]


def _image(read, name: str, n: int, source: str, shape: bool = False):
    """The RGBA pixels of a WebP image (or any Pillow reads), row-major: (n, 4) uint8
    (all of them when n is 0); with shape=True also the width."""
    from PIL import Image, UnidentifiedImageError, features

    if not features.check("webp"):
        raise DofsplatError(f"{source}: this Pillow was built without WebP, which SOG needs")
    data = read(name)
    try:
        with Image.open(io.BytesIO(data)) as image:
            image.load()
            width = image.width
            pixels = np.asarray(image.convert("RGBA")).reshape(-1, 4)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, EOFError) as e:
        raise DofsplatError(f"{source}: {name} is not a readable image ({_one_line(e)})") from e
    except Image.DecompressionBombError as e:
        raise DofsplatError(f"{source}: {name}: {_one_line(e)}") from e
    if len(pixels) < n:
        raise DofsplatError(f"{source}: {name} has {len(pixels):,} pixels for {n:,} Gaussians")
    pixels = pixels[:n] if n else pixels
    return (pixels, width) if shape else pixels


def _smallest_three(rgba: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z) from the quats image (module docstring); a tag that
    is not 252 to 255 gives the identity, as splat-transform reads it."""
    abc = (rgba[:, :3] / 255.0 * 2.0 - 1.0) / math.sqrt(2.0)
    tag = rgba[:, 3].astype(np.int64)
    valid = (tag >= 252) & (tag <= 255)
    which = np.where(valid, tag - 252, 0)
    q = np.empty((len(rgba), 4), np.float64)
    rows = np.arange(len(rgba))
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[which]
    for i in range(3):
        q[rows, others[:, i]] = abc[:, i]
    q[rows, which] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(abc * abc, axis=1)))
    q[~valid] = (1.0, 0.0, 0.0, 0.0)
    return q


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or "no details"
    return f"{type(e).__name__}: {text}"
