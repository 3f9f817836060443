"""Every command written in README.md and docs/*.md is tested as written, so a documented
command cannot rot unnoticed. Commands are found, not listed: a new command in the README is tested without
touching this file.

- `snakemake ...` (README, Snakefile header, profiles' headers): run verbatim with --dry-run
  added, in a copy of the workflow (the checkout's .snakemake/ and results/ stay untouched).
- `neumat ...` (README code blocks, and inline spans with arguments): run verbatim against the
  tiny run (conftest.py `tiny_run`), as `python -m neumat.cli ...` (the console script's
  module), side by side; a command that reads another's output runs after it. One mechanical
  substitution: the README names the default config's run, `results/default`; the commands run
  in a directory where `results/default` is a link to the tiny run's `results/tiny`, so their
  text is unchanged.
- The Quickstart's shell chains and the other commands (`python benchmarks/...`,
  `./.ci/run`): too costly to run here (an install, the whole suite, realistic data), so each
  part is checked cheaply: the file or extra it names exists, every flag it passes is one its
  program accepts (its --help, or an argparse literal in a benchmarks/ script), and `.ci/run` runs the README's test command verbatim. A command with no
  check fails the test, naming it."""

import importlib.util
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("*.md")),
        "Snakefile", *sorted(str(p.relative_to(ROOT)) for p in
                             (ROOT / "profiles").glob("*/config.yaml"))]


def _commands_in(text: str) -> list[str]:
    """`snakemake ...` commands in inline code spans (also those wrapped over lines), code
    blocks and comment lines; a shell chain (`a && snakemake ...`) contributes its snakemake
    part."""
    prose = re.sub(r"```.*?```", "", text, flags=re.S)  # fenced blocks: by lines, below
    spans = [" ".join(s.split()) for s in re.findall(r"`([^`]*snakemake [^`]*)`", prose)]
    lines = [ln.lstrip("# ").strip() for ln in text.splitlines()]
    spans += [ln for ln in lines if "snakemake " in ln and "`" not in ln]
    cmds = []
    for span in spans:
        for part in span.split("&&"):
            part = part.strip()
            if part.startswith("snakemake ") and part not in cmds:
                cmds.append(part)
    return cmds


def documented_commands() -> list[tuple[str, str]]:
    """(first document that has it, command), each command once."""
    seen = {}
    for doc in DOCS:
        for cmd in _commands_in((ROOT / doc).read_text()):
            seen.setdefault(cmd, doc)
    return [(doc, cmd) for cmd, doc in seen.items()]


def test_commands_are_found():
    """The extractor sees the commands we know are there (guards against a silent empty list)."""
    cmds = [c for _, c in documented_commands()]
    assert "snakemake --cores 2 report" in cmds
    assert any("--profile profiles/slurm" in c for c in cmds)
    assert any("config/tiny.yaml" in c for c in cmds)


def _missing_plugin(args: list[str]) -> str | None:
    """Why a command cannot run here (its profile's executor plugin is absent), or None."""
    if "--profile" not in args:
        return None
    profile = ROOT / args[args.index("--profile") + 1] / "config.yaml"
    m = re.search(r"^executor:\s*(\S+)", profile.read_text(), re.M)
    if m and m.group(1) not in ("local", "dryrun", "touch"):
        mod = f"snakemake_executor_plugin_{m.group(1).replace('-', '_')}"
        if importlib.util.find_spec(mod) is None:
            return f"executor plugin {mod} is not installed"
    return None


def _environ_copy(environ=os.environ) -> dict[str, str]:
    """os.environ as a dict while another thread may set or delete variables. Copying iterates
    its keys and then reads each, so a variable deleted in between raised KeyError (a resize
    would raise RuntimeError; CI of 2477188, in the test below, where it killed a spawning
    thread): retry, the window is a few microseconds."""
    for _ in range(1000):
        try:
            return dict(environ)
        except (KeyError, RuntimeError):
            continue
    raise RuntimeError("os.environ kept changing while it was copied")


