"""Download one MERL material, verified (size, header, pinned sha256), with retries."""
from neumat.data import merl_files
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    log.info("%s -> %s (sha256 %s)", p.url, snakemake.output[0], p.sha256 or "not checked")
    merl_files.download(p.url, snakemake.output[0], p.sha256 or None,
                        snakemake.config["merl"]["retries"])  # speed-only: not a param
    log.info("ok")
