"""Peak memory of the jobs whose Snakemake `mem_mb` is a formula of their input, against that
budget: the NeuMERL fit of an AugMERL shard (rules fit_shard and fit_template,
workflow/rules/fit.smk) and the HyperBRDF training (rule train_hyperbrdf,
workflow/rules/hyperbrdf.smk).

Each measurement runs the job script's path in a fresh Python process on synthetic shards in the
real file format (`augment.save_shard`: random positive values at random MERL bins), so its peak
RSS (VmHWM; Snakemake's benchmark files report the same as max_rss) holds imports, the shard
and what the job builds from it, and nothing from the run before:
- fit: `augment.load_shard` -> `fit.fit_many` with every material in one batch (the most a batch
  can hold: fit.materials_per_batch up to the shard) for 2 steps with an evaluation (the C
  kernel, as `fit.kernel: auto` picks it on x86). Its memory does not depend on the steps.
  The template: the same with the shard's first material alone (fit_template's path).
  `--kernel torch`: the torch step (fit.kernel: torch), whose evaluations hold activations per
  material of a batch: compare `--materials 100` and `--materials 25`.
- hyperbrdf: the rows of every shard kept at `train_bins` bins, concatenated, then
  `hyperbrdf.train` for 1 step, as workflow/scripts/train_hyperbrdf.py does.
- btf_load (`--jobs btf_load`): `neumat.btf.models.load` of a saved SH model (btf_eval loads
  every model of a material) against the way it loaded before: built zero-filled, then the
  state copied in.
- pca_a (`--jobs pca_a`): PCA-A's fit and sampling (rule baseline_pca, workflow/scripts/
  baseline_pca.py: `NielsenPCA.fit_source`, which reads the tables a block of bins at a time,
  then the draws written into one float32 array) on synthetic tables generated per block, at
  each `--pca-sizes` training tables x bins, with `--pca-ref` samples per draw and 3 draws;
  `--pca-whole` adds the fit before fit_source, on the tables held whole (`NielsenPCA.fit`,
  whose peak grew ~38 bytes a stored value), at the first size. Against common.smk
  `pca_a_mem_mb` (repeated here as pca_budget), the job's time beside it.
- diffusion (`--jobs diffusion`): a denoiser's training (rules train_diffusion, train_multimodal,
  train_refiner: workflow/rules/diffusion.smk, conditions.smk) as train_diffusion.py runs it,
  `neumat.diffusion.train` on 1920 random weight rows (the realistic training set's size), 3
  steps with a checkpoint, at each `--dn-sizes` width/depth/heads/batch (the default config's
  and paper.yaml's). Its memory does not depend on the steps or the rows (675 floats each), so
  its budget is a function of the model: common.smk `diffusion_mem_mb`, whose floor (2,500 MB)
  the script reads from the rule (`--dn-floor`).

Per size it prints the input, the peak, the RSS after imports, the growth per input unit (per MB
of shard; per material-bin), the rule's budget and the peak's fraction of that budget (the
bound: a job over it is killed by Slurm). A budget below the peak is reported as exceeded.
Over the sizes, the least-squares line of the peak against the input (the slope is what the
budget's factor must cover; at small sizes the fixed costs dominate the per-unit growth).

    python benchmarks/job_memory.py [--jobs fit hyperbrdf btf_load] [--fit-bins 131072 262144 524288]
                                    [--materials 100] [--kernel auto|c|torch]
                                    [--hb-materials 200 400] [--hb-bins 32768]
                                    [--dn-sizes 256/4/8/128 512/12/16/256]
                                    [--pca-sizes 1920x80000 1920x160000] [--pca-whole]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

MB = 2 ** 20
JOBS = ("fit", "hyperbrdf", "btf_load", "diffusion", "pca_a")


def status_mb(key: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    raise RuntimeError(f"no {key} in /proc/self/status")


def rss_mb() -> float:
    """Current resident set of this process (MB)."""
    return status_mb("VmRSS")


def peak_mb() -> float:
    """Peak resident set of this process (MB): VmHWM, the high-water mark of its own memory.
    Not ru_maxrss: Linux carries the forking parent's high-water mark over exec into it."""
    return status_mb("VmHWM")


