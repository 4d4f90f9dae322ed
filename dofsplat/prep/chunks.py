"""Points to surfels in chunks: a cloud of any size in bounded memory (issue 50).

``points_to_surfels`` prepares a cloud of more than ``pointcloud.CHUNK_POINTS`` distinct
points here. Its steps are local: a point's normal, its move onto its plane, its density,
its radius and its normalisation weight depend on its neighbours and theirs, a few spacings
away. So the cloud is cut into chunks of at most that many points (median splits along the
longest axis, the shape of the LOD tree's top, ``chunk_order``), and each chunk is prepared
by the in-memory steps (``pointcloud.surfel_stages``) together with a *halo*: the points
within ``HALO_SPACINGS`` x its median distance to the k-th neighbour of its box. The chunk
keeps its own points' results, computed from neighbourhoods that the halo holds whole;
memory is one chunk's and its halo's at a time, beside the cloud's own arrays (about 100
bytes a point: the positions read, the colours, the surfels written, the radii before the
cap). Each chunk's steps are a function of the cloud and the chunk alone (``surfel_chunk``,
``weight_chunk``), so they may run on Dask workers (``on_cluster``) with the same result.

Three steps are not local, and are joined across chunks instead:

* **orientation.** Within a chunk the normals are signed consistently over each component
  of its neighbour graph and each component gets ``outward_votes``' tally, as in memory. A
  surface that crosses a chunk's border is then two components; the halo says how they
  agree: a halo point is another chunk's own point, signed by both, so each pair of
  components that share points gets the sum of their signs' agreements there. A maximum
  spanning forest over those sums (``join_orientation``: Kruskal, largest agreement first,
  with the parity of each component against its tree's root) makes each surface one
  group; the group's views are summed in its root's sign and decided as ``outward_votes``
  decides a component's (``rules.sheet_votes`` for a tie), or it keeps a given normal's.
* **the radii's outlier cap** (``rules.outlier_cap``, a multiple of the whole cloud's
  median): each chunk keeps its radii under the cluster cap alone, and the minimum with the
  outlier cap is taken after the chunks, which is the in-memory radius (the minima commute).
* **the normalisation's level** (``normalise.rendered_level``, one factor for the model):
  read on the chunks' own surfels (at most ``LEVEL_CHUNKS`` of them, spread over the
  order), and their levels averaged, weighted by the chunks' points.

So the positions, normals, radii and uncalibrated weights are the in-memory preparation's
bit for bit wherever the neighbourhoods a point reads fit in its chunk's halo (all but a
handful of lone points on the 3.7 M-point synthetic scan), and the level is read on the
chunks (0.57 % lower there; docs/outofcore.md). ``tests/test_chunks.py`` checks both.
"""

from __future__ import annotations

import contextlib
import sys
from dataclasses import replace

from ..jit import numba
import numpy as np

from ..surfels import Surfels
from .rules import TIE_FRACTION, outlier_cap, sheet_votes

HALO_SPACINGS = 8.0  # a chunk's halo reaches this x its median distance to the k-th neighbour
HALO_SAMPLE = 4096  # chunk points whose k-th neighbour sets that distance
LEVEL_CHUNKS = 4  # chunks on which the normalisation's level is read


_CLIENT = None  # a Dask client whose workers take the chunks (``on_cluster``), or None


@contextlib.contextmanager
def on_cluster(client):
    """Within this block, the chunks' steps run on the workers of ``client`` (a
    ``dask.distributed.Client``; None: in this process): ``dofsplat prepare --workers N``
    or ``--scheduler ADDRESS``. The surfels are the same, each chunk's steps being a
    function of the cloud and the chunk alone."""
    global _CLIENT
    previous, _CLIENT = _CLIENT, client
    try:
        yield
    finally:
        _CLIENT = previous


def each_chunk(fn, shared: tuple, chunk_args):
    """fn(*shared, *args) for each chunk's args, in order, one at a time: in this process,
    or on the cluster's workers (``on_cluster``: shared sent once to each, the chunks
    submitted together and their results taken in order, each let go when read)."""
    if _CLIENT is None:
        for args in chunk_args:
            yield fn(*shared, *args)
        return
    remote = [_CLIENT.scatter(x, broadcast=True) if isinstance(x, (np.ndarray, Surfels))
              else x for x in shared]
    futures = [_CLIENT.submit(fn, *remote, *args, pure=False) for args in chunk_args]
    for i, future in enumerate(futures):
        yield future.result()
        futures[i] = None
        future.release()


