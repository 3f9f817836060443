"""Gallery labels are drawn whole: wrapped to the cell width onto as many lines as they need."""
import numpy as np
import pytest
from PIL import ImageFont

from neumat.render import gallery

LONG = ["silver-metallic-paint@rbg\nground truth",
        "nn: silver-metallic-paint@rbg (L1 0.123)",
        "metallic-paint (nn: specular-plastic)"]


def squeeze(s):
    return "".join(s.split())


@pytest.mark.parametrize("width", [48, 96, 128])
@pytest.mark.parametrize("label", LONG)
def test_wrap_label_keeps_the_whole_label_within_the_cell(label, width):
    """At 48 px the old wrap (width/6 characters, 2 lines) lost the L1 distance, the nearest
    type and the ground-truth suffix; at 128 px 'silver-metallic-paint@rbg ground truth' lost
    'truth'."""
    font = ImageFont.load_default()
    lines = gallery.wrap_label(label, width, font)
    assert squeeze("".join(lines)) == squeeze(label)  # only the spaces at breaks are dropped
    assert all(font.getlength(line) <= width for line in lines)
    if width >= 96:  # words that fit stay whole
        assert " ".join(lines).replace("- ", "-").split() == label.split()


def test_wrap_label_keeps_explicit_newlines():
    assert gallery.wrap_label("a\nb", 128) == ["a", "b"]
    assert gallery.wrap_label("", 48) == [""]


def test_the_label_band_grows_to_the_longest_label():
    imgs = [np.zeros((48, 48, 3), np.uint8)] * 2
    short = gallery.gallery(imgs, ["a", "b"], ncols=2)
    lines = gallery.wrap_label(LONG[1], 48)
    assert len(lines) > 2
    tall = gallery.gallery(imgs, ["a", LONG[1]], ncols=2)
    assert tall.shape[0] - short.shape[0] == 14 * (len(lines) - 1)
    assert tall.shape[1] == short.shape[1]
    band = tall[4 + 48:tall.shape[0] - 4, 4 + 48 + 4:]  # the second cell's label band
    assert (band < 128).any(axis=1).sum() > 14 * (len(lines) - 1)  # text on every line
