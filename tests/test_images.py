"""Image files (neumat.io.images): the layers an OpenEXR may hold, sRGB decoding, and the
DAG-time check of the user's conditioning images."""

import numpy as np
import OpenEXR
import pytest
from PIL import Image

from neumat.io import images

HEADER = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
KEY = "conditions.image.images"


def _exr(path, layers: dict):
    OpenEXR.File(dict(HEADER), {k: np.ascontiguousarray(v) for k, v in layers.items()}).write(str(path))
    return path


def test_exr_layers_rgb_rgba_and_grey(tmp_path):
    rgba = np.random.default_rng(0).uniform(0, 4, (5, 7, 4)).astype(np.float32)
    np.testing.assert_array_equal(images.read_exr(_exr(tmp_path / "a.exr", {"RGBA": rgba})),
                                  rgba[..., :3])  # alpha dropped
    half = rgba[..., :3].astype(np.float16)
    got = images.read_exr(_exr(tmp_path / "h.exr", {"RGB": half}))
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, half.astype(np.float32))
    y = images.read_exr(_exr(tmp_path / "y.exr", {"Y": rgba[..., 0]}))
    np.testing.assert_array_equal(y, np.repeat(rgba[..., :1], 3, -1))
    with pytest.raises(ValueError, match=r"z\.exr: no RGB, RGBA or Y channels .*it has Z"):
        images.read_exr(_exr(tmp_path / "z.exr", {"Z": rgba[..., 0]}))


def test_png_is_decoded_from_srgb(tmp_path):
    Image.fromarray(np.array([[[0, 10, 255], [188, 128, 255]]], np.uint8)).save(tmp_path / "a.png")
    got = images.read_linear(tmp_path / "a.png")
    # IEC 61966-2-1: 10/255 is on the linear segment; 188/255 -> 0.5029; 128/255 -> 0.2158
    np.testing.assert_allclose(got[0, :, :2], [[0, 10 / 255 / 12.92], [0.50289, 0.21586]],
                               atol=2e-5)
    assert got[0, 0, 2] == 1


def test_16_bit_grey_alpha_and_float_images(tmp_path):
    """Pillow's convert("RGB") clipped 16-bit grey to 0..255 (mid-grey read as white), dropped
    alpha (a cut-out's transparent pixels kept their stored colour) and clipped float TIFFs."""
    Image.fromarray(np.array([[32768, 1000]], np.uint16)).save(tmp_path / "g16.png")
    got = images.read_linear(tmp_path / "g16.png")
    want = images.srgb_to_linear(np.array([32768, 1000]) / 65535)
    np.testing.assert_allclose(got[0], np.repeat(want[:, None], 3, 1), rtol=1e-6)
    rgba = np.array([[[200, 200, 200, 0], [188, 188, 188, 255], [188, 188, 188, 128]]], np.uint8)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "cut.png")
    got = images.read_linear(tmp_path / "cut.png")
    np.testing.assert_allclose(got[0, :, 0], [0, 0.50289, 0.50289 * 128 / 255], atol=2e-5)
    Image.fromarray(np.full((2, 2), 2.5, np.float32)).save(tmp_path / "f.tif")
    with pytest.raises(ValueError, match=r"f\.tif: a floating-point \.tif image.*OpenEXR"):
        images.read_linear(tmp_path / "f.tif")
    ych = np.ones((3, 3), np.float32)
    with pytest.raises(ValueError, match=r"yc\.exr: a luminance/chroma"):
        images.read_exr(_exr(tmp_path / "yc.exr", {"Y": ych, "RY": ych, "BY": ych}))


def test_check_images_names_the_key_the_file_and_the_fault(tmp_path):
    good = tmp_path / "good.png"
    rng = np.random.default_rng(1)
    Image.fromarray(rng.integers(0, 256, (4, 4, 3), np.uint8)).save(good)
    images.check_images([good, _exr(tmp_path / "g.exr", {"RGB": rng.random((3, 3, 3), np.float32)})], KEY)
    with pytest.raises(FileNotFoundError, match=rf"config {KEY}: .*nope\.png is not a file.*OpenEXR"):
        images.check_images([good, tmp_path / "nope.png"], KEY)
    with pytest.raises(FileNotFoundError, match="is not a file"):
        images.check_images([tmp_path], KEY)  # a directory
    (tmp_path / "junk.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(ValueError, match=rf"config {KEY}: .*junk\.png cannot be read as an image"):
        images.check_images([tmp_path / "junk.png"], KEY)
    noisy = tmp_path / "noisy.png"
    Image.fromarray(np.random.default_rng(0).integers(0, 256, (32, 32, 3), np.uint8)).save(noisy)
    (tmp_path / "cut.png").write_bytes(noisy.read_bytes()[:1500])  # header intact, data cut
    with pytest.raises(ValueError, match=r"cut\.png cannot be read as an image"):
        images.check_images([tmp_path / "cut.png"], KEY)
    nan = np.ones((4, 4, 3), np.float32)
    nan[1, 2, 0], nan[3, 3] = np.nan, np.inf
    with pytest.raises(ValueError, match=rf"config {KEY}: .*n\.exr has 2 of 16 pixels NaN or infinite"):
        images.check_images([_exr(tmp_path / "n.exr", {"RGB": nan})], KEY)
    neg = rng.random((4, 4, 3), np.float32)
    neg[0, 0, 2], neg[3, 1, 0] = -0.25, -1e-4  # a difference image; a denoiser's undershoot
    with pytest.raises(ValueError, match=rf"config {KEY}: .*neg\.exr has 2 of 16 pixels with "
                                         r"negative radiance \(down to -0\.25\); clamp them at 0"):
        images.check_images([_exr(tmp_path / "neg.exr", {"RGB": neg})], KEY)
    Image.fromarray(np.full((4, 4, 3), 90, np.uint8)).save(tmp_path / "flat.png")
    Image.fromarray(np.full((1, 1, 3), 90, np.uint8)).save(tmp_path / "dot.png")
    for name, n in (("flat", 16), ("dot", 1)):  # a blank file; one pixel
        with pytest.raises(ValueError, match=rf"config {KEY}: .*{name}\.png has one value in all "
                                             rf"{n} pixels, so it shows no material"):
            images.check_images([tmp_path / f"{name}.png"], KEY)
