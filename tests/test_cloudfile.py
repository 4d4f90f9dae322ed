"""A point cloud on disk, in chunks (issue 50, ``prep.cloudfile``): the cloud's file written in
passes over the input, its chunks prepared from it with their halos, the same surfels as
the in-memory preparation's; an interrupted preparation resumes; LAS/LAZ files and
``dofsplat prepare --on-disk``."""

import tracemalloc

import numpy as np
import pytest

from dofsplat.errors import DofsplatError
from dofsplat.prep import chunks, cloudfile, neighbours
from dofsplat.prep import pointcloud as pc

from test_chunks import K, prepare, terrain


def blocks_of(pts, colors, size=7_000):
    """``write_cloud``'s blocks: the arrays a few thousand rows at a time."""
    return lambda: ((pts[a:a + size], colors[a:a + size]) for a in range(0, len(pts), size))


def written(folder, pts, colors, chunk_points):
    return cloudfile.write_cloud(folder, blocks_of(pts, colors), pts.min(axis=0),
                                 pts.max(axis=0), chunk_points, {"test": 1})


def matched(cloud, pts):
    """For each row of the cloud on disk, the row of the in-memory preparation's surfels
    (the input's first rows of each position, in the input's order)."""
    first, _ = pc.first_rows(pts)
    distinct = pts[first == np.arange(len(pts))]
    mine = cloud[np.arange(len(cloud))]
    a, b = np.lexsort(mine.T[::-1]), np.lexsort(distinct.T[::-1])
    assert np.array_equal(mine[a], distinct[b])  # the same points, each once
    rows = np.empty(len(mine), np.int64)
    rows[a] = b
    return rows


def with_duplicates(n, seed=0):
    """``terrain``, 500 of its points again at the end with other colours."""
    pts, colors = terrain(n, seed=seed)
    return (np.concatenate([pts, pts[:500]]),
            np.concatenate([colors, colors[:500][::-1]]).astype(np.float32))


def test_the_plan_cuts_the_cells_at_their_medians_under_the_budget():
    rng = np.random.default_rng(1)
    pts = rng.uniform(0.0, 1.0, (10_000, 3)) * (4.0, 1.0, 2.0)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    dims, cell = cloudfile.grid(lo, hi)
    assert np.prod(dims) <= cloudfile.GRID_CELLS
    assert np.all(lo + cell * (np.asarray(dims) - 1) <= hi)  # cubes that cover the box
    assert np.all(lo + cell * np.asarray(dims) > hi)
    counts = np.bincount(cloudfile.cell_ids(pts, lo, cell, dims), minlength=np.prod(dims))
    chunk, sizes = cloudfile.plan(counts.reshape(dims), 1_500)
    # 10,000 -> 5,000 -> 2,500 -> 1,250: eight chunks, each within a few cells' points of
    # its median's share
    assert len(sizes) == 8 and sizes.sum() == 10_000
    assert np.all(np.abs(sizes - 1_250) < 60)
    assert np.array_equal(np.bincount(chunk[cloudfile.cell_ids(pts, lo, cell, dims)]), sizes)
    # a part that one cell holds stays one chunk, over the budget
    chunk, sizes = cloudfile.plan(np.array([[[5_000]]]), 1_500)
    assert sizes.tolist() == [5_000] and chunk.tolist() == [0]


@pytest.mark.parametrize("n", [4_999, 5_000, 5_001, 23_456])
def test_the_median_in_passes_is_numpys(monkeypatch, n):
    """``rules.median`` of an array longer than a block counts its values by their leading
    bits and sorts the middle bucket's: np.median's value exactly, for an odd and an even
    count, values spread over decades, values in few buckets, ties, and (np.median's own
    fallback) a value <= 0."""
    from dofsplat.prep import rules

    monkeypatch.setattr(rules, "MEDIAN_BLOCK", 1_000)
    rng = np.random.default_rng(n)
    spread = rng.lognormal(0.0, 3.0, n)
    for a in (spread, np.round(rng.uniform(1.0, 1.001, n), 7), np.full(n, 0.25),
              np.concatenate([[-1.0], spread[1:]])):
        assert rules.median(a) == np.median(a)


