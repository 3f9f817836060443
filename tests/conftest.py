import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def one_thread():
    """Tiny models: one thread is fastest, and avoids spin-waiting on a shared 2-core box."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """config/tiny.yaml run once to its report, in a copy of the workflow (the checkout's
    results/ stay untouched); every test that needs a finished run shares it. Tests may add
    files next to it, never change its results."""
    wd = tmp_path_factory.mktemp("tiny")
    for item in ("Snakefile", "workflow", "config"):
        src = ROOT / item
        (shutil.copytree if src.is_dir() else shutil.copy)(src, wd / item)
    cmd = [sys.executable, "-m", "snakemake", "--cores", "2", "report", "--configfile",
           "config/tiny.yaml"]
    res = subprocess.run(cmd, cwd=wd, capture_output=True, text=True)
    if res.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{res.stdout[-4000:]}\n{res.stderr[-8000:]}")
    return wd
