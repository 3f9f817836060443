"""The conditioning report section's tables and figure (rule `conditions_section`,
workflow/scripts/conditions_section.py), from the files the conditioning rules write: the jobs'
cost, the mean image agreement, the share tables and the guidance sweep. The script writes the
prose around them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

# the TSVs' share columns as the section names them: "type hits 1 | samples with a training
# type 4" read as 1 of 4 where it means 100 % of 4
SHARE_COLUMNS = {"type hits": "type-hit share", "colour match": "colour-match share"}
IMAGE_MEANS = ["psnr_conditioned", "psnr_retrieval", "psnr_unconditional", "ssim_conditioned",
               "ssim_retrieval", "ssim_unconditional"]
# summary rows the sweep's distance and clamping panels draw as horizontal yardsticks
REAL_TEST = "reference: real test-split materials"
TRAINING_FITS = "reference: training fits"


def shares_table(df: pd.DataFrame) -> str:
    """Markdown table with the share columns named as shares and empty cells (NaN) as '–'."""
    df = df.rename(columns=SHARE_COLUMNS)
    return df.astype(object).where(df.notna(), None).to_markdown(
        index=False, floatfmt=".4g", missingval="–")


def job_costs(benchmarks) -> pd.DataFrame:
    """Wall and CPU seconds per job from Snakemake benchmark files (the job: the file's stem)."""
    rows = []
    for b in benchmarks:
        t = pd.read_csv(b, sep="\t")
        rows.append({"job": Path(b).stem, "wall s": t["s"].iloc[0], "CPU s": t["cpu_time"].iloc[0]})
    return pd.DataFrame(rows)


def image_means(image: pd.DataFrame) -> pd.DataFrame:
    """One row: the mean over conditioning images of each PSNR and SSIM column."""
    return image[IMAGE_MEANS].mean().to_frame("mean").T


def plot_sweep(sweep: pd.DataFrame, summary: pd.DataFrame, path) -> None:
    """Type hits, median distance to the nearest training material and the share clamping
    negatives against the guidance scale, one line per modality, with the real test split's
    distance and the training fits' clamping share as yardsticks and the 90 % type-hit goal."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(11, 3.2))
    # a marker, a dash and a small sideways offset per modality: where two modalities score
    # alike, one line hid the other (a review saw the type line missing under the text line)
    styles, span = ("o-", "s--", "^:", "D-."), float(np.ptp(sweep["scale"])) or 1.0
    for k, (mod, g) in enumerate(sweep.groupby("modality", sort=False)):
        x = g["scale"] + 0.015 * span * (k - 1)
        style = dict(fillstyle="none", ms=7 - k, label=mod)
        axes[0].plot(x, 100 * g["type hits"], styles[k % 4], **style)
        axes[1].plot(x, g["median BRDF-L1 to nearest training"], styles[k % 4], **style)
        axes[2].plot(x, 100 * g["share clamping negatives"], styles[k % 4], **style)
    ref = summary.set_index("set")
    for ax, col, scale, row in ((axes[1], "median BRDF-L1 to nearest training", 1, REAL_TEST),
                                (axes[2], "share clamping negatives", 100, TRAINING_FITS)):
        ax.axhline(scale * ref.loc[row, col], color="k", ls="--", lw=1, label=row.split(": ")[1])
    axes[0].axhline(90, color="k", ls=":", lw=1, label="goal 90 %")
    axes[0].set(xlabel="guidance scale", ylabel="type hits (%)")
    axes[1].set(xlabel="guidance scale", ylabel="median BRDF-L1 to nearest training", yscale="log")
    axes[2].set(xlabel="guidance scale", ylabel="samples clamping negatives (%)")
    for ax in axes:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