def write_shard(path: Path, first_id: int, materials: int, bins: np.ndarray, seed: int):
    from neumat import augment
    rng = np.random.default_rng(seed)
    values = rng.gamma(1.0, 0.2, (materials, 3, len(bins))).astype(np.float32)
    augment.save_shard(path, np.arange(first_id, first_id + materials), bins, values)


# ----------------------------------------------------------------------------- children


def child_fit(shard: str, out: str, template: bool, kernel: str) -> dict:
    """fit_shard's path (workflow/scripts/fit_shard.py) with all materials in one batch, or
    fit_template's (workflow/scripts/fit_template.py): the shard's first material alone."""
    from neumat import augment, fit, nbrdf
    base = rss_mb()
    sh = augment.load_shard(shard)
    if template:
        sh = dict(sh, values=sh["values"][:1], ids=sh["ids"][:1])
    n = len(sh["ids"])
    init = np.random.default_rng(0).normal(0, 0.1, nbrdf.N_PARAMS).astype(np.float32)
    settings = fit.FitSettings(steps=2, eval_every=1, materials_per_batch=n, checkpoint_every=1,
                               kernel=kernel)
    res = fit.fit_many(sh["values"], sh["bins"], sh["ids"], init, settings, 0, "cpu",
                       checkpoint=out)
    assert res["weights"].shape == (n, nbrdf.N_PARAMS)
    return dict(imports=base, peak=peak_mb(), kernel=fit.resolve_kernel(settings, "cpu"))


def child_hyperbrdf(shards: list[str], train_bins: int, out: str) -> dict:
    """train_hyperbrdf's path (workflow/scripts/train_hyperbrdf.py), 1 step."""
    from neumat import augment
    from neumat.baselines import hyperbrdf as hb
    base = rss_mb()
    values, keep, bins = [], None, None
    for path in shards:
        sh = augment.load_shard(path)
        if keep is None:
            keep = np.sort(np.random.default_rng(0).choice(len(sh["bins"]), train_bins, replace=False))
            bins = sh["bins"][keep]
        values.append(sh["values"][:, :, keep])
        del sh
    values = np.concatenate(values)
    median = np.full(len(bins), 0.05, np.float32)
    hb.train(values, bins, median, hb.HyperConfig(), hb.HyperTrainConfig(steps=1, checkpoint_every=1),
             Path(out) / "model.pt", Path(out) / "checkpoint.pt", 0, "cpu")
    return dict(imports=base, peak=peak_mb(), materials=len(values))


def child_btf_load(path: str, plain: bool) -> dict:
    """neumat.btf.models.load of a saved model, or (`plain`) the way it loaded before 455564a:
    the model built zero-filled, then the file's state copied in."""
    import torch
    from neumat.btf import models
    from neumat.io import modelfile
    base = rss_mb()
    if plain:
        ck = modelfile.load(path)
        m = models.GRID[ck["method"]](**ck["args"])
        m.load_state_dict(ck["state"])
    else:
        m = models.load(path)
    peak = peak_mb()
    size = sum(t.numel() * t.element_size() for t in (*m.parameters(), *m.buffers())) / MB
    assert all(bool(torch.isfinite(t).all()) for t in m.buffers())
    return dict(imports=base, peak=peak, model=size)


