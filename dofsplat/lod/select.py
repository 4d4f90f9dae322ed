"""Per-frame LOD selection: a cut through the hierarchy (Section 6.2).

The traversal starts at the root and, at each node, either culls it (outside the view
frustum, entirely behind the near plane, or entirely back-facing by its normal cone),
selects it (it is splatted, its subtree is not visited), or descends to its children.
A node is selected when

* it is a leaf; or
* its screen-space LOD blur fits inside the DOF blur everywhere in it (the DOF stop):
      lambda_max(J V^{q,l} J^T) <= kappa V^I(C_min),
  where J V^{q,l} J^T is the node's low-pass filter projected at its mean position
  (``ewa.screen_lod_variance``) and C_min the smallest circle of confusion over the
  node's depth range. kappa = 1 is the paper's rule; a smaller kappa stops one level lower
  (kappa = 1/2: 1.35-1.7 x the fragments, 0.1-2 dB closer to the reference in
  bench/paper.py's Figure 6). A node with texture at its own scale (``color_detail``
  above ``color_tol``) stops lower still: kappa is scaled by ``detail_factor``
  (docs/maths.md, "A finer cut where the texture needs it"). A node of fewer than
  ``min_node`` surfels is not drawn by this stop (RenderSettings.lod_min_node; 2: any
  node), and its surfels are drawn instead (docs/maths.md, "The smallest nodes").
  Then circumellipse(J V^{q,l} J^T, V^I) = V^I: the node's resampling kernel is exactly the
  no-LOD DOF kernel of eq. 11, rasterised from one splat instead of many (PAPER_NOTES §4);
* or it is smaller than the pixel threshold (QSplat's stop): its level basis V^l = V^r + V^q,
  as a disk radius 2 sigma along its largest screen axis, projects to at most
  ``pixel_threshold`` pixels.

A node whose mean normal faces away from the eye while its cone does not is never
selected (its flat splat would be a back face): the traversal descends instead.

In a frame without blur only the pixel stop selects inner nodes, and in a subtree none of
whose inner nodes can pass it (``leaves_below``) the walk runs the culling tests alone,
and flags a node too small for them as "its leaves" (LEAVES + m) without going below it:
the same cut, for a few integer operations on most nodes (docs/maths.md, "The pinhole
frame's walk").

The tree's top levels are walked serially down to ``SPLIT_DEPTH``; the subtrees below are
walked in parallel, one explicit stack each. The result is a flag per node.
"""

from __future__ import annotations

import math

from ..jit import numba
import numpy as np

from .hierarchy import (SMALL_NODE, V_COLOR_GRAD, attribute_rows, child_rows, node_height,
                        push_children, small_node, store_attributes, stored_nodes)
from ..splat.ewa import (coc_radius_px, dof_variance, jacobian_column, max_eigenvalue,
                         screen_lod_variance, shared, shared_inline, tangent_from_normal)

CULL, SELECT, DESCEND = 3, 1, 2  # also the flags of select_nodes (0: not visited)
# the walk's back-face rule (``cull_backfaces``, ``frame.backface_rule``): 0 none (two-sided
# splats), 1 cull, descending a node whose mean normal faces away to its children, 2 cull
# and, in a blurred region, drop such a node where the blur's stop would draw it
BACK_DESCEND, BACK_DROP_BLURRED = 1, 2
# ... and LEAVES + m: a node of m < CULL_TEST_MIN_COUNT surfels whose cut is its m leaves,
# which the pinhole walk does not visit (``_walk``; ``cut_run`` lists them)
LEAVES = 4
SPLIT_DEPTH = 10  # 1024 subtrees for the parallel walk
STACK = 96  # the median split keeps depth <= ceil(log2 N) + 1, far below this
# frustum and normal-cone culling cost square roots and inverse trigonometric functions:
# worth it only for nodes that would save a sizeable subtree; the surfels of small ones are
# culled exactly, one by one, by the projection
CULL_TEST_MIN_COUNT = 32
# a node with texture at its own scale stops at kappa x max(DETAIL_FLOOR,
# sqrt(color_tol / color_detail)) (docs/maths.md, "A finer cut where the texture needs it")
DETAIL_FLOOR = 0.3


