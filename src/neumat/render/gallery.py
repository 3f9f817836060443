"""Image grids: N images + labels -> one PNG (numpy layout, labels drawn with PIL)."""

from __future__ import annotations

import os
import re
import textwrap

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from neumat.render.sphere import tonemap


def wrap_label(label, width: int, font=None) -> list[str]:
    """Split `label` into lines no wider than `width` pixels in `font` (PIL's default font if
    None), keeping all of it: explicit newlines start a new line; words, and the pieces of a
    hyphenated word, are filled greedily; a piece wider than `width` alone is broken between
    characters. Only the whitespace at line breaks is dropped."""
    font = font or ImageFont.load_default()
    lines = []
    for para in str(label).split("\n"):
        line, space = "", ""
        for tok in re.findall(r"\s+|[^\s-]*-+|[^\s-]+", para):
            if tok.isspace():
                space = tok
                continue
            if not line or font.getlength(line + space + tok) > width:
                if line:
                    lines.append(line)
                line = tok
                while len(line) > 1 and font.getlength(line) > width:  # a piece too wide
                    cut = max([i for i in range(1, len(line))
                               if font.getlength(line[:i]) <= width] or [1])
                    lines.append(line[:cut])
                    line = line[cut:]
            else:
                line += space + tok
            space = ""
        lines.append(line)
    return lines


def gallery(images, labels, path: str | os.PathLike | None = None, ncols: int = 8,
            pad: int = 4, label_height: int = 14, background: int = 255,
            min_cell: int = 0, title: str | None = None) -> np.ndarray:
    """Lay out images (each (H, W, 3): uint8 sRGB, or float linear HDR, tone-mapped) in a grid
    with a label under each, wrapped to the cell width and never cut (`wrap_label`); cells are
    as large as the largest image (at least `min_cell` pixels wide, so labels of small images
    need fewer lines) and an optional `title` line on top.
    Saves a PNG if `path`.
    Returns the grid as uint8 (rows, cols, 3)."""
    images = [np.asarray(i) for i in images]
    if len(images) != len(labels):
        raise ValueError(f"gallery: {len(images)} images but {len(labels)} labels")
    if not images:
        raise ValueError("gallery: no images")
    images = [i if i.dtype == np.uint8 else tonemap(i) for i in images]
    h = max(i.shape[0] for i in images)
    w = max(max(i.shape[1] for i in images), min_cell)
    ncols = max(1, min(ncols, len(images)))
    nrows = -(-len(images) // ncols)
    font = ImageFont.load_default()
    # every label whole, as many lines as it needs: the label band grows to the longest
    lines = [wrap_label(lbl, w, font) for lbl in labels]
    lab_h = label_height * max(len(l) for l in lines)
    grid = np.full((nrows * (h + lab_h + pad) + pad, ncols * (w + pad) + pad, 3), background,
                   np.uint8)
    for k, img in enumerate(images):
        r, c = divmod(k, ncols)
        y, x = pad + r * (h + lab_h + pad), pad + c * (w + pad)
        grid[y:y + img.shape[0], x:x + img.shape[1]] = img[..., :3]
    pil = Image.fromarray(grid)
    draw = ImageDraw.Draw(pil)
    for k, text in enumerate(lines):
        r, c = divmod(k, ncols)
        y, x = pad + r * (h + lab_h + pad) + h + 1, pad + c * (w + pad)
        draw.text((x, y), "\n".join(text), fill=(0, 0, 0), font=font)
    if title:  # wrapped to the grid's width (a narrow grid cut a one-line title short), words
        # whole: a word longer than the grid widens the canvas
        rows = textwrap.wrap(str(title), max(8, (pil.width - 2 * pad) // 6),
                             break_long_words=False, break_on_hyphens=False) or [""]
        width = max(pil.width, 6 * max(len(r) for r in rows) + 2 * pad)
        top = Image.new("RGB", (width, label_height * len(rows) + pad), (background,) * 3)
        ImageDraw.Draw(top).text((pad, pad // 2), "\n".join(rows), fill=(0, 0, 0), font=font)
        framed = Image.new("RGB", (width, pil.height + top.height), (background,) * 3)
        framed.paste(top, (0, 0))
        framed.paste(pil, (0, top.height))
        pil = framed
    out = np.asarray(pil)
    if path is not None:
        pil.save(path)
    return out
