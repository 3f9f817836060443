"""Report figures of the NeuMERL fits."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_fit_quality(render_psnr, val_loss, steps, val_history, path: str | Path) -> None:
    """Report figure: histograms of render PSNR and val loss, and the val-loss curves
    (median and 10-90 % band over materials, (k, N) history at `steps`)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(12, 3.2))
    ax[0].hist(render_psnr, bins=30, color="tab:blue")
    ax[0].axvline(np.median(render_psnr), color="k", ls="--", label="median")
    ax[0].set(xlabel="render PSNR (dB)", ylabel="materials", title="render PSNR vs table")
    ax[0].legend()
    v = np.asarray(val_loss)
    ax[1].hist(v, bins=np.geomspace(max(v.min(), 1e-6), max(v.max(), 2e-6), 30), color="tab:orange")
    ax[1].set(xscale="log", xlabel="validation loss (eq. 2)", title="validation loss")
    h = np.asarray(val_history)
    if len(steps):
        ax[2].fill_between(steps, np.percentile(h, 10, 1), np.percentile(h, 90, 1), alpha=0.3)
        ax[2].plot(steps, np.median(h, 1), marker=".")
    ax[2].set(yscale="log", xlabel="step", ylabel="val loss", title="median, 10-90 % band")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
