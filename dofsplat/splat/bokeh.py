"""The aperture's shape in every splat: a Gaussian kernel convolved with a disc or a polygon.

A real lens blurs a point into the image of its aperture: a uniform disc of radius C_r (the
circle of confusion), or a regular polygon where the aperture has straight blades. The paper
replaces it by a Gaussian of variance C_r^2 / (2 ln 4) (Section 5.2); ``bokeh="gaussian"``
keeps that. With ``bokeh="disc"`` (the default) a splat's kernel is its unblurred Gaussian
resampling kernel G_W (W = J V^r J^T + I, plus an LOD node's filter) convolved with the
uniform disc of radius R = C_r.

**The form.** For an isotropic W = s^2 I the convolution is radial, and in units of s it is

    (G * disc_b)(d) / (G * disc_b)(0) = (1 - Q_1(d, b)) / (1 - exp(-b^2 / 2)) =: T(d, b),

d the distance from the centre and b = R / s (Q_1: Marcum's Q function; 1 - Q_1(d, b) is the
probability that a unit 2-D Gaussian centred at distance d lies inside the disc of radius b,
scipy's non-central chi-square ``ncx2.cdf(b^2, 2, d^2)``). For a general W we evaluate T in
W's whitened units along the direction n of the offset x:

    d = sqrt(x^T W^-1 x),    b = R(n) sqrt(n^T W^-1 n) = R(n) d / |x|,

R(n) the aperture's radius in that direction (R for a disc). This is exact for a circular W,
exact at R = 0 (T(d, 0) = exp(-d^2/2), the Gaussian), exact deep inside the disc (1) and on
the edge's profile for a circular W; for an elongated W it errs by how much the Gaussian's
profile across the edge differs from its profile along n (docs/maths.md bounds it; the tests
measure it against a numerical convolution). The kernel is normalised over its pixels like
every kernel (``ewa.kernel_pixel_sum``), so its shape, not its mass, is what T decides.

**The table.** T is tabulated once per cutoff on a grid of (u = d - b, b): u from -B_MAX to
the cutoff sqrt(2c), b from 0 to B_MAX (beyond, the disc is so much wider than the Gaussian
that the edge no longer depends on b: column B_MAX is used). Values are tapered so that the
kernel falls continuously to 0 at the cutoff (no hard-edged discs), by
T - s(b) T(u_c, b), s = smoothstep(b; 0, 1): at b = 0 (in focus) the paper's truncated
Gaussian stays as it was.

**Polygons.** A regular N-gon of circumradius R, rotated by theta_0: its radius in the
direction n is R_in / max_i (n_i . n), R_in = R cos(pi/N) the inradius, n_i the unit normals
of its edges.
"""

from __future__ import annotations

import math

from ..jit import numba
import numpy as np

from .ewa import pixel_bbox, shared

# the per-fragment functions are inlined at numba's level, like the Gaussian's forward
# differences: a call per fragment costs as much as the kernel
shared_inline = numba.njit(cache=True, nogil=True, inline="always")

B_MAX = 8.0  # disc radius in Gaussian sigmas beyond which the edge profile no longer changes
TABLE_B = 65  # columns over b in [0, B_MAX]
TABLE_U = 321  # rows over u in [-B_MAX, sqrt(2c)]
# a disc kernel's mass as a table (``aperture_mass``): rows over ln(l2 / l1), W's eigenvalue
# ratio, from ln(MASS_E_MIN) to 0; columns over v = sigma / (sigma + R), sigma^2 = tr W / 2,
# from 0 (a disc far wider than the Gaussian) to 1 (the Gaussian)
MASS_E = 49
MASS_V = 65
MASS_E_MIN = 1.0 / 1024.0  # more elongated kernels (grazing splats) take the quadrature
MASS_TABLE_ANGLES = 128  # directions per family of the quadrature that builds the table

_TABLES: dict = {}


