"""Per-splat EWA maths (paper Sections 4.2, 5.1, 5.2, 6.2, Appendix A) as scalar functions.

Scalar functions on floats, each wrapped by ``shared``: numba-jitted for the CPU kernels
(dispatchers compile lazily, on first call, and are cached on disk); the plain Python
function stays reachable as ``.py_func`` so that a GPU backend can compile the very same
source as device functions. The two backends share one copy of the maths. The slow numpy twins in ``dofsplat.slow``
re-derive the same quantities independently, and the tests compare the two.

Screen conventions are those of ``dofsplat.camera``: x_px = a_x X/U + b_x,
y_px = -a_y Y/U + b_y with depth U = -Z in camera space.
"""

import math

from ..jit import numba

# jitted on first use; cache=True keeps the machine code between processes
shared = numba.njit(cache=True, nogil=True)
# the same, inlined into its callers at numba's level: the projection's per-splat functions,
# which LLVM would otherwise call out of line (a numba call passes every tuple and array
# through memory and checks a status: project_splats took 0.42-0.67 x the time inlined,
# bench/RESULTS.md, "The projection inlined")
shared_inline = numba.njit(cache=True, nogil=True, inline="always")

LN4 = math.log(4.0)
# 1 / (2 ln 4): the L2-best circular Gaussian variance for a uniform disc of radius 1 (eq. after 5.2)
DOF_VARIANCE_FACTOR = 1.0 / (2.0 * LN4)
# an aperture radius under this x the kernel's smallest sigma is drawn as the Gaussian of its
# second moment (splat/bokeh.py)
SMALL_APERTURE = 1.0


@shared
def coc_radius_px(depth, coc_k, inv_focus):
    """C_r = K |1/U - 1/P| pixels (eqs. 1-3 reduced; see camera.py)."""
    return coc_k * abs(1.0 / depth - inv_focus)


@shared
def dof_variance(coc_r):
    """V^I = C_r^2 / (2 ln 4), the circular DOF Gaussian's variance per axis (Section 5.2)."""
    return coc_r * coc_r * DOF_VARIANCE_FACTOR


@shared
def tangent_from_normal(nx, ny, nz):
    """A unit tangent perpendicular to the unit normal n: n x e, e the axis least aligned with n."""
    ax, ay, az = abs(nx), abs(ny), abs(nz)
    if ax <= ay and ax <= az:  # e = x
        tx, ty, tz = 0.0, nz, -ny
    elif ay <= az:  # e = y
        tx, ty, tz = -nz, 0.0, nx
    else:  # e = z
        tx, ty, tz = ny, -nx, 0.0
    inv = 1.0 / math.sqrt(tx * tx + ty * ty + tz * tz)
    return tx * inv, ty * inv, tz * inv


@shared
def tangent_frame(nx, ny, nz):
    """(u, v) as a 6-tuple: ``tangent_from_normal`` and n x u, a right-handed tangent frame."""
    ux, uy, uz = tangent_from_normal(nx, ny, nz)
    return ux, uy, uz, ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux


