"""The CUDA backend against the CPU backend, the device choice, and ``--device`` on the CLI.

The parity tests run on a GPU where one works, or on numba's CUDA simulator with
``DOFSPLAT_TEST_CUDASIM=1`` (every CUDA thread is a Python thread there: the scenes are
tiny), and are skipped otherwise; ``DOFSPLAT_REQUIRE_CUDA=1`` turns that skip into an error
(for the GPU machine). They are marked ``cuda``: `pytest --cudasim` (the README's test command, CI) runs a selection of them
on the simulator, which must launch every kernel of backends/cuda.py (the last parity test
checks). The device-choice and CLI tests run everywhere.
"""

import ast
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numba
import numpy as np
import pytest

if os.environ.get("DOFSPLAT_TEST_CUDASIM") == "1" and "numba.cuda" not in sys.modules:
    os.environ["NUMBA_ENABLE_CUDASIM"] = "1"  # before numba.cuda is first imported
    numba.config.reload_config()

import dofsplat as ds  # noqa: E402
from dofsplat import backends  # noqa: E402
from dofsplat.cli import main  # noqa: E402
from dofsplat.errors import DofsplatError  # noqa: E402

from conftest import front_camera, grid_surfels  # noqa: E402

_PROBLEM = backends.cuda_problem()
SIMULATOR = _PROBLEM is None and bool(numba.config.ENABLE_CUDASIM)
GPU = _PROBLEM is None and not SIMULATOR
if _PROBLEM is not None and os.environ.get("DOFSPLAT_REQUIRE_CUDA") == "1":
    # on the GPU machine a broken setup must fail, not skip
    raise RuntimeError(f"DOFSPLAT_REQUIRE_CUDA=1 but the CUDA backend cannot run: {_PROBLEM}")
_skip_without_cuda = pytest.mark.skipif(
    _PROBLEM is not None,
    reason=f"no CUDA GPU here ({_PROBLEM}); DOFSPLAT_TEST_CUDASIM=1 runs these tests on "
           "numba's CUDA simulator")


def needs_cuda(test):
    """Skipped without a GPU or the simulator; marked ``cuda``, which `pytest --cudasim`'s simulator
    step selects and tests/skip_guard.py counts apart."""
    return pytest.mark.cuda(_skip_without_cuda(test))


# -- which kernels the tests launch ---------------------------------------------------------

LAUNCHED: set[str] = set()  # names of backends/cuda.py's kernels launched in this module


def _kernel_names(module) -> list[str]:
    """The kernels of a module: its functions decorated with a bare ``@cuda.jit`` (device
    functions take ``@cuda.jit(device=True)``)."""
    tree = ast.parse(Path(module.__file__).read_text(encoding="utf-8"))
    return [f.name for f in tree.body if isinstance(f, ast.FunctionDef)
            and any(ast.unparse(d) == "cuda.jit" for d in f.decorator_list)]


class _Noted:
    """A kernel that notes its name in LAUNCHED when launched (``kernel[grid, block](...)``)."""

    def __init__(self, name, kernel):
        self.name, self.kernel = name, kernel

    def __getitem__(self, launch_config):
        LAUNCHED.add(self.name)
        return self.kernel[launch_config]


@pytest.fixture(scope="module", autouse=True)
def _note_launches():
    """Wrap backends/cuda.py's kernels for this module (the host code looks them up as
    module globals at each launch): test_every_kernel_was_launched reads LAUNCHED."""
    if _PROBLEM is not None:
        yield
        return
    from dofsplat.backends import cuda as bc
    from dofsplat.backends import cuda_gauss as bg

    with pytest.MonkeyPatch.context() as mp:
        for module in (bc, bg):
            for name in _kernel_names(module):
                mp.setattr(module, name, _Noted(f"{module.__name__}.{name}",
                                                getattr(module, name)))
        yield


# Parity tolerances (issue 6): both backends run the same float64 maths; they differ only in
# rounding (exp(-q) per pixel on the GPU, forward differences along a row on the CPU: ~1e-15
# relative), which the float32 image turns into ~1e-7. The bounds leave room for a
# fragment at the very edge of a kernel's cutoff going one way on one device.
MEAN_ABS, MAX_ABS = 1e-3, 1e-2


def _layers(n: int) -> ds.Surfels:
    """A square of n x n opaque disks and, 0.4 in front, a translucent smaller square; the
    colours change across each square, so that LOD nodes carry colour gradients."""
    back = grid_surfels(n=n, spacing=1.0 / n, color=(0.2, 0.5, 0.8))
    front = grid_surfels(n=n // 2, spacing=0.6 / n, z=0.4, color=(0.9, 0.4, 0.1), opacity=0.7,
                         center=(0.2, 0.1))
    s = ds.Surfels(**{f: np.concatenate([getattr(back, f), getattr(front, f)])
                      for f in ("positions", "normals", "radius", "colors", "opacity")})
    ramp = s.colors + s.positions[:, [0, 1, 0]] * np.array([0.2, 0.2, -0.2], np.float32)
    return replace(s, colors=np.clip(ramp, 0.0, 1.0).astype(np.float32))


