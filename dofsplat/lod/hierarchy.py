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
surfel, and the tree stores nothing else for it: its attributes are its surfel's. The
attributes below are stored for the N - 1 inner nodes only, in preorder, so inner node i is
row ``i - start[i]`` (the leaves before i in preorder are exactly the surfels before its
first, start[i] of them; ``Hierarchy.row``). Each inner node carries what the per-frame
selection and the splatting need (Sections 5.3 and 6.2; docs/maths.md, "Level of detail"):

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
* ``level``: the node's height (0 at the leaves), for ``--show-lod``.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, fields
from pathlib import Path

import numba
import numpy as np

from ..errors import DofsplatError
from ..splat.ewa import tangent_frame
from ..surfels import Surfels

# a node whose unit normals spread by more than this in one component (1.4 ~ sqrt 2: normals
# about 90 degrees apart) is split by normal, not by position (docs/maths.md)
NORMAL_SPREAD = 1.4
FORMAT_VERSION = 6  # bump when the build or the stored arrays change: old files are rebuilt


@dataclass
class Hierarchy:
    """The flat-array LOD tree over a surfel model (M = 2N - 1 nodes for N surfels, K = N - 1
    of them inner nodes).

    order:    (N,) int32, surfel indices in leaf order
    The rest have a row per inner node, node i's row being ``row(i)`` = i - start[i]:
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
    level:    (K,) int8, height above the leaves
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
    level: np.ndarray
    fingerprint: str

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
        """Number of levels (the root's height + 1)."""
        return int(self.level[0]) + 1 if self.level.size else 1

    def row(self, node):
        """The row of inner node(s) ``node`` in the attribute arrays: node - start[node]."""
        return node - self.start[node]

    def children(self, node: int) -> tuple[int, int] | None:
        """(left, right) node indices, or None for a leaf."""
        m = int(self.count[node])
        if m == 1:
            return None
        return node + 1, node + 2 * (m // 2)

    def nbytes(self) -> int:
        return sum(getattr(self, f.name).nbytes for f in fields(self) if f.name != "fingerprint")

    # -- persistence -----------------------------------------------------------------

    def save(self, path) -> Path:
        """Write the tree to an ``.npz`` file (atomically); returns the path."""
        from ..io.images import atomic_write

        path = Path(path)
        arrays = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "fingerprint"}

        def write(tmp):
            with open(tmp, "wb") as fh:
                np.savez(fh, fingerprint=np.array(self.fingerprint),
                         version=np.array(FORMAT_VERSION), **arrays)

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
                data = {f.name: z[f.name] for f in fields(cls) if f.name != "fingerprint"}
                fp = str(z["fingerprint"])
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError) as exc:
            raise DofsplatError(f"{path}: not a dofsplat LOD file ({exc})") from None
        if surfels is not None and fp != fingerprint(surfels):
            return None
        tree = cls(fingerprint=fp, **data)
        if surfels is not None and tree.n_surfels != len(surfels):
            return None
        return tree