@shared_inline
def color_slope(p_world, n_world, grad, gain, view, ax, ay, w11, w12, w22, radius, ap_var):
    """A node's colour change per pixel, (r_x, r_y, g_x, g_y, b_x, b_y), for its kernel.

    grad: 6-tuple, the node's Cov(colour, position . t) in its world tangent frame
    (``lod/hierarchy.py``'s color_grad: r.u, r.v, g.u, g.v, b.u, b.v); gain: the shading's
    3-tuple factor on the colour (Phong is linear in it); W = (w11, w12, w22) the kernel's
    Gaussian variance and |radius| its aperture's radius (0 for none), pixels; ap_var the
    aperture's variance per axis at radius 1 (1/4 for the disc, (1 + 2 cos^2(pi/n)) / 12 for
    an n-gon of circumradius 1).

    The node stands for surfels spread about its mean, each splatted with the kernel; the
    colour they give at an offset d from the mean is the mean colour plus the colour
    gradient times the expected surfel offset given d, which for Gaussians is
    Cov(surfel, d) W_total^-1 d (docs/maths.md, "A node's colour gradient"): the slope is
    Cov(colour, screen position) W_total^-1, W_total = W + ap_var R^2 I the kernel's
    covariance (a disc of radius R has variance R^2 / 4 per axis).
    """
    px = view[0] * p_world[0] + view[1] * p_world[1] + view[2] * p_world[2] + view[3]
    py = view[4] * p_world[0] + view[5] * p_world[1] + view[6] * p_world[2] + view[7]
    pz = view[8] * p_world[0] + view[9] * p_world[1] + view[10] * p_world[2] + view[11]
    ux, uy, uz, vx, vy, vz = tangent_frame(n_world[0], n_world[1], n_world[2])
    # the tangent axes in camera space and their images on the screen
    cux = view[0] * ux + view[1] * uy + view[2] * uz
    cuy = view[4] * ux + view[5] * uy + view[6] * uz
    cuz = view[8] * ux + view[9] * uy + view[10] * uz
    cvx = view[0] * vx + view[1] * vy + view[2] * vz
    cvy = view[4] * vx + view[5] * vy + view[6] * vz
    cvz = view[8] * vx + view[9] * vy + view[10] * vz
    j11, j21 = jacobian_column(px, py, pz, cux, cuy, cuz, ax, ay)
    j12, j22 = jacobian_column(px, py, pz, cvx, cvy, cvz, ax, ay)
    extra = ap_var * radius * radius
    t11, t12, t22 = w11 + extra, w12, w22 + extra
    inv = 1.0 / (t11 * t22 - t12 * t12)
    i11, i12, i22 = t22 * inv, -t12 * inv, t11 * inv
    # per channel: m = Cov(colour, screen position) = J (Cov . u, Cov . v), slope = W^-1 m
    m0x = gain[0] * (j11 * grad[0] + j12 * grad[1])
    m0y = gain[0] * (j21 * grad[0] + j22 * grad[1])
    m1x = gain[1] * (j11 * grad[2] + j12 * grad[3])
    m1y = gain[1] * (j21 * grad[2] + j22 * grad[3])
    m2x = gain[2] * (j11 * grad[4] + j12 * grad[5])
    m2y = gain[2] * (j21 * grad[4] + j22 * grad[5])
    return (i11 * m0x + i12 * m0y, i12 * m0x + i22 * m0y,
            i11 * m1x + i12 * m1y, i12 * m1x + i22 * m1y,
            i11 * m2x + i12 * m2y, i12 * m2x + i22 * m2y)


@shared
def jacobian_column(px, py, pz, tx, ty, tz, ax, ay):
    """d(x_px, y_px)/ds along the camera-space tangent t at camera-space point p (pz < 0).

    Differentiating x = a_x X/U with U = -Z: dx = a_x (t_x U + X t_z) / U^2, and
    y = -a_y Y/U gives dy = -a_y (t_y U + Y t_z) / U^2.
    """
    u = -pz
    inv_u2 = 1.0 / (u * u)
    return ax * (tx * u + px * tz) * inv_u2, -ay * (ty * u + py * tz) * inv_u2


@shared
def circumellipse(m11, m12, m22, r):
    """Variance of the smallest ellipse containing the ellipse M and the circle r I (Appendix A).

    In M's eigenbasis the eigenvalues are clamped from below by r and the result is rotated
    back; the appendix's conic-coefficient route (eqs. 13-14) gives the same matrix
    (``dofsplat.slow.circumellipse_appendix`` is that route, and the tests compare them).
    """
    half_tr = 0.5 * (m11 + m22)
    diff = 0.5 * (m11 - m22)
    rad = math.sqrt(diff * diff + m12 * m12)
    l1 = half_tr + rad  # larger eigenvalue
    l2 = half_tr - rad
    if rad == 0.0:  # M is a circle: any basis is an eigenbasis
        lam = max(l1, r)
        return lam, 0.0, lam
    # unit eigenvector of l1: (m12, l1 - m11) or (l1 - m22, m12), whichever is longer
    vx, vy = l1 - m22, m12
    n2 = vx * vx + vy * vy
    if n2 < 1e-300:
        vx, vy = m12, l1 - m11
        n2 = vx * vx + vy * vy
    inv = 1.0 / math.sqrt(n2)
    c, s = vx * inv, vy * inv
    l1 = max(l1, r)
    l2 = max(l2, r)
    return (l1 * c * c + l2 * s * s, (l1 - l2) * c * s, l1 * s * s + l2 * c * c)


