"""Workflow smoke test: config/tiny.yaml end to end, plus DAG-time config errors.

The workflow runs in a copy of the repository's workflow files in a temporary directory, so the
test never touches results/ of the checkout."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _copy_workflow(dst: Path) -> Path:
    for item in ("Snakefile", "workflow", "config"):
        src = ROOT / item
        (shutil.copytree if src.is_dir() else shutil.copy)(src, dst / item)
    return dst


def _snakemake(cwd, *args, check=True):
    cmd = [sys.executable, "-m", "snakemake", "--cores", "2", *args]
    res = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if check and res.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{res.stdout[-4000:]}\n{res.stderr[-8000:]}")
    return res


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    wd = _copy_workflow(tmp_path_factory.mktemp("tiny"))
    _snakemake(wd, "report", "--configfile", "config/tiny.yaml")
    return wd


def test_tiny_config_runs_to_report(tiny_run):
    rep = tiny_run / "results/tiny/report"
    html = (rep / "index.html").read_text()
    md = (rep / "index.md").read_text()
    assert "<table>" in html and "AugMERL" in md
    for img in ("augmerl_permutations.png", "augmerl_interpolation.png"):
        assert (rep / "figures" / img).stat().st_size > 1000
    man = pd.read_csv(tiny_run / "results/tiny/augmerl/manifest.tsv", sep="\t",
                      keep_default_na=False)
    assert len(man) == 64 and set(man["split"]) == {"train", "test"}
    # every rule logged and benchmarked
    assert list((tiny_run / "results/tiny/logs").rglob("*.log"))
    assert (tiny_run / "results/tiny/benchmarks/augmerl_pca.tsv").exists()


def test_tiny_config_runs_every_stage(tiny_run):
    res = tiny_run / "results/tiny"
    md = (res / "report/index.md").read_text()
    for section in ("NeuMERL", "Rendering", "Hyperdiffusion", "Table 2", "Triple Plane"):
        assert section in md, section
    w = np.load(res / "neumerl/weights.npy")
    assert w.shape == (64, 675) and w.dtype == np.float32 and np.isfinite(w).all()
    fits = pd.read_csv(res / "neumerl/fits.tsv", sep="\t")
    assert {"id", "name", "train_loss", "val_loss", "render_psnr"} <= set(fits.columns)
    assert (res / "neumerl/merl/mix0000.binary").stat().st_size == 34_992_012
    table = pd.read_csv(res / "metrics/table2.csv")
    assert {"training_set", "ours", "merl100"} <= set(table.columns)
    assert len(table) == 13  # FID + 3 metrics x 4 distances
    q = pd.read_csv(res / "btf/quality.tsv", sep="\t")
    assert len(q) > 0


def test_tiny_config_runs_text_and_image_conditioning(tiny_run):
    res = tiny_run / "results/tiny"
    assert "Multi-modal conditioning" in (res / "report/index.md").read_text()
    man = pd.read_csv(res / "neumerl/manifest.tsv", sep="\t", keep_default_na=False)
    assert np.load(res / "conditions/text.npy").shape == (len(man), 384)
    prompts = pd.read_csv(res / "conditions/prompts.tsv", sep="\t", keep_default_na=False)
    assert {"test", "unseen"} == set(prompts["kind"]) and "red plastic" in set(prompts["prompt"])
    for s, n in (("text", 2 * len(prompts)), ("image", 2 * 3)):  # 2 test renders + 1 user PNG
        w = np.load(res / f"samples/{s}/weights.npy")
        assert w.shape == (n, 675) and np.isfinite(w).all(), s
    t = pd.read_csv(res / "samples/image/samples.tsv", sep="\t", keep_default_na=False)
    assert "config/tiny_reference.png" in set(t["source"])
    summary = pd.read_csv(res / "conditions/eval_summary.tsv", sep="\t")
    assert {"text", "image", "mm_type", "mm_uncond"} <= set(summary["set"])
    sweep = pd.read_csv(res / "conditions/guidance_sweep.tsv", sep="\t")
    assert set(sweep["modality"]) == {"type", "text", "image"}
    for f in ("conditions_text.png", "conditions_image.png", "conditions_guidance.png"):
        assert (res / "report/figures" / f).stat().st_size > 1000


def test_rerun_is_a_no_op(tiny_run):
    res = _snakemake(tiny_run, "report", "--dry-run", "--configfile", "config/tiny.yaml")
    assert "Nothing to be done" in res.stdout + res.stderr


def test_unknown_config_key_fails_before_any_job(tmp_path):
    wd = _copy_workflow(tmp_path)
    res = _snakemake(wd, "--configfile", "config/tiny.yaml", "--config", "augmerl={bogus: 1}",
                     "--dry-run", check=False)
    assert res.returncode != 0
    assert "bogus" in res.stderr + res.stdout
    assert not (wd / "results").exists()


def test_wrong_type_names_the_key(tmp_path):
    wd = _copy_workflow(tmp_path)
    res = _snakemake(wd, "--configfile", "config/tiny.yaml", "--config", "seed=abc",
                     "--dry-run", check=False)
    assert res.returncode != 0 and "seed" in res.stderr + res.stdout