def test_the_cloud_file_holds_each_position_once_in_chunks_in_their_boxes(tmp_path):
    pts, colors = with_duplicates(20_000)
    cloud = written(tmp_path, pts, colors, 3_000)
    assert len(cloud) == 20_000  # the 500 copies merged
    rows = matched(cloud, pts)
    merged = cloud.colours()[rows < 500]
    # a merged point's colour is the mean of its two
    first = np.flatnonzero(rows < 500)
    assert np.allclose(cloud.colours()[first],
                       0.5 * (colors[rows[first]] + colors[20_000 + rows[first]]), atol=1e-6)
    assert len(merged) == 500
    everything = cloud[np.arange(len(cloud))]
    for c, (a, b) in enumerate(cloud.bounds):
        assert 0 < b - a <= 3_000
        assert np.all(everything[a:b] >= cloud.lo[c]) and np.all(everything[a:b] <= cloud.hi[c])
    # a box's rows, read from the chunks that meet it, are the brute force's
    lo, hi = np.array([10.0, -5.0, 20.0]), np.array([25.0, 5.0, 31.0])
    inside = np.flatnonzero(np.all((everything >= lo) & (everything <= hi), axis=1))
    assert np.array_equal(cloud.rows_in_box(lo, hi), inside)
    some = np.sort(np.random.default_rng(2).choice(len(cloud), 700, replace=False))
    assert np.array_equal(cloud[some], everything[some])
    # the table reopens with its key only
    assert cloudfile.open_cloud(tmp_path, {"test": 1}).bounds == cloud.bounds
    assert cloudfile.open_cloud(tmp_path, {"test": 2}) is None


def test_the_cloud_on_disk_gives_the_whole_clouds_surfels(tmp_path, monkeypatch):
    """Each chunk with its halo, read from the neighbouring chunks' runs, gives its points
    the whole cloud's surfels bit for bit (as ``prep.chunks`` does in memory), the merged
    duplicates' mean colours included; the arrays are memory maps of the work folder. The
    passes over all points (the orientation's flips, the radii's cap and median, the
    surfels' checks) run in blocks of a few thousand here, as they do in blocks of 2^20 on
    a large cloud."""
    from dofsplat import surfels as surfels_module
    from dofsplat.prep import rules

    monkeypatch.setattr(chunks, "BLOCK", 7_000)
    monkeypatch.setattr(rules, "MEDIAN_BLOCK", 5_000)
    monkeypatch.setattr(surfels_module, "VALIDATE_ROWS", 6_000)
    pts, colors = with_duplicates(40_000)
    whole = prepare(pts, colors)
    cloud = written(tmp_path / "work", pts, colors, 6_000)
    rows = matched(cloud, pts)
    on_disk = pc.cloud_to_surfels(cloud, k=K, normalise="none", progress=False,
                                  store=tmp_path / "work")
    for name in ("positions", "normals", "radius", "weight", "colors"):
        assert np.array_equal(getattr(on_disk, name), getattr(whole, name)[rows]), name
    assert isinstance(on_disk.positions.base, np.memmap) or \
        isinstance(on_disk.positions, np.memmap)


def test_object_weights_on_disk_stay_near_the_whole_clouds(tmp_path):
    """As in memory (``test_chunks``): the normalisation reaches past the halo and its level
    is read on four chunks: the median ratio 1.000 and 99 % within 2 % on this terrain."""
    pts, colors = terrain(40_000, seed=2)
    whole = prepare(pts, colors, normalise="object")
    cloud = written(tmp_path, pts, colors, 6_000)
    on_disk = pc.cloud_to_surfels(cloud, k=K, normalise="object", progress=False,
                                  store=tmp_path)
    ratio = on_disk.weight / whole.weight[matched(cloud, pts)]
    assert abs(np.median(ratio) - 1.0) < 0.01
    assert np.quantile(np.abs(ratio - 1.0), 0.99) < 0.02