def _threaded_run(cmd: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess:
    """subprocess.run from a pool thread, with an explicit copy of the environment. Without
    one, the vfork'ed child reads libc's `environ`, which the main thread may reallocate at that
    moment (pytest sets and deletes PYTEST_CURRENT_TEST on every test phase): execve then failed
    with "[Errno 14] Bad address" (CI of 35b1bc2; test_threaded_runs_survive_environment_changes
    reproduces it without the copy)."""
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True,
                          env={**_environ_copy(), **env})


def test_environ_copy_retries_when_a_variable_vanishes_mid_copy():
    """The race test_threaded_runs_survive_environment_changes can only provoke by chance, made
    certain: the first copy finds a listed variable gone (KeyError), the second succeeds."""
    from collections.abc import Mapping

    class Racing(Mapping):
        def __init__(self):
            self.data, self.reads = {"A": "1", "B": "2"}, 0

        def __getitem__(self, k):
            self.reads += 1
            if self.reads == 2:  # deleted by another thread after the keys were listed
                raise KeyError(k)
            return self.data[k]

        def __iter__(self):
            return iter(list(self.data))

        def __len__(self):
            return len(self.data)

    env = Racing()
    assert _environ_copy(env) == {"A": "1", "B": "2"} and env.reads == 4


def test_threaded_runs_survive_environment_changes(tmp_path):
    """The pools below spawn while pytest's main thread changes the environment: no spawn may
    fail for it (without the copy, most of them did in this test)."""
    import threading
    import time
    errors, done, stop = [], [0], threading.Event()

    def spawn():
        while not stop.is_set():
            try:
                _threaded_run(["true"], tmp_path)
                done[0] += 1
            except Exception as e:  # noqa: BLE001 -- any failure is the test's, not a dead thread's
                errors.append(e)

    threads = [threading.Thread(target=spawn) for _ in range(2)]
    for t in threads:
        t.start()
    t0, k = time.monotonic(), 0
    try:
        # 2 s of churn and 20 spawns at least; a minute at most (spawns that keep failing)
        while (time.monotonic() - t0 < 2 or done[0] < 20) and time.monotonic() - t0 < 60:
            k += 1
            for j in range(20):
                os.environ[f"NEUMAT_TEST_CHURN_{j}_{k % 7}"] = "x" * 100
            for j in range(20):
                del os.environ[f"NEUMAT_TEST_CHURN_{j}_{k % 7}"]
    finally:
        stop.set()
        for t in threads:
            t.join()
    assert not errors, f"{len(errors)} of {len(errors) + done[0]} spawns failed: {errors[0]!r}"
    assert done[0] >= 20


def _stand_in_overlays(wd: Path, args: list[str]) -> None:
    """A realistic run's overlay (`--configfile results/<run>.yaml`: local, not committed; README
    "Realistic runs quoted here") gets a stand-in that names the run of the command's targets on
    synthetic MERL data, so that its targets, rule names and flags are still dry-run. The
    overlay's other keys are not (the stand-in does not know them)."""
    runs = {a.split("/")[1] for a in args if a.startswith("results/") and a.count("/") >= 2}
    for flag, path in zip(args, args[1:]):
        if flag == "--configfile" and path.startswith("results/") and not (wd / path).exists():
            assert len(runs) == 1, f"{args}: the overlay {path}'s run is not one target's"
            (wd / path).parent.mkdir(parents=True, exist_ok=True)
            (wd / path).write_text(f"run: {next(iter(runs))}\nmerl: {{source: synthetic}}\n")


def _dry_run(wd: Path, args: list[str]) -> subprocess.CompletedProcess:
    for item in ("Snakefile", "workflow", "config", "profiles", "src"):
        src = ROOT / item
        (shutil.copytree if src.is_dir() else shutil.copy)(src, wd / item)
    _stand_in_overlays(wd, args)
    return _threaded_run([sys.executable, "-m", "snakemake", *args[1:], "--dry-run"], wd)


@pytest.fixture(scope="module")
def dry_runs(tmp_path_factory):
    """Every runnable command's dry run, started at once, one per CPU (each is a Snakemake start
    and a DAG, seconds of one core), each in its own copy of the workflow."""
    from concurrent.futures import ThreadPoolExecutor
    pool = ThreadPoolExecutor(max_workers=os.cpu_count() or 1)
    runs = {cmd: pool.submit(_dry_run, tmp_path_factory.mktemp("docs"), shlex.split(cmd))
            for _, cmd in documented_commands() if _skip_reason(cmd) is None}
    yield runs
    pool.shutdown()


