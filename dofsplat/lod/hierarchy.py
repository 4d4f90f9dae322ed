"""A QSplat-style bounding-sphere hierarchy over the surfels, stored as flat arrays.

The tree is binary and built top down: each node's surfels are split at the median along
the longest axis of their bounding box (QSplat's split, with two children instead of up to
four), or, where their normals are about 90 degrees apart or more, along the normal
component that spreads most: a node then never spans two surfaces that meet at an angle (a
sphere and the floor it rests on, the two sides of a leaf), which one flat splat would draw
as a blend of both. A node with m surfels has 2m - 1 nodes in its subtree, and nodes are stored in
preorder, so the tree needs no child pointers:

    left child of node i  = i + 1
    right child of node i = i + 2 * (count[i] // 2)

Node i covers the surfels ``order[start[i] : start[i] + count[i]]``; a leaf (count 1) is one
surfel, and the tree stores nothing else for it: its attributes are its surfel's. A tree
over a large model (``COMPACT_FROM`` surfels or more) does not store its inner nodes of
2 or 3 surfels either (``Hierarchy.small`` = 3, else 1): they are half to two thirds of
the inner nodes, and the selection and the gather compute one from its surfels when they
reach it (``small_node``, by the build's own functions, so bit for bit what the build
would have stored), which costs the selection 1.4-1.9 x its time. The attributes below
are stored for the other nodes, in preorder (``tree_rows``; a walk down the tree counts
them with ``stored_nodes``). Each node carries what the per-frame selection and the
splatting need (Sections 5.3 and 6.2; docs/maths.md, "Level of detail"):

* a bounding sphere (``center``, ``bound``) that contains its children's spheres, for
  frustum and normal-cone culling; and ``extent``, the radius about the same centre of the
  tightest sphere containing the node's surfel disks (radius max(r_u, r_v) each), which
  gives the node's depth range for the DOF stop (the nested spheres grow looser towards
  the root: 1.4 x on a square);
* a normal and a normal-cone half-angle (``cone``, radians) for back-face culling;
* the prefiltered attributes of the level: area-weighted mean colour, opacity, position
  and normal, and the area (the sum of its surfels' areas r_u r_v weight);
* the variances of Section 5.3: ``sigma_r2``, the leaf basis variance V^r (isotropic,
  the area-weighted mean of its surfels' (r_u/2)(r_v/2)), and ``lod_cov``, the level's
  low-pass filter V^{q,l} as a world-space 3x3 covariance: three times the area-weighted
  covariance of its surfels' positions. Why three: a leaf on a grid of spacing h has
  variance h^2/4 (r = h, sigma = r/2; surfels.py), and m leaves spanning a length L = m h
  have positional variance (L^2 - h^2)/12, so 3 x that is L^2/4 - h^2/4: exactly the
  filter that turns the leaf basis V^r into the leaf convention applied to the node's
  own extent, V^l = V^r + V^{q,l} = L^2/4 along each axis. It is anisotropic (the median
  split makes 2:1 nodes on every other level) and zero at the leaves;
* ``color_grad``: the node's colour gradient, the area-weighted covariance of its surfels'
  colours with their positions along the two axes of its tangent frame (``tangent_frame``
  of its normal): where the box-filtered mean colour loses a texture's edges, the
  projection turns this into the colour's slope across the splat (docs/maths.md, "A node's
  colour gradient"); zero at the leaves;
* ``color_detail``: the texture at the node's own scale, which the gradient cannot draw.
  With res^2 the mean square of the surfels' colours about the node's linear fit in its
  tangent plane (area-weighted, linear RGB, the channels summed), the detail is
  sqrt(res^2 - the children's res^2, area-weighted): what splitting the node would fit,
  zero for a flat colour, a ramp or noise finer than the node's children. The cut draws
  a node of more detail finer (``select.detail_factor``; docs/maths.md, "A finer cut where
  the texture needs it"); zero at the leaves.

A node's height (for ``--show-lod``) is not stored either: the median split makes it
ceil(log2 count).
"""

from __future__ import annotations

import math
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

from ..jit import numba
import numpy as np

from ..errors import DofsplatError
from ..fingerprint import content_hash
from ..splat.ewa import tangent_frame
from ..surfels import Surfels

# a node whose unit normals spread by more than this in one component (1.4 ~ sqrt 2: normals
# about 90 degrees apart) is split by normal, not by position (docs/maths.md)
NORMAL_SPREAD = 1.4
# from this many surfels on, inner nodes of at most SMALL_NODE surfels are not stored (they
# are computed when a walk reaches them): the tree's memory falls from 128 bytes per surfel
# to 45-66 (the share of such nodes depends on N), and a frame's selection takes 1.4-1.9 x
# as long (bench/RESULTS.md). 2^22 until issue 50: at 2^21 a 3.7 M-surfel scan's frame at
# 1920 x 1080 holds 1.20-1.27 GB where the full tree (with its leaf-order copy) held
# 1.65-1.72, in 1.16-1.17 x the time (docs/maths.md, "A compact tree for large models")
COMPACT_FROM = 1 << 21
SMALL_NODE = 3
FORMAT_VERSION = 8  # bump when the build or the stored arrays change: old files are rebuilt


