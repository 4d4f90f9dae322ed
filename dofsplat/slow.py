"""Slow, obviously correct twins of the fast kernels, for the tests.

Everything here is numpy or plain Python, written from the paper's formulas in matrix form
rather than from the kernels' scalar code:

* ``project_reference``: transform, cull, J = dProj/dp . [t_u t_v], W = J V^r J^T + I + V^I
  (eq. 11, or eq. 12 with ``circumellipse_eig`` for LOD), bounding box and kernel sum over
  the pixel centres;
* ``rasterize_reference``: one global A-buffer of Python lists, splats in index order, the
  z-range merge rules of Section 6.4, and front-to-back "over" compositing; with the soft
  reconstruction, a front pass over numpy disks, each splat's visibility, and the resolve as
  an explicit sum over every partition of the surfaces into merged runs;
* ``circumellipse_appendix``: Appendix A's conic-coefficient algorithm (eqs. 13-14) as printed.
"""

from __future__ import annotations

import math

import numpy as np

from .camera import Camera
from .frame import RenderSettings
from .splat.source import from_surfels
from .surfels import Surfels, tangent_frame

LN4 = math.log(4.0)

# -- the twins' own constants ------------------------------------------------------------
# Written out here, never imported from the code the twins check: a constant changed in a
# kernel's module is then a difference between the kernels and their twins, which the
# comparisons find (an imported MERGE_REACH of 2, or SMALL_APERTURE of 4, passed every
# twin comparison: issue 52). ``TWIN_CONSTANTS`` names where each lives in the kernels'
# code, and tests/test_render.py checks that the two agree, so that a change made on
# purpose is made in both places.
SMALL_APERTURE = 1.0  # an aperture radius under this x the kernel's least sigma: its Gaussian
MAX_SPLAT_VARIANCE = 1.0e16  # px^2: a wider splat is dropped
BOX_SLACK, BOX_SLACK_REL = 1e-3, 1e-6  # px, and x (reach + |coordinate|): float32's slack
EXACT_NORMALISATION_MAX_AREA = 16384  # px: boxes up to this many pixels are summed
MAX_SURFACES = 8  # surfaces per pixel in the A-buffer
OPAQUE = 0.95  # a fragment at least this opaque hides what lies behind it (the front pass)
FRONT_CUTOFF = 2.0  # the front pass's unblurred disk: 1/2 x^T F^-1 x < FRONT_CUTOFF
FRONT_MARGIN = 128  # px of front map round the image
COVER_FULL, COVER_KNEE, COVER_SHARP_PX = 0.9, 0.85, 1.0  # a sharp surface covers its pixel
BLUR_COVER_KNEE, BLUR_COVER_FULL = 0.95, 0.98  # ... and a blurred one
MERGE_RHO0, MERGE_RHO1 = 0.15, 0.5  # the merge band of the parallax ratio rho
VIS_SAMPLES = 9  # a splat's visibility: its centre and 8 points of its 1-sigma ellipse
LENS_POINTS, LENS_RING, LENS_MARGIN = 4, 1.0, 2.0  # looks through the lens from each
HIDDEN_H0 = 0.9  # the share of hidden looks from which a splat is removed
MERGE_REACH = 6.0  # a surface's depths reach this x (its CoC + 1 px) along its tangent plane
B_MAX, TABLE_B, TABLE_U = 8.0, 65, 321  # the aperture table's b range and grid
MASS_E, MASS_V, MASS_E_MIN = 49, 65, 1.0 / 1024.0  # the disc's mass table
MASS_ANGLES, MASS_TABLE_ANGLES = 16, 128  # directions per family of the mass quadrature

# where each constant lives in the kernels' code: {twin name: "module:NAME"}
TWIN_CONSTANTS = {
    "SMALL_APERTURE": "dofsplat.splat.ewa:SMALL_APERTURE",
    "MAX_SPLAT_VARIANCE": "dofsplat.splat.ewa:MAX_SPLAT_VARIANCE",
    "BOX_SLACK": "dofsplat.splat.ewa:BOX_SLACK",
    "BOX_SLACK_REL": "dofsplat.splat.ewa:BOX_SLACK_REL",
    "EXACT_NORMALISATION_MAX_AREA": "dofsplat.splat.project:EXACT_NORMALISATION_MAX_AREA",
    "MAX_SURFACES": "dofsplat.raster.abuffer:MAX_SURFACES",
    "OPAQUE": "dofsplat.raster.abuffer:OPAQUE",
    "FRONT_CUTOFF": "dofsplat.raster.abuffer:FRONT_CUTOFF",
    "FRONT_MARGIN": "dofsplat.raster.abuffer:FRONT_MARGIN",
    "COVER_FULL": "dofsplat.raster.abuffer:COVER_FULL",
    "COVER_KNEE": "dofsplat.raster.abuffer:COVER_KNEE",
    "COVER_SHARP_PX": "dofsplat.raster.abuffer:COVER_SHARP_PX",
    "BLUR_COVER_KNEE": "dofsplat.raster.abuffer:BLUR_COVER_KNEE",
    "BLUR_COVER_FULL": "dofsplat.raster.abuffer:BLUR_COVER_FULL",
    "MERGE_RHO0": "dofsplat.raster.abuffer:MERGE_RHO0",
    "MERGE_RHO1": "dofsplat.raster.abuffer:MERGE_RHO1",
    "VIS_SAMPLES": "dofsplat.raster.abuffer:VIS_SAMPLES",
    "LENS_POINTS": "dofsplat.raster.abuffer:LENS_POINTS",
    "LENS_RING": "dofsplat.raster.abuffer:LENS_RING",
    "LENS_MARGIN": "dofsplat.raster.abuffer:LENS_MARGIN",
    "HIDDEN_H0": "dofsplat.raster.abuffer:HIDDEN_H0",
    "MERGE_REACH": "dofsplat.raster.abuffer:MERGE_REACH",
    "B_MAX": "dofsplat.splat.bokeh:B_MAX",
    "TABLE_B": "dofsplat.splat.bokeh:TABLE_B",
    "TABLE_U": "dofsplat.splat.bokeh:TABLE_U",
    "MASS_E": "dofsplat.splat.bokeh:MASS_E",
    "MASS_V": "dofsplat.splat.bokeh:MASS_V",
    "MASS_E_MIN": "dofsplat.splat.bokeh:MASS_E_MIN",
    "MASS_ANGLES": "dofsplat.splat.bokeh:MASS_ANGLES",
    "MASS_TABLE_ANGLES": "dofsplat.splat.bokeh:MASS_TABLE_ANGLES",
}


