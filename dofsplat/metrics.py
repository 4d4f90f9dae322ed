"""Image metrics: PSNR and SSIM between two renders, and a difference image.

Both metrics are computed on the **displayed** images: linear RGB clipped to [0, 1] and
sRGB-encoded, values in [0, 1] (data range 1). That is what a viewer sees and what a PNG
holds, so the numbers of a float render and of its 8-bit PNG differ only by the PNG's
quantisation (about 59 dB), and SSIM, designed for display-encoded images, is used as meant.
``space="linear"`` measures the clipped linear values instead (PSNR then weighs highlights
more and shadows less).

* PSNR = 10 log10(1 / MSE) dB over all pixels and colour channels; inf for identical images.
* SSIM: Wang et al. (2004) as in scikit-image, with their settings: Gaussian window
  sigma = 1.5 (11 x 11), K1 = 0.01, K2 = 0.03, population covariances, averaged over the
  image and the colour channels.

Only colour is compared: the renderer has already composited over the background, so the
alpha channel carries no extra picture. An image with 1 or 2 channels (grey, grey + alpha)
is compared as grey.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import DofsplatError
from .io.images import nonfinite_pixels

SPACES = ("srgb", "linear")
SSIM_SIGMA = 1.5  # Wang et al.'s Gaussian window
SSIM_MIN_SIDE = 11  # the Gaussian window's extent, 2 * int(3.5 sigma + 0.5) + 1
DIFF_GAIN = 10.0  # default amplification of the difference image


def display_values(image: np.ndarray, space: str = "srgb") -> np.ndarray:
    """(H, W, C) colour channels of a linear image as compared: clipped, sRGB-encoded or not.

    image: (H, W), (H, W, 1..4) float, linear. Returns (H, W, 3) or (H, W, 1) float64 in [0, 1].
    """
    from .io import linear_to_srgb

    if space not in SPACES:
        raise DofsplatError(f"colour space must be one of {', '.join(SPACES)}, got {space!r}")
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4) or 0 in a.shape:
        raise DofsplatError(f"expected an image of shape (H, W) or (H, W, 1..4), got {a.shape}")
    colour = a[..., :3] if a.shape[2] >= 3 else a[..., :1]
    colour = colour.astype(np.float64)
    bad = nonfinite_pixels(colour)
    if bad:
        raise DofsplatError(f"image has {bad} pixels with NaN or inf values")
    colour = np.clip(colour, 0.0, 1.0)
    return linear_to_srgb(colour) if space == "srgb" else colour


def psnr(a: np.ndarray, b: np.ndarray, space: str = "srgb") -> float:
    """PSNR in dB between two linear images (see the module notes); inf if identical."""
    return _psnr(*_pair(a, b, space))


def ssim(a: np.ndarray, b: np.ndarray, space: str = "srgb") -> float:
    """Mean SSIM between two linear images (see the module notes); 1 if identical."""
    return _ssim(*_pair(a, b, space))


def compare(a: np.ndarray, b: np.ndarray, space: str = "srgb") -> dict:
    """PSNR and SSIM between two linear images of the same size.

    a, b:  (H, W), (H, W, C) float, linear RGB(A) as rendered or read by ``io.read_image``;
           at least 11 x 11 pixels (SSIM's window)
    space: "srgb" (default: the displayed values) or "linear"

    Returns {"psnr": dB (inf for identical images), "ssim": mean SSIM in [-1, 1],
    "mse": mean squared error of the compared values, "space": space}.
    """
    x, y = _pair(a, b, space)
    mse = _mse(x, y)
    return {"psnr": _psnr(x, y, mse), "ssim": _ssim(x, y), "mse": mse, "space": space}


def _mse(x, y) -> float:
    from skimage.metrics import mean_squared_error

    return float(mean_squared_error(x, y))


def _psnr(x, y, mse: float | None = None) -> float:
    mse = _mse(x, y) if mse is None else mse
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)  # data range 1


def _ssim(x, y) -> float:
    from skimage.metrics import structural_similarity

    if min(x.shape[:2]) < SSIM_MIN_SIDE:
        raise DofsplatError(f"images of {x.shape[1]}x{x.shape[0]} pixels are too small to "
                            f"compare: SSIM needs at least {SSIM_MIN_SIDE}x{SSIM_MIN_SIDE}")
    return float(structural_similarity(x, y, data_range=1.0, channel_axis=2,
                                       gaussian_weights=True, sigma=SSIM_SIGMA,
                                       use_sample_covariance=False))


def difference_image(a: np.ndarray, b: np.ndarray, gain: float = DIFF_GAIN,
                     space: str = "srgb") -> np.ndarray:
    """gain x |a - b| of the compared values, per channel, clipped to [0, 1]: (H, W, 3) float64.

    The result is a display (sRGB) picture when space is "srgb"; black where the images agree.
    """
    if not (math.isfinite(gain) and gain > 0):
        raise DofsplatError(f"difference gain must be > 0, got {gain}")
    x, y = _pair(a, b, space)
    d = np.clip(gain * np.abs(x - y), 0.0, 1.0)
    return np.repeat(d, 3, axis=2) if d.shape[2] == 1 else d


def write_difference(path, a: np.ndarray, b: np.ndarray, gain: float = DIFF_GAIN,
                     space: str = "srgb"):
    """Write :func:`difference_image` so that a PNG shows exactly gain x |a - b|. Returns the path.

    The format follows the extension (.png, .npy, .exr); like every image, .npy and .exr hold
    linear values, here the linear values whose display is the difference picture. Atomic.
    """
    from .io import srgb_to_linear, write_image

    d = difference_image(a, b, gain, space)
    linear = srgb_to_linear(d) if space == "srgb" else d
    return write_image(path, linear.astype(np.float32))


def _pair(a, b, space: str) -> tuple[np.ndarray, np.ndarray]:
    x, y = display_values(a, space), display_values(b, space)
    if x.shape[:2] != y.shape[:2]:
        raise DofsplatError(f"the images differ in size: {x.shape[1]}x{x.shape[0]} and "
                            f"{y.shape[1]}x{y.shape[0]} pixels")
    if x.shape[2] != y.shape[2]:
        raise DofsplatError("cannot compare a colour image with a grey one")
    return x, y
