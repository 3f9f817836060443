"""profiles/slurm on a real single-node Slurm without accounting (no slurmdbd): a subset of the
tiny DAG runs through sbatch with retries 0, and its outputs equal a local run's; and the
README's one-allocation commands (`srun ... snakemake ...`, `sbatch ... --wrap "snakemake ..."`)
run as written, with --dry-run added.

Runs where it can set Slurm up: as root with apt (Debian packages munge, slurmctld, slurmd,
slurm-client, --no-install-recommends) or with those already installed. The daemons run from a
temporary directory with a minimal slurm.conf and are stopped by PID at the end. Elsewhere the
test skips and names what is missing."""

import contextlib
import importlib.util
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ["munge", "slurmctld", "slurmd", "slurm-client"]
BINARIES = ["munged", "slurmctld", "slurmd", "sbatch", "squeue", "sinfo", "srun", "scontrol"]
# one job of each data rule of the tiny DAG (a MERL table, a BTF): the whole data stage (10 jobs,
# `benchmarks/slurm_overhead.py --until synthetic_merl synthetic_btf`) added ~25 s of the same
# checks to the suite
TARGETS = ["results/tiny/merl/violet-rubber.binary", "results/tiny/btf/data/synthetic_wood.btf"]

pytestmark = [pytest.mark.slow]


def _missing() -> str | None:
    """Why a Slurm cannot be set up here, or None (installing the packages if needed)."""
    if not sys.platform.startswith("linux"):
        return "Linux only"
    if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
        return "snakemake-executor-plugin-slurm is not installed"
    if all(shutil.which(b) or Path(f"/usr/sbin/{b}").exists() for b in BINARIES):
        return None
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        return f"Slurm is not installed ({', '.join(BINARIES)}) and installing it needs root and apt"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    cmd = ["apt-get", "install", "-y", "-qq", "--no-install-recommends", *PACKAGES]
    if subprocess.run(cmd, env=env, capture_output=True).returncode != 0:
        subprocess.run(["apt-get", "update", "-qq"], env=env, capture_output=True)
        res = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if res.returncode != 0:
            return f"apt-get install {' '.join(PACKAGES)} failed: {res.stderr[-300:]}"
    return None


def _memory_mb() -> int:
    kb = int(re.search(r"MemTotal:\s+(\d+)", Path("/proc/meminfo").read_text()).group(1))
    return kb // 1024 - 1024  # leave the OS some


SYSTEM_CONF = Path("/etc/slurm/slurm.conf")


def _slurm_conf(d: Path) -> Path:
    """A minimal slurm.conf. At /etc/slurm/slurm.conf (removed at the end): srun inside a job
    looks there, whatever SLURM_CONF the job was submitted with."""
    host = socket.gethostname().split(".")[0]
    conf = SYSTEM_CONF
    conf.parent.mkdir(exist_ok=True)
    conf.write_text(f"""ClusterName=neumattest
SlurmctldHost={host}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation={d}/state
SlurmdSpoolDir={d}/spool
SlurmctldPidFile={d}/slurmctld.pid
SlurmdPidFile={d}/slurmd.pid
SlurmctldLogFile={d}/slurmctld.log
SlurmdLogFile={d}/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
MinJobAge=300
ReturnToService=2
NodeName={host} CPUs={os.cpu_count()} RealMemory={_memory_mb()} State=UNKNOWN
PartitionName=main Nodes=ALL Default=YES MaxTime=INFINITE State=UP
""")
    (d / "state").mkdir()
    (d / "spool").mkdir()
    return conf


def _sbin(name: str) -> str:
    return shutil.which(name) or f"/usr/sbin/{name}"


class SlurmUnavailable(Exception):
    """No Slurm can be set up here; the message says why."""