@pytest.mark.parametrize("step", ["surfel_chunk", "weight_chunk"])
def test_an_interrupted_preparation_resumes_from_the_chunks_done(tmp_path, monkeypatch, step):
    """A run stopped at its fourth chunk (of either pass) and run again in the same folder
    computes only the chunks not done, and gives the uninterrupted run's surfels."""
    pts, colors = terrain(30_000, seed=3)
    cloud = written(tmp_path / "a", pts, colors, 5_000)
    n_chunks = len(cloud.bounds)
    assert n_chunks >= 6
    options = dict(k=K, normalise="object", progress=False)
    straight = pc.cloud_to_surfels(cloud, store=tmp_path / "a", **options)
    cloud = written(tmp_path / "b", pts, colors, 5_000)
    original = getattr(chunks, step)
    calls, stop_at = [], [4]

    def stopping(*args):
        calls.append(1)
        if len(calls) == stop_at[0]:
            raise KeyboardInterrupt
        return original(*args)

    monkeypatch.setattr(chunks, step, stopping)
    with pytest.raises(KeyboardInterrupt):
        pc.cloud_to_surfels(cloud, store=tmp_path / "b", **options)
    calls.clear()
    stop_at[0] = 0
    resumed = pc.cloud_to_surfels(cloud, store=tmp_path / "b", **options)
    assert len(calls) == n_chunks - 3
    for name in ("positions", "normals", "radius", "weight", "colors"):
        assert np.array_equal(getattr(resumed, name), getattr(straight, name)), name


def test_the_disk_path_holds_chunks_not_the_clouds_arrays(tmp_path, monkeypatch):
    """numpy's peak (tracemalloc) while 40,000 and 80,000 points are prepared in chunks of
    8,000, from disk and in memory: what the 40,000 more points add. In memory it is the
    cloud's own arrays (measured: 116 bytes a point); from disk only what the orientation's
    join keeps of each chunk's halo (measured: 41; with these small chunks about half the
    points lie in a halo, 28 bytes each: at 2^20-point chunks, a few percent)."""
    monkeypatch.setattr(pc, "ROW_CHUNK", 300)
    monkeypatch.setattr(neighbours, "QUERY_CHUNK", 1000)

    def peak(run):
        tracemalloc.start()
        try:
            base = tracemalloc.get_traced_memory()[0]
            run()
            return tracemalloc.get_traced_memory()[1] - base
        finally:
            tracemalloc.stop()

    peaks = {}
    for n in (10_000, 40_000, 80_000):  # (the first compiles)
        pts, colors = terrain(n, seed=4)
        cloud = written(tmp_path / str(n), pts, colors, 8_000)
        peaks[n] = (peak(lambda: pc.cloud_to_surfels(cloud, k=K, normalise="none",
                                                     progress=False, store=tmp_path / str(n))),
                    peak(lambda: prepare(pts, colors, chunk=8_000)))
    disk, memory = ((peaks[80_000][i] - peaks[40_000][i]) / 40_000 for i in (0, 1))
    assert disk < 60, f"{disk:.0f} bytes a point from disk"
    assert memory > 90, f"{memory:.0f} bytes a point in memory"


def write_las(path, pts, colors):
    """pts (y-up) as a LAS file's z-up points far from the origin (UTM-like, so that the
    reader recentres them), millimetre scale, 16-bit colours."""
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=2, version="1.2")
    header.scales = [0.001] * 3
    header.offsets = [500_000.0, 4_000_000.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0] + 500_000.0, -pts[:, 2] + 4_000_000.0, pts[:, 1]
    las.red, las.green, las.blue = (colors * 65535).astype(np.uint16).T
    las.write(str(path))


