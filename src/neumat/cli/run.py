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
# config/schema.yaml, through a link beside this file that a wheel stores as the file itself
# (package data), so an installed `neumat` has the defaults too
SCHEMA = Path(__file__).with_name("schema.yaml")
ACTIVATIONS = ("relu", "leaky_relu")  # neumat.nbrdf.ACTIVATIONS, without importing torch
# what Sampler reads from a diffusion model file (neumat.diffusion.train.Sampler), of which type
MODEL_KEYS = {"model_cfg": dict, "sched_cfg": dict, "class_names": list, "ema": dict,
              "normalizer": dict}
_ABSENT = object()  # a key a config does not have (a recorded null is a value, None)


class CLIError(Exception):
    """An error the user can fix; the message says how."""

    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(message)
        self.code = code


def _progress(total: int, desc: str):
    """A tqdm bar on a terminal (silent when stderr is not one)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="it", disable=None, file=sys.stderr, leave=False)


def check_out_dir(path: Path, option: str) -> None:
    """CLIError unless directory `path` exists or can be made: its nearest existing ancestor
    is a directory (checked before any work, so no draw is lost to a bad --out)."""
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                raise CLIError(f"{option}: {p} is a file, not a directory; give another path")
            return


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

    def target(self, rel: str, flags: str = "") -> str:
        """The snakemake command that builds `rel` (inside this run), run in the workflow's
        directory: targets are relative to it (an absolute run path gave an absolute target,
        which Snakemake rejects with MissingRuleException); `flags` e.g. --forcerun RULE."""
        return (f"snakemake --cores 2 results/{self.name}/{rel} {flags + ' ' if flags else ''}"
                f"--configfile <the config whose run: is {self.name!r}>")

    def unreadable(self, rel: str, rule: str | None, why: Exception | str) -> CLIError:
        """The error for the run's file `rel` that is damaged or foreign: rule `rule` remakes it
        (--forcerun: the file exists, so Snakemake would not rebuild it otherwise); None where
        several rules write such files (samples/<set>/): --force on the file itself."""
        if isinstance(why, Exception):
            why = _cause(why)
        by = f" by rule {rule}" if rule else ""
        flags = f"--forcerun {rule}" if rule else "--force"
        return CLIError(f"{self.path / rel}: damaged, or not written{by} ({why}); "
                        f"rebuild it: `{self.target(rel, flags)}`")

    def array(self, rel: str, rule: str | None, mmap: bool = False):
        """The run's .npy file `rel` (no pickles), or the `unreadable` error naming it and the
        rule that remakes it (a truncated file gave numpy's bare EOF error)."""
        import numpy as np
        try:
            return np.load(self.path / rel, mmap_mode="r" if mmap else None)
        except (OSError, ValueError, EOFError) as e:
            raise self.unreadable(rel, rule, e) from None

    def table(self, rel: str, rule: str | None, columns=()):
        """The run's TSV `rel` as text-keeping pandas, with `columns`, or the `unreadable`
        error naming it and its rule."""
        import pandas as pd
        try:
            t = pd.read_csv(self.path / rel, sep="\t", keep_default_na=False)
        except (OSError, ValueError, UnicodeDecodeError) as e:  # ParserError, EmptyDataError
            raise self.unreadable(rel, rule, e) from None
        missing = [c for c in columns if c not in t.columns]
        if missing:
            raise self.unreadable(rel, rule, f"no column {', '.join(missing)}")
        return t

    def models(self) -> dict[str, Path]:
        return {p.parent.name: p for p in sorted(self.path.glob("diffusion/*/model.pt"))}

    def model_path(self, model: str, why: str = "") -> Path:
        """The model's file; `why` (e.g. "--text needs it") goes into the error when it is missing."""
        p = self.path / "diffusion" / model / "model.pt"
        if not p.exists():
            have = ", ".join(self.models()) or "none"
            raise CLIError(f"no diffusion model {model!r} in {self.path} (models here: {have})"
                           f"{'; ' + why if why else ''}. Build it with rule {model_rule(model)}: "
                           f"`{self.target(f'diffusion/{model}/model.pt')}`"
                           f"{'' if why else ', or pick one with --model'}")
        return p

    def load_model(self, model: str) -> dict:
        """The bundle of diffusion/<model>/model.pt (tensors and plain values only), with the
        keys sampling reads; a CLIError naming the rule that remakes a damaged or foreign file."""
        from neumat.io import modelfile
        rel = f"diffusion/{model}/model.pt"
        try:
            bundle = modelfile.load(self.path / rel, finite=True)
        except Exception as e:  # refused pickles and bad zips: the cause, under modelfile's error
            raise self.unreadable(rel, model_rule(model), e) from None
        get = bundle.get if isinstance(bundle, dict) else lambda k: None
        missing = [k for k, kind in MODEL_KEYS.items() if not isinstance(get(k), kind)]
        if missing:
            raise self.unreadable(rel, model_rule(model), f"no {', '.join(missing)} in it")
        return bundle

    def text_embedding(self, prompt: str):
        """(1, 384) float32: the run's own embedding of `prompt` when the run made one (a config
        or test-split prompt, rule prompt_embeddings' `conditions/prompts.npy`, or a training
        description, rule text_embeddings' `conditions/text.npy`), with the file it came from; else (None, None). The row is what
        the run's workflow conditioned on (the encoder, run on a batch, can differ from one
        prompt alone in the last bits), and the encoder's ~5 s of loading are saved."""
        import numpy as np
        import pandas as pd
        cond = self.path / "conditions"
        descriptions = cond / "descriptions.tsv"  # colour_words: measured, as embedded
        for table, column, rows, rule in (
                (cond / "prompts.tsv", "prompt", cond / "prompts.npy", "prompt_embeddings"),
                (descriptions, "embedded", cond / "text.npy", "text_embeddings")
                if descriptions.exists() else
                (self.path / "neumerl/manifest.tsv", "description", cond / "text.npy",
                 "text_embeddings")):
            try:
                texts = pd.read_csv(table, sep="\t", keep_default_na=False)[column].tolist()
            except (OSError, KeyError, ValueError):  # not built, or not this run's layout
                continue
            if prompt not in texts:
                continue
            try:
                emb = np.load(rows, mmap_mode="r")
                fits = emb.ndim == 2 and len(emb) == len(texts) and emb.dtype.kind == "f"
                why = "" if fits else f"shape {emb.shape} ({emb.dtype}) for {len(texts)} texts"
            except (OSError, ValueError) as e:
                why = _cause(e)
            if not why:
                return np.array(emb[texts.index(prompt)][None], np.float32), rows
            # the table lists the prompt but its embeddings are damaged or half rebuilt: say
            # so (the run's files are the user's to mend), then encode the prompt afresh
            print(f"neumat: {rows} does not hold {table.name}'s embeddings ({why}); encoding "
                  f"the prompt instead. Rebuild it: "
                  f"`{self.target(str(rows.relative_to(self.path)), f'--forcerun {rule}')}`",
                  file=sys.stderr)
        return None, None

    def image_encoder(self) -> Path | None:
        p = self.path / IMAGE_ENCODER
        return p if p.exists() else None

    def setting(self, *keys: str):
        """A config value of this run: a key in `overrides` first, then the run's recorded
        config (report/index.md; a recorded null is a value, e.g. constrained.bins: null = all
        bins), else the schema's default (a run that has not recorded its config yet)."""
        for source in (self.overrides, self.config()):
            value = _lookup(source, keys)
            if value is not _ABSENT:
                return value
        recorded = self.path / "report/index.md"
        return schema_default(*keys, hint=f"the run's recorded config ({recorded}) lacks it"
                              if self.config() else f"the run has no recorded config ({recorded})")

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
        try:
            cfg = yaml.load(m.group(1), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
        except yaml.YAMLError as e:
            raise self.unreadable("report/index.md", "report", e) from None
        if not isinstance(cfg, dict):
            raise self.unreadable("report/index.md", "report", "its configuration is not a mapping")
        return cfg

    def activation(self) -> str:
        cfg = self.config() or {}
        return cfg.get("fit", {}).get("activation", "relu")


def _cause(e: Exception) -> str:
    """An exception in one line; of torch.load(weights_only=True)'s page, which advises
    weights_only=False (running the file's code), only the cause (also under the ValueError of
    neumat.io.modelfile.load, which quotes the page's first line)."""
    e = e.__cause__ if isinstance(e.__cause__, Exception) else e
    text = str(e).strip()
    if "WeightsUnpickler error:" in text:
        cause = (text.split("WeightsUnpickler error:", 1)[1].strip().splitlines() or ["?"])[0]
        return f"torch.load(weights_only=True) refuses it: {cause}"
    return f"{type(e).__name__}: {(text.splitlines() or [''])[0]}"


def _lookup(node, keys: tuple[str, ...]):
    """node[keys[0]][keys[1]]..., or _ABSENT where a key is missing."""
    for k in keys:
        if not isinstance(node, dict) or k not in node:
            return _ABSENT
        node = node[k]
    return node


def schema_default(*keys: str, hint: str = ""):
    """The default of config key keys[0].keys[1]... from config/schema.yaml."""
    import yaml
    if not SCHEMA.is_file():  # e.g. a copy of the package without its data
        raise CLIError(f"no value for config key {'.'.join(keys)}: {hint or 'not in the run'}, and "
                       f"the config schema with the defaults ({SCHEMA}) is missing: reinstall "
                       f"neumat (`pip install .` in the source checkout), or build the run's "
                       f"report, which records its config")
    node = {"properties": yaml.safe_load(SCHEMA.read_text())["properties"]}
    for k in keys:
        node = (node or {}).get("properties", {}).get(k)
    if node is None or "default" not in node:
        raise CLIError(f"no value for config key {'.'.join(keys)}: {hint or 'not in the run'} and "
                       f"{SCHEMA} has no default for it; give the value on the command line")
    return node["default"]


def model_rule(model: str) -> str:
    """The rule that writes diffusion/<model>/model.pt (workflow/rules/)."""
    return {MULTIMODAL: "train_multimodal", "refiner": "train_refiner"}.get(model, "train_diffusion")


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
