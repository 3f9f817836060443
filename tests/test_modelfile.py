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
