"""The run a `neumat` command reads: its directory, models, config and schema defaults, and the
errors and exit codes every subcommand shares."""

from __future__ import annotations

import re
import sys
from pathlib import Path

from neumat.io.images import FORMATS

EXIT_USAGE, EXIT_BUDGET = 2, 3
MODALITIES = ("type", "text", "image")
VECTOR_MODALITIES = ("text", "image")
MULTIMODAL = "multimodal"  # the model rule train_multimodal writes (workflow/rules/conditions.smk)
IMAGE_ENCODER = "conditions/image_encoder.pt"  # rule train_image_encoder
IMAGE_FORMATS = f"{FORMATS} showing one sphere filling the frame, like the metric view"
SCHEMA = Path(__file__).resolve().parents[3] / "config" / "schema.yaml"  # a source checkout's


class CLIError(Exception):
    """An error the user can fix; the message says how."""

    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(message)
        self.code = code


def _progress(total: int, desc: str):
    """A tqdm bar on a terminal (silent when stderr is not one)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="it", disable=None, file=sys.stderr, leave=False)


# ----------------------------------------------------------------------------- the run


class Run:
    """What a results/<run> directory holds (paths only; nothing is loaded until asked)."""

    def __init__(self, path: str | Path, overrides: dict | None = None):
        """`overrides`: config keys that win over the run's recorded ones (a benchmark's
        --config)."""
        self.path = Path(path)
        self.overrides = overrides or {}
        if not self.path.is_dir():
            raise CLIError(f"no run directory {self.path}: a run lives in results/<run>/ (the "
                           f"config's `run:` name); make one with `snakemake --cores 2 report "
                           f"--configfile config/<config>.yaml`")
        self.name = self.path.name

    def target(self, rel: str) -> str:
        """The snakemake command that builds `rel` (inside this run), run in the workflow's
        directory: targets are relative to it (an absolute run path gave an absolute target,
        which Snakemake rejects with MissingRuleException)."""
        return (f"snakemake --cores 2 results/{self.name}/{rel} --configfile <the config whose "
                f"run: is {self.name!r}>")

    def models(self) -> dict[str, Path]:
        return {p.parent.name: p for p in sorted(self.path.glob("diffusion/*/model.pt"))}

    def model_path(self, model: str, why: str = "") -> Path:
        """The model's file; `why` (e.g. "--text needs it") goes into the error when it is missing."""
        p = self.path / "diffusion" / model / "model.pt"
        if not p.exists():
            have = ", ".join(self.models()) or "none"
            rule = {MULTIMODAL: "train_multimodal", "refiner": "train_refiner"}.get(
                model, "train_diffusion")
            raise CLIError(f"no diffusion model {model!r} in {self.path} (models here: {have})"
                           f"{'; ' + why if why else ''}. Build it with rule {rule}: "
                           f"`{self.target(f'diffusion/{model}/model.pt')}`"
                           f"{'' if why else ', or pick one with --model'}")
        return p

    def text_embedding(self, prompt: str):
        """(1, 384) float32: the run's own embedding of `prompt` when rule text_embeddings made
        one (a config or test-split prompt, `conditions/prompts.npy`, or a training description,
        `conditions/text.npy`), with the file it came from; else (None, None). The row is what
        the run's workflow conditioned on (the encoder, run on a batch, can differ from one
        prompt alone in the last bits), and the encoder's ~5 s of loading are saved."""
        import numpy as np
        import pandas as pd
        cond = self.path / "conditions"
        descriptions = cond / "descriptions.tsv"  # colour_words: measured, as embedded
        for table, column, rows in (
                (cond / "prompts.tsv", "prompt", cond / "prompts.npy"),
                (descriptions, "embedded", cond / "text.npy") if descriptions.exists() else
                (self.path / "neumerl/manifest.tsv", "description", cond / "text.npy")):
            try:
                texts = pd.read_csv(table, sep="\t", keep_default_na=False)[column].tolist()
                if prompt not in texts:
                    continue
                emb = np.load(rows, mmap_mode="r")
            except (OSError, KeyError, ValueError):  # not built, or not this run's layout
                continue
            if emb.ndim == 2 and len(emb) == len(texts):  # else a half-rebuilt run: encode
                return np.array(emb[texts.index(prompt)][None], np.float32), rows
        return None, None

    def image_encoder(self) -> Path | None:
        p = self.path / IMAGE_ENCODER
        return p if p.exists() else None

    def setting(self, *keys: str):
        """A config value of this run (report/index.md), or the schema's default when the run
        has not recorded its config yet (config/schema.yaml of a source checkout); a key in
        `overrides` first."""
        node = self.overrides
        for k in keys:
            if not isinstance(node, dict) or k not in node:
                break
            node = node[k]
        else:
            return node
        value = self.config()
        for k in keys:
            value = value.get(k) if isinstance(value, dict) else None
        if value is not None:
            return value
        return schema_default(*keys, hint=f"the run has no recorded config "
                                          f"({self.path / 'report/index.md'})")

    def config(self) -> dict | None:
        """The run's config (defaults filled in), as recorded in report/index.md by `report`;
        parsed once per Run (`neumat sample` asks it for several keys)."""
        if not hasattr(self, "_config"):
            self._config = self._read_config()
        return self._config

    def _read_config(self) -> dict | None:
        import yaml
        md = self.path / "report" / "index.md"
        if not md.exists():
            return None
        m = re.search(r"## Configuration of this run.*?```yaml\n(.*?)```", md.read_text(), re.S)
        if not m:
            return None
        return yaml.load(m.group(1), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))

    def activation(self) -> str:
        cfg = self.config() or {}
        return cfg.get("fit", {}).get("activation", "relu")


def schema_default(*keys: str, hint: str = ""):
    """The default of config key keys[0].keys[1]... from config/schema.yaml."""
    import yaml
    node = {"properties": yaml.safe_load(SCHEMA.read_text())["properties"]} if SCHEMA.exists() else None
    for k in keys:
        node = (node or {}).get("properties", {}).get(k)
    if node is None or "default" not in node:
        raise CLIError(f"no value for config key {'.'.join(keys)}: {hint or 'not in the run'} and "
                       f"{SCHEMA} has no default for it; give the value on the command line")
    return node["default"]


def load_model(path: Path) -> dict:
    import torch
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # a damaged or foreign file
        raise CLIError(f"{path}: not a neumat diffusion model ({type(e).__name__}: {e}); rebuild it "
                       f"with `snakemake --cores 2 {path} --forcerun train_diffusion --configfile ...`")


def model_conditions(bundle: dict) -> list[str]:
    """The conditions a model was trained with, in MODALITIES order."""
    vec = bundle["model_cfg"].get("vector_conditions", {}) or {}
    return (["type"] if bundle.get("class_names") else []) + [m for m in VECTOR_MODALITIES if m in vec]


def unsupported(bundle: dict, modality: str, path: Path) -> str | None:
    """Why `modality` cannot condition this model, or None when it can (the model was trained
    with it; encoders are checked where they are loaded)."""
    if modality in model_conditions(bundle):
        return None
    if modality == "type":
        return f"{path} was trained without type labels"
    return (f"{path} was trained without {modality} conditioning (its conditions: "
            f"{', '.join(model_conditions(bundle)) or 'none'}); {modality}-conditioned sampling "
            f"needs the multimodal model (rule train_multimodal; leave out --model to use it)")