# -- the frame's parameters, from their definitions --------------------------------------


def coc_coefficients_reference(camera: Camera, lens, settings: RenderSettings):
    """(K, 1/P) of C_r(U) = K |1/U - 1/P| (the lens's own, camera.py); (0, 0) for a pinhole
    or with ``dof`` off."""
    if lens is None or not settings.dof:
        return 0.0, 0.0
    return lens.coc_coefficients(camera)


def merge_parameters_reference(camera: Camera, lens, settings: RenderSettings):
    """(K, 1/P, rho0, rho1) of the soft merge (frame.merge_parameters): K = -1 for the
    paper's reconstruction (its "over" and min(1, w)), 0 for a pinhole."""
    if settings.reconstruction == "paper":
        return -1.0, 0.0, MERGE_RHO0, MERGE_RHO1
    return (*coc_coefficients_reference(camera, lens, settings), MERGE_RHO0, MERGE_RHO1)


def blade_normals_reference(blades: int, rotation_deg: float) -> np.ndarray:
    """(N, 2) unit normals of a regular N-gon's edges, pixels (x right, y down): the first
    vertex at the rotation angle, each edge's normal halfway between its two vertices."""
    if blades == 0:
        return np.zeros((0, 2))
    vertex = [math.radians(rotation_deg) + i * 2 * math.pi / blades for i in range(blades + 1)]
    mid = [(a + b) / 2 for a, b in zip(vertex[:-1], vertex[1:])]
    return np.array([[math.cos(a), -math.sin(a)] for a in mid])  # y down: the sine turns


def aperture_shape_reference(lens, settings: RenderSettings):
    """(disc, blades, moments): whether kernels carry the aperture's shape (a lens with
    ``bokeh="disc"`` in a frame with ``dof``), its edge normals ((0, 2): round) and the
    twin's own moments and mass table (``aperture_moments_reference``)."""
    disc = lens is not None and settings.dof and getattr(lens, "bokeh", "gaussian") == "disc"
    if not disc:
        return False, np.zeros((0, 2)), np.zeros((1, 1))
    return (True, blade_normals_reference(lens.blades, lens.blade_rotation),
            aperture_moments_reference(settings.cutoff))


def aperture_variance_reference(lens) -> float:
    """The aperture image's variance per axis at radius 1: E|u|^2 / 2 over the disc (1/4)
    or the regular n-gon of circumradius 1 ((1 + 2 cos^2(pi/n)) / 12: its n triangles of
    height cos(pi/n) and half-base sin(pi/n)); 1/4 where no kernel carries the aperture."""
    n = getattr(lens, "blades", 0) if lens is not None else 0
    if lens is None or getattr(lens, "bokeh", "gaussian") != "disc" or n == 0:
        return 0.25
    h, s = math.cos(math.pi / n), math.sin(math.pi / n)
    # a triangle's E|u|^2 from the centre: h^2 / 2 + s^2 / 6 (the apex at the centre)
    return (h * h / 2 + s * s / 6) / 2


def kernel_floor_reference(settings: RenderSettings) -> float:
    """A tapered kernel's floor: e^-c with ``taper``, else 0."""
    return math.exp(-settings.cutoff) if settings.taper else 0.0


_TWIN_TABLES: dict = {}


def disc_convolution(u, b, nodes: int = 160):
    """T(u, b) = (G * disc_b)(d) / (G * disc_b)(0), d = max(u + b, 0), by Gauss-Legendre
    quadrature of its definition: a unit 2-D Gaussian G and the uniform disc of radius b > 0
    (splat/bokeh.py's module notes). In polar coordinates about the disc's centre,

        (G * disc_b)(d) = int_0^b r exp(-(r^2 + d^2) / 2) I0(r d) dr,

    and at d = 0 that is 1 - exp(-b^2 / 2). I0(x) = i0e(x) e^x keeps the exponent
    -(r - d)^2 / 2 finite. u, b: arrays that broadcast; b > 0."""
    from scipy.special import i0e

    x, w = np.polynomial.legendre.leggauss(nodes)
    u, b = np.broadcast_arrays(np.asarray(u, float), np.asarray(b, float))
    d = np.maximum(u + b, 0.0)[..., None]
    half = (b / 2)[..., None]
    r = half * (x + 1)  # the nodes on [0, b]
    integrand = r * np.exp(-0.5 * (r - d) ** 2) * i0e(r * d)
    return np.sum(w * integrand, axis=-1) * half[..., 0] / -np.expm1(-0.5 * b * b)


def aperture_table_reference(cutoff: float) -> np.ndarray:
    """(TABLE_B, TABLE_U): the tapered T(u, b) on the aperture table's grid (b from 0 to
    B_MAX, u from -B_MAX to the cutoff sqrt(2c)), from ``disc_convolution``; the Gaussian
    exp(-d^2 / 2) at b = 0. The taper: T - s(b) T(sqrt(2c), b), s = smoothstep(b; 0, 1),
    so that a blurred kernel falls to 0 at its cutoff while an unblurred one (b = 0) stays
    the paper's truncated Gaussian."""
    key = ("table", float(cutoff))
    if key not in _TWIN_TABLES:
        u_c = math.sqrt(2 * cutoff)
        b = np.linspace(0, B_MAX, TABLE_B)
        u = np.linspace(-B_MAX, u_c, TABLE_U)
        table = np.empty((TABLE_B, TABLE_U))
        table[0] = np.exp(-0.5 * np.maximum(u, 0.0) ** 2)
        t = np.clip(disc_convolution(u[None, :], b[1:, None]), 0.0, 1.0)
        x = np.minimum(b[1:], 1.0)
        smooth = x * x * (3 - 2 * x)
        table[1:] = np.maximum(t - smooth[:, None] * t[:, -1:], 0.0)
        _TWIN_TABLES[key] = table
    return _TWIN_TABLES[key]


