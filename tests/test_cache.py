"""The disk cache (dofsplat.cache, io.prepared) and the newcomer's defaults around it
(issue 18, items 4 to 6): prepared models read back, keyed by content and options, the size
cap, ``dofsplat cache``, the summary's loading time, ``render`` without -o, the first
run's compilation notice."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from dofsplat import cache, cli
from dofsplat.io import LOADERS, load, prepared


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    """A private cache that is on (the suite's conftest turns caching off), and every model
    worth keeping (no minimum preparation time)."""
    monkeypatch.setenv("DOFSPLAT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("DOFSPLAT_CACHE_MAX", "1G")
    monkeypatch.setattr(prepared, "MIN_SECONDS", 0.0)
    return tmp_path / "cache"


def write_points(path, lift=0.0):
    """Bare points (no normals, no radii): a 40 x 40 grid, so loading prepares surfels."""
    g = np.linspace(-1, 1, 40)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    rng = np.random.default_rng(0)
    v = np.zeros(x.size, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    v["x"], v["y"], v["z"] = x, y, 0.01 * rng.standard_normal(x.size) + lift
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))
    return path


@pytest.fixture
def points_ply(tmp_path):
    return write_points(tmp_path / "grid points.ply")


@pytest.fixture
def counted_loader(monkeypatch):
    """The PLY loader, counting its calls (a cache hit does not call it)."""
    calls = []
    real = LOADERS[".ply"]

    def loader(path, **options):
        calls.append(options)
        return real(path, **options)

    loader.__wrapped__ = real  # the same signature for load()'s option check
    monkeypatch.setitem(LOADERS, ".ply", loader)
    return calls


def test_a_prepared_model_comes_back_from_the_cache(cache_dir, points_ply, counted_loader):
    first = load(points_ply)
    assert not first.load_info["from_cache"] and len(counted_loader) == 1
    again = load(points_ply)
    assert again.load_info["from_cache"] and len(counted_loader) == 1  # not prepared again
    for name in ("positions", "normals", "radius", "colors", "opacity", "weight"):
        a, b = getattr(first, name), getattr(again, name)
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_array_equal(a, b)
    assert again.material == first.material
    # other options, other content, or the cache off: prepared again
    load(points_ply, k=12)
    assert len(counted_loader) == 2
    load(points_ply, cache="off")
    assert len(counted_loader) == 3
    write_points(points_ply, lift=0.001)  # the same name, other content
    assert not load(points_ply).load_info["from_cache"] and len(counted_loader) == 4
    assert cache.cache_info()["surfels"][0] == 3  # default, k=12, the changed file


def test_a_damaged_cache_file_is_prepared_again(cache_dir, points_ply, counted_loader):
    load(points_ply)
    (entry,) = cache.cached_files("surfels")
    entry.write_bytes(b"not an npz")
    assert not load(points_ply).load_info["from_cache"] and len(counted_loader) == 2
    assert load(points_ply).load_info["from_cache"]  # replaced by a good one


@pytest.fixture
def stored_from(monkeypatch):
    """Models of 100 surfels or more kept as .dofsplat files (io.prepared.STORED_FROM)."""
    monkeypatch.setattr(prepared, "STORED_FROM", 100)


@pytest.mark.parametrize("memory", ["short", "plenty"])
def test_a_large_model_is_kept_as_a_model_file(cache_dir, points_ply, counted_loader,
                                               stored_from, monkeypatch, memory):
    """From STORED_FROM surfels on, a prepared model is kept as a .dofsplat file with its
    tree (``io.prepared.keep_stored``): a later load opens it without reading it. The first
    load returns the file's memory maps where memory is short against the model, else the
    model in memory with the tree kept on it (not built again); all draw the image of the
    model prepared in memory, bit for bit, LOD on and off."""
    import dofsplat as ds
    from dofsplat import machine
    from dofsplat.lod import cache as lod_cache, hierarchy_for
    from conftest import front_camera

    monkeypatch.setattr(machine, "available_memory", lambda: 10_000 if memory == "short" else 1e12)
    first = load(points_ply)
    assert isinstance(first.positions, np.memmap) == (memory == "short")
    assert not first.load_info["from_cache"]
    assert first.load_info["cache_file"].endswith(".dofsplat")
    if memory == "plenty":
        tree = first._lod_hierarchy
        monkeypatch.setattr(lod_cache, "build_hierarchy", None)  # (not called)
        assert lod_cache.cached_hierarchy(first) is tree
    assert [p.suffix for p in cache.cached_files()] == [".dofsplat"]
    again = load(points_ply)
    assert again.load_info["from_cache"] and len(counted_loader) == 1
    assert isinstance(again.positions, np.memmap)
    whole = load(points_ply, cache="off")
    camera = front_camera(64, 48, distance=3.0)
    lens = ds.ThinLens(focus_distance=2.5, aperture=0.3)
    for settings in (ds.RenderSettings(), ds.RenderSettings(lod=False)):
        a = ds.render(whole, camera, lens, settings, hierarchy=hierarchy_for(whole))
        b = ds.render(again, camera, lens, settings)
        assert a.stats["splats_rendered"] > 100
        if settings.lod:
            np.testing.assert_array_equal(a.image, b.image)
        else:  # (the surfels in another order: the A-buffer's merges to float rounding)
            assert np.abs(a.image - b.image).max() < 1e-6


def test_a_model_file_in_the_cache_pickles_with_its_arrays(cache_dir, points_ply, stored_from,
                                                           monkeypatch):
    """A model the cache keeps as a .dofsplat file lies in this machine's cache folder, which
    a Dask worker on another machine (``animate --scheduler``) does not have: it pickles with
    its arrays and its tree, and arrives as a model in memory, the same content, which
    renders without the file."""
    import pickle

    import dofsplat as ds
    from dofsplat import machine
    from dofsplat.fingerprint import content_hash
    from conftest import front_camera

    monkeypatch.setattr(machine, "available_memory", lambda: 10_000)
    model = load(points_ply)
    assert isinstance(model.positions, np.memmap)
    data = pickle.dumps(model)
    assert len(data) > model.positions.nbytes
    (entry,) = cache.cached_files("surfels")
    entry.unlink()  # (another machine)
    again = pickle.loads(data)
    assert type(again) is ds.Surfels and not hasattr(again, "model_file")
    assert content_hash(again) == content_hash(model, cached=True)  # (the header's, of its arrays)
    camera = front_camera(48, 36, distance=3.0)
    np.testing.assert_array_equal(ds.render(again, camera).image, ds.render(model, camera).image)


def test_a_damaged_model_file_is_prepared_again(cache_dir, points_ply, counted_loader,
                                                stored_from):
    load(points_ply)
    (entry,) = cache.cached_files("surfels")
    entry.write_bytes(entry.read_bytes()[:5000])  # cut short
    assert not load(points_ply).load_info["from_cache"] and len(counted_loader) == 2
    assert load(points_ply).load_info["from_cache"]  # replaced by a good one


def test_a_model_larger_than_the_cap_keeps_its_tree(cache_dir, points_ply, monkeypatch,
                                                    stored_from):
    """A model too large for the cache is returned in memory, with the tree built for the
    file attached: the render does not build it again (``lod.cache.cached_hierarchy``)."""
    from dofsplat.lod import cache as lod_cache

    monkeypatch.setenv("DOFSPLAT_CACHE_MAX", "1000")
    with pytest.warns(UserWarning, match=r"larger than the cache \(1000 B\): it is prepared "
                      r"again next time; `dofsplat prepare .*grid points.ply` keeps it"):
        model = load(points_ply)
    assert not isinstance(model.positions, np.memmap) and cache.cached_files() == []
    built = []
    monkeypatch.setattr(lod_cache, "build_hierarchy", lambda *a, **k: built.append(1))
    assert lod_cache.cached_hierarchy(model) is model._lod_hierarchy and built == []


def test_prepare_from_a_model_file_in_the_cache(cache_dir, points_ply, stored_from, tmp_path,
                                                capsys):
    """``dofsplat prepare`` of a model the cache holds as a .dofsplat file writes the file
    that it writes from the model prepared afresh (``--no-cache``), byte for byte."""
    load(points_ply)
    assert cli.main(["prepare", str(points_ply), "-o", str(tmp_path / "a.dofsplat"), "-q"]) == 0
    assert cli.main(["prepare", str(points_ply), "-o", str(tmp_path / "b.dofsplat"), "-q",
                     "--no-cache"]) == 0
    assert (tmp_path / "a.dofsplat").read_bytes() == (tmp_path / "b.dofsplat").read_bytes()


def test_the_cap_evicts_the_least_recently_used_first(cache_dir):
    files = []
    for i, kind in enumerate(["surfels", "lod", "surfels", "lod"]):
        folder = cache.cache_folder(kind)
        folder.mkdir(parents=True, exist_ok=True)
        p = folder / f"{i}.npz"
        p.write_bytes(b"x" * 1000)
        os.utime(p, (1000 + i, 1000 + i))  # file 0 is the oldest
        files.append(p)
    cache.touch(files[0])  # just used: now the newest
    gone = cache.enforce_cap(limit=2500, keep=files[3])
    assert gone == [files[1], files[2]]
    assert files[0].exists() and files[3].exists()
    assert cache.cache_info()["total"] == (2, 2000)
    assert cache.parse_size("1.5k") == 1536 and cache.parse_size("2G") == 2 << 30


def test_the_cap_of_zero_turns_the_cache_off(cache_dir, points_ply, counted_loader,
                                              monkeypatch):
    monkeypatch.setenv("DOFSPLAT_CACHE_MAX", "0")
    load(points_ply)
    load(points_ply)
    assert len(counted_loader) == 2 and cache.cached_files() == []


def test_cli_cache_info_and_clear(cache_dir, points_ply, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = ["render", str(points_ply), "--size", "64x48"]
    assert cli.main(argv) == 0
    err = capsys.readouterr().err
    # render without -o writes the model's name with .png, here; the summary says how long
    # the model took to load
    assert (tmp_path / "grid points.png").exists()
    assert re.search(r"model loaded in \d+\.\d\d s\)$", err.strip())
    assert cli.main(argv + ["-o", "again.png"]) == 0
    assert re.search(r"model from the cache in \d+\.\d\d s\)$", capsys.readouterr().err.strip())
    assert cli.main(["cache"]) == 0
    out = capsys.readouterr().out
    assert str(cache_dir) in out and re.search(r"surfels/ +prepared models: 1 file, ", out)
    assert re.search(r"lod/ +LOD hierarchies: 1 file, ", out)
    assert cli.main(["cache", "--clear", "lod"]) == 0
    assert "removed 1 file" in capsys.readouterr().out
    assert cli.main(["cache", "--clear"]) == 0
    assert cache.cached_files() == []
    monkeypatch.setenv("DOFSPLAT_CACHE_MAX", "lots")
    assert cli.main(argv) == 2
    assert "DOFSPLAT_CACHE_MAX: expected a size" in capsys.readouterr().err


def test_default_output_names():
    assert cli.default_output("scans/lion.laz") == "lion.png"
    assert cli.default_output("dragon_vrip.ply.gz") == "dragon_vrip.png"
    assert cli.default_output("/a/b/Model.OBJ") == "Model.png"


def test_reference_help_names_both_default_sizes(capsys):
    assert cli.main(["reference", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: 512x512; with --demo: 800x600)" in text


def test_the_first_run_says_that_it_compiles(tmp_path, monkeypatch, capsys):
    from dofsplat.backends import cpu

    assert cpu.kernels_compiled()  # this session's kernels are in numba's cache
    monkeypatch.setattr(cpu, "kernels_compiled", lambda: False)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["demo", "--size", "48x36", "-o", "d.png"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith(f"dofsplat: compiling the rendering kernels, once (about "
                             f"{cpu.COMPILE_SECONDS} s")
    assert cli.main(["demo", "--size", "48x36", "-o", "d.png", "-q"]) == 0
    assert capsys.readouterr().err == ""


def test_the_rasteriser_compiled_apart_has_the_frame_types():
    """``compile_rasteriser`` (a first run's second process) builds its inputs itself: they
    must have the types and layouts that a frame's projection gives, or the frame would
    compile every rasteriser kernel again. This session's frames compiled them (conftest's
    warm_up): no kernel gains a signature."""
    from dofsplat.backends import cpu
    from dofsplat.raster import abuffer

    kernels = (abuffer.rasterize_band, abuffer.bin_splats, abuffer.front_band,
               abuffer.apply_visibility, abuffer.tile_rows_pairs, abuffer.widen_boxes)
    before = [list(k.signatures) for k in kernels]
    assert all(len(s) == 1 for s in before)
    cpu.compile_rasteriser()
    assert [list(k.signatures) for k in kernels] == before


def test_a_first_run_compiles_the_rasteriser_beside_the_rest(monkeypatch):
    """warm_up on a first run: the second process starts before this one compiles the cut
    and the projection, and is waited for before the frame that needs its kernels."""
    from dofsplat.backends import cpu

    events = []

    class Helper:
        def wait(self):
            events.append("wait")

    monkeypatch.setattr(cpu, "_WARM", False)
    monkeypatch.setattr(cpu, "kernels_compiled", lambda: False)
    monkeypatch.setattr(cpu, "_start_rasteriser_compile",
                        lambda: events.append("start") or Helper())
    project = cpu.project
    monkeypatch.setattr(cpu, "project", lambda *a, **k: events.append("project") or project(*a, **k))
    rasterize = cpu.rasterize
    monkeypatch.setattr(cpu, "rasterize",
                        lambda *a, **k: events.append("rasterize") or rasterize(*a, **k))
    cpu.warm_up()
    assert events[:4] == ["start", "project", "wait", "project"] and "rasterize" in events[4:]


def test_a_mesh_key_follows_the_files_it_names_only(tmp_path):
    """A mesh's key covers its material library and the textures that names (a subfolder
    too), not other files beside it: render's default MODEL.png output changes nothing."""
    (tmp_path / "tex").mkdir()
    (tmp_path / "m.obj").write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "m.mtl").write_text("newmtl a\nmap_Kd tex/wood.png\n")
    (tmp_path / "tex" / "wood.png").write_bytes(b"wood")
    (tmp_path / "other.png").write_bytes(b"other")
    used = prepared.referenced_files(tmp_path / "m.obj")
    assert [p.relative_to(tmp_path).as_posix() for p in used] == ["m.mtl", "tex/wood.png"]
    loader = LOADERS[".obj"]
    key = prepared.cache_key(tmp_path / "m.obj", loader, {})
    (tmp_path / "m.png").write_bytes(b"a render of m.obj")
    assert prepared.cache_key(tmp_path / "m.obj", loader, {}) == key
    (tmp_path / "tex" / "wood.png").write_bytes(b"new wood!")
    assert prepared.cache_key(tmp_path / "m.obj", loader, {}) != key