def aperture_table(cutoff: float) -> np.ndarray:
    """(TABLE_B, TABLE_U) float64: the tapered T(u, b) for kernels cut at sqrt(2c) (module notes)."""
    key = float(cutoff)
    table = _TABLES.get(key)
    if table is None:
        from scipy.stats import ncx2

        u_c = math.sqrt(2.0 * key)
        b = np.linspace(0.0, B_MAX, TABLE_B)[:, None]
        u = np.linspace(-B_MAX, u_c, TABLE_U)[None, :]
        d = np.maximum(u + b, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            inside = ncx2.cdf(b * b, 2, d * d) / -np.expm1(-0.5 * b * b)
        gauss = np.exp(-0.5 * d * d)
        t = np.where(b > 0, inside, gauss)
        t = np.clip(np.nan_to_num(t, nan=1.0), 0.0, 1.0)
        x = np.clip(b, 0.0, 1.0)
        s = x * x * (3.0 - 2.0 * x)
        table = np.clip(t - s * t[:, -1:], 0.0, None)
        table[:, -1] = np.where(b[:, 0] > 0, table[:, -1], t[:, -1])
        table = np.ascontiguousarray(table)
        _TABLES[key] = table
    return table


def aperture_moments(cutoff: float) -> np.ndarray:
    """(TABLE_B + MASS_E, MASS_V) float64, two tables in one array (one argument for the
    kernels of both backends):

    * rows [0, TABLE_B), columns 0-2: I0(b) = int T(u, b) du and I1(b) = int T(u, b) u du
      over u in [-b, sqrt(2c)] (r >= 0), per column b of ``aperture_table``, and
      T(-B_MAX, b): a kernel's mass along a direction is (I1 + b I0) / s^2;
    * rows [TABLE_B, TABLE_B + MASS_E): a disc kernel's mass over pi (R^2 + 2 sqrt|W|) by
      W's eigenvalue ratio and sigma / (sigma + R) (``aperture_mass``; ``mass_table``)."""
    key = ("moments", float(cutoff))
    moments = _TABLES.get(key)
    if moments is None:
        table = aperture_table(cutoff)
        u_c = math.sqrt(2.0 * cutoff)
        u = np.linspace(-B_MAX, u_c, TABLE_U)
        b = np.linspace(0.0, B_MAX, TABLE_B)
        moments = np.zeros((TABLE_B + MASS_E, MASS_V))
        moments[:TABLE_B, 2] = table[:, 0]
        fine = np.linspace(0.0, 1.0, 4001)
        trapezoid = getattr(np, "trapezoid", None) or np.trapz  # numpy < 2 has only trapz
        for k in range(TABLE_B):
            uu = -b[k] + (u_c + b[k]) * fine  # u from -b to the cutoff
            t = np.interp(uu, u, table[k])
            moments[k, 0] = trapezoid(t, uu)
            moments[k, 1] = trapezoid(t * uu, uu)
        mass_table(moments)
        moments = np.ascontiguousarray(moments)
        _TABLES[key] = moments
    return moments


def blade_normals(blades: int, rotation_deg: float) -> np.ndarray:
    """(N, 2) float64 unit normals of a regular N-gon's edges (x right, y down in pixels),
    or (0, 2) for a round aperture (blades 0)."""
    if blades == 0:
        return np.zeros((0, 2))
    # the first vertex at the rotation angle; edge normals halfway between vertices
    a = math.radians(rotation_deg) + (np.arange(blades) + 0.5) * (2.0 * math.pi / blades)
    return np.ascontiguousarray(np.stack([np.cos(a), -np.sin(a)], axis=1))


@shared_inline
def direction_radius(dx, dy, rr, radius, normals):
    """The aperture's radius along the offset (dx, dy) of length rr > 0 (pixels)."""
    n = normals.shape[0]
    if n == 0:
        return radius
    best = -1.0
    for i in range(n):
        c = (normals[i, 0] * dx + normals[i, 1] * dy) / rr
        if c > best:
            best = c
    return radius * math.cos(math.pi / n) / best


@shared_inline
def table_cell(u, b, u_c):
    """Where T(u, b) lies in ``aperture_table``: (i_b, i_u, t_b, t_u), the cell's first row
    and column and the fractions along b and u. u below the table reads its first column,
    the disc's plateau. Branch-free."""
    fu = min(max((u + B_MAX) * ((TABLE_U - 1) / (u_c + B_MAX)), 0.0), TABLE_U - 1.000001)
    fb = min(b, B_MAX) * ((TABLE_B - 1) / B_MAX)
    ib = min(np.int32(fb), TABLE_B - 2)
    iu = np.int32(fu)
    return ib, iu, fb - ib, fu - iu


@shared_inline
def table_index(u, b, u_c):
    """``table_cell`` in the flattened table: (k, t_b, t_u), k = i_b TABLE_U + i_u, or -1
    from the cutoff on (T = 0 there)."""
    ib, iu, tb, tu = table_cell(u, b, u_c)
    return -1 if u >= u_c else ib * TABLE_U + iu, tb, tu


@shared_inline
def table_lerp(k, tb, tu, flat):
    """T by bilinear interpolation in the cell ``table_index`` found (``flat``: the table
    flattened)."""
    if k < 0:
        return 0.0
    v0 = flat[k] + tu * (flat[k + 1] - flat[k])
    v1 = flat[k + TABLE_U] + tu * (flat[k + TABLE_U + 1] - flat[k + TABLE_U])
    return v0 + tb * (v1 - v0)


@shared_inline
def table_value(u, b, table, u_c):
    """T(u, b) by bilinear interpolation in ``aperture_table`` (0 from the cutoff on)."""
    if u >= u_c:
        return 0.0
    ib, iu, tb, tu = table_cell(u, b, u_c)
    v0 = table[ib, iu] + tu * (table[ib, iu + 1] - table[ib, iu])
    v1 = table[ib + 1, iu] + tu * (table[ib + 1, iu + 1] - table[ib + 1, iu])
    return v0 + tb * (v1 - v0)


@shared
def edge_mix(radius, w11, w22):
    """lambda in [0, 1): how far a kernel is a wide aperture (1) rather than a Gaussian (0)."""
    r2 = radius * radius  # (radius may be negative: signed as in aperture_kernel)
    return r2 / (r2 + 0.5 * (w11 + w22))


@shared
def aperture_kernel(q, dx, dy, radius, w11, w12, w22, mix, normals, table, u_c):
    """The kernel at offset (dx, dy) from the splat's centre (module notes).

    q = 1/2 x^T W^-1 x; (w11, w12, w22) = W; radius < 0: the aperture turned by 180 degrees
    (a point before the focal plane); mix = ``edge_mix``.
    """
    return aperture_value(2.0 * q, w11 * dx * dx + 2.0 * w12 * dx * dy + w22 * dy * dy, dx, dy,
                          radius, mix, normals, table, u_c,
                          w22 / (w11 * w22 - w12 * w12), w11)


@shared_inline
def aperture_value(q2, p, dx, dy, radius, mix, normals, table, u_c, c11, w11):
    """``aperture_kernel`` from q2 = x^T W^-1 x and p = x^T W x: the scale along the
    offset's direction n moves from s_G = sqrt(n^T W^-1 n) (the Gaussian, exact at R = 0)
    to s_E = 1 / sqrt(n^T W n) (the Gaussian's profile across a wide aperture's edge) as
    ``mix`` goes from 0 to 1. c11 = (W^-1)_11 and w11 = W_11 give the scales along x, which
    the centre (x = 0, no direction) takes: its value is T(-b, b) of that direction.
    """
    r2 = dx * dx + dy * dy
    rr = 0.0
    if r2 <= 0.0:
        q2, p, r2, dx, dy = c11, w11, 1.0, 1.0, 0.0
    else:
        rr = math.sqrt(r2)
    if radius < 0.0:
        radius, dx, dy = -radius, -dx, -dy
    inv_r = 1.0 / math.sqrt(r2)
    s_gauss = math.sqrt(q2) * inv_r
    s_edge = math.sqrt(r2 / p)
    s = s_gauss + mix * (s_edge - s_gauss)
    rad = direction_radius(dx * inv_r, dy * inv_r, 1.0, radius, normals)
    return table_value((rr - rad) * s, rad * s, table, u_c)


# the disc rows' flags: no NaN or infinity reaches them (the centre is selected out), so
# LLVM may reorder and contract them and run them in SIMD lanes; with numba's "numpy" error
# model a division does not check for zero (that branch alone keeps a loop scalar)
ROW_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}
ROW_SHIFT = 4
ROW = 1 << ROW_SHIFT  # the rows of ``aperture_rows`` are this many pixels wide (a tile's)