def in_memory_and_on_disk(read, path, warning: str):
    """read(path, normalise="none") with the cloud in memory and on disk, each with its one
    warning: (in memory, on disk), checked to be the same surfels bit for bit but for their
    order (the rows sorted by position)."""
    models = []
    for mode in ("off", "on"):
        with pytest.warns(UserWarning, match=warning), cloudfile.on_disk(mode):
            models.append(read(path, normalise="none"))
    memory, disk = models
    assert len(disk) == len(memory)
    a, b = np.lexsort(memory.positions.T[::-1]), np.lexsort(disk.positions.T[::-1])
    for name in ("positions", "normals", "radius", "weight", "colors"):
        assert np.array_equal(getattr(disk, name)[b], getattr(memory, name)[a]), name
    return memory, disk


def test_a_las_file_on_disk_gives_the_in_memory_surfels(tmp_path, monkeypatch):
    """``read_las`` with the cloud on disk: the same surfels as with it in memory (recentred,
    turned y-up, its colours decoded), in the order of the chunks; the work folder goes in
    the cache folder and is removed when they are complete."""
    from dofsplat.io.las import read_las

    pts, colors = terrain(30_000, seed=7)
    write_las(tmp_path / "scan.las", pts, colors)
    monkeypatch.setenv("DOFSPLAT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(pc, "CHUNK_POINTS", 5_000)
    monkeypatch.setattr(cloudfile, "BLOCK", 7_000)  # (the decoded file read back in blocks)
    memory, disk = in_memory_and_on_disk(read_las, tmp_path / "scan.las", "shifted")
    assert list((tmp_path / "cache" / "work").iterdir()) == []


def test_the_mode_decides_by_the_memory_available(monkeypatch):
    import dofsplat.machine as machine

    monkeypatch.setattr(machine, "available_memory", lambda: 2 * 180 * 1_000_000)
    assert not cloudfile.wants_disk(1_000_000)
    assert cloudfile.wants_disk(1_000_001)
    with cloudfile.on_disk("off"):
        assert not cloudfile.wants_disk(10 ** 12)
    with cloudfile.on_disk("on"):
        assert cloudfile.wants_disk(10)
    with pytest.raises(DofsplatError, match="auto"):
        cloudfile.on_disk("always")


def test_prepare_on_disk_from_the_command_line(tmp_path, monkeypatch, capsys):
    """`dofsplat prepare --on-disk on --work-dir DIR`: a model file, the work folder gone;
    the same file as the in-memory preparation's but for the surfels' order, so the same
    model by its tree's size; a work folder that cannot be made is one line, exit 2; a
    disk too small is said before any work."""
    from dofsplat.cli import main
    from dofsplat.io import load

    pts, colors = terrain(12_000, seed=8)
    write_las(tmp_path / "scan.las", pts, colors)
    monkeypatch.setattr(pc, "CHUNK_POINTS", 4_000)
    out = tmp_path / "scan.dofsplat"
    assert main(["prepare", str(tmp_path / "scan.las"), "-o", str(out), "-q", "--no-cache",
                 "--on-disk", "on", "--work-dir", str(tmp_path / "w")]) == 0
    capsys.readouterr()
    assert list((tmp_path / "w").iterdir()) == []
    model = load(out)
    assert len(model) == 12_000
    (tmp_path / "file").write_text("x")
    code = main(["prepare", str(tmp_path / "scan.las"), "-o", str(out), "-q", "--no-cache",
                 "--on-disk", "on", "--work-dir", str(tmp_path / "file")])
    err = [line for line in capsys.readouterr().err.splitlines() if "shifted" not in line]
    assert code == 2 and len(err) == 1 and "work" in err[0], err
    import shutil
    from collections import namedtuple

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10 ** 9, 10 ** 9, 10 ** 5))
    assert main(["prepare", str(tmp_path / "scan.las"), "-o", str(out), "-q", "--no-cache",
                 "--on-disk", "on", "--work-dir", str(tmp_path / "w")]) == 2
    assert "--work-dir" in capsys.readouterr().err