def chunked_surfels(stages, pts: np.ndarray, cols, nrm, vp, *, k: int, smooth: bool,
                    normalise: str, chunk_points: int, progress: bool, source: str) -> Surfels:
    """``points_to_surfels`` (which see) of points without duplicates, chunk by chunk (the
    module docstring): Surfels. stages: ``pointcloud.surfel_stages``, each chunk's steps
    (passed in: ``pointcloud`` calls this module); cols (N, 3) the points' colours. Each
    chunk is ``surfel_chunk``'s and then ``weight_chunk``'s, functions of the cloud and the
    chunk alone (the joins run after them), so the result does not depend on the order the
    chunks are taken in."""
    n = len(pts)
    order, bounds = chunk_order(pts, chunk_points)
    out_pos = np.empty((n, 3), np.float32)
    out_nrm = np.empty((n, 3), np.float32)
    # each point's component, numbered over all chunks
    label = np.full(n, -1, np.int32 if n < 2 ** 31 else np.int64)
    # the radii before the outlier cap, whose median is the whole cloud's: r_area, r_area
    # under the cluster cap, the radius under it (``pointcloud.surfel_radii``)
    r_area = np.empty(n, np.float64)
    r_capped = np.empty(n, np.float64)
    r_radius = np.empty(n, np.float64)
    tallies, fixed, halos, boxes = [], [], [], []
    n_comp = 0
    with _chunk_bar(2 * n if normalise != "none" else n, source, progress) as bar:
        chunk_args = ((order[a:b], k, smooth) for a, b in bounds)
        for (a, b), c in zip(bounds, each_chunk(surfel_chunk, (stages, pts, nrm, vp),
                                                chunk_args)):
            own = order[a:b]
            boxes.append(c["box"])
            out_pos[own], out_nrm[own] = c["positions"], c["normals"]
            r_area[own], r_capped[own], r_radius[own] = c["r_area"], c["r_capped"], c["radius"]
            if c["label"] is not None:
                label[own] = c["label"] + n_comp
                tallies.append(c["tally"])
                fixed.append(c["fixed"])
                halos.append((c["halo_rows"], c["halo_label"] + n_comp, c["halo_normals"]))
                n_comp += len(c["fixed"])
            del c
            bar.update(b - a)
        if tallies:
            # how each chunk's components agree with the others' at the points they share
            shared = [agreements(comp, label[rows], nm, out_nrm[rows])
                      for rows, comp, nm in halos]
            del halos
            flip = join_orientation([np.concatenate([t[i] for t in tallies]) for i in range(4)],
                                    np.concatenate(fixed), shared)
            out_nrm[flip[label]] *= -1.0
        del label
        # the outlier cap, as ``surfel_radii`` takes it: min(radius, cap) is its radius
        # under min(cluster cap, cap), and the area's the same (the minima commute)
        cap = outlier_cap(r_area)
        del r_area
        np.minimum(r_radius, cap, out=r_radius)
        np.minimum(r_capped, cap, out=r_capped)
        out_rad = r_radius.astype(np.float32)
        out_w = ((r_capped / r_radius) ** 2).astype(np.float32)
        del r_radius, r_capped
        surfels = Surfels(positions=out_pos, normals=out_nrm, radius=out_rad, colors=cols,
                          weight=out_w)
        del out_pos, out_nrm, out_rad, out_w
        if normalise == "none":
            return surfels
        weight = np.empty(n, np.float32)
        levels = []
        reads = set(np.linspace(0, len(bounds) - 1, min(LEVEL_CHUNKS, len(bounds)))
                    .round().astype(int).tolist())
        chunk_args = ((order[a:b], boxes[i], normalise, i in reads)
                      for i, (a, b) in enumerate(bounds))
        for (a, b), (w, level) in zip(bounds, each_chunk(weight_chunk, (surfels, pts),
                                                         chunk_args)):
            weight[order[a:b]] = w
            if level is not None:
                levels.append((level, b - a))
            bar.update(b - a)
    level = sum(v * m for v, m in levels) / sum(m for _, m in levels)
    return replace(surfels, weight=(weight / level).astype(np.float32))


