"""The suite's own machinery (tests/conftest.py): the background tiny run that xdist workers
share, and the test groups that keep a module fixture on one worker."""

import json
import sys
from types import SimpleNamespace

import pytest

import conftest


def test_background_run_reports_success_to_any_waiter(tmp_path):
    proc = conftest._start_run(tmp_path, [sys.executable, "-c", "print('made it')"])
    assert conftest._wait_for_run(tmp_path, ["x"]) == tmp_path
    assert (tmp_path / "rc").read_text().strip() == "0" and proc.wait() == 0
    assert (tmp_path / "tiny_run.out").read_text() == "made it\n"


def test_background_run_failure_names_the_status_and_shows_stderr(tmp_path):
    conftest._start_run(tmp_path, [sys.executable, "-c",
                                   "import sys; sys.stderr.write('job broke'); sys.exit(3)"])
    with pytest.raises(AssertionError, match=r"(?s)snakemake --cores 2 failed \(3\):.*job broke"):
        conftest._wait_for_run(tmp_path, ["snakemake", "--cores", "2"])


def test_a_killed_run_is_reported_not_waited_on_forever(tmp_path):
    """A run that dies without an exit status (its shell killed) ends the wait."""
    import os
    import signal
    proc = conftest._start_run(tmp_path, [sys.executable, "-c", "import time; time.sleep(60)"])
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    with pytest.raises(AssertionError, match=r"failed \(killed\)"):
        conftest._wait_for_run(tmp_path, ["run"])


def _item(nodeid, *fixtures):
    """A collected test as the hooks see it: fixtures as (name, scope)."""
    defs = {name: [SimpleNamespace(scope=scope)] for name, scope in fixtures}
    marks = []
    return SimpleNamespace(nodeid=nodeid, fixturenames=list(defs), marks=marks,
                           _fixtureinfo=SimpleNamespace(name2fixturedefs=defs),
                           add_marker=marks.append)


def test_workers_group_tests_that_share_a_module_fixture(tmp_path):
    """On a worker: tests needing the tiny run go last and are `slow`; those sharing a module
    fixture form one group per module (the tiny ones their own); the controller's scheduler
    maps each node id to its group, every other test to itself."""
    items = [_item("tests/a.py::test_run", ("tiny_run", "session")),
             _item("tests/a.py::test_dry", ("dry_runs", "module")),
             _item("tests/a.py::test_cli", ("tiny_run", "session"), ("cli_runs", "module")),
             _item("tests/b.py::test_plain", ("tmp_path", "function")),
             _item("tests/a.py::test_dry2", ("dry_runs", "module"))]
    config = SimpleNamespace(workerinput={"neumat_session_dir": str(tmp_path)})
    conftest.pytest_collection_modifyitems(config, items)
    assert [it.nodeid for it in items] == ["tests/a.py::test_dry", "tests/b.py::test_plain",
                                          "tests/a.py::test_dry2", "tests/a.py::test_run",
                                          "tests/a.py::test_cli"]
    assert [bool(it.marks) for it in items] == [False, False, False, True, True]
    groups = json.loads((tmp_path / "xdist_groups.json").read_text())
    assert groups == {"tests/a.py::test_dry": "tests/a.py", "tests/a.py::test_dry2": "tests/a.py",
                      "tests/a.py::test_cli": "tests/a.py#tiny"}

    controller = SimpleNamespace(_neumat_groups=True, workerinput=config.workerinput,
                                 getvalue=lambda name: ["popen", "popen"])
    sched = conftest.pytest_xdist_make_scheduler(controller, None)
    assert sched._split_scope("tests/a.py::test_dry2") == "tests/a.py"
    assert sched._split_scope("tests/b.py::test_plain") == "tests/b.py::test_plain"
    # the user's own -n / --dist: xdist's scheduler
    assert conftest.pytest_xdist_make_scheduler(SimpleNamespace(), None) is None


def test_suite_profile_logs_each_python_process_and_names_its_kind(tmp_path):
    """benchmarks/suite_profile.py --processes: the sitecustomize probe writes one record per
    Python process at exit, and the report sorts them into kinds by argv."""
    import importlib.util
    import os
    import subprocess
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("suite_profile", root / "benchmarks/suite_profile.py")
    sp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sp)
    env = dict(os.environ, **sp.install_probe(tmp_path))
    subprocess.run([sys.executable, "-c", "sum(range(10 ** 6))", "x"], env=env, check=True)
    [rec] = [json.loads(f.read_text()) for f in (tmp_path / "procs").glob("*.json")]
    assert rec["argv"] == ["-c", "x"] and rec["cpu"] > 0 and rec["mods"] == []
    kinds = {"/w/.snakemake/scripts/tmpab_12.fit_shard.py": "job: fit_shard.py",
             "/v/site-packages/snakemake/__main__.py": "snakemake start",
             "/r/src/neumat/cli/__main__.py": "neumat CLI", "/v/bin/neumat": "neumat CLI",
             "-c": "pytest (controller, workers: the tests run in them)",
             "/v/lib/python3.11/venv/__main__.py": "other: -m venv"}
    assert {a: sp.process_kind([a, "--x"]) for a in kinds} == kinds
