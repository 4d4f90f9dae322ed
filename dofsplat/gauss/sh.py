"""Real spherical harmonics of degree 0-3: the colour of a Gaussian seen from a direction.

The basis, its order and its signs are 3DGS's (Kerbl et al. 2023, ``sh_utils.py``; gsplat's
``spherical_harmonics``): for the unit direction d = (x, y, z) from the camera centre to the
Gaussian's centre, colour = max(0, 0.5 + sum_k Y_k(d) c_k) per channel, in the trainer's
colour space. The constants are the normalisations sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!) of
the real harmonics (times sqrt(2) for m != 0).
"""

from __future__ import annotations

import numpy as np

from ..jit import numba

C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


@numba.njit(cache=True, nogil=True, inline="always")
def sh_color(x, y, z, sh, i, ch):
    """0.5 + sum_k Y_k(x, y, z) sh[i, k, ch]: Gaussian i's colour channel ch before the
    clamp at 0, for the unit direction (x, y, z), over its K = sh.shape[1] (1, 4, 9 or 16)
    coefficients. The basis is summed as it is evaluated (no array: the CUDA backend
    compiles this as a device function too)."""
    k = sh.shape[1]
    c = 0.5 + C0 * sh[i, 0, ch]
    if k > 1:
        c += C1 * (-y * sh[i, 1, ch] + z * sh[i, 2, ch] - x * sh[i, 3, ch])
    if k > 4:
        xx, yy, zz = x * x, y * y, z * z
        c += (C2[0] * x * y * sh[i, 4, ch] + C2[1] * y * z * sh[i, 5, ch]
              + C2[2] * (2.0 * zz - xx - yy) * sh[i, 6, ch] + C2[3] * x * z * sh[i, 7, ch]
              + C2[4] * (xx - yy) * sh[i, 8, ch])
        if k > 9:
            c += (C3[0] * y * (3.0 * xx - yy) * sh[i, 9, ch]
                  + C3[1] * x * y * z * sh[i, 10, ch]
                  + C3[2] * y * (4.0 * zz - xx - yy) * sh[i, 11, ch]
                  + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[i, 12, ch]
                  + C3[4] * x * (4.0 * zz - xx - yy) * sh[i, 13, ch]
                  + C3[5] * z * (xx - yy) * sh[i, 14, ch]
                  + C3[6] * x * (xx - 3.0 * yy) * sh[i, 15, ch])
    return c


def sh_basis_numpy(dirs: np.ndarray, k: int) -> np.ndarray:
    """(M, K) float64: the basis at unit directions (M, 3), written from the closed forms in
    Cartesian coordinates (the slow twin of ``sh_color``'s basis)."""
    d = np.asarray(dirs, np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    cols = [np.full_like(x, C0)]
    if k > 1:
        cols += [-C1 * y, C1 * z, -C1 * x]
    if k > 4:
        cols += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * z * z - x * x - y * y),
                 C2[3] * x * z, C2[4] * (x * x - y * y)]
    if k > 9:
        cols += [C3[0] * y * (3 * x * x - y * y), C3[1] * x * y * z,
                 C3[2] * y * (4 * z * z - x * x - y * y),
                 C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y),
                 C3[4] * x * (4 * z * z - x * x - y * y), C3[5] * z * (x * x - y * y),
                 C3[6] * x * (x * x - 3 * y * y)]
    return np.stack(cols, axis=1)
