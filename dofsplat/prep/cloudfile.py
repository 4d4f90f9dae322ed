"""A point cloud on disk, in chunks (issue 50): the preparation of a cloud larger than memory.

``chunks.chunked_surfels`` prepares a large cloud chunk by chunk, each with a halo of its
neighbours, but it held the cloud's own arrays in memory: the points read, their colours,
the surfels written and the radii before the cap, about 100 bytes a point. Here the cloud
lies in files instead, in the order of its chunks, and so do those arrays
(``cloud_to_surfels``): memory holds one chunk and its halo, and the kernel's page cache
holds what it can of the rest.

The cloud's file is written in three passes over the input (``write_cloud``), the shape of
PotreeConverter 2.0's counting and distribution:

1. **count**: each point's cell in a grid over the cloud's box (at most ``GRID_CELLS``
   cells, cubes), the points counted per cell;
2. **plan**: the grid's cells cut into chunks of at most ``chunk_points`` points by splits
   along the longest axis of each part at the cell plane nearest its median (``plan``; a
   part that one cell holds whole, or whose every split would leave a side under
   ``MIN_SHARE`` of it, stays one chunk);
3. **distribute**: each point written to its chunk's run of the file (the chunks' counts
   give their offsets), in the input's order within the chunk; then each chunk's exact
   duplicates merged (``duplicates.merge_duplicates``: the first point, the mean colour), as
   the in-memory preparation merges them. Points at the same position share a cell, so a
   chunk holds all of them.

The chunk of a point depends on its position alone, so the halo that a chunk reads from
its neighbours' runs holds the points the in-memory preparation would give it: the
positions, normals and radii are the in-memory preparation's bit for bit where a point's
neighbourhoods fit in the halo (``tests/test_cloudfile.py``). The surfels come out in the
cloud file's order, the chunks' runs one after another.

Each pass writes under a temporary name and renames when complete, and each chunk's
results are kept as they are computed (``chunks.chunked_surfels``' ``store``), so an
interrupted preparation in the same work folder resumes where it stopped; the folder is
removed when the surfels are complete (``io.on_disk``).
"""

from __future__ import annotations

import contextlib
import json
import mmap
import os
import shutil
from pathlib import Path

import numpy as np

from ..errors import DofsplatError
from ..jit import numba
from .duplicates import merge_duplicates

GRID_CELLS = 1 << 22  # the counting grid's cells at most (an int64 each: 32 MB)
BLOCK = 1 << 20  # points a pass reads and writes at a time
MIN_SHARE = 0.125  # a split leaves each side at least this share of its part's points
FORMAT = 2  # the work folder's layout (cloud.json)
# the bytes a point of a cloud takes in the in-memory preparation's peak (the 18.6 M-point
# synthetic scan's first render, 3.39 GB: docs/outofcore.md); ``wants_disk`` compares it
# with the memory available
IN_MEMORY_BYTES = 180
# the bytes a point takes in the work folder at the preparation's peak: the input's copy
# (30), the chunks' copy before and after the duplicates are merged (36 each), the surfels'
# arrays and the radii before the cap (84)
ON_DISK_BYTES = 190

_MODE = "auto"  # "auto", "on" or "off" (``on_disk``)
_FOLDER = None  # where the work folders go (``on_disk``); None: the cache folder's work/


class on_disk:
    """Within this block, a LAS/LAZ or binary PLY cloud is prepared from files in a work
    folder (mode "on"), in memory ("off"), or from files where its in-memory preparation
    would take more than half the memory available ("auto", the default); the work folders
    go in folder (None: the cache folder's ``work/``): ``dofsplat prepare --on-disk
    --work-dir``."""

    def __init__(self, mode: str = "auto", folder=None):
        if mode not in ("auto", "on", "off"):
            raise DofsplatError(f"on_disk must be 'auto', 'on' or 'off', got {mode!r}")
        self.mode, self.folder = mode, None if folder is None else Path(folder)

    def __enter__(self):
        global _MODE, _FOLDER
        self.previous = _MODE, _FOLDER
        _MODE, _FOLDER = self.mode, self.folder
        return self

    def __exit__(self, *exc):
        global _MODE, _FOLDER
        _MODE, _FOLDER = self.previous


