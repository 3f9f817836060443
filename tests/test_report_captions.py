"""Every figure the workflow writes under report/figures/ is in Snakemake's report with a caption:
a static check of the rule files (no workflow run). Fourteen figures had no caption (render,
diffusion and NeuMERL sections, category only) or were not in the report at all (btf_eval's
texture and tiling figures)."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RULES = ROOT / "workflow/rules"
FIGURES = "report/figures/"


def output_blocks(text: str):
    """(line number, source) of each rule's `output:` block: the lines indented deeper than
    the `output:` line that follow it (blank lines included), joined."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        m = re.match(r"^(\s+)output:\s*$", line)
        if not m:
            continue
        indent, body = len(m.group(1)), []
        for nxt in lines[i + 1:]:
            if nxt.strip() and len(nxt) - len(nxt.lstrip()) <= indent:
                break
            body.append(nxt)
        yield i + 1, "\n".join(body)


def strings(node) -> list[str]:
    """Every string constant in an expression (f-string parts included)."""
    return [n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)]


def uncaptioned_figures(rules_dir: Path) -> tuple[list[str], list[str]]:
    """(figure outputs checked, problems) over the rule files of `rules_dir`: an output whose
    path holds report/figures/ must be report(..., caption="<file>") with that file present
    (relative to the rule file, as Snakemake resolves it)."""
    checked, problems = [], []
    for smk in sorted(rules_dir.glob("*.smk")):
        for lineno, body in output_blocks(smk.read_text()):
            call = ast.parse("f(\n" + body + "\n)", f"{smk.name}:{lineno}").body[0].value
            args = [(None, a) for a in call.args] + [(k.arg, k.value) for k in call.keywords]
            for name, expr in args:
                paths = [s for s in strings(expr) if FIGURES in s]
                if not paths:
                    continue
                where = f"{smk.name}:{lineno} {name or ''} {paths[0]}"
                checked.append(where)
                if not (isinstance(expr, ast.Call) and isinstance(expr.func, ast.Name)
                        and expr.func.id == "report"):
                    problems.append(f"{where}: not wrapped in report(...)")
                    continue
                caption = {k.arg: k.value for k in expr.keywords}.get("caption")
                if not (isinstance(caption, ast.Constant) and isinstance(caption.value, str)):
                    problems.append(f"{where}: report(...) without a caption= path")
                    continue
                rst = smk.parent / caption.value
                if not rst.is_file() or not rst.read_text().strip():
                    problems.append(f"{where}: caption {caption.value} missing or empty")
    return checked, problems


def test_every_report_figure_output_has_a_caption_file():
    checked, problems = uncaptioned_figures(RULES)
    # the figures of the render, NeuMERL, diffusion, conditioning, constrained, HyperBRDF, AugMERL
    # and BTF sections: a parser that finds none would pass vacuously
    assert len(checked) >= 20, checked
    assert not problems, "\n".join(problems)
