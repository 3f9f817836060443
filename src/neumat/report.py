"""The run report: Markdown fragments of every stage -> index.md + a self-contained-looking
index.html (figures linked relative to the report directory)."""

from __future__ import annotations

import re
from pathlib import Path

import markdown
import pandas as pd

CSS = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;
color:#222}table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;
padding:2px 8px;text-align:right}th{background:#f3f3f3}img{max-width:100%}
h2{border-bottom:2px solid #ddd;margin-top:2em}code{background:#f6f6f6}"""


def duration(seconds: float) -> str:
    """Seconds, with minutes in brackets from a minute up (a tiny run's costs read "0.0 min")."""
    s = float(seconds)
    return f"{s:.1f} s" if s < 60 else f"{s:.0f} s ({s / 60:.1f} min)"


# the three places that give the test split's median distance to its nearest training material
NN_SECTIONS = ("the diffusion section", "the conditioning section", "Table 2's novelty table")


def nn_bins_note(here: str) -> str:
    """One sentence for `here` (one of NN_SECTIONS): its nearest-training BRDF-L1 is over its
    own random draw of `diffusion.nn_bins` bins, so the test split's median differs a little
    between the three places (the bin draw alone; a review found three values unexplained)."""
    others = " and ".join(s for s in NN_SECTIONS if s != here)
    return (f" The nearest-training BRDF-L1 here is over `diffusion.nn_bins` valid MERL bins drawn "
            f"at random for {here}; {others} draw their own, so the test split's median differs "
            f"a little between them (the bin draw alone): compare sets within one place.")


def md_table(df: pd.DataFrame, floatfmt: str = ".4g") -> str:
    """A DataFrame as a GitHub-style Markdown table."""
    return df.to_markdown(index=False, floatfmt=floatfmt)


def caption_text(path: str | Path, config: dict) -> str:
    """A figure's `report()` caption (workflow/report/*.rst: a Jinja template over
    snakemake.config, as Snakemake renders it for `snakemake --report`) as one Markdown
    paragraph: RST inline literals ``x`` become `x`, line breaks spaces."""
    import types

    import jinja2

    text = jinja2.Template(Path(path).read_text()).render(snakemake=types.SimpleNamespace(
        config=config))
    return re.sub(r"``([^`]+)``", r"`\1`", " ".join(text.split()))


def with_captions(md: str, captions: dict[str, str]) -> str:
    """Each figure line `![alt](figures/NAME)` of `md` followed by its caption: `captions` maps
    a regular expression of figure file names (the rule's output pattern, wildcards as
    [^/]+) to the caption's text. In index.md / index.html the figures had their alt text
    only; the captions were in `snakemake --report` alone."""
    lines, out = md.splitlines(), []
    for i, line in enumerate(lines):
        out.append(line)
        m = re.fullmatch(r"!\[[^\]]*\]\(figures/([^)]+)\)", line.strip())
        text = next((t for rx, t in captions.items() if m and re.fullmatch(rx, m.group(1))), None)
        if text:  # a blank line after it unless one follows: text below would join the quote
            out += ["", f"> {text}"] + ([""] if i + 1 < len(lines) and lines[i + 1].strip() else [])
    return "\n".join(out)


def stitch(sections: list[str | Path], title: str, footer: str = "",
           captions: dict[str, str] | None = None) -> tuple[str, str]:
    """Concatenate section fragments (in file-name order), each figure followed by its caption
    (`with_captions`) -> (markdown, html)."""
    parts = [f"# {title}"]
    parts += [with_captions(Path(s).read_text().strip(), captions or {})
              for s in sorted(sections, key=lambda p: Path(p).name)]
    parts += [footer] if footer else []
    md = "\n\n".join(parts) + "\n"
    body = markdown.markdown(md, extensions=["tables", "fenced_code"])
    html = (f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{title}</title>"
            f"<style>{CSS}</style></head><body>\n{body}\n</body></html>\n")
    return md, html
