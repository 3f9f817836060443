"""Copy (or symlink) one MERL material from merl.local_dir, verified like a download."""
from neumat.data import merl_files
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p, name = snakemake.params, snakemake.wildcards.merl
    link = snakemake.config["merl"]["link"]  # speed-only: not a param
    log.info("%s/%s.binary -> %s (%s, sha256 %s)", p.local_dir, name, snakemake.output[0],
             "link" if link else "copy", p.sha256 or "not checked")
    merl_files.copy_local(p.local_dir, name, snakemake.output[0], p.sha256 or None, link)
    log.info("ok")
