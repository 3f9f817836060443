"""Stitch the stage fragments into index.md and index.html."""
from pathlib import Path

import yaml

from neumat import report
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    footer = ("## Configuration of this run\n\nDefaults filled in; left out (config/speed_keys.yaml): "
              "the speed-only keys, and the neutral keys at their neutral value (the schema's "
              "default).\n\n```yaml\n" + yaml.safe_dump(dict(p.config), sort_keys=False) + "```")
    captions = {rx: report.caption_text(path, snakemake.config) for rx, path in p.captions.items()}
    md, html = report.stitch(snakemake.input.sections, f"neumat report: run `{p.run}`", footer,
                             captions)
    Path(snakemake.output.md).write_text(md)
    Path(snakemake.output.html).write_text(html)
    log.info("report with %d sections", len(snakemake.input.sections))
