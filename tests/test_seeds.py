"""Named seed streams (neumat.seeds, common.smk seed_for): stable, distinct per name, and
every stream of the default config's DAG distinct from every other."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from neumat.seeds import seed_for

ROOT = Path(__file__).resolve().parents[1]


def test_seed_for_is_stable_and_named():
    assert seed_for(0, "fit") == 3449718424  # fixed across processes and versions (no hash())
    assert seed_for(0, "fit") != seed_for(1, "fit")
    assert seed_for(0, "btf", "a", "b") != seed_for(0, "btf", "a b")
    assert seed_for(0, "btf", "a", "b") != seed_for(0, "btf", "b", "a")
    assert 0 <= seed_for(123, "x", 7) < 2**32


def test_seed_for_rejects_bad_seed():
    with pytest.raises(ValueError, match="seed"):
        seed_for(-1, "fit")


@pytest.mark.parametrize("configfile", ["config/config.yaml"])
def test_every_stream_of_a_config_is_distinct(tmp_path, configfile):
    for item in ("Snakefile", "workflow", "config", "src"):
        src = ROOT / item
        (shutil.copytree if src.is_dir() else shutil.copy)(src, tmp_path / item)
    seed_log = tmp_path / "seeds.tsv"
    res = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "1", "report", "--dry-run",
                          "--configfile", configfile], cwd=tmp_path, capture_output=True,
                         text=True, env={**os.environ, "NEUMAT_SEED_LOG": str(seed_log)})
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    streams = {}
    for line in seed_log.read_text().splitlines():
        *name, seed = line.split("\t")
        streams[tuple(name)] = int(seed)
    stages = {name[0] for name in streams}
    # the stages of the default DAG that draw random numbers
    assert {"augmerl", "fit", "train_diffusion", "sample", "metrics", "mitsuba_figure",
            "btf", "train_hyperbrdf", "btf_synthesis", "conditions", "train_baseline"} <= stages, stages
    by_seed = {}
    for name, seed in streams.items():
        by_seed.setdefault(seed, []).append(name)
    clashes = {s: n for s, n in by_seed.items() if len(n) > 1}
    assert not clashes, f"streams sharing a seed: {clashes}"
