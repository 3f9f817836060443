# Helpers shared by all rule files (paths, material lists, config look-ups).
import math
import os
import string
import sys
from pathlib import Path

import pandas as pd
import yaml

# The library lives in src/; make it importable for DAG-time helpers even without `pip install -e`.
SRC = str(Path(workflow.basedir) / "src")
sys.path.insert(0, SRC)
# ...and for the scripts' interpreters too (e.g. under --use-conda, where neumat is not installed).
os.environ.update(PYTHONPATH=os.pathsep.join(p for p in (SRC, os.getenv("PYTHONPATH")) if p))
# Jobs' idle OpenMP threads sleep (OMP_WAIT_POLICY=PASSIVE): libgomp's default spins 300,000
# times at every barrier, and a 2-thread job whose partner waits for a core then burns the other
# core, which Snakemake, other jobs and whatever else runs there need. benchmarks/omp_wait.py,
# 2 torch threads on a 2-core AMD EPYC (AVX-512), against the default: beside one busy process
# 0.74x and 0.57x the wall time (Inception features, denoiser training), for about half the CPU;
# alone 0.99-1.14x and 1.03-1.17x over four runs (one on torch's AVX2 kernels). Inside pytest, beside the niced tests, the
# tiny run's jobs took 235-254 instead of 304 CPU-s. A short spin (GOMP_SPINCOUNT=1000) costs
# less alone (0.98x, 1.04x) but measured worse inside pytest (316.1 against 306.1 s, tiny run
# 258 against 247 CPU-s) and binds only libgomp. Either variable set in the environment wins.
if "GOMP_SPINCOUNT" not in os.environ:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
CONDA_ENV = "../envs/neumat.yaml"

from neumat.data import catalog as _catalog  # noqa: E402
from neumat import seeds as _seeds  # noqa: E402

RUN = config["run"]
OUT = f"results/{RUN}"
SEED = config["seed"]


# a job whose script runs torch on config `device` asks Slurm for a GPU when that is cuda
# (with auto, the submitting host cannot know what a node has: none is asked for)
GPU = 1 if config["device"] == "cuda" else 0


def cond_guidance(name, refiner=False):
    """The guidance param of the sampler conditioned on `name` (type, text or image; None for
    mm_uncond): its own scale of conditions.guidance alone, none when its refiner (which takes
    no condition) draws, so another modality's scale reruns nothing there."""
    return {} if name is None or refiner else {name: config["conditions"]["guidance"][name]}


def seed_for(stage, *items):
    """Seed of the named random stream `stage` (for `items`, e.g. a material) of this run; see
    neumat.seeds. Every stochastic rule takes its seed from here, never from SEED + offset."""
    return _seeds.seed_for(SEED, stage, *items)  # logged where tests/test_seeds.py asks


# ----------------------------------------------------------------------------- params by value
# Snakemake compares a rule's params as repr() text: {"a": 1, "b": 2} and {"b": 2, "a": 1} differ,
# and so do 1 and 1.0. Numbers become the schema's type here (_typed), and params that
# hold several keys go through canon() (keys sorted at every level). Speed-only keys
# (config/speed_keys.yaml) never enter params: scripts read them from snakemake.config.


def _typed(value, schema):
    """`value` as its schema types it: an integer given for a `number` key as a float (1 -> 1.0),
    an integral float given for an `integer` key as an int (300.0 -> 300; JSON Schema accepts
    it as an integer, and the scripts then got a float), in dicts and lists at any depth. Each
    spelling of a number then has one params text (a review on 2026-11-29: `fit.steps: 300.0`
    reran 42 jobs, `conditions.sweep.scales: [0, 2]` the sweep)."""
    types = schema.get("type", [])
    types = [types] if isinstance(types, str) else types
    if type(value) is int and "number" in types and "integer" not in types:
        return float(value)
    if type(value) is float and value.is_integer() and "integer" in types and "number" not in types:
        return int(value)
    if isinstance(value, dict):
        props = schema.get("properties", {})
        for k, v in value.items():
            value[k] = _typed(v, props.get(k, {}))
    elif isinstance(value, list) and isinstance(schema.get("items"), dict):
        value[:] = [_typed(v, schema["items"]) for v in value]
    return value


