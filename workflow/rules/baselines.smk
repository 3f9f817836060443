# Table 2 baselines (paper §4.3): PCA-A, PCA-N, VAE-A, VAE-N, each writing metrics.draws draws
# of as many samples as the reference set, in a form the metrics score like ours:
#   AugMERL recipe + tables -> samples/pca_a/tables.npz (a table set at the metric bins)
#   neumerl/weights.npy -> samples/pca_n/weights.npy
#   neumerl/weights.npy -> baselines/vae_n/model.pt -> samples/vae_n/weights.npy
#   augmerl/shards -> baselines/vae_a/model.pt -> samples/vae_a/weights.npy
# Included after metrics.smk: PCA-A's table set holds exactly the bins the metrics read.

BASE = config["baselines"]


rule baseline_pca:
    input:
        # AugMERL's manifest: NeuMERL's is its byte copy, rewritten (so its readers rerun)
        # whenever the fits change, which PCA-A does not read
        manifest=out("augmerl/manifest.tsv"),
        recipe=out("augmerl/recipe.npz"),
        log_tables=out("augmerl/log_tables.npy"),
        log_index=out("augmerl/log_tables_index.npz"),
    output:
        samples=out("samples/{model}/tables.npz"),
        info=out("baselines/{model}/info.tsv"),
    wildcard_constraints:
        model="pca_a",
    params:
        components=BASE["pca_a"]["components"],
        seeds=lambda wc: draw_seeds("sample", wc.model),
        # PCA-A's tables at the metric bins and views; baseline_pca_n (which `use rule`
        # inherits these params into) reads none of them, so they rerun nothing there
        resolution=lambda wc: config["render"]["resolution"] if wc.model == "pca_a" else None,
        brdf_samples=lambda wc: METRICS["brdf_samples"] if wc.model == "pca_a" else None,
        brdf_seed=lambda wc: METRICS_SEED if wc.model == "pca_a" else None,
    log:
        log("baseline_pca/{model}"),
    benchmark:
        bench("baseline_pca/{model}")
    conda:
        CONDA_ENV
    threads: BASE["threads"]
    resources:
        mem_mb=lambda wc: pca_a_mem_mb() if wc.model == "pca_a" else 3000,
        runtime=60,
    script:
        "../scripts/baseline_pca.py"


# rule baseline_pca_n: PCA-N, baseline_pca's rule on the NeuMERL weights
use rule baseline_pca as baseline_pca_n with:
    input:
        manifest=out("neumerl/manifest.tsv"),
        weights=out("neumerl/weights.npy"),
    output:
        samples=out("samples/{model}/weights.npy"),
        info=out("baselines/{model}/info.tsv"),
    wildcard_constraints:
        model="pca_n",
    params:
        components=BASE["pca_n"]["components"],
        seeds=lambda wc: draw_seeds("sample", wc.model),
    log:
        log("baseline_pca/{model}"),
    benchmark:
        bench("baseline_pca/{model}")
    resources:
        mem_mb=2000,
        runtime=10,


rule train_vae:
    input:
        manifest=out("augmerl/manifest.tsv"),  # as baseline_pca's
        weights=lambda wc: out("neumerl/weights.npy") if wc.model == "vae_n" else [],
        shards=lambda wc: augmerl_shards() if wc.model == "vae_a" else [],
    output:
        model=out("baselines/{model}/model.pt"),
        history=out("baselines/{model}/history.tsv"),
    wildcard_constraints:
        model="vae_a|vae_n",
    params:
        cfg=lambda wc: settings(f"baselines.{wc.model}"),
        seed=lambda wc: seed_for("train_baseline", wc.model),
        activation=config["fit"]["activation"],
        # resumable state after a kill (model, Adam, draws, step), removed once trained
        checkpoint=out("baselines/{model}/checkpoint.pt"),
    log:
        log("train_vae/{model}"),
    benchmark:
        bench("train_vae/{model}")
    conda:
        CONDA_ENV
    threads: BASE["threads"]
    resources:
        mem_mb=4000,
        runtime=120,
    script:
        "../scripts/train_vae.py"


rule sample_vae:
    input:
        model=out("baselines/{model}/model.pt"),
        manifest=out("augmerl/manifest.tsv"),  # as baseline_pca's
    output:
        samples=out("samples/{model}/weights.npy"),
    wildcard_constraints:
        model="vae_a|vae_n",
    params:
        seeds=lambda wc: draw_seeds("sample", wc.model),
    log:
        log("sample_vae/{model}"),
    benchmark:
        bench("sample_vae/{model}")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=1000,
        runtime=10,
    script:
        "../scripts/sample_vae.py"
