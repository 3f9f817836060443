"""Download (or copy from ubo2014.local_dir) one UBO2014 BTF, header- and sha256-verified."""
from neumat.data import ubo2014
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    name = snakemake.wildcards.material
    log.info("%s <- %s", name, p.local_dir or p.url)
    ubo2014.fetch(name, snakemake.output[0], url=p.url, local_dir=p.local_dir, link=snakemake.config["ubo2014"]["link"],
                  lock_file=p.lock_file, retries=snakemake.config["ubo2014"]["retries"])
