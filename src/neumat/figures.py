"""Labelled image grids for the report (matplotlib, headless)."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def save_grid(images, labels, path: str | Path, ncols: int | None = None,
              title: str | None = None, cell: float = 1.6) -> None:
    """N uint8 images (N, H, W, 3) with one label each -> one PNG grid."""
    images = np.asarray(images)
    if len(images) != len(labels):
        raise ValueError(f"{len(images)} images but {len(labels)} labels")
    n = len(images)
    ncols = ncols or min(n, 8)
    nrows = math.ceil(n / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(cell * ncols, cell * nrows + 0.3 * bool(title)),
                             squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, img, lab in zip(axes.ravel(), images, labels):
        ax.imshow(img)
        ax.set_title(str(lab), fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def save_strip(images, labels, path, title=None):
    """One row of labelled images."""
    save_grid(images, labels, path, ncols=len(images), title=title)
