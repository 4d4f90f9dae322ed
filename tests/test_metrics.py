"""PSNR and SSIM (dofsplat.metrics) and the ``dofsplat compare`` command."""

import json
import math

import numpy as np
import pytest

from dofsplat.cli import main
from dofsplat.errors import DofsplatError
from dofsplat.io import linear_to_srgb, read_image, srgb_to_linear, write_image
from dofsplat.metrics import compare, difference_image, psnr, ssim


def random_image(h=40, w=50, seed=0, channels=4):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.05, 0.95, (h, w, channels)).astype(np.float32)


def perturbed(image, delta, space="srgb", seed=1):
    """image with every compared value moved by exactly +-delta (random signs)."""
    signs = np.random.default_rng(seed).choice([-1.0, 1.0], image.shape[:2] + (3,))
    x = image[..., :3].astype(np.float64)
    if space == "srgb":
        out = srgb_to_linear(linear_to_srgb(x) + delta * signs)
    else:
        out = x + delta * signs
    return np.concatenate([out, image[..., 3:]], axis=2)


def test_identical_images_give_infinite_psnr_and_ssim_one():
    a = random_image()
    got = compare(a, a.copy())
    assert got["psnr"] == math.inf and got["mse"] == 0.0
    assert got["ssim"] == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("space", ["srgb", "linear"])
@pytest.mark.parametrize("delta", [0.1, 0.01, 0.003])
def test_a_known_perturbation_gives_the_known_psnr(space, delta):
    """Every value off by +-delta: MSE = delta^2, PSNR = -20 log10(delta) exactly.

    The compared values lie in [0.15, 0.85], so +-0.1 clips nothing; the tolerance covers
    the float64 sRGB round trip (1e-12 relative).
    """
    x = np.random.default_rng(2).uniform(0.15, 0.85, (40, 50, 3))
    a = srgb_to_linear(x) if space == "srgb" else x
    b = perturbed(a, delta, space)
    assert psnr(a, b, space) == pytest.approx(-20 * math.log10(delta), abs=1e-6)
    # and SSIM drops below 1, the more the larger the perturbation
    assert ssim(a, b, space) < 1.0


def test_ssim_orders_perturbations():
    a = random_image()
    s = [ssim(a, perturbed(a, d)) for d in (0.003, 0.01, 0.1)]
    assert 1.0 > s[0] > s[1] > s[2]


def test_alpha_is_ignored_and_grey_images_compare():
    a = random_image()
    b = a.copy()
    b[..., 3] = 0.0
    assert compare(a, b)["psnr"] == math.inf
    assert compare(a[..., :3], a)["psnr"] == math.inf
    assert compare(a[..., 0], a[..., :1])["psnr"] == math.inf


def test_png_quantisation_costs_about_59_db(tmp_path):
    """8-bit rounding: uniform error of 1/255 width, PSNR = 10 log10(12 x 255^2) = 58.9 dB."""
    a = random_image(96, 96, channels=3)
    path = tmp_path / "a.png"
    write_image(path, a)
    got = compare(a, read_image(path))
    assert got["psnr"] == pytest.approx(10 * math.log10(12 * 255 ** 2), abs=0.3)
    assert got["ssim"] > 0.999


@pytest.mark.parametrize("a, b, message", [
    (np.zeros((20, 30, 3)), np.zeros((30, 20, 3)), "differ in size"),
    (np.zeros((20, 30, 3)), np.zeros((20, 30)), "grey"),
    (np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), "too small"),
    (np.full((20, 20, 3), np.nan), np.zeros((20, 20, 3)), "NaN"),
    (np.zeros((20, 20, 5)), np.zeros((20, 20, 5)), "shape"),
])
def test_mistakes_are_clear_errors(a, b, message):
    with pytest.raises(DofsplatError, match=message):
        compare(a, b)


def test_difference_image_is_gain_times_the_difference():
    a = random_image()
    b = perturbed(a, 0.01)
    d = difference_image(a, b, gain=10)
    np.testing.assert_allclose(d, 0.1, rtol=1e-9)
    assert difference_image(a, a).max() == 0.0


# -- the command line --------------------------------------------------------------------


@pytest.fixture
def two_images(tmp_path):
    a = random_image(48, 64)
    b = perturbed(a, 0.01).astype(np.float32)
    pa, pb = tmp_path / "a.npy", tmp_path / "b.npy"
    np.save(pa, a)
    np.save(pb, b)
    return pa, pb


def test_cli_compare_prints_psnr_and_ssim(two_images, tmp_path, capsys):
    pa, pb = two_images
    diff, record = tmp_path / "diff.png", tmp_path / "cmp.json"
    assert main(["compare", str(pa), str(pb), "--diff", str(diff), "--json", str(record)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("PSNR 40.00 dB  SSIM 0.9")  # delta = 0.01 (float32 storage)
    data = json.loads(record.read_text())
    assert data["psnr_db"] == pytest.approx(40.0, abs=1e-3) and not data["identical"]
    assert (data["width"], data["height"]) == (64, 48)
    # the PNG shows 10 x 0.01 in every channel, to 8-bit rounding
    shown = linear_to_srgb(read_image(diff).astype(np.float64))
    np.testing.assert_allclose(shown, 0.1, atol=0.5 / 255 + 1e-6)


def test_cli_compare_identical(two_images, tmp_path, capsys):
    pa, _ = two_images
    record = tmp_path / "same.json"
    assert main(["compare", str(pa), str(pa), "--json", str(record), "-q"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "PSNR inf dB  SSIM 1.0000\n" and captured.err == ""
    data = json.loads(record.read_text())
    assert data["psnr_db"] is None and data["identical"] and data["ssim"] == 1.0


def test_cli_compare_png_against_npy(tmp_path, capsys):
    a = random_image(32, 32, channels=3)
    write_image(tmp_path / "a.png", a)
    np.save(tmp_path / "a.npy", a)
    assert main(["compare", str(tmp_path / "a.png"), str(tmp_path / "a.npy")]) == 0
    value = float(capsys.readouterr().out.split()[1])
    assert 58 < value < 60


@pytest.mark.parametrize("make_b, diff_name, message", [
    (lambda p: np.save(p, np.zeros((10, 64, 4), np.float32)), "d.png", "differ in size"),
    (lambda p: None, "d.png", "no such file"),
    (lambda p: np.save(p, np.zeros((48, 64, 4), np.float32)), "d.gif", "unsupported image format"),
    (lambda p: np.save(p, np.zeros((48, 64, 4), np.float32)), "a.npy", "overwrite an input"),
    # the file named (the message had no name until 2026-11-27)
    (lambda p: np.save(p, np.full((48, 64, 4), np.nan, np.float32)), "d.png",
     "other.npy: 3,072 pixels with NaN or inf"),
    # an array of strings was a ValueError's traceback, exit status 1
    (lambda p: np.save(p, np.full((48, 64, 4), "a")), "d.png",
     "other.npy: expected an array of numbers, got dtype <U1"),
])
def test_cli_compare_mistakes(two_images, tmp_path, capsys, make_b, diff_name, message):
    pa, _ = two_images
    pb = tmp_path / "other.npy"
    make_b(pb)
    diff = tmp_path / diff_name
    before = pa.read_bytes()
    assert main(["compare", str(pa), str(pb), "--diff", str(diff)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dofsplat: error: ") and message in err and err.count("\n") == 1
    assert pa.read_bytes() == before
    if diff != pa:
        assert not diff.exists()