@shared_inline
def circumellipse_general(a11, a12, a22, b11, b12, b22):
    """Variance containing both ellipses A and B (B positive definite): circumellipse in B's frame.

    With B = L L^T (Cholesky), M = L^-1 A L^-T has its eigenvalues clamped from below by 1
    (the circle case of Appendix A) and the result is mapped back, L clamp(M) L^T. When B
    is a circle r I this is exactly ``circumellipse(A, r)``.
    """
    l11 = math.sqrt(b11)
    l21 = b12 / l11
    l22 = math.sqrt(max(b22 - l21 * l21, 1e-300))
    # M = L^-1 A L^-T with L^-1 = [[1/l11, 0], [-l21/(l11 l22), 1/l22]]
    i11, i21, i22 = 1.0 / l11, -l21 / (l11 * l22), 1.0 / l22
    m11 = i11 * i11 * a11
    m12 = i11 * (i21 * a11 + i22 * a12)
    m22 = i21 * i21 * a11 + 2.0 * i21 * i22 * a12 + i22 * i22 * a22
    n11, n12, n22 = circumellipse(m11, m12, m22, 1.0)
    # L N L^T
    return (l11 * l11 * n11, l11 * (l21 * n11 + l22 * n12),
            l21 * l21 * n11 + 2.0 * l21 * l22 * n12 + l22 * l22 * n22)


@shared_inline
def kernel_variance(j11, j12, j21, j22, su, sv, q11, q12, q22, v_dof):
    """Screen-space variance W of the blurred resampling kernel, (w11, w12, w22).

    J = [[j11, j12], [j21, j22]] maps the tangent-plane axes (u, v) to pixels;
    V^r = diag(su^2, sv^2) is the leaf basis variance; Q = [[q11, q12], [q12, q22]] is the
    LOD low-pass filter in screen space, J V^{q,l} J^T (0 at the leaves); v_dof is V^I.

        W = J V^r J^T + I + circumellipse(J V^{q,l} J^T, V^I + Q/3)     (eq. 12, Section 6.2)

    With Q = 0 this is eq. 11. For a node, Q/3 is the spread of its surfels about its mean
    position (hierarchy.py: V^q is 3 x their covariance), so V^I + Q/3 is the blur that the
    node's surfels, splatted one by one, would show (moment matching: without it, a node
    blurs less than its surfels would, and edges come out too sharp); the circumellipse
    keeps the blur at least the level's filter, which covers the space between nodes
    (docs/maths.md, "Level of detail").
    """
    a11, a21 = j11 * su, j21 * su
    a12, a22 = j12 * sv, j22 * sv
    w11 = a11 * a11 + a12 * a12 + 1.0
    w12 = a11 * a21 + a12 * a22
    w22 = a21 * a21 + a22 * a22 + 1.0
    if q11 > 0.0 or q22 > 0.0:
        # 1e-9: keeps B positive definite for a node that projects to a line at focus
        b11, b12, b22 = v_dof + q11 / 3.0 + 1e-9, q12 / 3.0, v_dof + q22 / 3.0 + 1e-9
        d11, d12, d22 = circumellipse_general(q11, q12, q22, b11, b12, b22)
    else:
        d11, d12, d22 = v_dof, 0.0, v_dof
    return w11 + d11, w12 + d12, w22 + d22