def aperture_moments_reference(cutoff: float) -> np.ndarray:
    """(TABLE_B + MASS_E, MASS_V), laid out as bokeh.aperture_moments: per column b of the
    twin's table, I0(b) = int T du and I1(b) = int T u du over u in [-b, sqrt(2c)] (the
    table's linear interpolation, integrated on a fine grid) and T(-B_MAX, b); below them
    the disc's mass over pi (R^2 + 2 sqrt|W|) for W = diag(1, e), e = MASS_E_MIN^(k /
    (MASS_E - 1)), and R = sigma (1 / v - 1), v = max(j / (MASS_V - 1), 1e-4), sigma^2 =
    (1 + e) / 2, by ``aperture_mass_reference``'s quadrature with MASS_TABLE_ANGLES
    directions per family."""
    key = ("moments", float(cutoff))
    if key not in _TWIN_TABLES:
        table = aperture_table_reference(cutoff)
        u_c = math.sqrt(2 * cutoff)
        u = np.linspace(-B_MAX, u_c, TABLE_U)
        moments = np.zeros((TABLE_B + MASS_E, MASS_V))
        trapezoid = getattr(np, "trapezoid", None) or np.trapz  # numpy < 2 has only trapz
        for k, b in enumerate(np.linspace(0, B_MAX, TABLE_B)):
            uu = np.linspace(-b, u_c, 20001)
            t = np.interp(uu, u, table[k])
            moments[k, :3] = trapezoid(t, uu), trapezoid(t * uu, uu), table[k, 0]
        for k in range(MASS_E):
            e = MASS_E_MIN ** (k / (MASS_E - 1))
            sigma = math.sqrt((1 + e) / 2)
            for j in range(MASS_V):
                v = max(j / (MASS_V - 1), 1e-4)
                r = sigma * (1 / v - 1)
                mix = r * r / (r * r + (1 + e) / 2)
                mass = aperture_mass_reference(np.diag([1.0, e]), r, mix, np.zeros((0, 2)),
                                               moments, family=MASS_TABLE_ANGLES)
                moments[TABLE_B + k, j] = mass / (math.pi * (r * r + 2 * math.sqrt(e)))
        _TWIN_TABLES[key] = moments
    return _TWIN_TABLES[key]


def circumellipse_eig(m, r):
    """Variance containing both the ellipse of variance m (2x2) and the circle r I."""
    lam, vec = np.linalg.eigh(np.asarray(m, np.float64))
    return vec @ np.diag(np.maximum(lam, r)) @ vec.T


def circumellipse_general_eig(a, b):
    """Variance containing the ellipses a and b: b^(1/2) clamp(b^-1/2 a b^-1/2, 1) b^(1/2)."""
    lam, vec = np.linalg.eigh(np.asarray(b, np.float64))
    root = vec @ np.diag(np.sqrt(lam)) @ vec.T
    inv_root = vec @ np.diag(1 / np.sqrt(lam)) @ vec.T
    return root @ circumellipse_eig(inv_root @ a @ inv_root, 1.0) @ root


def circumellipse_appendix(A, B, C, r):
    """Appendix A as printed: M = [[A, B/2], [B/2, C]], circle R = r. Returns (A'', B'', C'').

    Note B is twice the off-diagonal element, as in the appendix.
    """
    swapped = A < C
    if swapped:
        A, C = C, A
    root = math.sqrt((A - C) ** 2 + B * B)
    a1 = (A + C + root) / 2  # eq. 13
    c1 = (A + C - root) / 2
    a1, c1 = max(a1, r), max(c1, r)
    if root == 0.0:
        cos2, sin2t = 1.0, 0.0
    else:
        cos2 = 0.5 * ((A - C) / root + 1)  # eq. 14
        sin2t = B / root
    a2 = (a1 - c1) * cos2 + c1
    b2 = (a1 - c1) * sin2t
    c2 = (c1 - a1) * cos2 + a1
    if swapped:
        a2, c2 = c2, a2
    return a2, b2, c2