@pytest.mark.parametrize("damage", ["garbage", "cut"])
def test_a_damaged_lod_cache_entry_is_rebuilt(cache_dir, damage):
    """A cache entry that is not a tree, or a real one cut short (a BadZipFile, which
    every render of the model met as a traceback until 2026-11-27), is built again."""
    from dofsplat.lod.cache import cache_folder, cached_hierarchy
    from dofsplat.lod.hierarchy import fingerprint

    from conftest import grid_surfels

    s = grid_surfels(8)
    path = cache_folder() / f"{fingerprint(s)}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    if damage == "garbage":
        path.write_bytes(b"not a tree")
    else:
        cached_hierarchy(s, "auto")
        path.write_bytes(path.read_bytes()[:2000])
    s = grid_surfels(8)  # (a fresh object: the tree is not kept on it yet)
    tree = cached_hierarchy(s, "auto")  # no error: rebuilt, and kept again
    assert len(tree) == 2 * len(s) - 1 and path.stat().st_size > 2000


def test_a_cached_tree_of_another_layout_is_rebuilt(cache_dir, monkeypatch):
    """A tree kept before ``COMPACT_FROM`` moved (its ``small`` not today's for the model's
    size) draws the same frames at another memory: the cache builds today's instead."""
    from dofsplat.lod import hierarchy
    from dofsplat.lod.cache import cached_hierarchy

    from conftest import grid_surfels

    s = grid_surfels(8)
    assert cached_hierarchy(s, "auto").small == 1
    monkeypatch.setattr(hierarchy, "COMPACT_FROM", 16)  # today's default: compact
    logged = []
    tree = cached_hierarchy(grid_surfels(8), "auto", log=logged.append)
    assert tree.small == hierarchy.SMALL_NODE and len(logged) == 1
    assert cached_hierarchy(grid_surfels(8), "auto").small == hierarchy.SMALL_NODE


