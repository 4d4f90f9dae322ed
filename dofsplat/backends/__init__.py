"""Where a frame is rendered: on the CPU (numba) or on an NVIDIA GPU (numba-cuda).

``RenderSettings.device`` (and ``--device``) is one of ``DEVICES``:

* ``"cpu"``: the numba kernels of ``dofsplat.splat`` and ``dofsplat.raster`` (the default);
* ``"cuda"``: the kernels of ``dofsplat.backends.cuda``, the same per-splat maths compiled as
  CUDA device functions; an error (``DofsplatError``) where no GPU works;
* ``"auto"``: the GPU where one works, else the CPU, said once per process as a warning.

Importing this module touches no GPU and imports no CUDA package: ``cuda_problem`` does,
on first use, and keeps its answer.
"""

from __future__ import annotations

import warnings

from ..errors import DofsplatError
from ..frame import DEVICES

_PROBLEM: list[str | None] = []  # cuda_problem's answer, once computed
_FALLBACK_SAID = False


def cuda_problem() -> str | None:
    """Why the CUDA backend cannot run here (one line), or None when it can.

    Imports numba's CUDA target, looks for a GPU and runs a one-thread kernel (this also
    finds a missing NVVM compiler); under numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``,
    for the tests) the answer is None. The first call takes about a second on a GPU.
    """
    if not _PROBLEM:
        _PROBLEM.append(_probe_cuda())
    return _PROBLEM[0]


def resolve_device(device: str, flag: str = "device") -> str:
    """``"cpu"`` or ``"cuda"`` for a ``DEVICES`` entry (see the module docstring).

    flag: how messages name the setting (the CLI passes ``"--device"``).
    """
    global _FALLBACK_SAID
    if device not in DEVICES:
        raise DofsplatError(f"{flag} must be one of {', '.join(DEVICES)}, got {device!r}")
    if device == "cpu":
        return "cpu"
    problem = cuda_problem()
    if problem is None:
        return "cuda"
    if device == "cuda":
        raise DofsplatError(f"{flag} cuda cannot run here: {problem} (use {flag} cpu or auto)")
    if not _FALLBACK_SAID:
        _FALLBACK_SAID = True
        warnings.warn(f"no usable CUDA GPU ({problem}): rendering on the CPU", RuntimeWarning,
                      stacklevel=2)
    return "cpu"


def _probe_cuda() -> str | None:
    try:
        from numba import config, cuda
    except Exception as e:  # noqa: BLE001 - any import failure means "not installed"
        return f"numba's CUDA target does not import ({_first_line(e)}); pip install 'dofsplat[cuda]'"
    if config.ENABLE_CUDASIM:
        return None
    try:
        if not cuda.is_available():
            return "no CUDA GPU or driver was found"
        import numpy as np

        from .cuda import probe_kernel

        out = cuda.to_device(np.zeros(1, np.float64))
        probe_kernel[1, 1](out)
        if out.copy_to_host()[0] != 1.0:
            return "a test kernel ran but gave a wrong result"
    except Exception as e:  # noqa: BLE001 - driver, NVVM or launch failures all end here
        return f"a test kernel failed: {_first_line(e)}"
    return None


def _first_line(e: BaseException) -> str:
    lines = [line.strip() for line in str(e).splitlines() if line.strip()]
    return f"{type(e).__name__}: {lines[0]}" if lines else type(e).__name__