def project_reference(surfels: Surfels, rgb: np.ndarray, camera: Camera, lens,
                      settings: RenderSettings, lod_cov=None, color_grad=None, gain=None):
    """numpy twin of ``backends.cpu.project``: (splats (N, N_FIELDS), bbox (N, 4), visible (N,)).

    lod_cov: optional (N, 6) world covariances of an LOD filter V^{q,l} per surfel
    (xx, xy, xz, yy, yz, zz): the kernel is then eq. 12 with Section 6.2's circumellipse;
    color_grad: optional (N, 6) colour gradients of LOD nodes (Cov(colour, position . t) in
    each node's tangent frame, lod/hierarchy.py) and gain (N, 3) the shading's factor on
    the colour: a node's colour slope is then Cov(colour, screen position) W_total^-1.
    """
    # (the row's layout, not its maths: a wrong field index fails every comparison)
    from .splat.project import (ALPHA, AMP, BLUE, BX, BY, C11, C12, C22, COC, DEPTH, F11, F12,
                                F22, FLOOR, GREEN, GX, GY, GZX, GZY, MIX, MX, MY, N_FIELDS, RAD,
                                REACH, RED, RX, RY, X0, X1, ZHI, ZLO)

    n = len(surfels)
    c = float(settings.cutoff)
    taper = kernel_floor_reference(settings)  # an LOD node's kernel: exp(-q) - e^-c inside
    disc, blades, moments = aperture_shape_reference(lens, settings)
    src = from_surfels(surfels)
    ru, rv, area = src.ru, src.rv, src.area
    view = camera.camera_from_world()
    rot = view[:3, :3]
    p = surfels.positions.astype(np.float64) @ rot.T + view[:3, 3]
    nrm = surfels.normals.astype(np.float64) @ rot.T
    if surfels.is_elliptical:
        tu = surfels.tangent.astype(np.float64) @ rot.T
    else:
        tu = tangent_frame(surfels.normals)[0].astype(np.float64) @ rot.T
    tv = np.cross(nrm, tu)
    depth = -p[:, 2]
    ax, bx, ay, by = camera.screen_coefficients()
    near = camera.frustum_lrbtn()[4]
    coc_k, inv_focus = coc_coefficients_reference(camera, lens, settings)

    splats = np.zeros((n, N_FIELDS))
    bbox = np.zeros((n, 4), np.int32)
    visible = np.zeros(n, bool)
    for k in range(n):
        u = depth[k]
        if u <= near:
            continue
        if settings.cull_backfaces and nrm[k] @ p[k] >= 0:
            continue
        X, Y = p[k, 0], p[k, 1]
        m = np.array([ax * X / u + bx, -ay * Y / u + by])
        # derivative of the projection at p, (2, 3), applied to the tangent frame
        d_proj = np.array([[ax / u, 0.0, ax * X / u ** 2],
                           [0.0, -ay / u, -ay * Y / u ** 2]])
        J = d_proj @ np.stack([tu[k], tv[k]], axis=1)
        su, sv = 0.5 * ru[k], 0.5 * rv[k]
        Vr = np.diag([su * su, sv * sv])
        coc_r = coc_k * abs(1.0 / u - inv_focus)
        v_dof = coc_r ** 2 / (2 * LN4)
        # the LOD filter in screen space: world covariance through dProj/dp_world
        Sq = np.zeros((3, 3)) if lod_cov is None else _sym3(lod_cov[k])
        G = d_proj @ rot
        Q = G @ Sq @ G.T
        radius = 0.0
        if disc:  # the aperture's shape: the Gaussian keeps the unblurred kernel (bokeh.py)
            radius = coc_r
            if u * inv_focus < 1:
                radius = -radius  # before the focal plane: the aperture's image turned over
            # a node: Q/3, and at least its filter Q where the disc's V^I is smaller
            lam, vec = np.linalg.eigh(2 / 3 * Q - v_dof * np.eye(2))
            blur = Q / 3 + vec @ np.diag(np.maximum(lam, 0.0)) @ vec.T
        elif np.any(Q != 0):
            blur = circumellipse_general_eig(Q, v_dof * np.eye(2) + Q / 3 + 1e-9 * np.eye(2))
        else:
            blur = v_dof * np.eye(2)
        W = J @ Vr @ J.T + np.eye(2) + blur
        if radius ** 2 < SMALL_APERTURE ** 2 * np.linalg.eigvalsh(W).min():
            W = W + radius ** 2 / 4 * np.eye(2)  # a small aperture: its moment-matched Gaussian
            radius = 0.0
        F = J @ Vr @ J.T + Q + 1e-6 * np.eye(2)  # the unblurred disk
        if not (np.trace(W) + radius ** 2 <= MAX_SPLAT_VARIANCE
                and np.trace(F) <= MAX_SPLAT_VARIANCE):
            continue  # too wide to store (ewa.MAX_SPLAT_VARIANCE)
        hx, hy = math.sqrt(2 * c * W[0, 0]), math.sqrt(2 * c * W[1, 1])
        if radius != 0:
            mix = radius ** 2 / (radius ** 2 + 0.5 * np.trace(W))
            hx, hy = support_extent(W, radius, mix, math.sqrt(2 * c))
        # the pixel centres within hx, hy of the mean, and the slack for float32 rows
        hx += BOX_SLACK + BOX_SLACK_REL * (hx + abs(m[0]))
        hy += BOX_SLACK + BOX_SLACK_REL * (hy + abs(m[1]))
        x0, x1 = math.ceil(m[0] - hx - 0.5), math.floor(m[0] + hx - 0.5)
        y0, y1 = math.ceil(m[1] - hy - 0.5), math.floor(m[1] + hy - 0.5)
        if x0 > camera.width or x1 < -1 or y0 > camera.height or y1 < -1:
            continue  # more than a pixel outside the image
        cx0, cx1 = max(x0, 0), min(x1, camera.width - 1)
        cy0, cy1 = max(y0, 0), min(y1, camera.height - 1)
        if cx0 > cx1 or cy0 > cy1:
            cx0, cx1, cy0, cy1 = 0, -1, 0, -1  # within a pixel: no fragment, a front disk
        Wi = np.linalg.inv(W)
        floor = taper if np.trace(Sq) > 0 else 0.0
        area_px = abs(np.linalg.det(J)) * area[k]
        total = 0.0
        support = abs(radius) + math.sqrt(2 * c * np.linalg.eigvalsh(W).max())
        mix = radius ** 2 / (radius ** 2 + 0.5 * np.trace(W))
        if radius != 0:
            floor = 0.0
            total = aperture_mass_table_reference(W, radius, mix, blades, moments)
        elif settings.exact_normalization and (x1 - x0 + 1) * (y1 - y0 + 1) <= EXACT_NORMALISATION_MAX_AREA:
            q = _exponents(m, Wi, x0, x1, y0, y1)
            total = float((np.exp(-q[q < c]) - floor).sum())
        if total > 0:
            amp = area_px / total
        else:
            mass = 1 - math.exp(-c) - c * floor  # of exp(-q) - floor over q < c, per 2 pi |W|^1/2
            amp = area_px / (2 * math.pi * math.sqrt(np.linalg.det(W)) * mass)
        reach = math.sqrt(2 * c)
        # depth extent: the leaf basis, plus the node's surfels' spread V^q / 3
        var_z = max((su * tu[k, 2]) ** 2 + (sv * tv[k, 2]) ** 2 + rot[2] @ Sq @ rot[2] / 3, 0.0)
        sigma_l = math.sqrt(max(su, sv) ** 2 + np.trace(Sq) / 2)
        half = reach * math.sqrt(var_z) + settings.z_thickness * 2 * sigma_l
        splats[k, [MX, MY]] = m
        splats[k, [C11, C12, C22]] = Wi[0, 0], Wi[0, 1], Wi[1, 1]
        splats[k, AMP] = amp
        splats[k, [ZLO, ZHI, DEPTH]] = u - half, u + half, u
        splats[k, [RED, GREEN, BLUE]] = rgb[k]
        splats[k, ALPHA] = surfels.opacity[k]
        splats[k, COC] = coc_r
        splats[k, [X0, X1]] = x0, x1
        # the unblurred disk and the depth change per pixel across the tangent plane
        Fi = np.linalg.inv(F)
        splats[k, [F11, F12, F22]] = Fi[0, 0], Fi[0, 1], Fi[1, 1]
        splats[k, FLOOR] = floor
        splats[k, [RAD, REACH, MIX]] = radius, support, mix
        splats[k, [GZX, GZY]] = -np.array([tu[k, 2], tv[k, 2]]) @ np.linalg.inv(J)
        if color_grad is not None and np.trace(Sq) > 0:
            # the node's tangent frame in world space, from its normal (as the hierarchy's)
            nw = surfels.normals[k].astype(np.float64)
            e = np.zeros(3)
            e[np.argmin(np.abs(nw))] = 1.0
            uw = np.cross(nw, e)
            uw /= np.linalg.norm(uw)
            vw = np.cross(nw, uw)
            g = np.asarray(color_grad[k], np.float64).reshape(3, 2)
            # Cov(colour, world position) in the tangent plane, then on the screen
            cov_cs = (g @ np.stack([uw, vw])) @ G.T  # (3 channels, 2 screen axes)
            if gain is not None:
                cov_cs = cov_cs * np.asarray(gain[k], np.float64)[:, None]
            # the kernel's covariance: W and the aperture's (a disc: R^2 / 4 per axis)
            slope = cov_cs @ np.linalg.inv(W + aperture_variance_reference(lens) * radius ** 2
                                           * np.eye(2))
            splats[k, [RX, RY, GX, GY, BX, BY]] = slope.reshape(6)
        bbox[k] = cx0, cx1, cy0, cy1
        visible[k] = True
    return splats, bbox, visible


