"""The disc kernel per pixel: the scalar kernel against the SIMD rows (issue 14's cost).

    python bench/kernel_rows.py

A round aperture's kernel (R = 6 px, a 3:1 elongated W) over the 12-pixel spans of 16
rows of a tile, many times: ``bokeh.aperture_value`` pixel by pixel (three square roots, two
divisions and a look-up each), against ``bokeh.aperture_rows`` (whole 16-pixel rows in SIMD
lanes) followed by the per-fragment ``bokeh.table_lerp``, as the rasteriser runs them. Prints
nanoseconds per pixel of the spans, one thread, and checks that both give the same values.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dofsplat.splat.bokeh import (ROW, aperture_rows, aperture_table, aperture_value,  # noqa: E402
                                  edge_mix, table_lerp)

SPAN = 12  # pixels of each row inside the support
REPEAT = 100_000


@numba.njit(cache=True)
def scalar(out, reps, w, radius, mix, normals, table, u_c):
    c11, c12, c22 = w[1, 1] / (w[0, 0] * w[1, 1] - w[0, 1] ** 2), \
        -w[0, 1] / (w[0, 0] * w[1, 1] - w[0, 1] ** 2), w[0, 0] / (w[0, 0] * w[1, 1] - w[0, 1] ** 2)
    total = 0.0
    for r in range(reps):
        dx0 = -7.3 + 1e-7 * r
        for i in range(ROW):
            dy = i - 7.6
            for j in range(SPAN):
                dx = dx0 + j
                v = aperture_value(c11 * dx * dx + 2.0 * c12 * dx * dy + c22 * dy * dy,
                                   w[0, 0] * dx * dx + 2.0 * w[0, 1] * dx * dy + w[1, 1] * dy * dy,
                                   dx, dy, radius, mix, normals, table, u_c, c11, w[0, 0])
                out[i * ROW + j] = v
                total += v
    return total


@numba.njit(cache=True)
def simd(out, reps, w, radius, mix, table, u_c):
    det = w[0, 0] * w[1, 1] - w[0, 1] ** 2
    c11, c12, c22 = w[1, 1] / det, -w[0, 1] / det, w[0, 0] / det
    flat = table.reshape(-1)
    cell = np.empty(ROW * ROW, np.int32)
    frac = np.empty((2, ROW * ROW))
    total = 0.0
    for r in range(reps):
        dx0 = -7.3 + 1e-7 * r
        aperture_rows(cell, frac, ROW, dx0, -7.6, radius, c11, c12, c22, w[0, 0], w[0, 1],
                      w[1, 1], mix, u_c, 1.0)
        for i in range(ROW):
            for j in range(SPAN):
                e = i * ROW + j
                v = table_lerp(cell[e], frac[0, e], frac[1, e], flat)
                out[e] = v
                total += v
    return total


def main() -> int:
    w = np.array([[9.0, 2.0], [2.0, 3.0]])
    radius = 6.0
    mix = edge_mix(radius, w[0, 0], w[1, 1])
    table, u_c = aperture_table(2.5), math.sqrt(5.0)
    normals = np.zeros((0, 2))
    a, b = np.zeros(ROW * ROW), np.zeros(ROW * ROW)
    scalar(a, 1, w, radius, mix, normals, table, u_c)
    simd(b, 1, w, radius, mix, table, u_c)
    assert np.allclose(a, b, atol=1e-9), "the SIMD rows differ from the scalar kernel"
    pixels = REPEAT * ROW * SPAN
    for name, run in (("scalar aperture_value", lambda: scalar(a, REPEAT, w, radius, mix, normals, table, u_c)),
                      ("SIMD aperture_rows + table_lerp", lambda: simd(b, REPEAT, w, radius, mix, table, u_c))):
        t = time.perf_counter()
        run()
        print(f"{name:32s} {(time.perf_counter() - t) / pixels * 1e9:5.2f} ns per pixel")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
