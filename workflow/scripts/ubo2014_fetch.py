"""Download (or copy from ubo2014.local_dir) one UBO2014 BTF, header- and sha256-verified."""
from neumat.data import ubo2014
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    name = snakemake.wildcards.material
    cfg = snakemake.config["ubo2014"]
    # from the config, not params (the lock file, not the address, says what the file is:
    # config/speed_keys.yaml)
    row = ubo2014.load_catalog(cfg["catalog"], [name]).set_index("name").loc[name]
    url = cfg["url"].format(name=name, **row)
    local_dir = cfg["local_dir"] if cfg["source"] == "local" else None
    log.info("%s <- %s", name, local_dir or url)
    ubo2014.fetch(name, snakemake.output[0], url=url, local_dir=local_dir, link=cfg["link"],
                  lock_file=cfg["lock_file"], retries=cfg["retries"])
