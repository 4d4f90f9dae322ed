"""Each 3-D Gaussian's footprint on the screen, its colour, and the lens's blur of it.

The projection is 3DGS's (Zwicker et al. 2001's volume splatting, as Kerbl et al. 2023 and
gsplat 1.5.3 compute it), in the camera's OpenCV-style frame: x right, y down, z = U the
depth in front of the lens. With fx, fy, cx, cy the pinhole's intrinsics in pixels
(``intrinsics``; pixel (i, j) sampled at (j + 0.5, i + 0.5), as everywhere in dofsplat):

    mean:   (fx x/z + cx, fy y/z + cy)
    cov2d:  J W Sigma W^T J^T,  J = [[fx/z, 0, -fx t_x/z^2], [0, fy/z, -fy t_y/z^2]]

where W is the camera's rotation and t = z clamp(x/z, ...) holds the Jacobian's point to
1.3 x the half field of view (the trainers' clamp: a Gaussian far outside the image does not
get a huge footprint). Then the low-pass: cov2d + eps2d I (eps2d = 0.3 px^2); gsplat's
``antialiased`` mode scales the opacity by sqrt(det before / det after) too.

The lens (docs/maths.md, "Gaussian scenes through a lens"): a Gaussian at depth U is blurred
by the image of the aperture at its circle of confusion C_r(U) = K |1/U - 1/P|; here by a
Gaussian of the aperture's own second moment (C_r^2 / 4 per axis for a disc: the disc's
variance; C_r^2 / (2 ln 4) for the paper's Gaussian bokeh), added to cov2d. The opacity is
spread so that the footprint's integral, alpha's energy, is kept: o' = o sqrt(det / det').
The trainers' cut (alpha below 1/255 is skipped) is kept on the sharp footprint's scale,
1/255 x sqrt(det / det'), so a blurred faint Gaussian is spread, not dropped. The viewers'
method (PlayCanvas splat-transform, Spark) is the baseline: C_r^2 added per axis and the cut
at 1/255 of the spread opacity.

A row of ``rows`` holds, for Gaussian i: the mean (x, y) in pixels, the depth z, the conic
(the inverse of cov2d: a, b, c with 1/2 d^T [[a, b], [b, c]] d the exponent), the opacity,
the alpha cut, the colour, the CoC radius (pixels). ``boxes`` holds the pixels it may
reach, [x0, x1) x [y0, y1), clipped to the image; ``visible`` whether it is drawn.
"""

from __future__ import annotations

import math

import numpy as np

from ..jit import numba
from .sh import sh_color

# row fields
F_X, F_Y, F_DEPTH, F_CA, F_CB, F_CC, F_OPACITY, F_CUT, F_R, F_G, F_B, F_COC = range(12)
N_FIELDS = 12

EPS2D = 0.3  # px^2: the trainers' low-pass (3DGS, gsplat's eps2d)
MIN_ALPHA = 1.0 / 255.0  # a pixel's alpha below this is skipped (the trainers' cut)
MAX_ALPHA = 0.999  # a Gaussian never covers a pixel wholly (the trainers' clamp)
CLAMP_MARGIN = 0.3  # the Jacobian's point is held within (1 + this) x the half field of view
BOX_SLACK = 0.01  # px: a box holds the pixels within its reach and this much more (float32)

BLUR_NONE, BLUR_OURS, BLUR_VIEWERS = 0, 1, 2  # how the lens blurs a footprint (module doc)


def intrinsics(camera) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy), pixels: x_px = fx x/z + cx, y_px = fy y/z + cy in the camera's
    x-right, y-down, z-forward frame (the glFrustum window of ``Camera``, sheared ones too)."""
    ax, bx, ay, by = camera.screen_coefficients()
    return ax, ay, bx, by


def view_matrix(camera) -> np.ndarray:
    """(4, 4) float64: world to the camera's x-right, y-down, z-forward frame (OpenCV's, as
    gsplat's viewmats): ``Camera.camera_from_world`` with y and z turned over."""
    return np.diag([1.0, -1.0, -1.0, 1.0]) @ camera.camera_from_world()


