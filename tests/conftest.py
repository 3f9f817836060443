import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def _parallel_workers(config) -> int:
    """Workers for the unit tests as a whole (`pytest -m "not slow"`, no test path or -k): one
    per CPU up to 4, where pytest-xdist is installed and `-n` was not given. The full suite
    stays in one process (its tiny run is started by this process and keeps both cores busy),
    and so does a run of a few chosen tests, which workers' start-up would only slow."""
    if not config.pluginmanager.hasplugin("xdist"):
        return 0
    if config.getoption("numprocesses", None) is not None:
        return 0
    if "not slow" not in (config.option.markexpr or "") or os.environ.get("PYTEST_XDIST_WORKER"):
        return 0
    if config.getoption("file_or_dir", None) or config.getoption("keyword", ""):
        return 0
    n = min(os.cpu_count() or 1, 4)
    return n if n > 1 else 0


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads -n
def pytest_cmdline_main(config):
    n = _parallel_workers(config)
    if n:
        config.option.numprocesses = n
        config.option.dist = "load"


def pytest_report_header(config):
    n = config.getoption("numprocesses", None)
    if n and not os.environ.get("PYTEST_XDIST_WORKER"):
        return (f"unit tests on {n} pytest-xdist workers (tests/conftest.py); "
                "-n 0 runs them in one process")


if os.environ.get("PYTEST_XDIST_WORKER"):  # a worker: the cores are shared out between workers
    _workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", 1))
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // _workers))


@pytest.fixture
def one_thread():
    """Tiny models: one thread is fastest, and avoids spin-waiting on a shared 2-core box."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


TINY_CMD = [sys.executable, "-m", "snakemake", "--cores", "2", "report", "--configfile",
            "config/tiny.yaml"]
_tiny: dict = {}  # the background tiny run: its directory, process and output files


def _needs_tiny(item) -> bool:
    return "tiny_run" in getattr(item, "fixturenames", ())


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects: the mark below must be seen
def pytest_collection_modifyitems(config, items):
    """A test that needs the tiny run is `slow` (end to end), whether or not it says so, so
    `-m "not slow"` never starts the run. Those tests go last (a stable sort: the order is
    otherwise kept), so the others run while it builds in the background."""
    for item in filter(_needs_tiny, items):
        item.add_marker(pytest.mark.slow)
    items.sort(key=_needs_tiny)


def pytest_collection_finish(session):
    """Start the tiny run as soon as the selected tests are known, if one of them needs it: it is
    the suite's longest piece (~4 min on 2 cores) and runs while the unit tests do."""
    if session.config.option.collectonly or not any(map(_needs_tiny, session.items)):
        return
    # pytest's tmp_path_factory (a hook gets no fixtures): the run lands with the other tmp
    # dirs, its output in tiny_run.out / tiny_run.err there
    wd = session.config._tmp_path_factory.mktemp("tiny")
    for item in ("Snakefile", "workflow", "config"):
        src = ROOT / item
        (shutil.copytree if src.is_dir() else shutil.copy)(src, wd / item)
    out, err = (open(wd / f"tiny_run.{s}", "w+") for s in ("out", "err"))
    proc = subprocess.Popen(TINY_CMD, cwd=wd, stdout=out, stderr=err, start_new_session=True)
    _tiny.update(wd=wd, proc=proc, out=out, err=err)


def pytest_sessionfinish(session):
    """An unfinished tiny run (the session was cut short) is stopped with all its jobs."""
    proc = _tiny.get("proc")
    if proc is not None and proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait()


@pytest.fixture(scope="session")
def tiny_run():
    """config/tiny.yaml run once to its report, in a copy of the workflow (the checkout's
    results/ stay untouched), started in the background at collection; every test that needs a
    finished run shares it. Tests may add files next to it, never change its results."""
    if not _tiny:  # collected without the hook seeing it (e.g. requested dynamically)
        pytest.fail("tiny_run was requested by a test that does not declare it")
    proc, out, err = _tiny["proc"], _tiny["out"], _tiny["err"]
    if proc.wait() != 0:
        out.seek(0), err.seek(0)
        raise AssertionError(f"{' '.join(TINY_CMD)} failed:\n{out.read()[-4000:]}\n"
                             f"{err.read()[-8000:]}")
    return _tiny["wd"]