def test_a_damaged_las_or_ply_file_on_disk_is_one_line(tmp_path):
    from dofsplat.io.las import read_las

    pts, colors = terrain(12_000, seed=9)
    write_las(tmp_path / "scan.las", pts, colors)
    data = (tmp_path / "scan.las").read_bytes()
    (tmp_path / "cut.las").write_bytes(data[:len(data) // 2])
    with cloudfile.on_disk("on", tmp_path / "w"), pytest.raises(DofsplatError,
                                                                   match="truncated"):
        read_las(tmp_path / "cut.las")
    assert not (tmp_path / "w").exists() or list((tmp_path / "w").iterdir()) == []
    # a binary PLY cut short: its vertices run out while the work folder is filled
    from dofsplat.io.ply import read_ply

    write_ply(tmp_path / "cloud.ply", pts, colors, np.zeros_like(pts))
    data = (tmp_path / "cloud.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:len(data) // 2])
    with cloudfile.on_disk("on", tmp_path / "w"), pytest.raises(DofsplatError,
                                                                   match="truncated PLY"):
        read_ply(tmp_path / "cut.ply")
    assert list((tmp_path / "w").iterdir()) == []


def test_prepare_on_disk_on_local_workers_writes_the_same_file(tmp_path, monkeypatch):
    """`dofsplat prepare --on-disk on --workers 2`: the chunks' steps on two worker
    processes, which read the cloud and the surfels from the work folder's files: the same
    .dofsplat file, byte for byte, as in this process."""
    pytest.importorskip("dask.distributed")
    from dofsplat.cli import main

    pts, colors = terrain(20_000, seed=10)
    write_las(tmp_path / "scan.las", pts, colors)
    monkeypatch.setattr(pc, "CHUNK_POINTS", 5_000)
    for name, extra in (("here", []), ("workers", ["--workers", "2"])):
        assert main(["prepare", str(tmp_path / "scan.las"), "-o",
                     str(tmp_path / f"{name}.dofsplat"), "-q", "--no-cache", "--on-disk", "on",
                     "--work-dir", str(tmp_path / "w"), *extra]) == 0
    assert (tmp_path / "here.dofsplat").read_bytes() == \
        (tmp_path / "workers.dofsplat").read_bytes()


def test_an_interrupted_las_preparation_resumes_and_the_cache_command_shows_it(
        tmp_path, monkeypatch, capsys):
    """A LAS file's preparation on disk stopped in its chunks leaves its work folder in the
    cache folder: `dofsplat cache` shows it, a second run resumes from it (the uninterrupted
    run's surfels) and removes it; `dofsplat cache --clear work` removes one too."""
    from dofsplat.cli import main
    from dofsplat.io.las import read_las

    pts, colors = terrain(20_000, seed=11)
    write_las(tmp_path / "scan.las", pts, colors)
    monkeypatch.setenv("DOFSPLAT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(pc, "CHUNK_POINTS", 5_000)
    work = tmp_path / "cache" / "work"
    original = chunks.surfel_chunk

    def stopping(*args):
        raise KeyboardInterrupt

    with pytest.warns(UserWarning, match="shifted"), cloudfile.on_disk("on"):
        straight = read_las(tmp_path / "scan.las")
        monkeypatch.setattr(chunks, "surfel_chunk", lambda *a: (
            stopping() if len(list(work.glob("*/surfels-*.npz"))) == 2 else original(*a)))
        with pytest.raises(KeyboardInterrupt):
            read_las(tmp_path / "scan.las")
        assert len(list(work.glob("*/surfels-*.npz"))) == 2
        assert main(["cache"]) == 0
        assert "work/" in capsys.readouterr().out
        monkeypatch.setattr(chunks, "surfel_chunk", original)
        resumed = read_las(tmp_path / "scan.las")
    for name in ("positions", "normals", "radius", "weight", "colors"):
        assert np.array_equal(getattr(resumed, name), getattr(straight, name)), name
    assert list(work.iterdir()) == []
    monkeypatch.setattr(chunks, "surfel_chunk", stopping)
    with pytest.warns(UserWarning, match="shifted"), cloudfile.on_disk("on"), \
            pytest.raises(KeyboardInterrupt):
        read_las(tmp_path / "scan.las")
    assert len(list(work.iterdir())) == 1
    assert main(["cache", "--clear", "work"]) == 0
    assert "removed 1 work folder" in capsys.readouterr().out
    assert list(work.iterdir()) == []


def test_a_damaged_kept_chunk_is_done_again_and_a_cut_cloud_file_starts_clean(tmp_path):
    """After a crash, a chunk's kept file may be empty or cut short (renamed before its data
    reached the disk): that chunk is done again, the result the same. A cloud file shorter
    than its table says is not taken (``open_cloud``), so the input is read again."""
    pts, colors = terrain(20_000, seed=12)
    cloud = written(tmp_path, pts, colors, 5_000)
    options = dict(k=K, normalise="none", progress=False, store=tmp_path)
    first = pc.cloud_to_surfels(cloud, **options)
    (tmp_path / "surfels-1.npz").write_bytes(b"PK\x03\x04 cut")
    again = pc.cloud_to_surfels(cloud, **options)
    for name in ("positions", "normals", "radius", "weight"):
        assert np.array_equal(getattr(again, name), getattr(first, name)), name
    assert cloudfile.open_cloud(tmp_path, {"test": 1}) is not None
    with open(tmp_path / cloudfile.POINTS, "r+b") as f:
        f.truncate(1000)
    assert cloudfile.open_cloud(tmp_path, {"test": 1}) is None


def write_ply(path, pts, colors, normals, text=False):
    """A point cloud PLY: x y z as doubles, nx ny nz as floats, 8-bit colours."""
    from plyfile import PlyData, PlyElement

    v = np.zeros(len(pts), [("x", "f8"), ("y", "f8"), ("z", "f8"), ("nx", "f4"), ("ny", "f4"),
                            ("nz", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v["x"], v["y"], v["z"] = pts.T
    v["nx"], v["ny"], v["nz"] = normals.T
    v["red"], v["green"], v["blue"] = (colors * 255).astype(np.uint8).T
    PlyData([PlyElement.describe(v, "vertex")], text=text).write(str(path))


def test_a_binary_ply_on_disk_gives_the_in_memory_surfels(tmp_path, monkeypatch):
    """A binary point cloud PLY is read a block at a time into the work folder: with normals
    given for some points (zeros elsewhere: estimated), a few rows of NaN (dropped, with one
    warning) and duplicates, the same surfels as in memory, the up hint too; an ASCII PLY
    stays in memory whatever the mode (it cannot be read by blocks from its file)."""
    from dofsplat.io.ply import read_ply

    pts, colors = with_duplicates(20_000, seed=13)
    normals = np.zeros_like(pts)
    normals[:4_000, 1] = 1.0
    normals[4_000:4_010] = np.nan
    write_ply(tmp_path / "cloud.ply", pts, colors, normals)
    monkeypatch.setenv("DOFSPLAT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(pc, "CHUNK_POINTS", 5_000)
    monkeypatch.setattr(cloudfile, "BLOCK", 7_000)  # (the file's vertices in blocks)
    monkeypatch.setattr(pc, "ROW_BLOCK", 6_000)  # (ground_up's pass)
    memory, disk = in_memory_and_on_disk(read_ply, tmp_path / "cloud.ply", "dropped 10 of")
    assert len(disk) == 19_990
    assert disk.up_hint == memory.up_hint
    assert list((tmp_path / "cache" / "work").iterdir()) == []
    write_ply(tmp_path / "text.ply", pts[:3_000], colors[:3_000], normals[:3_000], text=True)
    with cloudfile.on_disk("on"):
        assert len(read_ply(tmp_path / "text.ply", normalise="none")) == 3_000
    assert list((tmp_path / "cache" / "work").iterdir()) == []