def work_folder(key: dict) -> Path:
    """The folder in which the cloud of key (the input and the options) is prepared, named
    by the key's digest, so that a run after an interruption finds its predecessor's."""
    import hashlib

    from .. import cache

    if _FOLDER is None:
        root = cache.cache_root() / "work"
        cache.check_folder(root)
    else:
        root = _FOLDER
        for above in (root, *root.parents):
            if above.exists() and not above.is_dir():
                raise DofsplatError(f"the work folder {root} cannot be made: {above} is a "
                                    "file, not a folder")
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:20]
    return root / digest


def check_space(folder: Path, n_points: int, source: str) -> None:
    """DofsplatError, before any work, where the disk holding folder has less room than a
    cloud of n_points takes there (``ON_DISK_BYTES`` a point)."""
    need = n_points * ON_DISK_BYTES
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if free < need:
        raise DofsplatError(f"{source}: preparing {n_points:,} points on disk takes about "
                            f"{need / 1e9:,.1f} GB in {folder.parent}, which has "
                            f"{free / 1e9:,.1f} GB free; give another folder with "
                            "--work-dir (or DOFSPLAT_CACHE_DIR)")


def wants_disk(n_points: int) -> bool:
    """Whether a cloud of n_points is prepared on disk (``on_disk``'s mode)."""
    if _MODE != "auto":
        return _MODE == "on"
    from ..machine import available_memory

    return n_points * IN_MEMORY_BYTES > available_memory() // 2


