"""Download (or copy from ubo2014.local_dir) one UBO2014 BTF, header- and sha256-verified."""
from neumat.data import ubo2014
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    name = snakemake.wildcards.material
    cfg = snakemake.config["ubo2014"]
    # from the config, not params (the lock file, not the address, says what the file is)
    row = ubo2014.load_catalog(cfg["catalog"], [name]).set_index("name").loc[name]
    url = cfg["url"].format(name=name, **row)
    log.info("%s <- %s", name, p.local_dir or url)
    ubo2014.fetch(name, snakemake.output[0], url=url, local_dir=p.local_dir, link=cfg["link"],
                  lock_file=p.lock_file, retries=cfg["retries"])
