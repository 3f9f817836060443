"""Bad input fails with a clear message before any job runs (or, for tables only readable by a
job, as soon as the table is read), naming the key or file and what to do."""

import logging
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from neumat import augment
from neumat.data import catalog, merl_files, ubo2014
from neumat.io import merl

ROOT = Path(__file__).resolve().parents[1]


def _dry_run(tmp_path, extra: dict, base="config/config.yaml"):
    for item in ("Snakefile", "workflow", "config", "src"):
        src = ROOT / item
        (shutil.copytree if src.is_dir() else shutil.copy)(src, tmp_path / item)
    (tmp_path / "extra.yaml").write_text(yaml.safe_dump(extra))
    res = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "1", "report", "--dry-run",
                          "--configfile", base, "extra.yaml"], cwd=tmp_path, capture_output=True,
                         text=True)
    return res.returncode, res.stdout + res.stderr


# check_cross_keys (common.smk): values the schema accepts one by one but that do not go
# together. Each had failed late (in a job: after training, after the fits, or as a
# MissingInputException naming a file, not the key) or silently given another result than asked.
# The keys that leave the split and the catalogue alone are refused together in one dry run
# (a DAG build each: 2.4 s; check_cross_keys names every clause); the rest one run each.
TOGETHER = [
    ({"diffusion": {"model": {"width": 60, "heads": 8}}},
     "diffusion.model.width 60 is not a multiple of diffusion.model.heads 8"),
    ({"diffusion": {"sample": {"steps": 500}, "schedule": {"timesteps": 100}}},
     "diffusion.sample.steps 500 exceeds diffusion.schedule.timesteps 100"),
    ({"conditions": {"image": {"encoder": {"crop": 40, "resolution": 32}}}},
     "conditions.image.encoder.crop 40 exceeds"),
    ({"metrics": {"models": ["training_set", "ourss"]}}, "metrics.models ['ourss']: not Table 2 models"),
    ({"diffusion": {"types": ["nonexistent_type"]}}, "diffusion.types ['nonexistent_type']: no material"),
    ({"fit": {"export": ["mix9999"]}}, "fit.export ['mix9999']: not AugMERL materials of this run"),
    # Table 3: each failed in a job (hyperbrdf_eval after both trainings; train_hyperbrdf after
    # reading every shard), naming one key (tiny: augmerl.bins 16384, train_bins 8192)
    ({"hyperbrdf": {"sparse_samples": 20000}}, "hyperbrdf.sparse_samples 20000 exceeds augmerl.bins 16384"),
    ({"hyperbrdf": {"train": {"query": 9000}}}, "hyperbrdf.train.query 9000 exceeds hyperbrdf.train_bins 8192"),
    # each failed in a job: the AugMERL figure after the PCA, the fits in fit_template
    ({"augmerl": {"figure_pair": ["nonexistent", "other"]}},
     "augmerl.figure_material / figure_pair ['nonexistent', 'other']: not materials of this run"),
    ({"fit": {"batch": 16000}}, "fit.batch 16000 exceeds the training bins of a fit: augmerl.bins 16384"),
    # constrained synthesis: medium-specular unreachable, its budget spent with no hint
    ({"constrained": {"derive": {"specular_quantiles": [0.9, 0.1]}}},
     "constrained.derive.specular_quantiles [0.9, 0.1]"),
    ({"constrained": {"thresholds": {"high_peak": 10, "medium_peak": 100}}},
     "constrained.thresholds.medium_peak 100.0 exceeds high_peak 10.0"),
    # export_samples failed after the trainings
    ({"diffusion": {"export_merl": 40}}, "diffusion.export_merl 40 exceeds the samples a set holds (16 test materials x metrics.draws 2)"),
    # the learning rate never reached diffusion.train.lr nor decayed; an untrained null class
    ({"diffusion": {"train": {"warmup_steps": 200}}},
     "diffusion.train.warmup_steps 200 is not below diffusion.train.steps 200"),
    ({"diffusion": {"train": {"cond_drop": 0.0}, "sample": {"guidance": 2.0}}},
     "diffusion.train.cond_drop 0 with diffusion.sample.guidance 2.0: guidance needs the null "
     "class"),
]