def surfel_chunk(stages, pts, nrm, vp, own: np.ndarray, k: int, smooth: bool) -> dict:
    """One chunk's steps 1-4 (stages: ``pointcloud.surfel_stages``) on its points (own:
    their rows, sorted) and its halo: a dict of its box widened by the halo (``halo_box``),
    its points' positions, normals (as propagated, before the votes), radius, r_area and
    r_capped (before the outlier cap), label (their components, or None where the normals
    were all given or turned towards vp), and the components' tally and fixed, and the
    halo's rows, components and normals (for ``agreements``)."""
    box = halo_box(pts, own, k)
    ids = rows_in_box(pts, *box)
    mine = np.searchsorted(ids, own)
    sub_vp = vp if vp is None or vp.ndim == 1 else vp[ids]
    p, nm, rad, _, orientation, (area, limit) = stages(
        pts[ids], None if nrm is None else nrm[ids], sub_vp, k, smooth, vote=False,
        outliers=False)
    out = {"box": box, "positions": p[mine], "normals": nm[mine], "radius": rad[mine],
           "r_area": area[mine], "r_capped": np.minimum(area[mine], limit[mine]),
           "label": None}
    if orientation is not None:
        lab, _, tally, has_fixed = orientation
        halo = np.ones(len(ids), bool)
        halo[mine] = False
        out.update(label=lab[mine], tally=tally, fixed=has_fixed, halo_rows=ids[halo],
                   halo_label=lab[halo], halo_normals=nm[halo].astype(np.float32))
    return out


def weight_chunk(surfels: Surfels, pts, own: np.ndarray, box, method: str, level: bool):
    """One chunk's normalisation weights (``normalise.normalise`` by method, uncalibrated)
    with its halo (box: ``surfel_chunk``'s, the same rows): (its points' weights, and
    ``rendered_level`` of them where level, else None)."""
    from .normalise import normalise as normalise_surfels, rendered_level

    ids = rows_in_box(pts, *box)
    mine = np.searchsorted(ids, own)
    sub = normalise_surfels(surfels.subset(ids), method, calibrate=False, progress=False)
    return sub.weight[mine], (rendered_level(sub.subset(mine), progress=False) if level
                              else None)


def chunk_order(pts: np.ndarray, chunk_points: int):
    """(order (N,) int64, bounds [(a, b), ...]): the points cut into chunks of at most
    chunk_points by median splits along the longest axis of each part's box, as the LOD
    tree splits (m into m // 2 and m - m // 2); chunk c is order[a:b], its rows sorted. The
    same points give the same chunks (``np.argpartition`` on the same values)."""
    n = len(pts)
    order = np.arange(n, dtype=np.int64)
    bounds = []
    stack = [(0, n)]
    while stack:
        a, b = stack.pop()
        if b - a <= chunk_points:
            order[a:b].sort()
            bounds.append((a, b))
            continue
        part = order[a:b]
        p = pts[part]
        axis = int(np.argmax(p.max(axis=0) - p.min(axis=0)))
        half = (b - a) // 2
        order[a:b] = part[np.argpartition(p[:, axis], half, kind="introselect")]
        del p
        stack.append((a + half, b))
        stack.append((a, a + half))
    return order, bounds


