"""The cloud into chunks on disk alone (issue 50, ``prep.cloudfile``): the LAS/LAZ file decoded
into a work folder, counted, planned, distributed and its duplicates merged, timed; the folder
removed after.

    /usr/bin/time -v python bench/cloud_file.py /tmp/synth20m.laz
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path


class _Quiet:
    def update(self, m: int) -> None:
        pass


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", help="a .las or .laz file")
    parser.add_argument("--chunk-points", type=float, default=2 ** 20,
                        help="a chunk's points at most (default 2^20, as dofsplat prepares)")
    args = parser.parse_args()

    from dofsplat.io import las
    from dofsplat.prep import cloudfile

    path = Path(args.path)
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (the recentring's)
        folder = Path(tmp)
        t0 = time.perf_counter()
        blocks, lo, hi = las._decoded(path, folder, _Quiet())
        t1 = time.perf_counter()
        cloud = cloudfile.write_cloud(folder, blocks, lo, hi, int(args.chunk_points), {})
        t2 = time.perf_counter()
        n = len(cloud)
        sizes = [b - a for a, b in cloud.bounds]
    print(f"{path}: {n:,} distinct points in {len(sizes)} chunks of {min(sizes):,} to "
          f"{max(sizes):,}; decoded in {t1 - t0:.1f} s, counted, planned, distributed and "
          f"merged in {t2 - t1:.1f} s: {n / (t2 - t0):,.0f} points a second")


if __name__ == "__main__":
    main()