# the simulator runs Python per thread: 2 x 2 tiles there, 8 x 6 on a GPU
N, SIZE = (48, (128, 96)) if GPU else (10, (24, 20))
# lens diameters: a pinhole, a blur of about 1 pixel, and one that makes the LOD cut select
# inner nodes at the paper's stop, lod_blur_fraction=1 (81 of 125 splats in the simulator's
# scene, 32 of them inner nodes; 693 of 2,880 in the GPU's)
APERTURES = (0.0, 0.5, 2.0)


@pytest.fixture(scope="module")
def scene():
    return _layers(N), front_camera(*SIZE)


def _lens(aperture):
    return ds.ThinLens(focus_distance=1.6, aperture=aperture) if aperture else None


def _assert_same_frame(cpu, gpu):
    diff = np.abs(cpu.image.astype(np.float64) - gpu.image)
    assert diff.mean() <= MEAN_ABS and diff.max() <= MAX_ABS, (diff.mean(), diff.max())
    np.testing.assert_array_equal(np.isfinite(cpu.depth), np.isfinite(gpu.depth))
    seen = np.isfinite(cpu.depth)
    np.testing.assert_allclose(gpu.depth[seen], cpu.depth[seen], rtol=1e-5)
    np.testing.assert_allclose(gpu.weight, cpu.weight, atol=MAX_ABS)
    for key in ("splats_selected", "splats_rendered", "tile_pairs"):
        assert gpu.stats[key] == cpu.stats[key], key
    # a fragment exactly at the cutoff may go either way on either device
    assert abs(gpu.stats["fragments"] - cpu.stats["fragments"]) <= 1e-3 * cpu.stats["fragments"] + 2


# -- parity: whole frames ------------------------------------------------------------------


@needs_cuda
@pytest.mark.parametrize("lod", [False, True], ids=["full", "lod"])
@pytest.mark.parametrize("aperture, parts", [(0.0, 4), (0.5, 4), (2.0, 4), (2.0, 1)],
                         ids=["pinhole", "A0.5", "A2", "A2-one-pass"])
def test_frame_matches_cpu(scene, aperture, parts, lod):
    """Whole frames: the lens in parts (each part from its own camera) and in one pass.
    LOD with the paper's stop (kappa 1): on this 125-surfel grid the default's finer stop
    (0.35) keeps every surfel, and the cut's inner nodes would go untested."""
    surfels, camera = scene
    if SIMULATOR and parts > 2:
        parts = 2  # the same kernels as 4 parts, in half the simulator's time (CI)
    settings = ds.RenderSettings(lod=lod, lens_samples=parts, lod_blur_fraction=1.0)
    cpu = ds.render(surfels, camera, _lens(aperture), settings)
    gpu = ds.render(surfels, camera, _lens(aperture), replace(settings, device="cuda"))
    assert gpu.stats["device"] == "cuda"
    assert gpu.stats["lens_samples"] == cpu.stats["lens_samples"] == (parts if aperture else 1)
    if lod and aperture == APERTURES[-1] and parts == 1:
        assert cpu.stats["splats_selected"] < len(surfels)  # the cut has inner nodes
    _assert_same_frame(cpu, gpu)


@needs_cuda
def test_wide_blurs_from_samples_match_cpu(scene):
    """A blur wide enough (A = 6, one pass) that splats of an aperture radius of 8 px or more
    are drawn from the coarse samples (``RenderSettings.coarse_blur_px``; the CPU frame
    differs from the one drawn at every pixel by 0.011): each GPU pixel sums its samples'
    fragments (``cuda._coarse_fragment``), the CPU interpolates its samples' surfaces."""
    surfels, camera = scene
    settings = ds.RenderSettings(lod=False)
    cpu = ds.render(surfels, camera, _lens(6.0), settings)
    fine = ds.render(surfels, camera, _lens(6.0), replace(settings, coarse_blur_px=0.0))
    assert np.abs(fine.image - cpu.image).max() > 1e-3
    gpu = ds.render(surfels, camera, _lens(6.0), replace(settings, device="cuda"))
    _assert_same_frame(cpu, gpu)