def halo_box(pts: np.ndarray, own: np.ndarray, k: int):
    """(lo, hi) (3,) each: the box of a chunk's points (own) widened by its halo,
    ``HALO_SPACINGS`` x the median distance to the k-th neighbour of up to ``HALO_SAMPLE``
    of its points."""
    from scipy.spatial import cKDTree

    p = pts[own]
    lo, hi = p.min(axis=0), p.max(axis=0)
    step = max(1, len(own) // HALO_SAMPLE)
    kk = min(k, len(own) - 1)
    d = cKDTree(p).query(p[::step], kk + 1, workers=-1)[0][:, kk]
    del p
    margin = HALO_SPACINGS * float(np.median(d))
    return lo - margin, hi + margin


def rows_in_box(pts: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The sorted rows of the points within the box [lo, hi]: a chunk's own and its halo
    (``halo_box``)."""
    inside = np.empty(len(pts), np.bool_)
    _in_box(pts, lo, hi, inside)
    return np.flatnonzero(inside)


@numba.njit(cache=True, nogil=True, parallel=True)
def _in_box(pts, lo, hi, out):
    """out[i] = whether point i lies in the box [lo, hi] (each axis, closed)."""
    for i in numba.prange(pts.shape[0]):
        out[i] = (lo[0] <= pts[i, 0] <= hi[0] and lo[1] <= pts[i, 1] <= hi[1]
                  and lo[2] <= pts[i, 2] <= hi[2])


def agreements(mine: np.ndarray, theirs: np.ndarray, normals: np.ndarray,
               their_normals: np.ndarray):
    """(pairs (P, 2) int64, sums (P,)): how a chunk's components agree with another's at
    the points they share (``join_orientation``): mine, theirs (M,) the points' components
    in this chunk and in their own; normals, their_normals (M, 3) their normals there; each
    pair of components once (the smaller first), its points' signs of n . n' summed."""
    a, b = np.minimum(mine, theirs), np.maximum(mine, theirs)
    sign = np.sign(np.sum(np.asarray(normals, np.float64) * their_normals, axis=1))
    pairs, inverse = np.unique(np.stack([a, b], axis=1).astype(np.int64), axis=0,
                               return_inverse=True)
    return pairs, np.bincount(inverse.ravel(), sign, len(pairs))


def join_orientation(tallies, fixed: np.ndarray, shared) -> np.ndarray:
    """(n_comp,) bool: which of the chunks' components to turn over (the module docstring).

    tallies: ``outward_votes``' (votes, raw votes, mass, mean normals) (tally=True) of each
    component, (n_comp,) each but the means (n_comp, 3); fixed: (n_comp,) whether it holds
    a given normal; shared: ``agreements`` of each chunk."""
    decided, raw, mass, mean = tallies
    n_comp = len(decided)
    pairs = np.concatenate([p for p, _ in shared]) if shared else np.zeros((0, 2), np.int64)
    sums = np.concatenate([t for _, t in shared]) if shared else np.zeros(0)
    key = pairs[:, 0] * n_comp + pairs[:, 1]
    keys, inverse = np.unique(key, return_inverse=True)
    total = np.bincount(inverse.ravel(), sums, len(keys))
    strongest = np.lexsort((keys, -np.abs(total)))  # largest agreement first, ties by key
    parent = np.arange(n_comp)
    parity = np.zeros(n_comp, np.int64)  # against the parent: 1 where opposite
    for e in strongest:
        if total[e] == 0:
            break
        u, v = int(keys[e] // n_comp), int(keys[e] % n_comp)
        ru, pu = _root(parent, parity, u)
        rv, pv = _root(parent, parity, v)
        if ru == rv:
            continue
        parent[rv] = ru
        parity[rv] = pu ^ pv ^ (1 if total[e] < 0 else 0)
    roots = np.empty(n_comp, np.int64)
    against = np.empty(n_comp, np.int64)  # each component's parity against its root
    for i in range(n_comp):
        roots[i], against[i] = _root(parent, parity, i)
    # each group's views summed in its root's sign, and decided as ``outward_votes``
    # decides a component's: a tie by the mean normal, none seen by the chunks' decisions
    sign = 1.0 - 2.0 * against
    group_vote = np.bincount(roots, sign * raw, n_comp)
    group_mass = np.bincount(roots, mass, n_comp)
    group_mean = np.stack([np.bincount(roots, sign * mean[:, a], n_comp) for a in range(3)],
                          axis=1)
    unclear = (np.abs(group_vote) < TIE_FRACTION * group_mass) & (group_mass > 0)
    group_vote[unclear] = sheet_votes(group_mean)[unclear]
    unseen = group_vote == 0
    group_vote[unseen] = np.bincount(roots, sign * decided, n_comp)[unseen]
    group_fixed = np.bincount(roots, fixed, n_comp) > 0
    turn_root = (group_vote < 0) & ~group_fixed
    flip = (against == 1) ^ turn_root[roots]
    # a group that holds given normals keeps them as they are: its other components take
    # the sign of the first such (as the in-memory propagation carries theirs)
    if group_fixed.any():
        first_fixed = np.full(n_comp, -1, np.int64)
        for i in np.flatnonzero(fixed)[::-1]:
            first_fixed[roots[i]] = i
        ref = first_fixed[roots]
        has = ref >= 0
        flip[has] = against[has] != against[ref[has]]
        flip[fixed] = False
    return flip


def _root(parent, parity, i):
    """(root, parity of i against it) in ``join_orientation``'s forest."""
    p = 0
    while parent[i] != i:
        p ^= int(parity[i])
        i = int(parent[i])
    return i, p


def _chunk_bar(total: int, source: str, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=f"{source}: points to surfels in chunks", unit="pt",
                unit_scale=True, file=sys.stderr, disable=not (enabled and sys.stderr.isatty()),
                leave=False)