def _sym3(c):
    """The symmetric 3x3 matrix of a 6-vector (xx, xy, xz, yy, yz, zz)."""
    xx, xy, xz, yy, yz, zz = (float(v) for v in c)
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


def support_extent(W, radius, mix, u_c):
    """Half-widths (x, y) of a box round an aperture kernel's support (bokeh.support_bbox):
    along a direction n the support ends within |R| + u_c sqrt(n^T W n) of its centre, a
    curve inside the ellipse of semi-axes g1 = |R| + u_c sqrt(l1) and g1^2 / sqrt(2 g1^2 -
    g2^2) along W's eigenvectors (g2^2 = R^2 + |R| u_c sqrt(l1) + u_c^2 l2 + |R| u_c l2 /
    sqrt(l1); docs/maths.md, "The support"), and inside the circle of |R| + u_c sqrt(l1);
    and within |R| + u_c sqrt(W_ii) / (1 - mix) along each axis (the scale s is at least
    (1 - mix) sqrt(n^T W^-1 n)). ``test_support_bbox_*`` checks the box against the kernel
    itself, pixel by pixel."""
    lam, vec = np.linalg.eigh(W)  # ascending: l2, l1
    l2, l1 = max(lam[0], 0.0), lam[1]
    r = abs(radius)
    g1 = r + u_c * math.sqrt(l1)
    g2sq = r * r + r * u_c * math.sqrt(l1) + u_c * u_c * l2 + r * u_c * l2 / math.sqrt(l1)
    axes = np.array([g1, g1 * g1 / math.sqrt(2 * g1 * g1 - g2sq)])  # along vec[:, 1], vec[:, 0]
    ext = np.minimum(np.sqrt((axes[0] * vec[:, 1]) ** 2 + (axes[1] * vec[:, 0]) ** 2), g1)
    if mix < 1:
        ext = np.minimum(ext, r + u_c * np.sqrt(np.diag(W)) / (1 - mix))
    return float(ext[0]), float(ext[1])


def _exponents(m, Wi, x0, x1, y0, y1):
    """1/2 d^T W^-1 d at the pixel centres of the box [x0, x1] x [y0, y1] (rows y, cols x)."""
    ys, xs = np.mgrid[y0:y1 + 1, x0:x1 + 1] + 0.5
    d = np.stack([xs - m[0], ys - m[1]], axis=-1)
    return 0.5 * np.einsum("...i,ij,...j->...", d, Wi, d)


def rasterize_reference(splats, bbox, visible, width, height, cutoff, background,
                        max_surfaces: int = MAX_SURFACES,
                        merge=(0.0, 0.0, MERGE_RHO0, MERGE_RHO1), blades=None,
                        sharp_visibility: bool = False, coarse: float = 0.0):
    """Python twin of the tile rasteriser: (image (H, W, 4), depth (H, W), weight (H, W), fragments).

    merge: (K, 1/P, rho0, rho1) of ``merge_parameters_reference`` (K <= 0: the paper's "over");
    blades: (N, 2) edge normals of a polygonal aperture (None: round);
    sharp_visibility: the front pass in a sharp frame too (RenderSettings.sharp_visibility);
    coarse: ``RenderSettings.coarse_blur_px``: a splat whose aperture radius is at least this
    goes into an A-buffer of the pixels of even row and column only, whose surfaces each
    pixel then takes, interpolated linearly between the samples around it (0: none).
    """
    from .splat.project import (ALPHA, AMP, BLUE, BX, BY, C11, C12, C22, DEPTH, FLOOR, GREEN, GX,
                                GY, MIX, MX, MY, RAD, REACH, RED, RX, RY, ZHI, ZLO)

    blades = np.zeros((0, 2)) if blades is None else blades

    splats = splats.copy()
    if merge[0] > 0 or (sharp_visibility and merge[0] >= 0):  # K < 0: the paper's, no front pass
        front = front_reference(splats, visible, width, height)
        for k in np.flatnonzero(visible):
            splats[k, AMP] *= visibility_reference(splats[k], front, merge, width)
    # per pixel: list of surfaces [w, wr, wg, wb, wa, wd, zlo, zhi]
    abuf = [[[] for _ in range(width)] for _ in range(height)]
    samples = {}  # (i, j) even: the coarse samples' surfaces
    fragments = 0
    for k in np.flatnonzero(visible):
        s = splats[k]
        if s[AMP] <= 0:
            continue
        Wi = np.array([[s[C11], s[C12]], [s[C12], s[C22]]])
        x0, x1, y0, y1 = bbox[k]
        wide = coarse > 0 and abs(s[RAD]) >= coarse
        if wide:  # the samples reach a row and a column past the image
            x1, y1 = x1 + (x1 == width - 1), y1 + (y1 == height - 1)
        if s[RAD] != 0:
            kern = aperture_reference(s[[MX, MY]], np.linalg.inv(Wi), s[RAD], s[MIX], s[REACH],
                                      blades, cutoff, x0, x1, y0, y1)
        else:
            q = _exponents(s[[MX, MY]], Wi, x0, x1, y0, y1)
            kern = np.where(q < cutoff, np.exp(-q) - s[FLOOR], 0.0)
            kern[q >= cutoff] = -1.0  # outside: no fragment (a tapered edge may be 0 inside)
        for i, j in zip(*np.nonzero(kern > 0 if s[RAD] != 0 else kern >= 0)):
            if wide and ((y0 + i) % 2 or (x0 + j) % 2):
                continue
            w = s[AMP] * kern[i, j]
            # an LOD node's colour slope (zero for a surfel), clamped at black
            d = np.array([x0 + j + 0.5 - s[MX], y0 + i + 0.5 - s[MY]])
            rgb = np.maximum(s[[RED, GREEN, BLUE]] + s[[[RX, RY], [GX, GY], [BX, BY]]] @ d, 0.0)
            frag = [w, w * rgb[0], w * rgb[1], w * rgb[2], w * s[ALPHA], w * s[DEPTH],
                    w if s[ALPHA] >= OPAQUE else 0.0, s[ZLO], s[ZHI]]
            if wide:  # a sample (counted where it is a pixel of the image)
                _insert(samples.setdefault((y0 + i, x0 + j), []), frag, max_surfaces)
                fragments += y0 + i < height and x0 + j < width
                continue
            _insert(abuf[y0 + i][x0 + j], frag, max_surfaces)
            fragments += 1
    for i in range(height):
        for j in range(width):
            # the samples around the pixel: itself where even, else the two beside it
            rows = (i - 1, i + 1) if i % 2 else (i,)
            cols = (j - 1, j + 1) if j % 2 else (j,)
            scale = 1.0 / (len(rows) * len(cols))
            for a in rows:
                for b in cols:
                    for surface in samples.get((a, b), ()):
                        _insert(abuf[i][j], [scale * v for v in surface[:7]] + surface[7:],
                                max_surfaces)
    image = np.zeros((height, width, 4))
    depth = np.full((height, width), np.inf)
    weight = np.zeros((height, width))
    for i in range(height):
        for j in range(width):
            image[i, j], depth[i, j], weight[i, j] = _resolve(abuf[i][j], background, merge)
    return image, depth, weight, fragments


