"""The prepared model on disk (``.dofsplat``, issue 50): surfels and their LOD tree in one
file, read through memory maps, so that a frame reads the pages of its cut and the page
cache does the caching (docs/outofcore.md).

    dofsplat prepare SCAN.laz -o SCAN.dofsplat      # once: surfels, tree, file
    dofsplat render SCAN.dofsplat -o out.png ...    # any number of times: milliseconds to open

The layout (little-endian; every array starts on a 4 KiB page):

    0     magic b"DOFSPLAT", format version (uint32), header length H (uint32)
    16    the header: H bytes of UTF-8 JSON (counts, material, fingerprints, bounds, source,
          and each array's name, dtype, shape and offset)
    ...   the arrays: the surfels' (positions, normals, radius, colors, opacity, and tangent,
          radius_v, weight where the model has them) in the tree's leaf order, the default
          camera's sample (``Surfels.sample``: the source's, 20,000 surfels at most), then
          the tree's (``lod.Hierarchy``: order, the identity, a row per stored node in the
          blocked layout of ``Hierarchy.blocked``, each row's first child's row, and
          ``lod.min_leaf_geo``, the pinhole walk's bound), in that order
    end   the trailer: b"DOFSPLAT-COMPLETE" padded to 24 bytes, then the header's BLAKE2b
          digest (8 bytes)

The surfels are stored in leaf order, so a subtree's surfels lie together on disk, and the
tree's rows in blocks of BLOCK_LEVELS levels, breadth first within a block, the blocks in
preorder (``Hierarchy.blocked``): a cut that stops a few levels into a block reads the
block's first rows, where rows in preorder put a cut's nodes on a page each. A file is trusted only when its size, its
trailer and the header's digest agree (a build writes the trailer last, into a temporary
file renamed at the end: an interrupted one leaves nothing a render reads); anything else is
one ``DofsplatError`` line ("not a complete dofsplat model file").

Not yet: the out-of-core build (the model is prepared in memory, then written), and the
quantised attributes of docs/outofcore.md's plan (this file holds float32 arrays:
``bytes_per_surfel`` says how many).
"""

from __future__ import annotations

import hashlib
import json
import mmap
import struct
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np

from ..errors import DofsplatError
from ..surfels import VIEW_SAMPLE, Material, Surfels

EXTENSION = ".dofsplat"
MAGIC = b"DOFSPLAT"
VERSION = 2  # 1: the tree's rows in preorder
BLOCK_LEVELS = 8  # the tree's rows in blocks of this many levels (Hierarchy.blocked)
PAGE = 4096
TRAILER_MARK = b"DOFSPLAT-COMPLETE".ljust(24, b"\0")
TRAILER = len(TRAILER_MARK) + 8  # the mark, then the header's digest
HINTS = ("up_hint", "shading_hint", "capture")  # what loaders tell render about a model (kept)
ROWS = 1 << 20  # an array is moved into the file's order and written this many rows at a time
SURFEL_ARRAYS = ("positions", "normals", "radius", "colors", "opacity", "tangent", "radius_v",
                 "weight")


