"""Writing and reading rendered images, and atomic file replacement.

Formats are chosen by extension:

* ``.png``: 8-bit sRGB RGB (the renderer has already composited over the background, so
  alpha would be redundant), via Pillow;
* ``.npy``: float32 (H, W, 4) linear RGBA, exactly as rendered;
* ``.exr``: float32 linear R G B A channels, plus Z (camera depth) when given, via the
  optional ``OpenEXR`` package (``pip install 'dofsplat[exr]'``).

Every writer goes through :func:`atomic_write`, so an interrupted or failed write never
leaves a half-written file where the output should be.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import DofsplatError
from ..colors import linear_to_srgb, srgb_to_linear

SUPPORTED_IMAGE_EXTENSIONS = (".png", ".npy", ".exr")

_EXR_MISSING = "writing .exr needs the optional OpenEXR package: pip install 'dofsplat[exr]'"
_U8_MAX = 255.0
_U16_MAX = 65535.0


# ---------------------------------------------------------------------------------------
# Atomic replacement


def atomic_write(path, write_fn: Callable[[str], None]) -> Path:
    """Create ``path`` by calling ``write_fn(tmp_path)`` on a temporary file, then rename.

    The temporary file lies in the destination's directory (so that ``os.replace`` is an
    atomic rename on the same file system) and ends with the destination's suffix (so that
    libraries that pick a format from the name, like Pillow, pick the right one). If
    ``write_fn`` raises, the temporary file is removed and the exception propagates; the
    destination is left untouched. OS errors (disk full, no permission) become
    :class:`DofsplatError`. Returns the destination path.
    """
    path = Path(path)
    _check_parent_dir(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    except OSError as e:
        raise DofsplatError(f"{path}: cannot write: {e.strerror or e}") from e
    try:
        os.close(fd)
        # mkstemp makes the file private (0600); a rendered image should get the
        # permissions any newly created file would.
        os.chmod(tmp, 0o666 & ~_umask())
        write_fn(tmp)
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(e, OSError):
            raise DofsplatError(f"{path}: cannot write: {e.strerror or e}") from e
        raise
    return path


_UMASK: int | None = None


def _umask() -> int:
    # os.umask can only be read by setting it (and putting it back), so read it once
    global _UMASK
    if _UMASK is None:
        _UMASK = os.umask(0o022)
        os.umask(_UMASK)
    return _UMASK


def _check_parent_dir(path: Path) -> None:
    parent = path.parent
    if not parent.is_dir():
        if parent.exists():
            raise DofsplatError(f"{path}: {str(parent)!r} is a file, not a directory")
        raise DofsplatError(f"{path}: directory {str(parent)!r} does not exist")


# ---------------------------------------------------------------------------------------
# Output paths


def check_writable_path(path, what: str = "a file name") -> Path:
    """Check that ``path`` can be created: not a directory, in an existing writable one.

    ``what`` names the expected file in the message. Raises DofsplatError; returns the path.
    """
    path = Path(path)
    if path.is_dir():
        raise DofsplatError(f"{path}: is a directory, expected {what}")
    _check_parent_dir(path)
    # a file made and removed there: os.access says yes to root everywhere, /proc included
    try:
        fd, probe = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".probe")
        try:
            os.close(fd)
        finally:
            os.unlink(probe)
    except OSError as e:
        raise DofsplatError(f"{path}: directory {str(path.parent)!r} is not writable "
                            f"({e.strerror or e})") from e
    return path


def check_output_path(path) -> Path:
    """Validate an image output path before any rendering work is done.

    Checks the extension (one of SUPPORTED_IMAGE_EXTENSIONS, any case), then
    :func:`check_writable_path`, and that the OpenEXR package is importable for ``.exr``.
    Raises DofsplatError; returns the path.
    """
    path = Path(path)
    fmt = _image_format(path)
    check_writable_path(path, "an image file name")
    if fmt == ".exr":
        _import_openexr()
    return path


def _image_format(path: Path) -> str:
    ext = path.suffix.lower()
    if ext not in SUPPORTED_IMAGE_EXTENSIONS:
        raise DofsplatError(f"{path}: unsupported image format {ext or '(no extension)'!r}; "
                            f"supported: {', '.join(SUPPORTED_IMAGE_EXTENSIONS)}")
    return ext


def _import_openexr():
    try:
        import OpenEXR
    except ImportError:
        raise DofsplatError(_EXR_MISSING) from None
    return OpenEXR


# ---------------------------------------------------------------------------------------
# Writing


def write_image(path, rgba: np.ndarray, depth: np.ndarray | None = None) -> Path:
    """Write a rendered image; the format follows the extension.

    rgba:  (H, W, 4) float, linear RGB already composited over the background, then alpha
           (coverage in [0, 1]). (H, W, 3) is accepted too.
    depth: (H, W) float or None, camera depth U in world units, inf where nothing was hit.
           Only ``.exr`` has room for it (a Z channel); ``.png`` and ``.npy`` ignore it,
           use :func:`write_depth` for a separate depth file.

    ``.png`` stores RGB as 8-bit sRGB (clipped to [0, 1], rounded); ``.npy`` stores the
    float32 array as given; ``.exr`` stores float32 R G B (A) (Z). Atomic; returns the path.
    """
    path = Path(path)
    fmt = _image_format(path)
    rgba = _check_rgba(rgba)
    if fmt == ".png":
        write_fn = _png_writer(_encode_srgb8(rgba[..., :3]))
    elif fmt == ".npy":
        write_fn = _npy_writer(rgba)
    else:
        channels = dict(zip("RGBA", np.moveaxis(rgba, -1, 0)))
        if depth is not None:
            channels["Z"] = _check_depth(depth, rgba.shape[:2])
        write_fn = _exr_writer(channels)
    return atomic_write(path, write_fn)


def write_depth(path, depth: np.ndarray) -> Path:
    """Write a depth map as its own file; the format follows the extension.

    depth: (H, W) float, camera depth U in world units; inf (or NaN) where empty.

    * ``.npy``: float32 (H, W), inf where empty;
    * ``.exr``: float32, a single Z channel, inf where empty;
    * ``.png``: 16-bit greyscale for viewing, not for measuring: the finite depths are
      mapped linearly from near (value 1) to far (value 65535), where near and far are the
      smallest and largest finite depth of this image; 0 means empty. near and far are
      kept in the PNG's text chunks ("near", "far").

    Atomic; returns the path.
    """
    path = Path(path)
    fmt = _image_format(path)
    depth = _check_depth(depth)
    depth = np.where(np.isnan(depth), np.float32(np.inf), depth)
    if fmt == ".npy":
        write_fn = _npy_writer(depth)
    elif fmt == ".exr":
        write_fn = _exr_writer({"Z": depth})
    else:
        write_fn = _png_depth_writer(depth)
    return atomic_write(path, write_fn)


def nonfinite_pixels(image) -> int:
    """How many pixels of an (H, W, C) image hold a NaN or an infinity in any channel."""
    return int(np.count_nonzero(~np.isfinite(image).all(axis=2)))


def _check_rgba(rgba) -> np.ndarray:
    rgba = np.asarray(rgba)
    if rgba.ndim != 3 or rgba.shape[2] not in (3, 4) or 0 in rgba.shape:
        raise DofsplatError(f"image must have shape (H, W, 4) or (H, W, 3), got {rgba.shape}")
    if not np.issubdtype(rgba.dtype, np.floating):
        raise DofsplatError(f"image must be floating point (linear RGB), got {rgba.dtype}")
    rgba = np.ascontiguousarray(rgba, dtype=np.float32)
    bad = nonfinite_pixels(rgba)
    if bad:
        raise DofsplatError(f"image has {bad} pixels with NaN or inf values")
    return rgba


def _check_depth(depth, shape=None) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.ndim != 2 or 0 in depth.shape:
        raise DofsplatError(f"depth must have shape (H, W), got {depth.shape}")
    if shape is not None and depth.shape != tuple(shape):
        raise DofsplatError(f"depth has shape {depth.shape} but the image is {tuple(shape)}")
    return np.ascontiguousarray(depth, dtype=np.float32)


def _encode_srgb8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, C) linear float -> (H, W, C) uint8 sRGB, rounded to nearest."""
    srgb = linear_to_srgb(np.clip(rgb.astype(np.float64), 0.0, 1.0))
    return np.round(srgb * _U8_MAX).astype(np.uint8)


