"""The run report: Markdown fragments of every stage -> index.md + a self-contained-looking
index.html (figures linked relative to the report directory)."""

from __future__ import annotations

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


def md_table(df: pd.DataFrame, floatfmt: str = ".4g") -> str:
    """A DataFrame as a GitHub-style Markdown table."""
    return df.to_markdown(index=False, floatfmt=floatfmt)


def stitch(sections: list[str | Path], title: str, footer: str = "") -> tuple[str, str]:
    """Concatenate section fragments (in file-name order) -> (markdown, html)."""
    parts = [f"# {title}"]
    parts += [Path(s).read_text().strip() for s in sorted(sections, key=lambda p: Path(p).name)]
    parts += [footer] if footer else []
    md = "\n\n".join(parts) + "\n"
    body = markdown.markdown(md, extensions=["tables", "fenced_code"])
    html = (f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{title}</title>"
            f"<style>{CSS}</style></head><body>\n{body}\n</body></html>\n")
    return md, html