@dataclass
class Hierarchy:
    """The flat-array LOD tree over a surfel model (M = 2N - 1 nodes for N surfels, K = N - 1
    of them inner nodes).

    order:    (N,) int32, surfel indices in leaf order
    small:    inner nodes of at most this many surfels are not stored (1 or SMALL_NODE)
    The rest have a row per stored node (more than ``small`` surfels), in preorder: node
    i's row is ``row(i)`` (``tree_rows``):
    center:   (K, 3) float32, bounding-sphere centre, world units
    bound:    (K,) float32, bounding-sphere radius (contains the children's spheres)
    extent:   (K,) float32, radius about ``center`` that just contains the node's disks
    position: (K, 3) float32, area-weighted mean position (where the node is splatted)
    normal:   (K, 3) float32, unit area-weighted mean normal
    cone:     (K,) float32, normal-cone half-angle, radians (pi: no culling possible)
    color:    (K, 3) float32, area-weighted mean linear colour (the prefiltered texture)
    opacity:  (K,) float32, area-weighted mean opacity
    area:     (K,) float32, sum of the surfels' areas r_u r_v weight, world units^2
    sigma_r2: (K,) float32, leaf basis variance V^r, world units^2
    lod_cov:  (K, 6) float32, the level's low-pass filter V^{q,l}, world covariance
              (xx, xy, xz, yy, yz, zz), world units^2
    color_grad: (K, 6) float32, Cov(colour, position . t) per channel and tangent axis
              (r.u, r.v, g.u, g.v, b.u, b.v; colour x world units), t = (u, v) the node's
              ``tangent_frame``
    color_detail: (K,) float32, sqrt(res^2 - children's res^2), res^2 the mean square of the
              surfels' colours about the node's linear fit (mean colour + gradient), RGB
    fingerprint: hash of the surfel arrays the tree was built from

    ``start`` and ``count`` ((M,) int32: each node's first leaf-order position and number of
    surfels) are not stored: the tree's shape depends on N alone (median splits, m into
    m // 2 and m - m // 2), so the walk derives them on its way down, and these properties
    compute them (``tree_shape``) for whoever asks, the CUDA backend and the tests.
    """

    order: np.ndarray
    center: np.ndarray
    bound: np.ndarray
    extent: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    cone: np.ndarray
    color: np.ndarray
    opacity: np.ndarray
    area: np.ndarray
    sigma_r2: np.ndarray
    lod_cov: np.ndarray
    color_grad: np.ndarray
    color_detail: np.ndarray
    fingerprint: str
    small: int = 1
    # the blocked layout of a stored model (``blocked``, ``io.model_file``): None, or (K,)
    # int32, each stored row's first stored child's row (-1: none); block_levels its blocks'
    # depth (0: rows in preorder, the in-memory layout)
    child: np.ndarray | None = None
    block_levels: int = 0

    def __len__(self) -> int:
        return 2 * self.n_surfels - 1

    @property
    def start(self) -> np.ndarray:
        return self._shape()[0]

    @property
    def count(self) -> np.ndarray:
        return self._shape()[1]

    def _shape(self):
        shape = self.__dict__.get("_shape_arrays")
        if shape is None:
            shape = self.__dict__["_shape_arrays"] = tree_shape(self.n_surfels)
        return shape

    @property
    def n_surfels(self) -> int:
        return self.order.shape[0]

    @property
    def depth(self) -> int:
        """Number of levels (the root's height + 1: the median split makes it
        ceil(log2 N) + 1)."""
        return int(node_height(self.n_surfels)) + 1

    @property
    def rows(self) -> np.ndarray:
        """(2N - 1,) int32: each node's row in the attribute arrays, -1 where the tree
        stores none (``tree_rows``)."""
        rows = self.__dict__.get("_rows")
        if rows is None:
            rows = tree_rows(self.n_surfels, self.small)
            if self.block_levels:
                rows = blocked_rows(rows, self.n_surfels, self.small, self.child,
                                    self.block_levels)
            self.__dict__["_rows"] = rows
        return rows

    def blocked(self, levels: int = 8) -> tuple["Hierarchy", np.ndarray]:
        """(the tree with its rows in the blocked layout, file_row): the same nodes, each
        stored row moved to file_row[its preorder row] (``blocked_layout``: blocks of
        ``levels`` levels, breadth first within a block, the blocks in preorder), and
        ``child`` set, so that a cut that stops in a block reads the block's first rows,
        not rows spread over the whole tree (docs/outofcore.md)."""
        file_row, child = self.block_rows(levels)
        moved = {name: np.empty_like(getattr(self, name)) for name in ATTRIBUTES}
        for name in ATTRIBUTES:
            moved[name][file_row] = getattr(self, name)
        tree = Hierarchy(order=self.order, fingerprint=self.fingerprint, small=self.small,
                         child=child, block_levels=levels, **moved)
        return tree, file_row

    def block_rows(self, levels: int = 8) -> tuple[np.ndarray, np.ndarray]:
        """(file_row, child) of ``blocked``'s layout (``blocked_layout``), without moving the
        attributes: for a writer that moves them an array at a time (``io.model_file``)."""
        if self.block_levels:
            raise ValueError("the tree is in the blocked layout already")
        k = len(self.center)
        file_row = np.empty(k, np.int64)
        child = np.empty(k, np.int32)
        blocked_layout(self.n_surfels, self.small, levels, file_row, child)
        return file_row, child

    def row(self, node):
        """The row of node(s) ``node`` in the attribute arrays (-1: not stored)."""
        return self.rows[node]

    def expanded(self, surfels: Surfels) -> dict:
        """The attribute arrays with a row for every inner node (N - 1 rows, node i's row
        i - start[i]): the stored rows, and the small nodes computed (``small_node``), by
        name (center, bound, ...). For the CUDA backend, whose walk reads every inner
        node's row, and for the tests."""
        if self.n_surfels != len(surfels):
            raise DofsplatError("the hierarchy was built for a different model")
        nodes = np.flatnonzero(self.count > 1)
        full = {name: np.empty((nodes.size,) + getattr(self, name).shape[1:], np.float32)
                for name in ATTRIBUTES}
        ru, rv, weight = _radii_weight(surfels)
        _expand(nodes, self.start, self.count, self.rows, self.order, surfels.positions,
                surfels.normals, ru, rv, weight, surfels.colors, surfels.opacity,
                *(getattr(self, name) for name in ATTRIBUTES), *full.values())
        return full

    def children(self, node: int) -> tuple[int, int] | None:
        """(left, right) node indices, or None for a leaf."""
        m = int(self.count[node])
        if m == 1:
            return None
        return node + 1, node + 2 * (m // 2)

    def nbytes(self) -> int:
        return sum(getattr(self, name).nbytes for name in ("order",) + ATTRIBUTES)

    # -- persistence -----------------------------------------------------------------

    def save(self, path) -> Path:
        """Write the tree to an ``.npz`` file (atomically); returns the path."""
        from ..io.images import atomic_write

        path = Path(path)
        arrays = {name: getattr(self, name) for name in ("order",) + ATTRIBUTES}

        def write(tmp):
            with open(tmp, "wb") as fh:
                np.savez(fh, fingerprint=np.array(self.fingerprint),
                         version=np.array(FORMAT_VERSION), small=np.array(self.small), **arrays)

        atomic_write(path, write)
        return path

    @classmethod
    def load(cls, path, surfels: Surfels | None = None) -> "Hierarchy | None":
        """Read a saved tree; None if it is stale (built from other surfels or an older format).

        With ``surfels`` given, the tree is returned only if it was built from exactly these
        surfel arrays (their fingerprint matches). A file that is not a readable tree is a
        DofsplatError.
        """
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                if int(z["version"]) != FORMAT_VERSION:
                    return None
                data = {name: z[name] for name in ("order",) + ATTRIBUTES}
                fp = str(z["fingerprint"])
                small = int(z["small"])
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            # (a cut or damaged .npz is a BadZipFile, which is none of the others)
            raise DofsplatError(f"{path}: not a dofsplat LOD file ({exc})") from None
        if surfels is not None and fp != fingerprint(surfels):
            return None
        if small not in (1, SMALL_NODE) or len(data["center"]) != stored_nodes(
                len(data["order"]), small):
            raise DofsplatError(f"{path}: not a dofsplat LOD file (its rows do not match its "
                                f"layout)")
        tree = cls(fingerprint=fp, small=small, **data)
        if surfels is not None and tree.n_surfels != len(surfels):
            return None
        return tree


ATTRIBUTES = ("center", "bound", "extent", "position", "normal", "cone", "color", "opacity",
              "area", "sigma_r2", "lod_cov", "color_grad", "color_detail")  # a row per stored node each


def _radii_weight(surfels: Surfels):
    """The surfels' r_u, r_v and normalisation weights as the build reads them (weights
    (0,) for a model without: 1 each)."""
    rv = surfels.radius_v if surfels.is_elliptical else surfels.radius
    weight = surfels.weight if surfels.weight is not None else np.zeros(0, np.float32)
    return surfels.radius, rv, weight


TREE_FIELDS = ("positions", "normals", "radius", "colors", "opacity", "tangent", "radius_v",
               "weight")  # the surfel arrays a tree is built from (not the material)


def fingerprint(surfels: Surfels, cached: bool = False) -> str:
    """The content hash (``dofsplat.fingerprint``) of every surfel array that the tree
    depends on, and of the tree's format: changes when the model does. cached: reuse the
    hash kept on the model while its arrays are the same objects (edits in place unseen)."""
    return content_hash(surfels, TREE_FIELDS, fingerprint_salt(), cached=cached)


def fingerprint_salt() -> str:
    """What ``fingerprint`` hashes first: the tree's format (a new one makes old trees stale)."""
    return f"lod v{FORMAT_VERSION}"


def built_for(tree: "Hierarchy | None", surfels: Surfels) -> bool:
    """Whether ``tree`` was built from these surfel arrays (their count and ``fingerprint``,
    kept on the model while its arrays are the same objects)."""
    return tree is not None and tree.n_surfels == len(surfels) and \
        tree.fingerprint == fingerprint(surfels, cached=True)


def default_small(n_surfels: int) -> int:
    """The ``small`` a tree over n surfels is built with: SMALL_NODE from COMPACT_FROM on."""
    return SMALL_NODE if n_surfels >= COMPACT_FROM else 1


def build_hierarchy(surfels: Surfels, progress: bool = False,
                    small: int | None = None) -> Hierarchy:
    """Build the LOD tree over ``surfels`` (O(N log N); a few seconds for a million surfels).

    small: inner nodes of at most this many surfels are not stored, 1 or SMALL_NODE
    (default: SMALL_NODE from COMPACT_FROM surfels on, else 1); the frames are the same.
    """
    n = len(surfels)
    if n >= 1 << 30:
        raise DofsplatError(f"{n} surfels is more than the LOD tree's int32 indices allow")
    if small is None:
        small = default_small(n)
    if small not in (1, SMALL_NODE):
        raise ValueError(f"small must be 1 or {SMALL_NODE}, got {small!r}")
    t0 = time.perf_counter()
    positions = surfels.positions
    ru, rv, weight = _radii_weight(surfels)

    # top down: median splits, level by level (each level's nodes in parallel)
    keys = np.ascontiguousarray(np.hstack([positions, surfels.normals]), np.float32)
    order = np.arange(n, dtype=np.int32)
    ids = np.zeros(1, np.int64)
    starts = np.zeros(1, np.int64)
    counts = np.full(1, n, np.int64)
    bar = _progress(progress, n)
    while ids.size:
        inner = counts > 1
        ids, starts, counts = ids[inner], starts[inner], counts[inner]
        if not ids.size:
            break
        _split_nodes(keys, order, starts, counts)
        half = counts // 2
        ids = np.concatenate([ids + 1, ids + 2 * half])
        starts = np.concatenate([starts, starts + half])
        counts = np.concatenate([half, counts - half])
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    del keys, ids, starts, counts

    # bottom up: spheres, cones and prefiltered attributes, for the nodes of more than
    # `small` surfels only (a leaf is its surfel, a small node is computed from its surfels
    # when needed), in preorder (tree_rows); depth first, holding only those rows
    rows = attribute_rows(stored_nodes(n, small))
    _aggregate_rows(order, positions, surfels.normals, ru, rv, weight, surfels.colors,
                    surfels.opacity, small, *rows)
    tree = Hierarchy(order=order, fingerprint=fingerprint(surfels), small=small,
                     **dict(zip(ATTRIBUTES, rows)))
    tree.build_seconds = time.perf_counter() - t0  # informational, not stored
    return tree


@numba.njit(cache=True, nogil=True, inline="always")
def push_children(stack, top, i, s, m):
    """Push the children of node i (first leaf s, m > 1 surfels) on a walk's stack, rows of
    (node, first leaf, count) in its first three columns, the right child first (visited
    second); returns the new top. The one place that says how a node's surfels split: the
    left child i + 1 takes the first m // 2, the right child i + 2 (m // 2) the rest."""
    h = m // 2
    stack[top, 0] = i + 2 * h
    stack[top, 1] = s + h
    stack[top, 2] = m - h
    stack[top + 1, 0] = i + 1
    stack[top + 1, 1] = s
    stack[top + 1, 2] = h
    return top + 2


@numba.njit(cache=True, nogil=True)
def tree_shape(n_surfels):
    """(start, count), (2N - 1,) int32 each: every node's first leaf-order position and
    number of surfels, in preorder, for the median splits of ``build_hierarchy``."""
    m_nodes = max(2 * n_surfels - 1, 0)
    start = np.empty(m_nodes, np.int32)
    count = np.empty(m_nodes, np.int32)
    if m_nodes == 0:
        return start, count
    stack = np.empty((96, 3), np.int64)
    stack[0, 0] = 0
    stack[0, 1] = 0
    stack[0, 2] = n_surfels
    top = 1
    while top > 0:
        top -= 1
        i, s, m = stack[top, 0], stack[top, 1], stack[top, 2]
        start[i] = s
        count[i] = m
        if m > 1:
            top = push_children(stack, top, i, s, m)
    return start, count


def _progress(enabled: bool, n: int):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=max(1, math.ceil(math.log2(max(n, 2)))), desc="LOD hierarchy",
                unit="level", leave=False)


