"""A benchmark run again in fresh processes, its figures gathered (`--processes N` of
btf_kernel_ab.py and btf_synthesis.py). A process's allocations, stack and libraries' addresses
move its CPU-time figures by more than its own rounds do: identical kernel code in two libraries
differed by 16.5 CPU-ms a frame (6.8 %) in one process, and HPB's overhead ranged +0.8 to +9.1 %
between five processes whose medians agreed within a point (Intel Xeon AVX-512, 2026-11-30;
docs/stages.md, "BTF synthesis on the positional plane"). So a verdict takes the median over
several processes.

The parent runs the same script with the same arguments plus FLAG; each child does one run and
prints its figures as one tagged JSON line (`emit`)."""

from __future__ import annotations

import json
import subprocess
import sys

FLAG = "--one-process"
TAG = "fresh_processes result: "


def emit(result: dict) -> None:
    """A child's figures to its parent: one tagged JSON line on stdout."""
    print(TAG + json.dumps(result), flush=True)


def gather(script: str, n: int) -> list[dict]:
    """The figures of `n` runs of `script` with this process's arguments, one fresh process each,
    in turn. A child that fails ends this process with its exit code and stderr."""
    runs = []
    for i in range(n):
        done = subprocess.run([sys.executable, script, *sys.argv[1:], FLAG],
                              capture_output=True, text=True)
        lines = [l for l in done.stdout.splitlines() if l.startswith(TAG)]
        if done.returncode or not lines:
            sys.exit(f"process {i + 1} of {n} failed (exit {done.returncode}):\n"
                     + done.stderr[-4000:])
        runs.append(json.loads(lines[-1][len(TAG):]))
        print(f"process {i + 1} of {n} done", file=sys.stderr, flush=True)
    return runs
