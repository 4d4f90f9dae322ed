"""The prepared model on disk (``.dofsplat``, ``io.model_file``; issue 50): the file renders
the image the model in memory renders, opens without reading its arrays, and a file that is
cut short, damaged or half-written is one error line, never trusted."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import front_camera, grid_surfels

import dofsplat as ds
from dofsplat import cli
from dofsplat.errors import DofsplatError
from dofsplat.io import load, save_surfels
from dofsplat.io import model_file
from dofsplat.lod import build_hierarchy, hierarchy_for
from dofsplat.surfels import VIEW_SAMPLE


def bumpy_model(n=40, seed=2):
    """An n x n grid of disks on a bumpy, coloured surface (a tree with real merges), with
    weights, in a shuffled order (so that the leaf order differs from the model's)."""
    rng = np.random.default_rng(seed)
    s = grid_surfels(n=n, spacing=1.0 / n)
    z = 0.05 * np.sin(7 * s.positions[:, 0]) * np.cos(5 * s.positions[:, 1])
    pos = s.positions + np.c_[np.zeros((len(s), 2)), z]
    pick = rng.permutation(len(s))
    return ds.Surfels(positions=pos[pick], normals=s.normals[pick], radius=s.radius[pick],
                      colors=rng.uniform(0.1, 0.9, (len(s), 3))[pick],
                      opacity=rng.uniform(0.7, 1.0, len(s)), weight=rng.uniform(0.8, 1.2, len(s)))


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """(the model in memory, its tree, the path of its .dofsplat file)."""
    model = bumpy_model()
    tree = build_hierarchy(model)
    path = tmp_path_factory.mktemp("model") / "bumpy.dofsplat"
    model_file.write_model_file(path, model, tree, source={"path": "bumpy"})
    return model, tree, path


@pytest.mark.parametrize("aperture", [0.0, 0.08], ids=["pinhole", "blurred"])
def test_the_file_renders_the_models_image(stored, aperture):
    """The same frame from the file (its surfels in the tree's leaf order, memory-mapped)
    and from the model in memory: equal bit for bit, LOD on (the cut walks the same tree,
    gathers the same surfels, in the same order) and off (the surfels drawn in another
    order: the A-buffer's merges are order-free to float rounding, 1e-6)."""
    model, tree, path = stored
    opened = load(path)
    assert isinstance(opened.positions, np.memmap) and len(opened) == len(model)
    camera = front_camera(96, 72, distance=1.6)
    lens = ds.ThinLens(focus_distance=1.4, aperture=aperture) if aperture else None
    a = ds.render(model, camera, lens, ds.RenderSettings(), hierarchy=tree)
    b = ds.render(opened, camera, lens, ds.RenderSettings())
    assert a.stats["splats_rendered"] > 500
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.depth, b.depth)
    c = ds.render(model, camera, lens, ds.RenderSettings(lod=False))
    d = ds.render(opened, camera, lens, ds.RenderSettings(lod=False))
    assert np.abs(c.image - d.image).max() < 1e-6


def test_opening_reads_no_array(stored, monkeypatch):
    """Opening a file and asking what a render asks first (its tree, its fingerprint, its
    bounds, the default camera's sample, the pinhole walk's bound) computes nothing over
    its arrays: each answer is the file's own (a file larger than memory would otherwise be
    read whole before the first frame)."""
    import dofsplat.fingerprint as fp
    import dofsplat.lod as lod
    from dofsplat.lod import min_leaf_geo

    model, tree, path = stored
    opened = load(path)

    def no_pass(*args, **kwargs):
        raise AssertionError("a pass over the model's arrays")

    monkeypatch.setattr(fp.hashlib, "blake2b", no_pass)
    monkeypatch.setattr(lod, "subtree_min_geo", no_pass, raising=False)
    monkeypatch.setattr("dofsplat.lod.select.subtree_min_geo", no_pass)
    kept = hierarchy_for(opened)
    assert kept is opened._lod_hierarchy and kept.leaf_ordered
    np.testing.assert_array_equal(opened.bounds()[0], model.bounds()[0])
    np.testing.assert_array_equal(opened.view_bounds()[1], model.view_bounds()[1])
    sample = opened.sample(VIEW_SAMPLE)
    np.testing.assert_array_equal(sample.positions, model.sample(VIEW_SAMPLE).positions)
    geo = min_leaf_geo(kept, opened, kept.small)
    assert geo.shape[0] == len(tree.center)


