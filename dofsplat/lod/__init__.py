"""Level of detail as blur (paper Sections 5.3, 6.2): the hierarchy and the per-frame cut.

``build_hierarchy`` makes the flat-array tree once per model (``Hierarchy.save``/``load``
keep it on disk); ``select_splats`` picks, each frame, the coarsest nodes whose low-pass
filter fits inside the circle of confusion, and returns them as a ``SplatSource`` for the
ordinary projection kernel.
"""

from __future__ import annotations

from .hierarchy import FORMAT_VERSION, Hierarchy, build_hierarchy, built_for, fingerprint
from .select import NO_CHILD, cut_nodes, gather_gradients, gather_splats, select_nodes

__all__ = ["FORMAT_VERSION", "Hierarchy", "build_hierarchy", "fingerprint", "gather_cut",
           "hierarchy_for", "leaf_arrays", "min_leaf_geo", "min_leaf_geo_keep", "select_cut",
           "select_splats", "select_nodes",
           "splat_buffers"]


def hierarchy_for(surfels, progress: bool = False) -> Hierarchy:
    """The hierarchy of ``surfels``, built on first use and kept on the object.

    The kept tree is reused while its fingerprint is the model's: an array assigned anew
    (``surfels.colors = ...``, with the same count too) builds it again. An edit in place
    (``surfels.colors[0] = ...``) is not seen: build a new ``Surfels`` (or call
    ``build_hierarchy``) after one.
    """
    tree = getattr(surfels, "_lod_hierarchy", None)
    if not built_for(tree, surfels):
        tree = build_hierarchy(surfels, progress=progress)
        surfels._lod_hierarchy = tree
    return tree


def select_splats(tree: Hierarchy, surfels, camera, coc_k: float, inv_focus: float,
                  cutoff: float, pixel_threshold: float, cull_backfaces: int,
                  blur_fraction: float = 1.0, color_tolerance: float = float("inf"),
                  min_node: int = 2):
    """The nodes of this frame's cut as a ``SplatSource``, in node (preorder) order."""
    return gather_cut(tree, surfels, select_cut(tree, surfels, camera, coc_k, inv_focus, cutoff,
                                                pixel_threshold, cull_backfaces, blur_fraction,
                                                color_tolerance, min_node))


def select_cut(tree: Hierarchy, surfels, camera, coc_k: float, inv_focus: float,
               cutoff: float, pixel_threshold: float, cull_backfaces: int,
               blur_fraction: float = 1.0, color_tolerance: float = float("inf"),
               min_node: int = 2, walk_to_leaves: bool = True):
    """This frame's cut: (nodes (S,) in preorder, their first leaves, their counts, their
    rows in the tree's arrays (-1: not stored)), int32 each (``select_nodes``,
    ``cut_nodes``). min_node: the smallest node the DOF stop draws
    (``RenderSettings.lod_min_node``; 2 here, any node, with the paper's stop as this
    function's other defaults). walk_to_leaves: in a frame without blur, run only the
    culling tests in a subtree that no pixel stop can end (``select.leaves_below``); False
    visits every node. The cut is the same either way."""
    import numpy as np

    if tree.n_surfels != len(surfels):
        raise ValueError("the hierarchy was built for a different model")
    ax, bx, ay, by = camera.screen_coefficients()
    near = camera.frustum_lrbtn()[4]
    view = np.ascontiguousarray(camera.camera_from_world()[:3].reshape(12))
    flags = np.empty(len(tree), np.uint8)
    sharp = walk_to_leaves and coc_k <= 0.0
    min_geo = min_leaf_geo(tree, surfels, tree.small) if sharp else np.zeros(0, np.float32)
    a_min = float(min(abs(ax), abs(ay))) if sharp else 0.0
    child = NO_CHILD if tree.child is None else tree.child
    select_nodes(tree.n_surfels, (tree.center, tree.bound, tree.extent, tree.position,
                                  tree.normal, tree.cone, tree.sigma_r2, tree.lod_cov,
                                  tree.color_detail),
                 tree.small, child, np.int64(tree.block_levels), model_arrays(tree, surfels),
                 min_geo, a_min, view, ax, bx, ay,
                 by, near, camera.width, camera.height, float(coc_k), float(inv_focus),
                 float(cutoff),
                 float(pixel_threshold) ** 2, float(blur_fraction), float(color_tolerance),
                 np.int64(min_node), int(cull_backfaces), flags)
    return cut_nodes(flags, tree.n_surfels, tree.small, child, np.int64(tree.block_levels))


def min_leaf_geo(tree: Hierarchy, surfels, small: int):
    """Each stored row's smallest leaf r_u r_v (``select.subtree_min_geo``) for a tree of
    this ``small`` (the tree's own; 1: a row per inner node, the CUDA backend's), (rows,)
    float32: made on first use and kept on the tree, for the same arrays, like
    ``leaf_arrays``."""
    import numpy as np

    from .hierarchy import stored_nodes
    from .select import subtree_min_geo

    order, _, _, _, _, _, ru, rv, _ = leaf_arrays(tree, surfels)
    hit = tree.__dict__.setdefault("_min_geo", {}).get(small)
    if hit is not None and _same(hit[0], ru) and _same(hit[1], rv):
        return hit[2]
    out = np.zeros(max(int(stored_nodes(tree.n_surfels, small)), 1), np.float32)
    subtree_min_geo(tree.n_surfels, small, order, ru, rv if rv.shape[0] else ru, out)
    if tree.block_levels and small == tree.small:  # (rows in preorder: to the tree's layout)
        from .hierarchy import tree_rows

        pre = tree_rows(tree.n_surfels, small)
        stored = pre >= 0
        moved = np.empty_like(out)
        moved[tree.rows[stored]] = out[pre[stored]]
        out = moved
    min_leaf_geo_keep(tree, surfels, out, small)
    return out