def _leaves(d: dict, path=()) -> list:
    return [x for k, v in d.items()
            for x in (_leaves(v, path + (k,)) if isinstance(v, dict) else [path + (k,)])]


def _merged(overlays: list) -> dict:
    """One overlay of several; a key given by two of them is an error (one would be lost)."""
    paths = [p for o in overlays for p in _leaves(o)]
    assert len(paths) == len(set(paths)), sorted(paths)
    out = {}
    for path in paths:
        node, src = out, next(o for o in overlays if path in _leaves(o))
        for k in path[:-1]:
            node, src = node.setdefault(k, {}), src[k]
        node[path[-1]] = src[path[-1]]
    return out


def test_keys_that_do_not_go_together_are_refused_together_when_the_dag_is_built(tmp_path):
    extra = _merged([e for e, _ in TOGETHER])
    rc, text = _dry_run(tmp_path, extra, "config/tiny.yaml")
    assert rc != 0 and "bad config: " in text, text[-3000:]
    missing = [says for _, says in TOGETHER if says not in text]
    assert not missing, (missing, text[-4000:])
    assert not (tmp_path / "results").exists()


@pytest.mark.parametrize("extra, says", [
    # Table 2's Training-set draws were cut to train // draws rows, below the reference set's
    # size, with only a warning in one log: its COV was capped and its 1-NNA off 50 %
    ({"augmerl": {"test_fraction": 0.5}},
     "the train split holds 32 materials, fewer than metrics.draws 2 x the 32-material test "
     "split: Table 2's Training-set draws would hold 16, not 32"),
    # every material downloaded the same file, and the checksum error advised pinning it
    ({"merl": {"source": "download", "url": "file:///tmp/one.binary"}},
     "merl.url 'file:///tmp/one.binary' has no {name} placeholder: every material would "
     "download the same file"),
    # MERL100 and HyperBRDF's merl model trained on the one train-split original, no message
    # (two sources split 1:1, the other checks quiet with one draw)
    ({"merl": {"synthetic": {"count": 2}}, "metrics": {"draws": 1}},
     "the train split holds 1 source material of 2 (merl.subset, merl.synthetic.count, "
     "augmerl.test_fraction): MERL100 and HyperBRDF's merl model"),
    # another augmerl.bins, fit.batch or diffusion.types than the run above gives
    ({"augmerl": {"bins": 900}, "hyperbrdf": {"sparse_samples": 500}},
     "hyperbrdf.train.context 1000 exceeds augmerl.bins 900"),
    ({"fit": {"batch": 500, "kernel": "c"}}, "fit.batch 500 is not a multiple of 16"),
    # each failed in a job, after the fits and the trainings: Table 2's sanity row (a test
    # split of 2), sample_type (acrylic: only held-out sources in tiny)
    ({"augmerl": {"permutations": False, "size": 8}, "fit": {"export": []}},
     "the test split holds 2 materials"),
    ({"diffusion": {"types": ["acrylic"]}}, "diffusion.types ['acrylic']: only test-split materials have that type"),
])
def test_keys_that_do_not_go_together_fail_when_the_dag_is_built(tmp_path, extra, says):
    rc, text = _dry_run(tmp_path, extra, "config/tiny.yaml")
    assert rc != 0 and "bad config: " in text and says in text, text[-2000:]
    assert not (tmp_path / "results").exists()


def test_no_btf_material_fails_when_the_dag_is_built(tmp_path):
    rc, text = _dry_run(tmp_path, {"ubo2014": {"synthetic": {"kinds": []}}}, "config/tiny.yaml")
    assert rc != 0 and "bad config (ubo2014.synthetic.kinds): [] names no BTF material" in text
    assert not (tmp_path / "results").exists()


