"""Workflow smoke test: config/tiny.yaml end to end, plus DAG-time config errors.

The workflow runs in a copy of the repository's workflow files in a temporary directory, so the
test never touches results/ of the checkout."""

import os
import re
import shutil
import signal
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


# ----------------------------------------------------------------------------- interrupted runs
# first of this module's tests on the tiny run: the longest, so xdist's last worker is not
# left alone with it at the end

NEUMERL = "results/tiny/neumerl/weights.npy"
SAME_BYTES = ["neumerl/weights.npy", "neumerl/fits.tsv", "neumerl/manifest.tsv"]


def _job_processes(wd: Path, names=("",)) -> list[int]:
    """Live (not zombie) processes running a job script of the workflow in `wd`."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            state = (proc / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if f"{wd}/.snakemake/scripts/" in cmd and state != "Z" and any(n in cmd for n in names):
            pids.append(int(proc.name))
    return pids


def _interrupt_during_fit(wd: Path, sig: int, *args):
    """Start snakemake towards NeuMERL, send `sig` once a fit job runs; return after it exits.
    SIGINT goes to the process group, as Ctrl-C in a terminal sends it (sent to snakemake alone,
    it lets its running jobs finish). Snakemake starts with SIGINT's default action: a process
    started with SIGINT ignored (pytest run as a background job of a script, or under nohup)
    passes that on, Python then installs no KeyboardInterrupt handler, and the run went on to
    its end ("no fit job started" in the SIGKILL case). SIGKILL goes to snakemake alone: its
    jobs must die with it (`neumat.logs.die_with_parent`)."""
    import time
    default_sigint = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
                      "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])")
    cmd = [sys.executable, "-c", default_sigint, "-m", "snakemake", "--cores", "2", NEUMERL, *args,
           "--configfile", "config/tiny.yaml"]
    log = wd / f"interrupted.{sig.name}.log"
    with open(log, "w") as out:
        smk = subprocess.Popen(cmd, cwd=wd, stdout=out, stderr=subprocess.STDOUT, process_group=0)
    try:
        deadline = time.time() + 600
        while not _job_processes(wd, ("fit_template.py", "fit_shard.py")):
            assert smk.poll() is None and time.time() < deadline, \
                f"no fit job started (snakemake ended {smk.poll()}):\n" + "\n".join(
                    f"--- {f.name}\n{f.read_text()[-3000:]}" for f in sorted(wd.glob("interrupted.*.log")))
            time.sleep(0.2)
        time.sleep(1.0)  # inside the fit
        if sig == signal.SIGINT:
            os.killpg(smk.pid, sig)
        else:
            smk.send_signal(sig)
        smk.wait(timeout=120)
    finally:
        if smk.poll() is None:
            smk.kill()
    for _ in range(100):  # the kernel signals the jobs at once; give them 10 s to exit
        if not _job_processes(wd):
            break
        time.sleep(0.1)
    return _job_processes(wd)


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="jobs die with snakemake via "
                    "prctl(PR_SET_PDEATHSIG), Linux only")
def test_interrupted_run_leaves_no_jobs_and_resumes_identically(tiny_run, tmp_path):
    """SIGINT, then SIGKILL, of snakemake while a fit runs: no job survives, and the README's
    resume commands ("When a run is interrupted") give the uninterrupted run's bytes. The SIGINT
    case is resumed with `--rerun-incomplete` and killed again in its fit, so one resume to the
    end serves both cases (the fits are most of this test's CPU)."""
    wd = _copy_workflow(tmp_path)
    # the tiny run's MERL tables and AugMERL shards, linked (their mtimes kept): only the fits
    # and what follows them run here
    for stage in ("merl", "augmerl"):
        shutil.copytree(tiny_run / "results/tiny" / stage, wd / "results/tiny" / stage,
                        copy_function=os.link)
    assert _interrupt_during_fit(wd, signal.SIGINT) == []
    # the README's resume after Ctrl-C; SIGKILL: snakemake cannot clean up, its jobs still die,
    # the lock stays behind
    assert _interrupt_during_fit(wd, signal.SIGKILL, "--rerun-incomplete") == []
    _snakemake(wd, NEUMERL, "--unlock", "--configfile", "config/tiny.yaml")
    _snakemake(wd, NEUMERL, "--rerun-incomplete", "--configfile", "config/tiny.yaml")
    for f in SAME_BYTES:
        assert (wd / "results/tiny" / f).read_bytes() == (tiny_run / "results/tiny" / f).read_bytes(), f


# tiny_run (conftest.py): the tiny config run once to its report, shared with other modules


@pytest.mark.slow
def test_tiny_config_runs_to_report(tiny_run):
    rep = tiny_run / "results/tiny/report"
    html = (rep / "index.html").read_text()
    md = (rep / "index.md").read_text()
    assert "<table>" in html and "AugMERL" in md
    # every figure is followed by its report() caption (as in `snakemake --report`)
    figures = re.findall(r"^!\[[^\]]*\]\(figures/[^)]+\)\n\n(.*)$", md, re.M)
    assert len(figures) >= 20 and all(c.startswith("> ") and len(c) > 80 for c in figures), figures
    for img in ("augmerl_permutations.png", "augmerl_interpolation.png"):
        assert (rep / "figures" / img).stat().st_size > 1000
    man = pd.read_csv(tiny_run / "results/tiny/augmerl/manifest.tsv", sep="\t",
                      keep_default_na=False)
    assert len(man) == 64 and set(man["split"]) == {"train", "test"}
    # every rule logged and benchmarked
    assert list((tiny_run / "results/tiny/logs").rglob("*.log"))
    assert (tiny_run / "results/tiny/benchmarks/augmerl_pca.tsv").exists()
    # the jobs' idle OpenMP threads sleep (common.smk), unless the user's environment (which
    # the tiny run inherits) says otherwise: a 2-thread job's log
    log = (tiny_run / "results/tiny/logs/metrics/ours.log").read_text()
    user = {k: os.environ[k] for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT") if k in os.environ}
    policy = user.get("OMP_WAIT_POLICY", "unset" if "GOMP_SPINCOUNT" in user else "PASSIVE")
    assert (f"threads 2, OMP_WAIT_POLICY={policy}, "
            f"GOMP_SPINCOUNT={user.get('GOMP_SPINCOUNT', 'unset')}") in log


@pytest.mark.slow
def test_tiny_config_runs_every_stage(tiny_run):
    res = tiny_run / "results/tiny"
    md = (res / "report/index.md").read_text()
    for section in ("NeuMERL", "Rendering", "Hyperdiffusion", "Table 2", "Table 3", "Triple Plane"):
        assert section in md, section
    w = np.load(res / "neumerl/weights.npy")
    assert w.shape == (64, 675) and w.dtype == np.float32 and np.isfinite(w).all()
    fits = pd.read_csv(res / "neumerl/fits.tsv", sep="\t")
    assert {"id", "name", "train_loss", "val_loss", "render_psnr"} <= set(fits.columns)
    assert (res / "neumerl/merl/mix0000.binary").stat().st_size == 34_992_012
    table = pd.read_csv(res / "metrics/table2.csv", index_col=[0, 1])
    assert list(table.columns) == ["Training set", "PCA-A", "PCA-N", "VAE-A", "VAE-N",
                                   "MERL100", "ours"]
    assert len(table) == 14  # FID 2048-d and 64-d + 3 metrics x 4 distances
    assert table.notna().all().all() and not (table == "n/a").any().any()  # FID filled
    assert table.map(lambda c: "±" in c).all().all()  # mean ± std over draws
    draws = pd.read_csv(res / "metrics/pca_a.csv")
    assert draws["draw"].nunique() >= 2 and (draws["metric"] == "FID").sum() == 2 * draws["draw"].nunique()
    assert "Sanity rows" in md
    # the clamp refit ran (config/tiny.yaml refit_steps 2) after the clamp step, and the
    # section says so; ours_plain is drawn without both
    timing = pd.read_csv(res / "samples/ours/timing.tsv", sep="\t").iloc[0]
    assert timing["refit_steps"] == 2 and timing["negative_step"] > 0
    plain = pd.read_csv(res / "samples/ours_plain/timing.tsv", sep="\t").iloc[0]
    assert plain["refit_steps"] == 0 and plain["negative_step"] == 0
    assert "Clamp-aware refit" in (res / "report/sections/40_diffusion.md").read_text()
    # novelty relative to the nearest's mean value: one scale per nearest training material
    near = pd.concat([pd.read_csv(res / f"samples/{s}/nearest.tsv", sep="\t")
                      for s in ("reference", "ours", "ours_type")])
    near = near[near["brdf_l1"] > 1e-3]
    scale = (near["brdf_l1"] / near["relative_l1"]).groupby(near["nearest_id"])
    assert near["nearest_id"].duplicated().any() and (scale.max() / scale.min() < 1 + 1e-4).all()
    assert scale.max().nunique() > 1  # each material's own mean, not one constant
    assert "relative to the nearest's mean value" in (res / "report/sections/40_diffusion.md").read_text()
    # finished: no draw kept for a resume, no training checkpoint left beside its model
    assert not list(res.rglob("draws.partial")), list(res.rglob("draws.partial"))
    assert not list((res / "baselines").rglob("checkpoint.pt"))
    assert not (res / "conditions/image_encoder_checkpoint.pt").exists()
    # ...but the long trainings keep their final checkpoint (a rerun of a finished job that
    # Snakemake marked incomplete resumes there: README, "When a run is interrupted")
    assert (res / "diffusion/ours/checkpoint.final.pt").is_file()
    assert not (res / "diffusion/ours/checkpoint.pt").exists()
    q = pd.read_csv(res / "btf/quality.tsv", sep="\t")
    assert len(q) > 0
    assert "Dynamic synthesis on the positional plane" in md
    syn = pd.read_csv(res / "btf_synthesize/synthesis.tsv", sep="\t")
    assert {"tiling", "linear", "hpb", "hextile", "quilting"} <= set(syn["method"])
    assert (syn[syn.method == "tiling"]["acf"] > 0.99).all()
    r2 = syn[syn.method == "hextile"]["lum_r2"]  # its luminance's linear fit, in the report
    assert len(r2) > 0 and ((r2 > 0) & (r2 <= 1)).all() and "R^2 of that fit" in md
    t3 = pd.read_csv(res / "hyperbrdf/table3.csv")
    assert list(t3["method"]) == ["mean training material", "HyperBRDF (merl)",
                                  "HyperBRDF (augmerl)", "NeuMERL fit"]
    assert t3.shape == (4, 7) and np.isfinite(t3.iloc[:, 1:].to_numpy(float)).all()


@pytest.mark.slow
def test_tiny_constrained_synthesis_and_cli(tiny_run, tmp_path):
    res = tiny_run / "results/tiny"
    rules = pd.read_csv(res / "constrained/rules.tsv", sep="\t")
    assert {"e", "metallic_exceptions", "mirror_peak", "plastic_sharpness"} <= set(rules["threshold"])
    classes = pd.read_csv(res / "constrained/classes.tsv", sep="\t", keep_default_na=False)
    assert (classes["set"] == "neumerl").sum() == 64 and (classes["set"] == "source").sum() == 8
    acc = pd.read_csv(res / "constrained/acceptance.tsv", sep="\t")
    assert len(acc) == 7 and (acc["drawn"] <= 16).all()
    pilots = acc.set_index("category")["pilot"]  # category guidance piloted where it exists
    # type guidance only with types some training material has (the others never trained)
    from neumat import constrained
    man = pd.read_csv(res / "neumerl/manifest.tsv", sep="\t", keep_default_na=False)
    trained = set(man.loc[man["split"] == "train", "type"]) - {""}
    src = classes[classes["set"] == "source"]
    log = (res / "logs/sample_constrained.log").read_text()
    for cat, types in constrained.category_types(src["type"], src["category"]).items():
        left = sorted(set(types) - trained)
        assert (f"{cat}: guide types {', '.join(left)} left out" in log) == bool(left), cat
        assert not any(t in pilots[cat].split("type: ")[-1].split(": ")[0].split(", ")
                       for t in left), (cat, pilots[cat])
    assert all("category guidance" in pilots[c] for c in ("diffuse", "metallic"))
    assert not any("category guidance" in pilots[c] for c in ("mirror", "plastic"))
    samples = pd.read_csv(res / "samples/constrained/samples.tsv", sep="\t")
    assert len(np.load(res / "samples/constrained/weights.npy")) == len(samples)
    assert samples.groupby("category").size().to_dict() == \
        acc.set_index("category")["accepted"][lambda a: a > 0].to_dict()
    md = (res / "report/index.md").read_text()
    assert "Constrained synthesis" in md
    # the command on the tiny run's output
    cli = [sys.executable, "-m", "neumat.cli"]
    out = tmp_path / "cli"
    r = subprocess.run([*cli, "sample", "--run", str(res), "-n", "1", "--steps", "5",
                        "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (out / "sample_000.binary").stat().st_size == 34_992_012
    assert (out / "scene.xml").exists() and (out / "sample_000.png").exists()
    r = subprocess.run([*cli, "info", str(res)], capture_output=True, text=True)
    assert r.returncode == 0 and "seed 0" in r.stdout and "constrained acceptance" in r.stdout


@pytest.mark.slow
def test_tiny_config_runs_text_and_image_conditioning(tiny_run):
    res = tiny_run / "results/tiny"
    assert "Multi-modal conditioning" in (res / "report/index.md").read_text()
    man = pd.read_csv(res / "neumerl/manifest.tsv", sep="\t", keep_default_na=False)
    assert np.load(res / "conditions/text.npy").shape == (len(man), 384)
    prompts = pd.read_csv(res / "conditions/prompts.tsv", sep="\t", keep_default_na=False)
    assert {"test", "unseen"} == set(prompts["kind"]) and "red plastic" in set(prompts["prompt"])
    # in_training: word for word a training description (as embedded), scored apart below
    train_desc = set(man.loc[man["split"] == "train", "description"])
    assert prompts["in_training"].tolist() == [q in train_desc for q in prompts["prompt"]]
    for s, n in (("text", 2 * len(prompts)), ("image", 2 * 3)):  # 2 test renders + 1 user PNG
        w = np.load(res / f"samples/{s}/weights.npy")
        assert w.shape == (n, 675) and np.isfinite(w).all(), s
    t = pd.read_csv(res / "samples/image/samples.tsv", sep="\t", keep_default_na=False)
    assert "config/tiny_reference.png" in set(t["source"])
    log = (res / "logs/sample_image.log").read_text()
    assert "render guidance, step 1, toward 3 conditioning images" in log
    # best of 3 (conditions.image.candidates 2 + unconstrained_candidates 1): each kept draw
    # named, the best of its three; per image 2 x 2 constrained draws first, then 2 without
    assert "best of 3: kept 6 of 18 draws by render PSNR" in log
    assert "of the 6 kept draws (6 of all 18) without the clamp constraint" in log
    assert set(t["candidate"]) <= set(range(6)) and t["render_psnr"].notna().all()
    assert (t["constrained"] == (t["candidate"] < 4)).all()
    summary = pd.read_csv(res / "conditions/eval_summary.tsv", sep="\t")
    assert {"text", "image", "mm_type", "mm_uncond", "text (unseen prompts)",
            "text (test descriptions, none a training description)"} <= set(summary["set"])
    per = pd.read_csv(res / "conditions/eval_per_sample.tsv", sep="\t", keep_default_na=False)
    held = per[(per["set"] == "text") & (per["kind"] == "unseen")
               & ~per["prompt"].isin(set(prompts.loc[prompts["in_training"], "prompt"]))]
    assert summary.set_index("set").loc["text (unseen prompts)", "samples"] == len(held)
    # the image yardsticks: one row per test render (not the user's PNG)
    yard = summary.set_index("set").loc[["image: the conditioning materials themselves",
                                         "image: retrieval"]]
    assert (yard["samples"] == 2).all()
    sweep = pd.read_csv(res / "conditions/guidance_sweep.tsv", sep="\t")
    assert set(sweep["modality"]) == {"type", "text", "image"}
    for f in ("conditions_text.png", "conditions_image.png", "conditions_guidance.png"):
        assert (res / "report/figures" / f).stat().st_size > 1000


@pytest.mark.slow
def test_tiny_cli_samples_text_and_image(tiny_run, tmp_path):
    """`neumat sample --text / --image` on the tiny run's multimodal model and image encoder:
    N finite samples, the same for the same seed, the conditions and the run's guidance recorded."""
    res = tiny_run / "results/tiny"

    def sample(out, *args):
        r = subprocess.run([sys.executable, "-m", "neumat.cli", "sample", "--run", str(res), "-n", "3",
                            "--steps", "5", "--no-binary", "--out", str(tmp_path / out), *args],
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        w = np.load(tmp_path / out / "weights.npy")
        assert w.shape == (3, 675) and np.isfinite(w).all()
        return w, pd.read_csv(tmp_path / out / "samples.tsv", sep="\t", keep_default_na=False)

    a, t = sample("a", "--text", "red plastic", "--seed", "3")
    b, _ = sample("b", "--text", "red plastic", "--seed", "3")
    np.testing.assert_array_equal(a, b)
    assert set(t["model"]) == {"multimodal"} and set(t["text"]) == {"red plastic"}
    assert set(t["guidance_text"]) == {2.0}  # conditions.guidance.text of the run's config
    ref = str(tiny_run / "config/tiny_reference.png")
    i, t = sample("i", "--image", ref, "--type", "fabric", "--guidance", "type=1")
    assert set(t["image"]) == {ref} and set(t["guidance_type"]) == {1.0}
    assert len(list((tmp_path / "i").glob("sample_*.png"))) == 3
    r = subprocess.run([sys.executable, "-m", "neumat.cli", "info", str(res)], capture_output=True, text=True)
    assert r.returncode == 0 and "conditions: type, text, image" in r.stdout
    assert "conditions/image_encoder.pt" in r.stdout


@pytest.mark.slow
def test_rerun_is_a_no_op(tiny_run):
    res = _snakemake(tiny_run, "report", "--dry-run", "--configfile", "config/tiny.yaml")
    assert "Nothing to be done" in res.stdout + res.stderr


@pytest.mark.slow
def test_snakemake_report(tiny_run):
    """README's `snakemake --report report.html`, on the finished tiny run."""
    _snakemake(tiny_run, "--report", "report.html", "--configfile", "config/tiny.yaml")
    assert (tiny_run / "report.html").stat().st_size > 10_000


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
    text = res.stderr + res.stdout
    assert res.returncode != 0
    # the key and the reason, not a traceback that merely passes through seed_for
    assert "bad config (seed): 'abc' is not of type 'integer'" in text, text[-3000:]
    assert len(text.splitlines()) < 15, text[-3000:]


@pytest.mark.slow
def test_tiny_run_used_the_fast_mitsuba_variant(tiny_run):
    """Every Mitsuba figure of the tiny run used llvm_ad_rgb when a libLLVM can be loaded (the
    karellen-llvm-core wheel is a dependency): scalar_rgb there costs minutes of the tiny run."""
    import json
    from neumat.render import mitsuba_bsdf as mb
    infos = sorted((tiny_run / "results/tiny/render/mitsuba").glob("*.json"))
    assert infos
    expect = "llvm_ad_rgb" if mb.find_libllvm() else "scalar_rgb"
    for f in infos:
        assert json.loads(f.read_text())["variant"] == expect, f
    # the reference figures show distinct sources, not one source's RGB permutations (the
    # two-material plane had mixed gray-acrylic with gray-acrylic@rbg)
    plane = json.loads((tiny_run / "results/tiny/render/mitsuba/mixed_plane.json").read_text())
    sources = [m.split("#")[0].split("@")[0] for m in plane["materials"]]
    assert len(sources) >= 2 and len(set(sources)) == len(sources), plane["materials"]


# ----------------------------------------------------------------------------- caching

# jobs that compute results (augmerl_figures, a report figure, is not one of them)
HEAVY = ("fit_shard", "fit_template", "augmerl_log_tables", "augmerl_pca", "augmerl_shard",
         "train_", "btf_triple_plane", "btf_neumip", "btf_pca", "btf_sh", "btf_td")


def _planned_jobs(wd: Path, configfile: str) -> list[str]:
    """Rules `snakemake -n` would run for the report with `configfile`."""
    import re
    res = _snakemake(wd, "report", "--dry-run", "--quiet", "rules", "--configfile", configfile)
    text = res.stdout + res.stderr
    if "Nothing to be done" in text:
        return []
    return [j for j in re.findall(r"^(\w+)\s+\d+$", text, re.M) if j != "total"]


def _set(cfg: dict, dotted: str, value):
    *path, last = dotted.split(".")
    for p in path:
        cfg = cfg.setdefault(p, {})
    cfg[last] = value


def _job_params(mode: str, *configs: str) -> dict:
    """tests/job_params.py's answer for the report DAG of `configs` (no job runs)."""
    import json
    res = subprocess.run([sys.executable, str(ROOT / "tests/job_params.py"), mode, *configs],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    if res.returncode == 3 and "UNAVAILABLE" in res.stdout:  # a Snakemake release moved it
        pytest.skip(res.stdout.strip().split("UNAVAILABLE ", 1)[1] + " (update tests/job_params.py)")
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")]
    assert res.returncode == 0 and line, res.stderr[-3000:]
    return json.loads(line[-1].split(" ", 1)[1])


def _tiny_params_with(tmp_path, overlay: str) -> dict:
    """Each job's params texts for the tiny config with the YAML `overlay` on top."""
    f = tmp_path / f"over{len(list(tmp_path.iterdir()))}.yaml"
    f.write_text(overlay + "\n")
    return _job_params("texts", "config/tiny.yaml", str(f))


def _changed(a: dict, b: dict) -> list[str]:
    """The jobs (same DAG) whose params differ between two _job_params('texts') answers."""
    assert a.keys() == b.keys()
    return sorted(k for k in a if a[k] != b[k])


def test_readme_names_the_gpu_rules_and_the_long_trainings(tmp_path):
    """README "Running on Slurm or a GPU": the rules that ask Slurm for a GPU with device: cuda
    (a rule a user leaves out of the GPU partition is refused), and the time limits at
    paper.yaml's size that exceed most partitions' (Slurm refuses the job: a review of
    2026-11-29), as the paper DAG's jobs ask for them."""
    import re
    readme = (ROOT / "README.md").read_text()
    cuda = tmp_path / "cuda.yaml"
    cuda.write_text("device: cuda\n")
    cpu, gpu = _job_params("resources", "config/paper.yaml"), \
        _job_params("resources", "config/paper.yaml", str(cuda))
    listed = re.search(r"These (\d+) rules ask for one \(.*?\): (.*?);\n", readme, re.S)
    names = set(re.findall(r"`(\w+)`", listed.group(2)))
    assert names == {r for r, v in gpu.items() if v["gpu"] == 1} and int(listed.group(1)) == len(names)
    assert not any(v["gpu"] == 1 for v in cpu.values())  # device auto: none asks
    trainings = ("train_diffusion", "train_multimodal", "train_refiner")
    assert {cpu[r]["runtime"] for r in trainings} == {20010}
    assert "ask\n  for 20,010 minutes (13.9 days) and `train_hyperbrdf` for 1,677" in readme
    assert cpu["train_hyperbrdf"]["runtime"] == 1677
    assert max(gpu[r]["runtime"] for r in (*trainings, "train_hyperbrdf")) == 410
    over_a_day = {r for r, v in cpu.items() if isinstance(v["runtime"], int) and v["runtime"] > 1440}
    assert over_a_day == {*trainings, "train_hyperbrdf"}


def test_btf_section_records_the_crop_as_applied(tmp_path):
    """btf.crop at least the BTF's side crops nothing (common.smk btf_roi): the report section
    said "centre crop 64 x 64 texels" of a 24-texel BTF. Its params now hold the crop applied."""
    texts = {}
    for crop in (16, 64):
        extra = tmp_path / f"crop{crop}.yaml"
        extra.write_text(f"btf: {{crop: {crop}}}\n")  # tiny: ubo2014.synthetic.size 24
        jobs = _job_params("texts", "config/tiny.yaml", str(extra))
        texts[crop] = next(v for k, v in jobs.items() if k.startswith("btf_section "))
    assert "16" in texts[16] and "64" not in texts[64] and "None" in texts[64], texts


def test_a_number_spelt_otherwise_changes_no_params(tmp_path):
    """`fit.steps: 300.0` for the tiny config's 300, `conditions.sweep.scales: [0, 2]` for its
    [0.0, 2.0] give every job the same params (a review found 42 jobs rerun for the first;
    common.smk _typed)."""
    import yaml
    tiny = yaml.safe_load((ROOT / "config/tiny.yaml").read_text())
    assert tiny["fit"]["steps"] == 300 and tiny["conditions"]["sweep"]["scales"] == [0.0, 2.0]
    overlay = tmp_path / "spelt.yaml"
    overlay.write_text("fit: {steps: 300.0}\nconditions: {sweep: {scales: [0, 2]}}\n")
    assert _job_params("texts", "config/tiny.yaml", str(overlay)) == \
        _job_params("texts", "config/tiny.yaml")


def test_the_sampling_batch_size_is_a_param_only_of_particle_guided_draws(tmp_path):
    """diffusion.sample.batch_size is a memory knob (samples equal at any batch size:
    tests/test_diffusion.py), so a new value reran every sampler, the conditioned and constrained
    ones included; now only the draws whose particle guidance repels the samples of one batch
    (`ours`' unconditional draws and ours_plain; tiny: particle_step 0.1) change params, and
    no draw without particle guidance."""
    def changed(extra: str):
        over = tmp_path / "over.yaml"
        base = tmp_path / "base.yaml"
        over.write_text(extra + "diffusion: {sample: {batch_size: 7}}\n" if not extra else
                        "diffusion: {sample: {batch_size: 7, " + extra + "}}\n")
        base.write_text("diffusion: {sample: {" + extra + "}}\n")
        a = _job_params("texts", "config/tiny.yaml", str(base))
        b = _job_params("texts", "config/tiny.yaml", str(over))
        assert a.keys() == b.keys()
        return sorted(k.split(" ")[0] + (" " + k.split("'model', '")[1].split("'")[0]
                                         if "'model', '" in k else "")
                      for k in a if a[k] != b[k])
    # diffusion_section: the report's record of the sampling settings (seconds to rebuild)
    assert changed("") == ["diffusion_section", "sample_plain", "sample_uncond ours"]
    assert changed("particle_step: 0.0") == ["diffusion_section"]


@pytest.mark.parametrize("configs", [["config/tiny.yaml"], [], ["config/paper.yaml"]],
                         ids=["tiny", "default", "paper"])
def test_params_that_share_a_value_are_also_given_by_name(configs):
    """Snakemake compares a job's params as a set of value texts, names left out: two params of
    one value could change unnoticed (conditions.text.start_match false reran no sample_text,
    refiner being true too). Every job of the shipped configs whose params share a value (None
    aside: PCA-N's unused keys) has them by name too (`named`)."""
    found = _job_params("collisions", *configs)
    unguarded = {rule: v["shared"] for rule, v in found.items() if not v["named"]}
    assert not unguarded, unguarded


@pytest.mark.slow
def test_reordered_config_reruns_nothing(tiny_run):
    """Params compare by value: the same config with its keys sorted, written by another YAML
    emitter, is not a change."""
    import yaml
    cfg = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
    (tiny_run / "config/tiny_sorted.yaml").write_text(yaml.safe_dump(cfg, sort_keys=True))
    assert _planned_jobs(tiny_run, "config/tiny_sorted.yaml") == []


@pytest.mark.slow
def test_speed_and_cosmetic_keys_rerun_no_fit(tiny_run):
    """Every key in config/speed_keys.yaml changed at once (then one at a time, to name the
    culprit): no fit, AugMERL or training job would rerun; speed-only keys rerun nothing."""
    import yaml
    kinds = yaml.safe_load((ROOT / "config/speed_keys.yaml").read_text())
    base = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())

    def plan(keys):
        cfg = yaml.safe_load(yaml.safe_dump(base))
        for k in keys:
            _set(cfg, k, kinds["speed"].get(k, kinds["cosmetic"].get(k, {})).get("try"))
        (tiny_run / "config/changed.yaml").write_text(yaml.safe_dump(cfg))
        return _planned_jobs(tiny_run, "config/changed.yaml")

    every = [*kinds["speed"], *kinds["cosmetic"]]
    jobs = plan(every)
    if any(j.startswith(HEAVY) for j in jobs):
        culprits = {k: [j for j in plan([k]) if j.startswith(HEAVY)] for k in every}
        pytest.fail(f"speed/cosmetic keys rerun heavy jobs: {({k: v for k, v in culprits.items() if v})}")
    assert plan(list(kinds["speed"])) == [], "speed-only keys rerun jobs"


@pytest.mark.slow
@pytest.mark.parametrize("key, value", [("negative_step", 7.0), ("refit_steps", 3)])
def test_clamp_keys_rerun_only_sampling(tiny_run, key, value):
    """diffusion.sample.negative_step (the clamp constraint) and refit_steps (the clamp refit)
    are params of the sampling rules only: changing one retrains nothing, and sample_plain
    (drawn without them) stays."""
    import yaml
    cfg = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
    _set(cfg, f"diffusion.sample.{key}", value)
    (tiny_run / f"config/{key}.yaml").write_text(yaml.safe_dump(cfg))
    jobs = _planned_jobs(tiny_run, f"config/{key}.yaml")
    assert "sample_uncond" in jobs and "sample_type" in jobs, jobs
    assert not [j for j in jobs if j.startswith(HEAVY + ("train_", "sample_plain"))], jobs


@pytest.mark.slow
@pytest.mark.parametrize("key", ["rgb_permute", "type_prior", "keep_look", "particle_step",
                                 "temperature"])
def test_unconditional_ours_keys_rerun_only_its_unconditional_sampling(tiny_run, key):
    """diffusion.sample.rgb_permute and type_prior (neutral false; the tiny config sets both
    true) are params of the unconditional draws of `ours` (and `ours_plain`, drawn with the same
    seeds) alone, particle_step (neutral 0; the tiny config sets 0.1) and temperature (neutral
    1; the tiny config sets 1.1) too, keep_look (neutral
    0; the tiny config sets 25) of `ours`' alone: off,
    merl100's, the type-conditioned, the conditioned and the constrained samples stay, and
    nothing retrains."""
    import re

    import pandas as pd
    import yaml
    says = {"rgb_permute": "random RGB channel order", "type_prior": "drawn as in training",
            "keep_look": "keep look (diffusion.sample.keep_look 25 dB)",
            "particle_step": "particle guidance (diffusion.sample.particle_step 0.1)",
            "temperature": "scaled by diffusion.sample.temperature 1.1"}
    log = (tiny_run / "results/tiny/logs/sample_uncond/ours.log").read_text()
    merl100 = (tiny_run / "results/tiny/logs/sample_uncond/merl100.log").read_text()
    assert says[key] in log and says[key] not in merl100
    if key == "type_prior":  # each sample's drawn type recorded, typed and untyped ones
        t = pd.read_csv(tiny_run / "results/tiny/samples/ours/samples.tsv", sep="\t",
                        keep_default_na=False)
        assert (t["type"] == "").all() and "" in set(t["prior_type"]) and len(set(t["prior_type"])) > 1
    if key == "keep_look":  # which samples kept their draw without the step, and the log agrees
        t = pd.read_csv(tiny_run / "results/tiny/samples/ours/samples.tsv", sep="\t")
        n = re.search(r"keep_look 25 dB\): (\d+) of (\d+) samples", log)
        assert n and int(n[1]) == t["kept_look"].sum() and int(n[2]) == len(t)
    cfg = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
    _set(cfg, f"diffusion.sample.{key}", 0.0 if key in ("keep_look", "particle_step") else
         1.0 if key == "temperature" else False)
    (tiny_run / f"config/{key}_off.yaml").write_text(yaml.safe_dump(cfg))
    res = _snakemake(tiny_run, "report", "--dry-run", "--quiet", "rules", "--configfile",
                     f"config/{key}_off.yaml")
    jobs = dict(re.findall(r"^(\w+)\s+(\d+)$", res.stdout + res.stderr, re.M))
    # ours_plain is drawn without the clamp step: keep_look is not its param
    assert jobs.get("sample_uncond") == "1", jobs
    assert jobs.get("sample_plain") == (None if key == "keep_look" else "1"), jobs
    assert not [j for j in jobs if j.startswith(HEAVY + ("train_", "sample_type", "sample_text",
                                                          "sample_image", "sample_m",
                                                          "sample_constrained"))], jobs


@pytest.mark.slow
def test_bf16_training_is_a_param_and_fp32_reruns_nothing(tiny_run):
    """diffusion.train.precision (config/speed_keys.yaml `neutral`): bf16 retrains the diffusion
    models (the tiny config's refiner too); fp32, set explicitly, is the arithmetic the run was
    made with and reruns nothing."""
    import yaml
    for value, expect in (("bf16", True), ("fp32", False)):
        cfg = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
        _set(cfg, "diffusion.train.precision", value)
        (tiny_run / f"config/precision_{value}.yaml").write_text(yaml.safe_dump(cfg))
        jobs = _planned_jobs(tiny_run, f"config/precision_{value}.yaml")
        if expect:
            assert {j for j in jobs if j.startswith("train_")} == {
                "train_diffusion", "train_multimodal", "train_refiner"}, jobs
            assert not [j for j in jobs if j.startswith(HEAVY) and not j.startswith("train_")], jobs
        else:
            assert jobs == [], jobs


@pytest.mark.slow
def test_render_step_reruns_only_image_sampling(tiny_run):
    """conditions.image.render_step (neutral 0; the tiny config sets 1) is a param of
    sample_image alone: turning it off reruns image sampling and what reads it, no training."""
    import yaml
    cfg = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
    _set(cfg, "conditions.image.render_step", 0.0)
    (tiny_run / "config/render_off.yaml").write_text(yaml.safe_dump(cfg))
    jobs = _planned_jobs(tiny_run, "config/render_off.yaml")
    assert "sample_image" in jobs and not [j for j in jobs if j.startswith(HEAVY)], jobs
    assert not {"sample_text", "sample_multimodal", "sample_mm_type"} & set(jobs), jobs


def test_refiner_off_reruns_only_image_sampling(tiny_run):
    """conditions.image.refiner (neutral false; the tiny config sets true): off, the image
    samples come from the multimodal model again: sample_image and what reads it rerun, no
    training; on, the tiny run trained the refiner on ours's rows with prediction v."""
    import yaml
    from neumat.io import modelfile
    res = tiny_run / "results/tiny"
    bundle = modelfile.load(res / "diffusion/refiner/model.pt")
    assert bundle["sched_cfg"]["prediction"] == "v" and bundle["sched_cfg"]["loss"] == "x0"
    assert "refining the retrieved materials" in (res / "logs/sample_image.log").read_text()
    cfg = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
    _set(cfg, "conditions.image.refiner", False)
    (tiny_run / "config/refiner_off.yaml").write_text(yaml.safe_dump(cfg))
    jobs = _planned_jobs(tiny_run, "config/refiner_off.yaml")
    assert "sample_image" in jobs and not [j for j in jobs if j.startswith(HEAVY)], jobs
    assert not {"sample_text", "sample_multimodal", "sample_mm_type"} & set(jobs), jobs


def test_type_start_samples_from_training_materials_of_the_type(tiny_run):
    """conditions.type.{strength, refiner} (neutral 1 / false; the tiny config sets 0.1 / true):
    each mm_type sample starts from a training material of its type, refined by the refiner;
    back at strength 1 only sample_mm_type and what reads it rerun, no training."""
    import yaml
    res = tiny_run / "results/tiny"
    man = pd.read_csv(res / "neumerl/manifest.tsv", sep="\t", keep_default_na=False)
    train = man[man["split"] == "train"].set_index("name")["type"]
    table = pd.read_csv(res / "samples/mm_type/samples.tsv", sep="\t", keep_default_na=False)
    assert len(table) and "start" in table
    # only the test prompts' types that training has are drawn (when any is): the model never
    # saw the others
    prompts = pd.read_csv(res / "conditions/prompts.tsv", sep="\t", keep_default_na=False)
    asked, have = set(prompts.loc[prompts["kind"] == "test", "type"]), set(train) - {""}
    assert set(table["type"]) == (asked & have or asked), (set(table["type"]), asked, have)
    for t, starts in zip(table["type"], table["start"]):
        if t in set(train):  # a type training has: k starts of that type
            names = starts.split(",")
            assert len(names) == 2 and all(train[n] == t for n in names), (t, starts)
    log = (res / "logs/sample_multimodal/mm_type.log").read_text()
    assert "refining the starts" in log and "start from a training material of their type" in log
    cfg = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
    _set(cfg, "conditions.type.strength", 1.0)
    _set(cfg, "conditions.type.refiner", False)
    (tiny_run / "config/type_noise.yaml").write_text(yaml.safe_dump(cfg))
    jobs = _planned_jobs(tiny_run, "config/type_noise.yaml")
    assert "sample_mm_type" in jobs and not [j for j in jobs if j.startswith(HEAVY)], jobs
    assert not {"sample_text", "sample_image", "sample_multimodal", "sample_type"} & set(jobs), jobs


def test_text_start_samples_from_the_nearest_descriptions_of_the_voted_type(tiny_run):
    """conditions.text.{strength, refiner, start_match} (neutral 1 / false / false; the tiny
    config sets 0.1 / true / true): a prompt's k samples start from its k nearest training
    materials by description embedding (cosine), nearest first, among those of the type its
    nearest typed descriptions vote for, those of its colour word first, refined by the
    refiner."""
    import yaml
    from neumat.conditions import evaluate
    from neumat.conditions import text as text_condition
    from neumat.render import sphere
    res = tiny_run / "results/tiny"
    man = pd.read_csv(res / "neumerl/manifest.tsv", sep="\t", keep_default_na=False)
    train = np.flatnonzero((man["split"] == "train").to_numpy())
    types = man["type"].iloc[train].to_numpy()
    text = np.load(res / "conditions/text.npy")[train].astype(np.float64)
    prompts = pd.read_csv(res / "conditions/prompts.tsv", sep="\t", keep_default_na=False)
    emb = np.load(res / "conditions/prompts.npy").astype(np.float64)
    table = pd.read_csv(res / "samples/text/samples.tsv", sep="\t", keep_default_na=False)
    assert {"start", "voted_type"} <= set(table) and len(table) == 2 * len(prompts)
    log = (res / "logs/sample_text.log").read_text()
    size = int(re.search(r"type vote over the (\d+) nearest typed descriptions", log)[1])
    unit = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)
    names = list(man["name"].iloc[train])
    schema = yaml.safe_load((tiny_run / "config/schema.yaml").read_text())
    activation = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())["fit"].get(
        "activation", schema["properties"]["fit"]["properties"]["activation"]["default"])
    rgb = evaluate.mean_colour(sphere.render_fields(
        np.load(res / "neumerl/weights.npy")[train], text_condition.COLOUR_RESOLUTION, activation))
    for c, row in table.groupby("condition")[["start", "voted_type"]].first().iterrows():
        sim = unit(text) @ unit(emb[c])
        assert row["voted_type"] == text_condition.vote_types(sim[None], types, size)[0] != ""
        starts = row["start"].split(",")
        assert len(starts) == 2 and set(starts) <= set(names), starts
        assert all(types[names.index(n)] == row["voted_type"] for n in starts), row
        # the type's materials of the prompt's colour (all, if none has it), nearest first
        pool = types == row["voted_type"]
        colour = prompts["colour"].iloc[c]
        match = np.array([bool(colour) and evaluate.colour_matches(x, colour) for x in rgb])
        if (pool & match).any():
            pool &= match
        got = [sim[names.index(n)] for n in starts]
        assert np.isclose(got[0], sim[pool].max()), (c, got, sim[pool].max())
        assert names.index(starts[0]) in np.flatnonzero(pool), (c, starts)
    assert "refining the starts" in log and "nearest training descriptions of its voted" in log


def test_type_guidance_reruns_no_text_or_image_sampling(tiny_run):
    """diffusion.sample.guidance is the type model's guidance: the conditioning rules take
    theirs from conditions.guidance, so changing it reruns type sampling, not theirs."""
    import yaml
    cfg = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
    _set(cfg, "diffusion.sample.guidance", 3.5)
    (tiny_run / "config/type_guidance.yaml").write_text(yaml.safe_dump(cfg))
    jobs = _planned_jobs(tiny_run, "config/type_guidance.yaml")
    assert "sample_type" in jobs and not [j for j in jobs if j.startswith(HEAVY)], jobs
    assert not {"sample_text", "sample_image", "sample_multimodal", "sample_mm_type",
                "guidance_sweep", "sample_uncond"} & set(jobs), jobs


def test_each_conditioned_sampler_reruns_for_its_own_guidance_and_dropout(tiny_run):
    """A sampler's guidance param is its own modality's scale, and none where its refiner
    (which takes no condition) draws: in the tiny config every modality is refined, so
    conditions.guidance.type reruns no sampler (each took the whole section: all four reran)
    and not the section, which prints "none" for a refined modality's scale (it reran to the
    same bytes). diffusion.train.cond_drop is ours's dropout, not
    the multimodal model's (conditions.cond_drop), so that one is not retrained."""
    import yaml
    base = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
    assert all(base["conditions"][m]["refiner"] for m in ("type", "text", "image"))
    cfg = yaml.safe_load(yaml.safe_dump(base))
    _set(cfg, "conditions.guidance.type", 3.5)
    (tiny_run / "config/mm_type_guidance.yaml").write_text(yaml.safe_dump(cfg))
    jobs = _planned_jobs(tiny_run, "config/mm_type_guidance.yaml")
    assert set(jobs) <= {"report"}, jobs  # the report's params hold the whole config
    cfg = yaml.safe_load(yaml.safe_dump(base))
    _set(cfg, "diffusion.train.cond_drop", 0.3)
    (tiny_run / "config/ours_cond_drop.yaml").write_text(yaml.safe_dump(cfg))
    jobs = _planned_jobs(tiny_run, "config/ours_cond_drop.yaml")
    assert "train_diffusion" in jobs and "train_multimodal" not in jobs, jobs
    # a retrained multimodal model reruns its own samples, not the refined ones (the refiner
    # draws them; each sampler had the multimodal model as an input and reran to the same bytes)
    cfg = yaml.safe_load(yaml.safe_dump(base))
    _set(cfg, "conditions.cond_drop", 0.3)
    (tiny_run / "config/mm_cond_drop.yaml").write_text(yaml.safe_dump(cfg))
    jobs = _planned_jobs(tiny_run, "config/mm_cond_drop.yaml")
    assert {"train_multimodal", "sample_multimodal"} <= set(jobs), jobs
    assert not {"sample_text", "sample_image", "sample_mm_type"} & set(jobs), jobs


@pytest.mark.slow
def test_measured_colour_words_retrain_only_the_conditioning(tiny_run):
    """conditions.text.colour_words (neutral `source`) is a param of text_embeddings alone:
    `measured` re-embeds the descriptions and retrains the encoder and the multimodal model
    that read them, nothing upstream and no other model."""
    import yaml
    cfg = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
    _set(cfg, "conditions.text.colour_words", "measured")
    (tiny_run / "config/colour_measured.yaml").write_text(yaml.safe_dump(cfg))
    jobs = _planned_jobs(tiny_run, "config/colour_measured.yaml")
    assert {"text_embeddings", "train_image_encoder", "train_multimodal", "sample_text"} <= set(jobs)
    assert not [j for j in jobs if j.startswith(HEAVY) and j not in
                ("train_image_encoder", "train_multimodal")], jobs
    assert not {"sample_uncond", "sample_type", "metrics"} & set(jobs), jobs


@pytest.mark.slow
def test_a_new_prompt_retrains_nothing(tiny_run):
    """conditions.text.prompts is a param of prompt_embeddings alone (not of text_embeddings,
    whose text.npy the image encoder and the multimodal model train on): a prompt added
    re-embeds the prompts and reruns the draws that read them, and trains no model."""
    import yaml
    cfg = yaml.safe_load((tiny_run / "config/tiny.yaml").read_text())
    _set(cfg, "conditions.text.prompts", [*cfg["conditions"]["text"]["prompts"], "blue rubber"])
    (tiny_run / "config/new_prompt.yaml").write_text(yaml.safe_dump(cfg))
    jobs = _planned_jobs(tiny_run, "config/new_prompt.yaml")
    assert {"prompt_embeddings", "sample_text"} <= set(jobs), jobs
    assert not [j for j in jobs if j.startswith(HEAVY)], jobs
    assert not {"text_embeddings", "image_embeddings", "sample_image", "metrics"} & set(jobs), jobs


def test_every_model_file_loads_with_weights_only(tiny_run):
    """Users share model files: all the tiny run writes are tensors and plain values."""
    import torch

    files = sorted((tiny_run / "results/tiny").rglob("*.pt"))
    assert len(files) >= 10, files  # diffusion, baselines, hyperbrdf, encoders, BTF models
    for f in files:
        torch.load(f, map_location="cpu", weights_only=True)


def _download_config(wd: Path, names, url_dir: Path, verify: bool, pins: dict) -> str:
    import yaml
    # a third source, never downloaded: a run needs 2 train-split sources (check_cross_keys)
    cfg = {"run": "dl", "merl": {"source": "download", "subset": [*names, "black-fabric"],
                                 "url": f"file://{url_dir}/{{name}}.binary", "retries": 0,
                                 "verify_sha256": verify, "sha256_override": pins},
           "metrics": {"draws": 1}}  # three sources split 2:1 (check_cross_keys: draws x test)
    (wd / "config/dl.yaml").write_text(yaml.safe_dump(cfg))
    return "config/dl.yaml"


@pytest.mark.slow
def test_new_merl_url_keeps_pinned_downloads(tmp_path):
    """A file pinned by its sha256 is the same from any mirror: a new merl.url reruns (and so
    deletes) no verified download. Unpinned (verify_sha256: false) the URL is a param: the file
    from another address may differ."""
    import hashlib
    from neumat.io.merl import write_merl
    wd = tmp_path / "wd"
    wd.mkdir()
    _copy_workflow(wd)
    names = ["alum-bronze", "blue-acrylic"]  # catalogue names, synthetic contents
    mirrors = [tmp_path / "mirror_a", tmp_path / "mirror_b"]
    pins = {}
    for i, name in enumerate(names):
        table = np.full((3, 90, 90, 180), 0.1 + 0.1 * i)
        for m in mirrors:
            m.mkdir(exist_ok=True)
            write_merl(m / f"{name}.binary", table)
        pins[name] = hashlib.sha256((mirrors[0] / f"{name}.binary").read_bytes()).hexdigest()
    targets = [f"resources/merl/{n}.binary" for n in names]

    def planned(cfg):
        res = _snakemake(wd, *targets, "--dry-run", "--quiet", "rules", "--configfile", cfg)
        text = res.stdout + res.stderr
        return [] if "Nothing to be done" in text else re.findall(r"^(\w+)\s+\d+$", text, re.M)

    _snakemake(wd, *targets, "--configfile", _download_config(wd, names, mirrors[0], True, pins))
    first = {t: (wd / t).stat().st_mtime_ns for t in targets}
    assert planned(_download_config(wd, names, mirrors[1], True, pins)) == []
    assert {t: (wd / t).stat().st_mtime_ns for t in targets} == first
    # unpinned: the same files, downloaded without a sha256, rerun for a new address
    _snakemake(wd, *targets, "--configfile", _download_config(wd, names, mirrors[0], False, {}))
    assert "download_merl" in planned(_download_config(wd, names, mirrors[1], False, {}))


@pytest.mark.slow
def test_new_ubo2014_url_keeps_locked_downloads(tmp_path):
    """The lock file pins each BTF from its first good copy, so a new ubo2014.url (a mirror)
    reruns (and deletes) no download."""
    import yaml
    from neumat.btf.directions import ubo2014_angles
    from neumat.io.dfmf import write_dfmf
    wd = tmp_path / "wd"
    wd.mkdir()
    _copy_workflow(wd)
    name, file = "wood06", "wood06_resampled_W400xH400_L151xV151.btf"
    ang = ubo2014_angles()  # a 400 x 400 x 151 x 151 DFMF of rank 1: 1 MB
    for m in ("mirror_a", "mirror_b"):
        (tmp_path / m).mkdir()
        write_dfmf(tmp_path / m / file, [np.ones((len(ang) ** 2, 1))] * 3,
                   [np.full((400 * 400, 1), 0.5)] * 3, ang, ang, 400, 400)
    target = f"resources/ubo2014/{file}"

    def config(mirror):
        cfg = {"run": "dl", "merl": {"source": "synthetic"},
               "ubo2014": {"source": "download", "materials": [name],
                           "url": f"file://{tmp_path / mirror}/{{file}}"}}
        (wd / f"config/{mirror}.yaml").write_text(yaml.safe_dump(cfg))
        return f"config/{mirror}.yaml"

    _snakemake(wd, target, "--configfile", config("mirror_a"))
    assert name in (wd / "resources/ubo2014/sha256.lock.tsv").read_text()
    before = (wd / target).stat().st_mtime_ns
    res = _snakemake(wd, target, "--dry-run", "--configfile", config("mirror_b"))
    assert "Nothing to be done" in res.stdout + res.stderr, res.stdout[-2000:]
    assert (wd / target).stat().st_mtime_ns == before


def test_field_term_keys_are_params_of_the_trainings_alone_and_only_while_on(tmp_path):
    """diffusion.train.field_loss (config/config.yaml 0.1, which the tiny config takes; schema
    default 0 = off) and its keys: on, another field_eps changes the params of the diffusion
    trainings (ours and merl100; the tiny config's refiner and multimodal model) and of the
    report's diffusion section alone, and so does turning the term off; off, its keys are no
    job's params (0 with another field_eps changes none)."""
    def params(extra: str) -> dict:
        return _tiny_params_with(tmp_path, "diffusion: {train: {" + extra + "}}")
    on, off = params(""), params("field_loss: 0.0")
    trainings = ["diffusion_section []", "train_diffusion [('model', 'merl100')]",
                 "train_diffusion [('model', 'ours')]", "train_multimodal []",
                 "train_refiner [('model', 'refiner')]"]
    assert _changed(on, params("field_eps: 0.01")) == trainings
    assert _changed(on, off) == trainings
    assert _changed(off, params("field_loss: 0.0, field_eps: 0.01")) == []


def test_conditions_clamp_step_is_a_param_of_the_conditioned_draws_alone(tmp_path):
    """conditions.negative_step (config/config.yaml 30, which the tiny config takes; schema
    default null = diffusion.sample.negative_step): null, or the value diffusion.sample's has,
    changes no job's params, so runs made before the key existed rerun nothing; another value
    changes the conditioning stage's draws alone; and while it is set, diffusion.sample's step
    no longer reaches those draws."""
    def params(overlay: str) -> dict:
        return _tiny_params_with(tmp_path, overlay)
    draws = ["guidance_sweep []", "sample_image []", "sample_mm_type []",
             "sample_multimodal []", "sample_text []"]
    base = params("conditions: {}")
    assert _changed(base, params("conditions: {negative_step: null}")) == []
    assert _changed(base, params("conditions: {negative_step: 10.0}")) == draws
    other = _changed(base, params("diffusion: {sample: {negative_step: 10.0}}"))
    assert other and not set(other) & set(draws), other