@shared
def detail_factor(detail, m, color_tol):
    """The factor on a node's DOF stop for its texture at its own scale, ``detail``
    (``Hierarchy.color_detail``): 1 up to ``color_tol``, then sqrt(color_tol / detail), at
    least DETAIL_FLOOR; 1 for nodes of at most SMALL_NODE surfels (which a compact tree
    does not store: both trees cut alike) and for color_tol = inf.

    Why the square root: a zero-mean texture of the node's size under the blur keeps
    about (node variance / blur variance)^2 of its amplitude, so the node's error,
    detail x (lambda / V)^2, stays under color_tol x kappa^2 (chosen on the fidelity
    suite against a plain threshold and a linear factor)."""
    if m <= SMALL_NODE or detail <= color_tol:
        return 1.0
    return max(DETAIL_FLOOR, math.sqrt(color_tol / detail))


@shared_inline
def visit_node(r, m, center, bound, extent, position, normal, cone, sigma_r2, lod_cov,
               color_detail, view, ax, bx, ay, by, near, width, height, coc_k, inv_focus, cutoff,
               thr2, kappa, color_tol, min_node, cull_backfaces, stops):
    """CULL, SELECT or DESCEND for a node of m surfels whose attributes are row r of the
    given arrays (the tree's stored row, ``Hierarchy.row``; or a node the tree does not
    store, put in row 0 of arrays of its own; see the module docstring). stops=False: the
    culling tests alone, DESCEND where they keep the node (a subtree of ``leaves_below``)."""
    if m == 1:
        # a leaf is one surfel: the projection culls it exactly (near plane, back face,
        # outside the image), so the tests below would only repeat that work
        return SELECT
    # bounding sphere in camera space
    wx, wy, wz = center[r, 0], center[r, 1], center[r, 2]
    cx = view[0] * wx + view[1] * wy + view[2] * wz + view[3]
    cy = view[4] * wx + view[5] * wy + view[6] * wz + view[7]
    cz = view[8] * wx + view[9] * wy + view[10] * wz + view[11]
    u = -cz
    rad = np.float64(bound[r])
    if u + rad <= near:
        return CULL  # entirely behind the near plane
    if m >= CULL_TEST_MIN_COUNT:
        # frustum, widened by the largest blurred kernel's reach: a blurred splat just outside
        # the image can still reach into it
        u_near = max(u - rad, near)
        coc_max = max(coc_radius_px(u_near, coc_k, inv_focus), coc_radius_px(u + rad, coc_k, inv_focus))
        margin = math.sqrt(2.0 * cutoff * (dof_variance(coc_max) + 1.0)) + 1.0
        # the truncated basis reaches sqrt(2c)/2 disk radii from the surfel's centre
        reach = rad * max(1.0, 0.5 * math.sqrt(2.0 * cutoff))
        s_left = (-margin - bx) / ax
        s_right = (width + margin - bx) / ax
        s_bottom = (by - height - margin) / ay
        s_top = (by + margin) / ay
        if (cx + s_left * cz) < -reach * math.sqrt(1.0 + s_left * s_left):
            return CULL
        if (-cx - s_right * cz) < -reach * math.sqrt(1.0 + s_right * s_right):
            return CULL
        if (cy + s_bottom * cz) < -reach * math.sqrt(1.0 + s_bottom * s_bottom):
            return CULL
        if (-cy - s_top * cz) < -reach * math.sqrt(1.0 + s_top * s_top):
            return CULL

    nwx, nwy, nwz = normal[r, 0], normal[r, 1], normal[r, 2]
    nx = view[0] * nwx + view[1] * nwy + view[2] * nwz
    ny = view[4] * nwx + view[5] * nwy + view[6] * nwz
    nz = view[8] * nwx + view[9] * nwy + view[10] * nwz
    if cull_backfaces and m >= CULL_TEST_MIN_COUNT:
        dist = math.sqrt(cx * cx + cy * cy + cz * cz)
        if dist > rad and cone[r] < 0.5 * math.pi:
            # every normal in the cone faces away from every point of the sphere
            cos_a = (nx * cx + ny * cy + nz * cz) / dist
            alpha = math.acos(min(1.0, max(-1.0, cos_a)))
            if alpha + cone[r] + math.asin(rad / dist) < 0.5 * math.pi:
                return CULL
    if not stops:
        return DESCEND

    # the node as a splat: its mean position and normal
    pwx, pwy, pwz = position[r, 0], position[r, 1], position[r, 2]
    px = view[0] * pwx + view[1] * pwy + view[2] * pwz + view[3]
    py = view[4] * pwx + view[5] * pwy + view[6] * pwz + view[7]
    pz = view[8] * pwx + view[9] * pwy + view[10] * pwz + view[11]
    if -pz <= near:
        return DESCEND
    back = cull_backfaces and nx * px + ny * py + nz * pz >= 0.0
    if back and cull_backfaces != BACK_DROP_BLURRED:
        return DESCEND  # a back-facing mean: let the children decide
    cov = (np.float64(lod_cov[r, 0]), np.float64(lod_cov[r, 1]), np.float64(lod_cov[r, 2]),
           np.float64(lod_cov[r, 3]), np.float64(lod_cov[r, 4]), np.float64(lod_cov[r, 5]))
    q11, q12, q22, q_depth = screen_lod_variance(px, py, pz, cov, view, ax, ay)
    lam_q = max_eigenvalue(q11, q12, q22)

    # pixel stop: the level's basis (V^r + V^q) as a disk radius 2 sigma, in pixels; the
    # Jacobian is needed only when the filter alone passes (most nodes fail here)
    if 4.0 * lam_q <= thr2:
        tux, tuy, tuz = tangent_from_normal(nx, ny, nz)
        tvx = ny * tuz - nz * tuy
        tvy = nz * tux - nx * tuz
        tvz = nx * tuy - ny * tux
        j11, j21 = jacobian_column(px, py, pz, tux, tuy, tuz, ax, ay)
        j12, j22 = jacobian_column(px, py, pz, tvx, tvy, tvz, ax, ay)
        lam_j = max_eigenvalue(j11 * j11 + j12 * j12, j11 * j21 + j12 * j22,
                               j21 * j21 + j22 * j22)
        if 4.0 * (np.float64(sigma_r2[r]) * lam_j + lam_q) <= thr2:
            # sharp: a back-facing node's front-facing children are seen, so they decide
            return DESCEND if back else SELECT
    # DOF stop: J V^q J^T inside V^I for the smallest CoC over the node's depth range
    if coc_k > 0.0:
        u_lo = max(u - extent[r], near)
        u_hi = u + extent[r]
        if inv_focus > 0.0 and u_lo <= 1.0 / inv_focus <= u_hi:
            return DESCEND  # the focal plane runs through the node
        coc_min = min(coc_radius_px(u_lo, coc_k, inv_focus), coc_radius_px(u_hi, coc_k, inv_focus))
        if m >= min_node and lam_q <= kappa * detail_factor(np.float64(color_detail[r]), m,
                                                            color_tol) * dof_variance(coc_min):
            # blurred: a back-facing node is dropped whole, its front-facing minority with it
            # (docs/maths.md, "A back-facing node under the blur")
            return CULL if back else SELECT
    return DESCEND