@numba.njit(cache=True, nogil=True, parallel=True)
def project_gaussians(positions, scales, rotations, opacity, sh, view, campos, fx, fy, cx, cy,
                      width, height, near, far, eps2d, antialiased, blur, coc_k, inv_focus,
                      blur_variance, share, rows, boxes, visible):
    """Fill rows (N, N_FIELDS) float32, boxes (N, 4) int32 and visible (N,) bool.

    positions, scales: (N, 3); rotations: (N, 4) unit (w, x, y, z); opacity: (N,);
    sh: (N, K, 3); view: (4, 4) float64 world -> camera (x right, y down, z forward);
    campos: (3,) float64, the centre of projection in world units; blur: BLUR_*; coc_k,
    inv_focus: C_r(U) = coc_k |1/U - 1/P|; blur_variance: the blur's variance per axis at
    C_r = 1 (1/4 for a disc); share: (N,) the visible share of each Gaussian over the lens
    (``backends.cpu_gauss.lens_visibility``), or (0,) for none.
    """
    for i in numba.prange(positions.shape[0]):
        project_gaussian(i, positions, scales, rotations, opacity, sh, view, campos, fx, fy,
                         cx, cy, width, height, near, far, eps2d, antialiased, blur, coc_k,
                         inv_focus, blur_variance, share, rows, boxes, visible)


@numba.njit(cache=True, nogil=True, inline="always")
def project_gaussian(i, positions, scales, rotations, opacity, sh, view, campos, fx, fy, cx,
                     cy, width, height, near, far, eps2d, antialiased, blur, coc_k, inv_focus,
                     blur_variance, share, rows, boxes, visible):
    """Gaussian i's row, box and visibility (``project_gaussians``'s, which see): the
    per-Gaussian maths that the CUDA backend compiles as a device function too."""
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + CLAMP_MARGIN * tan_x
    lim_x_neg = cx / fx + CLAMP_MARGIN * tan_x
    lim_y_pos = (height - cy) / fy + CLAMP_MARGIN * tan_y
    lim_y_neg = cy / fy + CLAMP_MARGIN * tan_y
    visible[i] = False
    px, py, pz = positions[i, 0], positions[i, 1], positions[i, 2]
    x = view[0, 0] * px + view[0, 1] * py + view[0, 2] * pz + view[0, 3]
    y = view[1, 0] * px + view[1, 1] * py + view[1, 2] * pz + view[1, 3]
    z = view[2, 0] * px + view[2, 1] * py + view[2, 2] * pz + view[2, 3]
    if not (z > near and z < far):
        return
    # Sigma = M M^T, M = R S (R from the unit quaternion)
    qw, qx, qy, qz = rotations[i, 0], rotations[i, 1], rotations[i, 2], rotations[i, 3]
    r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
    r01 = 2.0 * (qx * qy - qw * qz)
    r02 = 2.0 * (qx * qz + qw * qy)
    r10 = 2.0 * (qx * qy + qw * qz)
    r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
    r12 = 2.0 * (qy * qz - qw * qx)
    r20 = 2.0 * (qx * qz - qw * qy)
    r21 = 2.0 * (qy * qz + qw * qx)
    r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
    sx, sy, sz = scales[i, 0], scales[i, 1], scales[i, 2]
    # T = J W M: the 2 x 3 map from the Gaussian's own axes to pixels; cov2d = T T^T
    tx = z * min(lim_x_pos, max(-lim_x_neg, x / z))
    ty = z * min(lim_y_pos, max(-lim_y_neg, y / z))
    j00, j02 = fx / z, -fx * tx / (z * z)
    j11, j12 = fy / z, -fy * ty / (z * z)
    # rows of J W (2 x 3)
    a0 = j00 * view[0, 0] + j02 * view[2, 0]
    a1 = j00 * view[0, 1] + j02 * view[2, 1]
    a2 = j00 * view[0, 2] + j02 * view[2, 2]
    b0 = j11 * view[1, 0] + j12 * view[2, 0]
    b1 = j11 * view[1, 1] + j12 * view[2, 1]
    b2 = j11 * view[1, 2] + j12 * view[2, 2]
    # (J W) R S, column by column
    u0 = (a0 * r00 + a1 * r10 + a2 * r20) * sx
    u1 = (a0 * r01 + a1 * r11 + a2 * r21) * sy
    u2 = (a0 * r02 + a1 * r12 + a2 * r22) * sz
    v0 = (b0 * r00 + b1 * r10 + b2 * r20) * sx
    v1 = (b0 * r01 + b1 * r11 + b2 * r21) * sy
    v2 = (b0 * r02 + b1 * r12 + b2 * r22) * sz
    ca = u0 * u0 + u1 * u1 + u2 * u2
    cb = u0 * v0 + u1 * v1 + u2 * v2
    cc = v0 * v0 + v1 * v1 + v2 * v2
    det0 = ca * cc - cb * cb
    ca += eps2d
    cc += eps2d
    det = ca * cc - cb * cb
    if not det > 0.0:
        return
    o = opacity[i]
    if antialiased:
        o *= math.sqrt(max(det0 / det, 0.0))
    cut = MIN_ALPHA
    coc = coc_k * abs(1.0 / z - inv_focus)
    if blur != BLUR_NONE and coc > 0.0:
        var = blur_variance * coc * coc if blur == BLUR_OURS else coc * coc
        ca += var
        cc += var
        det_blur = ca * cc - cb * cb
        spread = math.sqrt(det / det_blur)
        o *= spread
        if blur == BLUR_OURS:
            cut = MIN_ALPHA * spread
            if share.shape[0] > 0:
                # as the blur outgrows the footprint, only the share of the Gaussian that
                # the lens sees is spread (what hides it in every view stays hidden)
                o *= share[i] ** (1.0 - spread)
        det = det_blur
    if o < cut:
        return
    # the box: alpha = min(MAX_ALPHA, o e^-s) >= cut needs s <= ln(o / cut), an ellipse
    # whose half-extents are sqrt(2 ln(o / cut) cov_xx) and sqrt(2 ln(o / cut) cov_yy)
    reach = 2.0 * math.log(o / cut)
    ex = math.sqrt(reach * ca) + BOX_SLACK
    ey = math.sqrt(reach * cc) + BOX_SLACK
    mx = fx * x / z + cx
    my = fy * y / z + cy
    x0 = max(math.ceil(mx - ex - 0.5), 0.0)
    x1 = min(math.floor(mx + ex - 0.5) + 1.0, float(width))
    y0 = max(math.ceil(my - ey - 0.5), 0.0)
    y1 = min(math.floor(my + ey - 0.5) + 1.0, float(height))
    if x0 >= x1 or y0 >= y1:
        return
    boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3] = int(x0), int(x1), int(y0), int(y1)
    # colour for the direction from the centre of projection to the mean
    dx = px - campos[0]
    dy = py - campos[1]
    dz = pz - campos[2]
    inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
    for ch in range(3):
        rows[i, F_R + ch] = max(sh_color(dx * inv, dy * inv, dz * inv, sh, i, ch), 0.0)
    rows[i, F_X] = mx
    rows[i, F_Y] = my
    rows[i, F_DEPTH] = z
    rows[i, F_CA] = cc / det
    rows[i, F_CB] = -cb / det
    rows[i, F_CC] = ca / det
    rows[i, F_OPACITY] = o
    rows[i, F_CUT] = cut
    rows[i, F_COC] = coc
    visible[i] = True