@needs_cuda
def test_elliptical_weighted_unshaded_frame_matches_cpu():
    """Elliptical surfels with weights, no shading, a background, back faces kept."""
    s = grid_surfels(n=N, spacing=1.0 / N)
    rng = np.random.default_rng(3)
    angle = rng.uniform(0, np.pi, len(s))
    tangent = np.stack([np.cos(angle), np.sin(angle), np.zeros(len(s))], axis=1)
    ell = ds.Surfels(positions=s.positions, normals=s.normals, radius=s.radius * 1.3,
                     colors=rng.uniform(0, 1, (len(s), 3)), tangent=tangent,
                     radius_v=s.radius * 0.6, weight=rng.uniform(0.8, 1.2, len(s)))
    settings = ds.RenderSettings(shading="none", background=(0.1, 0.2, 0.3), cull_backfaces=False)
    camera = front_camera(*SIZE)
    # the simulator draws the blurred frame only (the pinhole frame's kernels are the same)
    for lens in ((_lens(2.0),) if SIMULATOR else (None, _lens(2.0))):
        cpu = ds.render(ell, camera, lens, settings)
        gpu = ds.render(ell, camera, lens, replace(settings, device="cuda"))
        _assert_same_frame(cpu, gpu)


def _crossing_planes(n: int) -> ds.Surfels:
    """Two opaque planes crossing at 12 degrees: each hides the other from the whole lens on
    one side of their line (abuffer.splat_visibility's looks through the lens)."""
    flat = grid_surfels(n=n, spacing=1.2 / n, color=(0.8, 0.3, 0.2))
    a = np.radians(12.0)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    tilted = grid_surfels(n=n, spacing=1.2 / n, color=(0.1, 0.4, 0.9))
    tilted = replace(tilted, positions=tilted.positions @ turn.T, normals=tilted.normals @ turn.T)
    return ds.Surfels(**{f: np.concatenate([getattr(flat, f), getattr(tilted, f)])
                         for f in ("positions", "normals", "radius", "colors", "opacity")})


@needs_cuda
@pytest.mark.parametrize("aperture", [0.0, 0.5], ids=["sharp", "A0.5"])
def test_hidden_from_the_lens_matches_cpu(aperture):
    """The front pass's looks through the lens, and the same pass in a sharp frame
    (``sharp_visibility``), on planes crossing at a shallow angle."""
    surfels, camera = _crossing_planes(N), front_camera(*SIZE)
    settings = ds.RenderSettings(lod=False, sharp_visibility=True)
    cpu = ds.render(surfels, camera, _lens(aperture), settings)
    if not aperture:  # the pass removes something here, or the case tests nothing
        plain = ds.render(surfels, camera, None, replace(settings, sharp_visibility=False))
        assert np.abs(plain.image - cpu.image).max() > 1e-3
    gpu = ds.render(surfels, camera, _lens(aperture), replace(settings, device="cuda"))
    _assert_same_frame(cpu, gpu)


@needs_cuda
def test_show_lod_frame_matches_cpu(scene):
    surfels, camera = scene
    settings = ds.RenderSettings(show_lod=True)
    cpu = ds.render(surfels, camera, _lens(2.0), settings)
    gpu = ds.render(surfels, camera, _lens(2.0), replace(settings, device="cuda"))
    _assert_same_frame(cpu, gpu)


# -- parity: stages ------------------------------------------------------------------------


@needs_cuda
@pytest.mark.parametrize("small", [1, 3], ids=["full-tree", "compact-tree"])
def test_pinhole_walk_matches_cpu(scene, small):
    """A pinhole frame's cut, where leaves_below lets both walks skip the stops' visits (on
    the whole tree here: a narrow field of view makes every surfel wider than a pixel): the
    same nodes in the same order, and the same as the CPU's walk that visits every node."""
    from dofsplat.backends import cuda as bc
    from dofsplat.lod import build_hierarchy, min_leaf_geo, select_cut
    from dofsplat.lod.select import leaves_below
    from dofsplat.render import select

    surfels, wide = scene
    camera = front_camera(wide.width, wide.height, fov=12.0)
    tree = build_hierarchy(surfels, small=small)
    ax, _, ay, _ = camera.screen_coefficients()
    view = np.ascontiguousarray(camera.camera_from_world()[:3].reshape(12))
    assert leaves_below(0, tree.center, tree.bound, min_leaf_geo(tree, surfels, small), view,
                        min(ax, ay), camera.frustum_lrbtn()[4], 1.0)
    settings = ds.RenderSettings()
    cpu_src = select(surfels, camera, None, settings, tree)
    gpu_src = bc.select_cuda(surfels, bc.device_scene(surfels, tree), tree, camera, None,
                             settings)
    for name in ("positions", "area", "level"):
        np.testing.assert_array_equal(getattr(gpu_src, name).copy_to_host(), getattr(cpu_src, name),
                                      err_msg=name)
    visits = select_cut(tree, surfels, camera, 0.0, 0.0, settings.cutoff, 1.0, True,
                        walk_to_leaves=False)
    assert visits[0].size == cpu_src.size