@numba.njit(cache=True, nogil=True, fastmath=ROW_FASTMATH, error_model="numpy")
def aperture_rows(cell, frac, rows, dx0, dy0, radius, c11, c12, c22, w11, w12, w22, mix, u_c,
                  step):
    """The table cells (``table_index``) of ``aperture_value`` (round aperture) at ROW x rows
    pixels, offsets (dx0 + step j, dy0 + step i): cell[e] and frac[0, e], frac[1, e] with
    e = i ROW + j; ``table_lerp`` reads the kernel from them. step: 1, or 2 for the coarse
    samples of ``abuffer.rasterize_band``.

    One flat loop over whole rows, each pixel from its offset (no forward differences, which
    chain one pixel to the next) and without a branch, so that it runs in SIMD lanes; the
    lanes outside a row's span cost less than a scalar loop over the span
    (bench/RESULTS.md). The centre (x = 0) takes the scales along x (``aperture_value``)."""
    # in float32, the table's cell too (table_index's steps): twice the SIMD lanes of
    # float64, and frames equal to ~1e-7 (bench/RESULTS.md). Calling table_index, with its
    # conversion to float64 on the way, cost all of that back.
    f32 = np.float32
    rad = f32(abs(radius))  # a disc is its own image turned by 180 degrees
    x0, y0, st = f32(dx0), f32(dy0), f32(step)
    a11, a12, a22 = f32(c11), f32(c12), f32(c22)
    v11, v12, v22 = f32(w11), f32(w12), f32(w22)
    m, uc = f32(mix), f32(u_c)
    su = f32((TABLE_U - 1) / (u_c + B_MAX))
    sb = f32((TABLE_B - 1) / B_MAX)
    bmax, top = f32(B_MAX), f32(TABLE_U - 1)
    for e in range(rows * ROW):
        dx = x0 + st * f32(e & (ROW - 1))
        dy = y0 + st * f32(e >> ROW_SHIFT)
        r2 = dx * dx + dy * dy
        centre = r2 <= f32(0.0)
        q2 = a11 if centre else a11 * dx * dx + f32(2.0) * a12 * dx * dy + a22 * dy * dy
        p = v11 if centre else v11 * dx * dx + f32(2.0) * v12 * dx * dy + v22 * dy * dy
        r2 = f32(1.0) if centre else r2
        rr = math.sqrt(r2)
        s_gauss = math.sqrt(q2) / rr
        s_edge = math.sqrt(r2 / p)
        s = s_gauss + m * (s_edge - s_gauss)
        rr = f32(0.0) if centre else rr
        u = (rr - rad) * s
        b = rad * s
        fu = min(max((u + bmax) * su, f32(0.0)), top)
        fb = min(b, bmax) * sb
        ib = min(np.int32(fb), TABLE_B - 2)
        # clamped as ib is: float32 rounds table_cell's TABLE_U - 1.000001 up to the last
        # column, whose cell would read the next row (past the table's end from the last)
        iu = min(np.int32(fu), TABLE_U - 2)
        cell[e] = -1 if u >= uc else ib * TABLE_U + iu
        frac[0, e] = fb - f32(ib)
        frac[1, e] = fu - f32(iu)


