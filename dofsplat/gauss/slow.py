"""Slow, obviously correct twins of the Gaussian stages, in numpy, for the tests.

They share no code and no constant with ``project``, ``sh`` and ``composite``: the
trainers' numbers are written out here again (0.3 px^2, 1/255, 0.999, 1e-4, the 1.3 x
clamp) and the maths is the textbook form, with whole matrices: Sigma = R S S^T R^T,
cov2d = J W Sigma W^T J^T, and every pixel walks every Gaussian in depth order.
"""

from __future__ import annotations

import math

import numpy as np

EPS2D = 0.3
MIN_ALPHA = 1.0 / 255.0
MAX_ALPHA = 0.999
MIN_TRANSMITTANCE = 1e-4
CLAMP = 1.3


def rotation(q) -> np.ndarray:
    """The 3 x 3 rotation of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def real_sh(d, k: int) -> np.ndarray:
    """The K real spherical harmonics of 3DGS at unit direction d, from the general
    formula sqrt(2) N_l^|m| P_l^|m|(cos theta) {cos for m > 0, sin for m < 0}(|m| phi)
    (N_l^0 P_l for m = 0; P without the Condon-Shortley phase), ordered m = -l..l within
    each degree, times 3DGS's sign (SIGNS: the Condon-Shortley phase (-1)^m)."""
    x, y, z = (float(v) for v in d)
    theta, phi = math.acos(max(-1.0, min(1.0, z))), math.atan2(y, x)
    out = []
    for l in range(4):
        for m in range(-l, l + 1):
            if len(out) == k:
                return np.array(out)
            am = abs(m)
            norm = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - am)
                             / math.factorial(l + am))
            p = _legendre(l, am, math.cos(theta))
            if m == 0:
                value = norm * p
            elif m > 0:
                value = math.sqrt(2) * norm * p * math.cos(m * phi)
            else:
                value = math.sqrt(2) * norm * p * math.sin(am * phi)
            out.append(SIGNS[l * l + l + m] * value)
    return np.array(out[:k])


# (-1)^m at index l^2 + l + m: 3DGS's -C1 y, C1 z, -C1 x and so on
SIGNS = [(-1) ** abs(m) for l in range(4) for m in range(-l, l + 1)]


def _legendre(l: int, m: int, x: float) -> float:
    """The associated Legendre function P_l^m(x) without the Condon-Shortley phase."""
    pmm = 1.0
    s = math.sqrt(max(0.0, 1 - x * x))
    for i in range(1, m + 1):
        pmm *= (2 * i - 1) * s
    if l == m:
        return pmm
    pmm1 = x * (2 * m + 1) * pmm
    if l == m + 1:
        return pmm1
    for ll in range(m + 2, l + 1):
        pll = ((2 * ll - 1) * x * pmm1 - (ll + m - 1) * pmm) / (ll - m)
        pmm, pmm1 = pmm1, pll
    return pmm1


def project_one(position, scale, quaternion, opacity, sh, view, campos, fx, fy, cx, cy,
                width, height, blur_var=0.0, spread_cut=True, share=None):
    """(mean (2,), depth, conic (2, 2), opacity, cut, colour (3,)) of one Gaussian, or None
    when it is behind the near plane. blur_var: the lens blur's variance per axis (px^2)
    added to the footprint (``project``'s BLUR_OURS when spread_cut, else BLUR_VIEWERS);
    share: the Gaussian's visible share over the lens, which the blur spreads in place of
    the whole as it outgrows the footprint: o x share^(1 - spread)."""
    p = view[:3, :3] @ np.asarray(position, np.float64) + view[:3, 3]
    x, y, z = p
    if z <= 0:
        return None
    r = rotation(quaternion)
    s = np.diag(np.asarray(scale, np.float64))
    sigma = r @ s @ s.T @ r.T
    lim_x = ((width - cx) / fx + (CLAMP - 1) * 0.5 * width / fx, cx / fx + (CLAMP - 1) * 0.5 * width / fx)
    lim_y = ((height - cy) / fy + (CLAMP - 1) * 0.5 * height / fy, cy / fy + (CLAMP - 1) * 0.5 * height / fy)
    tx = z * min(lim_x[0], max(-lim_x[1], x / z))
    ty = z * min(lim_y[0], max(-lim_y[1], y / z))
    j = np.array([[fx / z, 0.0, -fx * tx / z ** 2], [0.0, fy / z, -fy * ty / z ** 2]])
    cov = j @ view[:3, :3] @ sigma @ view[:3, :3].T @ j.T + EPS2D * np.eye(2)
    o, cut = float(opacity), MIN_ALPHA
    if blur_var > 0:
        blurred = cov + blur_var * np.eye(2)
        spread = math.sqrt(np.linalg.det(cov) / np.linalg.det(blurred))
        o *= spread
        cut = MIN_ALPHA * spread if spread_cut else MIN_ALPHA
        if spread_cut and share is not None:
            o *= share ** (1 - spread)
        cov = blurred
    d = np.asarray(position, np.float64) - campos
    d /= np.linalg.norm(d)
    basis = real_sh(d, sh.shape[0])
    colour = np.maximum(0.5 + basis @ np.asarray(sh, np.float64), 0.0)
    mean = np.array([fx * x / z + cx, fy * y / z + cy])
    return mean, z, np.linalg.inv(cov), o, cut, colour


