"""Material catalogue of a run: name, sha256, type, text description and colour words, read from
config/merl_materials.tsv or made for the synthetic materials. How a name becomes a type and a
description is in neumat.data.names."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from neumat.data import synthetic_merl
from neumat.data.names import (COLOUR_WORDS, colour_words, description,  # noqa: F401
                               drop_colours, material_type)

COLUMNS = ["name", "sha256", "type", "description", "colours"]


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


def read_tsv(path: str | Path, key: str, columns) -> pd.DataFrame:
    """A catalogue (config `key`: MERL's or UBO2014's) read as text, with `columns` at least;
    an error naming the key and the file otherwise (the workflow reads it when it builds the
    DAG)."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"config {key}: {path} is not a file; give a tab-separated "
                                f"catalogue with columns {', '.join(columns)} (the default is "
                                f"the committed one)")
    try:
        cat = pd.read_csv(path, sep="\t", keep_default_na=False, dtype=str)
    except (UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as e:
        raise ValueError(f"config {key}: {path} is not a tab-separated text catalogue "
                         f"({type(e).__name__}: {e})") from e
    missing = [c for c in columns if c not in cat.columns]
    if missing:
        raise ValueError(f"config {key}: {path} lacks the column(s) {', '.join(missing)} "
                         f"(it has {', '.join(map(str, cat.columns))})")
    # a name is a material's file name and wildcard: empty, "resources/merl/.binary" was the
    # only error; a slash or outer blanks would put it elsewhere or fail far downstream
    if "name" in cat.columns:
        odd = [(i + 1, n) for i, n in enumerate(cat["name"])
               if not n or n != n.strip() or "/" in n or n in (".", "..")]
        if odd:  # rows as pandas counts them (blank lines skipped), the header not counted
            row, n = odd[0]
            raise ValueError(f"config {key}: {path} row {row}: name {n!r} is empty, has a "
                             f"slash or blanks around it ({len(odd)} such row(s)); each name "
                             f"becomes a file name: give a plain one")
    # a name is a material's key (its file, its split, its wildcard): a repeated one would
    # merge two rows into one split entry and could leave a split empty far downstream
    dup = sorted(set(cat.loc[cat["name"].duplicated(), "name"])) if "name" in cat.columns else []
    if dup:
        raise ValueError(f"config {key}: {path} lists the name(s) {', '.join(dup[:5])} more than "
                         f"once; each material needs a row of its own")
    return cat


def load_catalog(path: str | Path, subset=(), sha256_override=None) -> pd.DataFrame:
    """Read the committed catalogue, optionally restricted to `subset`, with checksum overrides."""
    cat = read_tsv(path, "merl.materials", COLUMNS)
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
    # as sha256sum prints them: Snakemake's ensure() compares the text, and on a mismatch it
    # deletes the file it has just verified (PowerShell's Get-FileHash prints upper case)
    cat["sha256"] = cat["sha256"].str.strip().str.lower()
    bad = cat[(cat["sha256"] != "") & ~cat["sha256"].str.fullmatch(r"[0-9a-f]{64}")]
    if len(bad):
        raise ValueError(f"config merl.materials: {path}: sha256 of {', '.join(bad['name'][:5])} is "
                         f"not 64 hexadecimal digits ({bad['sha256'].iloc[0]!r}); fix the column "
                         f"or give merl.sha256_override")
    return cat.reset_index(drop=True)


def unpinned(cat: pd.DataFrame) -> list[str]:
    """Materials of a catalogue without a sha256 (blank), which merl.verify_sha256 cannot check."""
    return list(cat.loc[cat["sha256"] == "", "name"])


def synthetic_catalog(count: int, seed: int) -> pd.DataFrame:
    """Catalogue of the analytic stand-in materials (merl.source = synthetic)."""
    specs = synthetic_merl.make_specs(count, seed)
    return pd.DataFrame({
        "name": [s.name for s in specs],
        "sha256": ["" for _ in specs],
        "type": [s.type for s in specs],
        "description": [description(s.name) for s in specs],
        "colours": [" ".join(colour_words(s.name)) for s in specs],
    })
