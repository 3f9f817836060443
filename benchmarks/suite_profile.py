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
suite's total. --processes also logs every Python process the suite starts (a `sitecustomize`
on PYTHONPATH writes its own CPU time, wall time, argv and whether it imported torch or
sentence-transformers when it exits) and prints their CPU by kind: workflow jobs (per script),
Snakemake starts, `neumat` CLI runs, the pytest processes. A process killed by a signal writes
nothing, and CPU outside Python (sbatch, the Slurm daemons) is not in it.

    python benchmarks/suite_profile.py --processes      # + CPU per kind of process
"""
from __future__ import annotations

import argparse
import json
import os
import re
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


PROC_ENV = "NEUMAT_PROCESS_LOG"
# the --processes probe: imported by every Python process that finds it on PYTHONPATH
PROBE = f"""import atexit, os, resource, sys, time
_t0 = time.time()
def _log():
    r = resource.getrusage(resource.RUSAGE_SELF)
    mods = [m for m in ("torch", "sentence_transformers") if m in sys.modules]
    try:
        with open(os.path.join(os.environ["{PROC_ENV}"], f"{{os.getpid()}}.json"), "w") as f:
            f.write(__import__("json").dumps({{"cpu": r.ru_utime + r.ru_stime,
                    "wall": time.time() - _t0, "argv": sys.argv, "mods": mods}}))
    except (KeyError, OSError):
        pass
atexit.register(_log)
"""


def install_probe(d: Path) -> dict[str, str]:
    """The probe as `d`/probe/sitecustomize.py, logging into `d`/procs: the environment
    variables that turn it on for the processes started with them."""
    (d / "probe").mkdir()
    (d / "procs").mkdir()
    (d / "probe" / "sitecustomize.py").write_text(PROBE)
    return {"PYTHONPATH": str(d / "probe"), PROC_ENV: str(d / "procs")}


def process_kind(argv: list[str]) -> str:
    """What a logged process was, from its argv."""
    job = re.search(r"\.snakemake/scripts/tmp\w+\.(\w+)\.py", " ".join(argv))
    if job:
        return f"job: {job.group(1)}.py"
    first = argv[0] if argv else ""
    if first.endswith("snakemake/__main__.py") or Path(first).name == "snakemake":
        return "snakemake start"
    if first.endswith("neumat/cli/__main__.py") or Path(first).name == "neumat":
        return "neumat CLI"
    if first == "-c" or "pytest" in first:  # xdist workers run `python -c ...`
        return "pytest (controller, workers: the tests run in them)"
    name = Path(first).name
    if name == "__main__.py":  # python -m <package>
        name = f"-m {Path(first).parent.name}"
    return f"other: {name or 'python'}"


def report_processes(procs: list[dict], top: int) -> None:
    kinds: dict[str, list] = {}
    for p in procs:
        kinds.setdefault(process_kind(p["argv"]), []).append(p)
    jobs = [p for k, ps in kinds.items() if k.startswith("job:") for p in ps]
    total = sum(p["cpu"] for p in procs)
    print(f"\n{len(procs)} Python processes logged, {total:.0f} CPU-s "
          f"({sum('torch' in p['mods'] for p in procs)} imported torch, "
          f"{sum('sentence_transformers' in p['mods'] for p in procs)} sentence-transformers)")
    print(f"{'count':>6} {'CPU-s':>7} {'per one':>8}  kind")
    rows = [(k, ps) for k, ps in kinds.items() if not k.startswith("job:")]
    rows.append(("workflow jobs, all scripts", jobs))
    for k, ps in sorted(rows, key=lambda kp: -sum(p["cpu"] for p in kp[1])):
        c = sum(p["cpu"] for p in ps)
        print(f"{len(ps):6d} {c:7.1f} {c / max(len(ps), 1):8.2f}  {k}")
    print(f"\n{'count':>6} {'CPU-s':>7} {'per one':>8}  workflow job script (top {top} by CPU)")
    per = sorted(((k, ps) for k, ps in kinds.items() if k.startswith("job:")),
                 key=lambda kp: -sum(p["cpu"] for p in kp[1]))
    for k, ps in per[:top]:
        c = sum(p["cpu"] for p in ps)
        print(f"{len(ps):6d} {c:7.1f} {c / len(ps):8.2f}  {k[5:]}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--top", type=int, default=20, help="tests and modules listed (default 20)")
    ap.add_argument("--processes", action="store_true",
                    help="also log every Python process and print CPU per kind of process")
    ap.add_argument("pytest_args", nargs="*", help="after --: arguments for pytest")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        env = dict(os.environ, **{ENV: d})
        path = [str(ROOT / "benchmarks")]
        if a.processes:
            probe = install_probe(Path(d))
            path.insert(0, probe.pop("PYTHONPATH"))
            env.update(probe)
        env["PYTHONPATH"] = os.pathsep.join([*path, env.get("PYTHONPATH", "")])
        c0, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
        launched = time.time()  # the tests' start times are wall-clock
        rc = subprocess.call([sys.executable, "-m", "pytest", "-p", "suite_profile",
                              *a.pytest_args], cwd=ROOT, env=env)
        wall, c1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
        rows = [dict(json.loads(line), worker=f.stem) for f in Path(d).glob("*.jsonl")
                for line in f.open()]
        waits = {f.stem: json.loads(f.read_text()) for f in Path(d).glob("*.wait")}
        procs = [json.loads(f.read_text()) for f in Path(d).glob("procs/*.json")]
    if not rows:
        print(f"pytest exited with {rc} and ran no test", file=sys.stderr)
        return rc or 1
    report(rows, waits, launched, wall, cpu, a.top)
    if a.processes:
        report_processes(procs, a.top)
    return rc


if __name__ == "__main__":
    sys.exit(main())