@shared
def support_conic(w11, w12, w22, radius, u_c):
    """The conic (inverse variance) of an ellipse that contains an aperture kernel's
    support (docs/maths.md, "The support"). Along a direction n the support ends at
    |x| = |R(n)| + u_c / s(n) <= |R| + u_c h(n), h(n) = sqrt(n^T W n) (both scales satisfy
    1/s <= h), and (|R| + u_c h)^2 <= n^T G n with G = (1 + 1/k) R^2 I + (1 + k) u_c^2 W,
    k = |R| / (u_c sqrt(l1)), l1 >= l2 W's eigenvalues: the support lies in the pedal region
    of the ellipse of G, whose semi-axes are g1 = |R| + u_c sqrt(l1) and g2 along W's
    eigenvectors, and that region lies in the ellipse of semi-axes g1 and
    g1^2 / sqrt(2 g1^2 - g2^2). Rows are scanned over this ellipse (``row_span`` with
    cutoff 1/2) instead of over the circle of ``reach``."""
    half_tr = 0.5 * (w11 + w22)
    diff = 0.5 * (w11 - w22)
    rad = math.sqrt(diff * diff + w12 * w12)
    l1 = half_tr + rad
    l2 = max(half_tr - rad, 0.0)
    # unit eigenvector of l1
    vx, vy = l1 - w22, w12
    n2 = vx * vx + vy * vy
    if n2 < 1e-300:
        vx, vy = 1.0, 0.0
        if w22 > w11:
            vx, vy = 0.0, 1.0
    else:
        inv = 1.0 / math.sqrt(n2)
        vx, vy = vx * inv, vy * inv
    r = abs(radius)
    s1 = math.sqrt(l1)
    g1 = r + u_c * s1
    g2sq = r * r + r * u_c * s1 + u_c * u_c * l2 + r * u_c * l2 / s1
    ia = 1.0 / (g1 * g1)
    ib = (2.0 * g1 * g1 - g2sq) / (g1 * g1 * g1 * g1)  # 1 / b^2
    return ia * vx * vx + ib * vy * vy, (ia - ib) * vx * vy, ia * vy * vy + ib * vx * vx