def lod_models(n_models):
    """Models of as many surfels, each its own fingerprint (their trees are the same size)."""
    from conftest import grid_surfels

    return [grid_surfels(16, z=0.1 * i) for i in range(n_models)]


def test_lod_trees_past_the_cap_evict_the_least_recently_used(cache_dir, monkeypatch):
    """In real use (``lod.cache.cached_hierarchy``): with room for two trees, a third evicts
    the least recently used; a hit renews a tree's age, so the older-but-used one stays."""
    from dofsplat.lod.cache import cache_folder, cached_hierarchy
    from dofsplat.lod.hierarchy import fingerprint

    models = lod_models(3)
    paths = [cache_folder() / f"{fingerprint(m)}.npz" for m in models]
    for age, (model, path) in enumerate(zip(models[:2], paths)):
        cached_hierarchy(model, "auto")
        os.utime(path, (1000 + age, 1000 + age))  # tree 0 the older
    size = max(p.stat().st_size for p in paths[:2])
    monkeypatch.setenv("DOFSPLAT_CACHE_MAX", str(int(2.5 * size)))
    logged = []
    again = lod_models(1)[0]  # model 0 again, a fresh object: read from the cache
    cached_hierarchy(again, "auto", log=logged.append)
    assert logged == []  # a hit: nothing built
    assert paths[0].stat().st_mtime > 1001  # and its age renewed
    cached_hierarchy(models[2], "auto")
    assert paths[0].exists() and not paths[1].exists() and paths[2].exists()
    assert cache.cache_info()["lod"][0] == 2


