"""Model files load as tensors and plain values only (torch.load weights_only=True): a shared
file holding pickled objects is refused with an error naming it, never unpickled."""

import pytest
import torch

from neumat.btf import models as btf_models
from neumat.diffusion import Sampler
from neumat.io import modelfile


class Payload:
    """Stands in for a foreign object in a pickle; unpickling it would run its __reduce__."""

    ran = False

    def __reduce__(self):
        return (Payload._mark, ())

    @staticmethod
    def _mark():
        Payload.ran = True
        return {}


def _foreign(path):
    torch.save({"ema": {}, "payload": Payload()}, path)
    return path


def test_plain_values_round_trip(tmp_path):
    obj = {"state": {"w": torch.arange(3.0)}, "history": [(1, 0.5)], "names": ["a"], "n": 2}
    torch.save(obj, tmp_path / "m.pt")
    back = modelfile.load(tmp_path / "m.pt")
    assert torch.equal(back["state"]["w"], obj["state"]["w"])
    assert back["history"] == [(1, 0.5)] and back["names"] == ["a"] and back["n"] == 2


@pytest.mark.parametrize("loader", [modelfile.load, Sampler, btf_models.load],
                         ids=["modelfile", "diffusion.Sampler", "btf.models.load"])
def test_foreign_objects_are_refused_not_run(tmp_path, loader):
    path = _foreign(tmp_path / "shared.pt")
    Payload.ran = False
    with pytest.raises(ValueError, match=r"shared\.pt: not a model file neumat can load safely"):
        loader(path)
    assert not Payload.ran


def test_truncated_file_names_it(tmp_path):
    torch.save({"w": torch.zeros(1000)}, tmp_path / "m.pt")
    data = (tmp_path / "m.pt").read_bytes()
    (tmp_path / "m.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"m\.pt: .*delete it and rebuild it"):
        modelfile.load(tmp_path / "m.pt")


def test_a_damaged_checkpoint_is_logged_and_training_starts_over(tmp_path, caplog):
    """A checkpoint is no Snakemake output (--rerun-incomplete never removes it): a truncated
    one is ignored with a warning naming it, so a rerun starts over instead of failing every
    time; a sound one still resumes."""
    lin = torch.nn.Linear(3, 2)
    torch.save({"fingerprint": "f", "step": 7, "model": lin.state_dict()}, tmp_path / "ck.pt")
    other = torch.nn.Linear(3, 2)
    assert modelfile.resume(tmp_path / "ck.pt", "f", model=other)["step"] == 7
    assert torch.equal(other.weight, lin.weight)
    data = (tmp_path / "ck.pt").read_bytes()
    (tmp_path / "ck.pt").write_bytes(data[: len(data) // 2])
    with caplog.at_level("WARNING"):
        assert modelfile.resume(tmp_path / "ck.pt", "f", model=torch.nn.Linear(3, 2)) is None
    assert "ignoring unreadable checkpoint" in caplog.text and "ck.pt" in caplog.text


def test_missing_file_names_it(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nope\.pt"):
        modelfile.load(tmp_path / "nope.pt")


@pytest.mark.parametrize("loader, kind", [(Sampler, "a diffusion model"),
                                          ("image", "an image encoder")])
def test_a_model_file_of_another_kind_names_the_file_and_the_rule(tmp_path, loader, kind):
    """A loadable file of the wrong kind (here a bare state dict) is refused by name, not with
    a KeyError from inside the loader."""
    if loader == "image":
        from neumat.conditions import image
        loader = image.load
    torch.save({"a": torch.zeros(2)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match=rf"other\.pt: not {kind} \(rule.*lacks"):
        loader(tmp_path / "other.pt")


def _btf_model_file(path, **args):
    from neumat.btf.neural import TriplePlane
    m = TriplePlane(8, 8, dir_res=4, hidden=8, layers=2)
    btf_models.save(m, path)
    ck = torch.load(path, weights_only=True)
    ck["args"].update(args)
    return m, ck


def test_a_model_with_nan_weights_is_refused_by_name(tmp_path):
    """A shared model file with NaN (a diverged training) loaded silently before: a BTF model
    was scored as a poor fit, a diffusion model sampled NaN materials into black renders."""
    _, ck = _btf_model_file(tmp_path / "tp.pt")
    btf_models.load(tmp_path / "tp.pt")  # sound: loads
    ck["state"]["f_u"][3, 2, 1] = float("nan")
    torch.save(ck, tmp_path / "tp.pt")
    with pytest.raises(ValueError, match=r"tp\.pt: tensor state\.f_u holds NaN or inf"):
        btf_models.load(tmp_path / "tp.pt")
    torch.save({"ema": {"w": torch.tensor([1.0, float("inf")])}, "n": 1}, tmp_path / "d.pt")
    with pytest.raises(ValueError, match=r"d\.pt: tensor ema\.w holds NaN or inf"):
        Sampler(tmp_path / "d.pt")
    assert modelfile.load(tmp_path / "d.pt")["n"] == 1  # not asked to check: loads as before


def test_a_state_that_does_not_fit_its_config_names_the_file_and_the_rule(tmp_path):
    """torch's load_state_dict RuntimeError named no file; now each loader says which file and
    which rule rebuilds it."""
    from neumat.baselines import hyperbrdf
    _, ck = _btf_model_file(tmp_path / "tp.pt", width=16)
    torch.save(ck, tmp_path / "tp.pt")
    with pytest.raises(ValueError, match=r"tp\.pt: its state does not fit its config .*"
                                         r"rule btf_triple_plane"):
        btf_models.load(tmp_path / "tp.pt")
    torch.save({"a": torch.zeros(2)}, tmp_path / "h.pt")
    with pytest.raises(ValueError, match=r"h\.pt: not a HyperBRDF model \(rule train_hyperbrdf"):
        hyperbrdf.load(tmp_path / "h.pt")