def footprint_alpha(mean, conic, o, cut, px, py) -> float:
    """A footprint's alpha at pixel (px, py): min(0.999, o e^-s), 0 where s < 0 or alpha is
    below the cut."""
    dv = mean - (px + 0.5, py + 0.5)
    s = 0.5 * dv @ conic @ dv
    if s < 0:
        return 0.0
    alpha = min(MAX_ALPHA, o * math.exp(-s))
    return alpha if alpha >= cut else 0.0


def composite(footprints, width, height):
    """(colour (H, W, 3), transmittance (H, W)) of projected footprints (``project_one``'s
    tuples), every pixel walking every Gaussian nearest first (ties in list order)."""
    order = sorted(range(len(footprints)), key=lambda i: footprints[i][1])
    colour = np.zeros((height, width, 3))
    trans = np.ones((height, width))
    for py in range(height):
        for px in range(width):
            t, c = 1.0, np.zeros(3)
            for i in order:
                mean, _, conic, o, cut, rgb = footprints[i]
                alpha = footprint_alpha(mean, conic, o, cut, px, py)
                if alpha == 0.0:
                    continue
                if t * (1 - alpha) <= MIN_TRANSMITTANCE:
                    break
                c += alpha * t * rgb
                t *= 1 - alpha
            colour[py, px], trans[py, px] = c, t
    return colour, trans


def composite_summed(footprints, width, height, weights):
    """(colour (H, W, 3), transmittance (H, W)) of projected footprints added, each times
    its weight (a summed layer: opacity and cut both scaled, then the trainers' skip and
    clamp), every pixel's coverage clamped at 1 (its colour then divided by the coverage)."""
    colour = np.zeros((height, width, 3))
    cover = np.zeros((height, width))
    for (mean, _, conic, o, cut, rgb), w in zip(footprints, weights):
        o, cut = o * w, cut * w
        for py in range(height):
            for px in range(width):
                alpha = footprint_alpha(mean, conic, o, cut, px, py)
                colour[py, px] += alpha * rgb
                cover[py, px] += alpha
    over = cover > 1.0
    colour[over] /= cover[over][:, None]
    return colour, 1.0 - np.minimum(cover, 1.0)


def select_cut(tree, view, fx, near, coc_k, inv_focus, blur_variance, fraction) -> np.ndarray:
    """``gauss.lod.select_cut``, level by level with whole-array numpy: a level's candidates
    (ascending) that stop (in front of the near plane, size^2 <= fraction blur_variance
    C_r^2, size = fx extent / z) are drawn, the others' children are the next level's;
    level 0's candidates are all drawn. The rows, each level's in index order, top first."""
    top = tree.n_levels - 1
    candidates = np.arange(tree.offsets[top], tree.offsets[top + 1])
    drawn = []
    for level in range(top, -1, -1):
        if level == 0:
            drawn.append(candidates)
            break
        p = tree.positions[candidates].astype(np.float64)
        z = p @ view[2, :3] + view[2, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            coc = coc_k * np.abs(1.0 / z - inv_focus)
            size = fx * tree.extent[candidates] / z
        stop = (z > near) & (size * size <= fraction * blur_variance * coc * coc)
        drawn.append(candidates[stop])
        local = candidates[~stop] - tree.offsets[level]
        below = tree.offsets[level - 1]
        n_below = tree.offsets[level] - below
        children = np.concatenate([2 * local, 2 * local + 1])
        candidates = np.sort(below + children[children < n_below])
    return np.concatenate(drawn)