# the bound's margin for float32 rounding: sigma_r2 is a float32 mean of float32 values, the
# normal a float32 unit vector (its tangent frame unit to 1e-7)
LEAVES_MARGIN = 1.001


@shared_inline
def leaves_below(r, center, bound, min_geo, view, a_min, near, thr2):
    """Whether no inner node of the subtree at stored row r can pass the pixel stop, in a
    frame without blur (coc_k <= 0: the DOF stop selects nothing), so that the walk runs
    only the culling tests there (docs/maths.md, "The pinhole frame's walk").

    The stop selects a node where 4 (sigma_r2 lam_j + lam_q) <= thr2. sigma_r2 is a
    weighted mean of the subtree's leaves' r_u r_v / 4, so at least min_geo[r] / 4 (the
    subtree's smallest r_u r_v, ``subtree_min_geo``); lam_q >= 0; and lam_j, the largest
    squared stretch of the node's tangent plane on screen, is at least (a_min / U)^2: the
    plane holds a direction parallel to the image, which moves a_x t_x / U, a_y t_y / U
    pixels, and every node of the subtree lies in the sphere (center[r], bound[r]), at
    most U = u + bound from the eye. a_min = min(|a_x|, |a_y|); 0 turns the test off."""
    wx, wy, wz = center[r, 0], center[r, 1], center[r, 2]
    u = -(view[8] * wx + view[9] * wy + view[10] * wz + view[11])
    rad = np.float64(bound[r])
    if u - rad <= near:
        return False  # the near plane cuts the sphere: let the visits decide
    u_far = u + rad
    return np.float64(min_geo[r]) * a_min * a_min > LEAVES_MARGIN * thr2 * u_far * u_far