def aperture_reference(m, W, radius, mix, reach, blades, cutoff, x0, x1, y0, y1):
    """The aperture kernel (splat/bokeh.py) at the pixel centres of [x0, x1] x [y0, y1],
    from its definition in numpy, the table read by scipy's linear interpolation; 0 beyond
    ``reach`` pixels of the centre."""
    from scipy.interpolate import RegularGridInterpolator

    u_c = math.sqrt(2 * cutoff)
    table = RegularGridInterpolator((np.linspace(0, B_MAX, TABLE_B),
                                     np.linspace(-B_MAX, u_c, TABLE_U)),
                                    aperture_table_reference(cutoff))
    ys, xs = np.mgrid[y0:y1 + 1, x0:x1 + 1] + 0.5
    d = np.stack([xs - m[0], ys - m[1]], axis=-1)
    r = np.hypot(d[..., 0], d[..., 1])
    # the centre has no direction: it takes x's (bokeh.aperture_value)
    n = np.where((r > 0)[..., None], d / np.maximum(r, 1e-300)[..., None], [1.0, 0.0])
    flip = -1.0 if radius < 0 else 1.0  # before the focal plane the polygon is turned over
    radius = abs(radius)
    s_gauss = np.sqrt(np.einsum("...i,ij,...j->...", n, np.linalg.inv(W), n))
    s_edge = 1 / np.sqrt(np.einsum("...i,ij,...j->...", n, W, n))
    scale = s_gauss + mix * (s_edge - s_gauss)
    rad = np.full(r.shape, radius)
    if len(blades):
        rad = radius * math.cos(math.pi / len(blades)) / np.max(flip * n @ blades.T, axis=-1)
    b = rad * scale
    u = r * scale - b
    value = table(np.stack([np.minimum(b, B_MAX), np.clip(u, -B_MAX, u_c)], axis=-1))
    value = np.where(u >= u_c, 0.0, value)  # below -B_MAX: the plateau, the first column
    inside = (ys - 0.5 - m[1] + 0.5) ** 2 + (xs - m[0]) ** 2 <= reach ** 2
    return np.where(inside, value, 0.0)


def aperture_mass_reference(W, radius, mix, blades, moments, angles=None, family=None):
    """bokeh.aperture_mass in numpy: the kernel's integral, int f(theta) dtheta with
    f = (I1(b) + b I0(b)) / s^2 (I0, I1 interpolated in b), by the same two families of
    directions (uniform, and W^(1/2) m of uniform m, from numpy's eigh) and the balance
    heuristic; ``angles`` directions per family instead, uniform only, for a fine plain
    quadrature that the test compares both with; ``family`` directions per family instead
    of MASS_ANGLES (twice that for a polygon), as the mass table's are."""

    W = np.asarray(W, float)
    Wi = np.linalg.inv(W)

    def f(n):
        s_gauss = np.sqrt(np.einsum("ki,ij,kj->k", n, Wi, n))
        s_edge = 1 / np.sqrt(np.einsum("ki,ij,kj->k", n, W, n))
        s = s_gauss + mix * (s_edge - s_gauss)
        rad = np.full(len(n), abs(radius))
        if len(blades):
            rad = abs(radius) * math.cos(math.pi / len(blades)) / np.max(n @ blades.T, axis=1)
        b = rad * s
        grid = np.linspace(0, B_MAX, TABLE_B)
        m = moments[:TABLE_B]  # the moments' rows (the mass table follows them)
        plateau = m[-1, 2]  # the table's first column: T beyond u = -B_MAX
        i0 = np.where(b >= B_MAX, m[-1, 0] + plateau * (b - B_MAX), np.interp(b, grid, m[:, 0]))
        i1 = np.where(b >= B_MAX, m[-1, 1] - plateau * (b * b - B_MAX ** 2) / 2,
                      np.interp(b, grid, m[:, 1]))
        return (i1 + b * i0) / s ** 2

    def unit(a):
        return np.stack([np.cos(a), np.sin(a)], axis=1)

    if angles is not None:
        return float(np.sum(f(unit((np.arange(angles) + 0.5) * 2 * math.pi / angles)))
                     * 2 * math.pi / angles)
    family = family or MASS_ANGLES
    family = family if len(blades) == 0 else 2 * family
    m = unit((np.arange(family) + 0.5) * 2 * math.pi / family)
    lam, vec = np.linalg.eigh(W)
    v = m @ ((vec * np.sqrt(lam)) @ vec.T)  # W^(1/2) m (W^(1/2) is symmetric)
    total = 0.0
    for n in (m, v / np.linalg.norm(v, axis=1)[:, None]):
        # balance heuristic: f / (p_U + p_G), p_U = 1/2pi, p_G = 1 / (2pi sqrt|W| n^T W^-1 n)
        g = np.einsum("ki,ij,kj->k", n, Wi, n)
        total += np.sum(2 * math.pi * f(n) / (1 + 1 / (math.sqrt(np.linalg.det(W)) * g)))
    return float(total / family)


def aperture_mass_table_reference(W, radius, mix, blades, moments):
    """bokeh.aperture_mass in numpy: a disc's mass read from the table in ``moments``' rows
    past TABLE_B (bokeh.mass_table), by W's eigenvalues from numpy's eigvalsh and a
    bilinear interpolation in (ln(l2 / l1) / ln(MASS_E_MIN), sigma / (sigma + R)) written
    out again; a polygon, or a kernel more elongated than 1 / MASS_E_MIN, by the quadrature
    (``aperture_mass_reference``)."""

    l2, l1 = np.linalg.eigvalsh(np.asarray(W, float))
    if len(blades) or l2 < MASS_E_MIN * l1:
        return aperture_mass_reference(W, radius, mix, blades, moments)
    r = abs(radius)
    sigma = math.sqrt((l1 + l2) / 2)
    x = math.log(l2 / l1) / math.log(MASS_E_MIN) * (MASS_E - 1)
    y = sigma / (sigma + r) * (MASS_V - 1)
    i, j = min(int(x), MASS_E - 2), min(int(y), MASS_V - 2)
    a, b = x - i, y - j
    H = moments[TABLE_B:TABLE_B + MASS_E, :MASS_V]
    h = ((1 - a) * ((1 - b) * H[i, j] + b * H[i, j + 1])
         + a * ((1 - b) * H[i + 1, j] + b * H[i + 1, j + 1]))
    return float(h * math.pi * (r * r + 2 * math.sqrt(l1 * l2)))