@numba.njit(cache=True, nogil=True, inline="always")
def move_footprint(i, j, rows, visible, out_rows, out_boxes, out_visible, shift_x, shift_y,
                   inv_focus, scale, margin, width, height):
    """Row i's footprint (``rows``, ``visible``) carried onto another image as row j of
    ``out_rows``, ``out_boxes``, ``out_visible`` (the same arrays and i == j move it in place):

        mean' = (mean + (shift_x, shift_y) (1/P - 1/z)) / scale + margin,
        cov2d' = cov2d / scale^2

    The shift is the view from another point of the lens (``camera.lens_camera``: a point at
    depth z moves by K (1/P - 1/z) (u_x, -u_y) pixels; inv_focus = 1/P), exact for the mean;
    the footprint's shape stays the projection's (the other view's Jacobian differs at second
    order). scale and margin put it on an image of 1/scale the resolution whose pixel
    (margin, margin) is the first of the image's own: the low-pass and the lens's blur, in
    the projection's pixels, are kept. The box is the projection's rule (the pixels where
    alpha can reach the row's cut), clipped to width x height."""
    if not visible[i]:
        out_visible[j] = False
        return
    mx = rows[i, F_X]
    my = rows[i, F_Y]
    z = rows[i, F_DEPTH]
    ca, cb, cc = rows[i, F_CA], rows[i, F_CB], rows[i, F_CC]
    # the covariance, from the conic, in the new image's pixels
    det_conic = ca * cc - cb * cb
    s2 = scale * scale
    cov_xx = cc / det_conic / s2
    cov_xy = -cb / det_conic / s2
    cov_yy = ca / det_conic / s2
    det = cov_xx * cov_yy - cov_xy * cov_xy
    parallax = inv_focus - 1.0 / z
    mx = (mx + shift_x * parallax) / scale + margin
    my = (my + shift_y * parallax) / scale + margin
    reach = 2.0 * math.log(rows[i, F_OPACITY] / rows[i, F_CUT])
    ex = math.sqrt(reach * cov_xx) + BOX_SLACK
    ey = math.sqrt(reach * cov_yy) + BOX_SLACK
    x0 = max(math.ceil(mx - ex - 0.5), 0.0)
    x1 = min(math.floor(mx + ex - 0.5) + 1.0, float(width))
    y0 = max(math.ceil(my - ey - 0.5), 0.0)
    y1 = min(math.floor(my + ey - 0.5) + 1.0, float(height))
    if x0 >= x1 or y0 >= y1:
        out_visible[j] = False
        return
    for f in range(N_FIELDS):
        out_rows[j, f] = rows[i, f]
    out_rows[j, F_X] = mx
    out_rows[j, F_Y] = my
    out_rows[j, F_CA] = cov_yy / det
    out_rows[j, F_CB] = -cov_xy / det
    out_rows[j, F_CC] = cov_xx / det
    out_rows[j, F_COC] = rows[i, F_COC] / scale
    out_boxes[j, 0], out_boxes[j, 1] = int(x0), int(x1)
    out_boxes[j, 2], out_boxes[j, 3] = int(y0), int(y1)
    out_visible[j] = True


