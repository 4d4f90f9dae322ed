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
cap), which for a cloud on disk (``cloudfile``) are files in a work folder instead. Each chunk's steps are a function of the cloud and the chunk alone (``surfel_chunk``,
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
import os
import sys
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..surfels import Surfels
from .cloudfile import BLOCK, CloudFile, SurfelFiles, array_rows_in_box, mapped, release
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
              else x for x in shared]  # (a CloudFile or SurfelFiles goes as its paths)
    futures = [_CLIENT.submit(fn, *remote, *args, pure=False) for args in chunk_args]
    for i, future in enumerate(futures):
        yield future.result()
        futures[i] = None
        future.release()


def chunked_surfels(stages, pts, cols, nrm, vp, *, k: int, smooth: bool, normalise: str,
                    chunk_points: int, progress: bool, source: str, store=None) -> Surfels:
    """``points_to_surfels`` (which see) of points without duplicates, chunk by chunk (the
    module docstring): Surfels. stages: ``pointcloud.surfel_stages``, each chunk's steps
    (passed in: ``pointcloud`` calls this module); pts (N, 3) float64, or a
    ``cloudfile.CloudFile`` (the cloud on disk, its chunks its own); cols (N, 3) the points'
    colours. Each chunk is ``surfel_chunk``'s and then ``weight_chunk``'s, functions of the
    cloud and the chunk alone (the joins run after them), so the result does not depend on
    the order the chunks are taken in.

    store: a folder, or None. Given, the arrays over all points are memory maps of files
    there, written chunk by chunk and unmapped after each (the process's memory then holds
    a chunk's), and each chunk's other results are kept as it completes, so that a run in
    the same folder after an interruption takes the chunks done from it."""
    n = len(pts)
    if isinstance(pts, CloudFile):
        bounds = pts.bounds
        rows = lambda a, b: np.arange(a, b, dtype=np.int64)  # noqa: E731
    else:
        order, bounds = chunk_order(pts, chunk_points)
        rows = lambda a, b: order[a:b]  # noqa: E731
    kept = _Kept(store)
    if store is None:
        new = lambda name, shape, dtype: np.empty(shape, dtype)  # noqa: E731
    else:
        new = lambda name, shape, dtype: mapped(store, name, dtype, shape,  # noqa: E731
                                                fresh=kept.fresh)
    out_pos = new("positions.f32", (n, 3), np.float32)
    # the normals as each chunk propagated them, before the orientation's join
    chunk_nrm = new("chunk_normals.f32", (n, 3), np.float32)
    # each point's component, numbered over all chunks (-1: none)
    label = new("label", n, np.int32 if n < 2 ** 31 else np.int64)
    if kept.fresh:
        label[:] = -1
    # the radii before the outlier cap, whose median is the whole cloud's: r_area, r_area
    # under the cluster cap, the radius under it (``pointcloud.surfel_radii``)
    r_area = new("r_area.f64", n, np.float64)
    r_capped = new("r_capped.f64", n, np.float64)
    r_radius = new("r_radius.f64", n, np.float64)
    big = (out_pos, chunk_nrm, label, r_area, r_capped, r_radius)
    tallies, fixed, halos, boxes = [], [], [], []
    n_comp = 0
    with _chunk_bar(2 * n if normalise != "none" else n, source, progress) as bar:
        stored = kept.read_all("surfels", len(bounds))
        todo = [i for i in range(len(bounds)) if i not in stored]
        computed = each_chunk(surfel_chunk, (stages, pts, nrm, vp),
                              ((rows(*bounds[i]), k, smooth) for i in todo))
        for i, (a, b) in enumerate(bounds):
            own = rows(a, b)
            c = stored.pop(i, None)
            if c is None:
                c = next(computed)
                out_pos[own], chunk_nrm[own] = c["positions"], c["normals"]
                r_area[own], r_capped[own] = c["r_area"], c["r_capped"]
                r_radius[own] = c["radius"]
                if c["label"] is not None:
                    label[own] = c["label"] + n_comp
                release(*big)
                kept.write("surfels", i, {key: v for key, v in c.items() if key not in
                                          ("positions", "normals", "r_area", "r_capped",
                                           "radius", "label")} | {"labelled": c["label"]
                                                                  is not None})
            boxes.append(c["box"])
            if c["labelled"] if "labelled" in c else c["label"] is not None:
                tallies.append(c["tally"])
                fixed.append(c["fixed"])
                halos.append((c["halo_rows"], c["halo_label"] + n_comp, c["halo_normals"]))
                n_comp += len(c["fixed"])
            del c
            bar.update(b - a)
        computed.close()  # (the cluster lets go of what it was sent for these)
        # (into arrays of their own where kept, so that a run resumed repeats these steps)
        out_nrm = chunk_nrm if store is None else new("normals.f32", (n, 3), np.float32)
        flip = np.zeros(1, bool)
        if tallies:
            # how each chunk's components agree with the others' at the points they share
            shared = [agreements(comp, label[rows_], nm, chunk_nrm[rows_])
                      for rows_, comp, nm in halos]
            del halos
            flip = join_orientation([np.concatenate([t[i] for t in tallies]) for i in range(4)],
                                    np.concatenate(fixed), shared)
        for s in range(0, n, BLOCK):
            part = np.array(chunk_nrm[s:s + BLOCK])
            lab = label[s:s + BLOCK]
            part[flip[lab] & (lab >= 0)] *= -1.0
            out_nrm[s:s + BLOCK] = part
        release(out_nrm, chunk_nrm, label)
        del label, chunk_nrm
        # the outlier cap, as ``surfel_radii`` takes it: min(radius, cap) is its radius
        # under min(cluster cap, cap), and the area's the same (the minima commute)
        cap = outlier_cap(r_area)
        del r_area
        out_rad = new("radius.f32", n, np.float32)
        out_w = new("area_weight.f32", n, np.float32)
        for s in range(0, n, BLOCK):
            radius = np.minimum(r_radius[s:s + BLOCK], cap)
            out_rad[s:s + BLOCK] = radius
            out_w[s:s + BLOCK] = (np.minimum(r_capped[s:s + BLOCK], cap) / radius) ** 2
        release(out_rad, out_w)
        del r_radius, r_capped
        surfels = Surfels(positions=out_pos, normals=out_nrm, radius=out_rad, colors=cols,
                          weight=out_w)
        del out_pos, out_nrm, out_rad, out_w
        if normalise == "none":
            return surfels
        raw_weight = new("raw_weight.f32", n, np.float32)
        levels = []
        reads = set(np.linspace(0, len(bounds) - 1, min(LEVEL_CHUNKS, len(bounds)))
                    .round().astype(int).tolist())
        stored = kept.read_all("weights", len(bounds))
        todo = [i for i in range(len(bounds)) if i not in stored]
        target = surfels
        if store is not None and _CLIENT is not None and isinstance(cols, np.memmap):
            # the workers read the surfels from the files (on this file system) rather than
            # being sent them whole
            target = SurfelFiles({"positions": Path(store) / "positions.f32",
                                  "normals": Path(store) / "normals.f32",
                                  "radius": Path(store) / "radius.f32",
                                  "colors": cols.filename,
                                  "weight": Path(store) / "area_weight.f32"}, n,
                                 surfels.material)
        computed = each_chunk(weight_chunk, (target, pts),
                              ((rows(*bounds[i]), boxes[i], normalise, i in reads)
                               for i in todo))
        for i, (a, b) in enumerate(bounds):
            c = stored.pop(i, None)
            if c is None:
                w, level = next(computed)
                raw_weight[rows(a, b)] = w
                release(raw_weight)
                c = {"level": np.nan if level is None else level}
                kept.write("weights", i, c)
            if i in reads:
                levels.append((float(c["level"]), b - a))
            bar.update(b - a)
        computed.close()
    level = sum(v * m for v, m in levels) / sum(m for _, m in levels)
    weight = raw_weight if store is None else new("weight.f32", n, np.float32)
    for s in range(0, n, BLOCK):
        weight[s:s + BLOCK] = (raw_weight[s:s + BLOCK] / level).astype(np.float32)
    release(weight, raw_weight)
    return replace(surfels, weight=weight)


