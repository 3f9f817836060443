"""CONTRIBUTING.md's "Where an output comes from" table stays true: every rule it names is a rule
of the workflow, and the rule file it names defines it (or makes it in a loop, as btf.smk its
fits); every script exists; every `neumat.` library name imports."""

import importlib
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _rows() -> list[list[str]]:
    text = (ROOT / "CONTRIBUTING.md").read_text()
    table = text.split("| output | rule (file) | script | library |", 1)[1].strip().splitlines()
    rows = []
    for ln in table[1:]:  # after the |---| line, up to the first line that is no table row
        if not ln.startswith("|"):
            break
        rows.append([c.strip() for c in ln.strip().strip("|").split(" | ")])
    assert len(rows) >= 15 and all(len(r) == 4 for r in rows), rows
    return rows


def _resolve(name: str):
    """neumat.a.b.c -> the module or attribute it names (the longest importable module, then
    attributes)."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError as e:
            if e.name != ".".join(parts[:i]):  # a module that fails to import: say so
                raise
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr)
        return obj
    raise ModuleNotFoundError(name)


def test_the_output_table_names_rules_scripts_and_library_calls_that_exist():
    listed = subprocess.run([sys.executable, "-m", "snakemake", "--list-rules", "--configfile",
                             "config/tiny.yaml"], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout.split()
    assert "diffusion_section" in listed, listed
    rules = scripts = libs = 0
    for output, rule, script, library in _rows():
        texts = [(ROOT / "workflow/rules" / f).read_text()
                 for f in re.findall(r"\((\w+\.smk)", rule)]
        assert texts, f"{output}: no rule file named"
        for name in re.findall(r"`(\w+)`", rule):
            assert name in listed, f"{output}: no rule {name}"
            defined = any(re.search(rf"^(rule|use rule \w+ as) {name}\b", t, re.M) for t in texts)
            assert defined or "the loop" in rule, f"{output}: no file of {rule!r} defines {name}"
            rules += 1
        for name in re.findall(r"`(\w+\.py)`", script):
            assert (ROOT / "workflow/scripts" / name).is_file(), (output, name)
            scripts += 1
        for name in re.findall(r"`(neumat(?:\.\w+)+)`", library):
            _resolve(name)  # ImportError / AttributeError names it
            libs += 1
    assert rules >= 20 and scripts >= 15 and libs >= 15, (rules, scripts, libs)