def _png_writer(rgb8: np.ndarray):
    def write(tmp):
        from PIL import Image

        Image.fromarray(rgb8, mode="RGB").save(tmp, format="PNG")

    return write


def _png_depth_writer(depth: np.ndarray):
    finite = np.isfinite(depth)
    near = float(depth[finite].min()) if finite.any() else 0.0
    far = float(depth[finite].max()) if finite.any() else 0.0
    span = far - near if far > near else 1.0
    # 1..65535 for near..far so that 0 stays free to mean "empty"
    scaled = 1.0 + np.round((np.where(finite, depth, near) - near) / span * (_U16_MAX - 1))
    grey = np.where(finite, scaled, 0.0).astype(np.uint16)

    def write(tmp):
        from PIL import Image, PngImagePlugin

        info = PngImagePlugin.PngInfo()
        info.add_text("near", repr(near))
        info.add_text("far", repr(far))
        Image.fromarray(grey).save(tmp, format="PNG", pnginfo=info)

    return write


def _npy_writer(array: np.ndarray):
    def write(tmp):
        # a file object, because np.save appends ".npy" to names that lack it
        with open(tmp, "wb") as f:
            np.save(f, array)

    return write


def _exr_writer(channels: dict[str, np.ndarray]):
    OpenEXR = _import_openexr()
    channels = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def write(tmp):
        OpenEXR.File(header, channels).write(str(tmp))

    return write