def test_independent_bad_keys_are_refused_together(tmp_path):
    """Each failed in a job (train_vae, btf_pca, every download with a bare KeyError,
    sample_constrained spending its budget, the tiling renders): one dry run names them all, a
    clause each (one run, not five: each dry run costs a DAG build)."""
    extra = {"baselines": {"vae_a": {"context": 5000}},
             "btf": {"pca": {"components": 10, "fit_texels": 4},
                     "tiling": {"lights": [[0.5, 0.5, 0.0]]}},
             "merl": {"url": "http://x/{nam}.binary"},
             "constrained": {"per_category": 100, "budget": 16}}
    rc, text = _dry_run(tmp_path, extra, "config/tiny.yaml")
    assert rc != 0 and "bad config: " in text, text[-2000:]
    for says in ("baselines.vae_a.context 5000 + queries",
                 "btf.pca.components 10 exceeds btf.pca.fit_texels 4",
                 "merl.url 'http://x/{nam}.binary': KeyError 'nam'",
                 "constrained.per_category 100 exceeds constrained.budget 16",
                 "btf.tiling.lights [[0.5, 0.5, 0.0]]: on or below the plane"):
        assert says in text, (says, text[-2000:])
    assert not (tmp_path / "results").exists()


def test_subset_of_one_material_fails_when_the_dag_is_built(tmp_path):
    rc, text = _dry_run(tmp_path, {"merl": {"subset": ["alum-bronze"]}})
    assert rc != 0
    assert "merl.subset" in text and "augmerl.test_fraction" in text and "at least 2" in text
    assert not (tmp_path / "results").exists()


def test_eps_prediction_with_an_x0_loss_fails_when_the_dag_is_built(tmp_path):
    rc, text = _dry_run(tmp_path, {"diffusion": {"schedule": {"prediction": "eps", "loss": "x0"}}},
                        "config/tiny.yaml")
    assert rc != 0 and "prediction: eps with diffusion.schedule.loss: x0" in text
    assert not (tmp_path / "results").exists()


def test_start_keys_without_a_start_fail_when_the_dag_is_built(tmp_path):
    """conditions.text.start_match picks a start material: at strength 1 there is none. The
    check (neumat.conditions.starts.check; each key: test_start_keys_need_a_strength_below_one)
    runs when the DAG is built."""
    rc, text = _dry_run(tmp_path, {"conditions": {"text": {
        "start_match": True, "refiner": False, "strength": 1.0}}}, "config/tiny.yaml")
    assert rc != 0
    assert "conditions.text.start_match" in text and "conditions.text.strength < 1" in text
    assert not (tmp_path / "results").exists()


@pytest.mark.parametrize("modality, key", [("image", "refiner"), ("type", "refiner"),
                                            ("text", "refiner"), ("text", "start_match")])
def test_start_keys_need_a_strength_below_one(modality, key):
    """conditions.{image,type,text}.refiner refine a start material and
    conditions.text.start_match picks it: at strength 1 there is none, and the error names both
    keys; below 1, or with the key off, the config passes."""
    from neumat.conditions import starts
    cfg = {m: {"strength": 1.0, "refiner": False, "start_match": False}
           for m in ("image", "type", "text")}
    starts.check(cfg)
    cfg[modality][key] = True
    with pytest.raises(ValueError, match=rf"conditions\.{modality}\.{key}: true .*"
                                         rf"conditions\.{modality}\.strength < 1"):
        starts.check(cfg)
    cfg[modality]["strength"] = 0.05
    starts.check(cfg)


def test_check_split():
    augment.check_split(["a", "b"], 0.05)
    with pytest.raises(ValueError, match=r"merl.subset.*\['a'\].*test_fraction = 0.5.*at least 2"):
        augment.check_split(["a"], 0.5)
    with pytest.raises(ValueError, match="test_fraction = 0"):
        augment.check_split(["a", "b"], 0)
    # two sources without permutations: one row a split, nothing to interpolate
    augment.check_split(["a", "b"], 0.5, permutations=False, size=2)
    augment.check_split(["a", "b"], 0.5, permutations=True, size=40)
    with pytest.raises(ValueError, match="augmerl.size = 8 .* augmerl.permutations is false"):
        augment.check_split(["a", "b"], 0.5, permutations=False, size=8)