@numba.njit(cache=True, nogil=True)
def subtree_min_geo(n_surfels, small, order, ru, rv, out):
    """out[r] = the smallest r_u r_v among the leaves of stored row r's subtree (the rows of a
    tree whose nodes of at most ``small`` surfels are not stored; small = 1: a row per inner
    node, the CUDA backend's), for ``leaves_below``. ru, rv: in the surfels' order, read
    through ``order`` (rv = ru for round surfels). A walk in post-order with an explicit
    stack: O(N), no per-node array."""
    stack = np.empty((2 * STACK, 4), np.int64)  # first leaf, count, row, children done
    values = np.empty(2 * STACK, np.float64)
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = 0, n_surfels, 0, 0
    top, n_values = 1, 0
    while top > 0:
        top -= 1
        s, m, r, done = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        if m <= small:  # not stored (a leaf, or a small node): its leaves
            v = np.inf
            for t in range(s, s + m):
                k = order[t]
                v = min(v, np.float64(ru[k]) * np.float64(rv[k]))
            values[n_values] = v
            n_values += 1
        elif done:
            v = min(values[n_values - 1], values[n_values - 2])
            n_values -= 1
            values[n_values - 1] = v
            out[r] = v
        else:
            h = m // 2
            stack[top, 3] = 1  # back to this row once both children are done
            stack[top + 1, 0], stack[top + 1, 1] = s + h, m - h
            stack[top + 1, 2], stack[top + 1, 3] = r + 1 + stored_nodes(h, small), 0
            stack[top + 2, 0], stack[top + 2, 1] = s, h
            stack[top + 2, 2], stack[top + 2, 3] = r + 1, 0
            top += 3