@contextlib.contextmanager
def slurm_cluster(d: Path):
    """A single-node Slurm without accounting, its files under `d`: yields the environment
    (SLURM_CONF) for sbatch/squeue and snakemake, and stops the daemons it started by PID.
    Also used by benchmarks/slurm_overhead.py. Raises SlurmUnavailable elsewhere."""
    reason = _missing()
    if reason:
        raise SlurmUnavailable(reason)
    if SYSTEM_CONF.exists():
        raise SlurmUnavailable(f"{SYSTEM_CONF} exists: a Slurm is configured here, the test does "
                               "not touch it")
    conf = _slurm_conf(d)
    env = {**os.environ, "SLURM_CONF": str(conf)}
    pids = []
    try:
        # munge: the packaged key, our own socket and pid file
        key = Path("/etc/munge/munge.key")
        if not key.exists():
            subprocess.run(["mungekey", "--create", "--keyfile", str(key)], check=True)
            shutil.chown(key, "munge", "munge")
        if subprocess.run(["munge", "-n"], capture_output=True).returncode != 0:  # no munged yet
            Path("/run/munge").mkdir(exist_ok=True)
            shutil.chown("/run/munge", "munge", "munge")
            pid = Path("/run/munge/munged.neumat-test.pid")  # a directory the munge user can write
            subprocess.run(["runuser", "-u", "munge", "--", _sbin("munged"), "--force",
                            "--pid-file", str(pid)], check=True)
            pids.append(pid)
        for daemon in ("slurmctld", "slurmd"):
            subprocess.run([_sbin(daemon), "-f", str(conf)], check=True, env=env)
            pids.append(d / f"{daemon}.pid")
        for _ in range(120):
            out = subprocess.run(["sinfo", "-h", "-o", "%t"], env=env, capture_output=True, text=True)
            if out.stdout.strip() in ("idle", "mix"):
                break
            time.sleep(0.5)
        else:
            raise RuntimeError(f"the Slurm node did not come up: {out.stdout} {out.stderr}\n"
                               + (d / "slurmctld.log").read_text()[-2000:])
        yield env
    finally:
        for pid_file in reversed(pids):  # stop what we started, by PID
            if pid_file.exists():
                try:
                    os.kill(int(pid_file.read_text().split()[0]), signal.SIGTERM)
                except (ProcessLookupError, ValueError):
                    pass
        SYSTEM_CONF.unlink(missing_ok=True)


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    try:
        with slurm_cluster(tmp_path_factory.mktemp("slurm")) as env:
            yield env
    except SlurmUnavailable as e:
        pytest.skip(str(e))


def _copy_workflow(dst: Path) -> Path:
    dst.mkdir(parents=True)
    for item in ("Snakefile", "workflow", "config", "profiles", "src"):
        src = ROOT / item
        (shutil.copytree if src.is_dir() else shutil.copy)(src, dst / item)
    return dst


def test_profile_runs_jobs_through_sbatch_without_accounting(slurm, tmp_path):
    remote, local = _copy_workflow(tmp_path / "slurm"), _copy_workflow(tmp_path / "local")
    cmd = [sys.executable, "-m", "snakemake", *TARGETS, "--retries", "0"]
    t0 = time.time()
    # --cores: the most CPUs a (group) job may ask for, this node's (the profile's is 8)
    res = subprocess.run([*cmd, "--profile", "profiles/slurm", "--cores", str(os.cpu_count()),
                          "--configfile", "config/tiny.yaml"],
                         cwd=remote, env=slurm, capture_output=True, text=True, timeout=1800)
    slurm_s = time.time() - t0
    text = res.stdout + res.stderr
    assert res.returncode == 0, text[-6000:]
    t0 = time.time()
    subprocess.run([*cmd, "--cores", "2", "--configfile", "config/tiny.yaml"], cwd=local,
                   check=True, capture_output=True)
    local_s = time.time() - t0
    # every job went through sbatch: each one the run executed is listed under a (group) job
    # that was submitted, and none ran on the submit host ("localrule")
    n_done = int(re.findall(r"(\d+) of \d+ steps", text)[-1])  # "2 of 2 steps"
    executed = sum(int(n) for n in re.findall(r"^Execute (\d+) jobs", text, re.M))
    submitted = re.findall(r"submitted with SLURM jobid", text)
    listed = re.findall(r"^\s*rule \w+:$", text, re.M)
    assert "localrule " not in text and len(submitted) == executed >= 1, text[-3000:]
    assert len(listed) == n_done == len(TARGETS), text[-3000:]
    files = sorted(p.relative_to(local) for p in (local / "results/tiny").rglob("*")
                   if p.is_file() and "/logs/" not in str(p) and "/benchmarks/" not in str(p))
    assert files
    for f in files:
        assert (remote / f).read_bytes() == (local / f).read_bytes(), f
    # not asserted: on a shared 2-core machine the ratio swings with the load
    print(f"{n_done} jobs in {len(submitted)} sbatch jobs: via Slurm {slurm_s:.0f} s, "
          f"local {local_s:.0f} s ({slurm_s / local_s:.2f}x), load {os.getloadavg()[0]:.1f}")


