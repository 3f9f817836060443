"""The tiny run through profiles/slurm against the same run locally, on the same node.

Sets up the single-node Slurm of tests/test_slurm.py (root, munge/slurmctld/slurmd installed or
installable with apt; no accounting), copies the workflow twice, runs the targets locally
(`--cores N`) and via Slurm (`--profile profiles/slurm`), back to back, each with its own `run:`
name, and prints both walls, their ratio, the job counts (local vs sbatch vs local rules on the
submit host), the load average and the CPU, and the local run's wall against its CPU bound,
CPU-s (Snakemake and its jobs, waited-for children) / cores (the Slurm run's jobs are slurmd's
children, not this process's: their CPU is not measured here). Then, per Slurm job, where the
time went:

    ready -> sbatch     the outer Snakemake decided to run the job -> slurmctld got it
    sbatch -> start     slurmctld queue: waiting for a free CPU/memory, then the scheduler
    in job              the allocation's life minus the job's own run (its benchmark `s`):
                        the sbatch-level Snakemake, srun, the inner Snakemake, file checks
    end -> detected     slurmctld marked it complete -> the outer Snakemake saw it (status poll)

    python benchmarks/slurm_overhead.py                       # whole tiny run (report)
    python benchmarks/slurm_overhead.py --until synthetic_merl synthetic_btf   # test subset
    python benchmarks/slurm_overhead.py --order slurm-first --keep /tmp/slurm_bench
    python benchmarks/slurm_overhead.py --slurm-mode allocation   # Snakemake inside one allocation

`--slurm-mode allocation` runs the Slurm side as the README's one-allocation command does,
`srun --cpus-per-task N snakemake --cores N ...`: one allocation whose Snakemake runs every job
locally on its CPUs (no per-job sbatch, so no per-job breakdown). srun, not `sbatch --wait`: the
latter polls the job's state at growing intervals; in a scratch variant of this script it
returned 19 s after a 23 s job had ended (AMD EPYC, 2 cores, 2026-11-26).

Outputs of both runs are compared byte for byte (logs and benchmarks aside). Times are wall
clock on a machine that may be shared: it prints `uptime`'s load next to each run.
"""
import argparse
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "src"))

import test_slurm  # noqa: E402  (its Slurm set-up: slurm_cluster, _copy_workflow)
from neumat import machine  # noqa: E402


def load() -> str:
    return "load average " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def run_snakemake(cmd, cwd, env, log_path):
    """Run `cmd`, time-stamping every output line as it arrives: (wall s, [(t, line)])."""
    t0 = time.time()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, bufsize=1)
    lines = []
    with open(log_path, "w") as f:
        for line in proc.stdout:
            t = time.time()
            lines.append((t, line.rstrip("\n")))
            f.write(f"{t:.3f} {line}")  # epoch seconds, as slurmctld.log's times
    rc = proc.wait()
    wall = time.time() - t0
    if rc:
        tail = "\n".join(line for _, line in lines[-60:])
        raise SystemExit(f"{' '.join(cmd)} failed ({rc}) in {cwd}; log {log_path}\n{tail}")
    return wall, lines


def outer_events(lines):
    """Per Snakemake jobid: rule, time it was announced, SLURM id, time its end was seen;
    and the jobs run on the submit host (localrule)."""
    jobs = defaultdict(dict)
    local = []
    pending = None  # (time, rule, is_local) until its "jobid:" line
    current = None  # the jobid whose announcement is being read (for its "benchmark:" line)
    for t, line in lines:
        m = re.match(r"^(local)?rule (\w+):$", line.strip())
        if m:
            pending = (t, m.group(2), bool(m.group(1)))
            continue
        m = re.match(r"^jobid: (\d+)$", line.strip())
        if m and pending:
            j = jobs[int(m.group(1))]
            j.update(announced=pending[0], rule=pending[1], local=pending[2])
            if pending[2]:
                local.append(pending[1])
            pending, current = None, int(m.group(1))
            continue
        m = re.match(r"^benchmark: (\S+)$", line.strip())
        if m and current is not None:
            jobs[current]["bench"] = m.group(1)
            current = None
            continue
        m = re.search(r"Job (\d+) has been submitted with SLURM jobid (\d+)", line)
        if m:
            jobs[int(m.group(1))].update(slurm=int(m.group(2)), submitted_seen=t)
            continue
        m = re.search(r"Finished jobid: (\d+)", line)
        if m:
            jobs[int(m.group(1))]["detected"] = t
    return jobs, local