@numba.njit(cache=True, nogil=True)
def _walk(root, root_start, root_count, root_row, root_leaves, root_depth, max_depth, tree,
          small, child, levels, model, min_geo, a_min, view, ax, bx, ay, by, near, width,
          height, coc_k, inv_focus, cutoff, thr2, kappa, color_tol, min_node, cull_backfaces,
          flags, pending, n_pending):
    """Depth-first walk of the subtree at node ``root`` (its first leaf, count and row
    given): flags each node visited (SELECT, CULL, DESCEND or LEAVES + m); nodes deeper
    than max_depth that need a visit are appended to ``pending`` (rows of node, first leaf,
    count, row, leaves, depth) instead. Returns the new n_pending.

    In a frame without blur (coc_k <= 0), in the subtree of a stored node that cannot hold a
    node of the pixel stop (``leaves_below``; min_geo: ``subtree_min_geo``'s rows, a_min:
    the smaller screen scale, 0 to visit every node) only the culling tests run, on the
    nodes they apply to (CULL_TEST_MIN_COUNT surfels and more), and a node of fewer
    surfels is flagged LEAVES + m without a visit below it: the cut is the visits'
    (root_leaves: the root is inside such a subtree).

    tree: the stored attribute arrays (``select_nodes``); model: the surfel arrays that
    ``small_node`` reads for a node of at most ``small`` surfels (``Hierarchy.small``),
    which the tree does not store. A node's first leaf s and count m come down from its parent (left
    child: s, m // 2; right child: s + m // 2, m - m // 2; the tree's shape depends on N
    alone), and so does a stored node's row (``hierarchy.child_rows``: in preorder, the left
    child's the parent's + 1, the right child's that + the left subtree's stored nodes; in a
    blocked layout, ``child`` and ``levels`` say, ``Hierarchy.blocked``)."""
    center, bound, extent, position, normal, cone, sigma_r2, lod_cov, color_detail = tree
    order, positions, normals, ru, rv, weight, colors, alpha = model
    # where a small node is put to be visited as a stored row (row 0)
    w0, w1, w2, w3, w4, w5, w6, w7, w8, w9, w10, w11, w12 = attribute_rows(1)
    stack = np.empty((STACK, 6), np.int64)  # node, first leaf, count, depth, row, leaves
    stack[0, 0] = root
    stack[0, 1] = root_start
    stack[0, 2] = root_count
    stack[0, 3] = root_depth
    stack[0, 4] = root_row
    stack[0, 5] = root_leaves
    sharp = coc_k <= 0.0 and a_min > 0.0
    top = 1
    while top > 0:
        top -= 1
        i, s, m, d, r = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3], stack[top, 4]
        leaves = stack[top, 5]
        if d > max_depth:
            pending[n_pending, 0] = i
            pending[n_pending, 1] = s
            pending[n_pending, 2] = m
            pending[n_pending, 3] = r
            pending[n_pending, 4] = leaves
            pending[n_pending, 5] = d
            n_pending += 1
            continue
        if m == 1:
            flags[i] = SELECT  # a leaf: its surfel (visit_node's first rule)
            continue
        if not leaves and sharp and m > small:
            leaves = np.int64(1 if leaves_below(r, center, bound, min_geo, view, a_min, near,
                                                thr2) else 0)
        if leaves and m < CULL_TEST_MIN_COUNT:
            # no culling test runs on it or below it, and the near plane misses its sphere
            # (leaves_below): its cut is its leaves, flagged at once instead of 2m - 1
            # visits (the pinhole plane's walk visited 383,691 of its 524,287 nodes;
            # bench/RESULTS.md)
            flags[i] = LEAVES + m
            continue
        if m > small:
            what = visit_node(r, m, center, bound, extent, position, normal, cone, sigma_r2,
                              lod_cov, color_detail, view, ax, bx, ay, by, near, width, height,
                              coc_k, inv_focus, cutoff, thr2, kappa, color_tol, min_node,
                              cull_backfaces, leaves == 0)
        else:
            v = small_node(s, m, order, positions, normals, ru, rv, weight, colors, alpha, False)
            store_attributes(v, 0, w0, w1, w2, w3, w4, w5, w6, w7, w8, w9, w10, w11, w12)
            what = visit_node(0, m, w0, w1, w2, w3, w4, w5, w9, w10, w12, view, ax, bx, ay, by,
                              near, width, height, coc_k, inv_focus, cutoff, thr2, kappa,
                              color_tol, min_node, cull_backfaces, True)
        flags[i] = what
        if what == DESCEND:
            left, right = child_rows(r, m, d, small, child, levels)
            stack[top, 3] = d + 1
            stack[top + 1, 3] = d + 1
            stack[top + 1, 4] = left  # (pushed second)
            stack[top, 4] = right
            stack[top, 5] = leaves
            stack[top + 1, 5] = leaves
            top = push_children(stack, top, i, s, m)
    return n_pending


@numba.njit(cache=True, nogil=True, parallel=True)
def select_nodes(n_surfels, tree, small, child, levels, model, min_geo, a_min, view, ax, bx,
                 ay, by, near, width, height, coc_k, inv_focus, cutoff, thr2, kappa, color_tol,
                 min_node, cull_backfaces, flags):
    """Set flags[i] = SELECT for every node of the cut, CULL for a culled node, DESCEND for a
    node whose children were visited, LEAVES + m for a node of m surfels whose cut is its
    leaves, found without visiting them (the pinhole walk, ``_walk``), and 0 for the rest
    (below a selected, culled or LEAVES node). ``cut_nodes`` reads the cut from the flags.

    tree: the hierarchy's (center, bound, extent, position, normal, cone, sigma_r2,
    lod_cov, color_detail), its ``small``, and its layout (``child``, empty in preorder, and
    ``block_levels``: ``_walk``); model: the surfels' (order (the tree's), positions,
    normals, r_u, r_v, weight, colors, opacity), for the nodes the tree does not store
    (``small_node``); min_geo, a_min: the pinhole frame's walk to the leaves (``_walk``;
    a_min = 0: every node visited)."""
    flags[:] = 0
    pending = np.empty((1 << (SPLIT_DEPTH + 1), 6), np.int64)
    # both calls pass the same types (no literal constants, which numba compiles a
    # specialisation for): one _walk to compile, not two
    zero = np.int64(0)
    pending[0, :] = 0
    pending[0, 2] = n_surfels
    n_pending = _walk(pending[0, 0], pending[0, 1], pending[0, 2], pending[0, 3], pending[0, 4],
                      zero, np.int64(SPLIT_DEPTH - 1), tree, small, child, levels, model,
                      min_geo, a_min, view, ax, bx, ay, by, near, width, height, coc_k,
                      inv_focus, cutoff, thr2, kappa, color_tol, min_node, cull_backfaces,
                      flags, pending, zero)
    dummy = np.empty((1, 6), np.int64)
    for t in numba.prange(n_pending):
        _walk(pending[t, 0], pending[t, 1], pending[t, 2], pending[t, 3], pending[t, 4],
              pending[t, 5], np.int64(STACK), tree, small, child, levels, model, min_geo, a_min,
              view, ax, bx, ay, by, near, width, height, coc_k, inv_focus, cutoff, thr2, kappa,
              color_tol, min_node, cull_backfaces, flags, dummy, zero)


