"""``dofsplat cache``: where prepared models and LOD hierarchies are kept; --clear empties it."""

from __future__ import annotations

from .options import EXIT_OK, HelpFormatter


def add_parser(commands) -> None:
    """The ``cache`` subcommand's options."""
    cache = commands.add_parser(
        "cache", allow_abbrev=False, formatter_class=HelpFormatter,
        help="show or clear the cache of prepared models and LOD hierarchies",
        description="Show where dofsplat keeps prepared models (point clouds and meshes "
                    "made into surfels) and LOD hierarchies, and how much room they take; "
                    "or clear it. The cache holds at most 2 GB unless DOFSPLAT_CACHE_MAX says "
                    "otherwise (e.g. 500M, 10G; 0 turns it off); the least recently used "
                    "files go first.",
        epilog="examples:\n  dofsplat cache\n  dofsplat cache --clear\n"
               "  dofsplat cache --clear lod")
    cache.add_argument("--info", action="store_true",
                       help="show the folder, the files and their size (the default)")
    cache.add_argument("--clear", nargs="?", const="all",
                       choices=("all", "surfels", "lod", "work"),
                       help="delete the cached files: all (the default), or one kind; work: "
                            "the work folders of interrupted preparations on disk")
    cache.set_defaults(run=run)


def run(args) -> int:
    """``dofsplat cache``: the cache's folder and size; --clear empties it."""
    from .. import cache

    root = cache.cache_root()
    if args.clear is not None:
        if args.clear in ("all", "work"):
            n, size = cache.clear_work()
            if n or args.clear == "work":
                print(f"removed {n:,} work folder{'s' * (n != 1)} "
                      f"({cache.format_bytes(size)}) from {root / 'work'}")
        if args.clear != "work":
            kind = None if args.clear == "all" else args.clear
            n, size = cache.clear_cache(kind)
            print(f"removed {n:,} file{'s' * (n != 1)} ({cache.format_bytes(size)}) from {root}")
        return EXIT_OK
    info = cache.cache_info()
    limit = cache.max_bytes()
    print(f"cache folder: {root}")
    for kind, what in cache.KINDS.items():
        n, size = info[kind]
        print(f"  {kind + '/':10s}{what}: {n:,} file{'s' * (n != 1)}, {cache.format_bytes(size)}")
    n, size = info["total"]
    cap = "off (DOFSPLAT_CACHE_MAX=0)" if limit == 0 else cache.format_bytes(limit)
    print(f"  total: {cache.format_bytes(size)} of at most {cap}; least recently used files "
          "go first (DOFSPLAT_CACHE_MAX sets the cap, DOFSPLAT_CACHE_DIR the folder)")
    n, size = info["work"]
    if n:
        print(f"  {'work/':10s}interrupted preparations of clouds on disk, which a run of the "
              f"same input resumes: {n:,} folder{'s' * (n != 1)}, {cache.format_bytes(size)} "
              "(outside the cap)")
    print("  'dofsplat cache --clear' empties it (or --clear surfels, --clear lod, "
          "--clear work)")
    return EXIT_OK