def ctld_events(log: Path, slurmd_log: Path | None = None):
    """Per SLURM jobid: submit, allocate (start) and complete times from slurmctld.log, and
    from slurmd.log when given, the launch of its step (the job script's Snakemake calls srun)
    and the step's end (the inner Snakemake, around the rule, is done)."""
    ev = defaultdict(dict)
    pats = {"submit": r"_slurm_rpc_submit_batch_job: JobId=(\d+)",
            "start": r"(?:Allocate|_start_job: Started) JobId=(\d+)",  # scheduler or backfill
            "end": r"_job_complete: JobId=(\d+) done",
            "step": r"launch task StepId=(\d+)\.0 ",
            "step_end": r"\[(\d+)\.0\] done with job"}
    text = log.read_text() + (slurmd_log.read_text() if slurmd_log else "")
    for line in text.splitlines():
        m = re.match(r"^\[([\d\-T:.]+)\] (.*)$", line)
        if not m:
            continue
        t = datetime.fromisoformat(m.group(1)).timestamp()
        for key, pat in pats.items():
            mm = re.search(pat, m.group(2))
            if mm:
                ev[int(mm.group(1))].setdefault(key, t)
    return ev


def job_seconds(path: Path) -> float:
    """A job's own run time: its benchmark file's `s` (the script, timed inside the job)."""
    return float(path.read_text().splitlines()[-1].split("\t")[0])


def mean_allocated(log: Path) -> float:
    """CPUs Slurm kept allocated, on average from the first start to the last end."""
    start, cpus, total, first, last = {}, {}, 0.0, None, None
    for line in log.read_text().splitlines():
        m = re.match(r"^\[([\d\-T:.]+)\] (.*)$", line)
        if not m:
            continue
        t = datetime.fromisoformat(m.group(1)).timestamp()
        a = re.search(r"(?:Allocate|Started) JobId=(\d+)(?: NodeList=\S+ #CPUs=(\d+))?", m.group(2))
        if a:  # a backfill start does not name its CPUs: counted as 1
            start[a.group(1)], cpus[a.group(1)] = t, int(a.group(2) or 1)
            first = first or t
        e = re.search(r"_job_complete: JobId=(\d+) done", m.group(2))
        if e and e.group(1) in start:
            total += (t - start[e.group(1)]) * cpus[e.group(1)]
            last = t
    return total / (last - first) if first and last and last > first else 0.0


def breakdown(jobs, ctld, wd):
    """Rows (rule, ready->sbatch, queue, in-job overhead, job s, end->detected) per sbatch job."""
    rows = []
    for j in jobs.values():
        if "slurm" not in j or j["slurm"] not in ctld:
            continue
        c = ctld[j["slurm"]]
        if not {"submit", "start", "end"} <= set(c) or "detected" not in j:
            continue
        s = job_seconds(wd / j["bench"])
        rows.append(dict(rule=j["rule"], ready=c["submit"] - j["announced"],
                         queue=c["start"] - c["submit"], injob=c["end"] - c["start"] - s,
                         own=s, detect=j["detected"] - c["end"],
                         script=c.get("step", c["start"]) - c["start"],  # split of "in job"
                         inner=c.get("step_end", c["end"]) - c.get("step", c["start"]) - s,
                         after=c["end"] - c.get("step_end", c["end"])))
    return rows