class CloudFile:
    """A cloud of N points on disk in chunks: positions (N, 3) float64 and colours (N, 3)
    float32 (linear) in files of the folder, chunk c's points the rows offsets[c] to
    offsets[c + 1] - 1 and inside the box lo[c] to hi[c]. It reads as an (N, 3) array where
    ``chunks`` reads the cloud: ``cloud[rows]`` (sorted rows) and ``rows_in_box``. It
    pickles as its folder's path and the chunks' table (a worker on the same file system
    reads the files)."""

    def __init__(self, folder, offsets: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                 has_normals: bool = False):
        self.folder = Path(folder)
        self.has_normals = has_normals
        self.offsets = np.asarray(offsets, np.int64)
        self.lo, self.hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        self.shape = (int(self.offsets[-1]), 3)

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def bounds(self) -> list[tuple[int, int]]:
        """[(a, b), ...]: the chunks' rows, a to b - 1."""
        return [(int(a), int(b)) for a, b in zip(self.offsets[:-1], self.offsets[1:])]

    def __getitem__(self, rows) -> np.ndarray:
        """The positions of the sorted rows, (M, 3) float64."""
        return self._rows(POINTS, np.float64, np.asarray(rows, np.int64))

    def colours(self) -> np.ndarray:
        """The colours, (N, 3) float32: a read-only memory map of the file."""
        return np.memmap(self.folder / COLOURS, np.float32, "r", shape=self.shape)

    def normals(self) -> "GivenNormals | None":
        """The normals the input gave (rows of zeros or NaN: none), read as
        ``cloud.normals()[rows]``, (M, 3) float64; None where it gave none."""
        return GivenNormals(self) if self.has_normals else None

    def rows_in_box(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """The sorted rows of the points within the box [lo, hi] (``chunks.rows_in_box``):
        only the chunks whose boxes meet it are read."""
        found = []
        meets = np.all((self.lo <= hi) & (self.hi >= lo), axis=1)
        for c in np.flatnonzero(meets):
            a, b = int(self.offsets[c]), int(self.offsets[c + 1])
            found.append(a + array_rows_in_box(read_rows(self.folder / POINTS, np.float64, a,
                                                         b), lo, hi))
        return np.concatenate(found) if found else np.zeros(0, np.int64)

    def _rows(self, name: str, dtype, rows: np.ndarray) -> np.ndarray:
        out = np.empty((len(rows), 3), dtype)
        if not len(rows):
            return out
        # each chunk the rows touch is read from its first row to its last
        first = np.searchsorted(self.offsets, rows[0], "right") - 1
        last = np.searchsorted(self.offsets, rows[-1], "right") - 1
        for c in range(first, last + 1):
            i, j = np.searchsorted(rows, self.offsets[c:c + 2])
            if i < j:
                a = int(rows[i])
                part = read_rows(self.folder / name, dtype, a, int(rows[j - 1]) + 1)
                out[i:j] = part[rows[i:j] - a]
        return out


POINTS, COLOURS, NORMALS, TABLE = "points.f64", "colours.f32", "normals.f64", "cloud.json"


class GivenNormals:
    """A cloud file's given normals, read by sorted rows: ``normals[rows]``."""

    def __init__(self, cloud: CloudFile):
        self.cloud = cloud

    def __getitem__(self, rows) -> np.ndarray:
        return self.cloud._rows(NORMALS, np.float64, np.asarray(rows, np.int64))


def read_rows(path: Path, dtype, a: int, b: int, width: int = 3) -> np.ndarray:
    """Rows a to b - 1 of a file of (N, width) dtype values, read (not mapped, so that the
    pages stay out of the process's memory)."""
    size = np.dtype(dtype).itemsize * width
    with open(path, "rb") as f:
        f.seek(a * size)
        out = np.fromfile(f, dtype, (b - a) * width)
    if len(out) != (b - a) * width:
        raise DofsplatError(f"{path}: the work file is cut short (remove its folder)")
    return out.reshape(b - a, width)


def open_cloud(folder, key: dict) -> CloudFile | None:
    """The cloud that ``write_cloud`` completed in folder for the input and options key,
    or None."""
    try:
        table = json.loads((Path(folder) / TABLE).read_text())
    except (OSError, ValueError):
        return None
    if table.get("format") != FORMAT or table.get("key") != key:
        return None
    n = int(table["offsets"][-1])
    files = ((POINTS, 24), (COLOURS, 12)) + (((NORMALS, 24),) if table["normals"] else ())
    for name, size in files:  # (files cut short by a crash)
        path = Path(folder) / name
        if not path.is_file() or path.stat().st_size != n * size:
            return None
    return CloudFile(folder, table["offsets"], table["lo"], table["hi"], table["normals"])


def write_cloud(folder, blocks, lo, hi, chunk_points: int, key: dict, bar=None) -> CloudFile:
    """The cloud that blocks gives, written to folder in chunks (the module docstring):
    CloudFile. blocks(): an iterator over the cloud in its input order, each block
    (positions (M, 3) float64, colours (M, 3) float32 linear[, normals (M, 3) float64 or
    None: given normals, rows of zeros or NaN for none]); called once for each pass.
    lo, hi (3,): the cloud's bounds. key: the input and options, kept in the table (a later
    ``open_cloud`` with another key does not take it). bar: a tqdm bar that each pass
    advances by its points."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    dims, cell = grid(lo, hi)

    # 1. count
    counts = np.zeros(int(np.prod(dims)), np.int64)
    for p, *_ in blocks():
        counts += np.bincount(cell_ids(p, lo, cell, dims), minlength=len(counts))
        _advance(bar, len(p))
    n_in = int(counts.sum())
    # 2. plan
    cell_chunk, sizes = plan(counts.reshape(dims), chunk_points)
    del counts
    # 3. distribute, each chunk a run in the input's order
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    spread = folder / "spread.f64"
    spread_colours = folder / "spread.f32"
    filled = starts[:-1].copy()
    has_normals = False
    spread_normals = folder / "spread_normals.f64"
    with open(spread, "wb") as fp, open(spread_colours, "wb") as fc, \
            open(spread_normals, "wb") as fn:
        fp.truncate(n_in * 24)
        fc.truncate(n_in * 12)
        for p, c, *given in blocks():
            nrm = given[0] if given else None
            if nrm is not None and not has_normals:
                has_normals = True
                fn.truncate(n_in * 24)
            chunk = cell_chunk[cell_ids(p, lo, cell, dims)]
            order = np.argsort(chunk, kind="stable")
            chunk = chunk[order]
            p, c = p[order], c[order]
            nrm = None if nrm is None else np.ascontiguousarray(nrm[order], np.float64)
            edges = np.flatnonzero(np.diff(chunk)) + 1
            for a, b in zip(np.concatenate([[0], edges]), np.concatenate([edges, [len(p)]])):
                q = int(chunk[a])
                os.pwrite(fp.fileno(), p[a:b].tobytes(), int(filled[q]) * 24)
                os.pwrite(fc.fileno(), c[a:b].tobytes(), int(filled[q]) * 12)
                if nrm is not None:
                    os.pwrite(fn.fileno(), nrm[a:b].tobytes(), int(filled[q]) * 24)
                filled[q] += b - a
            _advance(bar, len(p))
    # each chunk's duplicates merged (the first normal kept), its box measured
    offsets = [0]
    box_lo, box_hi = [], []
    names = (POINTS, COLOURS, NORMALS) if has_normals else (POINTS, COLOURS)
    with contextlib.ExitStack() as files:
        out = [files.enter_context(open(folder / (name + ".part"), "wb")) for name in names]
        for q in range(len(sizes)):
            a, b = int(starts[q]), int(starts[q + 1])
            p = read_rows(spread, np.float64, a, b)
            c = read_rows(spread_colours, np.float32, a, b)
            nrm = read_rows(spread_normals, np.float64, a, b) if has_normals else None
            p, c, nrm, _ = merge_duplicates(p, c, nrm, "")
            for f, values in zip(out, (p, c, nrm)):
                f.write(np.ascontiguousarray(values).tobytes())
            offsets.append(offsets[-1] + len(p))
            box_lo.append(p.min(axis=0).tolist())
            box_hi.append(p.max(axis=0).tolist())
            _advance(bar, b - a)
    for name in names:
        os.replace(folder / (name + ".part"), folder / name)
    for path in (spread, spread_colours, spread_normals):
        path.unlink()
    table = {"format": FORMAT, "key": key, "offsets": offsets, "lo": box_lo, "hi": box_hi,
             "normals": has_normals}
    (folder / (TABLE + ".part")).write_text(json.dumps(table))
    os.replace(folder / (TABLE + ".part"), folder / TABLE)
    return CloudFile(folder, offsets, box_lo, box_hi, has_normals)


def grid(lo: np.ndarray, hi: np.ndarray) -> tuple[tuple[int, int, int], float]:
    """(cells along each axis, the cells' edge): cubes over the box [lo, hi], at most
    ``GRID_CELLS`` of them."""
    extent = np.maximum(hi - lo, 0.0)
    size = max(float(extent.max()), 1e-12)
    edge = size / GRID_CELLS  # (one row of cells: the finest the budget allows)
    low, high = edge, size
    for _ in range(64):  # bisection on the edge for the most cells within the budget
        mid = 0.5 * (low + high)
        if np.prod(np.floor(extent / mid) + 1) <= GRID_CELLS:
            high = mid
        else:
            low = mid
    dims = tuple(int(d) for d in np.floor(extent / high) + 1)
    return dims, high


def cell_ids(p: np.ndarray, lo: np.ndarray, cell: float, dims) -> np.ndarray:
    """Each point's cell in ``grid``'s cells, numbered x-major: (M,) int64."""
    ijk = np.floor((p - lo) / cell).astype(np.int64)
    np.clip(ijk, 0, np.asarray(dims) - 1, out=ijk)
    return (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]


def plan(counts: np.ndarray, chunk_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(each cell's chunk (cells,) int32, each chunk's points (C,) int64): counts (X, Y, Z)
    the points per cell, cut by splits along the longest axis of each part (the cells are
    cubes: the axis of most cells) at the cell plane nearest its median until a part holds
    at most chunk_points (the module docstring).
    Chunks are numbered depth first, the low side first; empty parts are no chunk."""
    chunk = np.full(counts.shape, -1, np.int32)
    sizes = []
    stack = [((0, 0, 0), counts.shape)]
    while stack:
        o, s = stack.pop()
        part = tuple(slice(o[a], o[a] + s[a]) for a in range(3))
        block = counts[part]
        total = int(block.sum())
        if total == 0:
            continue
        cut = None
        if total > chunk_points:
            for axis in sorted((a for a in range(3) if s[a] > 1), key=lambda a: -s[a]):
                along = np.cumsum(block.sum(axis=tuple(b for b in range(3) if b != axis)))
                j = int(np.clip(np.searchsorted(along, 0.5 * total), 1, s[axis] - 1))
                if j > 1 and abs(along[j - 2] - 0.5 * total) < abs(along[j - 1] - 0.5 * total):
                    j -= 1
                if min(along[j - 1], total - along[j - 1]) >= MIN_SHARE * total:
                    cut = axis, j
                    break
        if cut is None:
            chunk[part] = len(sizes)
            sizes.append(total)
            continue
        axis, j = cut
        low_s, high_s, high_o = list(s), list(s), list(o)
        low_s[axis], high_s[axis], high_o[axis] = j, s[axis] - j, o[axis] + j
        stack.append((tuple(high_o), tuple(high_s)))
        stack.append((o, tuple(low_s)))
    return chunk.ravel(), np.asarray(sizes, np.int64)


class SurfelFiles:
    """Surfels whose arrays are files (float32: positions and normals (N, 3), radius (N,),
    colors (N, 3), weight (N,); given as {name: path}), for a chunk's steps on a Dask
    worker: ``subset`` reads the rows it takes. It pickles as the paths (a worker on the
    same file system reads the files), where Surfels of memory maps pickle their arrays
    whole."""

    def __init__(self, paths: dict, n: int, material):
        self.paths, self.n, self.material = {k: str(v) for k, v in paths.items()}, n, material

    def subset(self, rows: np.ndarray):
        """The surfels of the sorted rows: Surfels."""
        from ..surfels import Surfels

        arrays = {}
        for name, path in self.paths.items():
            width = 3 if name in ("positions", "normals", "colors") else 1
            shape = (self.n, 3) if width == 3 else (self.n,)
            arrays[name] = np.array(np.memmap(path, np.float32, "r", shape=shape)[rows])
        return Surfels(material=self.material, **arrays)


def mapped(folder: Path, name: str, dtype, shape, fresh: bool) -> np.ndarray:
    """A writable memory map of folder/name, (shape) dtype: a new file of zeros where fresh,
    else the file as it is (a preparation resumed)."""
    path = Path(folder) / name
    shape = tuple(np.atleast_1d(shape).tolist())
    if fresh or not path.exists():
        with open(path, "wb") as f:
            f.truncate(int(np.prod(shape)) * np.dtype(dtype).itemsize)
    return np.memmap(path, dtype, "r+", shape=shape)


def release(*arrays) -> None:
    """Write the memory maps' changes to their files and unmap their pages from this
    process (they stay in the page cache), so that the process's resident memory does not
    grow with the files it writes."""
    for a in arrays:
        m = getattr(a, "_mmap", None)
        if m is None:
            continue
        m.flush()
        if hasattr(m, "madvise") and hasattr(mmap, "MADV_DONTNEED"):
            m.madvise(mmap.MADV_DONTNEED)


def array_rows_in_box(pts: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The sorted rows of the points (N, 3) float64 within the box [lo, hi]."""
    inside = np.empty(len(pts), np.bool_)
    _in_box(pts, lo, hi, inside)
    return np.flatnonzero(inside)


@numba.njit(cache=True, nogil=True, parallel=True)
def _in_box(pts, lo, hi, out):
    """out[i] = whether point i lies in the box [lo, hi] (each axis, closed)."""
    for i in numba.prange(pts.shape[0]):
        out[i] = (lo[0] <= pts[i, 0] <= hi[0] and lo[1] <= pts[i, 1] <= hi[1]
                  and lo[2] <= pts[i, 2] <= hi[2])


def remove(folder: Path) -> None:
    """The work folder removed (files still mapped stay readable until unmapped)."""
    shutil.rmtree(folder, ignore_errors=True)


def _advance(bar, m: int) -> None:
    if bar is not None:
        bar.update(m)