def fingerprint(surfels: Surfels) -> str:
    """A hash of every surfel array that the tree depends on (changes when the model does)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(f"v{FORMAT_VERSION} n{len(surfels)}".encode())
    for a in (surfels.positions, surfels.normals, surfels.radius, surfels.colors,
              surfels.opacity, surfels.tangent, surfels.radius_v, surfels.weight):
        h.update(b"-" if a is None else np.ascontiguousarray(a).view(np.uint8).data)
    return h.hexdigest()


def build_hierarchy(surfels: Surfels, progress: bool = False) -> Hierarchy:
    """Build the LOD tree over ``surfels`` (O(N log N); a few seconds for a million surfels)."""
    n = len(surfels)
    if n >= 1 << 30:
        raise DofsplatError(f"{n} surfels is more than the LOD tree's int32 indices allow")
    t0 = time.perf_counter()
    positions = surfels.positions
    ru = surfels.radius
    rv = surfels.radius_v if surfels.is_elliptical else surfels.radius
    weight = surfels.weight if surfels.weight is not None else np.ones(n, np.float32)

    # top down: median splits, level by level (each level's nodes in parallel)
    keys = np.ascontiguousarray(np.hstack([positions, surfels.normals]), np.float32)
    m_nodes = 2 * n - 1
    order = np.arange(n, dtype=np.int32)
    start = np.empty(m_nodes, np.int32)
    count = np.empty(m_nodes, np.int32)
    ids = np.zeros(1, np.int64)
    starts = np.zeros(1, np.int64)
    counts = np.full(1, n, np.int64)
    bar = _progress(progress, n)
    while ids.size:
        start[ids] = starts
        count[ids] = counts
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

    # bottom up: spheres, cones and prefiltered attributes
    center = np.empty((m_nodes, 3), np.float32)
    bound = np.empty(m_nodes, np.float32)
    extent = np.empty(m_nodes, np.float32)
    position = np.empty((m_nodes, 3), np.float32)
    normal = np.empty((m_nodes, 3), np.float32)
    cone = np.empty(m_nodes, np.float32)
    color = np.empty((m_nodes, 3), np.float32)
    opacity = np.empty(m_nodes, np.float32)
    area = np.empty(m_nodes, np.float32)
    sigma_r2 = np.empty(m_nodes, np.float32)
    lod_cov = np.empty((m_nodes, 6), np.float32)
    color_grad = np.empty((m_nodes, 6), np.float32)
    level = np.empty(m_nodes, np.int8)
    _node_spheres(order, start, count, positions, ru, rv, center, extent)
    bound[:] = extent
    _aggregate(order, start, count, positions, surfels.normals, ru, rv, weight,
               surfels.colors, surfels.opacity, center, bound, position, normal, cone,
               color, opacity, area, sigma_r2, lod_cov, color_grad, level)
    # keep the inner nodes' rows only (a leaf is its surfel): in preorder, so node i's row
    # is i - start[i]
    inner = count > 1
    center, bound, extent, position, normal, cone, color, opacity, area, sigma_r2, lod_cov, \
        color_grad, level = (a[inner] for a in (center, bound, extent, position, normal, cone,
                                                color, opacity, area, sigma_r2, lod_cov,
                                                color_grad, level))
    tree = Hierarchy(order=order, center=center, bound=bound,
                     extent=extent,
                     position=position, normal=normal, cone=cone, color=color,
                     opacity=opacity, area=area, sigma_r2=sigma_r2, lod_cov=lod_cov,
                     color_grad=color_grad, level=level,
                     fingerprint=fingerprint(surfels))
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


@numba.njit(cache=True, nogil=True, parallel=True)
def _node_spheres(order, start, count, positions, ru, rv, center, bound):
    """Each node's sphere: centred on its surfels' bounding box, just containing their disks."""
    for i in numba.prange(count.shape[0]):
        s = start[i]
        e = s + count[i]
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
        center[i, 0], center[i, 1], center[i, 2] = cx, cy, cz
        bound[i] = rad


@numba.njit(cache=True, nogil=True)
def _aggregate(order, start, count, positions, normals, ru, rv, weight, colors, alpha,
               center, bound, position, normal, cone, color, opacity, area, sigma_r2, lod_cov,
               color_grad, level):
    """Fill the node arrays, children before parents (reverse preorder)."""
    m_nodes = count.shape[0]
    # geometric area of each node (r_u r_v summed, no normalisation weights): weights sigma_r2
    geo = np.empty(m_nodes, np.float64)
    # area-weighted mean position and covariance of the node's surfels, in float64
    mean = np.empty((m_nodes, 3), np.float64)
    cov = np.empty((m_nodes, 6), np.float64)
    # area-weighted mean colour and colour-position covariance (channel x world axis)
    cmean = np.empty((m_nodes, 3), np.float64)
    ccov = np.empty((m_nodes, 9), np.float64)
    for i in range(m_nodes - 1, -1, -1):
        m = count[i]
        if m == 1:
            k = order[start[i]]
            a_geo = np.float64(ru[k]) * np.float64(rv[k])
            geo[i] = a_geo
            area[i] = a_geo * weight[k]
            for d in range(3):
                position[i, d] = positions[k, d]
                normal[i, d] = normals[k, d]
                color[i, d] = colors[k, d]
            cone[i] = 0.0
            opacity[i] = alpha[k]
            sigma_r2[i] = 0.25 * a_geo
            for d in range(3):
                mean[i, d] = positions[k, d]
                cmean[i, d] = colors[k, d]
            for d in range(6):
                cov[i, d] = 0.0
                lod_cov[i, d] = 0.0
                color_grad[i, d] = 0.0
            for d in range(9):
                ccov[i, d] = 0.0
            level[i] = 0
            continue
        l = i + 1
        r = i + 2 * (m // 2)
        al, ar = np.float64(area[l]), np.float64(area[r])
        a = al + ar
        # area-weighted means; equal weights if both children carry no area
        if a > 0.0:
            fl, fr = al / a, ar / a
        else:
            fl = fr = 0.5
        area[i] = a
        opacity[i] = fl * opacity[l] + fr * opacity[r]
        for d in range(3):
            color[i, d] = fl * color[l, d] + fr * color[r, d]
        gl, gr = geo[l], geo[r]
        g = gl + gr
        geo[i] = g
        sigma_r2[i] = (gl * sigma_r2[l] + gr * sigma_r2[r]) / g
        # parallel-axis combination of the children's moments
        for d in range(3):
            mean[i, d] = fl * mean[l, d] + fr * mean[r, d]
            position[i, d] = mean[i, d]
        d0l, d1l, d2l = mean[l, 0] - mean[i, 0], mean[l, 1] - mean[i, 1], mean[l, 2] - mean[i, 2]
        d0r, d1r, d2r = mean[r, 0] - mean[i, 0], mean[r, 1] - mean[i, 1], mean[r, 2] - mean[i, 2]
        cov[i, 0] = fl * (cov[l, 0] + d0l * d0l) + fr * (cov[r, 0] + d0r * d0r)
        cov[i, 1] = fl * (cov[l, 1] + d0l * d1l) + fr * (cov[r, 1] + d0r * d1r)
        cov[i, 2] = fl * (cov[l, 2] + d0l * d2l) + fr * (cov[r, 2] + d0r * d2r)
        cov[i, 3] = fl * (cov[l, 3] + d1l * d1l) + fr * (cov[r, 3] + d1r * d1r)
        cov[i, 4] = fl * (cov[l, 4] + d1l * d2l) + fr * (cov[r, 4] + d1r * d2r)
        cov[i, 5] = fl * (cov[l, 5] + d2l * d2l) + fr * (cov[r, 5] + d2r * d2r)
        for d in range(6):
            lod_cov[i, d] = 3.0 * cov[i, d]
        level[i] = max(level[l], level[r]) + 1
        for c in range(3):
            cmean[i, c] = fl * cmean[l, c] + fr * cmean[r, c]
            el, er = cmean[l, c] - cmean[i, c], cmean[r, c] - cmean[i, c]
            ccov[i, 3 * c] = fl * (ccov[l, 3 * c] + el * d0l) + fr * (ccov[r, 3 * c] + er * d0r)
            ccov[i, 3 * c + 1] = fl * (ccov[l, 3 * c + 1] + el * d1l) \
                + fr * (ccov[r, 3 * c + 1] + er * d1r)
            ccov[i, 3 * c + 2] = fl * (ccov[l, 3 * c + 2] + el * d2l) \
                + fr * (ccov[r, 3 * c + 2] + er * d2r)

        # normal: area-weighted mean; the cone must contain both children's cones
        nx = fl * normal[l, 0] + fr * normal[r, 0]
        ny = fl * normal[l, 1] + fr * normal[r, 1]
        nz = fl * normal[l, 2] + fr * normal[r, 2]
        nn = math.sqrt(nx * nx + ny * ny + nz * nz)
        if nn < 1e-6:  # opposite normals: no meaningful mean, no culling
            normal[i, 0], normal[i, 1], normal[i, 2] = normal[l, 0], normal[l, 1], normal[l, 2]
            cone[i] = math.pi
        else:
            nx, ny, nz = nx / nn, ny / nn, nz / nn
            normal[i, 0], normal[i, 1], normal[i, 2] = nx, ny, nz
            wide = 0.0
            for c in (l, r):
                dot = nx * normal[c, 0] + ny * normal[c, 1] + nz * normal[c, 2]
                ang = math.acos(min(1.0, max(-1.0, dot))) + cone[c]
                wide = max(wide, ang)
            # float32 storage: round the angle up a little so the cone stays conservative
            cone[i] = min(math.pi, wide * (1.0 + 1e-6) + 1e-6)

        # the colour gradient in the node's tangent frame, from its normal as stored (float32),
        # so that the projection derives the same frame
        ux, uy, uz, vx, vy, vz = tangent_frame(np.float64(normal[i, 0]), np.float64(normal[i, 1]),
                                               np.float64(normal[i, 2]))
        for c in range(3):
            gx, gy, gz = ccov[i, 3 * c], ccov[i, 3 * c + 1], ccov[i, 3 * c + 2]
            color_grad[i, 2 * c] = gx * ux + gy * uy + gz * uz
            color_grad[i, 2 * c + 1] = gx * vx + gy * vy + gz * vz

        # the sphere (centred on the node's bounding box, _node_spheres) must also contain
        # both children's spheres; the extra slack covers the float32 rounding of centres
        cx, cy, cz = np.float64(center[i, 0]), np.float64(center[i, 1]), np.float64(center[i, 2])
        rad = np.float64(bound[i])
        for c in (l, r):
            dx = np.float64(center[c, 0]) - cx
            dy = np.float64(center[c, 1]) - cy
            dz = np.float64(center[c, 2]) - cz
            rad = max(rad, math.sqrt(dx * dx + dy * dy + dz * dz) + bound[c])
        bound[i] = rad * (1.0 + 1e-6) + 4e-7 * (abs(cx) + abs(cy) + abs(cz))
