"""Wide blurs drawn at every second pixel (``RenderSettings.coarse_blur_px``, issue 49 item 3).

A splat whose aperture radius is at least ``coarse_blur_px`` pixels is drawn into an A-buffer
of the samples at the pixels of even row and column (``raster/abuffer.py``,
``rasterize_band``), and every pixel takes the surfaces of the samples around it,
interpolated linearly. The slow twin (``slow.rasterize_reference``'s ``coarse``) and the
banding and thread-count tests (tests/test_render.py, tests/test_lod.py) check the kernels;
these check what the samples mean for an image.
"""

from __future__ import annotations

import numpy as np

import dofsplat as ds
from dofsplat import demo
from dofsplat.metrics import psnr


APERTURE = 1.0


def lone_point(width=40, height=34):
    """One small opaque surfel before a camera focused far behind it: a disc of bokeh of
    radius ~10 px, off the pixel grid, whose edge crosses tile borders (16 px)."""
    s = ds.Surfels(positions=[[0.013, -0.007, 0.0]], normals=[[0, 0, 1]], radius=[0.01],
                   colors=[[1.0, 0.8, 0.6]])
    cam = ds.Camera(eye=(0, 0, 2.0), target=(0, 0, 0), width=width, height=height, fov_y=20)
    lens = ds.ThinLens(focus_distance=3.0, aperture=APERTURE)
    return s, cam, lens


def test_a_wide_splat_is_its_samples_interpolated():
    """The weights (linear in the kernel) of a lone blurred splat: at the pixels of even row
    and column those of the frame drawn at every pixel, elsewhere the mean of the two or
    four samples beside them, up to the image's last row and column (the samples past the
    edge are drawn too). The samples are the kernel's values, so this is exact up to the
    float32 weights (1e-6 of the peak)."""
    s, cam, lens = lone_point()
    st = ds.RenderSettings(shading="none", lod=False)
    fine = ds.render(s, cam, lens, ds.RenderSettings(shading="none", lod=False,
                                                     coarse_blur_px=0.0)).weight
    coarse = ds.render(s, cam, lens, st).weight
    assert fine.max() > 0 and (fine > 0).sum() > 300  # a disc of ~10 px radius
    h, w = fine.shape
    expect = np.empty_like(fine)
    for i in range(h):
        for j in range(w):
            rows = (i - 1, i + 1) if i % 2 else (i,)
            cols = (j - 1, j + 1) if j % 2 else (j,)
            if max(rows) >= h or max(cols) >= w:
                expect[i, j] = np.nan  # needs a sample past the edge (not in `fine`)
                continue
            expect[i, j] = np.mean([fine[a, b] for a in rows for b in cols])
    inside = np.isfinite(expect)
    np.testing.assert_allclose(coarse[inside], expect[inside], atol=1e-6 * fine.max())
    even = np.zeros_like(fine, bool)
    even[::2, ::2] = True
    np.testing.assert_allclose(coarse[even], fine[even], atol=1e-6 * fine.max())
    assert np.abs(coarse - fine).max() > 1e-3 * fine.max()  # the odd pixels are interpolated


def test_wide_blurs_from_samples_draw_the_contact_as_every_pixel_does():
    """The contact scene (spheres on a floor) at 192 x 144 and a largest CoC of ~19 px: the
    frame with the samples against the frame drawn at every pixel. Measured 76.3 dB at the
    default threshold, 8 px (51.2 dB at 4 px, where blurred spheres meet the sharp floor
    at the contact: the interpolated sphere's z-range there spans the samples', and merges
    with the floor; docs/maths.md, "Wide blurs at every second pixel"); the bound, 65 dB,
    fails at 4 px. And it draws fewer fragments (0.998 of the fine frame's here, where the
    widest blur is 19 px; 0.36-0.68 at 40 px on the fidelity suite)."""
    s, cam, lens = demo.contact_scene(192, 144)
    lens = ds.ThinLens(focus_distance=lens.focus_distance, aperture=0.3)
    fine = ds.render(s, cam, lens, ds.RenderSettings(coarse_blur_px=0.0))
    coarse = ds.render(s, cam, lens, ds.RenderSettings())
    assert psnr(coarse.image[..., :3], fine.image[..., :3]) >= 65.0
    assert coarse.stats["fragments"] < fine.stats["fragments"]


def test_the_threshold_is_on_the_command_line(tmp_path, capsys):
    """``--coarse-blur PX`` sets it (0: every pixel), the stats record it, and a negative
    value is a one-line error (exit 2)."""
    import json

    from dofsplat.cli import main

    frames = {}
    for px in ("0", "8"):
        out = tmp_path / f"d{px}.npy"
        assert main(["demo", "--size", "160x120", "--aperture", "0.8", "--coarse-blur", px,
                     "-o", str(out), "--stats", str(tmp_path / f"d{px}.json"), "-q"]) == 0
        stats = json.loads((tmp_path / f"d{px}.json").read_text())
        assert stats["settings"]["coarse_blur_px"] == float(px)
        frames[px] = np.load(out)
    assert np.abs(frames["0"] - frames["8"]).max() > 1e-4  # the demo at A = 0.8 is that wide
    assert main(["demo", "--coarse-blur", "-1", "-o", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--coarse-blur" in err[0], err
    assert not (tmp_path / "x.png").exists()
