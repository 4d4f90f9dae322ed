"""sRGB transfer functions (IEC 61966-2-1).

The renderer works in linear RGB; 8-bit files (PNG, uchar PLY colours) are sRGB-encoded.
These are the exact piecewise formulas, not the gamma-2.2 approximation, so that an
8-bit value decodes and re-encodes to itself.
"""

from __future__ import annotations

import numpy as np

# Breakpoints of the piecewise curve: below them the curve is a straight line.
SRGB_KNEE = 0.04045  # in encoded (sRGB) units
_LINEAR_KNEE = 0.0031308  # the same point in linear units


def srgb_to_linear(x) -> np.ndarray:
    """Decode sRGB values to linear ones.

    x: array-like of floats in [0, 1], sRGB-encoded. Returns an array of the same shape,
    float32 if x is float32, else float64.
    """
    x = _as_float(x)
    # max() keeps the power away from negative inputs in the branch np.where discards
    curve = ((np.maximum(x, SRGB_KNEE) + 0.055) / 1.055) ** 2.4
    return np.where(x <= SRGB_KNEE, x / 12.92, curve).astype(x.dtype, copy=False)


def linear_to_srgb(x) -> np.ndarray:
    """Encode linear values as sRGB.

    x: array-like of floats in [0, 1], linear. Returns an array of the same shape,
    float32 if x is float32, else float64.
    """
    x = _as_float(x)
    curve = 1.055 * np.maximum(x, _LINEAR_KNEE) ** (1.0 / 2.4) - 0.055
    return np.where(x <= _LINEAR_KNEE, x * 12.92, curve).astype(x.dtype, copy=False)


def _as_float(x) -> np.ndarray:
    x = np.asarray(x)
    if x.dtype != np.float32:
        x = x.astype(np.float64)
    return x
