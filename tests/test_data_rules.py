"""Getting MERL files verified (neumat.data.merl_files) and the data rules' DAG-time checks."""

import functools
import http.server
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from neumat.data import merl_files as mf
from neumat.io import merl

ROOT = Path(__file__).parents[1]


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """A valid MERL file and its sha256."""
    d = tmp_path_factory.mktemp("src")
    t = np.full(merl.SHAPE, 0.25)
    merl.write_merl(d / "chrome.binary", t)
    return d / "chrome.binary", mf.sha256_of(d / "chrome.binary")


@pytest.fixture
def served(good, tmp_path):
    """A local HTTP server over a directory holding the good file and a truncated one."""
    root = tmp_path / "www"
    root.mkdir()
    shutil.copy(good[0], root / "chrome.binary")
    (root / "short.binary").write_bytes(good[0].read_bytes()[:1000])
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(root))
    handler.log_message = lambda *a: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def test_sha256_known_answer(tmp_path):
    (tmp_path / "abc").write_bytes(b"abc")
    assert mf.sha256_of(tmp_path / "abc") == (
        "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad")


def test_checksum_mismatch_names_file_and_hashes_and_removes_it(good, tmp_path):
    p = tmp_path / "chrome.binary"
    shutil.copy(good[0], p)
    wrong = "f" * 64
    with pytest.raises(mf.ChecksumError) as e:
        mf.verify(p, wrong)
    msg = str(e.value)
    assert "chrome.binary" in msg and wrong in msg and good[1] in msg
    assert "sha256_override" in msg
    assert not p.exists()


def test_good_file_not_touched(good, tmp_path):
    p = tmp_path / "chrome.binary"
    shutil.copy2(good[0], p)
    before = (p.stat().st_mtime_ns, p.read_bytes())
    mf.verify(p, good[1])
    mf.verify(p, good[1].upper())  # hex case does not matter
    mf.verify(p, None)
    assert (p.stat().st_mtime_ns, p.read_bytes()) == before


def test_bad_format_removed_with_clear_error(good, tmp_path):
    p = tmp_path / "cut.binary"
    p.write_bytes(good[0].read_bytes()[:-8])
    with pytest.raises(merl.MerlFormatError, match=r"cut\.binary: 34992004 bytes"):
        mf.verify(p)
    assert not p.exists()


def test_download_good(served, good, tmp_path):
    dest = tmp_path / "res" / "chrome.binary"
    mf.download(f"{served}/chrome.binary", dest, good[1], retries=0)
    assert dest.read_bytes() == good[0].read_bytes()
    assert list(dest.parent.iterdir()) == [dest]  # no temporary left


def test_download_checksum_mismatch_keeps_nothing(served, tmp_path):
    dest = tmp_path / "res" / "chrome.binary"
    with pytest.raises(mf.ChecksumError, match="chrome.binary.*expected 0{64}, got [0-9a-f]{64}"):
        mf.download(f"{served}/chrome.binary", dest, "0" * 64, retries=1, backoff=0)
    assert list(dest.parent.iterdir()) == []


def test_download_truncated_is_format_error(served, tmp_path):
    dest = tmp_path / "res" / "chrome.binary"
    with pytest.raises(merl.MerlFormatError, match=r"chrome\.binary: 1000 bytes"):
        mf.download(f"{served}/short.binary", dest, retries=0)
    assert list(dest.parent.iterdir()) == []


def test_download_404_is_permanent(served, tmp_path):
    with pytest.raises(mf.DownloadError, match=r"HTTP 404.*merl\.url.*merl\.source: local"):
        mf.download(f"{served}/nope.binary", tmp_path / "nope.binary", retries=5, backoff=100)


def test_download_unreachable_says_what_to_do(tmp_path):
    with pytest.raises(mf.DownloadError) as e:
        mf.download("http://127.0.0.1:9/chrome.binary", tmp_path / "chrome.binary",
                    retries=2, backoff=0)
    msg = str(e.value)
    assert "after 3 attempt(s)" in msg and "merl.local_dir" in msg and "config/tiny.yaml" in msg
    assert list(tmp_path.iterdir()) == []


def test_download_keeps_existing_good_file_on_failure(good, tmp_path):
    dest = tmp_path / "chrome.binary"
    shutil.copy(good[0], dest)
    with pytest.raises(mf.DownloadError):
        mf.download("http://127.0.0.1:9/chrome.binary", dest, retries=0)
    assert dest.read_bytes() == good[0].read_bytes()


@pytest.mark.parametrize("link", [False, True])
def test_copy_local(good, tmp_path, link):
    dest = tmp_path / "res" / "chrome.binary"
    mf.copy_local(good[0].parent, "chrome", dest, good[1], link=link)
    assert dest.is_symlink() == link
    assert dest.read_bytes() == good[0].read_bytes()


