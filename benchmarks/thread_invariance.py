"""Which results depend on the thread keys (config/speed_keys.yaml: speed-only, so changing one
reruns nothing): the tiny config run twice in temporary copies of the workflow, once as shipped
(every `*.threads` 1) and once with every `*.threads` 2, then compared file by file.

    python benchmarks/thread_invariance.py                 # two fresh tiny runs (~7 min on 2 cores)
    python benchmarks/thread_invariance.py --runs A B      # compare two finished results/<run> dirs

Prints, per differing file, the largest absolute difference of its arrays (.npy, .npz, .pt);
logs, benchmarks, the report and timing columns are expected to differ and are left out. The
baseline is the run with one thread: the figures are how far two threads move each output."""
import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import yaml

from neumat import machine

ROOT = Path(__file__).resolve().parents[1]
SECTIONS = ("fit", "diffusion", "hyperbrdf", "conditions", "baselines", "btf")
SKIP = ("logs/", "benchmarks/", "report/")


def tiny_run(wd: Path, threads: int) -> Path:
    for item in ("Snakefile", "workflow", "config"):
        (shutil.copytree if (ROOT / item).is_dir() else shutil.copy)(ROOT / item, wd / item)
    cfg = yaml.safe_load((ROOT / "config/tiny.yaml").read_text())
    for s in SECTIONS:
        cfg.setdefault(s, {})["threads"] = threads
    (wd / "config/threads.yaml").write_text(yaml.safe_dump(cfg))
    res = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "report",
                          "--configfile", "config/threads.yaml"], cwd=wd, capture_output=True,
                         text=True)
    if res.returncode:
        sys.exit(f"the tiny run with {threads} thread(s) failed:\n{res.stderr[-4000:]}")
    print(f"tiny run, every *.threads {threads}: done", flush=True)
    return wd / "results" / cfg["run"]


def _diff(a, b, key="") -> list[tuple[str, float]]:
    """(key, max |a - b|) of the tensors/arrays that differ, walking dicts and lists."""
    if isinstance(a, (torch.Tensor, np.ndarray)):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape:
            return [(key, float("inf"))]
        if a.dtype.kind not in "fiub" or a.size == 0:
            return [] if np.array_equal(a, b) else [(key, float("nan"))]
        d = float(np.abs(a.astype(np.float64) - b.astype(np.float64)).max())
        return [(key, d)] if d else []
    if isinstance(a, dict):
        return [x for k in a if not str(k).endswith("seconds")  # wall times, not results
                for x in _diff(a[k], b.get(k), f"{key}.{k}")]
    if isinstance(a, (list, tuple)):
        return [x for i, (p, q) in enumerate(zip(a, b)) for x in _diff(p, q, f"{key}[{i}]")]
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return [] if a == b else [(key, abs(float(a) - float(b)))]
    return [] if a == b else [(key, float("nan"))]


def _load(path: Path):
    if path.suffix == ".npy":
        return np.load(path)
    if path.suffix == ".npz":
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    if path.suffix == ".pt":
        return torch.load(path, weights_only=True)
    return None


def compare(a: Path, b: Path) -> None:
    same, rows = 0, []
    for f in sorted(p for p in a.rglob("*") if p.is_file()):
        rel = f.relative_to(a).as_posix()
        g = b / rel
        if rel.startswith(SKIP) or not g.exists():
            continue
        if f.read_bytes() == g.read_bytes():
            same += 1
            continue
        x = _load(f)
        if x is None:  # tables, images: a byte difference only
            rows.append((rel, "bytes differ"))
            continue
        d = _diff(x, _load(g))
        if not d:
            same += 1  # only a timing entry or the pickle's framing differs
            continue
        key, worst = max(d, key=lambda kd: kd[1] if kd[1] == kd[1] else -1.0)  # nan: not numbers
        rows.append((rel, f"max |diff| {worst:.3g} ({len(d)} arrays; largest in {key or 'it'})"))
    print(f"{same} files the same, {len(rows)} differ:")
    for rel, what in rows:
        print(f"  {rel}: {what}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs=2, type=Path, metavar=("ONE", "TWO"),
                    help="results/<run> dirs to compare instead of running the tiny config")
    args = ap.parse_args()
    print(f"machine: {machine.describe()}; torch {torch.__version__}", flush=True)
    if args.runs:
        compare(*args.runs)
        return
    with tempfile.TemporaryDirectory() as d1, tempfile.TemporaryDirectory() as d2:
        compare(tiny_run(Path(d1), 1), tiny_run(Path(d2), 2))


if __name__ == "__main__":
    main()