def _skip_reason(cmd: str) -> str | None:
    args = shlex.split(cmd)
    if "--report" in args:
        return ("--report needs a finished run: test_workflow.py::test_snakemake_report runs it "
                "on the tiny run")
    return _missing_plugin(args)


@pytest.mark.parametrize("doc,cmd", documented_commands(),
                         ids=[f"{d}:{c}" for d, c in documented_commands()])
def test_documented_command_dry_runs(dry_runs, doc, cmd):
    reason = _skip_reason(cmd)
    if reason:
        pytest.skip(f"{cmd!r} ({doc}): {reason}")
    res = dry_runs[cmd].result()
    assert res.returncode == 0, (f"{cmd!r} from {doc} fails (with --dry-run):\n"
                                 f"{res.stdout[-2000:]}\n{res.stderr[-4000:]}")


# ----------------------------------------------------------------------------- neumat commands

README = ROOT / "README.md"


def neumat_commands(text: str) -> list[str]:
    """`neumat ...` commands in document order: lines of fenced code blocks (a trailing
    `# comment` dropped) and inline code spans with arguments (a bare `neumat sample` names the
    subcommand, it is no command)."""
    cmds = []
    pattern = r"```[^\n]*\n(.*?)```|`(neumat [^`]+)`"
    for block, span in re.findall(pattern, text, re.S):
        lines = block.splitlines() if block else [" ".join(span.split())]
        for ln in lines:
            ln = re.sub(r"\s+#.*$", "", ln).strip()
            if ln.startswith("neumat ") and len(shlex.split(ln)) > 2 and ln not in cmds:
                cmds.append(ln)
    return cmds


# the README and the pages under docs/ (docs/stages.md: each stage and its measurements)
DOC_TEXT = "\n".join((ROOT / d).read_text() for d in DOCS if d.endswith(".md"))
NEUMAT = neumat_commands(DOC_TEXT)


def test_neumat_commands_are_found():
    assert any(c.startswith("neumat sample ") for c in NEUMAT), NEUMAT
    assert any(c.startswith("neumat render ") for c in NEUMAT), NEUMAT
    assert neumat_commands("x `neumat sample` y\n```bash\nneumat info r  # c\n```\n") == ["neumat info r"]


@pytest.fixture(scope="module")
def cli_dir(tiny_run, tmp_path_factory):
    d = tmp_path_factory.mktemp("readme_cli")
    (d / "results").mkdir()
    (d / "results/default").symlink_to(tiny_run / "results/tiny", target_is_directory=True)
    return d


def reads_from(cmds: list[str]) -> list[set[int]]:
    """For each command, the earlier commands whose `--out` it names (or a path under it): it
    must wait for them. Any other command may run alongside."""
    outs, deps = {}, []
    for i, cmd in enumerate(cmds):
        args = shlex.split(cmd)
        deps.append({j for j, o in outs.items() for a in args[1:]
                     if a == o or a.startswith(o.rstrip("/") + "/")})
        if "--out" in args:
            outs[i] = args[args.index("--out") + 1]
    return deps


def test_reads_from_orders_what_depends():
    cmds = ["neumat sample -n 2 --out a", "neumat sample -n 2 --out b",
            "neumat sample --image a/sample_000.png --out c", "neumat render b/scene.xml --out b.png",
            "neumat render ab/x.binary --out d.png"]
    assert reads_from(cmds) == [set(), set(), {0}, {1}, set()]


