"""Download one MERL material, verified (size, header, pinned sha256), with retries."""
from neumat.data import merl_files
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    # from the config, not params: params.url is blank where a sha256 pins the file
    url = snakemake.config["merl"]["url"].format(name=snakemake.wildcards.merl)
    log.info("%s -> %s (sha256 %s)", url, snakemake.output[0], p.sha256 or "not checked")
    merl_files.download(url, snakemake.output[0], p.sha256 or None,
                        snakemake.config["merl"]["retries"])  # speed-only: not a param
    log.info("ok")
