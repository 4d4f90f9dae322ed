"""How point-cloud normals are oriented, across k and smoothing (dofsplat.prep.pointcloud).

For the lion scan (z up) at k = 8 ... 32, with and without smoothing, prints the share of
the flat surfels in the lowest tenth of the scan whose normal faces up (the ground), and
the share of normals that agree in sign with those of the defaults (k = 24, smoothing,
the vote); ``--old-rule`` orients the same runs with Hoppe's single root (the point
farthest from its component's centroid, oriented away from it) in place of the
visibility vote. For the
dragon meshes (dragon_vrip_res4.ply, 5,205 vertices, and the full dragon_vrip.ply.gz),
prints the share of oriented PCA normals that agree in sign with the mesh's vertex
normals, and their median angle, with the defaults and with k = 16 and no smoothing.

    python bench/orientation.py              # the visibility vote (about 2 minutes)
    python bench/orientation.py --old-rule   # the single root, for comparison
"""

from __future__ import annotations

import argparse
import gzip
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import dofsplat.prep.pointcloud as pc
from dofsplat.prep.meshes import vertex_normals

sys.path.insert(0, str(Path(__file__).resolve().parent))
from uniformity import DATA, read_ply_points  # noqa: E402


def single_root_votes(positions, normals, label, n_comp, **_):
    """The rule outward_votes replaced: each component's point farthest from its
    centroid must point away from it."""
    votes = np.ones(n_comp)
    for c in range(n_comp):
        members = np.nonzero(label == c)[0]
        offset = positions[members] - positions[members].mean(axis=0)
        far = np.argmax(np.sum(offset * offset, axis=1))
        votes[c] = np.dot(normals[members[far]], offset[far]) or 1.0
    return votes


def agreement(surfels, ref_positions, ref_normals):
    """Share of surfels whose normal agrees in sign with the nearest reference point's."""
    _, nearest = cKDTree(ref_positions).query(surfels.positions.astype(np.float64))
    dots = np.sum(surfels.normals * ref_normals[nearest], axis=1)
    return float(np.mean(dots > 0)), dots


def lion(ks, old_rule: bool):
    pos, _ = read_ply_points(DATA / "lion_takanawa" / "lion_takanawa_xyzrgb.ply")
    ref = pc.points_to_surfels(pos, normalise="none", progress=False)  # defaults, vote
    ref_pos, ref_nrm = ref.positions.astype(np.float64), ref.normals.astype(np.float64)
    if old_rule:
        pc.outward_votes = single_root_votes
    print("| k | smoothing | ground facing up | agree with the defaults |")
    print("|---:|---|---:|---:|")
    for k in ks:
        for smooth in (False, True):
            s = pc.points_to_surfels(pos, k=k, smooth=smooth, normalise="none",
                                     progress=False)
            z, nz = s.positions[:, 2], s.normals[:, 2]
            ground = (z < np.quantile(z, 0.1)) & (np.abs(nz) > 0.9)
            agree, _ = agreement(s, ref_pos, ref_nrm)
            print(f"| {k} | {'on' if smooth else 'off'} | {np.mean(nz[ground] > 0):.3f} | "
                  f"{agree:.3f} |", flush=True)


def mesh_normals(path):
    from plyfile import PlyData

    opener = gzip.open if path.name.endswith(".gz") else open
    with opener(path, "rb") as f:
        ply = PlyData.read(f)
    v = ply["vertex"]
    pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    vert_n = vertex_normals(pts, np.vstack(ply["face"]["vertex_indices"]))
    used = np.linalg.norm(vert_n, axis=1) > 0  # no face, or back-to-back faces
    return pts, vert_n, used


def dragons():
    print("| model | k | smoothing | agree with the mesh | median angle (deg) |")
    print("|---|---:|---|---:|---:|")
    for name in ("dragon_vrip_res4.ply", "dragon_vrip.ply.gz"):
        pts, vert_n, used = mesh_normals(DATA / "stanford_dragon" / name)
        for k, smooth in ((None, True), (16, False)):
            s = pc.points_to_surfels(pts, k=k, smooth=smooth, normalise="none",
                                     progress=False)
            if len(s) == len(pts):  # no duplicates merged: the same order
                nearest = np.arange(len(pts))
            else:  # smoothing moves points: match the original positions
                nearest = cKDTree(pts).query(s.positions.astype(np.float64))[1]
            keep = used[nearest]  # surfels of vertices that belong to a face
            dots = np.sum(s.normals[keep] * vert_n[nearest[keep]], axis=1)
            agree = float(np.mean(dots > 0))
            angle = np.median(np.degrees(np.arccos(np.clip(np.abs(dots), 0, 1))))
            print(f"| {name} | {k or pc.DEFAULT_K} | {'on' if smooth else 'off'} | "
                  f"{agree:.3f} | {angle:.1f} |", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-rule", action="store_true",
                    help="orient components by the single farthest point (the old rule)")
    ap.add_argument("--ks", type=int, nargs="*", default=[8, 12, 16, 20, 24, 32],
                    help="the lion's k values (none: the dragons only)")
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        raise SystemExit(f"{DATA} not found")
    if args.ks:
        lion(args.ks, args.old_rule)
        print()
    dragons()


if __name__ == "__main__":
    main()
