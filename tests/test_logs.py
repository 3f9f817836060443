"""Script logging: messages and crashes land in the rule's log; scripts keep to `threads:`."""
import logging
import types

import pytest
import torch

from neumat.logs import script_logging


def test_log_file_gets_messages_and_the_traceback(tmp_path, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "2")  # restored afterwards, as MKL_NUM_THREADS
    monkeypatch.setenv("MKL_NUM_THREADS", "2")
    before = torch.get_num_threads()
    smk = types.SimpleNamespace(log=[str(tmp_path / "job.log")], threads=1, rule="demo")
    try:
        with pytest.raises(ValueError, match="bad input"):
            with script_logging(smk) as log:
                assert torch.get_num_threads() == 1
                log.info("working on shard 007")
                import warnings
                warnings.warn("array is not writable", UserWarning)
                raise ValueError("bad input")
    finally:
        torch.set_num_threads(before)
    text = (tmp_path / "job.log").read_text()
    assert "neumat.demo INFO: working on shard 007" in text
    assert "failed:" in text and "ValueError: bad input" in text
    assert "py.warnings WARNING" in text and "UserWarning: array is not writable" in text


def test_input_error_stops_with_its_message_and_logs_the_traceback(tmp_path, capsys):
    """An InputError (a message that says what to do): the script exits 1 with that message
    once on stderr, no traceback there; the log file keeps the traceback."""
    from neumat.logs import InputError

    class Unreachable(InputError, RuntimeError):
        pass

    smk = types.SimpleNamespace(log=[str(tmp_path / "job.log")], rule="demo")
    with pytest.raises(SystemExit) as e:
        with script_logging(smk):
            raise Unreachable("x.binary: could not download; set merl.source: local")
    assert e.value.code == 1
    err = capsys.readouterr().err
    assert err.count("failed: Unreachable: x.binary: could not download") == 1
    assert "Traceback" not in err
    text = (tmp_path / "job.log").read_text()
    assert "failed: Unreachable: x.binary" in text and "Traceback" in text


def test_the_device_a_job_uses_is_logged(caplog, monkeypatch):
    """resolve_device says what `device` became (under auto a node with broken CUDA falls back
    to the CPU, and the job's log is where that shows); cuda without a GPU says what to do."""
    import torch

    from neumat.device import resolve_device
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with caplog.at_level(logging.INFO, logger="neumat.device"):
        assert resolve_device("auto") == torch.device("cpu")
        assert resolve_device("cpu") == torch.device("cpu")
    assert [r.getMessage().split(" (")[0] for r in caplog.records] == ["device auto -> cpu",
                                                                     "device cpu -> cpu"]
    assert "no GPU in use; torch " in caplog.records[0].getMessage()
    with pytest.raises(RuntimeError, match=r"config device: cuda, but torch sees no CUDA device "
                                           r"\(torch .*\); run on a GPU node, or set device: auto"):
        resolve_device("cuda")