def _load_yaml(name):
    """A config/ file, with libyaml's parser where PyYAML has it: every job on a cluster parses
    this Snakefile twice, and the 40 kB schema takes 0.08 s with the pure-Python parser against
    0.01 s (measured, AMD EPYC)."""
    with open(Path(workflow.basedir) / "config" / name) as f:
        return yaml.load(f, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


_typed(config, _load_yaml("schema.yaml"))
_KEY_KINDS = _load_yaml("speed_keys.yaml")
SPEED_KEYS = set(_KEY_KINDS["speed"])  # never params
COSMETIC_KEYS = set(_KEY_KINDS["cosmetic"])  # params of report/figure rules only
# at these values, params as before the key existed (results made then stay valid)
NEUTRAL = {k: v["value"] for k, v in _KEY_KINDS.get("neutral", {}).items()}


def canon(value):
    """A params value compared by value: every dict's keys sorted, at every level."""
    if isinstance(value, dict):
        return {k: canon(value[k]) for k in sorted(value)}
    if isinstance(value, (list, tuple)):
        return [canon(v) for v in value]
    return value


def named(params):
    """A rule's keyword `params` plus `named`: their plain (not callable) values by name, canon.
    Snakemake records a job's params as the set of their values' texts, without their names
    (snakemake.persistence params_changed): where two params share a value, setting one to a
    value another holds, or swapping two, changed nothing it compares (a review of 2026-11-29:
    `conditions.text.start_match: false` reran no sample_text). A dict's text holds its keys.
    For the rules whose params share a value in a shipped config (tests/test_workflow.py
    checks them): `params: **named(dict(...))`."""
    return {**params, "named": canon({k: v for k, v in params.items() if not callable(v)})}


def settings(section, keys=None, drop=()):
    """Params value of config `section` ("fit", "diffusion.sample"): its `keys` (default all)
    minus `drop`, without speed-only and (unless listed in `keys`) cosmetic keys, at any depth,
    canonical."""
    node = config
    for part in section.split("."):
        node = node[part]

    chosen = {k: node[k] for k in (keys or node) if k not in drop}
    keep = {f"{section}.{k}" for k in keys or ()}  # cosmetic keys asked for by name stay
    return canon(substantive(chosen, section, keep))


def train_settings():
    """diffusion.train's params for the diffusion trainings: the field term's settings only
    while it is on (off, they change nothing)."""
    on = config["diffusion"]["train"]["field_loss"]
    return settings("diffusion.train", drop=() if on else ("field_eps", "field_bins", "field_power"))


def neutral_params(section, keys):
    """Keyword params for single keys of `section` (`**neutral_params(...)` in a rule's params):
    each key that is not at its neutral value (config/speed_keys.yaml), so that a key added
    after results existed reruns nothing at its default. Scripts read them with getattr(p, key,
    neutral value)."""
    return settings(section, keys)


def substantive(d, path="", keep=()):
    """`d` (config or a section at `path`) without speed-only and cosmetic keys, and without
    neutral keys at their neutral value, at any depth."""
    kept = {}
    for k, v in d.items():
        key = f"{path}.{k}" if path else k
        if key in SPEED_KEYS or (key in COSMETIC_KEYS and key not in keep):
            continue
        if key in NEUTRAL and v == NEUTRAL[key]:
            continue
        kept[k] = substantive(v, key, keep) if isinstance(v, dict) else v
    return kept


def out(path):
    """Output path under results/<run>/."""
    return f"{OUT}/{path}"


def log(name):
    return f"{OUT}/logs/{name}.log"


def bench(name):
    return f"{OUT}/benchmarks/{name}.tsv"


# ----------------------------------------------------------------------------- MERL


def merl_catalog():
    """DataFrame of the MERL materials this run uses (name, type, description, colours, sha256)."""
    m = config["merl"]
    if m["source"] == "synthetic":
        return _catalog.synthetic_catalog(m["synthetic"]["count"], seed_for("synthetic_merl"))
    return _catalog.load_catalog(m["materials"], m["subset"], m["sha256_override"])


MERL = merl_catalog()
MERL_NAMES = list(MERL["name"])
_UNPINNED = _catalog.unpinned(MERL) if config["merl"]["source"] != "synthetic" else []
if config["merl"]["verify_sha256"] and _UNPINNED:
    raise ValueError(f"config merl.materials: no sha256 for {', '.join(_UNPINNED[:5])}; give it "
                     f"(merl.sha256_override) or set merl.verify_sha256: false")
from neumat import augment as _augment  # noqa: E402

_augment.check_split(MERL_NAMES, config["augmerl"]["test_fraction"],
                     "merl.synthetic.count" if config["merl"]["source"] == "synthetic"
                     else "merl.subset", config["augmerl"]["permutations"], config["augmerl"]["size"])
_MERL_SHA256 = dict(zip(MERL["name"], MERL["sha256"]))


def merl_table(name):
    """Path of one MERL-format table of this run."""
    source = config["merl"]["source"]
    if source == "synthetic":
        return out(f"merl/{name}.binary")
    # local tables may be unverified stand-ins: never mix them with verified downloads
    return f"resources/{'merl' if source == 'download' else 'merl_local'}/{name}.binary"


def merl_sha256(name):
    return _MERL_SHA256[name]


# ----------------------------------------------------------------------------- AugMERL


def augmerl_count():
    a = config["augmerl"]
    base = len(MERL_NAMES) * (6 if a["permutations"] else 1)
    return max(a["size"], base)


AUG_SHARDS = [f"{i:03d}" for i in range(math.ceil(augmerl_count() / config["augmerl"]["shard_size"]))]


def metric_bins_upper():
    """An upper bound of the MERL bins a table set is stored at (the BRDF-L1 bins plus every
    row of the metric view)."""
    brdf = config["metrics"]["brdf_samples"]
    res = config["render"]["resolution"]
    return min(1_096_216, (1_096_216 if brdf == "all" else brdf) + math.pi / 4 * res ** 2 + 24 * 32 * 16)


def pca_a_mem_mb():
    """Memory of PCA-A's fit and draws (baseline_pca), which reads the training tables a block
    of bins at a time (neumat.baselines.pca fit_source): 1.5 GB, 4 copies of the float64 Gram
    matrix of the 3n observations (itself, eigh's vectors and workspace), the components,
    mean, median and cos map per bin, and twice the float32 draws (all draws, and one being
    made), on an upper bound of the bins. `python benchmarks/job_memory.py --jobs pca_a
    --pca-sizes 480x80000 1920x80000 --pca-whole` (Intel Xeon AVX-512, 2026-11-29): 1,941 and
    1,886 MB peak, 0.46 and 0.36 of this; the fit on the tables held whole, as before, 2,141 MB
    at 480 x 80,000 and 17,012 MB max_rss for 1,920 tables x 3 x 78,985 bins on real40."""
    rows = 3 * int(augmerl_count() * (1 - config["augmerl"]["test_fraction"]))
    bins, k = metric_bins_upper(), config["baselines"]["pca_a"]["components"]
    draws = DRAWS * split_sizes()["test"]
    return int(1500 + (32 * rows ** 2 + 8 * (k + 4) * bins + 2 * 4 * 3 * draws * bins) / 2 ** 20)


def metrics_mem_mb(model):
    """Memory of a metrics job: METRICS_MEM_MB (renders, pairwise SSIM chunks), plus for a
    table-set model (PCA-A) its float32 tables, held whole: on real41 (2026-11-29) its job
    peaked at 4,394 MB against 3,409 declared, its 1,440 tables of 3 x 81,200 bins (1.40 GB)
    loaded twice (a float32 copy of float32 values, since dropped)."""
    tables = DRAWS * split_sizes()["test"] if model == "pca_a" else 0
    return int(METRICS_MEM_MB + 4 * 3 * tables * metric_bins_upper() / 1e6)
# the template material (fit first; its weights start every other fit): the first train-split
# original, from the split augmerl_pca draws (the same function, config and seed)
_PLANNED_ROWS = _augment.plan_rows(
    MERL, config["augmerl"]["permutations"],
    _augment.split_sources(MERL_NAMES, config["augmerl"]["test_fraction"], seed_for("augmerl")))
TEMPLATE_ID = _augment.template_id(_PLANNED_ROWS)
TEMPLATE_SHARD = f"{TEMPLATE_ID // config['augmerl']['shard_size']:03d}"


def split_sizes():
    """Rows of the train and test splits of the manifest augmerl_pca will write (the same
    split, rows and interpolation counts), known before any job runs."""
    rows = _PLANNED_ROWS
    mixes = _augment.interpolation_counts(rows, augmerl_count() - len(rows))
    return {s: int((rows["split"] == s).sum()) + mixes.get(s, 0) for s in ("train", "test")}


def train_split_types():
    """Types of the source materials in the train split (what a type-conditioned draw needs)."""
    rows = _PLANNED_ROWS
    return set(rows.loc[rows["split"] == "train", "type"]) - {""}


def augmerl_shards():
    return expand(out("augmerl/shards/{shard}.npz"), shard=AUG_SHARDS)


# ----------------------------------------------------------------------------- report

# Every stage's Markdown fragment, listed here (not filled by `include` order): the `report`
# rule stitches them, in this order, into index.md and index.html. A new stage adds its line.
REPORT_SECTIONS = [
    out("report/sections/10_dataset.md"),  # augment.smk: dataset_section
    out("report/sections/20_neumerl.md"),  # fit.smk: neumerl_section
    out("report/sections/30_rendering.md"),  # render.smk: render_section
    out("report/sections/40_diffusion.md"),  # diffusion.smk: diffusion_section
    out("report/sections/42_conditions.md"),  # conditions.smk: conditions_section
    out("report/sections/45_constrained.md"),  # constrained.smk: constrained_section
    out("report/sections/50_table2.md"),  # metrics.smk: metrics_table
    out("report/sections/55_hyperbrdf.md"),  # hyperbrdf.smk: hyperbrdf_table
    out("report/sections/60_btf.md"),  # btf.smk: btf_section
    # btf_synthesis.smk: btf_synthesis_section (only when synthesis methods are configured)
    *([out("report/sections/61_btf_synthesis.md")] if config["btf_synthesis"]["methods"] else []),
]


def figure_captions():
    """{regular expression of a figure's file name: its caption file} for every report()
    output of the workflow's rules (read after they are all defined: rule report, last), so
    that index.md / index.html show the captions `snakemake --report` shows. The caption's
    path is Snakemake's (ReportObject.caption); a Snakemake that keeps it elsewhere gives no
    captions rather than an error."""
    import re

    found = {}
    for r in workflow.rules:
        for f in r.output:
            rep = getattr(f, "flags", {}).get("report")
            caption = getattr(rep, "caption", None)
            if caption is None:
                continue
            name = re.escape(Path(str(f)).name)
            found[re.sub(r"\\\{[^}]*\\\}", "[^/]+", name)] = os.path.relpath(str(caption))
    return dict(sorted(found.items()))


def report_inputs():
    return [out("report/index.html"), out("report/index.md")]


# ----------------------------------------------------------------------------- MERL files (data.smk)


def merl_checked(path):
    """`path` flagged with the material's pinned sha256, unless merl.verify_sha256 is false."""
    if config["merl"]["verify_sha256"]:
        return ensure(path, sha256=lambda w: merl_sha256(w.merl))
    return path


def merl_url(name):
    """Where download_merl fetches a material (merl.url with {name} replaced)."""
    return config["merl"]["url"].format(name=name)


def merl_expected_sha256(wildcards):
    """The sha256 a data rule's script checks ('' = size/header only)."""
    return merl_sha256(wildcards.merl) if config["merl"]["verify_sha256"] else ""


# ----------------------------------------------------------------------------- metrics

# Table 2: model name -> its sample set: neural-field weights (N, 675) as .npy, or a table set
# (.npz: values at the bins the metrics read, see neumat.metrics.materials). Each holds
# metrics.draws draws of as many materials as the reference set, every draw from its own seed.
# The reference set every model is scored against is the NeuMERL test split;
# `reference_halves` is the sanity row: random halves of the reference set against each other.
MODEL_WEIGHTS = {
    "training_set": out("samples/training/weights.npy"),
    "pca_a": out("samples/pca_a/tables.npz"),
    "pca_n": out("samples/pca_n/weights.npy"),
    "vae_a": out("samples/vae_a/weights.npy"),
    "vae_n": out("samples/vae_n/weights.npy"),
    "merl100": out("samples/merl100/weights.npy"),
    "ours": out("samples/ours/weights.npy"),
    "reference_halves": out("samples/reference/weights.npy"),
}
REFERENCE_WEIGHTS = out("samples/reference/weights.npy")


def _cross_model(errors):
    """The denoiser, its sampling and training, and the image encoder."""
    d, enc = config["diffusion"], config["conditions"]["image"]["encoder"]
    if d["model"]["width"] % d["model"]["heads"]:
        errors.append(f"diffusion.model.width {d['model']['width']} is not a multiple of "
                      f"diffusion.model.heads {d['model']['heads']}")
    if d["sample"]["steps"] > d["schedule"]["timesteps"]:
        errors.append(f"diffusion.sample.steps {d['sample']['steps']} exceeds "
                      f"diffusion.schedule.timesteps {d['schedule']['timesteps']}")
    if enc["crop"] > enc["resolution"]:
        errors.append(f"conditions.image.encoder.crop {enc['crop']} exceeds its resolution "
                      f"{enc['resolution']}")
    t = d["train"]
    if t["warmup_steps"] >= t["steps"]:
        errors.append(f"diffusion.train.warmup_steps {t['warmup_steps']} is not below "
                      f"diffusion.train.steps {t['steps']}: the learning rate would never reach "
                      f"diffusion.train.lr nor decay")
    if t["cond_drop"] == 0 and d["sample"]["guidance"] != 1:
        errors.append(f"diffusion.train.cond_drop 0 with diffusion.sample.guidance "
                      f"{d['sample']['guidance']}: guidance needs the null class, which a "
                      f"cond_drop of 0 leaves untrained; give cond_drop > 0 (e.g. 0.1) or "
                      f"guidance 1")


def _cross_table2(errors):
    """Table 2's models, the split it scores on, and the sets drawn for it."""
    d = config["diffusion"]
    models = set(config["metrics"]["models"])
    unknown = sorted((models - set(MODEL_WEIGHTS)) | (models & {"reference_halves"}))
    if unknown:
        errors.append(f"metrics.models {unknown}: not Table 2 models; known: "
                      f"{sorted(set(MODEL_WEIGHTS) - {'reference_halves'})}")
    perms = _augment.PERMS if config["augmerl"]["permutations"] else _augment.PERMS[:1]
    rows = {n if q == "rgb" else f"{n}@{q}" for n in MERL_NAMES for q in perms}
    n_mix = augmerl_count() - len(rows)
    rows |= {f"mix{k:04d}" for k in range(n_mix)}  # augment.build_manifest's names
    absent = [n for n in config["fit"]["export"] if n not in rows]
    if absent:
        errors.append(f"fit.export {absent[:5]}: not AugMERL materials of this run (a material's "
                      f"name, <name>@<permutation>, or " + (f"mix0000 to mix{n_mix - 1:04d}" if n_mix
                                                           else "no mixNNNN: augmerl.size adds none") + ")")
    missing = sorted(set(d["types"]) - set(MERL["type"]))
    trained = train_split_types()
    if missing:
        errors.append(f"diffusion.types {missing}: no material of this run has that type; its "
                      f"types: {sorted(set(MERL['type']) - {''})}")
    elif set(d["types"]) - trained:
        errors.append(f"diffusion.types {sorted(set(d['types']) - trained)}: only test-split "
                      f"materials have that type, so no model trains on it; types in training: "
                      f"{sorted(trained)}")
    # Table 2: the reference set is the test split; its sanity row splits it into two halves
    # of at least 2, and the Training-set column draws metrics.draws subsets of >= 2 rows
    sizes, draws = split_sizes(), config["metrics"]["draws"]
    if sizes["test"] < 4:
        errors.append(f"the test split holds {sizes['test']} materials (augmerl.test_fraction, the "
                      f"source materials, augmerl.permutations, augmerl.size); Table 2's sanity "
                      f"row splits it into two halves of at least 2: give it at least 4")
    # MERL100 and HyperBRDF's `merl` model train on the train split's originals alone
    originals = int(((_PLANNED_ROWS["split"] == "train") &
                     (_PLANNED_ROWS["operation"] == "original")).sum())
    if originals < 2:
        errors.append(f"the train split holds {originals} source material of {len(MERL_NAMES)} "
                      f"(merl.subset, merl.synthetic.count, augmerl.test_fraction): MERL100 and "
                      f"HyperBRDF's merl model, which train on its originals alone, would learn "
                      f"one material; give at least 2 (more materials or a lower test_fraction)")
    if sizes["train"] < 2 * draws:
        errors.append(f"the train split holds {sizes['train']} materials, too few for "
                      f"metrics.draws {draws} Training-set subsets of at least 2")
    elif sizes["train"] < draws * sizes["test"]:  # each draw as large as the reference set
        errors.append(f"the train split holds {sizes['train']} materials, fewer than "
                      f"metrics.draws {draws} x the {sizes['test']}-material test split: Table "
                      f"2's Training-set draws would hold {sizes['train'] // draws}, not "
                      f"{sizes['test']}, and its sanity rows would drift; lower metrics.draws "
                      f"or augmerl.test_fraction (at most about 1 / (metrics.draws + 1))")
    if d["export_merl"] > sizes["test"] * draws:
        errors.append(f"diffusion.export_merl {d['export_merl']} exceeds the samples a set holds "
                      f"({sizes['test']} test materials x metrics.draws {draws})")


def _cross_urls(errors):
    """Download patterns."""
    for key, section, names, needs in (("merl.url", "merl", ("name",), ("name",)),
                                       ("ubo2014.url", "ubo2014", ("name", "category", "file"),
                                        ("name", "file"))):
        pattern = config[section]["url"]
        try:
            pattern.format(**{n: "x" for n in names})
        except (KeyError, IndexError, ValueError) as e:
            errors.append(f"{key} {pattern!r}: {type(e).__name__} {e} in its placeholders; it "
                          f"may use {', '.join(f'{{{n}}}' for n in names)}")
            continue
        fields = {f for _, f, _, _ in string.Formatter().parse(pattern) if f}
        if config[section]["source"] == "download" and not fields & set(needs):
            errors.append(f"{key} {pattern!r} has no {' or '.join(f'{{{n}}}' for n in needs)} "
                          f"placeholder: every material would download the same file")


def _cross_bins(errors):
    """Sample counts against the stored MERL bins: Table 3, the fits, VAE-A."""
    # augmerl.bins: an integer or "all" valid bins (1,096,216, more than any N)
    stored = config["augmerl"]["bins"]
    stored = stored if isinstance(stored, int) else None
    # Table 3: samples drawn without replacement from a material's stored bins and, for
    # training, from the hyperbrdf.train_bins of them
    hb = config["hyperbrdf"]
    if stored is not None and hb["sparse_samples"] > stored:
        errors.append(f"hyperbrdf.sparse_samples {hb['sparse_samples']} exceeds augmerl.bins "
                      f"{stored} (the stored bins of a test material the encoder samples from)")
    per_step = {k: hb["train"][k] for k in ("context", "query")}
    key, most = max(per_step.items(), key=lambda kv: kv[1])
    for limit_key, limit in (("hyperbrdf.train_bins", hb["train_bins"]), ("augmerl.bins", stored)):
        if limit is not None and most > limit:
            errors.append(f"hyperbrdf.train.{key} {most} exceeds {limit_key} {limit} (training "
                          f"samples each step's context and query from min(hyperbrdf.train_bins, "
                          f"augmerl.bins) bins per material)")
    # the fits' minibatches come from the stored bins less the validation share
    # (fit.split_bins); the C step takes minibatches of whole vectors
    f = config["fit"]
    if stored is not None and f["batch"] > stored - int(round(f["val_fraction"] * stored)):
        errors.append(f"fit.batch {f['batch']} exceeds the training bins of a fit: augmerl.bins "
                      f"{stored} less the fit.val_fraction {f['val_fraction']} held out")
    if f["kernel"] == "c" and f["batch"] % 16:  # fit_kernel.VECTOR
        errors.append(f"fit.batch {f['batch']} is not a multiple of 16, which fit.kernel: c "
                      f"needs (auto falls back to torch)")
    va = config["baselines"]["vae_a"]
    limit = min(va["bins"], stored) if stored is not None else va["bins"]
    if va["context"] + va["queries"] > limit:
        errors.append(f"baselines.vae_a.context {va['context']} + queries {va['queries']} exceed "
                      f"the {limit} bins VAE-A keeps per material (min of baselines.vae_a.bins "
                      f"and augmerl.bins); the queries are other bins than the context's")


def _cross_figures_constrained_btf(errors):
    """The AugMERL figure, constrained synthesis and the BTF stage."""
    a = config["augmerl"]
    shown = [a["figure_material"]] if a["figure_material"] else []
    absent = [n for n in shown + list(a["figure_pair"]) if n not in MERL_NAMES]
    if absent:
        errors.append(f"augmerl.figure_material / figure_pair {absent}: not materials of this "
                      f"run (merl.materials, merl.subset)")
    # constrained synthesis: medium-specular is medium_peak <= peak < high_peak, so an
    # inverted pair makes that category unreachable and spends its whole budget
    c = config["constrained"]
    lo, hi = c["derive"]["specular_quantiles"]
    if lo > hi:
        errors.append(f"constrained.derive.specular_quantiles [{lo}, {hi}]: the first is "
                      f"medium_peak's quantile, the second high_peak's; give them ascending")
    t = c["thresholds"]
    if t["medium_peak"] is not None and t["high_peak"] is not None and t["medium_peak"] > t["high_peak"]:
        errors.append(f"constrained.thresholds.medium_peak {t['medium_peak']} exceeds high_peak "
                      f"{t['high_peak']}: no material could be medium-specular")
    if c["per_category"] > c["budget"]:
        errors.append(f"constrained.per_category {c['per_category']} exceeds constrained.budget "
                      f"{c['budget']} (samples drawn per category): no category could complete")
    low = [li for li in config["btf"]["tiling"]["lights"] if li[2] <= 0]
    if low:
        errors.append(f"btf.tiling.lights {low}: on or below the plane (z = 0); give z > 0")
    bp = config["btf"]["pca"]
    if bp["components"] > bp["fit_texels"]:
        errors.append(f"btf.pca.components {bp['components']} exceeds btf.pca.fit_texels "
                      f"{bp['fit_texels']} (the texels the basis is fitted on)")


def check_cross_keys():
    """Config values the schema accepts one by one that do not go together, refused before any
    job runs (each failed in a job: after training, after the NeuMERL fits, or as Snakemake's
    MissingInputException naming a file, not the key). Every clause is collected, then one error
    names them all."""
    errors = []
    for check in (_cross_model, _cross_table2, _cross_urls, _cross_bins,
                  _cross_figures_constrained_btf):
        check(errors)
    if errors:
        raise ValueError("bad config: " + "; ".join(errors))


check_cross_keys()


DRAWS = config["metrics"]["draws"]


def draw_seeds(stage, name):
    """One seed per Table-2 draw (metrics.draws) of sample set `name`."""
    return [seed_for(stage, name, d) for d in range(DRAWS)]


def model_weights(model):
    """Weights file of a Table-2 model (see MODEL_WEIGHTS)."""
    if model not in MODEL_WEIGHTS:
        raise ValueError(f"unknown model {model!r} (metrics.models); known: {sorted(MODEL_WEIGHTS)}")
    return MODEL_WEIGHTS[model]


# ----------------------------------------------------------------------------- NeuMERL fits


def fit_runtime(materials, steps):
    """Minutes for a fit job: ~0.11 ms per material-step on one CPU thread with the torch
    path (measured; the C kernel takes ~0.03 ms), x3 for slower cluster cores, plus slack."""
    return 10 + math.ceil(materials * steps / 180000)


# ----------------------------------------------------------------------------- diffusion


def diffusion_runtime():
    """Minutes for a train_diffusion job: 0.5 s per step of a width-256, depth-4, batch-128
    model (measured 0.135 s with 2 threads on a 2-core Xeon; the margin is for slower cluster
    cores), scaled by width^2 * depth * batch (a GPU: assumed 50x faster)."""
    m, t = config["diffusion"]["model"], config["diffusion"]["train"]
    per_step = 0.5 * (m["width"] / 256) ** 2 * m["depth"] / 4 * t["batch_size"] / 128
    per_step /= 50 if config["device"] == "cuda" else 1
    return 10 + math.ceil(t["steps"] * per_step / 60)


def diffusion_mem_mb(floor=2500):
    """Memory of a denoiser's training (train_diffusion, train_multimodal, train_refiner):
    `floor`, or 1.5 x (610 MB + 51 bytes a parameter) where that is more, with about
    12 depth width^2 parameters. `python benchmarks/job_memory.py --jobs diffusion` (train_diffusion's
    path, 3 steps with a checkpoint, one thread, Intel Xeon AVX-512, 2026-11-29): 607 MB peak
    at width 256, depth 4, batch 128 and 2,394 MB at paper.yaml's 512, 12, 256 (39.1M
    parameters), i.e. 423 MB + 52.9 bytes a parameter; real41's train_diffusion job at the
    former 773 MB max_rss. paper.yaml's jobs had 2,500 MB declared. The benchmark's dn_budget
    repeats this formula."""
    m = config["diffusion"]["model"]
    params = 12 * m["depth"] * m["width"] ** 2 + 150_000
    return max(floor, int(1.5 * (610 + 51e-6 * params)))


def diffusion_exports():
    """MERL .binary exports of the first `diffusion.export_merl` samples of ours and merl100."""
    return expand(out("samples/{set}/merl/sample_{i:03d}.binary"), set=["ours", "merl100"],
                  i=range(config["diffusion"]["export_merl"]))


# ----------------------------------------------------------------------------- BTF (btf.smk)


from neumat.data import ubo2014 as _ubo2014

UBO = config["ubo2014"]
BTF = config["btf"]
BTF_SUFFIX = "_resampled_W400xH400_L151xV151.btf"

if UBO["source"] == "synthetic":
    BTF_NAMES = [f"synthetic_{k}" for k in UBO["synthetic"]["kinds"]]
else:
    UBO_CAT = _ubo2014.load_catalog(UBO["catalog"], UBO["materials"]).set_index("name")
    BTF_NAMES = list(UBO["materials"])
if not BTF_NAMES:  # the BTF section and its tables need one material (they failed at the last job)
    raise ValueError(f"bad config (ubo2014.{'synthetic.kinds' if UBO['source'] == 'synthetic' else 'materials'}): "
                     f"[] names no BTF material; give at least one")


def btf_file(name):
    """The DFMF file of one material in this run."""
    if UBO["source"] == "synthetic":
        return out(f"btf/data/{name}.btf")
    return f"resources/ubo2014/{name}{BTF_SUFFIX}"


def btf_size():
    """Texels per side of this run's BTFs (UBO2014's are 400)."""
    return UBO["synthetic"]["size"] if UBO["source"] == "synthetic" else 400


def btf_crop():
    """btf.crop as applied: None where it is null or not smaller than the BTFs (btf_roi)."""
    c = BTF["crop"]
    return None if c is None or c >= btf_size() else c


def btf_roi(name):
    """Centre crop (x0, y0, w, h) from config btf.crop, or None for the whole texture."""
    c = btf_crop()
    if c is None:
        return None
    o = (btf_size() - c) // 2
    return [o, o, c, c]


def btf_texels():
    """Texels of each BTF this run fits and evaluates (btf.crop of the texture, or all)."""
    return (btf_crop() or btf_size()) ** 2


def synthetic_btf_mem_mb():
    """synthetic_btf's memory: its SVD holds three texel Gram matrices and eigh's workspace
    (about 64 bytes x texels^2) and, below 512 MiB, the whole decorrelated matrix (22801 rows
    x texels x 3 float32); max_rss 595 / 1,229 / 4,918 MB at 32^2 / 64^2 / 96^2 texels
    (Intel Xeon AVX-512, 2026-11-29; the jobs' benchmark files of `snakemake --cores 2
    results/<run>/btf/eval/synthetic_wood/metrics.tsv` with config/tiny.yaml and an overlay
    setting run, ubo2014.synthetic.size S and btf.crop null), against 1,047 / 1,774 / 6,136 MB
    here."""
    t = UBO["synthetic"]["size"] ** 2
    held = 22801 * t * 12 if 22801 * t * 12 <= 1 << 29 else 0
    return int(700 + 64e-6 * t ** 2 + held / 1e6)


def synthetic_btf_runtime():
    """Minutes: its Gram pass costs about 9.6 us x texels^2 (7 / 103 / 667 s at 32^2 / 64^2 /
    96^2 texels, same machine), doubled for slower cores, + 5."""
    return int(5 + 2 * 9.65e-6 * UBO["synthetic"]["size"] ** 4 / 60)


def btf_fit_runtime(method):
    """Minutes for a neural BTF fit (btf_triple_plane, btf_neumip): 5 us per query-step (batch x
    steps), plus 10. `OMP_NUM_THREADS=2 python benchmarks/btf_fit_step.py --steps 4 --warmup 2
    --repeat 3` at paper.yaml's batch of 65,536 (Intel Xeon AVX-512, 2026-11-29, three runs):
    Triple Plane 101-148 ms a step on 1 thread, 84-124 on 2 (a step's MLP is too small to
    share well), NeuMIP 105-117 / 62-72, i.e. 1.6-2.3 us a query-step; the margin is for slower
    cluster cores, and no speed-up from more threads is assumed. paper.yaml's 200,000 steps:
    1,103 minutes (the rules had 600 whatever the steps; a review of 2026-11-29)."""
    s = BTF[method]
    return 10 + math.ceil(s["steps"] * s["batch"] * 5e-6 / 60)


def btf_eval_mem_mb():
    """btf_eval's memory: every model of a material loaded at once (the SH one 16 KB a texel)
    beside bounded query chunks: max_rss 853 / 911 MB at 64^2 / 96^2 synthetic texels (Intel
    Xeon AVX-512, 2026-11-29, the runs of synthetic_btf_mem_mb), 11 KB a texel; here 1.2 GB + 30 KB a texel (6.0 GB for a whole 400^2
    UBO2014 texture, btf.crop null)."""
    return int(1200 + 0.03 * btf_texels())


def btf_seed(name, method):
    """Seed of one BTF material's data ('data') or of one method's fit on it."""
    return seed_for("btf", name, method)


def _btf_fit_rule_params(method):
    return dict(method=method, roi=lambda w: btf_roi(w.material),
                seed=lambda w: btf_seed(w.material, method),
                settings=settings(f"btf.{method}") if method in BTF else {})


# ----------------------------------------------------------------------------- conditions (conditions.smk)


def cond_seed(stage):
    """Seed of one conditioning stage: the named stream ("conditions", stage)."""
    return seed_for("conditions", stage)


def image_sampling():
    """How the conditioned samplers drew, for the report: sample_image's model, start and
    render guidance, and where set, the starts of mm_type and text samples."""
    img = COND["image"]
    how = ("the refiner (rule train_refiner; prediction v, loss x0) refining each image's "
           "retrieved training material, without the image condition" if IMAGE_REFINER else
           "the multimodal model under the image condition")
    if img["strength"] < 1 and not IMAGE_REFINER:
        how += ", from each image's retrieved training material"
    start = f"strength {img['strength']:g}" if img["strength"] < 1 else "from noise"
    render = f"render step {img['render_step']:g}" if img["render_step"] else "no render guidance"
    text = f"Image samples: {how} ({start}, {render})."
    n, free = img["candidates"], img["unconstrained_candidates"]
    if n + free > 1:  # said only when set: the default run's section is unchanged
        drawn = f"{n} with the clamp constraint and {free} without" if free else f"{n}"
        text += (f" Each kept sample is the best of {n + free} draws ({drawn}) by the PSNR of "
                 f"its metric-view render against the image, less {img['clamp_penalty']:g} dB "
                 "where its field clamps negative values.")
    typ = COND["type"]
    if typ["strength"] < 1:  # said only when set: the default run's section is unchanged
        by = ("the refiner, unconditionally" if TYPE_REFINER else
              "the multimodal model under the type condition")
        text += (f" `mm_type` samples: a training material of each sample's type, noised to "
                 f"strength {typ['strength']:g} and denoised by {by}.")
    txt = COND["text"]
    if txt["strength"] < 1:
        by = ("the refiner, unconditionally" if TEXT_REFINER else
              "the multimodal model under the text condition")
        typed = (" of the type its nearest typed descriptions vote for (those of its colour "
                 "word first)" if txt["start_match"] else "")
        text += (f" Text samples: the training materials whose descriptions are nearest each "
                 f"prompt{typed}, noised to strength {txt['strength']:g} and denoised by {by}.")
    return text


# ----------------------------------------------------------------------------- Table 3 (hyperbrdf.smk)


def hyperbrdf_runtime():
    """Minutes for a train_hyperbrdf job: 0.25 s per material-step of 6000 samples (measured
    0.19 s: 1.5 s per step of 8 materials x (4000 + 2000) samples, 1 thread, two jobs on a shared
    2-core AMD EPYC), scaled by samples, x2 margin for slower cores (a GPU: assumed 20x faster)."""
    t = config["hyperbrdf"]["train"]
    per_step = 0.5 * t["materials_per_step"] * (t["context"] + t["query"]) / 6000
    per_step /= 20 if config["device"] == "cuda" else 1
    return 10 + math.ceil(t["steps"] * per_step / 60)


# ----------------------------------------------------------------------------- BTF synthesis (btf_synthesis.smk)


def syn_seed(*items):
    """Seed of the synthesis of one (material, method): the named stream "btf_synthesis"."""
    return seed_for("btf_synthesis", *items)


def _syn_models(w):
    return [out(f"btf/models/{w.material}/{m}.pt") for m in syn_planes()]


def syn_planes():
    """The plane models (Triple Plane, NeuMIP) of btf.methods that synthesis applies to."""
    return [m for m in ("triple_plane", "neumip") if m in BTF["methods"]]