def min_leaf_geo_keep(tree: Hierarchy, surfels, values, small: int | None = None) -> None:
    """Keep ``min_leaf_geo``'s values for this tree, these surfels and ``small`` (the tree's
    own where None): a stored model's file holds them (``io.model_file``)."""
    _, _, _, _, _, _, ru, rv, _ = leaf_arrays(tree, surfels)
    tree.__dict__.setdefault("_min_geo", {})[tree.small if small is None else small] = (
        ru, rv, values)


def _same(a, b) -> bool:
    """The same array object, or both empty (a round model's r_v is a new empty array)."""
    return a is b or (a.size == 0 and b.size == 0)


def model_arrays(tree: Hierarchy, surfels):
    """What ``small_node`` reads: (the leaf order, the surfels' positions, normals, r_u,
    r_v, weights ((0,) without), colours, opacities), as ``leaf_arrays`` gives them."""
    order, pos, nrm, col, alpha, _, ru, rv, weight = leaf_arrays(tree, surfels)
    return order, pos, nrm, ru, rv if rv.shape[0] else ru, weight, col, alpha


def leaf_arrays(tree: Hierarchy, surfels):
    """The surfel arrays that the gather and the walk read, and the leaf order that indexes
    them: (order, positions, normals, colours, opacities, tangents ((0, 3) for round
    surfels), r_u, r_v ((0,) for round surfels), weights ((0,) without)).

    For a full tree these are copies in the tree's leaf order, and the order is the
    identity: a cut's leaves are then read one after the other instead of all over the
    model (the lion's gather took 9 x as long through ``tree.order``, bench/RESULTS.md).
    Made on first use and kept on the tree, for the same arrays (``hierarchy_for``: edits
    in place are not seen). A compact tree (a large model) reads the surfels through
    ``tree.order``: the copies would cost 44 bytes a surfel."""
    import numpy as np

    empty = np.zeros(0, np.float32)
    arrays = (surfels.positions, surfels.normals, surfels.colors, surfels.opacity,
              surfels.tangent if surfels.is_elliptical else np.zeros((0, 3), np.float32),
              surfels.radius, surfels.radius_v if surfels.is_elliptical else empty,
              surfels.weight if surfels.weight is not None else empty)
    if tree.small != 1 or getattr(tree, "leaf_ordered", False):
        # (a stored model's surfels are in leaf order already: io.model_file)
        return (tree.order, *arrays)
    cached = getattr(tree, "_leaf_arrays", None)
    if cached is None or any(a is not b and (a.size or b.size) for a, b in zip(cached[0], arrays)):
        n = tree.order.shape[0]
        copies = tuple(a[tree.order] if a.shape[0] == n else a for a in arrays)
        cached = (arrays, (np.arange(n, dtype=tree.order.dtype), *copies))
        tree._leaf_arrays = cached
    return cached[1]


def splat_buffers(n: int, surfels):
    """A ``SplatSource`` of n uninitialised rows for ``gather_splats`` to fill (tangents
    only for elliptical surfels)."""
    import numpy as np

    from ..splat.source import SplatSource

    return SplatSource(
        positions=np.empty((n, 3), np.float32), normals=np.empty((n, 3), np.float32),
        colors=np.empty((n, 3), np.float32), opacity=np.empty(n, np.float32),
        tangents=np.empty((n if surfels.is_elliptical else 0, 3), np.float32),
        ru=np.empty(n, np.float32), rv=np.empty(n, np.float32), area=np.empty(n, np.float32),
        lod_cov=np.empty((n, 6), np.float32), color_grad=np.empty((n, 6), np.float32),
        level=np.empty(n, np.int8), material=surfels.material)


def gather_cut(tree: Hierarchy, surfels, cut):
    """The nodes of ``cut`` ((nodes, start, count, row) as ``select_cut`` gives them, or rows
    of it) as a ``SplatSource``: a leaf is its surfel, an inner node its prefiltered
    attributes (``gather_splats``)."""
    nodes, start, count, row = cut
    out = splat_buffers(nodes.size, surfels)
    order, pos, nrm, col, alpha, tan, ru, rv, weight = leaf_arrays(tree, surfels)
    gather_splats(row, order, start, count, tree.position, tree.normal,
                  tree.color, tree.opacity, tree.area, tree.sigma_r2, tree.lod_cov,
                  pos, nrm, col, alpha, tan, ru, rv, weight, out.positions,
                  out.normals, out.colors, out.opacity, out.tangents, out.ru, out.rv, out.area,
                  out.lod_cov, out.level, out.color_grad)
    # the stored nodes' colour gradients (zero for a surfel) in a pass of their own: two
    # more arrays in gather_splat stop numba inlining it, which made the cut 2.5 x slower
    gather_gradients(row, count, tree.color_grad, out.color_grad)
    return out
