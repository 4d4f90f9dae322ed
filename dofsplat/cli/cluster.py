"""A Dask cluster for the commands that spread their work: ``animate``'s frames and
``prepare``'s chunks (``--workers N`` for a local one, ``--scheduler ADDRESS`` for an
existing one)."""

from __future__ import annotations

import os
import sys

from ..errors import DofsplatError
from .options import positive_int


def add_cluster_options(group, what: str) -> None:
    """--workers and --scheduler, for ``what`` ("render", "prepare the chunks")."""
    group.add_argument("--workers", metavar="N", type=positive_int,
                       help=f"{what} on a local Dask cluster of N processes, at most one per "
                            "core (default: in this process)")
    group.add_argument("--scheduler", metavar="ADDRESS",
                       help=f"{what} on an existing Dask cluster, e.g. tcp://host:8786")


def check_cluster_args(args, alone: str) -> None:
    """The cluster options' mistakes, before any work; alone: what happens without them."""
    if args.scheduler is not None and not args.scheduler.strip():
        raise DofsplatError("--scheduler needs the Dask scheduler's address, e.g. "
                            f"tcp://host:8786 (without it, {alone})")
    if args.workers and args.scheduler:
        raise DofsplatError("give --workers (a local cluster) or --scheduler (an existing "
                            "one), not both")
    if args.workers or args.scheduler:
        need_dask()


def need_dask() -> None:
    try:
        import dask.distributed  # noqa: F401
    except ImportError:
        raise DofsplatError("--workers and --scheduler need Dask: pip install "
                            "'dofsplat[animate]'") from None


def client_for(args):
    """(client, cluster) for --workers or --scheduler, else (None, None)."""
    if not (args.workers or args.scheduler):
        return None, None
    from dask.distributed import Client, LocalCluster

    if args.scheduler:
        try:
            return Client(args.scheduler, timeout="10s"), None
        except (OSError, TimeoutError, ValueError) as e:  # unreachable, or malformed
            raise DofsplatError(f"cannot reach the Dask scheduler at {args.scheduler}: "
                                f"{e}") from None
    cores = available_cores()
    if args.workers > cores:
        # more processes than cores only share them, each starting its own interpreter
        # and kernels (64 on 2 cores printed 127 lines of Dask's warnings)
        if not args.quiet:
            print(f"dofsplat: --workers {args.workers} is more than the {cores} core"
                  f"{'s' * (cores != 1)} here: using {cores}", file=sys.stderr)
        args.workers = cores
    threads = max(1, cores // args.workers)
    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                           dashboard_address=None,
                           env={"NUMBA_NUM_THREADS": str(threads), "TQDM_DISABLE": "1"})
    return Client(cluster), cluster


def close(client, cluster) -> None:
    """Close what ``client_for`` opened."""
    if client is not None:
        client.close()
    if cluster is not None:
        cluster.close()


def available_cores() -> int:
    """The cores this process may run on (its affinity where the system says)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)