def write_model_file(path, surfels: Surfels, tree, source: dict | None = None,
                     progress: bool = False, block_levels: int = BLOCK_LEVELS) -> Path:
    """Write ``surfels`` and their LOD ``tree`` (``lod.Hierarchy``, built for them) as a
    ``.dofsplat`` file, atomically; returns the path. source: what the model was prepared
    from (kept in the header). block_levels: the tree's blocks (0: its rows in preorder, for
    ``bench/model_file.py``'s comparison).

    Each array is moved into the file's order ROWS rows at a time as it is written, and the
    fingerprints are hashed from those pieces (``fingerprint.HashStream``): beside the model
    and its tree, the write holds the tree's row maps (16 bytes a stored row) and a piece."""
    from ..fingerprint import HashStream
    from ..io.images import atomic_write
    from ..lod import FORMAT_VERSION
    from ..lod.hierarchy import TREE_FIELDS, fingerprint, fingerprint_salt

    if tree.n_surfels != len(surfels) or tree.fingerprint != fingerprint(surfels, cached=True):
        raise DofsplatError("write_model_file: the LOD tree was not built for these surfels")
    if tree.block_levels and tree.block_levels != block_levels:
        raise ValueError(f"the tree is in blocks of {tree.block_levels} levels already")
    arrays = _file_arrays(surfels, tree, block_levels)
    # the bounds are the leaf-ordered model's (a box and a largest radius: any order's)
    lo, hi = surfels.bounds()
    view_lo, view_hi = surfels.view_bounds()
    unknown = "0" * 32  # the two hashes' length, until the arrays are written and hashed
    header = {
        "kind": "surfels",
        "count": len(surfels),
        "material": asdict(surfels.material),
        "tree": {"small": int(tree.small), "format": FORMAT_VERSION,
                 "block_levels": int(block_levels),
                 "fingerprint": unknown, "fields": list(TREE_FIELDS)},
        "content_hash": unknown,
        "bounds": [lo.tolist(), hi.tolist()],
        "view_bounds": [view_lo.tolist(), view_hi.tolist()],
        "source": source or {},
        "hints": {name: _plain(getattr(surfels, name)) for name in HINTS
                  if getattr(surfels, name, None) is not None},
        "arrays": [],
    }
    # offsets: the header's length is not known until the offsets are, so lay the arrays
    # out after a first guess and grow it until it fits
    first = PAGE
    while True:
        offset, listing = first, []
        for name, (dtype, shape, _) in arrays.items():
            listing.append({"name": name, "dtype": dtype.str, "shape": list(shape),
                            "offset": offset})
            offset = _page(offset + dtype.itemsize * int(np.prod(shape)))
        header["arrays"] = listing
        text = json.dumps(header, separators=(",", ":")).encode()
        if 16 + len(text) <= first:
            break
        first = _page(16 + len(text))
    end = offset

    def write(tmp):
        # the leaf-ordered model's own fingerprints (what a render checks the tree against:
        # those of the Surfels.stored that read_model_file makes), hashed field by field
        # from the pieces written, then the header that holds them, then the trailer
        tree_hash = HashStream(Surfels.__qualname__, fingerprint_salt())
        model_hash = HashStream(Surfels.__qualname__)
        offsets = {entry["name"]: entry["offset"] for entry in listing}
        bar = _bar(sum(dtype.itemsize * int(np.prod(shape))
                       for dtype, shape, _ in arrays.values()), progress)
        with open(tmp, "wb") as fh:

            def put(name, hashes=()):
                fh.seek(offsets[name])
                for piece in arrays[name][2]():
                    fh.write(np.ascontiguousarray(piece).reshape(-1).view(np.uint8))
                    for h in hashes:
                        h.update(piece)
                    bar.update(piece.nbytes)

            for field in (f.name for f in fields(Surfels)):  # content_hash's order
                name = f"surfels.{field}"
                hashes = (tree_hash, model_hash) if field in TREE_FIELDS else (model_hash,)
                if name in arrays:
                    for h in hashes:
                        h.array(field, *arrays[name][:2])
                    put(name, hashes)
                else:  # None, or the material
                    for h in hashes:
                        h.value(field, getattr(surfels, field))
            for name in arrays:
                if not name.startswith("surfels."):
                    put(name)
            bar.close()
            header["tree"]["fingerprint"] = tree_hash.hexdigest()
            header["content_hash"] = model_hash.hexdigest()
            final = json.dumps(header, separators=(",", ":")).encode()
            assert len(final) == len(text)  # (the placeholders had the hashes' length)
            fh.seek(0)
            fh.write(MAGIC + struct.pack("<II", VERSION, len(final)) + final)
            fh.seek(end)
            digest = hashlib.blake2b(final, digest_size=8).digest()
            fh.write(TRAILER_MARK + digest)  # last: the file is complete

    return atomic_write(path, write)


def _file_arrays(surfels: Surfels, tree, block_levels: int) -> dict:
    """Each array of the file, by name, in the file's order: (dtype, shape, pieces), pieces()
    yielding its rows in the file's order ROWS at a time (``_gathered``): the surfels in the
    tree's leaf order, the default camera's sample, the tree's identity order, its rows in
    blocks of ``block_levels`` levels (``Hierarchy.block_rows``; 0: preorder) with each one's
    first child's row, and the pinhole walk's bound per row (``lod.min_leaf_geo``)."""
    from ..lod import min_leaf_geo
    from ..lod.hierarchy import ATTRIBUTES

    order = np.asarray(tree.order)
    arrays = {}
    for name in SURFEL_ARRAYS:
        a = getattr(surfels, name)
        if a is not None:
            arrays[f"surfels.{name}"] = _gathered(a, order)
    # the default camera's sample (Surfels.sample), the source's own
    sample = surfels.sample(VIEW_SAMPLE)
    for name in SURFEL_ARRAYS:
        a = getattr(sample, name)
        if a is not None:
            arrays[f"sample.{name}"] = _gathered(a)
    arrays["tree.order"] = (order.dtype, order.shape, lambda: (  # the identity
        np.arange(i, min(i + ROWS, len(order)), dtype=order.dtype)
        for i in range(0, len(order), ROWS)))
    geo = min_leaf_geo(tree, surfels, tree.small)
    if block_levels and tree.block_levels == block_levels:  # a stored model's: as it is
        arrays.update({f"tree.{name}": _gathered(getattr(tree, name)) for name in ATTRIBUTES})
        arrays["tree.child"] = _gathered(tree.child)
        arrays["tree.min_geo"] = _gathered(geo)
    elif block_levels:
        file_row, child = tree.block_rows(block_levels)
        rows = np.empty_like(file_row)  # the preorder row at each row of the file
        rows[file_row] = np.arange(len(file_row))
        del file_row
        arrays.update({f"tree.{name}": _gathered(getattr(tree, name), rows)
                       for name in ATTRIBUTES})
        arrays["tree.child"] = _gathered(child)
        arrays["tree.min_geo"] = _gathered(geo[:len(rows)], rows)
    else:
        arrays.update({f"tree.{name}": _gathered(getattr(tree, name)) for name in ATTRIBUTES})
        arrays["tree.min_geo"] = _gathered(geo)
    return arrays