@shared
def support_bbox(mx, my, w11, w12, w22, radius, mix, u_c):
    """Unclipped inclusive pixel bbox (x0, x1, y0, y1) of an aperture kernel's support. Along
    a direction n the support ends at |R(n)| + u_c / s(n) <= |R| + u_c h(n) (``aperture_value``,
    ``support_conic``), so it lies inside three shapes, and the box is the smallest of
    theirs along each axis: ``support_conic``'s ellipse; the circle of its reach
    |R| + u_c sqrt(l1) (l1: W's larger eigenvalue); and, as s >= (1 - mix) s_G with 1 / s_G
    the radial function of W's ellipse, the box |R| + u_c sqrt(W_ii) / (1 - mix), which
    is the tightest across an elongated kernel with an aperture not much wider (mix is
    ``edge_mix``). (The Gaussian's box widened by |R|, the box until 2026-11-27, does not
    hold the support: where the kernel's edge follows the aperture, the support reaches past
    it, by up to a pixel in the suite's frames and 4 px in a scan of random kernels.)"""
    b11, b12, b22 = support_conic(w11, w12, w22, radius, u_c)
    det = b11 * b22 - b12 * b12
    half_tr = 0.5 * (w11 + w22)
    diff = 0.5 * (w11 - w22)
    reach = abs(radius) + u_c * math.sqrt(half_tr + math.sqrt(diff * diff + w12 * w12))
    hx = min(math.sqrt(b22 / det), reach)
    hy = min(math.sqrt(b11 / det), reach)
    if mix < 1.0:
        hx = min(hx, abs(radius) + u_c * math.sqrt(w11) / (1.0 - mix))
        hy = min(hy, abs(radius) + u_c * math.sqrt(w22) / (1.0 - mix))
    return pixel_bbox(mx, my, hx, hy)


MASS_ANGLES = 16  # directions of each of the two families of aperture_mass (x 2: polygons)


