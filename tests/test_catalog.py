"""The MERL material catalogue (config/merl_materials.tsv, neumat.data.catalog)."""

from pathlib import Path

import pandas as pd
import pytest

from neumat.data import catalog

ROOT = Path(__file__).parents[1]
TSV = ROOT / "config" / "merl_materials.tsv"
SHARED_CHECKSUMS = Path(__file__).parents[2] / "shared" / "data" / "merl_checksums.tsv"


@pytest.fixture(scope="module")
def cat():
    return catalog.load_catalog(TSV)


def test_hundred_materials_48_types(cat):
    assert len(cat) == 100 and cat["name"].is_unique
    assert cat["sha256"].str.fullmatch(r"[0-9a-f]{64}").all()
    assert cat["type"].nunique() == 48
    assert list(cat["type"]) == [catalog.material_type(n) for n in cat["name"]]
    counts = cat["type"].value_counts()
    assert counts["fabric"] == 11 and counts["metallic-paint"] == 10
    assert counts["rubber"] == 4 and counts["steel"] == 2  # merged stems


@pytest.mark.parametrize("name, type_", [
    ("blue-metallic-paint2", "metallic-paint"), ("cherry-235", "cherry"),
    ("specular-violet-phenolic", "specular-phenolic"), ("neoprene-rubber", "rubber"),
    ("pure-rubber", "rubber"), ("ss440", "steel"), ("color-changing-paint3", "color-changing-paint"),
    ("two-layer-gold", "two-layer"), ("dark-blue-paint", "paint"), ("natural-209", "natural"),
])
def test_material_type(name, type_):
    assert catalog.material_type(name) == type_


def test_descriptions_and_colours(cat):
    row = cat.set_index("name")
    assert catalog.description("blue-metallic-paint2") == "blue metallic paint"
    assert row.at["blue-metallic-paint2", "description"] == "blue metallic paint"
    assert row.at["specular-violet-phenolic", "colours"] == "violet"
    assert row.at["dark-blue-paint", "colours"] == "dark blue"
    assert row.at["cherry-235", "description"] == "cherry"
    assert row.at["alum-bronze", "colours"] == ""
    assert list(cat["description"]) == [catalog.description(n) for n in cat["name"]]


def test_drop_colours():
    assert catalog.drop_colours("red metallic paint", "red") == "metallic paint"
    assert catalog.drop_colours("dark blue paint", ["dark", "blue"]) == "paint"
    assert catalog.drop_colours("alum bronze", "") == "alum bronze"
    # only whole words: "redwood" is not a colour
    assert catalog.drop_colours("red redwood", "red") == "redwood"


def test_subset_and_override(cat):
    sub = catalog.load_catalog(TSV, subset=["chrome", "alum-bronze"],
                               sha256_override={"chrome": "0" * 64})
    assert list(sub["name"]) == ["alum-bronze", "chrome"]  # catalogue order
    assert sub.set_index("name").at["chrome", "sha256"] == "0" * 64
    assert sub.set_index("name").at["alum-bronze", "sha256"] == cat.set_index("name").at["alum-bronze", "sha256"]


def test_sha256_as_sha256sum_prints_it(tmp_path):
    """Upper case or padded hashes (PowerShell's Get-FileHash) are read as sha256sum prints them
    (Snakemake's ensure() compares the text, and deletes a verified file on a mismatch); a
    value that is no sha256 is refused naming the key; blanks are listed as unpinned."""
    text = TSV.read_text().splitlines()
    name, sha = text[1].split("\t")[:2]
    rows = [text[0], text[1].replace(sha, " " + sha.upper() + " "), text[2].replace(text[2].split("\t")[1], "")]
    (tmp_path / "c.tsv").write_text("\n".join(rows) + "\n")
    cat = catalog.load_catalog(tmp_path / "c.tsv")
    assert cat.at[0, "sha256"] == sha and catalog.unpinned(cat) == [rows[2].split("\t")[0]]
    (tmp_path / "d.tsv").write_text("\n".join([text[0], text[1].replace(sha, sha[:20])]) + "\n")
    with pytest.raises(ValueError, match=rf"merl.materials: .*d.tsv: sha256 of {name} is not 64"):
        catalog.load_catalog(tmp_path / "d.tsv")


def test_unknown_subset_names_error():
    with pytest.raises(ValueError, match=r"merl\.subset.*\['chrom', 'nope'\]"):
        catalog.load_catalog(TSV, subset=["chrome", "nope", "chrom"])
    with pytest.raises(ValueError, match=r"sha256_override.*'nope'"):
        catalog.load_catalog(TSV, sha256_override={"nope": "0" * 64})


def test_missing_columns_error(tmp_path):
    p = tmp_path / "bad.tsv"
    pd.read_csv(TSV, sep="\t").drop(columns=["type"]).to_csv(p, sep="\t", index=False)
    with pytest.raises(ValueError, match=r"bad\.tsv.*type"):
        catalog.load_catalog(p)


def test_matches_shared_checksums(cat):
    if not SHARED_CHECKSUMS.exists():
        pytest.skip(f"{SHARED_CHECKSUMS} not available")
    ref = pd.read_csv(SHARED_CHECKSUMS, sep="\t")
    assert dict(zip(ref["name"], ref["sha256"])) == dict(zip(cat["name"], cat["sha256"]))
    rebuilt = catalog.build_catalog(SHARED_CHECKSUMS)
    pd.testing.assert_frame_equal(rebuilt, cat[catalog.COLUMNS])