def child_diffusion(width: int, depth: int, heads: int, batch: int, out: str) -> dict:
    """train_diffusion's path (workflow/scripts/train_diffusion.py), 3 steps, 1920 rows."""
    from neumat import nbrdf
    from neumat.diffusion import DenoiserConfig, ScheduleConfig, TrainConfig, train
    base = rss_mb()
    rng = np.random.default_rng(0)
    weights = rng.normal(0, 0.5, (1920, nbrdf.N_PARAMS)).astype(np.float32)
    labels = np.where(rng.random(1920) < 0.25, rng.integers(0, 24, 1920), -1)
    names = [f"type{i}" for i in range(24)]
    model = DenoiserConfig(width=width, depth=depth, heads=heads, n_classes=len(names))
    cfg = TrainConfig(steps=3, batch_size=batch, warmup_steps=1, checkpoint_every=2, log_every=1)
    train(weights, labels, names, model, ScheduleConfig(), cfg, Path(out) / "model.pt",
          Path(out) / "checkpoint.pt", 0, "cpu")
    return dict(imports=base, peak=peak_mb(), params=diffusion_params(width, depth))


def _synthetic_tables(n: int, sl: slice) -> np.ndarray:
    """(n, 3, len) positive tables at bins sl.start ... sl.stop - 1, the same for the same bin
    whatever the block (a generator per bin would be slow: a fixed pattern of materials x bins,
    scaled per bin)."""
    bins = np.arange(sl.start, sl.stop)
    mat = np.random.default_rng(0).gamma(1.0, 0.2, (n, 3, 1)).astype(np.float32)
    wave = (1.1 + np.sin(np.outer(np.arange(1, n + 1), bins * 1e-3)))[:, None, :]
    return (mat * wave * (1 + (bins % 7) / 7)).astype(np.float32)


def child_pca_a(n: int, nbins: int, ref: int, whole: bool) -> dict:
    """baseline_pca's path for PCA-A (32 components, 3 draws of `ref`)."""
    import time
    from neumat.baselines import pca
    from neumat.io import merl
    base = rss_mb()
    t0 = time.perf_counter()
    bins = np.flatnonzero(merl.valid_mask())[:nbins]
    f = pca.NielsenPCA(32, bins)
    if whole:
        f.fit(_synthetic_tables(n, slice(0, nbins)))
    else:
        f.fit_source(lambda sl: _synthetic_tables(n, sl), n)
    values = np.zeros((3 * ref, 3, nbins), dtype=np.float32)
    for i in range(3):
        values[i * ref:(i + 1) * ref] = f.sample(ref, i)
    return dict(imports=base, peak=peak_mb(), seconds=time.perf_counter() - t0,
                explained=float(f.pca.explained))


def diffusion_params(width: int, depth: int) -> int:
    """Parameters of a Denoiser (counted on the meta device: no memory)."""
    import torch
    from neumat.diffusion import DenoiserConfig
    from neumat.diffusion.model import Denoiser
    with torch.device("meta"):
        m = Denoiser(DenoiserConfig(width=width, depth=depth, n_classes=24))
    return sum(p.numel() for p in m.parameters())


