"""A point cloud larger than memory prepared from a work folder (issue 50): what the LAS/LAZ
and PLY readers share once they can give the cloud's points a block at a time
(``prep.cloudfile`` writes the chunks, ``prep.pointcloud.cloud_to_surfels`` prepares them)."""

from __future__ import annotations

import sys
from pathlib import Path

from ..errors import DofsplatError
from ..surfels import Surfels


def prepare_on_disk(path: Path, n_points: int, decode, *, k: int | None = None,
                    smooth: bool = True, normalise: str = "object",
                    progress: bool = True) -> Surfels:
    """The surfels of the cloud in path (n_points, as its header says), prepared in the work
    folder of the input and the options (``cloudfile.work_folder``): Surfels whose arrays
    are memory maps of the folder's files, in the order of the chunks. decode(folder, bar):
    (blocks, lo, hi) for ``cloudfile.write_cloud``, after one pass over the input that
    advances the bar by its points (a LAS file decoded into the folder, a PLY's bounds);
    files it writes into the folder are named input.*, and removed once the chunks are
    written.

    The folder is removed once the surfels are complete (the maps keep their files), or
    when the input is at fault; a run stopped in the chunks leaves it for the next run to
    resume from, and one stopped before them leaves nothing."""
    from tqdm import tqdm

    from ..prep import cloudfile
    from ..prep.pointcloud import CHUNK_POINTS, cloud_to_surfels

    stat = path.stat()
    key = {"path": str(path.resolve()), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns,
           "chunk_points": CHUNK_POINTS, "smooth": smooth, "k": k, "normalise": normalise}
    folder = cloudfile.work_folder(key)
    try:
        cloud = cloudfile.open_cloud(folder, key)
        if cloud is None:
            cloudfile.remove(folder)  # another input's, or a run cut short before its chunks
            cloudfile.check_space(folder, n_points, str(path))
            try:  # (a run stopped here starts clean: nothing of it is kept)
                with tqdm(total=4 * n_points, desc=f"{path.name}: the cloud into chunks on "
                          "disk", unit="pt", unit_scale=True, file=sys.stderr,
                          disable=not (progress and sys.stderr.isatty()), leave=False) as bar:
                    blocks, lo, hi = decode(folder, bar)
                    cloud = cloudfile.write_cloud(folder, blocks, lo, hi, CHUNK_POINTS, key,
                                                  bar)
            except BaseException:
                cloudfile.remove(folder)
                raise
            for copy in folder.glob("input.*"):  # (decode's copy of the input, if it made one)
                copy.unlink()
        try:
            surfels = cloud_to_surfels(cloud, k=k, smooth=smooth, normalise=normalise,
                                       progress=progress, source=str(path), store=folder)
        except DofsplatError:  # the input's fault: nothing to resume
            cloudfile.remove(folder)
            raise
    except OSError as e:  # the work folder's (the input's own are DofsplatErrors)
        raise DofsplatError(f"{path}: cannot prepare it in the work folder {folder}: "
                            f"{e.strerror or e}") from e
    cloudfile.remove(folder)
    return surfels