def test_the_cli_prepares_and_renders_it(tmp_path, monkeypatch, capsys):
    """``dofsplat prepare MODEL.ply`` writes MODEL.dofsplat beside it, and ``render`` of it
    writes the image ``render`` of the PLY writes (its default camera and focus too: the
    file keeps the model's bounds and the default camera's sample); ``reference`` of it
    too, to a level of 8 bits (every surfel drawn, in the file's order rather than the
    PLY's: the A-buffer's merges are order-free to float rounding). The file's arrays are
    read-only memory maps, which the reference's shading once tried to write through."""
    from PIL import Image

    monkeypatch.chdir(tmp_path)
    save_surfels(tmp_path / "bumpy.ply", bumpy_model())
    assert cli.main(["prepare", "bumpy.ply", "-q"]) == 0
    assert (tmp_path / "bumpy.dofsplat").is_file()
    for command, extra, tolerance in (("render", [], 0), ("reference", ["--samples", "4"], 1)):
        for name in ("bumpy.ply", "bumpy.dofsplat"):
            assert cli.main([command, name, "-o", f"{command}.{name}.png", "--size", "80x60",
                             "--aperture", "0.1", "-q", *extra]) == 0
        a, b = (np.asarray(Image.open(tmp_path / f"{command}.bumpy.{ext}.png"), np.int16)
                for ext in ("ply", "dofsplat"))
        assert np.abs(a - b).max() <= tolerance, command
    capsys.readouterr()


@pytest.mark.parametrize("argv, says", [
    (["prepare", "{ply}", "-o", "out.ply"], "ending in .dofsplat"),
    (["prepare", "{gauss}"], "Gaussian scene"),
    (["prepare", "missing.ply"], "no such file"),
])
def test_prepare_mistakes_are_one_line(tmp_path, monkeypatch, capsys, argv, says):
    from conftest import gaussian_ply_columns
    from plyfile import PlyData, PlyElement

    monkeypatch.chdir(tmp_path)
    save_surfels(tmp_path / "m.ply", grid_surfels(n=4))
    rng = np.random.default_rng(0)
    cols = gaussian_ply_columns(rng.normal(size=(3, 3)), np.full((3, 3), -3.0),
                                np.tile([1.0, 0, 0, 0], (3, 1)), np.zeros(3), np.zeros((3, 1, 3)))
    PlyData([PlyElement.describe(np.rec.fromarrays(list(cols.values()), names=list(cols)),
                                 "vertex")]).write(str(tmp_path / "g.ply"))
    status = cli.main([a.format(ply="m.ply", gauss="g.ply") for a in argv])
    err = capsys.readouterr().err
    assert status == 2 and len(err.splitlines()) == 1 and says in err, err
    assert not list(tmp_path.glob("*.dofsplat"))