@shared_inline
def screen_lod_variance(px, py, pz, cov, view, ax, ay):
    """J V^{q,l} J^T for a world-space filter covariance, and its camera-depth variance.

    cov: 6-tuple (xx, xy, xz, yy, yz, zz) of the symmetric 3x3 world covariance; p the
    camera-space point (pz < 0). G = dProj/dp_camera . R (R: camera_from_world rotation)
    maps world offsets to pixels; returns (q11, q12, q22, var_depth) with Q = G cov G^T.
    """
    u = -pz
    inv_u = 1.0 / u
    # rows of dProj/dp in camera space: x: ax [1/U, 0, X/U^2]; y: -ay [0, 1/U, Y/U^2]
    fx, fz = ax * inv_u, ax * px * inv_u * inv_u
    gy, gz = -ay * inv_u, -ay * py * inv_u * inv_u
    g1x = fx * view[0] + fz * view[8]
    g1y = fx * view[1] + fz * view[9]
    g1z = fx * view[2] + fz * view[10]
    g2x = gy * view[4] + gz * view[8]
    g2y = gy * view[5] + gz * view[9]
    g2z = gy * view[6] + gz * view[10]
    cxx, cxy, cxz, cyy, cyz, czz = cov[0], cov[1], cov[2], cov[3], cov[4], cov[5]
    # cov . g for g = row 1, row 2, and the camera z axis (R row 3)
    h1x = cxx * g1x + cxy * g1y + cxz * g1z
    h1y = cxy * g1x + cyy * g1y + cyz * g1z
    h1z = cxz * g1x + cyz * g1y + czz * g1z
    h2x = cxx * g2x + cxy * g2y + cxz * g2z
    h2y = cxy * g2x + cyy * g2y + cyz * g2z
    h2z = cxz * g2x + cyz * g2y + czz * g2z
    zx, zy, zz = view[8], view[9], view[10]
    var_depth = (zx * (cxx * zx + cxy * zy + cxz * zz) + zy * (cxy * zx + cyy * zy + cyz * zz)
                 + zz * (cxz * zx + cyz * zy + czz * zz))
    return (g1x * h1x + g1y * h1y + g1z * h1z, g2x * h1x + g2y * h1y + g2z * h1z,
            g2x * h2x + g2y * h2y + g2z * h2z, var_depth)


@shared
def max_eigenvalue(a11, a12, a22):
    """Largest eigenvalue of the symmetric 2x2 matrix [[a11, a12], [a12, a22]]."""
    half_diff = 0.5 * (a11 - a22)
    return 0.5 * (a11 + a22) + math.sqrt(half_diff * half_diff + a12 * a12)


@shared
def conic(w11, w12, w22):
    """Inverse of W, (c11, c12, c22), and det W."""
    det = w11 * w22 - w12 * w12
    inv = 1.0 / det
    return w22 * inv, -w12 * inv, w11 * inv, det


@shared
def row_span(dy, c11, c12, c22, cutoff):
    """Interval (dx_lo, dx_hi) of offsets dx where 1/2 [dx dy] W^-1 [dx dy]^T < cutoff.

    Returns (1.0, -1.0), an empty interval, when the row misses the ellipse.
    """
    # c11 dx^2 + 2 c12 dy dx + c22 dy^2 - 2 cutoff < 0
    b = c12 * dy
    disc = b * b - c11 * (c22 * dy * dy - 2.0 * cutoff)
    if disc < 0.0:
        return 1.0, -1.0
    root = math.sqrt(disc)
    return (-b - root) / c11, (-b + root) / c11


@shared
def exponent(dx, dy, c11, c12, c22):
    """beta/2 = 1/2 x^T W^-1 x: the kernel is exp(-exponent), truncated where it reaches c."""
    return 0.5 * (c11 * dx * dx + 2.0 * c12 * dx * dy + c22 * dy * dy)