@shared_inline
def mass_direction(nx, ny, radius, c11, c12, c22, w11, w12, w22, sqrt_det, mix, normals,
                   moments, plateau):
    """The mass integrand along the unit direction n, 2 pi f(n) / (1 + p_G(n) / p_U), for
    ``aperture_mass``: f = (I1(b) + b I0(b)) / s^2, p_U = 1 / 2 pi, p_G the density of the
    directions that whiten W."""
    g = c11 * nx * nx + 2.0 * c12 * nx * ny + c22 * ny * ny  # n^T W^-1 n
    s_gauss = math.sqrt(g)
    s_edge = 1.0 / math.sqrt(w11 * nx * nx + 2.0 * w12 * nx * ny + w22 * ny * ny)
    s = s_gauss + mix * (s_edge - s_gauss)
    b = direction_radius(nx, ny, 1.0, radius, normals) * s
    if b >= B_MAX:  # the plateau, u from -b to -B_MAX, reads the table's first column
        i0 = moments[TABLE_B - 1, 0] + plateau * (b - B_MAX)
        i1 = moments[TABLE_B - 1, 1] - 0.5 * plateau * (b * b - B_MAX * B_MAX)
    else:
        fb = b * ((TABLE_B - 1) / B_MAX)
        ib = min(int(fb), TABLE_B - 2)
        tb = fb - ib
        i0 = moments[ib, 0] + tb * (moments[ib + 1, 0] - moments[ib, 0])
        i1 = moments[ib, 1] + tb * (moments[ib + 1, 1] - moments[ib, 1])
    return 2.0 * math.pi * (i1 + b * i0) / (s * s) / (1.0 + 1.0 / (sqrt_det * g))


# per splat, on the CPU: without numba's zero-division checks (a branch per division; W is
# positive definite and s > 0, so none can divide by zero) the loop pipelines
@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def aperture_mass(radius, w11, w12, w22, mix, normals, moments):
    """The integral of ``aperture_kernel`` over the plane (pixels^2). A disc's is read from
    a table (``mass_table``): the kernel scales with W and R together (x -> k x, W -> k^2 W,
    R -> k R multiplies the mass by k^2) and a disc turns with W, so its mass is
    pi (R^2 + 2 sqrt|W|) H(l2 / l1, sigma / (sigma + R)), l1 >= l2 W's eigenvalues and
    sigma^2 = tr W / 2; H is smooth, bilinear in (ln(l2 / l1), sigma / (sigma + R)) on a
    49 x 65 grid (within 6.8e-4 of a 4096-direction quadrature over 3000 random
    kernels; tests/test_bokeh.py bounds it by 1.5e-3). A
    polygon (which does not turn with W) and a kernel more elongated than 1 / MASS_E_MIN
    take the quadrature (``aperture_mass_quadrature``)."""
    if normals.shape[0] == 0:
        half_tr = 0.5 * (w11 + w22)
        d = math.sqrt(0.25 * (w11 - w22) * (w11 - w22) + w12 * w12)
        l1, l2 = half_tr + d, half_tr - d
        if l2 >= MASS_E_MIN * l1:
            r = abs(radius)
            sigma = math.sqrt(half_tr)
            fe = (math.log(l2 / l1) / math.log(MASS_E_MIN)) * (MASS_E - 1)  # 0 at l2 = l1
            ie = min(int(fe), MASS_E - 2)
            te = fe - ie
            fv = sigma / (sigma + r) * (MASS_V - 1)
            iv = min(int(fv), MASS_V - 2)
            tv = fv - iv
            row0, row1 = TABLE_B + ie, TABLE_B + ie + 1
            h0 = moments[row0, iv] + tv * (moments[row0, iv + 1] - moments[row0, iv])
            h1 = moments[row1, iv] + tv * (moments[row1, iv + 1] - moments[row1, iv])
            return (h0 + te * (h1 - h0)) * math.pi * (r * r + 2.0 * math.sqrt(l1 * l2))
    return aperture_mass_quadrature(radius, w11, w12, w22, mix, normals, moments, MASS_ANGLES)