def print_breakdown(rows):
    cols = ["ready", "queue", "injob", "own", "detect"]
    print(f"\nper sbatch job, seconds (mean over the rule's jobs; {len(rows)} jobs):")
    print(f"{'rule':28s} {'n':>3s} {'ready->sbatch':>13s} {'sbatch->start':>13s} "
          f"{'in job (ovh)':>12s} {'own run':>8s} {'end->detect':>11s}")
    groups = defaultdict(list)
    for r in rows:
        groups[r["rule"]].append(r)
    for rule, rs in sorted(groups.items(), key=lambda kv: -sum(r["own"] for r in kv[1])):
        m = [sum(r[c] for r in rs) / len(rs) for c in cols]
        print(f"{rule:28s} {len(rs):3d} {m[0]:13.2f} {m[1]:13.2f} {m[2]:12.2f} {m[3]:8.2f} {m[4]:11.2f}")
    if rows:
        tot = [sum(r[c] for r in rows) for c in cols]
        mean = [x / len(rows) for x in tot]
        print(f"{'mean':28s} {len(rows):3d} " + " ".join(f"{x:{w}.2f}" for x, w in
                                                       zip(mean, (13, 13, 12, 8, 11))))
        print(f"{'sum':28s} {'':3s} " + " ".join(f"{x:{w}.1f}" for x, w in
                                                 zip(tot, (13, 13, 12, 8, 11))))
        split = [sum(r[c] for r in rows) / len(rows) for c in ("script", "inner", "after")]
        print("in job, mean: job script's Snakemake until srun {:.2f} s, inner Snakemake around "
              "the rule {:.2f} s (its step minus the rule's own run), step end to job end "
              "{:.2f} s".format(*split))


def read_log(path: Path):
    """[(t, line)] back from a log written by run_snakemake."""
    return [(float(t), line.rstrip("\n")) for t, _, line in
            (raw.partition(" ") for raw in open(path))]


def analyse(work: Path):
    jobs, local = outer_events(read_log(work / "slurm.log"))
    print_breakdown(breakdown(jobs, ctld_events(work / "slurmctld.log", work / "slurmd.log"),
                              work / "slurm"))
    print(f"local rules on the submit host: {len(local)}; CPUs allocated by Slurm, mean: "
          f"{mean_allocated(work / 'slurmctld.log'):.2f}")


def same_outputs(a: Path, b: Path, run_a: str, run_b: str):
    """Relative paths whose bytes differ between the two runs (logs, benchmarks, the report's
    HTML/Markdown, which name the run, aside)."""
    ra, rb = a / f"results/{run_a}", b / f"results/{run_b}"
    skip = ("logs/", "benchmarks/", "report/")
    files = sorted(p.relative_to(ra) for p in ra.rglob("*") if p.is_file()
                   and not str(p.relative_to(ra)).startswith(skip))
    missing = [f for f in files if not (rb / f).exists()]
    differ = [f for f in files if (rb / f).exists() and (ra / f).read_bytes() != (rb / f).read_bytes()]
    return len(files), missing, differ