def _damaged(path, tmp_path, how):
    data = bytearray(path.read_bytes())
    out = tmp_path / f"{how}.dofsplat"
    if how == "cut":  # an interrupted copy
        data = data[:len(data) // 2]
    elif how == "no trailer":  # a write stopped before its completion mark
        data = data[:-model_file.TRAILER]
    elif how == "header":  # one byte of the header changed
        data[20] ^= 0x20
    elif how == "magic":
        data[:8] = b"NOTMODEL"
    elif how == "version":
        data[8] = 99
    elif how == "empty":
        data = b""
    out.write_bytes(bytes(data))
    return out


@pytest.mark.parametrize("how", ["cut", "no trailer", "header", "magic", "version", "empty"])
def test_a_damaged_file_is_one_error_line(stored, tmp_path, capsys, how):
    """A file cut short, without its completion mark, with a changed header, of another
    format or version, or empty: DofsplatError from load, exit status 2 and one line from
    the command line, no image written."""
    _, _, path = stored
    bad = _damaged(path, tmp_path, how)
    with pytest.raises(DofsplatError, match="dofsplat model file"):
        load(bad)
    status = cli.main(["render", str(bad), "-o", str(tmp_path / "x.png"), "-q"])
    err = capsys.readouterr().err
    assert status == 2 and len(err.splitlines()) == 1 and err.startswith("dofsplat: error: ")
    assert not (tmp_path / "x.png").exists()


def test_an_interrupted_write_leaves_nothing(stored, tmp_path, monkeypatch):
    """A write that stops part way (here: the disk fills after the first array) leaves no
    file at the destination and no temporary file beside it; an older complete file there
    is kept as it was."""
    model, tree, path = stored
    target = tmp_path / "m.dofsplat"
    calls = []

    def failing(a, index=None):
        dtype, shape, pieces = original(a, index)

        def some():
            calls.append(1)
            if len(calls) > 1:
                raise OSError(28, "No space left on device")
            yield from pieces()

        return dtype, shape, some

    original = model_file._gathered
    monkeypatch.setattr(model_file, "_gathered", failing)
    with pytest.raises(DofsplatError, match="No space left"):
        model_file.write_model_file(target, model, tree)
    assert list(tmp_path.iterdir()) == []
    target.write_bytes(path.read_bytes())
    calls.clear()
    with pytest.raises(DofsplatError):
        model_file.write_model_file(target, model, tree)
    assert target.read_bytes() == path.read_bytes()
    assert len(load(target)) == len(model)


def test_the_arrays_are_written_a_piece_at_a_time(stored, tmp_path, monkeypatch):
    """The writer moves each array into the file's order a piece of ROWS rows at a time and
    hashes the pieces (``fingerprint.HashStream``): in pieces of 100 rows the file is the
    same byte for byte, its header's hashes are those of its own arrays read back (the
    content hash over every field, None ones between them, and the tree's fingerprint), and
    the tree's rows are the blocked layout's (``Hierarchy.blocked``)."""
    from dofsplat.fingerprint import content_hash
    from dofsplat.lod.hierarchy import ATTRIBUTES, fingerprint

    model, tree, path = stored
    monkeypatch.setattr(model_file, "ROWS", 100)
    again = tmp_path / "pieces.dofsplat"
    model_file.write_model_file(again, model, tree, source={"path": "bumpy"})
    assert again.read_bytes() == path.read_bytes()
    header = model_file.read_header(again)
    opened = load(again)
    fresh = ds.Surfels.stored(material=opened.material, **{
        name: None if getattr(opened, name) is None else np.array(getattr(opened, name))
        for name in model_file.SURFEL_ARRAYS})
    assert fresh.tangent is None and fresh.weight is not None
    assert header["content_hash"] == content_hash(fresh)
    assert header["tree"]["fingerprint"] == fingerprint(fresh)
    blocked, _ = tree.blocked(model_file.BLOCK_LEVELS)
    mine = hierarchy_for(opened)
    for name in ATTRIBUTES + ("child",):
        np.testing.assert_array_equal(np.asarray(getattr(mine, name)), getattr(blocked, name))


def test_rows_read_through_the_file(stored, tmp_path):
    """``read_rows`` reads a stored array's rows through the file, not its memory map (a
    pass over every row maps none of them): the rows of the map, at any bounds; an array in
    memory gives its own rows; a file cut short since it was opened is one error line."""
    model, _, path = stored
    opened = load(path)
    for a in (opened.positions, opened.radius, model.positions):
        for lo, hi in ((0, 7), (5, 1000), (1590, 5000), (2000, 3000), (0, len(a))):
            got = model_file.read_rows(a, lo, hi)
            np.testing.assert_array_equal(got, np.asarray(a[lo:hi]))
            assert got.dtype == a.dtype and not isinstance(got, np.memmap)  # (read, not mapped)
    copy = tmp_path / "copy.dofsplat"
    copy.write_bytes(path.read_bytes())
    weights = load(copy).weight  # the last surfel array in the file
    with open(copy, "r+b") as f:
        f.truncate(weights.offset + 100)
    with pytest.raises(DofsplatError, match="cut short"):
        model_file.read_rows(weights, 0, len(weights))


def test_a_tree_of_another_model_is_refused(stored, tmp_path):
    model, _, _ = stored
    other = build_hierarchy(bumpy_model(seed=5))
    with pytest.raises(DofsplatError, match="not built for these surfels"):
        model_file.write_model_file(tmp_path / "x.dofsplat", model, other)


def test_a_stored_model_pickles_as_its_path(stored):
    """Sent to a Dask worker (``animate --scheduler``), a model opened from a file is its
    path, not its arrays (under a kilobyte here, where the arrays are 150 kB), and the
    worker's copy is the same model, memory-mapped (its content hash, which a sequence's
    manifest records, the same)."""
    import pickle

    from dofsplat.fingerprint import content_hash

    _, _, path = stored
    opened = load(path)
    data = pickle.dumps(opened)
    assert len(data) < 1000
    again = pickle.loads(data)
    assert isinstance(again.positions, np.memmap) and again.model_file == opened.model_file
    assert content_hash(again, cached=True) == content_hash(opened, cached=True)