def test_a_split_of_one_row_gets_no_interpolations():
    """plan_pairs crashed (numpy: cannot take a larger sample than population) on a split of
    one row; its share of the interpolations now goes to the splits that can mix."""
    import pandas as pd
    names = ["a", "b", "c", "d"]
    cat = pd.DataFrame({"name": names, "sha256": "", "type": "t", "description": names,
                        "colours": ""})
    split = {"a": "test", "b": "train", "c": "train", "d": "train"}
    rows = augment.plan_rows(cat, False, split)
    pairs = augment.plan_pairs(rows, 10, 0)
    assert len(pairs) == 10 and all(rows.at[a, "split"] == "train" == rows.at[b, "split"]
                                    for a, b, _ in pairs)
    one_each = augment.plan_rows(cat.iloc[:2], False, {"a": "test", "b": "train"})
    assert augment.plan_pairs(one_each, 0, 0) == []
    with pytest.raises(ValueError, match="no split has two rows"):
        augment.plan_pairs(one_each, 3, 0)


def test_catalogues_that_are_missing_or_not_text_name_key_and_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"config merl.materials: .*nope\.tsv is not a file"):
        catalog.load_catalog(tmp_path / "nope.tsv")
    (tmp_path / "img.tsv").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    with pytest.raises(ValueError, match=r"config merl.materials: .*img\.tsv is not a tab-separated"):
        catalog.load_catalog(tmp_path / "img.tsv")
    (tmp_path / "cols.tsv").write_text("name\tcategory\ncarpet01\tcarpet\n")
    with pytest.raises(ValueError, match=r"config ubo2014.catalog: .*cols\.tsv lacks the column\(s\) "
                                         r"file \(it has name, category\)"):
        ubo2014.load_catalog(tmp_path / "cols.tsv")
    # a repeated name: split_sources would merge its two rows into one split entry
    rows = (ROOT / "config/merl_materials.tsv").read_text().splitlines()
    (tmp_path / "dup.tsv").write_text("\n".join(rows + [rows[3]]) + "\n")
    name = rows[3].split("\t")[0]
    with pytest.raises(ValueError, match=rf"config merl.materials: .*dup\.tsv lists the name\(s\) "
                                         rf"{name} more than once"):
        catalog.load_catalog(tmp_path / "dup.tsv")
    # an empty name or one with a slash: the dry run's only word was a missing
    # resources/merl/.binary
    for bad in ("", "sub/dir", " blue"):
        row = rows[3].split("\t")
        (tmp_path / "odd.tsv").write_text("\n".join(rows[:3] + ["\t".join([bad] + row[1:])]) + "\n")
        with pytest.raises(ValueError, match=rf"config merl.materials: .*odd\.tsv row 3: name "
                                             rf"{bad!r} is empty, has a slash"):
            catalog.load_catalog(tmp_path / "odd.tsv")


def test_missing_catalogue_fails_when_the_dag_is_built(tmp_path):
    rc, text = _dry_run(tmp_path, {"merl": {"materials": "my_materials.tsv"}})
    assert rc != 0
    assert "config merl.materials: my_materials.tsv is not a file" in text
    assert not (tmp_path / "results").exists()


def test_empty_subset_means_every_material():
    """`merl.subset: []` (the default) is documented as 'all of the catalogue'."""
    all_ = catalog.load_catalog(ROOT / "config/merl_materials.tsv", [])
    assert len(all_) == 100
    assert "empty" in (ROOT / "config/schema.yaml").read_text().split("subset:")[1][:400]
    assert "`merl.subset: []`" in (ROOT / "README.md").read_text()


def test_missing_local_btf_is_named_when_the_dag_is_built(tmp_path):
    (tmp_path / "btfs").mkdir()
    rc, text = _dry_run(tmp_path, {"ubo2014": {"source": "local", "local_dir": str(tmp_path / "btfs"),
                                               "materials": ["leather08"]}}, "config/tiny.yaml")
    assert rc != 0
    assert "ubo2014.local_dir" in text
    assert "leather08_resampled_W400xH400_L151xV151.btf" in text


def test_missing_conditioning_image_is_named_when_the_dag_is_built(tmp_path):
    """Without the check, a run that had sampled before skipped the missing image silently."""
    rc, text = _dry_run(tmp_path, {"conditions": {"image": {"images": ["photos/sphere.png"]}}},
                        "config/tiny.yaml")
    assert rc != 0
    assert "config conditions.image.images: photos/sphere.png is not a file" in text
    assert not (tmp_path / "results").exists()


