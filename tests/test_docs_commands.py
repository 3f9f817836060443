"""Every `snakemake ...` command written in README.md, the Snakefile header and the profiles'
headers runs verbatim (with --dry-run added), so a documented command cannot rot unnoticed.

Commands are found, not listed: a new command in the README is tested without touching this file.
Each runs in a copy of the workflow, so the checkout's .snakemake/ and results/ stay untouched."""

import importlib.util
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ["README.md", "Snakefile", *sorted(str(p.relative_to(ROOT)) for p in
                                          (ROOT / "profiles").glob("*/config.yaml"))]


def _commands_in(text: str) -> list[str]:
    """`snakemake ...` commands in inline code spans, code blocks and comment lines; a shell
    chain (`a && snakemake ...`) contributes its snakemake part."""
    spans = re.findall(r"`([^`\n]*snakemake [^`\n]*)`", text)
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


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    wd = tmp_path_factory.mktemp("docs")
    for item in ("Snakefile", "workflow", "config", "profiles", "src"):
        src = ROOT / item
        (shutil.copytree if src.is_dir() else shutil.copy)(src, wd / item)
    return wd


@pytest.mark.parametrize("doc,cmd", documented_commands(),
                         ids=[f"{d}:{c}" for d, c in documented_commands()])
def test_documented_command_dry_runs(workdir, doc, cmd):
    args = shlex.split(cmd)
    if "--report" in args:
        pytest.skip("--report needs a finished run: test_workflow.py::test_snakemake_report runs "
                    "it on the tiny run")
    reason = _missing_plugin(args)
    if reason:
        pytest.skip(f"{cmd!r} ({doc}): {reason}")
    full = [sys.executable, "-m", "snakemake", *args[1:], "--dry-run"]
    res = subprocess.run(full, cwd=workdir, capture_output=True, text=True)
    assert res.returncode == 0, (f"{cmd!r} from {doc} fails (with --dry-run):\n"
                                 f"{res.stdout[-2000:]}\n{res.stderr[-4000:]}")