def merge_fraction_reference(d_front, d_back, opacity_front, merge):
    """The merge fraction of two surfaces (abuffer.merge_fraction), from its definition."""

    coc_k, inv_focus, rho0, rho1 = merge
    if coc_k <= 0:
        return 0.0
    blur = max(coc_k * abs(1 / d - inv_focus) for d in (d_front, d_back))
    if blur <= 0:
        return 0.0
    rho = (coc_k * abs(1 / d_front - 1 / d_back) + 1) / blur
    t = float(np.clip((rho - rho0) / (rho1 - rho0), 0, 1))
    opaque = float(np.clip((opacity_front - OPAQUE + 0.05) / 0.05, 0, 1))
    return (1 - (3 * t * t - 2 * t ** 3)) * opaque


def front_reference(splats, visible, width, height, margin=None):
    """((H + 2 margin) * (W + 2 margin), 3): per pixel of the image and ``margin`` pixels
    round it (default abuffer.FRONT_MARGIN; map pixel (i, j) is the image's (i - margin,
    j - margin)) the least depth and z_hi of the opaque unblurred disks on it, and the
    nearest one's z_hi + MERGE_REACH |g| (C_r + 1) (abuffer.front_fragments)."""
    from .splat.project import ALPHA, COC, DEPTH, F11, F12, F22, GZX, GZY, MX, MY, ZHI

    margin = FRONT_MARGIN if margin is None else margin
    fw, fh = width + 2 * margin, height + 2 * margin
    front = np.full((fh, fw, 3), np.inf)
    for k in np.flatnonzero(visible):
        s = splats[k]
        if s[ALPHA] < OPAQUE or not np.all(np.isfinite(s[[MX, MY]])):
            continue
        Fi = np.array([[s[F11], s[F12]], [s[F12], s[F22]]])  # the conic: F's inverse
        # the disk lies within sqrt(2 c / lambda_min(F^-1)) of its centre: its map pixels
        r = math.sqrt(2 * FRONT_CUTOFF / np.linalg.eigvalsh(Fi).min()) + 1
        cx, cy = s[MX] + margin, s[MY] + margin
        x0, x1 = max(int(cx - r), 0), min(int(cx + r) + 1, fw)
        y0, y1 = max(int(cy - r), 0), min(int(cy + r) + 1, fh)
        if x0 >= x1 or y0 >= y1:
            continue
        ys, xs = np.mgrid[y0:y1, x0:x1] + 0.5
        d = np.stack([xs - cx, ys - cy], axis=-1)
        inside = 0.5 * np.einsum("...i,ij,...j->...", d, Fi, d) < FRONT_CUTOFF
        reach = s[ZHI] + MERGE_REACH * math.hypot(s[GZX], s[GZY]) * (s[COC] + 1)
        f = front[y0:y1, x0:x1]
        nearer = inside & (s[DEPTH] < f[..., 0])
        f[..., 2] = np.where(nearer, reach, f[..., 2])
        f[..., 0] = np.where(nearer, s[DEPTH], f[..., 0])
        f[..., 1] = np.where(inside, np.minimum(f[..., 1], s[ZHI]), f[..., 1])
    return front.reshape(-1, 3)


def visibility_reference(s, front, merge, width, margin=None):
    """A splat's visibility (abuffer.splat_visibility): 9 points of its unblurred disk, then,
    if it is hidden at all of them, 4 looks through the lens from each; front: the image's
    front map and ``margin`` pixels round it (``front_reference``), width the image's."""
    from .splat.project import COC, DEPTH, F11, F12, F22, GZX, GZY, MX, MY, ZLO

    s = np.asarray(s, np.float64)  # as the kernel reads a float32 row: in float64
    margin = FRONT_MARGIN if margin is None else margin
    fw = width + 2 * margin
    height = front.shape[0] // fw - 2 * margin
    F = np.linalg.inv(np.array([[s[F11], s[F12]], [s[F12], s[F22]]]))
    L = np.linalg.cholesky(F)
    angles = np.arange(VIS_SAMPLES - 1) * 2 * math.pi / (VIS_SAMPLES - 1)
    points = [np.zeros(2)] + [L @ np.array([math.cos(a), math.sin(a)]) for a in angles]
    g = np.array([s[GZX], s[GZY]])
    zlo = s[ZLO] - 0.75 * np.linalg.norm(g)
    m = np.array([s[MX], s[MY]])

    def index(c):
        return (math.floor(c[1]) + margin) * fw + math.floor(c[0]) + margin

    def pixel(x):
        """The map's pixel where the front is read for point x, and the shift to it: the
        point's own, in the image or where a disk covers the margin; else the front goes
        on as it is at the centre of the nearest edge pixel of the image."""
        inside = 0 <= x[0] < width and 0 <= x[1] < height
        in_map = -margin <= x[0] < width + margin and -margin <= x[1] < height + margin
        if inside or (in_map and front[index(x), 0] < np.inf):
            return index(x), np.zeros(2)
        c = np.array([0.5 if x[0] < 0 else width - 0.5 if x[0] >= width else x[0],
                      0.5 if x[1] < 0 else height - 0.5 if x[1] >= height else x[1]])
        return index(c), c - x

    if not np.all(np.isfinite(m)):
        return 1.0

    removed, hidden = 0.0, 0
    for o in points:
        p, e = pixel(m + o)
        f_depth, f_zhi = front[p, :2]
        if zlo + g @ e > f_zhi:  # its own depth carried along its tangent plane to the edge
            hidden += 1
            removed += merge_fraction_reference(f_depth, s[DEPTH], 1.0, merge)
    removed /= VIS_SAMPLES
    if hidden < VIS_SAMPLES or removed >= 1 or np.linalg.norm(g) >= 1e29:
        return 1 - removed
    p, e = pixel(m)
    if removed == 0 and \
            zlo + g @ e - MERGE_REACH * np.linalg.norm(g) * (s[COC] + 1) > front[p, 2]:
        return 1.0  # nothing merges it into the front: "over" hides it
    looks = []
    for n, o in enumerate(points):
        parallax = (LENS_RING * merge[0] * abs(1 / front[pixel(m + o)[0], 0] - 1 / s[DEPTH])
                    + LENS_MARGIN)
        for l in range(LENS_POINTS):
            a = (l + n / VIS_SAMPLES) * 2 * math.pi / LENS_POINTS
            shift = parallax * np.array([math.cos(a), math.sin(a)])
            p, e = pixel(m + o + shift)
            looks.append(zlo + g @ (shift + e) > front[p, 1])
    t = float(np.clip((np.mean(looks) - HIDDEN_H0) / (1 - HIDDEN_H0), 0, 1))
    return 1 - max(removed, t * t * (3 - 2 * t))


