"""One source of truth for defaults: every library default that has a config key equals that
key's default in config/schema.yaml, so a library user gets the workflow's model."""

import dataclasses
import inspect
from pathlib import Path

import pytest
import yaml

from neumat.baselines.hyperbrdf import HyperConfig, HyperTrainConfig
from neumat.conditions.image import ImageEncoderConfig
from neumat.constrained import sample_category
from neumat.diffusion.model import DenoiserConfig
from neumat.diffusion.plausibility import plausibility
from neumat.diffusion.schedule import ScheduleConfig
from neumat.diffusion.train import Sampler, TrainConfig
from neumat.fit import FitSettings

SCHEMA = yaml.safe_load((Path(__file__).resolve().parents[1] / "config/schema.yaml").read_text())


def schema_defaults(*path: str) -> dict:
    """{key: default} of the schema section at `path` (e.g. 'diffusion', 'model')."""
    node = SCHEMA
    for p in path:
        node = node["properties"][p]
    return {k: v["default"] for k, v in node["properties"].items() if "default" in v}


def _dataclass_defaults(cls) -> dict:
    return {f.name: f.default for f in dataclasses.fields(cls)
            if f.default is not dataclasses.MISSING}


def _signature_defaults(fn) -> dict:
    return {k: p.default for k, p in inspect.signature(fn).parameters.items()
            if p.default is not inspect.Parameter.empty}


# (library defaults, schema section, library names without a config key: why)
CASES = {
    "FitSettings": (_dataclass_defaults(FitSettings), ("fit",), {}),
    "DenoiserConfig": (_dataclass_defaults(DenoiserConfig), ("diffusion", "model"),
                       {"n_classes": "set by the workflow from the catalogue's types"}),
    "ScheduleConfig": (_dataclass_defaults(ScheduleConfig), ("diffusion", "schedule"), {}),
    # HyperTrainConfig had the reference code's 20000 steps, 1 material a step and 4000 query
    # samples, ImageEncoderConfig 2000 steps (a review, 2026-11-29)
    "HyperConfig": (_dataclass_defaults(HyperConfig), ("hyperbrdf", "model"), {}),
    "HyperTrainConfig": (_dataclass_defaults(HyperTrainConfig), ("hyperbrdf", "train"), {}),
    "ImageEncoderConfig": (_dataclass_defaults(ImageEncoderConfig), ("conditions", "image", "encoder"), {}),
    "TrainConfig": (_dataclass_defaults(TrainConfig), ("diffusion", "train"), {}),
    "Sampler.sample": (_signature_defaults(Sampler.sample), ("diffusion", "sample"),
                       {"types": "None = unconditional; the workflow lists them",
                        "activation": "fit.activation: how the NBRDF decodes",
                        "category": "None = no category: constrained.sample_category names one",
                        "category_step": "constrained.guidance_step, which sample_category "
                                         "(checked below) passes with its category",
                        "offset": "rows of a draw made in several calls (neumat sample's "
                                  "batches), not a setting"}),
    # its `bins` is the bin indices (grid_bins(constrained.bins)), not the key's count
    "sample_category": ({k: v for k, v in _signature_defaults(sample_category).items() if k != "bins"},
                        ("constrained",),
                        {"guide_types": "the workflow derives them (constrained.guide: auto)",
                         "activation": "fit.activation: how the NBRDF decodes",
                         "progress": "a callback, not a setting",
                         "pilot_every_mode": "the workflow reports every mode's pilot (True); "
                                             "the CLI stops once -n are accepted"}),
    "plausibility": (
        {"angles": _signature_defaults(plausibility)["n_angles"],
         "explode_factor": _signature_defaults(plausibility)["explode_factor"]},
        ("diffusion",), {}),
}


@pytest.mark.parametrize("name", CASES)
def test_library_defaults_equal_schema_defaults(name):
    lib, path, exempt = CASES[name]
    schema = schema_defaults(*path)
    if name == "plausibility":
        schema = {"angles": schema["plausibility_angles"], "explode_factor": schema["explode_factor"]}
    shared = {k for k in lib if k in schema}
    unmatched = set(lib) - shared - set(exempt)
    assert not unmatched, f"{name}: library defaults with no key in schema {'.'.join(path)}: {unmatched}"
    diff = {k: (lib[k], schema[k]) for k in shared if lib[k] != schema[k]}
    assert not diff, f"{name} vs schema {'.'.join(path)} (library, schema): {diff}"


def test_speed_and_cosmetic_keys_are_schema_keys():
    """config/speed_keys.yaml names real schema keys, each with why and a value to try."""
    kinds = yaml.safe_load((Path(__file__).resolve().parents[1] / "config/speed_keys.yaml").read_text())
    assert set(kinds) == {"speed", "cosmetic", "neutral"}
    assert not set(kinds["speed"]) & set(kinds["cosmetic"])
    for key, entry in {**kinds["speed"], **kinds["cosmetic"]}.items():
        node = SCHEMA
        for part in key.split("."):
            assert part in node.get("properties", {}), f"{key}: not in config/schema.yaml"
            node = node["properties"][part]
        assert entry.get("why") and "try" in entry, key


def test_every_key_to_try_differs_from_the_tiny_config():
    """The caching test (tests/test_workflow.py) sets each speed or cosmetic key to its `try`
    on the tiny run: a `try` equal to the tiny config's value (or its default) tests nothing."""
    root = Path(__file__).resolve().parents[1]
    kinds = yaml.safe_load((root / "config/speed_keys.yaml").read_text())
    tiny = yaml.safe_load((root / "config/tiny.yaml").read_text())
    same = []
    for key, entry in {**kinds["speed"], **kinds["cosmetic"]}.items():
        node, cfg = SCHEMA, tiny
        for part in key.split("."):
            node = node["properties"][part]
            cfg = cfg.get(part, {}) if isinstance(cfg, dict) else {}
        value = cfg if cfg != {} else node.get("default")
        if entry["try"] == value:
            same.append(key)
    assert not same, same


def test_neutral_keys_default_to_their_neutral_value():
    """A neutral key leaves params only at the value that reproduces results made before it
    existed, and that value is its default: a config that does not set it reruns nothing."""
    kinds = yaml.safe_load((Path(__file__).resolve().parents[1] / "config/speed_keys.yaml").read_text())
    assert kinds["neutral"]
    for key, entry in kinds["neutral"].items():
        assert key not in kinds["speed"] and key not in kinds["cosmetic"], key
        node = SCHEMA
        for part in key.split("."):
            assert part in node.get("properties", {}), f"{key}: not in config/schema.yaml"
            node = node["properties"][part]
        assert entry.get("why") and node.get("default") == entry["value"], key