class StoredSurfels(Surfels):
    """Surfels whose arrays are memory maps of a ``.dofsplat`` file (``read_model_file``).
    Pickled as the file's path: a Dask worker (``animate --scheduler``) opens the file
    itself, at the same path (a shared disk), instead of receiving a copy of its arrays.
    But a file the cache keeps (``io.prepared.keep_stored``) lies in this machine's own
    cache folder, which another machine's worker does not have: such a model is pickled
    with its arrays and tree, as a model in memory is, and arrives as one."""

    def __reduce__(self):
        from .. import cache

        try:
            cached = Path(self.model_file).is_relative_to(cache.cache_root().resolve())
        except (OSError, ValueError):
            cached = False
        if cached:
            return _in_memory, ({k: v for k, v in self.__dict__.items() if k != "model_file"},)
        return read_model_file, (self.model_file, self.material)


def _in_memory(state: dict) -> Surfels:
    """A ``StoredSurfels`` of the cache, unpickled: Surfels with its arrays and tree."""
    surfels = Surfels.__new__(Surfels)
    surfels.__dict__.update(state)
    return surfels


def read_model_file(path, material: Material | None = None) -> Surfels:
    """The surfels of a ``.dofsplat`` file, their arrays memory maps of it (nothing is read
    until a frame needs it), with their LOD tree attached (``lod.hierarchy_for`` finds it),
    ``model_file`` the file's path. material: replaces the file's. Raises
    DofsplatError for a file that is not a complete dofsplat model file of this version."""
    from ..fingerprint import remember_hash
    from ..lod import FORMAT_VERSION, Hierarchy, min_leaf_geo_keep
    from ..lod.hierarchy import ATTRIBUTES, TREE_FIELDS, fingerprint_salt

    path = Path(path)
    header = read_header(path)
    maps = {}
    for entry in header["arrays"]:
        shape = tuple(entry["shape"])
        dtype = np.dtype(entry["dtype"])
        if int(np.prod(shape)) == 0:
            maps[entry["name"]] = np.zeros(shape, dtype)
        else:
            maps[entry["name"]] = np.memmap(path, dtype=dtype, mode="r",
                                            offset=entry["offset"], shape=shape)
    tree_info = header["tree"]
    if tree_info["format"] != FORMAT_VERSION:
        raise DofsplatError(f"{path}: a dofsplat model file of an older LOD format "
                            f"({tree_info['format']}, this version reads {FORMAT_VERSION}): "
                            "prepare it again (dofsplat prepare)")
    try:
        own = Material(**header["material"])
        if material == own:
            material = None  # (the file's: its content hash holds)
        surfels = StoredSurfels.stored(
            material=own if material is None else material,
            **{name: maps.get(f"surfels.{name}") for name in SURFEL_ARRAYS})
        tree = Hierarchy(fingerprint=tree_info["fingerprint"], small=int(tree_info["small"]),
                         order=maps["tree.order"], child=maps.get("tree.child"),
                         block_levels=int(tree_info["block_levels"]),
                         **{name: maps[f"tree.{name}"] for name in ATTRIBUTES})
    except (KeyError, TypeError) as exc:
        raise DofsplatError(f"{path}: not a complete dofsplat model file (missing {exc})") \
            from None
    tree.leaf_ordered = True  # order is the identity: lod.leaf_arrays reads the surfels as they are
    remember_hash(surfels, TREE_FIELDS, fingerprint_salt(), tree_info["fingerprint"])
    if material is None:
        remember_hash(surfels, None, "", header["content_hash"])
    for name, value in header.get("hints", {}).items():
        if name in HINTS:
            setattr(surfels, name, tuple(value) if name == "up_hint" else value)
    surfels.remember_bounds(header["bounds"], header["view_bounds"])
    sample = {name: maps.get(f"sample.{name}") for name in SURFEL_ARRAYS}
    surfels.remember_sample(VIEW_SAMPLE, Surfels.stored(material=surfels.material, **{
        name: None if a is None else np.array(a) for name, a in sample.items()}))
    # the pinhole walk's bound per row (lod.min_leaf_geo), computed from every leaf
    min_leaf_geo_keep(tree, surfels, maps["tree.min_geo"])
    surfels._lod_hierarchy = tree
    surfels.model_file = str(path.resolve())
    return surfels


