"""The `neumat` command: --help, round trips (sample -> .binary -> read back), the scene XML,
render, info and its error messages. The run is a miniature made in-process (a tiny diffusion
model trained for a few steps), so these tests take seconds."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from neumat import cli, constrained, nbrdf
from neumat.diffusion import DenoiserConfig, ScheduleConfig, TrainConfig, train
from neumat.io import merl

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


def main(*args):
    return cli.main([str(a) for a in args])


def test_help_for_every_subcommand(capsys):
    for sub in ("info", "sample", "render"):
        with pytest.raises(SystemExit) as e:
            cli.main([sub, "--help"])
        assert e.value.code == 0
        assert "usage: neumat " + sub in capsys.readouterr().out
    res = subprocess.run([sys.executable, "-m", "neumat.cli", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "{info,sample,render}" in res.stdout


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
    assert Image.open(tmp_path / "t.png").size == (32, 32)


def test_category_round_trip(run, tmp_path):
    (run / "constrained").mkdir(exist_ok=True)
    th = constrained.Thresholds(mirror_peak=1e9, mirror_body=1e9, plastic_sharpness=1e9,
                                high_peak=1e9, medium_peak=1e9)
    th.to_frame().to_csv(run / "constrained/rules.tsv", sep="\t", index=False)
    out = tmp_path / "c"
    rc = main("sample", "--run", run, "--category", "metallic", "-n", 2, "--steps", 3, "--budget", 4,
              "--batch", 4, "--bins", 16384, "--no-binary", "--out", out)
    w = np.load(out / "weights.npy") if (out / "weights.npy").exists() else np.zeros((0, 675))
    # whatever the model made, what was kept is metallic by the rules, and a shortfall says so
    if len(w):
        st = constrained.field_stats(w, bins=constrained.grid_bins(16384, 0))
        assert set(constrained.classify(st, th)) == {"metallic"}
    assert rc == (0 if len(w) == 2 else cli.EXIT_BUDGET)


def test_info_lists_models_and_missing_config(run, capsys):
    assert main("info", run) == 0
    o = capsys.readouterr().out
    assert "ours" in o and "conditions: type" in o and "not recorded yet" in o


@pytest.mark.parametrize("args, message", [
    (["info", "{tmp}/nope"], "snakemake --cores 2 report"),
    (["sample", "--run", "{run}", "--model", "merl100", "--out", "{tmp}/o"], "rule train_diffusion"),
    (["sample", "--run", "{run}", "--text", "red plastic", "--out", "{tmp}/o"], "trained without text"),
    (["sample", "--run", "{run}", "--image", "x.png", "--out", "{tmp}/o"], "trained without image"),
    (["sample", "--run", "{run}", "--type", "wood", "--out", "{tmp}/o"], "known: fabric, steel"),
    (["sample", "--run", "{run}", "--category", "shiny", "--out", "{tmp}/o"], "choose one of diffuse"),
    (["render", "{tmp}/missing.binary", "--out", "{tmp}/x.png"], "no such file"),
    (["render", "{tmp}/bad.binary", "--out", "{tmp}/x.png"], "MERL .binary has a 12-byte header"),
    (["render", "{tmp}/bad.npy", "--out", "{tmp}/x.png"], "expected NBRDF weights"),
])
def test_errors_say_what_to_do(run, tmp_path, capsys, args, message):
    (tmp_path / "bad.binary").write_bytes(b"1234")
    np.save(tmp_path / "bad.npy", np.zeros((2, 5)))
    args = [a.format(run=run, tmp=tmp_path) for a in args]
    assert cli.main(args) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert message in err and err.startswith(f"neumat {args[0]}: error:")


def test_category_without_rules_names_the_rule(tmp_path, run, capsys):
    import shutil
    bare = tmp_path / "bare"
    shutil.copytree(run / "diffusion", bare / "diffusion")
    rc = main("sample", "--run", bare, "--category", "diffuse", "--out", tmp_path / "o")
    err = capsys.readouterr().err
    assert rc == cli.EXIT_USAGE and "rule constrained_rules" in err and "constrained/rules.tsv" in err


def test_text_refused_even_for_a_text_model(run):
    bundle = torch.load(run / "diffusion/ours/model.pt", weights_only=True)
    bundle["model_cfg"]["vector_conditions"] = {"text": 384}
    why = cli.unsupported(bundle, "text", Path("m.pt"))
    assert "not wired into `neumat sample` yet" in why
    assert cli.unsupported(bundle, "type", Path("m.pt")) is None