class _Kept:
    """Each chunk's results other than its points' arrays, kept in a folder as the chunk
    completes (``chunked_surfels``' store; None: nothing is kept): ``has``, ``read`` (a dict,
    or None where not kept) and ``write`` (under a temporary name, renamed when written)."""

    def __init__(self, store):
        self.store = None if store is None else Path(store)
        self.fresh = self.store is None or not any(self.store.glob("surfels-*.npz"))

    def _path(self, step: str, i: int) -> Path:
        return self.store / f"{step}-{i}.npz"

    def has(self, step: str, i: int) -> bool:
        return self.store is not None and self._path(step, i).exists()

    def read(self, step: str, i: int):
        if not self.has(step, i):
            return None
        try:
            with np.load(self._path(step, i)) as z:
                c = {key: z[key] for key in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            return None  # damaged (a crash before the file reached the disk): done again
        if "box_lo" in c:
            c["box"] = (c.pop("box_lo"), c.pop("box_hi"))
        if "tally_0" in c:
            c["tally"] = tuple(c.pop(f"tally_{j}") for j in range(4))
        return c

    def read_all(self, step: str, n_chunks: int) -> dict:
        """{chunk: ``read``'s dict} of the chunks kept (and whole)."""
        found = {i: self.read(step, i) for i in range(n_chunks) if self.has(step, i)}
        return {i: c for i, c in found.items() if c is not None}

    def write(self, step: str, i: int, c: dict) -> None:
        if self.store is None:
            return
        arrays = {key: v for key, v in c.items() if key not in ("box", "tally")}
        if "box" in c:
            arrays["box_lo"], arrays["box_hi"] = c["box"]
        if c.get("tally") is not None:
            arrays.update({f"tally_{j}": t for j, t in enumerate(c["tally"])})
        part = self._path(step, i).with_suffix(".part")
        with open(part, "wb") as f:
            np.savez(f, **arrays)
        os.replace(part, self._path(step, i))


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
    ``rendered_level`` of them where level, else None). surfels: Surfels, or a
    ``cloudfile.SurfelFiles`` (on a worker, the cloud on disk)."""
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


def rows_in_box(pts, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The sorted rows of the points within the box [lo, hi]: a chunk's own and its halo
    (``halo_box``). pts: (N, 3) float64, or a ``cloudfile.CloudFile``, which reads the
    chunks that meet the box."""
    if isinstance(pts, CloudFile):
        return pts.rows_in_box(lo, hi)
    return array_rows_in_box(pts, lo, hi)


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