@needs_cuda
@pytest.mark.parametrize("min_node", [2, 4])
@pytest.mark.parametrize("small", [1, 3], ids=["full-tree", "compact-tree"])
def test_lod_cut_and_projection_match_cpu(scene, small, min_node):
    """The cut (same nodes, same order, same gathered arrays) and the projected splats; the
    GPU reads every inner node's row, which a compact tree (lod/hierarchy.py) computes for
    it where it stores none; with lod_min_node 4 neither draws a node of 2-3 surfels for
    the blur."""
    from dofsplat.backends import cuda as bc
    from dofsplat.backends.cpu import shade_splats
    from dofsplat.lod import build_hierarchy
    from dofsplat.render import project, select

    surfels, camera = scene
    # the paper's stop: inner nodes here
    settings = ds.RenderSettings(lod_blur_fraction=1.0, lod_min_node=min_node)
    lens = _lens(2.0)
    tree = build_hierarchy(surfels, small=small)
    cpu_src = select(surfels, camera, lens, settings, tree)
    gpu_src = bc.select_cuda(surfels, bc.device_scene(surfels, tree), tree, camera, lens, settings)
    for name in ("positions", "normals", "colors", "opacity", "ru", "rv", "area", "lod_cov",
                 "color_grad", "level"):
        np.testing.assert_array_equal(getattr(gpu_src, name).copy_to_host(), getattr(cpu_src, name),
                                      err_msg=name)

    rgb, gain = shade_splats(cpu_src, camera, settings)
    gpu_rgb, gpu_gain = bc.shade_cuda(gpu_src, camera, settings)
    np.testing.assert_allclose(gpu_rgb.copy_to_host(), rgb, rtol=1e-6, atol=1e-7)
    assert gain.shape == (cpu_src.size, 3)  # shaded nodes: their colour gradients are too
    np.testing.assert_allclose(gpu_gain.copy_to_host(), gain, rtol=1e-6, atol=1e-7)

    splats, bbox, visible = project(cpu_src, rgb, camera, lens, settings, gain=gain)
    g_splats, g_bbox, g_visible = bc.project_cuda(gpu_src, bc._upload(rgb), camera, lens, settings,
                                                  bc._upload(gain))
    g_visible = g_visible.copy_to_host()
    np.testing.assert_array_equal(g_visible, visible)
    np.testing.assert_array_equal(g_bbox.copy_to_host()[visible], bbox[visible])
    # the CPU keeps its rows in float32 (backends.cpu.project), the GPU in float64: the
    # same maths, compared at float32's precision (a rounding step, 6e-8 relative)
    g = g_splats.copy_to_host()[visible]
    from dofsplat.splat.project import BY, RX
    # inner nodes, and their colour slopes, are compared (measured: 6 of them with
    # lod_min_node 4, whose nodes of 2-3 surfels are drawn as their surfels)
    assert (cpu_src.level > 0).sum() > (10 if min_node == 2 else 4)
    assert np.abs(splats[visible][:, RX:BY + 1]).max() > 1e-4
    assert splats.dtype == np.float32
    np.testing.assert_allclose(g.astype(np.float32), splats[visible], rtol=2e-7, atol=1e-30)