# cut_nodes reads the flags in at most this many runs of at least CUT_RUN nodes, in
# parallel: a fixed cut, so the cut does not depend on the thread count
CUT_RUNS = 64
CUT_RUN = 16384


def cut_nodes(flags, n_surfels, small, child=None, levels=0):
    """The selected nodes in preorder, with each one's first leaf, count and row: (nodes
    (S,) int32, start (S,) int32, count (S,) int32, row (S,) int32: the node's row in the
    tree's attribute arrays, -1 where it stores none: ``small``), from ``select_nodes``' flags
    (``cut_runs``, in runs of CUT_RUN nodes and more). child, levels: the tree's layout
    (``Hierarchy.child``, ``block_levels``; None: preorder)."""
    return cut_runs(flags, n_surfels, small, NO_CHILD if child is None else child, levels,
                    min(max(flags.shape[0] // CUT_RUN, 1), CUT_RUNS))


NO_CHILD = np.zeros(0, np.int32)  # the preorder layout's (``hierarchy.child_rows``)


@numba.njit(cache=True, nogil=True, parallel=True)
def cut_runs(flags, n_surfels, small, child, levels, runs):
    """``cut_nodes`` with the flags cut into ``runs`` runs of node numbers, in parallel. A
    node's subtree is a run of numbers (preorder: node i of m surfels and its subtree are
    i .. i + 2m - 2), so the selected nodes, in preorder, are those flagged SELECT and the m
    leaves of those flagged LEAVES + m, in increasing number: each run counts its own, and
    then walks the tree again (no per-node first leaf or count is stored) into its slots,
    entering only the subtrees that reach into it (``cut_run``). It was one serial walk: 0.8 ms of the pinhole plane's 44 ms
    frame on two threads, where every other stage runs in parallel."""
    n = flags.shape[0]
    first = np.zeros(runs + 1, np.int64)
    for c in numba.prange(runs):
        k = 0
        for i in range(c * n // runs, (c + 1) * n // runs):
            f = flags[i]
            if f == SELECT:
                k += 1
            elif f > LEAVES:
                k += f - LEAVES  # a node's leaves, listed by the run that holds its number
        first[c + 1] = k
    for c in range(runs):
        first[c + 1] += first[c]
    total = first[runs]
    nodes = np.empty(total, np.int32)
    start = np.empty(total, np.int32)
    count = np.empty(total, np.int32)
    row = np.empty(total, np.int32)
    for c in numba.prange(runs):
        cut_run(flags, n_surfels, small, child, levels, c * n // runs, (c + 1) * n // runs,
                first[c], nodes, start, count, row)
    return nodes, start, count, row


@numba.njit(cache=True, nogil=True)
def cut_run(flags, n_surfels, small, child, levels, lo, hi, t, nodes, start, count, row):
    """The selected nodes numbered lo .. hi - 1, and the leaves of the LEAVES nodes
    numbered so, in preorder, into slots t, t + 1, ... of ``cut_runs``' arrays: a walk of
    the visited part of the tree that skips the subtrees numbered wholly outside the run."""
    stack = np.empty((STACK, 5), np.int64)  # node, first leaf, count, row, depth
    stack[0, 0] = 0
    stack[0, 1] = 0
    stack[0, 2] = n_surfels
    stack[0, 3] = 0
    stack[0, 4] = 0
    top = 1
    while top > 0:
        top -= 1
        i, s, m, r, d = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3], \
            stack[top, 4]
        if i >= hi or i + 2 * m - 1 <= lo:
            continue  # the subtree's numbers i .. i + 2m - 2 miss the run
        f = flags[i]
        if f == SELECT:
            if i >= lo:
                nodes[t] = i
                start[t] = s
                count[t] = m
                row[t] = r if m > small else -1
                t += 1
        elif f > LEAVES:
            if i >= lo:  # its leaves, in preorder, from the stack's free rows up
                stack[top, 0], stack[top, 1], stack[top, 2] = i, s, m
                base, top = top, top + 1
                while top > base:
                    top -= 1
                    j, sj, mj = stack[top, 0], stack[top, 1], stack[top, 2]
                    if mj == 1:
                        nodes[t] = j
                        start[t] = sj
                        count[t] = 1
                        row[t] = -1
                        t += 1
                    else:
                        top = push_children(stack, top, j, sj, mj)
        elif f == DESCEND:
            left, right = child_rows(r, m, d, small, child, levels)
            stack[top + 1, 3] = left
            stack[top, 3] = right
            stack[top, 4] = d + 1
            stack[top + 1, 4] = d + 1
            top = push_children(stack, top, i, s, m)


# inlined at numba's level, like project_splat; the CUDA backend compiles it as its device twin
@numba.njit(cache=True, nogil=True, inline="always")
def gather_splat(t, r, order, start, count, position, normal, color, opacity, area,
                 sigma_r2, lod_cov, s_pos, s_nrm, s_col, s_alpha, s_tan, s_ru, s_rv, s_weight,
                 out_pos, out_nrm, out_col, out_alpha, out_tan, out_ru, out_rv, out_area,
                 out_cov, out_level):
    """Row t of the splat arrays: the node whose first leaf and count are start[t] and
    count[t] (``cut_nodes``; ``gather_splats``; one GPU thread per row); an inner node's
    attributes are row r of position, normal, ... (``small_node``'s work arrays for a node
    the tree does not store).

    s_tan, s_rv: (0, 3) and (0,) for circular surfels; s_weight: (0,) without weights.
    """
    elliptical = s_tan.shape[0] > 0
    has_weight = s_weight.shape[0] > 0
    k, ru, rv, a = node_splat(r, start[t], count[t], order, sigma_r2, area, s_ru, s_rv,
                              s_weight, elliptical, has_weight)
    if k >= 0:  # a leaf: its surfel, unchanged
        for d in range(3):
            out_pos[t, d] = s_pos[k, d]
            out_nrm[t, d] = s_nrm[k, d]
            out_col[t, d] = s_col[k, d]
        out_alpha[t] = s_alpha[k]
        if elliptical:
            for d in range(3):
                out_tan[t, d] = s_tan[k, d]
        for d in range(6):
            out_cov[t, d] = 0.0
        out_level[t] = 0
    else:  # an inner node: its prefiltered attributes and LOD filter
        for d in range(3):
            out_pos[t, d] = position[r, d]
            out_nrm[t, d] = normal[r, d]
            out_col[t, d] = color[r, d]
        out_alpha[t] = opacity[r]
        if elliptical:
            for d in range(3):
                out_tan[t, d] = 0.0  # derive the tangent from the normal
        for d in range(6):
            out_cov[t, d] = lod_cov[r, d]
        out_level[t] = node_height(count[t])
    out_ru[t] = ru
    out_rv[t] = rv
    out_area[t] = a


GATHER_CHUNK = 4096  # rows per task of gather_splats (one set of small_node's work arrays each)


@numba.njit(cache=True, nogil=True, parallel=True)
def gather_splats(rows, order, start, count, position, normal, color, opacity, area,
                  sigma_r2, lod_cov, s_pos, s_nrm, s_col, s_alpha, s_tan, s_ru, s_rv,
                  s_weight, out_pos, out_nrm, out_col, out_alpha, out_tan, out_ru, out_rv,
                  out_area, out_cov, out_level, out_grad):
    """Fill the splat arrays (one row per selected node) from the tree and the surfels;
    rows, start, count: each selected node's row, first leaf and count (``cut_nodes``).

    A leaf is its surfel, unchanged; an inner node is a circular splat at its mean position
    with the leaf basis radius 2 sqrt(V^r), its area, prefiltered colour and LOD filter. A
    node the tree does not store (row -1) is computed from its surfels (``small_node``),
    its colour gradient too (``gather_gradients`` fills the other rows').
    """
    n = rows.shape[0]
    rv = s_rv if s_rv.shape[0] > 0 else s_ru  # small_node reads r_v for round surfels too
    for c in numba.prange((n + GATHER_CHUNK - 1) // GATHER_CHUNK):
        w0, w1, w2, w3, w4, w5, w6, w7, w8, w9, w10, w11, w12 = attribute_rows(1)
        for t in range(c * GATHER_CHUNK, min(n, (c + 1) * GATHER_CHUNK)):
            r = rows[t]
            if r >= 0 or count[t] == 1:
                gather_splat(t, r, order, start, count, position, normal, color, opacity, area,
                             sigma_r2, lod_cov, s_pos, s_nrm, s_col, s_alpha, s_tan, s_ru,
                             s_rv, s_weight, out_pos, out_nrm, out_col, out_alpha, out_tan,
                             out_ru, out_rv, out_area, out_cov, out_level)
                continue
            v = small_node(start[t], count[t], order, s_pos, s_nrm, s_ru, rv, s_weight, s_col,
                           s_alpha, True)
            store_attributes(v, 0, w0, w1, w2, w3, w4, w5, w6, w7, w8, w9, w10, w11, w12)
            gather_splat(t, 0, order, start, count, w3, w4, w6, w7, w8, w9, w10, s_pos,
                         s_nrm, s_col, s_alpha, s_tan, s_ru, s_rv, s_weight, out_pos, out_nrm,
                         out_col, out_alpha, out_tan, out_ru, out_rv, out_area, out_cov,
                         out_level)
            for d in range(6):
                out_grad[t, d] = v[V_COLOR_GRAD + d]


@numba.njit(cache=True, nogil=True, parallel=True)
def gather_gradients(rows, count, color_grad, out):
    """``gather_gradient`` for every row."""
    for t in numba.prange(rows.shape[0]):
        gather_gradient(t, rows[t], count, color_grad, out)


@numba.njit(cache=True, nogil=True, inline="always")
def gather_gradient(t, r, count, color_grad, out):
    """out[t] = the colour gradient of the node of count[t] surfels whose attributes are
    row r: that row of ``color_grad`` for an inner node, zero for a leaf (a surfel's colour
    is flat); a node the tree does not store (r < 0) is left alone (``gather_splats``
    writes it). Shared with the CUDA backend, one thread per row."""
    if count[t] > 1:
        if r >= 0:
            for d in range(6):
                out[t, d] = color_grad[r, d]
    else:
        for d in range(6):
            out[t, d] = 0.0


@numba.njit(cache=True, nogil=True)
def node_splat(row, s, m, order, sigma_r2, area, s_ru, s_rv, s_weight, elliptical,
               has_weight):
    """The node of m surfels from first leaf s, its attributes (if inner) in row ``row``,
    as a splat: (k, r_u, r_v, area), for ``gather_splat``.

    A leaf is its surfel k, unchanged (its radii, and the area r_u r_v weight it stands
    for); an inner node (k = -1) is circular, with the leaf basis radius 2 sqrt(V^r), and
    stands for its surfels' total area.
    """
    if m == 1:
        k = order[s]
        ru = s_ru[k]
        rv = ru
        if elliptical:
            rv = s_rv[k]
        a = ru * rv  # float32, as the surfels' own area (splat/source.py)
        if has_weight:
            a *= s_weight[k]
        return k, np.float64(ru), np.float64(rv), np.float64(a)
    r = 2.0 * math.sqrt(sigma_r2[row])
    return -1, r, r, np.float64(area[row])