@pytest.fixture(scope="module")
def cli_runs(cli_dir, request):
    """The selected README `neumat` commands and those they read from, each started once the
    commands it reads from have finished, one per CPU (each is one process of about one core):
    the README's order where it matters, the suite's wall time where it does not."""
    from concurrent.futures import ThreadPoolExecutor
    deps, futures = reads_from(NEUMAT), {}
    selected = {it.callspec.params["cmd"] for it in request.session.items
                if getattr(it, "originalname", "") == "test_readme_neumat_command_runs_on_the_tiny_run"}
    needed = {i for i, c in enumerate(NEUMAT) if c in selected}
    for i in sorted(needed, reverse=True):  # deps point to earlier commands: one pass closes
        needed |= deps[i]

    def run(i):
        for j in deps[i]:  # submitted earlier, so started earlier: no deadlock
            futures[j].result()
        args = shlex.split(NEUMAT[i])
        # one torch thread each, as many commands as CPUs: a thread per core in each would
        # spin-wait on shared cores (conftest.py, the workers' OMP_NUM_THREADS)
        threads = os.environ.get("OMP_NUM_THREADS", "1")
        return _threaded_run([sys.executable, "-m", "neumat.cli", *args[1:]], cli_dir,
                             OMP_NUM_THREADS=threads)

    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        for i in sorted(needed):
            futures[i] = pool.submit(run, i)
        yield {NEUMAT[i]: f for i, f in futures.items()}


@pytest.mark.slow
@pytest.mark.parametrize("cmd", NEUMAT, ids=NEUMAT)
def test_readme_neumat_command_runs_on_the_tiny_run(cli_dir, cli_runs, cmd):
    """A later command may read what an earlier one wrote (`render diffuse/...`): it waits."""
    args = shlex.split(cmd)
    res = cli_runs[cmd].result()
    assert res.returncode == 0, f"{cmd!r} (README) fails on the tiny run:\n{res.stdout[-2000:]}\n{res.stderr[-3000:]}"
    if "--out" in args:
        out = cli_dir / args[args.index("--out") + 1]
        assert out.exists() and (out.is_dir() or out.stat().st_size > 100), out


# ----------------------------------------------------------------------------- other commands

def other_commands(text: str) -> list[str]:
    """Shell commands of the README that are neither snakemake nor neumat ones: each part of the
    Quickstart's `&&` chains, and inline spans that run a program (python, pip, pytest, a
    benchmarks/ script, ./.ci/run)."""
    parts = []
    quick = text.split("## Quickstart", 1)[1].split("\n## ", 1)[0]
    for block in re.findall(r"```bash\n(.*?)```", quick, re.S):
        parts += [p.strip() for ln in block.splitlines() for p in ln.split("&&")]
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    for span in re.findall(r"`([^`]+)`", prose):
        span = " ".join(span.split())
        if re.match(r"(\w+=\S+ )*(python3? |pip |pytest|\./\.ci/run|benchmarks/\S+\.py)", span) \
                or re.match(r"time \./", span):
            parts.append(span)
    cmds = []
    for p in parts:
        if p and not p.startswith(("snakemake ", "neumat ")) and p not in cmds:
            cmds.append(p)
    return cmds


OTHER = other_commands(DOC_TEXT)


def _accepts(prog: list[str], flags: list[str]) -> str | None:
    """None if `prog --help` lists every flag, else what is missing."""
    if not flags:
        return None
    res = subprocess.run([*prog, "--help"], cwd=ROOT, capture_output=True, text=True)
    if res.returncode != 0:
        return f"{' '.join(prog)} --help fails: {res.stderr[-500:]}"
    missing = [f for f in flags if f.split("=")[0] not in res.stdout]
    return f"{' '.join(prog)} does not accept {missing}" if missing else None


