"""How the jitted loops share their work among threads.

numba hands each thread of a ``prange`` one contiguous run of its indices (a static
schedule; on the OpenMP threading layer ``numba.set_parallel_chunksize`` did not change
that, bench/RESULTS.md). Work in index order is often work in image order: tile rows from
top to bottom, splats in the LOD tree's spatial order. Where one part of the frame costs
most (a floor near the camera and its blur, foliage before the lens), one thread then works
alone. A loop that visits its n items in the order (k * weyl_stride(n)) mod n gives every
run of consecutive k items from all over the range, and the frame is the same bit for bit
(each item writes its own outputs).
"""

from __future__ import annotations

import contextlib
import signal
import threading

from .jit import numba

PHI_INVERSE = 0.6180339887498949


@numba.njit(cache=True, nogil=True)
def weyl_stride(n):
    """A step s coprime to n, near n / phi: (k s) mod n for k = 0 .. n - 1 visits each of
    0 .. n - 1 once, and any run of consecutive k spreads over the whole range (a Weyl
    sequence: the golden ratio's multiples spread most evenly)."""
    s = max(int(n * PHI_INVERSE), 1)
    while True:
        a, b = s, n
        while b:
            a, b = b, a % b
        if a == 1:
            return s
        s += 1


@contextlib.contextmanager
def interrupt_after():
    """Hold Ctrl-C until the block ends, then deliver it (Python's handler raises
    KeyboardInterrupt).

    For calls whose worker threads write into buffers that the calling thread owns:
    scipy's k-d tree query with ``workers`` waits for its threads in Python, so Ctrl-C
    unwound the call and freed its buffers while they still wrote, and the process died of
    a segmentation fault (one interrupted load in four, 2026-11-27). Outside the main
    thread, or where SIGINT is ignored, the block simply runs.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = []
    previous = signal.getsignal(signal.SIGINT)
    if previous in (signal.SIG_IGN, None):
        yield
        return
    signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if held:
        # the held Ctrl-C to whoever had it: Python's own handler raises KeyboardInterrupt,
        # an application's runs as it would have
        signal.raise_signal(signal.SIGINT)