def test_missing_inception_weights_fail_when_the_dag_is_built(tmp_path):
    """A file the user named is an error, not an 'unavailable' FID (that is for the package)."""
    rc, text = _dry_run(tmp_path, {"metrics": {"inception_weights": "weights/pt_inception.pth"}},
                        "config/tiny.yaml")
    assert rc != 0
    assert "config metrics.inception_weights: weights/pt_inception.pth is not a file" in text
    assert not (tmp_path / "results").exists()


@pytest.mark.parametrize("content, says", [
    (b"<html>404 Not Found</html>", "not a weights file neumat can load safely"),
    (None, "not a pytorch-fid Inception checkpoint"),
])
def test_inception_weights_that_are_not_weights_fail_when_the_dag_is_built(tmp_path, content, says):
    """A download that went wrong (an HTML page) or another model's weights failed in every
    metrics job, after the sampling; now the DAG is refused, naming the key."""
    import torch
    (tmp_path / "weights").mkdir()
    bad = tmp_path / "weights/pt_inception.pth"
    if content is None:
        torch.save({"fc.weight": torch.zeros(2, 2)}, bad)
    else:
        bad.write_bytes(content)
    rc, text = _dry_run(tmp_path, {"metrics": {"inception_weights": "weights/pt_inception.pth"}},
                        "config/tiny.yaml")
    assert rc != 0
    assert "config weights/pt_inception.pth (metrics.inception_weights): " + says in text, text[-2000:]
    assert not (tmp_path / "results").exists()


def _table(n_negative: int, seed=0) -> np.ndarray:
    """A physical-looking table with -1 below the horizon and `n_negative` negative valid bins."""
    rng = np.random.default_rng(seed)
    t = np.full((3, merl.N_BINS), -1.0)
    valid = np.flatnonzero(merl.valid_mask())
    t[:, valid] = rng.uniform(0.01, 1, (3, len(valid)))
    t[1, valid[:n_negative]] *= -1  # a sign-flipped block in one channel
    return t


def test_real_like_table_passes_quietly(caplog):
    with caplog.at_level(logging.WARNING):
        assert merl.check_negative("real.binary", _table(45)) == 45  # as the real MERL fits
    assert not caplog.records


def test_some_negative_bins_warn_with_the_count(caplog):
    n = int(merl.WARN_NEGATIVE_SHARE * merl.valid_mask().sum()) + 100
    with caplog.at_level(logging.WARNING):
        assert merl.check_negative("odd.binary", _table(n)) == n
    assert f"odd.binary: {n} of" in caplog.text


def test_many_negative_bins_are_refused_naming_file_and_share(tmp_path):
    half = int(merl.valid_mask().sum()) // 2
    with pytest.raises(merl.MerlFormatError, match=r"flipped.binary: 50.0% of its above-horizon"):
        merl.check_negative("flipped.binary", _table(half))
    # the data rules refuse (and remove) such a file; AugMERL refuses it too
    path = tmp_path / "flipped.binary"
    merl.write_merl(path, _table(half).reshape(3, 90, 90, 180))
    with pytest.raises(merl.MerlFormatError, match="flipped.binary"):
        augment.load_log_tables([path], negative={})
    with pytest.raises(merl.MerlFormatError, match="50.0%"):
        merl_files.verify(path)
    assert not path.exists()