@needs_cuda
def test_tile_lists_match_cpu(scene):
    """Same tile lists as the CPU's counting sort, each in increasing splat index."""
    from dofsplat.backends import cuda as bc
    from dofsplat.raster.abuffer import TILE, bin_splats
    from dofsplat.render import project, shade_surfels
    from dofsplat.splat.source import from_surfels

    surfels, camera = scene
    settings = ds.RenderSettings(lod=False)
    src = from_surfels(surfels)
    _, bbox, visible = project(src, shade_surfels(src, camera, settings), camera, _lens(2.0), settings)
    n_tx, n_ty = -(-camera.width // TILE), -(-camera.height // TILE)
    offsets, ids = bin_splats(bbox, visible, n_tx, 0, n_ty)
    g_offsets, g_ids, n_visible = bc.bin_cuda(bc._upload(bbox), bc._upload(visible),
                                              camera.width, camera.height)
    np.testing.assert_array_equal(g_offsets.copy_to_host(), offsets)
    np.testing.assert_array_equal(g_ids.copy_to_host(), ids)
    assert n_visible == np.count_nonzero(visible)


@needs_cuda
def test_exclusive_scan_matches_numpy():
    from dofsplat.backends import cuda as bc

    rng = np.random.default_rng(5)
    block = bc.SCAN_BLOCK
    # one block, one full block, a second level, and a third (block^2 + 1)
    for n in (0, 1, block, block + 1, 10 * block + 3, block * block + 1):
        x = rng.integers(0, 7, n).astype(np.uint8)
        out = bc.cuda.device_array(n + 1, np.int64)
        bc.exclusive_scan(bc._upload(x), n, out, f"test{n}")
        np.testing.assert_array_equal(out.copy_to_host(), np.concatenate([[0], np.cumsum(x)]))


@needs_cuda
def test_tile_sort_in_shared_and_global_memory():
    from dofsplat.backends import cuda as bc

    rng = np.random.default_rng(7)
    lengths = [0, 1, 2, 3, 17, bc.THREADS + 1, bc.SORT_SHARED, bc.SORT_SHARED + 37]
    ids = np.concatenate([rng.permutation(10 * m)[:m] for m in lengths]).astype(np.int32)
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    d_ids = bc._upload(ids)
    bc._sort_tiles[len(lengths), bc.THREADS](bc._upload(offsets), d_ids)
    got = d_ids.copy_to_host()
    for a, b in zip(offsets[:-1], offsets[1:]):
        np.testing.assert_array_equal(got[a:b], np.sort(ids[a:b]))


@needs_cuda
def test_device_copies_follow_the_model():
    """A new Surfels object (or new arrays) is uploaded again; the same one is reused."""
    from dofsplat.backends import cuda as bc

    a = grid_surfels(n=4)
    scene_a = bc.device_scene(a)
    assert bc.device_scene(a) is scene_a
    b = grid_surfels(n=4, color=(0.1, 0.9, 0.1))
    np.testing.assert_allclose(bc.device_scene(b).source.colors.copy_to_host(), b.colors)


# -- parity: Gaussian scenes ---------------------------------------------------------------


def _gaussians(n: int = 60, seed: int = 1) -> ds.Gaussians:
    """n random Gaussians of SH degree 3 in a 1-unit cube (tests/test_gaussians.py's scene),
    a tenth of them at one depth (sort ties, which both devices break by index)."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-0.5, 0.5, (n, 3))
    pos[: n // 10, 2] = 0.1
    return ds.Gaussians(positions=pos, scales=rng.uniform(0.01, 0.08, (n, 3)),
                        rotations=rng.normal(size=(n, 4)), opacity=rng.uniform(0.3, 1.0, n),
                        sh=rng.normal(0, 0.4, (n, 16, 3)))


# 2 x 2 tiles in the simulator (a Python thread per pixel), 8 x 6 on a GPU
G_SIZE = (128, 96) if GPU else (24, 18)


def _gaussian_camera(size=G_SIZE):
    return ds.Camera(eye=(0.3, -0.2, 2.5), target=(0, 0, 0), width=size[0], height=size[1],
                     fov_y=40.0, near=0.01)


def _assert_same_gaussian_frame(cpu, gpu):
    """The issue-6 bounds: both devices run the same float32/float64 maths (exp and sqrt of
    libm against libdevice: ~1e-7 in the image); an alpha at its cut or a pixel's stop at
    T = 1e-4 may go the other way on one device."""
    diff = np.abs(cpu.image.astype(np.float64) - gpu.image)
    assert diff.mean() <= MEAN_ABS and diff.max() <= MAX_ABS, (diff.mean(), diff.max())
    np.testing.assert_array_equal(np.isfinite(cpu.depth), np.isfinite(gpu.depth))
    seen = np.isfinite(cpu.depth)
    np.testing.assert_allclose(gpu.depth[seen], cpu.depth[seen], rtol=1e-5)
    assert gpu.stats["splats_rendered"] == cpu.stats["splats_rendered"]
    assert abs(gpu.stats["fragments"] - cpu.stats["fragments"]) <= 1e-3 * cpu.stats["fragments"] + 2


@needs_cuda
@pytest.mark.parametrize("aperture, settings", [
    (0.0, {}),
    # the default frame: 4 lens parts in layers, LOD, lens visibility by shifts; a blur of
    # up to 5 px at 32 x 24 (20 at 128 x 96), so that the layers include coarse ones on
    # either side of the focus
    (3.0, {}),
    (0.3, {"gaussian_blur": "viewers"}),
    (0.3, {"gaussian_lod": False, "gaussian_lens_samples": 1, "gaussian_antialiased": True}),
], ids=["pinhole", "default", "viewers", "one-pass-antialiased"])
def test_gaussian_frame_matches_cpu(aperture, settings):
    """A Gaussian scene's frame on both devices: the pinhole, the default frame through a
    lens (the lens in layers, ``cpu_gauss.LAYERS``, a summed layer among them: with the
    stage tests it launches every kernel of backends/cuda_gauss.py but the parts drawn
    whole's), the viewers' blur, and
    one pass with gsplat's antialiased opacity."""
    scene, camera = _gaussians(), _gaussian_camera()
    lens = ds.ThinLens(focus_distance=2.5, aperture=aperture) if aperture else None
    cpu = ds.render(scene, camera, lens, ds.RenderSettings(**settings))
    gpu = ds.render(scene, camera, lens, ds.RenderSettings(device="cuda", **settings))
    assert gpu.stats["device"] == "cuda"
    assert cpu.stats["splats_rendered"] > 0 and np.ptp(cpu.image[..., :3]) > 0.1
    if "layers" in cpu.stats:  # the images of each part's layers,
        # one layer summed (``cpu_gauss.mark_summed``), its weights from its own views
        assert cpu.stats["layers"] >= 9 and gpu.stats["layers"] == cpu.stats["layers"]
        assert cpu.stats["summed_layers"] >= 1
        assert gpu.stats["summed_layers"] == cpu.stats["summed_layers"]
    _assert_same_gaussian_frame(cpu, gpu)


@needs_cuda
def test_gaussian_frame_without_layers_matches_cpu(monkeypatch):
    """``cpu_gauss.LAYERS`` off, read at the call on both devices: each part of the lens
    drawn whole, with ``lens_visibility`` (at 16 x 12 in the simulator, 2 parts of one tile:
    the cheapest frame that launches the kernels of the parts drawn whole)."""
    import dataclasses

    from dofsplat.backends import cpu_gauss

    monkeypatch.setattr(cpu_gauss, "LAYERS", dataclasses.replace(cpu_gauss.LAYERS,
                                                                 enabled=False))
    scene, camera = _gaussians(), _gaussian_camera(G_SIZE if GPU else (16, 12))
    lens = ds.ThinLens(focus_distance=2.5, aperture=3.0)
    parts = {"gaussian_lens_samples": 4 if GPU else 2}  # (the simulator's time)
    cpu = ds.render(scene, camera, lens, ds.RenderSettings(**parts))
    gpu = ds.render(scene, camera, lens, ds.RenderSettings(device="cuda", **parts))
    assert "layers" not in cpu.stats and "layers" not in gpu.stats
    assert gpu.stats["lens_samples"] == parts["gaussian_lens_samples"]
    assert cpu.stats["splats_rendered"] > 0 and np.ptp(cpu.image[..., :3]) > 0.1
    _assert_same_gaussian_frame(cpu, gpu)


@needs_cuda
def test_gaussian_tile_lists_match_cpu():
    """The GPU's tile lists, as sort keys, decode to the CPU's depth_order then bin_tiles:
    nearest first, equal depths in index order; enough Gaussians in one tile that the
    simulator's sort runs in global memory too (over SORT_KEYS keys)."""
    from dofsplat.backends import cuda as bc
    from dofsplat.backends import cuda_gauss as bg
    from dofsplat.backends.cpu_gauss import project
    from dofsplat.gauss.composite import TILE, bin_tiles, depth_order

    scene, camera = _gaussians(n=120, seed=3), _gaussian_camera()
    settings = ds.RenderSettings()
    rows, boxes, visible = project(scene, camera, None, settings)
    n_tx, n_ty = -(-camera.width // TILE), -(-camera.height // TILE)
    offsets, ids = bin_tiles(depth_order(rows, visible), boxes, n_tx, n_ty)
    assert np.diff(offsets).max() > bc.SORT_KEYS or GPU
    d_rows, d_boxes, d_visible = bg.project_cuda(bg.device_gaussians(scene), camera, None,
                                                 settings)
    np.testing.assert_array_equal(d_boxes.copy_to_host()[visible], boxes[visible])
    g_offsets, keys, totals = bg.bin_cuda(bg.one_image(camera.width, camera.height, len(scene)),
                                          d_rows, d_boxes, d_visible)
    np.testing.assert_array_equal(g_offsets.copy_to_host(), offsets)
    np.testing.assert_array_equal(keys.copy_to_host() & bg.INDEX_MASK, ids)
    assert totals[:2] == [len(ids), np.count_nonzero(visible)]


@needs_cuda
def test_gaussian_layers_match_cpu(monkeypatch):
    """A layered frame's stages on both devices, from the same plan: every projection moved
    onto its image (``project_layers``), the rows listed per tile of every image in memory
    order (``bin_images``: nearest first within a layer; 16 x 12 in the simulator, a blur of
    up to 5 px there: images of scale 1 and 2 with margins), with an in-focus slab drawn
    once from the lens centre (``LayerSettings.sharp_coc`` 1 px; 0, none, by default)."""
    import dataclasses

    from dofsplat.backends import cpu_gauss
    from dofsplat.backends import cuda_gauss as bg
    from dofsplat.backends.cpu_gauss import NO_SHARE, in_layers, project_plan
    from dofsplat.frame import lens_parts
    from dofsplat.gauss.layers import IM_ROW0, IM_ROW1, IM_SCALE, bin_images
    from dofsplat.gauss.project import N_FIELDS

    camera = _gaussian_camera(G_SIZE if GPU else (16, 12))
    lens = ds.ThinLens(focus_distance=2.5, aperture=6.0)
    settings = ds.RenderSettings()
    monkeypatch.setattr(cpu_gauss, "LAYERS", dataclasses.replace(cpu_gauss.LAYERS,
                                                                 sharp_coc=1.0))
    parts = lens_parts(camera, lens, replace(settings, lens_samples=4))
    scene, layers = in_layers(_gaussians(), camera, lens, parts, settings, lod=False)
    assert layers.spans[layers.sharp, 1] > 0  # the slab holds Gaussians
    views, campos, cameras, spans, table, _, _ = bg.layer_plan(len(scene), layers, camera,
                                                               lens, parts, settings)
    assert len(table) >= 9 and set(table[:, IM_SCALE]) >= {1, 2}
    rows, boxes, visible = project_plan(scene, views, campos, cameras, spans, table)
    n_rows = len(rows)
    row_image = np.repeat(np.arange(len(table), dtype=np.int32),
                          table[:, IM_ROW1] - table[:, IM_ROW0])
    offsets, ids, tile_image = bin_images(table, np.arange(n_rows, dtype=np.int32), boxes,
                                          visible)

    images = bg.device_images(table)
    np.testing.assert_array_equal(images.tile_image.copy_to_host(), tile_image)
    np.testing.assert_array_equal(images.row_image.copy_to_host(), row_image)
    d_rows = bg.cuda.device_array((n_rows, N_FIELDS), np.float32)
    d_boxes = bg.cuda.to_device(np.zeros((n_rows, 4), np.int32))
    d_visible = bg.cuda.device_array(n_rows, np.bool_)
    arrays = bg.device_gaussians(scene)
    bg._project_layers[bg._blocks(n_rows), bg.THREADS](
        arrays["positions"], arrays["scales"], arrays["rotations"], arrays["opacity"],
        arrays["sh"], bg.cuda.to_device(NO_SHARE), bg._upload(views), bg._upload(campos),
        bg._upload(cameras), bg._upload(spans), False, 0.04, images.table, images.row_image,
        d_rows, d_boxes, d_visible)
    np.testing.assert_array_equal(d_visible.copy_to_host(), visible)
    np.testing.assert_array_equal(d_boxes.copy_to_host(), boxes)
    # libdevice's exp, sqrt and log against libm's: float32 rounding
    np.testing.assert_allclose(d_rows.copy_to_host()[visible], rows[visible], rtol=1e-5,
                               atol=1e-6)
    g_offsets, keys, totals = bg.bin_cuda(images, d_rows, d_boxes, d_visible, by_depth=False)
    np.testing.assert_array_equal(g_offsets.copy_to_host(), offsets)
    np.testing.assert_array_equal(keys.copy_to_host() & bg.INDEX_MASK, ids)
    assert totals[:2] == [len(ids), np.count_nonzero(visible)]


@needs_cuda
def test_gaussian_live_tiles_match_cpu():
    """``live_tiles`` on both devices, for images of 1 x 1 to 6 x 5 tiles whose tiles list
    a Gaussian or none at random: a tile is live where it or a neighbour in its image does."""
    from dofsplat.backends import cuda_gauss as bg
    from dofsplat.gauss.layers import image_table, live_tiles

    rng = np.random.default_rng(4)
    table = image_table([(w, h, 1, 0, 0, 0) for w, h in ((90, 70), (16, 16), (40, 20),
                                                          (20, 75))])
    images = bg.device_images(table)
    counts = rng.integers(0, 3, images.n_tiles) * (rng.random(images.n_tiles) < 0.15)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    expected = live_tiles(offsets, table, images.tile_image.copy_to_host())
    assert 0 < expected.sum() < len(expected)  # some tiles are not live: the test bites
    live = bg.cuda.to_device(np.zeros(images.n_tiles, np.bool_))
    bg._live_tiles[bg._blocks(images.n_tiles), bg.THREADS](bg._upload(offsets), images.table,
                                                           images.tile_image, live)
    np.testing.assert_array_equal(live.copy_to_host(), expected)


@needs_cuda
@pytest.mark.parametrize("by_shifts", [False, True], ids=["whole", "by-shifts"])
def test_gaussian_lens_visibility_matches_cpu(by_shifts):
    """The lens visibility of the default frame's Gaussians, on both devices
    (``lens_visibility``, the parts drawn whole's, or ``lens_visibility_by_shifts``, the
    layers'): the same shares, but for float rounding of the seen sums (added in another
    order on the GPU). At 32 x 24 pixels on every machine: 21 % and 23 % of these Gaussians
    are seen less than wholly there (at 128 x 96, none)."""
    from dofsplat.backends import cuda_gauss as bg
    from dofsplat.backends.cpu_gauss import lens_visibility, lens_visibility_by_shifts

    scene, camera = _gaussians(n=120), _gaussian_camera((32, 24))
    lens, settings = ds.ThinLens(focus_distance=2.5, aperture=0.3), ds.RenderSettings()
    arrays = bg.device_gaussians(scene)
    if by_shifts:
        cpu = lens_visibility_by_shifts(scene, camera, lens, settings)
        gpu = bg.lens_visibility_by_shifts_cuda(arrays, scene.positions, camera, lens,
                                                settings)
    else:
        cpu = lens_visibility(scene, camera, lens, settings)
        gpu = bg.lens_visibility_cuda(arrays, camera, lens, settings)
    assert cpu.min() < 0.5 and cpu.max() == 1.0  # some mostly hidden: the test bites
    np.testing.assert_allclose(gpu.copy_to_host(), cpu, atol=1e-5)


@needs_cuda
def test_probe_kernel_writes_one():
    """The kernel ``backends.cuda_problem`` runs on a GPU (it answers without it in the
    simulator)."""
    from dofsplat.backends import cuda as bc

    out = bc.cuda.to_device(np.zeros(1, np.float64))
    bc.probe_kernel[1, 1](out)
    assert out.copy_to_host()[0] == 1.0


@needs_cuda
def test_every_kernel_was_launched():
    """The tests above (run before this one, in file order) launch every kernel of
    backends/cuda.py and backends/cuda_gauss.py: `pytest --cudasim` runs a selection of them
    that must."""
    from dofsplat.backends import cuda as bc
    from dofsplat.backends import cuda_gauss as bg

    kernels = {f"{m.__name__}.{k}" for m in (bc, bg) for k in _kernel_names(m)}
    assert len(kernels) >= 33  # the parse found them (20 + 13 with the layers on the GPU)
    assert not kernels - LAUNCHED, sorted(kernels - LAUNCHED)


# -- the device choice and the CLI (everywhere) -----------------------------------------------


@pytest.fixture
def no_gpu(monkeypatch):
    """Make the CUDA probe answer "no GPU" for this test, whatever the machine has."""
    monkeypatch.setattr(backends, "_PROBLEM", ["no CUDA GPU or driver was found"])
    monkeypatch.setattr(backends, "_FALLBACK_SAID", False)


def test_device_setting_is_validated():
    with pytest.raises(DofsplatError, match="device must be one of cpu, cuda, auto"):
        ds.RenderSettings(device="gpu")


def test_cuda_without_gpu_is_an_error_and_auto_falls_back_once(no_gpu):
    s, cam = grid_surfels(n=4), front_camera(16, 16)
    with pytest.raises(DofsplatError, match="device cuda cannot run here: no CUDA GPU"):
        ds.render(s, cam, None, ds.RenderSettings(device="cuda"))
    with pytest.warns(RuntimeWarning, match="rendering on the CPU") as caught:
        a = ds.render(s, cam, None, ds.RenderSettings(device="auto"))
        b = ds.render(s, cam, None, ds.RenderSettings(device="auto"))
    assert len(caught) == 1  # said once
    assert "device" not in a.stats  # the CPU's stats
    np.testing.assert_array_equal(a.image, b.image)


def test_cli_device_cuda_without_gpu_is_one_line(no_gpu, tmp_path, capsys):
    out = tmp_path / "demo.png"
    assert main(["demo", "--device", "cuda", "--size", "32x24", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dofsplat: error: --device cuda cannot run here")
    assert "--device cpu or auto" in err[0]
    assert not out.exists() and not any(tmp_path.iterdir())


def test_cli_device_auto_without_gpu_renders_on_cpu(no_gpu, tmp_path, capsys):
    out = tmp_path / "demo.png"
    assert main(["demo", "--device", "auto", "--size", "32x24", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert err.count("rendering on the CPU") == 1
    assert out.exists()


@pytest.mark.skipif(GPU, reason="this machine has a working CUDA GPU")
def test_cli_device_cuda_on_this_machine_is_one_line(tmp_path):
    """No monkeypatching: the real probe, in a fresh process without the simulator."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_ENABLE_CUDASIM", "DOFSPLAT_TEST_CUDASIM")}
    out = tmp_path / "demo.png"
    proc = subprocess.run([sys.executable, "-m", "dofsplat", "demo", "--device", "cuda",
                           "--size", "32x24", "-o", str(out)], capture_output=True, text=True,
                          env=env, cwd=Path(__file__).parents[1], timeout=300)
    if proc.returncode == 0:
        pytest.skip("the fresh process found a working GPU")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dofsplat: error: --device cuda"), lines
    assert not out.exists()


def test_cpu_render_imports_no_cuda():
    """The package and a CPU frame never import numba's CUDA target."""
    code = ("import sys, dofsplat as ds\n"
            "s = ds.Surfels(positions=[[0, 0, 0]], normals=[[0, 0, 1]], radius=[0.1], colors=[[1, 1, 1]])\n"
            "ds.render(s, ds.Camera(eye=(0, 0, 1), target=(0, 0, 0), width=8, height=8))\n"
            "assert 'numba.cuda' not in sys.modules, 'numba.cuda was imported'\n")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          cwd=Path(__file__).parents[1], timeout=300)
    assert proc.returncode == 0, proc.stderr
