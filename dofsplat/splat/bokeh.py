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

import numba
import numpy as np

from .ewa import exponent, shared

# the per-fragment functions are inlined at numba's level, like the Gaussian's forward
# differences: a call per fragment costs as much as the kernel
shared_inline = numba.njit(cache=True, nogil=True, inline="always")

B_MAX = 8.0  # disc radius in Gaussian sigmas beyond which the edge profile no longer changes
TABLE_B = 65  # columns over b in [0, B_MAX]
TABLE_U = 321  # rows over u in [-B_MAX, sqrt(2c)]

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
    """(TABLE_B, 2) float64: I0(b) = int T(u, b) du and I1(b) = int T(u, b) u du over
    u in [-b, sqrt(2c)] (r >= 0), per column b of ``aperture_table``: a kernel's mass along a
    direction is (I1 + b I0) / s^2 (``aperture_mass``)."""
    key = ("moments", float(cutoff))
    moments = _TABLES.get(key)
    if moments is None:
        table = aperture_table(cutoff)
        u_c = math.sqrt(2.0 * cutoff)
        u = np.linspace(-B_MAX, u_c, TABLE_U)
        b = np.linspace(0.0, B_MAX, TABLE_B)
        moments = np.zeros((TABLE_B, 2))
        fine = np.linspace(0.0, 1.0, 4001)
        trapezoid = getattr(np, "trapezoid", None) or np.trapz  # numpy < 2 has only trapz
        for k in range(TABLE_B):
            uu = -b[k] + (u_c + b[k]) * fine  # u from -b to the cutoff
            t = np.interp(uu, u, table[k])
            moments[k, 0] = trapezoid(t, uu)
            moments[k, 1] = trapezoid(t * uu, uu)
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
def table_value(u, b, table, u_c):
    """T(u, b) by bilinear interpolation in ``aperture_table`` (1 deep inside, 0 outside)."""
    if u >= u_c:
        return 0.0
    if b >= B_MAX:
        b = B_MAX
    fu = (u + B_MAX) * ((TABLE_U - 1) / (u_c + B_MAX))
    if fu <= 0.0:
        return 1.0
    fb = b * ((TABLE_B - 1) / B_MAX)
    ib = min(int(fb), TABLE_B - 2)
    iu = min(int(fu), TABLE_U - 2)
    tb = fb - ib
    tu = fu - iu
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
    return aperture_value(q, w11 * dx * dx + 2.0 * w12 * dx * dy + w22 * dy * dy, dx, dy,
                          radius, mix, normals, table, u_c)


@shared_inline
def aperture_value(q, p, dx, dy, radius, mix, normals, table, u_c):
    """``aperture_kernel`` from q = 1/2 x^T W^-1 x and p = x^T W x (both kept up to date
    along a row by forward differences): the scale along the offset's direction n moves
    from s_G = sqrt(n^T W^-1 n) (the Gaussian, exact at R = 0) to s_E = 1 / sqrt(n^T W n)
    (the Gaussian's profile across a wide aperture's edge) as ``mix`` goes from 0 to 1.
    """
    r2 = dx * dx + dy * dy
    if r2 <= 0.0:
        return 1.0 if radius != 0.0 else table_value(-B_MAX, 0.0, table, u_c)
    if radius < 0.0:
        radius, dx, dy = -radius, -dx, -dy
    rr = math.sqrt(r2)
    s_gauss = math.sqrt(2.0 * q / r2)
    s_edge = rr / math.sqrt(p)
    s = s_gauss + mix * (s_edge - s_gauss)
    rad = direction_radius(dx, dy, rr, radius, normals)
    return table_value((rr - rad) * s, rad * s, table, u_c)


@shared
def support_conic(w11, w12, w22, radius, u_c):
    """The conic (inverse variance) of an ellipse that contains an aperture kernel's
    support: with W's eigenvalues l_i, the ellipse of semi-axes u_c sqrt(l_i) + |R| along
    W's eigenvectors. The support lies where |x| < |R(n)| + u_c / s(n), and both scales
    satisfy 1/s <= sqrt(n^T W n), so it lies in the disc of radius |R| plus the ellipse
    u_c^2 W, which this ellipse contains. Rows are scanned over it (``row_span`` with
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
    a = u_c * math.sqrt(l1) + abs(radius)
    b = u_c * math.sqrt(l2) + abs(radius)
    ia, ib = 1.0 / (a * a), 1.0 / (b * b)
    return ia * vx * vx + ib * vy * vy, (ia - ib) * vx * vy, ia * vy * vy + ib * vx * vx


@shared
def aperture_row_start(j, i, mx, my, c11, c12, c22, w11, w12, w22):
    """At pixel (i, j): q = 1/2 x^T W^-1 x, p = x^T W x, their steps to pixel j + 1, and the
    offset (dx, dy). Along a row q(j+1) = q + dq, dq += c11; p(j+1) = p + dp, dp += 2 w11."""
    dx = j + 0.5 - mx
    dy = i + 0.5 - my
    q = exponent(dx, dy, c11, c12, c22)
    dq = c11 * dx + 0.5 * c11 + c12 * dy
    p = w11 * dx * dx + 2.0 * w12 * dx * dy + w22 * dy * dy
    dp = 2.0 * (w11 * dx + w12 * dy) + w11
    return q, dq, p, dp, dx, dy


MASS_ANGLES = 32  # directions of the angular quadrature in aperture_mass


@shared
def aperture_mass(radius, w11, w12, w22, mix, normals, moments):
    """The integral of ``aperture_kernel`` over the plane (pixels^2), by quadrature over the
    direction: int (I1(b) + b I0(b)) / s^2 dtheta (``aperture_moments``). The kernel is a
    Gaussian convolved with the aperture, at least a pixel wide (the prefilter), so its sum
    over pixel centres equals this integral to far below a percent (tests/test_bokeh.py)."""
    if radius < 0.0:
        radius = -radius
    det = w11 * w22 - w12 * w12
    total = 0.0
    for t in range(MASS_ANGLES):
        a = (t + 0.5) * (2.0 * math.pi / MASS_ANGLES)
        nx, ny = math.cos(a), math.sin(a)
        s_gauss = math.sqrt((w22 * nx * nx - 2.0 * w12 * nx * ny + w11 * ny * ny) / det)
        s_edge = 1.0 / math.sqrt(w11 * nx * nx + 2.0 * w12 * nx * ny + w22 * ny * ny)
        s = s_gauss + mix * (s_edge - s_gauss)
        b = direction_radius(nx, ny, 1.0, radius, normals) * s
        if b >= B_MAX:
            i0 = moments[TABLE_B - 1, 0] + (b - B_MAX)
            i1 = moments[TABLE_B - 1, 1] - 0.5 * (b * b - B_MAX * B_MAX)
        else:
            fb = b * ((TABLE_B - 1) / B_MAX)
            ib = min(int(fb), TABLE_B - 2)
            tb = fb - ib
            i0 = moments[ib, 0] + tb * (moments[ib + 1, 0] - moments[ib, 0])
            i1 = moments[ib, 1] + tb * (moments[ib + 1, 1] - moments[ib, 1])
        total += (i1 + b * i0) / (s * s)
    return total * (2.0 * math.pi / MASS_ANGLES)