def mass_table(moments: np.ndarray) -> None:
    """Fill ``aperture_moments``' mass rows from its moment rows: H(e, v) = the quadrature's
    mass of W = diag(1, e), R = sigma (1 / v - 1), over pi (R^2 + 2 sqrt(e)), with
    MASS_TABLE_ANGLES directions per family; row TABLE_B + k holds e = MASS_E_MIN^(k /
    (MASS_E - 1)), column j v = j / (MASS_V - 1) (v = 0, a disc infinitely wider than the
    Gaussian, is taken at v = 1e-4)."""
    _fill_mass_table(moments, np.zeros((0, 2)))


@numba.njit(cache=True, nogil=True)
def _fill_mass_table(moments, no_blades):
    for k in range(MASS_E):
        e = MASS_E_MIN ** (k / (MASS_E - 1))
        sigma = math.sqrt(0.5 * (1.0 + e))
        for j in range(MASS_V):
            v = max(j / (MASS_V - 1), 1e-4)
            r = sigma * (1.0 / v - 1.0)
            m = aperture_mass_quadrature(r, 1.0, 0.0, e, edge_mix(r, 1.0, e), no_blades,
                                         moments, MASS_TABLE_ANGLES)
            moments[TABLE_B + k, j] = m / (math.pi * (r * r + 2.0 * math.sqrt(e)))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def aperture_mass_quadrature(radius, w11, w12, w22, mix, normals, moments, mass_angles):
    """The integral of ``aperture_kernel`` over the plane (pixels^2): int f(theta) dtheta
    with f = (I1(b) + b I0(b)) / s^2 along each direction (``aperture_moments``).

    f is flat in theta where the aperture dominates (f ~ R^2 / 2) and peaked about W's
    long axis where the Gaussian does (f ~ 1 / n^T W^-1 n, as narrow as the kernel is
    elongated: 32 uniform angles missed 5-40 % of a 10:1 kernel's mass). The quadrature
    takes MASS_ANGLES uniform directions and MASS_ANGLES directions W^(1/2) m of uniform m
    (twice as many for a polygon, whose radius has corners)
    (their density is the Gaussian part's shape) and weighs both by the balance heuristic
    of multiple importance sampling: within 0.5 % of the integral up to 30:1 kernels, 1 %
    for polygons (tests/test_bokeh.py). The kernel is a Gaussian convolved with the aperture, at least a
    pixel wide, so its sum over pixel centres equals the integral as closely."""
    if radius < 0.0:
        radius = -radius
    det = w11 * w22 - w12 * w12
    sqrt_det = math.sqrt(det)
    c11, c12, c22 = w22 / det, -w12 / det, w11 / det
    # W^(1/2) of a 2x2 W: (W + sqrt(det W) I) / sqrt(tr W + 2 sqrt(det W))
    k = 1.0 / math.sqrt(w11 + w22 + 2.0 * sqrt_det)
    h11, h12, h22 = (w11 + sqrt_det) * k, w12 * k, (w22 + sqrt_det) * k
    plateau = moments[TABLE_B - 1, 2]
    # f and the densities are the same at n and -n for a centrally symmetric aperture (a
    # disc, an even polygon): half the directions of each family, counted twice
    family = mass_angles if normals.shape[0] == 0 else 2 * mass_angles  # a polygon has corners
    angles = family // 2 if normals.shape[0] % 2 == 0 else family
    step = 2.0 * math.pi / family
    cs, sn = math.cos(step), math.sin(step)
    mx, my = math.cos(0.5 * step), math.sin(0.5 * step)
    total = 0.0
    for _ in range(angles):
        total += mass_direction(mx, my, radius, c11, c12, c22, w11, w12, w22, sqrt_det, mix,
                                normals, moments, plateau)
        vx, vy = h11 * mx + h12 * my, h12 * mx + h22 * my
        inv = 1.0 / math.sqrt(vx * vx + vy * vy)
        total += mass_direction(vx * inv, vy * inv, radius, c11, c12, c22, w11, w12, w22,
                                sqrt_det, mix, normals, moments, plateau)
        mx, my = mx * cs - my * sn, mx * sn + my * cs  # the next direction
    return total / angles