# A splat whose kernel or unblurred disk has a variance above this (px^2: sigma 1e8 px,
# 10^4 times the widest image) is dropped by ``project_surfel``: its conic, stored in
# float32, would underflow, and the rasteriser and the front pass divide by its
# determinant (a surfel radius of 1e30 a few units from the eye was a segmentation fault
# in the command line). Such a splat would wash the whole image in one colour.
MAX_SPLAT_VARIANCE = 1.0e16


@shared_inline
def project_surfel(p_world, n_world, t_world, ru, rv, area, view, ax, bx, ay, by, near,
                   coc_k, inv_focus, lod_cov, cutoff, z_margin, cull_backfaces, disc):
    """Project one surfel; everything but the kernel's pixel sum.

    p_world, n_world, t_world: 3-tuples (t_world = (0, 0, 0) for a circular surfel);
    ru, rv: disk radii along t and n x t (world units); area: the area the surfel stands
    for (world units^2, normalisation weight included); view: 12-tuple, rows of the 3x4
    camera_from_world matrix; lod_cov: 6-tuple (xx, xy, xz, yy, yz, zz), the world
    covariance of the LOD filter V^{q,l} (zeros for a surfel).

    disc: the aperture's shape is drawn (bokeh.py): W is then the unblurred kernel and
    |radius| the aperture's radius in pixels, negative before the focal plane (the image of
    the aperture turned by 180 degrees); else W carries the paper's Gaussian blur.

    Returns (ok, mx, my, w11, w12, w22, det_j, depth, z_lo, z_hi, coc_r, f11, f12, f22,
    gz_x, gz_y, radius): ok
    is False for a culled surfel (behind the near plane, or a back face when culling is on);
    F = (f11, f12, f22) is the unblurred disk J V^r J^T + J V^{q,l} J^T, the splat as a
    pinhole sees it, without the prefilter; (gz_x, gz_y) the depth change per pixel (x right,
    y down) along the tangent plane (the front pass of the A-buffer, raster/abuffer.py;
    (1e30, 0) for a plane seen edge-on).
    """
    px = view[0] * p_world[0] + view[1] * p_world[1] + view[2] * p_world[2] + view[3]
    py = view[4] * p_world[0] + view[5] * p_world[1] + view[6] * p_world[2] + view[7]
    pz = view[8] * p_world[0] + view[9] * p_world[1] + view[10] * p_world[2] + view[11]
    depth = -pz
    if depth <= near:
        return False, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, depth, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0
    nx = view[0] * n_world[0] + view[1] * n_world[1] + view[2] * n_world[2]
    ny = view[4] * n_world[0] + view[5] * n_world[1] + view[6] * n_world[2]
    nz = view[8] * n_world[0] + view[9] * n_world[1] + view[10] * n_world[2]
    if cull_backfaces and nx * px + ny * py + nz * pz >= 0.0:  # normal points away from the eye
        return False, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, depth, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0
    if t_world[0] == 0.0 and t_world[1] == 0.0 and t_world[2] == 0.0:
        tux, tuy, tuz = tangent_from_normal(nx, ny, nz)
    else:
        tux = view[0] * t_world[0] + view[1] * t_world[1] + view[2] * t_world[2]
        tuy = view[4] * t_world[0] + view[5] * t_world[1] + view[6] * t_world[2]
        tuz = view[8] * t_world[0] + view[9] * t_world[1] + view[10] * t_world[2]
    # t_v = n x t_u completes the right-handed tangent frame
    tvx = ny * tuz - nz * tuy
    tvy = nz * tux - nx * tuz
    tvz = nx * tuy - ny * tux

    mx = ax * px / depth + bx
    my = -ay * py / depth + by
    j11, j21 = jacobian_column(px, py, pz, tux, tuy, tuz, ax, ay)
    j12, j22 = jacobian_column(px, py, pz, tvx, tvy, tvz, ax, ay)
    det_j = abs(j11 * j22 - j12 * j21)

    # basis variance: the disk radius is the Gaussian's 2-sigma contour (surfels.py)
    su, sv = 0.5 * ru, 0.5 * rv
    coc_r = coc_radius_px(depth, coc_k, inv_focus)
    q11, q12, q22, q_depth = screen_lod_variance(px, py, pz, lod_cov, view, ax, ay)
    radius = 0.0  # the aperture's radius in the kernel (bokeh.py); 0: the paper's Gaussian
    # the unblurred kernel J V^r J^T + I
    b11, b12, b22 = kernel_variance(j11, j12, j21, j22, su, sv, 0.0, 0.0, 0.0, 0.0)
    if disc:
        # the Gaussian part is the unblurred kernel; the aperture is the disc C_r. A node's
        # surfels, each blurred by that disc, spread by Q/3 (their positions' covariance):
        # the node keeps the whole disc and a Gaussian of Q/3, and at least its filter Q
        # where the blur is too small to cover the space between nodes (Section 6.2's
        # circumellipse, the disc counted as its L2 Gaussian V^I): Q/3 + max(2Q/3 - V^I, 0)
        v_dof = dof_variance(coc_r)
        e11, e12, e22 = circumellipse(2.0 / 3.0 * q11 - v_dof, 2.0 / 3.0 * q12,
                                      2.0 / 3.0 * q22 - v_dof, 0.0)
        w11 = b11 + q11 / 3.0 + e11
        w12 = b12 + q12 / 3.0 + e12
        w22 = b22 + q22 / 3.0 + e22
        radius = coc_r
        # an aperture no wider than the kernel is the Gaussian of its second moment, to an
        # L1 distance under 0.01 (b = R / sigma_min < 1; docs/maths.md), and cheaper
        lam_min = w11 + w22 - max_eigenvalue(w11, w12, w22)
        if radius * radius < SMALL_APERTURE * SMALL_APERTURE * lam_min:
            w11 += 0.25 * radius * radius
            w22 += 0.25 * radius * radius
            radius = 0.0
        elif depth * inv_focus < 1.0:
            radius = -radius  # before the focal plane the aperture's image is upside down
    else:
        w11, w12, w22 = kernel_variance(j11, j12, j21, j22, su, sv, q11, q12, q22,
                                        dof_variance(coc_r))
    # the unblurred disk (what a pinhole sees, without the prefilter: a far sub-pixel disk
    # must not claim pixels beyond its own surface): the basis and a node's own filter
    f11, f12, f22 = b11 - 1.0 + q11 + 1e-6, b12 + q12, b22 - 1.0 + q22 + 1e-6
    if not (w11 + w22 + radius * radius <= MAX_SPLAT_VARIANCE
            and f11 + f22 <= MAX_SPLAT_VARIANCE):
        # a splat too wide to store (or NaN): dropped, as a culled one
        return False, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, depth, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0

    # z-range in camera space, not enlarged by the blur (Section 6.4): the truncated leaf
    # basis reaches sqrt(2c) sigma in depth; a node adds the depth spread of its surfels
    # (V^q / 3, their positional covariance: the z-ranges of its surfels, and no more, or
    # a curved node would merge with surfaces behind it); z_margin adds a thickness
    # proportional to the basis radius
    reach = math.sqrt(2.0 * cutoff)
    # q_depth of a flat node seen face-on rounds to about -1e-16: clamp, or the range is NaN
    var_z = max((su * tuz) ** 2 + (sv * tvz) ** 2 + q_depth / 3.0, 0.0)
    sigma_l = math.sqrt(max(su, sv) ** 2 + 0.5 * (lod_cov[0] + lod_cov[3] + lod_cov[5]))
    half = reach * math.sqrt(var_z) + z_margin * 2.0 * sigma_l
    # depth change per pixel along the tangent plane: (dU/du, dU/dv) J^-1 with U = -Z
    det_s = j11 * j22 - j12 * j21
    gx, gy = 1e30, 0.0
    if det_s != 0.0:
        gx = (-tuz * j22 + tvz * j21) / det_s
        gy = (tuz * j12 - tvz * j11) / det_s
    return (True, mx, my, w11, w12, w22, det_j * area, depth, depth - half, depth + half, coc_r,
            f11, f12, f22, gx, gy, radius)


