# AugMERL (paper §3.1): RGB permutations x6 + PCA interpolation, sharded tables.
#   source tables -> augmerl_log_tables (float32 log1p over the common valid bins, read once;
#   every consumer below memory-maps it) -> augmerl_pca -> augmerl_shard, figures, ...


rule augmerl_log_tables:
    input:
        tables=[merl_table(n) for n in MERL_NAMES],
    output:
        logs=out("augmerl/log_tables.npy"),
        index=out("augmerl/log_tables_index.npz"),
    params:
        names=MERL_NAMES,  # row order of the cache (merl.subset / the synthetic catalog)
    log:
        log("augmerl_log_tables"),
    benchmark:
        bench("augmerl_log_tables")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        # the float32 logs twice (all bins above the horizon, then the common valid ones)
        mem_mb=1000 + 30 * len(MERL_NAMES),
        runtime=10 + len(MERL_NAMES) // 5,
    script:
        "../scripts/augmerl_log_tables.py"


rule augmerl_pca:
    input:
        log_tables=out("augmerl/log_tables.npy"),
        log_index=out("augmerl/log_tables_index.npz"),
    output:
        manifest=out("augmerl/manifest.tsv"),
        recipe=out("augmerl/recipe.npz"),
    params:
        catalog=MERL.to_dict("records"),
        cfg=settings("augmerl", ["permutations", "size", "test_fraction", "pca_dims", "bins",
                                 "shard_size"]),
        seed=seed_for("augmerl"),
    log:
        log("augmerl_pca"),
    benchmark:
        bench("augmerl_pca")
    conda:
        CONDA_ENV
    threads: 2
    resources:
        mem_mb=2000 + 40 * len(MERL_NAMES),
        runtime=60,
    script:
        "../scripts/augmerl_pca.py"


rule augmerl_shard:
    input:
        log_tables=out("augmerl/log_tables.npy"),
        log_index=out("augmerl/log_tables_index.npz"),
        manifest=out("augmerl/manifest.tsv"),
        recipe=out("augmerl/recipe.npz"),
    output:
        out("augmerl/shards/{shard}.npz"),
    log:
        log("augmerl_shard/{shard}"),
    benchmark:
        bench("augmerl_shard/{shard}")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=3000 + 60 * len(MERL_NAMES),
        runtime=60,
    script:
        "../scripts/augmerl_shard.py"


rule augmerl_figures:
    input:
        log_tables=out("augmerl/log_tables.npy"),
        log_index=out("augmerl/log_tables_index.npz"),
        manifest=out("augmerl/manifest.tsv"),
        recipe=out("augmerl/recipe.npz"),
    output:
        permutations=report(out("report/figures/augmerl_permutations.png"),
                            caption="../report/augmerl_permutations.rst", category="Dataset"),
        interpolation=report(out("report/figures/augmerl_interpolation.png"),
                             caption="../report/augmerl_interpolation.rst", category="Dataset"),
    params:
        material=config["augmerl"]["figure_material"] or MERL_NAMES[0],
        pair=config["augmerl"]["figure_pair"] or MERL_NAMES[:2],
        pca_dims=config["augmerl"]["pca_dims"],
        resolution=config["report"]["sphere_resolution"],
    log:
        log("augmerl_figures"),
    benchmark:
        bench("augmerl_figures")
    conda:
        CONDA_ENV
    threads: 2
    resources:
        mem_mb=2000 + 40 * len(MERL_NAMES),
        runtime=30,
    script:
        "../scripts/augmerl_figures.py"


rule dataset_section:
    input:
        manifest=out("augmerl/manifest.tsv"),
        recipe=out("augmerl/recipe.npz"),
        shards=augmerl_shards(),
        permutations=out("report/figures/augmerl_permutations.png"),
        interpolation=out("report/figures/augmerl_interpolation.png"),
    output:
        out("report/sections/10_dataset.md"),
    params:
        source=config["merl"]["source"],
    log:
        log("dataset_section"),
    benchmark:
        bench("dataset_section")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=1000,
        runtime=10,
    script:
        "../scripts/dataset_section.py"
