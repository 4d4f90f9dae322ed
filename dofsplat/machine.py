"""What this machine has now: the memory a new allocation can take without swapping. The CPU
frame's splat budget reads it (``frame.splat_rows_budget``), and so does the cache when it
decides whether a large model's first frame is drawn from its file (``io.prepared``)."""

from __future__ import annotations

import os

FALLBACK_MEMORY = 4 << 30  # what is assumed available where the system does not say


def available_memory() -> int:
    """Bytes of memory available to a new allocation without swapping: /proc/meminfo's
    MemAvailable on Linux, else the free pages sysconf reports, else FALLBACK_MEMORY."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return FALLBACK_MEMORY