@pytest.mark.parametrize("link", [False, True])
def test_copy_local_mismatch_keeps_source(good, tmp_path, link):
    src = tmp_path / "mine"
    src.mkdir()
    shutil.copy(good[0], src / "chrome.binary")
    dest = tmp_path / "res" / "chrome.binary"
    with pytest.raises(mf.ChecksumError, match=str(src / "chrome.binary")):
        mf.copy_local(src, "chrome", dest, "1" * 64, link=link)
    assert os.listdir(dest.parent) == []
    assert (src / "chrome.binary").read_bytes() == good[0].read_bytes()  # the user's file stays


def test_local_errors_name_the_key(tmp_path, good):
    with pytest.raises(ValueError, match="merl.local_dir: required"):
        mf.check_local_dir(None, ["chrome"])
    with pytest.raises(FileNotFoundError, match=f"merl.local_dir: {tmp_path / 'x'} is not a directory"):
        mf.check_local_dir(tmp_path / "x", ["chrome"])
    with pytest.raises(FileNotFoundError, match=r"lacks 2 of 3 files: a\.binary, b\.binary"):
        mf.check_local_dir(good[0].parent, ["a", "chrome", "b"])
    mf.check_local_dir(good[0].parent, ["chrome"])
    with pytest.raises(FileNotFoundError, match=r"merl.local_dir: .*nope\.binary does not exist"):
        mf.copy_local(good[0].parent, "nope", tmp_path / "nope.binary")


def snakemake_dry_run(tmp_path, merl_yaml):
    """Dry-run the workflow in a scratch directory with an extra config file."""
    (tmp_path / "config").symlink_to(ROOT / "config")
    (tmp_path / "extra.yaml").write_text(merl_yaml)
    return subprocess.run(
        [sys.executable, "-m", "snakemake", "-n", "--cores", "1", "-s", str(ROOT / "Snakefile"),
         "-d", str(tmp_path), "--configfile", str(ROOT / "config" / "config.yaml"),
         str(tmp_path / "extra.yaml")],
        capture_output=True, text=True, timeout=300)


def test_dag_local_dir_missing_files(tmp_path, good):
    r = snakemake_dry_run(tmp_path, f"merl:\n  source: local\n  local_dir: {good[0].parent}\n")
    assert r.returncode != 0
    assert f"config merl.local_dir: {good[0].parent} lacks 99 of 100 files" in r.stderr + r.stdout


def test_dag_local_subset_uses_local_rule(tmp_path, good):
    for name in ("gold-paint", "alum-bronze"):  # a run needs 2 train-split sources
        shutil.copy(good[0], good[0].parent / f"{name}.binary")
    # three sources split 2:1, so one Table 2 draw (check_cross_keys: draws x test <= train)
    r = snakemake_dry_run(tmp_path, f"merl:\n  source: local\n  local_dir: {good[0].parent}\n"
                                    "  subset: [chrome, gold-paint, alum-bronze]\nmetrics:\n"
                                    "  draws: 1\n")
    out = r.stdout + r.stderr
    assert "local_merl" in out and "download_merl" not in out, out[-2000:]


def test_offline_download_job_says_what_to_do_without_tracebacks(tmp_path):
    """A download job that cannot reach the server ends with the DownloadError's message and
    its remedy, once per job, and no traceback on the terminal (an offline run of the default
    config buried the remedy under two tracebacks per failed job); the traceback stays in the
    job's log."""
    (tmp_path / "extra.yaml").write_text(
        "merl:\n  url: http://127.0.0.1:9/{name}.binary\n  retries: 0\n"
        "  subset: [chrome, gold-paint, alum-bronze]\nmetrics:\n  draws: 1\n")  # as above
    for item in ("Snakefile", "workflow", "config"):
        (shutil.copytree if (ROOT / item).is_dir() else shutil.copy)(ROOT / item, tmp_path / item)
    targets = ["resources/merl/chrome.binary", "resources/merl/gold-paint.binary"]
    r = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", *targets,
                        "--configfile", "config/config.yaml", "extra.yaml"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300)
    out = r.stdout + r.stderr
    assert r.returncode != 0
    assert "Traceback" not in out, out[-3000:]
    for name in ("chrome", "gold-paint"):
        line = (f"failed: DownloadError: {name}.binary: could not download "
                f"http://127.0.0.1:9/{name}.binary")
        assert out.count(line) == 1, out[-3000:]
    assert out.count("merl.local_dir") == 2 and "config/tiny.yaml" in out
    logs = list((tmp_path / "results").rglob("download_merl/chrome.log"))
    assert logs and "Traceback" in logs[0].read_text()
    assert not list((tmp_path / "resources/merl").glob("*.binary"))