# -- kernels -----------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True, inline="always")
def _bounds(positions, order, s, e, col=0):
    """Bounding box (lo x, y, z, hi x, y, z) of the surfels order[s:e] (columns col..col+2)."""
    lo0 = lo1 = lo2 = np.inf
    hi0 = hi1 = hi2 = -np.inf
    for j in range(s, e):
        k = order[j]
        x, y, z = positions[k, col], positions[k, col + 1], positions[k, col + 2]
        lo0, hi0 = min(lo0, x), max(hi0, x)
        lo1, hi1 = min(lo1, y), max(hi1, y)
        lo2, hi2 = min(lo2, z), max(hi2, z)
    return lo0, lo1, lo2, hi0, hi1, hi2


@numba.njit(cache=True, nogil=True, parallel=True)
def _split_nodes(keys, order, starts, counts):
    """For each node, move the lower half of its surfels first, along its bbox's longest axis,
    or along the normal component that spreads most, where it spreads over NORMAL_SPREAD.

    keys: (N, 6) float32, positions then unit normals.
    """
    for t in numba.prange(starts.shape[0]):
        s = starts[t]
        e = s + counts[t]
        lo0, lo1, lo2, hi0, hi1, hi2 = _bounds(keys, order, s, e, 0)
        axis = 0
        ext = hi0 - lo0
        if hi1 - lo1 > ext:
            axis, ext = 1, hi1 - lo1
        if hi2 - lo2 > ext:
            axis, ext = 2, hi2 - lo2
        # a node over two surfaces (a sphere on a floor, two sides of a leaf) would be drawn
        # as one flat splat: where the normals spread widely, separate the surfaces first
        n0, n1, n2, m0, m1, m2 = _bounds(keys, order, s, e, 3)
        spread = NORMAL_SPREAD
        if m0 - n0 > spread:
            axis, spread = 3, m0 - n0
        if m1 - n1 > spread:
            axis, spread = 4, m1 - n1
        if m2 - n2 > spread:
            axis = 5
        _select_nth(order, s, e - 1, s + counts[t] // 2, keys, axis)


@numba.njit(cache=True, nogil=True)
def _select_nth(order, lo, hi, nth, positions, axis):
    """Quickselect (Hoare partition, median-of-three pivot) on order[lo..hi] by coordinate.

    Afterwards every surfel before position ``nth`` has a coordinate <= every one from
    ``nth`` on. Equal keys are handled without quadratic behaviour.
    """
    while hi > lo:
        mid = (lo + hi) >> 1
        a = positions[order[lo], axis]
        b = positions[order[mid], axis]
        c = positions[order[hi], axis]
        pivot = max(min(a, b), min(max(a, b), c))  # median of three
        i, j = lo, hi
        while i <= j:
            while positions[order[i], axis] < pivot:
                i += 1
            while positions[order[j], axis] > pivot:
                j -= 1
            if i <= j:
                tmp = order[i]
                order[i] = order[j]
                order[j] = tmp
                i += 1
                j -= 1
        if nth <= j:
            hi = j
        elif nth >= i:
            lo = i
        else:
            return


@numba.njit(cache=True, nogil=True, inline="always")
def _sphere(order, s, e, positions, ru, rv):
    """The sphere of the surfels order[s:e]: centred on their bounding box, just containing
    their disks; (cx, cy, cz, radius), float64."""
    lo0, lo1, lo2, hi0, hi1, hi2 = _bounds(positions, order, s, e)
    cx = 0.5 * (np.float64(lo0) + hi0)
    cy = 0.5 * (np.float64(lo1) + hi1)
    cz = 0.5 * (np.float64(lo2) + hi2)
    rad = 0.0
    for j in range(s, e):
        k = order[j]
        dx = positions[k, 0] - cx
        dy = positions[k, 1] - cy
        dz = positions[k, 2] - cz
        rad = max(rad, math.sqrt(dx * dx + dy * dy + dz * dz) + max(ru[k], rv[k]))
    return cx, cy, cz, rad


def whole_array_rows(surfels: Surfels, order: np.ndarray, small: int):
    """The stored rows (``attribute_rows``' arrays) of the tree over order's surfels, the
    way the build computed them before issue 50: every node's attributes and float64
    moments in arrays of 2N - 1 rows (``_node_spheres``, ``_aggregate``, about 640 bytes a
    surfel), the stored ones taken after. The twin of ``_aggregate_rows`` for the tests."""
    n = len(order)
    start, count = tree_shape(n)
    m_nodes = 2 * n - 1
    whole = [np.empty((m_nodes,) + a.shape[1:], np.float32) for a in attribute_rows(1)]
    ru, rv, weight = _radii_weight(surfels)
    _node_spheres(order, start, count, surfels.positions, ru, rv, whole[0], whole[2])
    _aggregate(order, start, count, surfels.positions, surfels.normals, ru, rv, weight,
               surfels.colors, surfels.opacity, *whole)
    keep = count > small
    return tuple(a[keep] for a in whole)


@numba.njit(cache=True, nogil=True, parallel=True)
def _node_spheres(order, start, count, positions, ru, rv, center, extent):
    """Each node's sphere (``_sphere``): its centre and its ``extent``."""
    for i in numba.prange(count.shape[0]):
        cx, cy, cz, rad = _sphere(order, start[i], start[i] + count[i], positions, ru, rv)
        center[i, 0], center[i, 1], center[i, 2] = cx, cy, cz
        extent[i] = rad


# -- one node's values ------------------------------------------------------------------------
# A node as one tuple of float64 (no arrays: numba passes a tuple of scalars for free, where
# arrays passed between functions cost reference counting): its attributes as the tree
# stores them (rounded to float32), then the build's float64 moments. Offsets:
V_CENTER, V_BOUND, V_EXTENT, V_POSITION, V_NORMAL, V_CONE = 0, 3, 4, 5, 8, 11
V_COLOR, V_OPACITY, V_AREA, V_SIGMA_R2, V_LOD_COV, V_COLOR_GRAD = 12, 15, 16, 17, 18, 24
V_COLOR_DETAIL = 30
V_GEO, V_MEAN, V_COV, V_CMEAN, V_CCOV, V_CVAR, V_RES2 = 31, 32, 35, 41, 44, 53, 54  # geometric area, moments
N_VALUES = 55


@numba.njit(cache=True, nogil=True, inline="always")
def _f32(x):
    """x as a float32 array stores it."""
    return np.float64(np.float32(x))


@numba.njit(cache=True, nogil=True, inline="always")
def _leaf_values(px, py, pz, nx, ny, nz, red, green, blue, ru, rv, weight, alpha):
    """A leaf's values from its surfel's (float32 values, weight 1 for a model without)."""
    a_geo = ru * rv
    reach = max(ru, rv)  # its sphere: centred on it, its disk's radius
    z = 0.0
    return (px, py, pz, reach, reach, px, py, pz, nx, ny, nz, z, red, green, blue, alpha,
            _f32(a_geo * weight), _f32(0.25 * a_geo), z, z, z, z, z, z, z, z, z, z, z, z, z,
            a_geo, px, py, pz, z, z, z, z, z, z, red, green, blue, z, z, z, z, z, z, z, z, z, z, z)


@numba.njit(cache=True, nogil=True, inline="always")
def _surfel_leaf(k, positions, normals, ru, rv, weight, colors, alpha):
    """``_leaf_values`` of surfel k (weight: (0,) for a model without)."""
    w = 1.0
    if weight.shape[0] > 0:
        w = np.float64(weight[k])
    return _leaf_values(np.float64(positions[k, 0]), np.float64(positions[k, 1]),
                        np.float64(positions[k, 2]), np.float64(normals[k, 0]),
                        np.float64(normals[k, 1]), np.float64(normals[k, 2]),
                        np.float64(colors[k, 0]), np.float64(colors[k, 1]),
                        np.float64(colors[k, 2]), np.float64(ru[k]), np.float64(rv[k]), w,
                        np.float64(alpha[k]))


# not inlined at numba's level, nor is small_node: inlined into every walk and gather, their
# tuples of N_VALUES took numba 80 s to compile (bench/RESULTS.md, "The first run"); the
# calls cost the compact tree's selection 1.1-1.25 x
@numba.njit(cache=True, nogil=True)
def _combine(L, R, cx, cy, cz, extent, full):
    """A node's values from its children's, L and R, and its sphere (``_sphere``: centre
    and extent, as stored). full=False leaves out (as zeros) what the selection does not
    read: the colour, opacity, colour gradient, colour detail and the normal cone."""
    al, ar = L[V_AREA], R[V_AREA]
    a = al + ar
    # area-weighted means; equal weights if both children carry no area
    if a > 0.0:
        fl, fr = al / a, ar / a
    else:
        fl = fr = 0.5
    gl, gr = L[V_GEO], R[V_GEO]
    g = gl + gr
    sigma_r2 = (gl * L[V_SIGMA_R2] + gr * R[V_SIGMA_R2]) / g
    # parallel-axis combination of the children's moments
    m0 = fl * L[V_MEAN] + fr * R[V_MEAN]
    m1 = fl * L[V_MEAN + 1] + fr * R[V_MEAN + 1]
    m2 = fl * L[V_MEAN + 2] + fr * R[V_MEAN + 2]
    d0l, d1l, d2l = L[V_MEAN] - m0, L[V_MEAN + 1] - m1, L[V_MEAN + 2] - m2
    d0r, d1r, d2r = R[V_MEAN] - m0, R[V_MEAN + 1] - m1, R[V_MEAN + 2] - m2
    c0 = fl * (L[V_COV] + d0l * d0l) + fr * (R[V_COV] + d0r * d0r)
    c1 = fl * (L[V_COV + 1] + d0l * d1l) + fr * (R[V_COV + 1] + d0r * d1r)
    c2 = fl * (L[V_COV + 2] + d0l * d2l) + fr * (R[V_COV + 2] + d0r * d2r)
    c3 = fl * (L[V_COV + 3] + d1l * d1l) + fr * (R[V_COV + 3] + d1r * d1r)
    c4 = fl * (L[V_COV + 4] + d1l * d2l) + fr * (R[V_COV + 4] + d1r * d2r)
    c5 = fl * (L[V_COV + 5] + d2l * d2l) + fr * (R[V_COV + 5] + d2r * d2r)

    opacity = red = green = blue = 0.0
    e0 = e1 = e2 = 0.0  # the mean colour, float64
    q0 = q1 = q2 = q3 = q4 = q5 = q6 = q7 = q8 = 0.0  # colour x position covariance
    cvar = 0.0  # the colour's variance, the channels' summed
    if full:
        opacity = _f32(fl * L[V_OPACITY] + fr * R[V_OPACITY])
        red = _f32(fl * L[V_COLOR] + fr * R[V_COLOR])
        green = _f32(fl * L[V_COLOR + 1] + fr * R[V_COLOR + 1])
        blue = _f32(fl * L[V_COLOR + 2] + fr * R[V_COLOR + 2])
        e0 = fl * L[V_CMEAN] + fr * R[V_CMEAN]
        e1 = fl * L[V_CMEAN + 1] + fr * R[V_CMEAN + 1]
        e2 = fl * L[V_CMEAN + 2] + fr * R[V_CMEAN + 2]
        el, er = L[V_CMEAN] - e0, R[V_CMEAN] - e0
        q0 = fl * (L[V_CCOV] + el * d0l) + fr * (R[V_CCOV] + er * d0r)
        q1 = fl * (L[V_CCOV + 1] + el * d1l) + fr * (R[V_CCOV + 1] + er * d1r)
        q2 = fl * (L[V_CCOV + 2] + el * d2l) + fr * (R[V_CCOV + 2] + er * d2r)
        el, er = L[V_CMEAN + 1] - e1, R[V_CMEAN + 1] - e1
        q3 = fl * (L[V_CCOV + 3] + el * d0l) + fr * (R[V_CCOV + 3] + er * d0r)
        q4 = fl * (L[V_CCOV + 4] + el * d1l) + fr * (R[V_CCOV + 4] + er * d1r)
        q5 = fl * (L[V_CCOV + 5] + el * d2l) + fr * (R[V_CCOV + 5] + er * d2r)
        el, er = L[V_CMEAN + 2] - e2, R[V_CMEAN + 2] - e2
        q6 = fl * (L[V_CCOV + 6] + el * d0l) + fr * (R[V_CCOV + 6] + er * d0r)
        q7 = fl * (L[V_CCOV + 7] + el * d1l) + fr * (R[V_CCOV + 7] + er * d1r)
        q8 = fl * (L[V_CCOV + 8] + el * d2l) + fr * (R[V_CCOV + 8] + er * d2r)
        dl = ((L[V_CMEAN] - e0) ** 2 + (L[V_CMEAN + 1] - e1) ** 2 + (L[V_CMEAN + 2] - e2) ** 2)
        dr = ((R[V_CMEAN] - e0) ** 2 + (R[V_CMEAN + 1] - e1) ** 2 + (R[V_CMEAN + 2] - e2) ** 2)
        cvar = fl * (L[V_CVAR] + dl) + fr * (R[V_CVAR] + dr)

    # normal: area-weighted mean; the cone must contain both children's cones
    nx = fl * L[V_NORMAL] + fr * R[V_NORMAL]
    ny = fl * L[V_NORMAL + 1] + fr * R[V_NORMAL + 1]
    nz = fl * L[V_NORMAL + 2] + fr * R[V_NORMAL + 2]
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    cone = 0.0
    if nn < 1e-6:  # opposite normals: no meaningful mean, no culling
        sx, sy, sz = L[V_NORMAL], L[V_NORMAL + 1], L[V_NORMAL + 2]
        cone = _f32(math.pi)
    else:
        nx, ny, nz = nx / nn, ny / nn, nz / nn
        sx, sy, sz = _f32(nx), _f32(ny), _f32(nz)  # as stored
        if full:
            wide = 0.0
            for c in (L, R):
                dot = nx * c[V_NORMAL] + ny * c[V_NORMAL + 1] + nz * c[V_NORMAL + 2]
                ang = math.acos(min(1.0, max(-1.0, dot))) + c[V_CONE]
                wide = max(wide, ang)
            # float32 storage: round the angle up a little so the cone stays conservative
            cone = _f32(min(math.pi, wide * (1.0 + 1e-6) + 1e-6))

    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    detail = res2 = 0.0
    if full:
        # the colour gradient in the node's tangent frame, from its normal as stored
        # (float32), so that the projection derives the same frame
        ux, uy, uz, vx, vy, vz = tangent_frame(sx, sy, sz)
        g0 = _f32(q0 * ux + q1 * uy + q2 * uz)
        g1 = _f32(q0 * vx + q1 * vy + q2 * vz)
        g2 = _f32(q3 * ux + q4 * uy + q5 * uz)
        g3 = _f32(q3 * vx + q4 * vy + q5 * vz)
        g4 = _f32(q6 * ux + q7 * uy + q8 * uz)
        g5 = _f32(q6 * vx + q7 * vy + q8 * vz)
        # what the linear fit leaves, and how much of it a split into the children fits
        res2 = _residual2(cvar, q0, q1, q2, q3, q4, q5, q6, q7, q8, c0, c1, c2, c3, c4, c5,
                          ux, uy, uz, vx, vy, vz)
        detail = _f32(math.sqrt(max(res2 - fl * L[V_RES2] - fr * R[V_RES2], 0.0)))

    # the sphere (centred on the node's bounding box, _sphere) must also contain both
    # children's spheres; the extra slack covers the float32 rounding of centres
    rad = extent
    for c in (L, R):
        dx = c[V_CENTER] - cx
        dy = c[V_CENTER + 1] - cy
        dz = c[V_CENTER + 2] - cz
        rad = max(rad, math.sqrt(dx * dx + dy * dy + dz * dz) + c[V_BOUND])
    bound = _f32(rad * (1.0 + 1e-6) + 4e-7 * (abs(cx) + abs(cy) + abs(cz)))

    return (cx, cy, cz, bound, extent, _f32(m0), _f32(m1), _f32(m2), sx, sy, sz, cone,
            red, green, blue, opacity, _f32(a), _f32(sigma_r2),
            _f32(3.0 * c0), _f32(3.0 * c1), _f32(3.0 * c2), _f32(3.0 * c3), _f32(3.0 * c4),
            _f32(3.0 * c5), g0, g1, g2, g3, g4, g5, detail,
            g, m0, m1, m2, c0, c1, c2, c3, c4, c5, e0, e1, e2, q0, q1, q2, q3, q4, q5, q6, q7, q8,
            cvar, res2)


@numba.njit(cache=True, nogil=True, inline="always")
def _residual2(cvar, q0, q1, q2, q3, q4, q5, q6, q7, q8, c0, c1, c2, c3, c4, c5,
               ux, uy, uz, vx, vy, vz):
    """The mean square of a node's colours about their least-squares linear fit in its
    tangent plane: Var(colour) - sum over channels of g^T C^-1 g, g = Cov(channel, (p.u, p.v)) and C
    the positions' 2 x 2 covariance in the frame (u, v); C regularised by 1e-9 of its trace,
    so a node whose surfels lie on a line fits along it alone, and none fitted where they
    all sit at one point."""
    # C in the tangent frame, from the world covariance (xx, xy, xz, yy, yz, zz)
    cux = c0 * ux + c1 * uy + c2 * uz
    cuy = c1 * ux + c3 * uy + c4 * uz
    cuz = c2 * ux + c4 * uy + c5 * uz
    cvx = c0 * vx + c1 * vy + c2 * vz
    cvy = c1 * vx + c3 * vy + c4 * vz
    cvz = c2 * vx + c4 * vy + c5 * vz
    a = ux * cux + uy * cuy + uz * cuz
    b = ux * cvx + uy * cvy + uz * cvz
    d = vx * cvx + vy * cvy + vz * cvz
    eps = 1e-9 * (a + d)
    a += eps
    d += eps
    det = a * d - b * b
    if not det > 0.0:  # every surfel at one point: no slope to fit
        return max(cvar, 0.0)
    explained = 0.0
    for gx, gy, gz in ((q0, q1, q2), (q3, q4, q5), (q6, q7, q8)):
        gu = gx * ux + gy * uy + gz * uz
        gv = gx * vx + gy * vy + gz * vz
        explained += (d * gu * gu - 2.0 * b * gu * gv + a * gv * gv) / det
    return max(cvar - explained, 0.0)


@numba.njit(cache=True, nogil=True, inline="always")
def load_attributes(i, center, bound, extent, position, normal, cone, color, opacity, area,
                    sigma_r2, lod_cov, color_grad, color_detail):
    """Row i of the attribute arrays: the first V_GEO values of ``_combine``'s tuple."""
    f = np.float64
    return (f(center[i, 0]), f(center[i, 1]), f(center[i, 2]), f(bound[i]), f(extent[i]),
            f(position[i, 0]), f(position[i, 1]), f(position[i, 2]), f(normal[i, 0]),
            f(normal[i, 1]), f(normal[i, 2]), f(cone[i]), f(color[i, 0]), f(color[i, 1]),
            f(color[i, 2]), f(opacity[i]), f(area[i]), f(sigma_r2[i]), f(lod_cov[i, 0]),
            f(lod_cov[i, 1]), f(lod_cov[i, 2]), f(lod_cov[i, 3]), f(lod_cov[i, 4]),
            f(lod_cov[i, 5]), f(color_grad[i, 0]), f(color_grad[i, 1]), f(color_grad[i, 2]),
            f(color_grad[i, 3]), f(color_grad[i, 4]), f(color_grad[i, 5]), f(color_detail[i]))


@numba.njit(cache=True, nogil=True, inline="always")
def _load(i, center, bound, extent, position, normal, cone, color, opacity, area, sigma_r2,
          lod_cov, color_grad, color_detail, geo, mean, cov, cmean, ccov, cvar, res2):
    """Node i's values from the build's arrays (``_combine``'s tuple)."""
    return load_attributes(i, center, bound, extent, position, normal, cone, color, opacity,
                           area, sigma_r2, lod_cov, color_grad, color_detail) + (
        geo[i], mean[i, 0], mean[i, 1], mean[i, 2], cov[i, 0], cov[i, 1], cov[i, 2],
        cov[i, 3], cov[i, 4], cov[i, 5], cmean[i, 0], cmean[i, 1], cmean[i, 2], ccov[i, 0],
        ccov[i, 1], ccov[i, 2], ccov[i, 3], ccov[i, 4], ccov[i, 5], ccov[i, 6], ccov[i, 7],
        ccov[i, 8], cvar[i], res2[i])


@numba.njit(cache=True, nogil=True, inline="always")
def store_attributes(v, t, center, bound, extent, position, normal, cone, color, opacity,
                     area, sigma_r2, lod_cov, color_grad, color_detail):
    """A node's values ``v`` into row t of the attribute arrays (ATTRIBUTES' order)."""
    for d in range(3):
        center[t, d] = v[V_CENTER + d]
        position[t, d] = v[V_POSITION + d]
        normal[t, d] = v[V_NORMAL + d]
        color[t, d] = v[V_COLOR + d]
    bound[t] = v[V_BOUND]
    extent[t] = v[V_EXTENT]
    cone[t] = v[V_CONE]
    opacity[t] = v[V_OPACITY]
    area[t] = v[V_AREA]
    sigma_r2[t] = v[V_SIGMA_R2]
    color_detail[t] = v[V_COLOR_DETAIL]
    for d in range(6):
        lod_cov[t, d] = v[V_LOD_COV + d]
        color_grad[t, d] = v[V_COLOR_GRAD + d]


@numba.njit(cache=True, nogil=True)
def _aggregate(order, start, count, positions, normals, ru, rv, weight, colors, alpha,
               center, bound, extent, position, normal, cone, color, opacity, area, sigma_r2,
               lod_cov, color_grad, color_detail):
    """Fill the node arrays, children before parents (reverse preorder); each node's sphere
    (center, extent) is there already (``_node_spheres``)."""
    m_nodes = count.shape[0]
    # geometric area of each node (r_u r_v summed, no normalisation weights): weights sigma_r2
    geo = np.empty(m_nodes, np.float64)
    # area-weighted mean position and covariance of the node's surfels, in float64
    mean = np.empty((m_nodes, 3), np.float64)
    cov = np.empty((m_nodes, 6), np.float64)
    # area-weighted mean colour and colour-position covariance (channel x world axis)
    cmean = np.empty((m_nodes, 3), np.float64)
    ccov = np.empty((m_nodes, 9), np.float64)
    cvar = np.empty(m_nodes, np.float64)  # the colour's variance, channels summed
    res2 = np.empty(m_nodes, np.float64)  # its mean square about the node's linear fit
    for i in range(m_nodes - 1, -1, -1):
        m = count[i]
        if m == 1:
            v = _surfel_leaf(order[start[i]], positions, normals, ru, rv, weight, colors, alpha)
        else:
            v = _combine(_load(i + 1, center, bound, extent, position, normal, cone, color,
                               opacity, area, sigma_r2, lod_cov, color_grad, color_detail, geo,
                               mean, cov, cmean, ccov, cvar, res2),
                         _load(i + 2 * (m // 2), center, bound, extent, position, normal, cone,
                               color, opacity, area, sigma_r2, lod_cov, color_grad, color_detail,
                               geo, mean, cov, cmean, ccov, cvar, res2),
                         np.float64(center[i, 0]), np.float64(center[i, 1]),
                         np.float64(center[i, 2]), np.float64(extent[i]), True)
        store_attributes(v, i, center, bound, extent, position, normal, cone, color, opacity,
                         area, sigma_r2, lod_cov, color_grad, color_detail)
        geo[i] = v[V_GEO]
        cvar[i] = v[V_CVAR]
        res2[i] = v[V_RES2]
        for d in range(3):
            mean[i, d] = v[V_MEAN + d]
            cmean[i, d] = v[V_CMEAN + d]
        for d in range(6):
            cov[i, d] = v[V_COV + d]
        for d in range(9):
            ccov[i, d] = v[V_CCOV + d]


# -- the build's bottom-up pass, depth first (issue 50) ---------------------------------------
# ``_aggregate`` holds every node's attributes and float64 moments, about 640 bytes a surfel
# at once; a depth-first walk holds only the stored rows and a stack of values (a node's
# children are needed once, by it), and gives the same rows bit for bit: a child's values
# are taken as ``_load`` would read them back (``_as_stored``: the attributes rounded to
# float32, the moments as they are), and each node's sphere is ``_sphere``'s, rounded as
# ``_node_spheres`` stores it.
SUBTREE_DEPTH = 7  # the walk's top levels: 2^7 subtrees walked in parallel below them
WALK_STACK = 128  # frames and values on a walk's stacks (the tree's depth is ~log2 N < 31)


@numba.njit(cache=True, nogil=True, inline="always")
def _push_values(vals, j, v):
    """Values v (``_combine``'s tuple) into row j of a walk's value stack, as stored."""
    for d in range(V_GEO):
        vals[j, d] = _f32(v[d])
    for d in range(V_GEO, N_VALUES):
        vals[j, d] = v[d]


@numba.njit(cache=True, nogil=True, inline="always")
def _stacked_values(vals, j):
    """Row j of a walk's value stack as ``_combine``'s tuple."""
    return (vals[j, 0], vals[j, 1], vals[j, 2], vals[j, 3], vals[j, 4], vals[j, 5],
            vals[j, 6], vals[j, 7], vals[j, 8], vals[j, 9], vals[j, 10], vals[j, 11],
            vals[j, 12], vals[j, 13], vals[j, 14], vals[j, 15], vals[j, 16], vals[j,
            17], vals[j, 18], vals[j, 19], vals[j, 20], vals[j, 21], vals[j, 22],
            vals[j, 23], vals[j, 24], vals[j, 25], vals[j, 26], vals[j, 27], vals[j,
            28], vals[j, 29], vals[j, 30], vals[j, 31], vals[j, 32], vals[j, 33],
            vals[j, 34], vals[j, 35], vals[j, 36], vals[j, 37], vals[j, 38], vals[j,
            39], vals[j, 40], vals[j, 41], vals[j, 42], vals[j, 43], vals[j, 44],
            vals[j, 45], vals[j, 46], vals[j, 47], vals[j, 48], vals[j, 49], vals[j,
            50], vals[j, 51], vals[j, 52], vals[j, 53], vals[j, 54])


@numba.njit(cache=True, nogil=True)
def _walk_rows(i0, s0, m0, depth0, row0, stop_depth, tasks, task_vals, order, positions,
               normals, ru, rv, weight, colors, alpha, small, center, bound, extent, position,
               normal, cone, color, opacity, area, sigma_r2, lod_cov, color_grad, color_detail,
               out, out_j):
    """Node i0's subtree (first leaf s0, m0 surfels, at depth0), depth first: each stored
    node's attributes (more than ``small`` surfels) into its row, from row0 on in
    preorder; the subtree's root values into out[out_j] (``_push_values``). Below
    stop_depth the subtrees are not walked: the nodes at that depth take the values of
    task_vals in preorder (the next of tasks' rows), and their stored nodes' rows are
    skipped (``stored_nodes``). Returns the row after the subtree's last."""
    st = np.empty((WALK_STACK, 5), np.int64)  # frames: node, first leaf, count, depth, step
    rows = np.empty(WALK_STACK, np.int64)
    vals = np.empty((WALK_STACK, N_VALUES), np.float64)
    top = 1
    n_vals = 0
    row = row0
    task = 0
    st[0, 0], st[0, 1], st[0, 2], st[0, 3], st[0, 4] = i0, s0, m0, depth0, 0
    while top > 0:
        f = top - 1
        i, s, m, depth, step = st[f, 0], st[f, 1], st[f, 2], st[f, 3], st[f, 4]
        if step == 0:
            if m == 1:
                _push_values(vals, n_vals, _surfel_leaf(order[s], positions, normals, ru, rv,
                                                        weight, colors, alpha))
                n_vals += 1
                top -= 1
                continue
            if depth == stop_depth:  # a subtree walked on its own
                for d in range(N_VALUES):
                    vals[n_vals, d] = task_vals[task, d]
                n_vals += 1
                task += 1
                row += stored_nodes(m, small)
                top -= 1
                continue
            rows[f] = -1
            if m > small:
                rows[f] = row
                row += 1
        h = m // 2
        if step == 0 or step == 1:  # the left child, then the right
            st[f, 4] = step + 1
            c = top
            if step == 0:
                st[c, 0], st[c, 1], st[c, 2] = i + 1, s, h
            else:
                st[c, 0], st[c, 1], st[c, 2] = i + 2 * h, s + h, m - h
            st[c, 3], st[c, 4] = depth + 1, 0
            top += 1
            continue
        cx, cy, cz, rad = _sphere(order, s, s + m, positions, ru, rv)
        v = _combine(_stacked_values(vals, n_vals - 2), _stacked_values(vals, n_vals - 1),
                     _f32(cx), _f32(cy), _f32(cz), _f32(rad), True)
        n_vals -= 2
        if rows[f] >= 0:
            store_attributes(v, rows[f], center, bound, extent, position, normal, cone, color,
                             opacity, area, sigma_r2, lod_cov, color_grad, color_detail)
        _push_values(vals, n_vals, v)
        n_vals += 1
        top -= 1
    for d in range(N_VALUES):
        out[out_j, d] = vals[0, d]
    return row


@numba.njit(cache=True, nogil=True)
def _subtrees(n, depth, small):
    """The nodes at this depth of the tree of n surfels, in preorder: (K, 4) int64 rows
    (node, first leaf, count, first stored row of its subtree)."""
    out = np.empty((1 << depth, 4), np.int64)
    st = np.empty((WALK_STACK, 4), np.int64)
    st[0, 0], st[0, 1], st[0, 2], st[0, 3] = 0, 0, n, 0
    top = 1
    k = 0
    row = 0
    while top > 0:
        top -= 1
        i, s, m, d = st[top, 0], st[top, 1], st[top, 2], st[top, 3]
        if m == 1:
            continue
        if d == depth:
            out[k, 0], out[k, 1], out[k, 2], out[k, 3] = i, s, m, row
            row += stored_nodes(m, small)
            k += 1
            continue
        if m > small:
            row += 1
        h = m // 2
        st[top, 0], st[top, 1], st[top, 2], st[top, 3] = i + 2 * h, s + h, m - h, d + 1
        st[top + 1, 0], st[top + 1, 1], st[top + 1, 2], st[top + 1, 3] = i + 1, s, h, d + 1
        top += 2
    return out[:k]


@numba.njit(cache=True, nogil=True, parallel=True)
def _aggregate_rows(order, positions, normals, ru, rv, weight, colors, alpha, small, center,
                    bound, extent, position, normal, cone, color, opacity, area, sigma_r2,
                    lod_cov, color_grad, color_detail):
    """The stored rows of the tree over order's surfels (``_aggregate``'s values, the rows
    of ``tree_rows``), depth first: the subtrees below ``SUBTREE_DEPTH`` in parallel, then
    the levels above them."""
    n = order.shape[0]
    tasks = _subtrees(n, SUBTREE_DEPTH, small)
    task_vals = np.empty((tasks.shape[0], N_VALUES), np.float64)
    for t in numba.prange(tasks.shape[0]):
        _walk_rows(tasks[t, 0], tasks[t, 1], tasks[t, 2], SUBTREE_DEPTH, tasks[t, 3], -1,
                   tasks, task_vals, order, positions, normals, ru, rv, weight, colors, alpha,
                   small, center, bound, extent, position, normal, cone, color, opacity, area,
                   sigma_r2, lod_cov, color_grad, color_detail, task_vals, t)
    root = np.empty((1, N_VALUES), np.float64)
    _walk_rows(0, 0, n, 0, 0, SUBTREE_DEPTH, tasks, task_vals, order, positions, normals, ru,
               rv, weight, colors, alpha, small, center, bound, extent, position, normal, cone,
               color, opacity, area, sigma_r2, lod_cov, color_grad, color_detail, root, 0)


# -- the nodes that are not stored ------------------------------------------------------------


@numba.njit(cache=True, nogil=True, inline="always")
def _pair(s, order, positions, normals, ru, rv, weight, colors, alpha, full):
    """The values of a node of the two surfels order[s], order[s + 1]."""
    cx, cy, cz, rad = _sphere(order, s, s + 2, positions, ru, rv)
    return _combine(_surfel_leaf(order[s], positions, normals, ru, rv, weight, colors, alpha),
                    _surfel_leaf(order[s + 1], positions, normals, ru, rv, weight, colors,
                                 alpha),
                    _f32(cx), _f32(cy), _f32(cz), _f32(rad), full)


@numba.njit(cache=True, nogil=True)  # not inlined: see _combine
def small_node(s, m, order, positions, normals, ru, rv, weight, colors, alpha, full):
    """The values (``_combine``'s tuple) of the node of m surfels (m = 2 or 3)
    whose first leaf is s, which the tree does not store: computed as ``build_hierarchy``
    computes a node, by the same functions on its subtree, so bit for bit what the build
    would have stored. full=False leaves out the colour, opacity, gradient, colour detail
    and the cone."""
    if m == 2:
        return _pair(s, order, positions, normals, ru, rv, weight, colors, alpha, full)
    # three surfels: a leaf (the first) and a pair, split as push_children splits
    cx, cy, cz, rad = _sphere(order, s, s + 3, positions, ru, rv)
    return _combine(_surfel_leaf(order[s], positions, normals, ru, rv, weight, colors, alpha),
                    _pair(s + 1, order, positions, normals, ru, rv, weight, colors, alpha, full),
                    _f32(cx), _f32(cy), _f32(cz), _f32(rad), full)


@numba.njit(cache=True, nogil=True)
def attribute_rows(n):
    """Empty attribute arrays (ATTRIBUTES' order) of n rows: where a walk puts a node that
    the tree does not store, to read it as it reads a stored row."""
    f32 = np.float32
    return (np.empty((n, 3), f32), np.empty(n, f32), np.empty(n, f32), np.empty((n, 3), f32),
            np.empty((n, 3), f32), np.empty(n, f32), np.empty((n, 3), f32), np.empty(n, f32),
            np.empty(n, f32), np.empty(n, f32), np.empty((n, 6), f32), np.empty((n, 6), f32),
            np.empty(n, f32))


EXPAND_CHUNK = 4096  # nodes per task of _expand


@numba.njit(cache=True, nogil=True, parallel=True)
def _expand(nodes, start, count, rows, order, positions, normals, ru, rv, weight, colors,
            alpha, center, bound, extent, position, normal, cone, color, opacity, area, sigma_r2,
            lod_cov, color_grad, color_detail, o_center, o_bound, o_extent, o_position, o_normal,
            o_cone, o_color, o_opacity, o_area, o_sigma_r2, o_lod_cov, o_color_grad,
            o_color_detail):
    """Row t of the o_ arrays = inner node nodes[t]: its stored row, or ``small_node``'s."""
    n = nodes.shape[0]
    for c in numba.prange((n + EXPAND_CHUNK - 1) // EXPAND_CHUNK):
        for t in range(c * EXPAND_CHUNK, min(n, (c + 1) * EXPAND_CHUNK)):
            i = nodes[t]
            r = rows[i]
            if r < 0:
                v = small_node(start[i], count[i], order, positions, normals, ru, rv, weight,
                               colors, alpha, True)[:V_GEO]
            else:
                v = load_attributes(r, center, bound, extent, position, normal, cone, color,
                                    opacity, area, sigma_r2, lod_cov, color_grad, color_detail)
            store_attributes(v, t, o_center, o_bound, o_extent, o_position, o_normal, o_cone,
                             o_color, o_opacity, o_area, o_sigma_r2, o_lod_cov, o_color_grad,
                             o_color_detail)


@numba.njit(cache=True, nogil=True)
def node_height(m):
    """The height of a node of m surfels (0: a leaf): ceil(log2 m), as the median split
    halves the count."""
    h = 0
    while m > 1:
        m = (m + 1) // 2
        h += 1
    return h


@numba.njit(cache=True, nogil=True)
def stored_nodes(m, small):
    """How many nodes of a subtree of m surfels the tree stores (those of more than
    ``small`` surfels). The median split leaves nodes of two sizes at each depth, q and
    q + 1: count them level by level."""
    if small == 1:
        return max(m - 1, 0)  # every inner node
    total = 0
    q, n_q, n_q1 = m, 1, 0  # n_q nodes of q surfels, n_q1 of q + 1, at this depth
    while q > small or (n_q1 > 0 and q + 1 > small):
        h = q // 2
        a = b = 0  # the next depth's nodes of h and h + 1 surfels
        if q > small:  # q -> q // 2 and q - q // 2
            total += n_q
            if q % 2 == 0:
                a += 2 * n_q
            else:
                a += n_q
                b += n_q
        if n_q1 > 0 and q + 1 > small:  # q + 1 -> (q + 1) // 2 and the rest
            total += n_q1
            if (q + 1) % 2 == 0:
                b += 2 * n_q1
            else:
                a += n_q1
                b += n_q1
        q, n_q, n_q1 = h, a, b
    return total


@numba.njit(cache=True, nogil=True)
def blocked_layout(n_surfels, small, levels, file_row, child):
    """The blocked layout of a tree's stored rows (``Hierarchy.blocked``): file_row[r] = the
    row in the layout of the stored node whose preorder row is r; child[f] = the layout row
    of the first stored child of the node at layout row f, -1 for none.

    Blocks: the stored nodes at depths [b levels, (b + 1) levels) below one at depth
    b levels (a block root). Within a block the nodes are breadth first (a node's two
    children next to each other); each block is followed by its child blocks' subtrees, left
    to right (the blocks in preorder), so a subtree of m surfels is a run of
    ``stored_nodes(m, small)`` rows from its block root's. The walk's rule follows
    (``child_rows``): a node's children are child[f] and, where both are stored, child[f]
    + 1 within a block or child[f] + stored_nodes(m // 2, small) across a block's edge."""
    width = 1 << levels
    # block roots still to lay out: node, first leaf, count, preorder row, depth, the
    # parent's layout row (-1: none) and whether the root is the parent's first stored child
    blocks = np.empty((64 * width, 7), np.int64)
    queue = np.empty((width, 5), np.int64)  # a block's nodes, breadth first
    roots = np.empty((width, 7), np.int64)  # its child blocks, left to right
    n_blocks = 0
    if n_surfels > small:
        blocks[0, 0], blocks[0, 1], blocks[0, 2], blocks[0, 3] = 0, 0, n_surfels, 0
        blocks[0, 4], blocks[0, 5], blocks[0, 6] = 0, -1, 0
        n_blocks = 1
    next_row = 0
    while n_blocks > 0:
        n_blocks -= 1
        base = next_row
        if blocks[n_blocks, 5] >= 0 and blocks[n_blocks, 6]:
            child[blocks[n_blocks, 5]] = base
        bottom = blocks[n_blocks, 4] + levels - 1  # the block's last depth
        for c in range(5):
            queue[0, c] = blocks[n_blocks, c]
        head, tail, n_roots = 0, 1, 0
        while head < tail:
            i, s, m, r, d = queue[head, 0], queue[head, 1], queue[head, 2], queue[head, 3], \
                queue[head, 4]
            row = base + head
            head += 1
            file_row[r] = row
            child[row] = -1
            h = m // 2
            # the children: (node, first leaf, count, preorder row), stored ones only
            first = True
            for side in range(2):
                if side == 0:
                    ci, cs, cm, cr = i + 1, s, h, r + 1
                else:
                    ci, cs, cm, cr = i + 2 * h, s + h, m - h, r + 1 + stored_nodes(h, small)
                if cm <= small:
                    continue
                if d < bottom:  # in this block, breadth first
                    if first:
                        child[row] = base + tail
                    queue[tail, 0], queue[tail, 1], queue[tail, 2] = ci, cs, cm
                    queue[tail, 3], queue[tail, 4] = cr, d + 1
                    tail += 1
                else:  # a child block's root
                    roots[n_roots, 0], roots[n_roots, 1], roots[n_roots, 2] = ci, cs, cm
                    roots[n_roots, 3], roots[n_roots, 4] = cr, d + 1
                    roots[n_roots, 5], roots[n_roots, 6] = row, 1 if first else 0
                    n_roots += 1
                first = False
        next_row = base + tail
        for j in range(n_roots - 1, -1, -1):  # the leftmost on top: laid out first
            for c in range(7):
                blocks[n_blocks, c] = roots[j, c]
            n_blocks += 1


@numba.njit(cache=True, nogil=True)
def blocked_rows(rows, n_surfels, small, child, levels):
    """``tree_rows``' preorder rows (every node's, -1 where not stored) moved to a blocked
    layout's (``blocked_layout``), by a walk that follows ``child_rows``."""
    out = np.full(rows.shape[0], -1, np.int32)
    if n_surfels <= small:
        return out
    stack = np.empty((128, 5), np.int64)  # node, count, depth, layout row, preorder row
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3], stack[0, 4] = 0, n_surfels, 0, 0, 0
    top = 1
    while top > 0:
        top -= 1
        i, m, d, f, r = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3], \
            stack[top, 4]
        if m <= small:
            continue
        out[i] = f
        h = m // 2
        left, right = child_rows(f, m, d, small, child, levels)
        stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3] = i + 2 * h, m - h, d + 1, right
        stack[top, 4] = r + 1 + stored_nodes(h, small)
        stack[top + 1, 0], stack[top + 1, 1], stack[top + 1, 2] = i + 1, h, d + 1
        stack[top + 1, 3], stack[top + 1, 4] = left, r + 1
        top += 2
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def child_rows(r, m, d, small, child, levels):
    """(left, right): the rows of the children of the stored node at row r (m surfels, depth
    d): in preorder (``child`` empty) r + 1 and r + 1 + the left subtree's stored nodes; in
    a blocked layout (``blocked_layout``) child[r], and child[r] + 1 within a block or + the
    left subtree's stored nodes across a block's edge. A child the tree does not store
    (``small``) gets a row that is never read."""
    h = m // 2
    if child.shape[0] == 0:
        return r + 1, r + 1 + stored_nodes(h, small)
    c = np.int64(child[r])
    if h <= small:  # (only the right child can be stored)
        return c, c
    if (d + 1) % levels != 0:
        return c, c + 1
    return c, c + stored_nodes(h, small)


@numba.njit(cache=True, nogil=True)
def tree_rows(n_surfels, small):
    """(2N - 1,) int32: every node's row in the stored attribute arrays, in preorder; -1 for
    the nodes not stored (leaves, and inner nodes of at most ``small`` surfels)."""
    m_nodes = max(2 * n_surfels - 1, 0)
    rows = np.full(m_nodes, -1, np.int32)
    start, count = tree_shape(n_surfels)
    r = 0
    for i in range(m_nodes):  # preorder: the stored nodes' rows in order
        if count[i] > small:
            rows[i] = r
            r += 1
    return rows