def read_rows(a: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """The rows ``a[lo:hi]``. For a memory map of a model file (one of
    ``read_model_file``'s arrays) the rows are read through the file, not the map: a pass
    over every row (``framing.fit_camera``) then leaves none of the file's pages mapped
    in the process, counted in its RSS, and the page cache keeps or drops them."""
    if not (isinstance(a, np.memmap) and isinstance(a.base, mmap.mmap) and a.ndim
            and a.flags.c_contiguous and a.filename):
        return a[lo:hi]
    lo, hi = max(0, min(lo, len(a))), max(0, min(hi, len(a)))
    n = max(hi - lo, 0)
    row = a.itemsize * int(np.prod(a.shape[1:], dtype=np.int64))
    with open(a.filename, "rb") as f:
        f.seek(a.offset + lo * row)
        out = np.fromfile(f, dtype=a.dtype, count=n * (row // a.itemsize))
    if out.size != n * (row // a.itemsize):
        raise DofsplatError(f"{a.filename}: not a complete dofsplat model file (cut short)")
    return out.reshape((n,) + a.shape[1:])


def read_header(path: Path) -> dict:
    """The header of a ``.dofsplat`` file, after checking its magic, version, length,
    trailer and digest (module docstring); DofsplatError otherwise."""
    def broken(why):
        return DofsplatError(f"{path}: not a complete dofsplat model file ({why}); prepare "
                             "it again (dofsplat prepare)")

    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            start = fh.read(16)
            if len(start) < 16 or start[:8] != MAGIC:
                raise broken("no dofsplat header")
            version, length = struct.unpack("<II", start[8:])
            if version != VERSION:
                raise DofsplatError(f"{path}: a dofsplat model file of format {version}; this "
                                    f"version reads format {VERSION}: prepare it again")
            if 16 + length + TRAILER > size:
                raise broken("cut short")
            text = fh.read(length)
            fh.seek(size - TRAILER)
            trailer = fh.read(TRAILER)
    except OSError as exc:
        raise DofsplatError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if trailer[:len(TRAILER_MARK)] != TRAILER_MARK:
        raise broken("no completion mark: cut short, or an interrupted write")
    if trailer[len(TRAILER_MARK):] != hashlib.blake2b(text, digest_size=8).digest():
        raise broken("its header does not match its completion mark")
    try:
        header = json.loads(text)
        end = 0
        for entry in header["arrays"]:
            nbytes = int(np.prod(entry["shape"])) * np.dtype(entry["dtype"]).itemsize
            end = max(end, int(entry["offset"]) + nbytes)
    except (ValueError, KeyError, TypeError) as exc:
        raise broken(f"its header is damaged: {exc}") from None
    if end + TRAILER > size:
        raise broken("cut short")
    return header


def _plain(value):
    """value with numpy arrays and scalars as lists and numbers (for the JSON header)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    return value.item() if isinstance(value, np.generic) else value


def _page(offset: int) -> int:
    return -(-offset // PAGE) * PAGE


def _gathered(a: np.ndarray, index: np.ndarray | None = None):
    """(dtype, shape, pieces) of ``a[index]`` (``a`` where index is None): pieces() yields
    its rows in order, ROWS at a time, so that the whole is never in memory."""
    n = len(a) if index is None else len(index)

    def pieces():
        for i in range(0, n, ROWS):
            yield a[i:i + ROWS] if index is None else a[index[i:i + ROWS]]

    return a.dtype, (n,) + a.shape[1:], pieces


def _bar(total: int, progress: bool):
    from tqdm import tqdm

    return tqdm(total=total, unit="B", unit_scale=True, desc="writing", disable=not progress,
                leave=False)