def _check(cmd: str) -> str | None:
    """None if the command would run as written (cheap checks), else why not."""
    import tomllib
    args = shlex.split(cmd)
    while args and re.match(r"\w+=", args[0]) or args[:1] == ["time"]:
        args = args[1:]  # environment assignments, `time`
    flags = [a for a in args if a.startswith("-") and not re.fullmatch(r"-[\d.]+", a)]  # -0.5: a value
    prog = args[0]
    if "*" in prog:
        return None if list(ROOT.glob(prog)) else f"{prog} matches no file"
    if prog == "python3" and args[1:4] == ["-m", "venv", ".venv"]:
        return _accepts([sys.executable, "-m", "venv"], flags[1:])
    if prog == "." and args[1:] == [".venv/bin/activate"]:
        return None  # what `python3 -m venv .venv` makes on POSIX
    if prog == "pip" and args[1] == "install":
        m = re.fullmatch(r"\.(?:\[([\w,]+)\])?", args[-1])
        if not m or not (ROOT / "pyproject.toml").exists():
            return f"installs {args[-1]!r}, not this project"
        extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"].get(
            "optional-dependencies", {})
        unknown = [e for e in (m.group(1) or "").split(",") if e and e not in extras]
        return f"pyproject.toml has no extra {unknown}" if unknown else \
            _accepts([sys.executable, "-m", "pip", "install"], flags)
    if prog == "pytest":
        ini = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
        markers = {m.split(":")[0] for m in ini.get("markers", [])}
        for i, a in enumerate(args):
            if a == "-m":
                names = set(re.findall(r"\w+", args[i + 1])) - {"not", "and", "or"}
                if names - markers:
                    return f"marker(s) {names - markers} not registered in pyproject.toml"
        return _accepts([sys.executable, "-m", "pytest"], flags)
    if prog in ("python", "python3") and args[1:2] == ["-m"]:
        return _accepts([sys.executable, "-m", args[2]], flags[1:])
    if prog in ("python", "python3") or prog.startswith("benchmarks/"):
        script = args[1] if prog.startswith("python") else prog
        if not (ROOT / script).is_file():
            return f"{script} does not exist"
        src = (ROOT / script).read_text()  # argparse flags as literals: no torch import here
        missing = [f for f in flags if f'"{f.split("=")[0]}"' not in src]
        return f"{script} has no option {missing}" if missing else None
    if prog == "./.ci/run":
        return None if os.access(ROOT / ".ci/run", os.X_OK) else ".ci/run is not executable"
    return "no check for this kind of command: add one to _check"


@pytest.mark.parametrize("cmd", OTHER, ids=OTHER)
def test_readme_command_would_run(cmd):
    reason = _check(cmd)
    assert reason is None, f"README command {cmd!r}: {reason}"


def test_ci_runs_the_readme_test_command():
    """.ci/run installs and tests exactly as the README's Quickstart says (after its own venv)."""
    quick = README.read_text().split("## Quickstart", 1)[1]
    test_cmd = re.findall(r"```bash\n(.*?)\n```", quick, re.S)[1]
    tail = test_cmd.split("&&", 2)[2].strip()  # after creating and activating the venv
    assert tail in (ROOT / ".ci/run").read_text(), tail


def test_suite_runs_on_several_workers(monkeypatch):
    """`pytest` and `pytest -m "not slow"` (README) spread over pytest-xdist workers on a
    multi-core machine, the tiny run shared between them; a test path or -k (a few tests), an
    explicit `-n`, a missing xdist or a single CPU keep one process (or the user's choice)."""
    from types import SimpleNamespace

    import conftest

    def config(markexpr, n=None, xdist=True, paths=(), keyword=""):
        opts = {"numprocesses": n, "file_or_dir": list(paths), "keyword": keyword}
        return SimpleNamespace(option=SimpleNamespace(markexpr=markexpr),
                               pluginmanager=SimpleNamespace(hasplugin=lambda name: xdist),
                               getoption=lambda name, default=None: opts.get(name, default))

    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)
    monkeypatch.setattr(conftest.os, "cpu_count", lambda: 2)
    assert conftest._parallel_workers(config("not slow")) == 2
    assert conftest._parallel_workers(config("")) == 2
    assert conftest._parallel_workers(config("slow")) == 2
    assert conftest._parallel_workers(config("", n=0)) == 0
    assert conftest._parallel_workers(config("", xdist=False)) == 0
    assert conftest._parallel_workers(config("not slow", paths=["tests/test_fit.py"])) == 0
    assert conftest._parallel_workers(config("", keyword="psnr")) == 0
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw0")
    assert conftest._parallel_workers(config("")) == 0
    monkeypatch.delenv("PYTEST_XDIST_WORKER")
    monkeypatch.setattr(conftest.os, "cpu_count", lambda: 1)
    assert conftest._parallel_workers(config("")) == 0
    monkeypatch.setattr(conftest.os, "cpu_count", lambda: 16)
    assert conftest._parallel_workers(config("")) == 4