@pytest.mark.parametrize("extra, key, says", [
    ({"augmerll": {"size": 8}}, "top level", "'augmerll' was unexpected"),
    ({"augmerl": {"pca_dim": 3}}, "augmerl", "'pca_dim' was unexpected"),
    ({"fit": {"steps": "many"}}, "fit.steps", "'many' is not of type 'integer'"),
    ({"btf": {"tiling": {"lights": []}}}, "btf.tiling.lights", "[] should be non-empty"),
    # each of these passed the DAG and failed late: NaN weights written without an error, a
    # TypeError, an IndexError, an empty concatenation
    ({"diffusion": {"schedule": {"kind": "linear", "beta_end": 1.5}}}, "diffusion.schedule.beta_end",
     "1.5 is greater than or equal to the maximum of 1"),
    ({"diffusion": {"sample": {"clip": 0}}}, "diffusion.sample.clip", "less than or equal to the minimum of 0"),
    ({"metrics": {"brdf_samples": "everything"}}, "metrics.brdf_samples", "'everything' is not valid"),
    ({"augmerl": {"figure_pair": ["nickel"]}}, "augmerl.figure_pair", "['nickel'] is not valid"),
    ({"btf": {"methods": []}}, "btf.methods", "[] should be non-empty"),
    ({"constrained": {"categories": []}}, "constrained.categories", "[] should be non-empty"),
    # an empty guidance sweep failed in conditions_section (pandas' EmptyDataError); run ".."
    # wrote every output into the checkout
    ({"conditions": {"sweep": {"scales": []}}}, "conditions.sweep.scales", "[] should be non-empty"),
    ({"run": ".."}, "run", "'..' does not match"),
    ({"conditions": {"text": {"prompts": [""]}}}, "conditions.text.prompts.0", "'' should be non-empty"),
    ({"metrics": {"models": []}}, "metrics.models", "[] should be non-empty"),
    # its Gram matrices grow with the 4th power of the side: 160 was killed for memory
    ({"ubo2014": {"synthetic": {"size": 160}}}, "ubo2014.synthetic.size",
     "160 is greater than the maximum of 128"),
    # no scale crashed btf_synthesis_eval (np.stack of nothing); a cond_drop of 0 trains no null
    # condition for guidance, of 1 no condition
    ({"btf_synthesis": {"render": {"scales": []}}}, "btf_synthesis.render.scales",
     "[] should be non-empty"),
    ({"conditions": {"cond_drop": 0}}, "conditions.cond_drop",
     "0 is less than or equal to the minimum of 0"),
    ({"conditions": {"cond_drop": 1}}, "conditions.cond_drop",
     "1 is greater than or equal to the maximum of 1"),
    # a block of 7.5 texels was cut to 7, of 3 raised to 6, both without a word; an anyOf
    # error quotes the key's description (jsonschema names none of the alternatives)
    ({"btf_synthesis": {"quilting": {"block": 7.5}}}, "btf_synthesis.quilting.block",
     "7.5 is not valid under any of the given schemas: block side: <= 1 a fraction of the "
     "exemplar side (at least 6 texels are used), else a whole number of texels >= 6"),
])
def test_bad_config_key_is_one_short_message(tmp_path, extra, key, says):
    """A misspelt key or a wrong type: the key's path and jsonschema's reason in a few lines,
    not Snakemake's dump of the whole schema and config (thousands of lines for a misspelt
    key, whose tail showed the defaults rather than the mistake)."""
    rc, text = _dry_run(tmp_path, extra, "config/tiny.yaml")
    assert rc != 0
    assert f"bad config ({key}): " in text and says in text and "config/schema.yaml" in text
    assert len(text.splitlines()) < 15, text[:3000]
    assert not (tmp_path / "results").exists()


def test_btf_jobs_ask_for_the_memory_they_were_measured_to_use(tmp_path):
    """Slurm kills a job above its mem_mb. Measured max_rss (Intel Xeon, 2026-11-29):
    synthetic_btf 4,918 MB and 11 min at 96^2 texels, where it asked for 2,000 MB and 10 min;
    btf_eval 911 MB at 96^2 (its Tucker query, blocked since; 2,115 MB before)."""
    import re
    for item in ("Snakefile", "workflow", "config", "src"):
        src = ROOT / item
        (shutil.copytree if src.is_dir() else shutil.copy)(src, tmp_path / item)
    (tmp_path / "extra.yaml").write_text(yaml.safe_dump(
        {"ubo2014": {"synthetic": {"size": 96}}, "btf": {"crop": None}}))
    res = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "1", "report", "--dry-run",
                          "--configfile", "config/tiny.yaml", "extra.yaml"], cwd=tmp_path,
                         capture_output=True, text=True)
    asked = {rule: (int(mem), int(minutes)) for rule, minutes, mem in re.findall(
        r"^rule (\w+):\n(?:    .*\n)*?    resources: tmpdir=[^,]*, runtime=(\d+),(?: gpu=\d,)? mem_mb=(\d+)",
        res.stdout, re.M)}
    assert asked["synthetic_btf"][0] >= 1.2 * 4918 and asked["synthetic_btf"][1] >= 1.5 * 11, asked
    assert asked["btf_eval"][0] >= 1.5 * 911, asked
