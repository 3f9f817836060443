"""The conditioning report section's tables and figure (neumat.conditions.summary) on hand-made
files with known answers."""

import math

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from neumat.conditions import summary


def test_shares_table_names_shares_and_shows_no_data_as_a_dash():
    df = pd.DataFrame({"set": ["text", "mm_uncond"], "type hits": [0.5, math.nan],
                       "samples with a training type": [4, 0]})
    md = summary.shares_table(df).splitlines()
    assert "type-hit share" in md[0] and "type hits" not in md[0]
    assert md[2].split("|")[2].strip() == "0.5"
    assert md[3].split("|")[2].strip() == "–"


def test_job_costs_read_snakemake_benchmark_files(tmp_path):
    paths = []
    for name, s, cpu in (("train_multimodal", 12.5, 20.0), ("text_embeddings", 1.0, 0.5)):
        p = tmp_path / f"{name}.tsv"
        p.write_text("s\th:m:s\tmax_rss\tcpu_time\n"
                     f"{s}\t0:00:{int(s):02d}\t100.0\t{cpu}\n")
        paths.append(p)
    t = summary.job_costs(paths)
    assert t.to_dict("records") == [{"job": "train_multimodal", "wall s": 12.5, "CPU s": 20.0},
                                    {"job": "text_embeddings", "wall s": 1.0, "CPU s": 0.5}]


def test_image_means_average_each_column_over_the_images():
    img = pd.DataFrame({c: [1.0, 3.0] for c in summary.IMAGE_MEANS} | {"image": ["a", "b"]})
    img["ssim_retrieval"] = [0.5, 0.7]
    m = summary.image_means(img)
    assert list(m.columns) == summary.IMAGE_MEANS and len(m) == 1
    assert m.loc["mean", "psnr_conditioned"] == 2.0
    assert abs(m.loc["mean", "ssim_retrieval"] - 0.6) < 1e-12


def test_plot_sweep_draws_every_modality(tmp_path):
    sweep = pd.DataFrame({"modality": ["type", "type", "text", "text"], "scale": [1.0, 2, 1, 2],
                          "type hits": [0.5, 0.75, 0.25, 0.5],
                          "median BRDF-L1 to nearest training": [0.2, 0.3, 0.2, 0.25],
                          "share clamping negatives": [0.1, 0.2, 0.1, 0.1]})
    ref = pd.DataFrame({"set": [summary.REAL_TEST, summary.TRAINING_FITS],
                        "median BRDF-L1 to nearest training": [0.3, 0.0],
                        "share clamping negatives": [0.0, 0.2]})
    path, one = tmp_path / "sweep.png", tmp_path / "one.png"
    summary.plot_sweep(sweep, ref, path)
    assert Image.open(path).size == (1100, 320)
    # the text line is drawn: without it the figure differs
    summary.plot_sweep(sweep[sweep["modality"] == "type"], ref, one)
    assert np.asarray(Image.open(path)).tobytes() != np.asarray(Image.open(one)).tobytes()
    with pytest.raises(KeyError):  # a summary without the yardstick rows
        summary.plot_sweep(sweep, ref.iloc[:1], tmp_path / "none.png")
