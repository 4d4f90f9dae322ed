"""numba, with dofsplat's compiled kernels cached in the user's cache folder.

Every module of dofsplat that jits a kernel imports numba from here (``from ..jit import
numba``). Importing it registers a cache locator that puts the compiled code of kernels
defined in dofsplat's own sources under ``<cache folder>/kernels/<versions>/`` (the cache
folder of ``dofsplat.cache``: ``~/.cache/dofsplat`` unless ``DOFSPLAT_CACHE_DIR`` or
``XDG_CACHE_HOME`` moves it; ``DOFSPLAT_KERNEL_DIR`` moves the kernels alone), never inside
the installed package. numba's own default is
``__pycache__`` beside the source, which inside ``site-packages`` breaks two things:

* ``pip uninstall`` does not know those files, so the package's folders outlive it holding
  only ``__pycache__``; after ``pip install . && pip install -e .`` Python took
  ``site-packages/dofsplat/splat`` for a namespace package and ``dofsplat demo`` failed
  with ``No module named 'dofsplat.splat.subaperture'`` (issue 51);
* a read-only install (system, conda or container site-packages) cannot hold them.

``<versions>`` names dofsplat's, numba's and Python's versions, so that an upgrade starts a
clean folder rather than piling stale entries beside the live ones (numba's index already
refuses code compiled from another source file's stamp). Kernels of other code (a user's
own ``@numba.njit(cache=True)``) keep numba's default. The locator builds on numba's
locator classes (``numba.core.caching``, not a public interface): where they are missing,
numba's default applies and nothing fails.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numba

from .cache import cache_root

_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__))


def kernel_cache_folder() -> Path:
    """The folder that holds dofsplat's compiled kernels for these versions:
    ``DOFSPLAT_KERNEL_DIR`` where set (the tests keep one there while they point the rest of
    the cache at a temporary folder), else under the cache folder."""
    from . import __version__

    if os.environ.get("DOFSPLAT_KERNEL_DIR"):
        return Path(os.environ["DOFSPLAT_KERNEL_DIR"])
    py = f"{sys.version_info.major}{sys.version_info.minor}"
    return cache_root() / "kernels" / f"dofsplat-{__version__}-numba-{numba.__version__}-py{py}"


def _in_package(py_file: str) -> bool:
    path = os.path.abspath(py_file)
    return os.path.commonpath([path, _PACKAGE_DIR]) == _PACKAGE_DIR


def _register() -> bool:
    """Put the locator first in numba's list; False where numba's internals differ."""
    try:
        from numba.core import caching

        impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl")
        base = (caching._SourceFileBackedLocatorMixin, caching._CacheLocator)
    except (ImportError, AttributeError):
        return False

    class KernelCacheLocator(*base):
        """dofsplat's kernels: cached under ``kernel_cache_folder()``, by source folder."""

        def __init__(self, py_func, py_file):
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno
            self._cache_path = str(kernel_cache_folder()
                                   / self.get_suitable_cache_subpath(py_file))

        def get_cache_path(self):
            return self._cache_path

        @classmethod
        def from_function(cls, py_func, py_file):
            if not _in_package(py_file):
                return None  # not ours: numba's next locator decides
            # None where the folder cannot be made or written: numba's next locator then
            # tries (the source's __pycache__, then its user-wide folder)
            return super().from_function(py_func, py_file)

    locators = impl._locator_classes
    if not any(c.__name__ == "KernelCacheLocator" for c in locators):
        locators.insert(0, KernelCacheLocator)
    return True


REGISTERED = _register()

__all__ = ["numba", "kernel_cache_folder", "REGISTERED"]
