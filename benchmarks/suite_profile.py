"""Where the suite's time goes: `pytest` run as the README runs it, with this file as a plugin
on every xdist worker recording each test's start, wall time and CPU time (its process and the
children it waited for: the snakemake, neumat and python processes tests start).

Prints the suite's wall and CPU time against its bound on this machine, CPU-s / CPUs (the
suite is CPU-bound when wall is near it: then only less CPU work shortens it), the tests with
the most CPU, the CPU per module, when the tests that read the finished tiny run started
(conftest.py runs the tiny run in the background; those tests are the suite's tail), how long
start-up took before the first test, and per worker when its last test ended and how long it
waited for the tiny run (idle cores, where the suite is not CPU-bound).

    python benchmarks/suite_profile.py                  # the whole suite, as the README runs it
    python benchmarks/suite_profile.py --top 30 -- -m "not slow"   # arguments after -- go to pytest

The tiny run's own CPU is not attributed to a test (it runs in the background); it is in the
suite's total.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = "NEUMAT_PYTEST_PROFILE_DIR"


def _cpu() -> float:
    """CPU seconds of this process and of its waited-for children."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):  # the plugin: one JSON line per test
    out = os.environ.get(ENV)
    t0, c0 = time.time(), _cpu()
    yield
    if out:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        row = {"id": item.nodeid, "start": t0, "wall": time.time() - t0, "cpu": _cpu() - c0,
               "tiny": "tiny_run" in getattr(item, "fixturenames", ())}
        with open(Path(out) / f"{worker}.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")


@pytest.hookimpl(hookwrapper=True)
def pytest_fixture_setup(fixturedef, request):  # how long a worker waited for the tiny run
    t0 = time.time()
    yield
    out = os.environ.get(ENV)
    if out and fixturedef.argname == "tiny_run":
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(Path(out) / f"{worker}.wait", "w") as f:
            json.dump({"start": t0, "wall": time.time() - t0}, f)


def report(rows: list[dict], waits: dict, launched: float, wall: float, cpu: float,
           top: int) -> None:
    from neumat import machine
    n = os.cpu_count() or 1
    print(f"machine: {machine.describe()}")
    print(f"suite: {wall:.1f} s wall, {cpu:.0f} CPU-s; bound on {n} CPUs {cpu / n:.1f} s: wall is "
          f"{wall / (cpu / n):.2f}x the bound, the cores {cpu / (n * wall):.0%} busy")
    attributed = sum(r["cpu"] for r in rows)
    print(f"{len(rows)} tests: {attributed:.0f} CPU-s attributed to tests; the rest "
          f"({cpu - attributed:.0f} CPU-s) is the background tiny run, worker start-up and collection")
    t0 = min(r["start"] for r in rows)
    tiny = [r for r in rows if r["tiny"]]
    if tiny:
        first = min(r["start"] for r in tiny) - t0
        print(f"tests reading the tiny run: first started {first:.1f} s in; the suite ended "
              f"{wall - first:.1f} s later")
    print(f"start-up (pytest, workers, collection): the first test started {t0 - launched:.1f} s "
          f"after launch")
    for worker in sorted({r["worker"] for r in rows}):
        mine = [r for r in rows if r["worker"] == worker]
        end = max(r["start"] + r["wall"] for r in mine) - launched
        print(f"  {worker}: {sum(r['tiny'] for r in mine)} of its {len(mine)} tests read the tiny "
              f"run; its last test ended {end:.1f} s after launch, {wall - end:.1f} s before the end")
        if worker in waits:
            w = waits[worker]
            print(f"  {worker}: waited {w['wall']:.1f} s for the tiny run to finish, from "
                  f"{w['start'] - launched:.1f} s after launch")
    print(f"\n{'CPU-s':>7} {'wall s':>7}  test (top {top} by CPU)")
    for r in sorted(rows, key=lambda r: -r["cpu"])[:top]:
        print(f"{r['cpu']:7.1f} {r['wall']:7.1f}  {r['id']}")
    per = Counter()
    for r in rows:
        per[r["id"].split("::")[0]] += r["cpu"]
    print(f"\n{'CPU-s':>7}  module")
    for mod, c in per.most_common(top):
        print(f"{c:7.1f}  {mod}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--top", type=int, default=20, help="tests and modules listed (default 20)")
    ap.add_argument("pytest_args", nargs="*", help="after --: arguments for pytest")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        env = dict(os.environ, **{ENV: d})
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "benchmarks"), env.get("PYTHONPATH", "")])
        c0, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
        launched = time.time()  # the tests' start times are wall-clock
        rc = subprocess.call([sys.executable, "-m", "pytest", "-p", "suite_profile",
                              *a.pytest_args], cwd=ROOT, env=env)
        wall, c1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
        rows = [dict(json.loads(line), worker=f.stem) for f in Path(d).glob("*.jsonl")
                for line in f.open()]
        waits = {f.stem: json.loads(f.read_text()) for f in Path(d).glob("*.wait")}
    if not rows:
        print(f"pytest exited with {rc} and ran no test", file=sys.stderr)
        return rc or 1
    report(rows, waits, launched, wall, cpu, a.top)
    return rc


if __name__ == "__main__":
    sys.exit(main())
