# Table 3 (M3ashy §4.6): the HyperBRDF model trained on MERL vs AugMERL, scored on sparse
# reconstruction (N samples) and compression (all stored samples through the latent) of the
# test-split source materials, with a per-material NeuMERL fit (upper bound) and the mean
# training material (floor) in the same run.
#   augmerl -> hyperbrdf_median -> train_hyperbrdf {merl, augmerl} -> hyperbrdf_eval
#   (+ neumerl) -> hyperbrdf_table (Table 3 CSV/MD/HTML, report section, figure)

HB = config["hyperbrdf"]
HB_TRAINSETS = ["merl", "augmerl"]  # wildcard {trainset}: what a HyperBRDF model trains on


rule hyperbrdf_median:
    input:
        manifest=out("augmerl/manifest.tsv"),
        recipe=out("augmerl/recipe.npz"),
        log_tables=out("augmerl/log_tables.npy"),
        log_index=out("augmerl/log_tables_index.npz"),
    output:
        out("hyperbrdf/median.npy"),
    log:
        log("hyperbrdf_median"),
    benchmark:
        bench("hyperbrdf_median")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=2500 + 40 * len(MERL_NAMES),
        runtime=30,
    script:
        "../scripts/hyperbrdf_median.py"


rule train_hyperbrdf:
    input:
        shards=augmerl_shards(),
        manifest=out("augmerl/manifest.tsv"),
        median=out("hyperbrdf/median.npy"),
    output:
        model=out("hyperbrdf/{trainset}/model.pt"),
        history=out("hyperbrdf/{trainset}/history.tsv"),
    params:
        cfg=settings("hyperbrdf", ["model", "train", "train_bins"]),
        seed=seed_for("train_hyperbrdf"),  # the same init for both training sets
        checkpoint=out("hyperbrdf/{trainset}/checkpoint.pt"),
    wildcard_constraints:
        trainset="|".join(HB_TRAINSETS),
    log:
        log("train_hyperbrdf/{trainset}"),
    benchmark:
        bench("train_hyperbrdf/{trainset}")
    conda:
        CONDA_ENV
    threads: HB["threads"]
    resources:
        # one shard at a time, then the kept bins' values and their mapped targets. Peak RSS
        # of this script's path (shard rows -> concatenate -> hb.train, 1 step, CPU;
        # `python benchmarks/job_memory.py --jobs hyperbrdf`, 200 and 400 materials x 32768
        # bins, the schema's training settings, Intel Xeon AVX-512, 2026-11-29): 634 MB + 19.0
        # bytes per material-bin, i.e. 6.3 per stored value (material x channel x bin), the
        # values' 4 bytes about twice (rows + their concatenation, then values + targets); 26
        # per material-bin budgeted. (443 MB + 24.6 bytes at the library's defaults before they
        # were made the schema's: 1 material a step, 4000 query samples)
        mem_mb=lambda wc, input: 2000 + 2 * input.size_mb // len(AUG_SHARDS)
        + 26 * augmerl_count() * HB["train_bins"] // 2**20,
        runtime=hyperbrdf_runtime(),
        gpu=1 if config["device"] == "cuda" else 0,
    script:
        "../scripts/train_hyperbrdf.py"


rule hyperbrdf_eval:
    input:
        models=expand(out("hyperbrdf/{trainset}/model.pt"), trainset=HB_TRAINSETS),
        median=out("hyperbrdf/median.npy"),
        shards=augmerl_shards(),
        manifest=out("augmerl/manifest.tsv"),
        recipe=out("augmerl/recipe.npz"),
        log_tables=out("augmerl/log_tables.npy"),
        log_index=out("augmerl/log_tables_index.npz"),
        weights=out("neumerl/weights.npy"),
    output:
        scores=out("hyperbrdf/scores.tsv"),
        renders=out("hyperbrdf/renders.npz"),
    params:
        models=HB_TRAINSETS,
        sparse_samples=HB["sparse_samples"],
        resolution=HB["resolution"],
        activation=config["fit"]["activation"],
        seed=seed_for("hyperbrdf_eval"),
    log:
        log("hyperbrdf_eval"),
    benchmark:
        bench("hyperbrdf_eval")
    conda:
        CONDA_ENV
    threads: HB["threads"]
    resources:
        mem_mb=3000 + 40 * len(MERL_NAMES),
        runtime=30,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/hyperbrdf_eval.py"


rule hyperbrdf_table:
    input:
        scores=out("hyperbrdf/scores.tsv"),
        renders=out("hyperbrdf/renders.npz"),
        models=expand(out("hyperbrdf/{trainset}/model.pt"), trainset=HB_TRAINSETS),
        histories=expand(out("hyperbrdf/{trainset}/history.tsv"), trainset=HB_TRAINSETS),
    output:
        csv=out("hyperbrdf/table3.csv"),
        md=out("hyperbrdf/table3.md"),
        html=out("hyperbrdf/table3.html"),
        paired=out("hyperbrdf/table3_paired.csv"),
        section=out("report/sections/55_hyperbrdf.md"),
        figure=report(out("report/figures/hyperbrdf_reconstructions.png"),
                      caption="../report/hyperbrdf_reconstructions.rst", category="Table 3"),
    params:
        models=HB_TRAINSETS,
        examples=HB["examples"],
        latent=HB["model"]["latent"],
        train={k: HB["train"][k] for k in ("steps", "materials_per_step", "lr")},
        sparse_samples=HB["sparse_samples"],
        resolution=HB["resolution"],
        seed=seed_for("hyperbrdf_table"),  # the paired bootstrap and Monte Carlo sign flips
    log:
        log("hyperbrdf_table"),
    benchmark:
        bench("hyperbrdf_table")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=1500,
        runtime=10,
    script:
        "../scripts/hyperbrdf_table.py"