# -- pixel footprint of a truncated kernel ----------------------------------------------

COORD_LIMIT = 1.0e9  # clamp screen coordinates before converting them to int


# rows of a bbox narrower than this are scanned whole: cheaper than solving for the span
# (a square root, and two exps to restart the forward differences, per row: 8 here took
# 1.9 x as long to normalise the pinhole kernels, then 8-11 pixels wide in the box rounded
# outwards; kernel_bbox's)
NARROW_BBOX = 16
# kernel_pixel_sum's recurrence down the rows of a narrow kernel: at most this many rows
# (taller kernels restart each row). Its q stays far from exp's range: W >= I (the
# prefilter), so q = x^T W^-1 x / 2 <= |x|^2 / 2 <= (16^2 + 24^2) / 2 = 416 over the
# bbox, and exp(-416) ~ 1e-181 is a normal float64
NARROW_ROWS = 24


@shared
def row_pixel_range(i, mx, my, c11, c12, c22, cutoff, x0, x1):
    """Inclusive pixel columns (j0, j1) of row i that may lie inside the truncated kernel.

    x0, x1: the kernel's unclipped bbox columns. Narrow kernels scan the whole bbox row;
    wider ones solve for the row's span, one pixel wider on each side. Either way the
    per-pixel test ``exponent < cutoff`` decides, identically in every implementation.
    """
    if x1 - x0 < NARROW_BBOX:
        return x0, x1
    lo, hi = row_span(i + 0.5 - my, c11, c12, c22, cutoff)
    if lo > hi:
        return 1, 0
    j0 = math.floor(max(mx + lo - 0.5, -COORD_LIMIT))
    j1 = math.ceil(min(mx + hi - 0.5, COORD_LIMIT))
    return int(j0), int(j1)