def readme_allocation_commands() -> list[str]:
    """`srun ...` and `sbatch ...` lines of the README's bash blocks: Snakemake in one allocation."""
    blocks = re.findall(r"```bash\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    return [ln.strip() for b in blocks for ln in b.splitlines()
            if ln.strip().startswith(("srun ", "sbatch "))]


def test_readme_has_allocation_commands():
    cmds = readme_allocation_commands()
    assert {c.split()[0] for c in cmds} == {"srun", "sbatch"}, cmds
    assert all("snakemake --cores" in c for c in cmds), cmds


@pytest.mark.parametrize("cmd", readme_allocation_commands())
def test_readme_allocation_command_runs_in_slurm(slurm, tmp_path, cmd):
    """Each command as written, with --dry-run added to the Snakemake it runs (and, for sbatch,
    --output, to read the batch job's output): Snakemake plans the whole DAG for the local
    executor inside the allocation."""
    import shlex
    wd = _copy_workflow(tmp_path / "wf")
    args = shlex.split(cmd)
    if args[0] == "sbatch":
        i = args.index("--wrap") + 1
        args[i] += " --dry-run"
        args += ["--output", "allocation.out"]
    else:
        args.append("--dry-run")
    res = subprocess.run(args, cwd=wd, env=slurm, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    out = res.stdout + res.stderr
    if args[0] == "sbatch":
        job = re.match(r"Submitted batch job (\d+)", res.stdout).group(1)
        state = _wait_for(job, slurm)  # not `sbatch --wait`: it polls at growing intervals
        out = (wd / "allocation.out").read_text()
        assert state == ("COMPLETED", "0:0"), (state, out[-3000:])
    assert re.search(r"^report\s+1$", out, re.M) and "This was a dry-run" in out, out[-3000:]


def _wait_for(job: str, env: dict, timeout: float = 600) -> tuple[str, str]:
    """(JobState, ExitCode) of a batch job once it has ended (MinJobAge keeps it listed)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        info = subprocess.run(["scontrol", "show", "job", job], env=env, capture_output=True,
                              text=True).stdout
        state = re.search(r"JobState=(\S+)", info)
        if state and state.group(1) not in ("PENDING", "RUNNING", "CONFIGURING", "COMPLETING"):
            return state.group(1), re.search(r"ExitCode=(\S+)", info).group(1)
        time.sleep(0.25)
    raise AssertionError(f"batch job {job} did not end within {timeout} s")


def test_overhead_benchmark_work_dir(tmp_path):
    """benchmarks/slurm_overhead.py's default invocation (no --keep) once failed on the directory
    mkdtemp had made; --keep empties and reuses its directory."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("slurm_overhead", ROOT / "benchmarks/slurm_overhead.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    tmp = bench.work_dir(None)
    assert tmp.is_dir() and not any(tmp.iterdir())
    tmp.rmdir()
    keep = tmp_path / "keep"
    (bench.work_dir(keep) / "old").write_text("x")
    assert bench.work_dir(keep) == keep and not any(keep.iterdir())


def test_every_rule_that_runs_torch_on_the_config_device_can_ask_for_a_gpu():
    """With `device: cuda` a job whose script resolves the config's device must ask Slurm for
    a GPU (resources gpu), or it lands on a node without one and fails ('torch sees no CUDA
    device'); six rules asked for none."""
    scripts = {p.name for p in (ROOT / "workflow/scripts").glob("*.py")
               if 'config["device"]' in p.read_text()}
    missing, seen = [], 0
    for smk in (ROOT / "workflow/rules").glob("*.smk"):
        text = smk.read_text()
        for m in re.finditer(r"^rule (\w+):(.*?)(?=^rule |\Z)", text, re.S | re.M):
            script = re.search(r'script:\s*\n\s*"\.\./scripts/(\w+\.py)"', m.group(2))
            if script and script.group(1) in scripts:
                seen += 1
                if not re.search(r"\n        gpu=", m.group(2)):
                    missing.append(f"{smk.name}: {m.group(1)}")
    assert seen >= 20 and not missing, missing