def run_child(args: list[str]) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    r = subprocess.run([sys.executable, __file__, "--child", json.dumps(args)], env=env,
                       capture_output=True, text=True)
    if r.returncode:
        sys.exit(f"child {args[0]} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- parent


def fit_budget(shard_mb: float, kernel: str, materials: int) -> float:
    """mem_mb of rule fit_shard (workflow/rules/fit.smk, FIT_MEM_EVAL) at config fit.kernel
    `kernel`, `materials` a batch."""
    return 1000 + 2.5 * shard_mb + (0 if kernel == "c" else 13 * materials)


def template_budget(shard_mb: float) -> float:
    """mem_mb of rule fit_template."""
    return 1000 + 2 * shard_mb


def hb_budget(shard_mb: float, shards: int, materials: int, train_bins: int) -> float:
    """mem_mb of rule train_hyperbrdf (workflow/rules/hyperbrdf.smk); shard_mb: all shards."""
    return 2000 + 2 * shard_mb // shards + 26 * materials * train_bins // MB


def dn_budget(width: int, depth: int, floor: int) -> float:
    """mem_mb of rules train_diffusion / train_multimodal / train_refiner (common.smk
    diffusion_mem_mb, the same formula: keep the two in step)."""
    params = 12 * depth * width ** 2 + 150_000
    return max(floor, int(1.5 * (610 + 51e-6 * params)))


def bench_diffusion(tmp: Path, sizes: list[str], floor: int):
    print("diffusion: a denoiser's training on 1920 rows, 3 steps with a checkpoint, one thread, "
          "a fresh process each")
    print(f"{'width/depth/heads/batch':>24s} {'params':>10s} {'peak MB':>8s} {'imports':>8s} "
          f"{'B/param':>8s} {'budget':>7s} {'of it':>6s}")
    rows = []
    for size in sizes:
        w, d, h, b = (int(x) for x in size.split("/"))
        r = run_child(["diffusion", w, d, h, b, str(tmp)])
        budget = dn_budget(w, d, floor)
        rows.append((r["params"], r["peak"]))
        print(f"{size:>24s} {r['params']:10d} {r['peak']:8.0f} {r['imports']:8.0f} "
              f"{(r['peak'] - r['imports']) * MB / r['params']:8.1f} {budget:7.0f} "
              f"{r['peak'] / budget:6.2f}" + ("  EXCEEDED" if r["peak"] > budget else ""))
    if len(rows) >= 2:
        x, y = np.array(rows, dtype=float).T
        slope, icpt = np.polyfit(x, y, 1)
        print(f"diffusion: peak = {icpt:.0f} MB + {slope * MB:.1f} bytes per parameter (least "
              f"squares over {len(rows)} sizes); budgeted max({floor}, 1.5 x (610 MB + 51 bytes "
              "per parameter))")


def pca_budget(n: int, nbins: int, ref: int, components: int = 32) -> float:
    """mem_mb of rule baseline_pca for PCA-A (common.smk pca_a_mem_mb, the same formula)."""
    rows = 3 * n
    return 1500 + (4 * 8 * rows ** 2 + 8 * (components + 4) * nbins
                   + 4 * 3 * 3 * ref * nbins * 2) / MB


def bench_pca_a(sizes: list[str], ref: int, whole: bool):
    print(f"pca_a: fit_source on synthetic tables, 32 components, 3 draws x {ref}, one thread, "
          "a fresh process each")
    print(f"{'tables x bins':>16s} {'peak MB':>8s} {'imports':>8s} {'seconds':>8s} "
          f"{'budget':>7s} {'of it':>6s}")
    for i, size in enumerate(sizes):
        n, nbins = (int(x) for x in size.split("x"))
        runs = [("fit_source", False)] + ([("whole (before)", True)] if whole and i == 0 else [])
        for name, w in runs:
            r = run_child(["pca_a", n, nbins, ref, w])
            budget = pca_budget(n, nbins, ref)
            print(f"{size:>16s} {r['peak']:8.0f} {r['imports']:8.0f} {r['seconds']:8.1f} "
                  f"{budget:7.0f} {r['peak'] / budget:6.2f}  {name}, explained {r['explained']:.4f}"
                  + ("  EXCEEDED" if r["peak"] > budget and not w else ""))


def bench_fit(tmp: Path, materials: int, sizes: list[int], kernel: str):
    from neumat.io import merl
    rows = []
    print(f"fit_shard: {materials} materials in one batch, 2 steps with an evaluation; fit_template: "
          "the first alone; a fresh process each")
    print(f"{'bins':>8s} {'shard MB':>9s} {'peak MB':>8s} {'imports':>8s} {'(peak-imp)/shard':>17s} "
          f"{'budget':>7s} {'of it':>6s} {'template peak':>14s} {'(peak-imp)/shard':>17s} "
          f"{'budget':>7s} {'of it':>6s}")
    for i, b in enumerate(sizes):
        rng = np.random.default_rng(i)
        bins = np.sort(rng.choice(merl.N_BINS, b, replace=False))
        shard = tmp / f"fit_{b}.npz"
        write_shard(shard, 0, materials, bins, i)
        mb = shard.stat().st_size / MB
        r = run_child(["fit", str(shard), str(tmp / f"fit_{b}.ckpt.npz"), False, kernel])
        t = run_child(["fit", str(shard), str(tmp / f"template_{b}.ckpt.npz"), True, kernel])
        shard.unlink()
        bs, bt = fit_budget(mb, kernel, materials), template_budget(mb)
        rows.append((mb, r["peak"]))
        print(f"{b:8d} {mb:9.0f} {r['peak']:8.0f} {r['imports']:8.0f} "
              f"{(r['peak'] - r['imports']) / mb:17.2f} {bs:7.0f} {r['peak'] / bs:6.2f} "
              f"{t['peak']:14.0f} {(t['peak'] - t['imports']) / mb:17.2f} {bt:7.0f} "
              f"{t['peak'] / bt:6.2f}" + ("  EXCEEDED" if r["peak"] > bs or t["peak"] > bt else "")
              + f"  (kernel {r['kernel']})")
    if len(rows) >= 2:
        x, y = np.array(rows).T
        slope, icpt = np.polyfit(x, y, 1)
        print(f"fit: peak = {icpt:.0f} MB + {slope:.2f} x the shard (least squares over "
              f"{len(rows)} sizes); fit_shard budget 1000 + 2.5 x"
              + ("" if kernel == "c" else f" + 13 MB x {materials} materials (fit.kernel {kernel})"))


def bench_hyperbrdf(tmp: Path, materials: list[int], train_bins: int, shard_bins: int):
    from neumat.io import merl
    bins = np.sort(np.random.default_rng(9).choice(merl.N_BINS, shard_bins, replace=False))
    print(f"hyperbrdf: shards of 100 materials x {shard_bins} bins, {train_bins} train_bins, 1 step, "
          "a fresh process each")
    rows = []
    print(f"{'materials':>9s} {'shards MB':>10s} {'peak MB':>8s} {'imports':>8s} "
          f"{'B/material-bin':>15s} {'budget':>7s} {'of it':>6s}")
    for m in materials:
        shards = []
        for k in range(0, m, 100):
            p = tmp / f"hb_{m}_{k}.npz"
            write_shard(p, k, min(100, m - k), bins, k)
            shards.append(p)
        mb = sum(p.stat().st_size for p in shards) / MB
        r = run_child(["hyperbrdf", [str(p) for p in shards], train_bins, str(tmp)])
        for p in shards:
            p.unlink()
        per = (r["peak"] - r["imports"]) * MB / (m * train_bins)
        budget = hb_budget(mb, len(shards), m, train_bins)
        rows.append((m * train_bins, r["peak"]))
        print(f"{m:9d} {mb:10.0f} {r['peak']:8.0f} {r['imports']:8.0f} {per:15.1f} {budget:7.0f} "
              f"{r['peak'] / budget:6.2f}" + ("  EXCEEDED" if r["peak"] > budget else ""))
    if len(rows) >= 2:
        x, y = np.array(rows).T
        slope, icpt = np.polyfit(x, y, 1)
        print(f"hyperbrdf: peak = {icpt:.0f} MB + {slope * MB:.1f} bytes per material-bin (least "
              f"squares over {len(rows)} sizes); budgeted 26 bytes per material-bin")


def bench_btf_load(tmp: Path, side: int):
    """Peak growth of loading an SH model of a side x side crop (the paper's whole BTF: 400)."""
    import torch
    from neumat.btf import models
    from neumat.btf.classical import SH
    from neumat.btf.directions import to_cartesian, ubo2014_angles
    d = to_cartesian(ubo2014_angles())
    m = SH(side, side, d, d)
    m.coef.normal_(generator=torch.Generator().manual_seed(0))
    path = tmp / "sh.pt"
    models.save(m, path)
    del m
    new, old = (run_child(["btf_load", str(path), plain]) for plain in (False, True))
    print(f"btf_eval's model load: SH of a {side} x {side} crop ({new['model']:.0f} MB), "
          "a fresh process each")
    for name, r in (("models.load (meta device, assign)", new),
                    ("built zero-filled, state copied in", old)):
        print(f"  {name:36s} peak growth {r['peak'] - r['imports']:7.0f} MB = "
              f"{(r['peak'] - r['imports']) / r['model']:.2f} x the model")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--jobs", nargs="+", default=list(JOBS), choices=JOBS)
    ap.add_argument("--materials", type=int, default=100, help="fit: materials in the shard")
    ap.add_argument("--kernel", default="auto", choices=["auto", "c", "torch"],
                    help="fit: the step on the CPU (fit.kernel; auto: the C kernel on x86)")
    ap.add_argument("--fit-bins", type=int, nargs="+", default=[131072, 262144, 524288],
                    help="fit: stored bins per material, one shard per value")
    ap.add_argument("--hb-materials", type=int, nargs="+", default=[200, 400],
                    help="hyperbrdf: training materials, one run per value")
    ap.add_argument("--btf-side", type=int, default=200,
                    help="btf_load: the SH model's crop side (400: a whole UBO2014 BTF, 2.4 GB)")
    ap.add_argument("--hb-bins", type=int, default=32768, help="hyperbrdf: train_bins")
    ap.add_argument("--dn-sizes", nargs="+", default=["256/4/8/128", "512/12/16/256"],
                    help="diffusion: width/depth/heads/batch (config/config.yaml's, paper.yaml's)")
    ap.add_argument("--pca-sizes", nargs="+", default=["1920x80000", "1920x160000"],
                    help="pca_a: training tables x bins (the default config's: 1920 x ~80,000)")
    ap.add_argument("--pca-ref", type=int, default=480, help="pca_a: samples a draw")
    ap.add_argument("--pca-whole", action="store_true",
                    help="pca_a: also the fit on tables held whole, at the first size")
    ap.add_argument("--dn-floor", type=int, default=2500,
                    help="diffusion: diffusion_mem_mb's floor (train_diffusion's; 3000 for "
                         "train_multimodal and train_refiner)")
    ap.add_argument("--hb-shard-bins", type=int, default=65536, help="hyperbrdf: bins the shards store")
    a = ap.parse_args()
    if a.child:
        kind, *rest = json.loads(a.child)
        out = {"fit": child_fit, "hyperbrdf": child_hyperbrdf, "btf_load": child_btf_load,
               "diffusion": child_diffusion, "pca_a": child_pca_a}[kind](*rest)
        print(json.dumps(out))
        return
    if a.hb_bins > a.hb_shard_bins:
        ap.error("--hb-bins must not exceed --hb-shard-bins")
    from neumat import machine
    import torch
    print(f"machine: {machine.describe()}; torch {torch.__version__}, "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '1 (set by this script)')}")
    with tempfile.TemporaryDirectory(prefix="job_memory_") as d:
        if "fit" in a.jobs:
            bench_fit(Path(d), a.materials, a.fit_bins, a.kernel)
        if "btf_load" in a.jobs:
            bench_btf_load(Path(d), a.btf_side)
        if "hyperbrdf" in a.jobs:
            bench_hyperbrdf(Path(d), a.hb_materials, a.hb_bins, a.hb_shard_bins)
        if "diffusion" in a.jobs:
            bench_diffusion(Path(d), a.dn_sizes, a.dn_floor)
        if "pca_a" in a.jobs:
            bench_pca_a(a.pca_sizes, a.pca_ref, a.pca_whole)


if __name__ == "__main__":
    main()