# ---------------------------------------------------------------------------------------
# Reading


def read_image(path) -> np.ndarray:
    """Read an image as linear float32 (H, W, C).

    ``.png``: 8- or 16-bit samples are sRGB-decoded; an alpha channel is kept linear.
    ``.npy``: the stored (H, W, C) or (H, W) float array. ``.exr``: the R G B A channels
    that exist, in that order; a file without colour channels (a depth map) gives its
    channels in name order, e.g. (H, W, 1) for Z.
    """
    path = Path(path)
    fmt = _image_format(path)
    if not path.is_file():
        raise DofsplatError(f"no such file: {path}")
    reader = {".png": _read_png, ".npy": _read_npy, ".exr": _read_exr}[fmt]
    try:
        image = reader(path)
    except DofsplatError:
        raise
    except Exception as e:  # each library has its own exception types for a bad file
        raise DofsplatError(f"{path}: cannot read image: {e}") from e
    if image.ndim == 2:
        image = image[:, :, None]
    return np.ascontiguousarray(image, dtype=np.float32)


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        if im.mode in ("I;16", "I;16B", "I;16L", "I"):
            grey = np.asarray(im, dtype=np.float64) / _U16_MAX
            return srgb_to_linear(grey)
        if im.mode not in ("L", "LA", "RGB", "RGBA"):
            im = im.convert("RGBA" if "A" in im.getbands() or "transparency" in im.info
                            else "RGB")
        values = np.asarray(im, dtype=np.float64) / _U8_MAX
    if values.ndim == 2:
        return srgb_to_linear(values)
    colour = srgb_to_linear(values)
    if values.shape[2] in (2, 4):  # alpha is coverage, never sRGB-encoded
        colour[..., -1] = values[..., -1]
    return colour


def _read_npy(path: Path) -> np.ndarray:
    image = np.load(path, allow_pickle=False)
    if image.dtype.kind not in "biuf":  # strings, complex, dates: no pixel values
        raise DofsplatError(f"{path}: expected an array of numbers, got dtype {image.dtype}")
    if image.ndim not in (2, 3):
        raise DofsplatError(f"{path}: expected an (H, W) or (H, W, C) array, "
                            f"got shape {image.shape}")
    return image


def _read_exr(path: Path) -> np.ndarray:
    try:
        import OpenEXR
    except ImportError:
        raise DofsplatError("reading .exr needs the optional OpenEXR package: "
                            "pip install 'dofsplat[exr]'") from None
    channels = OpenEXR.File(str(path), separate_channels=True).channels()
    names = [c for c in "RGBA" if c in channels] or sorted(channels)
    return np.stack([np.asarray(channels[c].pixels, dtype=np.float32) for c in names],
                    axis=-1)