def work_dir(keep: Path | None) -> Path:
    """An empty directory for the two runs: `keep` (emptied first) or a new temporary one."""
    if keep is None:
        return Path(tempfile.mkdtemp(prefix="slurm_overhead_"))
    if keep.exists():
        shutil.rmtree(keep)
    keep.mkdir(parents=True)
    return keep


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("targets", nargs="*", default=["report"])
    ap.add_argument("--until", nargs="+", default=None, help="snakemake --until RULES")
    ap.add_argument("--configfile", default="config/tiny.yaml")
    ap.add_argument("--cores", type=int, default=os.cpu_count(),
                    help="local --cores, and the most CPUs one Slurm job asks for")
    ap.add_argument("--order", choices=["local-first", "slurm-first"], default="local-first")
    ap.add_argument("--only", choices=["both", "local", "slurm"], default="both")
    ap.add_argument("--keep", type=Path, default=None, help="work in this directory and keep it")
    ap.add_argument("--analyse", type=Path, default=None, metavar="DIR",
                    help="only print the per-job breakdown of a run kept with --keep DIR")
    ap.add_argument("--slurm-mode", choices=["jobs", "allocation"], default="jobs",
                    help="jobs: profiles/slurm, one sbatch job per job (default); allocation: "
                    "the whole run in one allocation, by srun (README, Running on Slurm)")
    ap.add_argument("--slurm-args", default="", help="extra snakemake args for the Slurm run, "
                    "e.g. '--slurm-array-jobs=all'")
    args = ap.parse_args()
    if args.analyse:
        return analyse(args.analyse)

    work = work_dir(args.keep)
    print(f"machine: {machine.describe()}; work dir {work}")
    base = [sys.executable, "-m", "snakemake", *args.targets]
    if args.until:
        base += ["--until", *args.until]
    base += ["--retries", "0"]
    runs = {"local": "bench_local", "slurm": "bench_slurm"}
    order = ["local", "slurm"] if args.order == "local-first" else ["slurm", "local"]
    order = [o for o in order if args.only in ("both", o)]
    results = {}
    with test_slurm.slurm_cluster(work) as env:
        env = {**env, "OMP_NUM_THREADS": env.get("OMP_NUM_THREADS", "1")}
        for kind in order:
            wd = test_slurm._copy_workflow(work / kind)
            if kind == "local" or args.slurm_mode == "allocation":
                cmd = [*base, "--cores", str(args.cores)]
            else:
                cmd = [*base, "--profile", "profiles/slurm", "--cores", str(args.cores),
                       "--slurm-keep-successful-logs", *args.slurm_args.split()]
            cmd += ["--configfile", args.configfile, "--config", f"run={runs[kind]}"]
            before = load()
            print(f"\n[{kind}] {' '.join(cmd[2:])}\n[{kind}] before: {before}", flush=True)
            if kind == "slurm" and args.slurm_mode == "allocation":
                cmd = ["srun", "--cpus-per-task", str(args.cores), *cmd]
            c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            wall, lines = run_snakemake(cmd, wd, env, work / f"{kind}.log")
            c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = c1.ru_utime - c0.ru_utime + c1.ru_stime - c0.ru_stime
            jobs, local = outer_events(lines)
            done = sum(1 for j in jobs.values() if "detected" in j)
            n_sbatch = sum(1 for j in jobs.values() if "slurm" in j)
            results[kind] = dict(wall=wall, wd=wd, jobs=jobs, local=local, done=done,
                                 sbatch=n_sbatch, load=(before, load()))
            where = ("in one srun allocation" if kind == "slurm" and args.slurm_mode == "allocation"
                     else f"{n_sbatch} via sbatch, "
                     f"{len(local) if kind == 'slurm' else done} on the submit host")
            print(f"[{kind}] wall {wall:.1f} s, {done} jobs ({where}); "
                  f"after: {results[kind]['load'][1]}", flush=True)
            if kind == "local":  # only here is every job a waited-for child of this process
                n = min(args.cores, os.cpu_count() or 1)
                print(f"[local] {cpu:.1f} CPU-s; bound on {n} cores {cpu / n:.1f} s: wall is "
                      f"{wall / (cpu / n):.2f}x the bound, the cores {cpu / (n * wall):.0%} busy",
                      flush=True)
        ctld_log = work / "slurmctld.log"
        if "slurm" in results and args.slurm_mode == "jobs":
            rows = breakdown(results["slurm"]["jobs"], ctld_events(ctld_log, work / "slurmd.log"),
                             results["slurm"]["wd"])
            print_breakdown(rows)
            print(f"CPUs allocated by Slurm, mean: {mean_allocated(ctld_log):.2f}")
            if local := results["slurm"]["local"]:
                print(f"local rules on the submit host: {len(local)} "
                      f"({', '.join(sorted(set(local)))})")

    print(f"\nmachine: {machine.describe()}")
    if len(results) == 2:
        lo, sl = results["local"], results["slurm"]
        n, missing, differ = same_outputs(lo["wd"], sl["wd"], runs["local"], runs["slurm"])
        # files that record wall times (train_seconds, timing.tsv, info.tsv) differ between
        # any two runs; the list is printed whole so that the rest can be checked by hand
        print(f"outputs: {n} files compared, {len(missing)} missing via Slurm, {len(differ)} "
              "differ" + (f": {' '.join(map(str, missing + differ))}" if missing or differ else ""))
        print(f"local: {lo['wall']:.1f} s, {lo['done']} jobs ({lo['load'][0]} before)")
        if args.slurm_mode == "allocation":
            print(f"slurm: {sl['wall']:.1f} s, {sl['done']} jobs in one srun allocation of "
                  f"{args.cores} CPUs ({sl['load'][0]} before)")
        else:
            print(f"slurm: {sl['wall']:.1f} s, {sl['done']} jobs: {sl['sbatch']} via sbatch, "
                  f"{len(sl['local'])} local rules ({sl['load'][0]} before)")
        print(f"ratio slurm/local: {sl['wall'] / lo['wall']:.2f}x")
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
