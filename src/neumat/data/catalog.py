"""Material catalogue: MERL names -> type, text description, colour words.

The type is the name without colour words and numeric suffixes ("blue-metallic-paint2" ->
"metallic-paint"), with three merges that bring the 51 raw stems to the 48 types the M3ashy
paper uses: neoprene-rubber and pure-rubber -> rubber, ss440 (stainless steel) -> steel.
The description is the name in words ("blue metallic paint"); colour words are kept separately
so RGB-permuted copies can drop them (paper §4.4).
"""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd

COLOUR_WORDS = {
    "beige", "black", "blue", "brown", "dark", "light", "gold", "green", "gray", "maroon",
    "orange", "pink", "purple", "red", "silver", "violet", "white", "yellow",
}
TYPE_MERGES = {"neoprene-rubber": "rubber", "pure-rubber": "rubber", "ss440": "steel"}
COLUMNS = ["name", "sha256", "type", "description", "colours"]


def material_type(name: str) -> str:
    """'blue-metallic-paint2' -> 'metallic-paint'; 'cherry-235' -> 'cherry'."""
    if name in TYPE_MERGES:
        return TYPE_MERGES[name]
    words = [w for w in name.split("-") if w not in COLOUR_WORDS and not w.isdigit()]
    stem = "-".join(words)
    return TYPE_MERGES.get(stem, re.sub(r"(?<=[a-z])\d+$", "", stem))


def colour_words(name: str) -> list[str]:
    return [w for w in name.split("-") if w in COLOUR_WORDS]


def description(name: str) -> str:
    """'blue-metallic-paint2' -> 'blue metallic paint' (numbers dropped)."""
    words = [re.sub(r"\d+$", "", w) for w in name.split("-")]
    return " ".join(w for w in words if w)


def drop_colours(text: str, colours: list[str] | str) -> str:
    """Remove colour words from a description ('red metallic paint' -> 'metallic paint')."""
    if isinstance(colours, str):
        colours = colours.split() if colours else []
    return " ".join(w for w in text.split() if w not in set(colours))


def build_catalog(checksums_tsv: str | Path) -> pd.DataFrame:
    """The catalogue from a checksum table (name, sha256, ...): used to write
    config/merl_materials.tsv once; the workflow reads the committed TSV."""
    src = pd.read_csv(checksums_tsv, sep="\t")
    return pd.DataFrame({
        "name": src["name"],
        "sha256": src["sha256"],
        "type": [material_type(n) for n in src["name"]],
        "description": [description(n) for n in src["name"]],
        "colours": [" ".join(colour_words(n)) for n in src["name"]],
    })


def load_catalog(path: str | Path, subset=(), sha256_override=None) -> pd.DataFrame:
    """Read the committed catalogue, optionally restricted to `subset`, with checksum overrides."""
    cat = pd.read_csv(path, sep="\t", keep_default_na=False)
    missing = [c for c in COLUMNS if c not in cat.columns]
    if missing:
        raise ValueError(f"{path}: missing columns {missing}")
    sha256_override = sha256_override or {}
    unknown = sorted(set(subset) - set(cat["name"])) + sorted(set(sha256_override) - set(cat["name"]))
    if unknown:
        raise ValueError(f"config merl.subset / merl.sha256_override: unknown material(s) {unknown} "
                         f"(not in {path})")
    if subset:
        cat = cat[cat["name"].isin(subset)]
    cat = cat.copy()
    for name, sha in sha256_override.items():
        cat.loc[cat["name"] == name, "sha256"] = sha
    return cat.reset_index(drop=True)


def synthetic_catalog(count: int, seed: int) -> pd.DataFrame:
    """Catalogue of the analytic stand-in materials (merl.source = synthetic)."""
    from neumat.data import synthetic_merl

    specs = synthetic_merl.make_specs(count, seed)
    return pd.DataFrame({
        "name": [s.name for s in specs],
        "sha256": ["" for _ in specs],
        "type": [s.type for s in specs],
        "description": [description(s.name) for s in specs],
        "colours": [" ".join(colour_words(s.name)) for s in specs],
    })
