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


def blurred(channels, source, image, sigma):
    """(h, w, C): a summed layer's image blurred from its sharp view's channels (H, W, C):
    the Gaussian of standard deviation sigma (the view's pixels) sampled at the image's
    pixel centres, cut at 3 sigma and normalised over every tap, inside the view or not
    (outside it there is nothing).
    source, image: (scale, margin) of the view and of the image (w, h, scale, margin); a
    pixel x of the image is centred on full-resolution point (x - margin + 1/2) scale."""
    s_k, m_k = source
    w, h, s_i, m_i = image

    def weights(n_out, n_in):
        u = (np.arange(n_out) - m_i + 0.5) * s_i / s_k + m_k - 0.5
        out = np.zeros((n_out, n_in))
        for x, centre in enumerate(u):
            taps = np.arange(math.ceil(centre - 3 * sigma), math.floor(centre + 3 * sigma) + 1)
            wt = np.exp(-0.5 * ((taps - centre) / sigma) ** 2)
            inside = (taps >= 0) & (taps < n_in)
            out[x, taps[inside]] = wt[inside] / wt.sum()
        return out

    wy, wx = weights(h, channels.shape[0]), weights(w, channels.shape[1])
    return np.stack([wy @ channels[..., c] @ wx.T for c in range(channels.shape[2])], -1)


def srgb_decode(x):
    """sRGB to linear, written out (``colors.srgb_to_linear``'s curve)."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def srgb_encode(x):
    """Linear to sRGB, written out."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0) ** (1 / 2.4) - 0.055)


def join(layers, background):
    """A part's layers joined back to front over background (3,) (sRGB), layer by layer:
    layers, front to back, (colour (H, W, 3), T (H, W), linear): a summed layer's colour is
    linear light and joins there (colour + T behind); another's is sRGB and joins there
    (colour + T encode(behind), clipped to [0, 1], decoded). Returns (linear colour (H, W,
    3), the product of the T)."""
    colour, t = layers[0][:2]
    behind = np.broadcast_to(srgb_decode(background), colour.shape).astype(np.float64)
    t_all = np.ones(t.shape)
    for colour, t, linear in reversed(layers):
        if linear:
            behind = colour + t[..., None] * np.clip(behind, 0.0, 1.0)
        else:
            behind = srgb_decode(np.clip(colour + t[..., None] * srgb_encode(
                np.clip(behind, 0.0, 1.0)), 0.0, 1.0))
        t_all = t_all * t
    return np.clip(behind, 0.0, 1.0), t_all


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
