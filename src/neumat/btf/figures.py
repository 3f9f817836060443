"""Figures of the BTF branch: texture grids (paper Figs. 4, 8) and tiled planes (Fig. 5)."""

from __future__ import annotations

import numpy as np


def texture_grid(path, rows: list[str], cols: list[str], images, notes=None, title=""):
    """images[r][c] display images; notes[r][c] a caption under each panel (metrics)."""
    # lazily: most BTF jobs draw no figure, and pyplot costs ~0.4 s to import (AMD EPYC)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(1.8 * len(cols), 1.9 * len(rows)),
                             squeeze=False)
    for r in range(len(rows)):
        for c in range(len(cols)):
            ax = axes[r][c]
            ax.imshow(np.clip(images[r][c], 0, 1), interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
            if r == 0:
                ax.set_title(cols[c], fontsize=8)
            if c == 0:
                ax.set_ylabel(rows[r], fontsize=7)
            if notes and notes[r][c]:
                ax.set_xlabel(notes[r][c], fontsize=6)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