def test_a_tree_larger_than_the_cap_is_not_kept(cache_dir, monkeypatch):
    from dofsplat.lod.cache import cache_folder, cached_hierarchy
    from dofsplat.lod.hierarchy import fingerprint

    first, second = lod_models(2)
    cached_hierarchy(first, "auto")
    size = (cache_folder() / f"{fingerprint(first)}.npz").stat().st_size
    monkeypatch.setenv("DOFSPLAT_CACHE_MAX", str(size // 2))
    logged = []
    tree = cached_hierarchy(second, "auto", log=logged.append)
    assert len(tree) == 2 * len(second) - 1  # built and used
    assert logged and logged[0].endswith(", larger than the cache")
    assert not (cache_folder() / f"{fingerprint(second)}.npz").exists()
    assert cache.cached_files() == []  # (the older tree went first, then this one)


def unwritable_cache(tmp_path, monkeypatch):
    """A cache whose folders cannot be made: a file stands where each would be
    (permissions do not stop the tests' root). (A cache folder that lies under a file is
    refused at once, with a message: ``cache.cache_root``'s callers.)"""
    root = tmp_path / "cache"
    root.mkdir()
    for kind in cache.KINDS:
        (root / kind).write_text("a file, not a folder")
    monkeypatch.setenv("DOFSPLAT_CACHE_DIR", str(root))
    monkeypatch.setenv("DOFSPLAT_CACHE_MAX", "1G")
    monkeypatch.setattr(prepared, "MIN_SECONDS", 0.0)


def test_an_unwritable_cache_costs_a_preparation_not_an_error(tmp_path, monkeypatch,
                                                             points_ply, counted_loader):
    """A model is prepared each time, without an error (io.prepared)."""
    unwritable_cache(tmp_path, monkeypatch)
    load(points_ply)
    assert not load(points_ply).load_info["from_cache"] and len(counted_loader) == 2


def test_an_unwritable_cache_costs_a_tree_rebuild_not_an_error(tmp_path, monkeypatch):
    """A tree is built and used, with a line saying why it was not kept."""
    from dofsplat.lod.cache import cached_hierarchy

    unwritable_cache(tmp_path, monkeypatch)
    logged = []
    (model,) = lod_models(1)
    tree = cached_hierarchy(model, "auto", log=logged.append)
    assert len(tree) == 2 * len(model) - 1
    assert len(logged) == 1 and "could not keep it in" in logged[0]