# The rasteriser reads a splat's mean and conic from its row, float32 on the CPU: a pixel
# centre that the float64 projection puts a hair outside the cutoff may lie inside it
# there (1 of 200,000 random splats drew such a pixel, a review's scan). Boxes are wider by
# this many pixels, and by BOX_SLACK_REL of the reach and of the coordinate (float32's
# 6e-8, with room): no centre farther than that from the cutoff is ever inside
BOX_SLACK = 1e-3
BOX_SLACK_REL = 1e-6


@shared
def pixel_bbox(mx, my, hx, hy):
    """Unclipped inclusive pixel bbox (x0, x1, y0, y1) of the pixel centres (j + 1/2,
    i + 1/2) that lie within hx, hy of (mx, my) along each axis (and BOX_SLACK): the pixels
    that a kernel reaching that far may draw, and no others but those within the slack."""
    hx += BOX_SLACK + BOX_SLACK_REL * (hx + abs(mx))
    hy += BOX_SLACK + BOX_SLACK_REL * (hy + abs(my))
    x0 = math.ceil(max(mx - hx - 0.5, -COORD_LIMIT))
    x1 = math.floor(min(mx + hx - 0.5, COORD_LIMIT))
    y0 = math.ceil(max(my - hy - 0.5, -COORD_LIMIT))
    y1 = math.floor(min(my + hy - 0.5, COORD_LIMIT))
    return int(x0), int(x1), int(y0), int(y1)


@shared
def kernel_bbox(mx, my, w11, w22, cutoff):
    """Unclipped inclusive pixel bbox (x0, x1, y0, y1) of the Gaussian truncated at cutoff:
    where 1/2 x^T W^-1 x < cutoff, |x_i| < sqrt(2 cutoff W_ii). (The aperture's kernels:
    ``bokeh.support_bbox``.)"""
    return pixel_bbox(mx, my, math.sqrt(2.0 * cutoff * w11), math.sqrt(2.0 * cutoff * w22))