@numba.njit(cache=True, nogil=True, parallel=True)
def project_shifted_views(positions, scales, rotations, opacity, sh, view, campos, fx, fy, cx,
                          cy, width, height, near, far, eps2d, antialiased, margin, shifts,
                          inv_focus, rows, boxes, visible, view_rows, view_boxes, view_visible):
    """Pinhole footprints seen from V points of the lens, from one projection: each
    Gaussian's ``project_gaussian`` (no blur) into rows, boxes, visible (an image of width x
    height whose margin pixels on each side lie outside the views: what moves into them is
    kept), then ``move_footprint``'d into view_rows (V N, N_FIELDS), view_boxes (V N, 4),
    view_visible (V N,): view v's row of Gaussian i is v N + i, on an image of (width - 2
    margin) x (height - 2 margin). shifts: (V, 2) each view's (shift_x, shift_y), pixels at
    1/P - 1/z = 1; inv_focus = 1/P. Each Gaussian's is ``project_shifted_view``'s."""
    no_share = np.zeros(0, np.float32)
    for i in numba.prange(positions.shape[0]):
        project_shifted_view(i, positions, scales, rotations, opacity, sh, view, campos, fx,
                             fy, cx, cy, width, height, near, far, eps2d, antialiased, margin,
                             shifts, inv_focus, no_share, rows, boxes, visible, view_rows,
                             view_boxes, view_visible)


@numba.njit(cache=True, nogil=True, inline="always")
def project_shifted_view(i, positions, scales, rotations, opacity, sh, view, campos, fx, fy,
                         cx, cy, width, height, near, far, eps2d, antialiased, margin, shifts,
                         inv_focus, no_share, rows, boxes, visible, view_rows, view_boxes,
                         view_visible):
    """Gaussian i of ``project_shifted_views`` (which see; no_share: any (0,) float32): the
    per-Gaussian maths that the CUDA backend compiles as a device function too."""
    n = positions.shape[0]
    out_w = width - 2 * margin
    out_h = height - 2 * margin
    project_gaussian(i, positions, scales, rotations, opacity, sh, view, campos, fx, fy, cx,
                     cy, width, height, near, far, eps2d, antialiased, BLUR_NONE, 0.0, 0.0, 0.0,
                     no_share, rows, boxes, visible)
    for v in range(shifts.shape[0]):
        move_footprint(i, v * n + i, rows, visible, view_rows, view_boxes, view_visible,
                       shifts[v, 0], shifts[v, 1], inv_focus, 1.0, -float(margin), out_w, out_h)