# a surface: [w, wr, wg, wb, wa, wd, w of opaque fragments, z_lo, z_hi]
def _overlaps(a, b):
    return a[7] <= b[8] and a[8] >= b[7]


def _add(dst, src):
    for f in range(7):
        dst[f] += src[f]
    dst[7] = min(dst[7], src[7])
    dst[8] = max(dst[8], src[8])


def _alpha(s, merge):
    """A surface's opacity (abuffer.layer_alpha): min(1, w) x mean opacity, at least the
    coverage of its opaque fragments' weights w_o; where the surface is sharp (CoC radius at
    its mean depth up to COVER_SHARP_PX, fading out by twice that: abuffer.sharpness), that
    coverage reaches 1 at w_o = COVER_FULL, rising linearly from w_o at COVER_KNEE; where
    it is blurred, at BLUR_COVER_FULL from BLUR_COVER_KNEE (weighted by 1 - sharpness). The
    paper's reconstruction keeps min(1, w_o)."""

    coc_k, inv_focus = merge[0], merge[1]
    d = s[5] / s[0]
    wo = s[6]
    cover = min(1.0, wo)
    if coc_k < 0:  # the paper's reconstruction: its own min(1, w)
        return max(min(1.0, s[0]) * s[4] / s[0], cover)
    elif coc_k == 0 or d <= 0:  # a pinhole
        sharp = 1.0
    else:
        sharp = float(np.clip(2 - coc_k * abs(1 / d - inv_focus) / COVER_SHARP_PX, 0, 1))
    if sharp < 1 and wo > BLUR_COVER_KNEE:
        ramp = float(np.interp(wo, [BLUR_COVER_KNEE, BLUR_COVER_FULL], [BLUR_COVER_KNEE, 1.0]))
        cover += (1 - sharp) * (ramp - cover)
    if sharp > 0 and wo > COVER_KNEE:
        knee = float(np.interp(wo, [COVER_KNEE, COVER_FULL], [COVER_KNEE, 1.0]))
        cover += sharp * (knee - cover)
    return max(min(1.0, s[0]) * s[4] / s[0], cover)


def _insert(surfaces, frag, max_surfaces):
    hit = next((i for i, s in enumerate(surfaces) if _overlaps(frag, s)), None)
    if hit is None and len(surfaces) == max_surfaces:
        gaps = [max(s[7] - frag[8], frag[7] - s[8]) for s in surfaces]
        hit = int(np.argmin(gaps))
    if hit is None:
        surfaces.append(list(frag))
        return
    _add(surfaces[hit], frag)
    # coalesce: surfaces the united range now reaches are the same surface
    j = 0
    while j < len(surfaces):
        if j != hit and _overlaps(surfaces[j], surfaces[hit]):
            _add(surfaces[hit], surfaces[j])
            last = len(surfaces) - 1
            surfaces[j] = surfaces[last]  # same slot bookkeeping as the kernel
            surfaces.pop()
            if hit == last:
                hit = j
            j = 0
            continue
        j += 1


def _resolve(surfaces, background, merge=(0.0, 0.0, 0.15, 0.5)):
    """One pixel: the expectation over every partition of the depth-sorted surfaces into runs
    (run i..j merged with probability m_i ... m_(j-1) (1 - m_j)) of "over" of the runs."""
    import itertools

    def mean_depth(s):
        return s[5] / s[0] if s[0] > 0 else 0.5 * (s[7] + s[8])

    order = sorted(range(len(surfaces)), key=lambda i: (mean_depth(surfaces[i]), i))
    ss = [surfaces[i] for i in order]
    n = len(ss)
    m = [merge_fraction_reference(mean_depth(ss[t]), mean_depth(ss[t + 1]),
                                  ss[t][4] / ss[t][0] if ss[t][0] > 0 else 0.0, merge)
         for t in range(n - 1)]
    rgb, trans = np.zeros(3), 0.0
    for cuts in itertools.product((False, True), repeat=max(n - 1, 0)):
        # cuts[t]: a run ends after surface t
        prob = math.prod((1 - m[t]) if cut else m[t] for t, cut in enumerate(cuts))
        if prob == 0:
            continue
        runs, start = [], 0
        for t in range(n):
            if t == n - 1 or cuts[t]:
                runs.append(np.sum([ss[u][:7] for u in range(start, t + 1)], axis=0))
                start = t + 1
        c, tr = np.zeros(3), 1.0
        for run in runs:
            if run[0] <= 0:
                continue
            alpha = _alpha(run, merge)
            c += tr * alpha * run[1:4] / run[0]
            tr *= 1 - alpha
        rgb += prob * c
        trans += prob * tr
    if n == 0:
        trans = 1.0
    # the depth of the surface that contributes most, by "over" of the separate surfaces
    tr, best, best_depth = 1.0, 0.0, np.inf
    for s in ss:
        if s[0] <= 0:
            continue
        alpha = _alpha(s, merge)
        if tr * alpha > best:
            best, best_depth = tr * alpha, mean_depth(s)
        tr *= 1 - alpha
    rgb += trans * np.asarray(background)
    nearest = ss[0][0] if ss else 0.0
    return np.array([*rgb, 1 - trans]), best_depth, nearest


def render_reference(surfels: Surfels, camera: Camera, lens=None, settings=None):
    """The whole pipeline from the twins (shading is shared: it is numpy already)."""
    from .backends.cpu import shade_surfels

    settings = settings or RenderSettings()
    rgb = shade_surfels(surfels, camera, settings)
    splats, bbox, visible = project_reference(surfels, rgb, camera, lens, settings)
    return rasterize_reference(splats, bbox, visible, camera.width, camera.height,
                               settings.cutoff, settings.background,
                               merge=merge_parameters_reference(camera, lens, settings),
                               blades=aperture_shape_reference(lens, settings)[1],
                               sharp_visibility=settings.sharp_visibility
                               and settings.reconstruction == "soft",
                               coarse=settings.coarse_blur_px)