@shared
def row_start(j, i, mx, my, c11, c12, c22):
    """Exponent q, its step dq to pixel j + 1, and exp(-q), exp(-dq) at pixel (i, j).

    Along a row the exponent is quadratic in j, so q(j+1) = q(j) + dq(j) and
    dq(j+1) = dq(j) + c11: the kernel then needs two multiplications per pixel instead of
    an exp (forward differencing; ``exp(-c11)`` is the step's own factor).
    """
    dx = j + 0.5 - mx
    dy = i + 0.5 - my
    q = exponent(dx, dy, c11, c12, c22)
    dq = c11 * dx + 0.5 * c11 + c12 * dy
    return q, dq, math.exp(-q), math.exp(-dq)


@shared
def column_start(j, i, mx, my, c11, c12, c22):
    """``row_start`` at pixel (i, j), and what carries it down the column to (i + 1, j):
    (q, dq, e, f, dqc, g, step_g, step_f) for ``column_step``. Down a column q grows by
    dqc = q(i + 1, j) - q(i, j), itself growing by c22 a row, and dq by c12; e = exp(-q)
    and f = exp(-dq) by the factors g = exp(-dqc), step_g = exp(-c22) and step_f =
    exp(-c12): six exps for a kernel whose rows all start at column j."""
    q, dq, e, f = row_start(j, i, mx, my, c11, c12, c22)
    dqc = c22 * (i + 0.5 - my) + 0.5 * c22 + c12 * (j + 0.5 - mx)
    return q, dq, e, f, dqc, math.exp(-dqc), math.exp(-c22), math.exp(-c12)


@shared
def column_step(col, c12, c22):
    """``column_start``'s values one row down (forward differences; to ~1e-14 of a fresh
    ``row_start`` over NARROW_ROWS rows)."""
    q, dq, e, f, dqc, g, step_g, step_f = col
    return q + dqc, dq + c12, e * g, f * step_f, dqc + c22, g * step_g, step_g, step_f


@shared_inline
def kernel_pixel_sum(mx, my, c11, c12, c22, cutoff, x0, x1, y0, y1, floor):
    """Sum of exp(-exponent) - floor over all pixel centres inside the truncated kernel
    (unclipped); floor = e^-c tapers the kernel to 0 at its cutoff, 0 keeps the paper's step."""
    total = 0.0
    step2 = math.exp(-c11)
    if x1 - x0 < NARROW_BBOX and y1 - y0 < NARROW_ROWS:
        # every row is scanned whole from x0: the row's first value and step follow from
        # the previous row's by forward differences down the column too (column_start:
        # six exps per kernel instead of two per row)
        col = column_start(x0, y0, mx, my, c11, c12, c22)
        for _ in range(y0, y1 + 1):
            total += row_sum(col[0], col[1], col[2], col[3], x1 - x0 + 1, c11, step2, cutoff,
                             floor)
            col = column_step(col, c12, c22)
        return total
    for i in range(y0, y1 + 1):
        j0, j1 = row_pixel_range(i, mx, my, c11, c12, c22, cutoff, x0, x1)
        if j0 > j1:
            continue
        q, dq, e, f = row_start(j0, i, mx, my, c11, c12, c22)
        total += row_sum(q, dq, e, f, j1 - j0 + 1, c11, step2, cutoff, floor)
    return total


@numba.njit(cache=True, nogil=True, inline="always")
def row_sum(q, dq, e, f, n, c11, step2, cutoff, floor):
    """Sum of exp(-q) - floor over n pixels of a row where q < cutoff, from the first
    pixel's q, its step dq, e = exp(-q) and f = exp(-dq) (``row_start``): forward differences,
    q and dq growing by dq and c11, e and f by the factors f and step2 = exp(-c11)."""
    total = 0.0
    for _ in range(n):
        if q < cutoff:
            total += e - floor
        q += dq
        dq += c11
        e *= f
        f *= step2
    return total
