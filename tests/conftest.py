import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _parallel_workers(config) -> int:
    """Workers for a run of the suite as a whole (`pytest`, `pytest -m "not slow"`: no test path
    or -k): one per CPU up to 4, where pytest-xdist is installed and `-n` was not given. The
    tiny run is shared by the workers (`tiny_run` below). A run of a few chosen tests stays in
    one process, which workers' start-up would only slow."""
    if not config.pluginmanager.hasplugin("xdist"):
        return 0
    if config.getoption("numprocesses", None) is not None or os.environ.get("PYTEST_XDIST_WORKER"):
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
        config.option.dist = "loadscope"
        config.option.loadscopereorder = False  # collection order: the tiny run's tests last
        config._neumat_groups = True  # the scopes: pytest_xdist_make_scheduler below


def pytest_report_header(config):
    n = config.getoption("numprocesses", None)
    if n and not os.environ.get("PYTEST_XDIST_WORKER"):
        return (f"tests on {n} pytest-xdist workers (tests/conftest.py); "
                "-n 0 runs them in one process")


# the tiny run gets this: it runs as a user would run it, without the workers' variables
_USER_ENV = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}

if os.environ.get("PYTEST_XDIST_WORKER"):  # a worker: the cores are shared out between workers
    # torch here and in `one_thread`, not at the top: the xdist controller runs no test, and
    # would import it before it starts the workers, while one core idles
    import torch

    _workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", 1))
    _threads = max(1, (os.cpu_count() or 1) // _workers)
    torch.set_num_threads(_threads)
    # and the processes the tests start (`neumat sample`, ...): torch would start a thread per
    # core in each, and spin-wait on cores they share (a pair of README commands side by side:
    # 37.5 CPU-s, 20.1 s with torch's default threads; 23.5 CPU-s, 14.6 s with one thread each)
    os.environ.setdefault("OMP_NUM_THREADS", str(_threads))


@pytest.fixture
def one_thread():
    """Tiny models: one thread is fastest, and avoids spin-waiting on a shared 2-core box."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


TINY_CMD = [sys.executable, "-m", "snakemake", "--cores", "2", "report", "--configfile",
            "config/tiny.yaml"]
_tiny: dict = {}  # this process's part in the tiny run: its directory, and its process if started here


def _needs_tiny(item) -> bool:
    return "tiny_run" in getattr(item, "fixturenames", ())


def _shares_a_fixture(item) -> bool:
    """The test uses a module- or class-scoped fixture (a trained model, a set of dry runs)."""
    defs = getattr(item, "_fixtureinfo", None)
    return defs is not None and any(d.scope in ("module", "class", "package")
                                    for ds in defs.name2fixturedefs.values() for d in ds)


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects: the mark below must be seen
def pytest_collection_modifyitems(config, items):
    """A test that needs the tiny run is `slow` (end to end), whether or not it says so, so
    `-m "not slow"` never starts the run. Those tests go last (a stable sort: the order is
    otherwise kept), so the others run while it builds in the background. On xdist workers the
    tests of a module that share a module fixture go to one worker, so it is built once (those
    that need the tiny run apart from the others, or they would hold a worker early); every
    other test is scheduled on its own."""
    for item in filter(_needs_tiny, items):
        item.add_marker(pytest.mark.slow)
    items.sort(key=_needs_tiny)
    if hasattr(config, "workerinput"):  # every worker writes the same map; the controller reads it
        groups = {it.nodeid: it.nodeid.split("::")[0] + ("#tiny" if _needs_tiny(it) else "")
                  for it in filter(_shares_a_fixture, items)}
        part = _session_dir(config) / f"xdist_groups.{os.getpid()}"
        part.write_text(json.dumps(groups))
        part.replace(part.with_name("xdist_groups.json"))


def _session_dir(config) -> Path:
    """One directory per session, shared by the xdist workers (the controller makes it and hands
    it to them, `pytest_configure_node`): the tiny run's. Beside the workflow copy and its
    results it holds `pid` (of the run's shell; its process group), `rc` (the exit status,
    written when the run ends), `tiny_run.out` / `tiny_run.err`, and the workers' test groups."""
    if hasattr(config, "workerinput"):
        return Path(config.workerinput["neumat_session_dir"])
    if "wd" not in _tiny:  # pytest's tmp_path_factory (a hook gets no fixtures)
        _tiny["wd"] = config._tmp_path_factory.mktemp("tiny")
    return _tiny["wd"]


@pytest.hookimpl(optionalhook=True)  # an xdist hook, on the controller
def pytest_configure_node(node):
    node.workerinput["neumat_session_dir"] = str(_session_dir(node.config))


@pytest.hookimpl(optionalhook=True)  # an xdist hook, on the controller
def pytest_xdist_make_scheduler(config, log):
    """xdist's scope scheduling over the workers' groups (`pytest_collection_modifyitems`): a
    test with a group goes with the others of its group, every other test on its own. (xdist's
    own `xdist_group` mark sets `item._nodeid`, which pytest 9.2 no longer reads.)"""
    if not getattr(config, "_neumat_groups", False):  # the user's own -n / --dist
        return None
    from xdist.scheduler import LoadScopeScheduling

    groups_file = _session_dir(config) / "xdist_groups.json"

    class GroupScheduling(LoadScopeScheduling):
        groups = None

        def _split_scope(self, nodeid):  # called once every worker has collected
            if self.groups is None:
                self.groups = json.loads(groups_file.read_text())
            return self.groups.get(nodeid, nodeid)

    return GroupScheduling(config, log)


def pytest_collection_finish(session):
    """Start the tiny run as soon as the selected tests are known, if one of them needs it: it is
    the suite's longest piece (~3 min on 2 cores) and runs while the other tests do. Of several
    workers the first to get here starts it (a file lock); the others find it running."""
    import fcntl
    if session.config.option.collectonly or not any(map(_needs_tiny, session.items)):
        return
    wd = _session_dir(session.config)
    with open(wd / "start.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (wd / "pid").exists():
            for item in ("Snakefile", "workflow", "config"):
                src = ROOT / item
                (shutil.copytree if src.is_dir() else shutil.copy)(src, wd / item)
            _tiny["proc"] = _start_run(wd, TINY_CMD)
    # the run is the suite's critical path: the tests (this process and what it starts) yield
    # the cores to it, and fill what it leaves idle. Inside pytest the run took 181-185 s with
    # the tests at nice 19, 196-207 s at nice 10, and 171 s alone (2-core AMD EPYC, 2026-11-25)
    os.nice(19)


def _start_run(wd: Path, cmd: list[str]) -> subprocess.Popen:
    """`cmd` in `wd`, in its own process group, in the background. A shell records its exit
    status in `wd/rc` for whichever process waits (xdist workers cannot wait() on another's
    child), and its pid in `wd/pid`."""
    with open(wd / "tiny_run.out", "w") as out, open(wd / "tiny_run.err", "w") as err:
        # its own process group (killpg), not its own session: Linux's autogroup scheduler
        # would share the cores evenly between sessions, and the tests' nice would not count
        proc = subprocess.Popen(["sh", "-c", '"$@"; echo $? > rc.part && mv rc.part rc', "sh",
                                 *cmd], cwd=wd, stdout=out, stderr=err, process_group=0,
                                env=_USER_ENV)
    (wd / "pid").write_text(str(proc.pid))
    return proc


def _wait_for_run(wd: Path, cmd: list[str]) -> Path:
    """`wd` once the run started there has succeeded; else an error with its output's tail."""
    pid = int((wd / "pid").read_text())
    while not (wd / "rc").exists() and _alive(pid):
        time.sleep(0.5)
    rc = (wd / "rc").read_text().strip() if (wd / "rc").exists() else "killed"
    if rc != "0":
        out, err = ((wd / f"tiny_run.{s}").read_text() for s in ("out", "err"))
        raise AssertionError(f"{' '.join(cmd)} failed ({rc}):\n{out[-4000:]}\n{err[-8000:]}")
    return wd


def _alive(pid: int) -> bool:
    """The process exists and is no zombie (a worker's finished child may wait to be reaped)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False
    except OSError:  # no /proc: ask the kernel
        try:
            os.kill(pid, 0)
            return True
        except ProcessLookupError:
            return False


def pytest_sessionfinish(session):
    """An unfinished tiny run (the session was cut short) is stopped with all its jobs, by the
    process that owns the session: one process, or the xdist controller (a worker that finishes
    early leaves it to the others)."""
    proc = _tiny.get("proc")
    if proc is not None and proc.poll() is not None:
        return
    if hasattr(session.config, "workerinput") or "wd" not in _tiny:
        return
    wd = _tiny["wd"]
    if (wd / "pid").exists() and not (wd / "rc").exists():
        pid = int((wd / "pid").read_text())
        try:
            os.killpg(pid, signal.SIGTERM)
        except ProcessLookupError:
            return
        for _ in range(300):  # snakemake lets running jobs finish on SIGTERM; give it 30 s
            if not _alive(pid):
                return
            time.sleep(0.1)
        with contextlib.suppress(ProcessLookupError):  # its jobs die with it (PR_SET_PDEATHSIG)
            os.killpg(pid, signal.SIGKILL)


@pytest.fixture(scope="session")
def tiny_run(request):
    """config/tiny.yaml run once to its report, in a copy of the workflow (the checkout's
    results/ stay untouched), started in the background at collection; every test that needs a
    finished run shares it, on every worker. Tests may add files next to it, never change its
    results."""
    wd = _session_dir(request.config)
    if not (wd / "pid").exists():  # collected without the hook seeing it (requested dynamically)
        pytest.fail("tiny_run was requested by a test that does not declare it")
    return _wait_for_run(wd, TINY_CMD)
