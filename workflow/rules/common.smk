# Helpers shared by all rule files (paths, material lists, config look-ups).
import math
import os
import sys
from pathlib import Path

import pandas as pd

# The library lives in src/; make it importable for DAG-time helpers even without `pip install -e`.
SRC = str(Path(workflow.basedir) / "src")
sys.path.insert(0, SRC)
# ...and for the scripts' interpreters too (e.g. under --use-conda, where neumat is not installed).
os.environ.update(PYTHONPATH=os.pathsep.join(p for p in (SRC, os.getenv("PYTHONPATH")) if p))
CONDA_ENV = "../envs/neumat.yaml"

from neumat.data import catalog as _catalog  # noqa: E402

RUN = config["run"]
OUT = f"results/{RUN}"
SEED = config["seed"]


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
        return _catalog.synthetic_catalog(m["synthetic"]["count"], SEED)
    return _catalog.load_catalog(m["materials"], m["subset"], m["sha256_override"])


MERL = merl_catalog()
MERL_NAMES = list(MERL["name"])
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


def augmerl_shards():
    return expand(out("augmerl/shards/{shard}.npz"), shard=AUG_SHARDS)


# ----------------------------------------------------------------------------- report

# Every stage appends its Markdown fragment(s) (out("report/sections/NN_stage.md")) here;
# the `report` rule stitches them, in file-name order, into index.md and index.html.
REPORT_SECTIONS = []


def report_inputs():
    return [out("report/index.html"), out("report/index.md")]


# ----------------------------------------------------------------------------- MERL files (data.smk)


def merl_checked(path):
    """`path` flagged with the material's pinned sha256, unless merl.verify_sha256 is false."""
    if config["merl"]["verify_sha256"]:
        return ensure(path, sha256=lambda w: merl_sha256(w.name))
    return path


def merl_expected_sha256(wildcards):
    """The sha256 a data rule's script checks ('' = size/header only)."""
    return merl_sha256(wildcards.name) if config["merl"]["verify_sha256"] else ""


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


DRAWS = config["metrics"]["draws"]


def stream_seed(stage, *items):
    """Seed of a named stream: numpy SeedSequence over (config seed, stage, items). Stand-in
    for issue 20's `seed_for(stage, *items)`; switch callers to it when it lands."""
    import zlib

    import numpy as np

    key = [SEED] + [zlib.crc32(str(k).encode()) for k in (stage, *items)]
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def draw_seeds(stage, name):
    """One seed per Table-2 draw (metrics.draws) of sample set `name`."""
    return [stream_seed(stage, name, d) for d in range(DRAWS)]


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


def diffusion_exports():
    """MERL .binary exports of the first `diffusion.export_merl` samples of ours and merl100."""
    return expand(out("samples/{set}/merl/sample_{i:03d}.binary"), set=["ours", "merl100"],
                  i=range(config["diffusion"]["export_merl"]))


# ----------------------------------------------------------------------------- BTF (btf.smk)

import re as _re

from neumat.data import ubo2014 as _ubo2014

UBO = config["ubo2014"]
BTF = config["btf"]
BTF_SUFFIX = "_resampled_W400xH400_L151xV151.btf"

if UBO["source"] == "synthetic":
    BTF_NAMES = [f"synthetic_{k}" for k in UBO["synthetic"]["kinds"]]
else:
    UBO_CAT = _ubo2014.load_catalog(UBO["catalog"], UBO["materials"]).set_index("name")
    BTF_NAMES = list(UBO["materials"])
BTF_NAME_RE = "|".join(map(_re.escape, BTF_NAMES)) or "^$"


def btf_file(name):
    """The DFMF file of one material in this run."""
    if UBO["source"] == "synthetic":
        return out(f"btf/data/{name}.btf")
    return f"resources/ubo2014/{name}{BTF_SUFFIX}"


def btf_roi(name):
    """Centre crop (x0, y0, w, h) from config btf.crop, or None for the whole texture."""
    size = UBO["synthetic"]["size"] if UBO["source"] == "synthetic" else 400
    c = BTF["crop"]
    if c is None or c >= size:
        return None
    o = (size - c) // 2
    return [o, o, c, c]


def btf_seed(name, method):
    return SEED + 6000 + 100 * BTF_NAMES.index(name) + ["data", *BTF["methods"]].index(method)


def _btf_fit_rule_params(method):
    return dict(method=method, roi=lambda w: btf_roi(w.name),
                seed=lambda w: btf_seed(w.name, method), settings=BTF.get(method, {}))
