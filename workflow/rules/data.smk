# MERL tables, one file per material: downloaded (sha256-pinned), taken from a local directory,
# or synthesised (analytic BRDFs, offline). Only the configured source's rule is defined, so
# every table has exactly one producer; downstream rules ask merl_table(name) (common.smk).
from neumat.data import merl_files as _merl_files

MERL_CFG = config["merl"]


if MERL_CFG["source"] == "download":

    rule download_merl:
        output:
            merl_checked("resources/merl/{merl}.binary"),
        params:
            sha256=merl_expected_sha256,
            # the URL is a param only where no sha256 pins the file: a pinned file is the same
            # from any mirror, and a new merl.url must not rerun (so delete) good downloads
            url=lambda w: "" if MERL_CFG["verify_sha256"] else merl_url(w.merl),
        log:
            log("download_merl/{merl}"),
        benchmark:
            bench("download_merl/{merl}")
        conda:
            CONDA_ENV
        threads: 1
        resources:
            mem_mb=512,
            runtime=30,
        script:
            "../scripts/download_merl.py"

elif MERL_CFG["source"] == "local":
    # fail at DAG time, naming the key, rather than with "missing input" per job
    _merl_files.check_local_dir(MERL_CFG["local_dir"], MERL_NAMES)

    rule local_merl:
        input:
            lambda w: f"{MERL_CFG['local_dir']}/{w.merl}.binary",
        output:
            merl_checked("resources/merl_local/{merl}.binary"),
        params:
            local_dir=MERL_CFG["local_dir"],
            sha256=merl_expected_sha256,
        log:
            log("local_merl/{merl}"),
        benchmark:
            bench("local_merl/{merl}")
        conda:
            CONDA_ENV
        threads: 1
        resources:
            mem_mb=512,
            runtime=5,
        script:
            "../scripts/local_merl.py"

else:

    rule synthetic_merl:
        output:
            out("merl/{merl}.binary"),
        params:
            n_materials=MERL_CFG["synthetic"]["count"],
            seed=seed_for("synthetic_merl"),  # as merl_catalog()
        log:
            log("synthetic_merl/{merl}"),
        benchmark:
            bench("synthetic_merl/{merl}")
        conda:
            CONDA_ENV
        threads: 1
        resources:
            mem_mb=1000,
            runtime=5,
        script:
            "../scripts/synthetic_merl.py"
