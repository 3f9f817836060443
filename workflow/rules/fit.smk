# NeuMERL (paper §3.2): one NBRDF field per AugMERL material, fitted in batches per shard.
#   fit_template (manifest id 0, longer) -> fit_shard (parallel, checkpointed) -> fit_eval
#   (render PSNR per shard) -> neumerl (merge) -> neumerl_section; neumerl_export -> .binary

FIT = config["fit"]
# what a fit's result depends on (fit.threads, materials_per_batch, checkpoint_every: speed only)
FIT_KEYS = ["steps", "template_steps", "lr", "lr_final", "batch", "activation", "mirror_phi_d",
            "val_fraction", "eval_every", "eval_bins", "kernel"]
FIT_SETTINGS = settings("fit", FIT_KEYS)
FIT_SEED = seed_for("fit")  # template and shards share splits and minibatch order
# Peak RSS of a fit job (`python benchmarks/job_memory.py --jobs fit --kernel c`, and `--kernel torch
# --materials 100` / `25`; Intel Xeon AVX-512, torch 2.13 CPU, 1 thread, 2026-11-29; 100
# materials in one batch, 2 steps with an evaluation):
#   C kernel: 267 MB + 2.08 x the shard (its values, their log targets in the fitter's
#   layout, the bins' geometry; 253 MB of imports): 581, 895, 1523 MB for shards of 151, 302,
#   604 MB, so about 2900 MB at paper scale (1263 MB: every valid bin).
#   The template's job: 1.13-1.18 x its shard over the imports (939 MB at 604 MB).
#   torch step on the CPU (kernel torch, or auto where the C step is the slower one): the
#   evaluations' activations (32768 points a pass) add about 9 MB per material of a batch at
#   100 materials and 14 at 25 (the fitted intercepts: 1153 and 605 MB). On a GPU the host
#   holds what the C path does. Budget: 1000 + 2.5 x (+ 13 MB per material of a batch off the
#   C kernel): 0.42-0.61 of it on the C path at 151-604 MB (`--kernel c`; 0.22-0.40 of the
#   budget at fit.kernel auto, which adds the 13 MB a material), 0.55 on torch's at 151 MB.
FIT_MEM_EVAL = 0 if FIT["kernel"] == "c" else 13 * min(FIT["materials_per_batch"],
                                                         config["augmerl"]["shard_size"])


rule fit_template:
    input:
        shard=out(f"augmerl/shards/{TEMPLATE_SHARD}.npz"),
    output:
        out("neumerl/template.npz"),
    params:
        template=TEMPLATE_ID,
        # fit.steps is not used here (the template trains fit.template_steps) but stays: taking
        # it out would rerun every existing run's template, and after it every shard
        cfg=FIT_SETTINGS,
        seed=FIT_SEED,
        checkpoint=out("neumerl/checkpoints/template.npz"),
    log:
        log("fit_template"),
    benchmark:
        bench("fit_template")
    conda:
        CONDA_ENV
    threads: FIT["threads"]
    resources:
        mem_mb=lambda wc, input: 1000 + 2 * input.size_mb,
        runtime=fit_runtime(1, FIT["template_steps"]),
        gpu=1 if config["device"] == "cuda" else 0,
    script:
        "../scripts/fit_template.py"


rule fit_shard:
    input:
        shard=out("augmerl/shards/{shard}.npz"),
        template=out("neumerl/template.npz"),
    output:
        out("neumerl/shards/{shard}.npz"),
    params:
        cfg=FIT_SETTINGS,
        seed=FIT_SEED,
        checkpoint=out("neumerl/checkpoints/{shard}.npz"),
    wildcard_constraints:
        shard=r"\d{3}",
    log:
        log("fit_shard/{shard}"),
    benchmark:
        bench("fit_shard/{shard}")
    conda:
        CONDA_ENV
    threads: FIT["threads"]
    resources:
        mem_mb=lambda wc, input: int(1000 + 2.5 * input.size_mb) + FIT_MEM_EVAL,  # measured, above
        runtime=fit_runtime(config["augmerl"]["shard_size"], FIT["steps"]),
        gpu=1 if config["device"] == "cuda" else 0,
    script:
        "../scripts/fit_shard.py"


rule fit_eval:
    input:
        fits=out("neumerl/shards/{shard}.npz"),
        recipe=out("augmerl/recipe.npz"),
        log_tables=out("augmerl/log_tables.npy"),
        log_index=out("augmerl/log_tables_index.npz"),
    output:
        out("neumerl/eval/{shard}.tsv"),
    params:
        resolution=FIT["render_resolution"],
        activation=FIT["activation"],
    wildcard_constraints:
        shard=r"\d{3}",
    log:
        log("fit_eval/{shard}"),
    benchmark:
        bench("fit_eval/{shard}")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=2500 + 15 * len(MERL_NAMES),
        runtime=30,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/fit_eval.py"


rule neumerl:
    input:
        fits=expand(out("neumerl/shards/{shard}.npz"), shard=AUG_SHARDS),
        evals=expand(out("neumerl/eval/{shard}.tsv"), shard=AUG_SHARDS),
        manifest=out("augmerl/manifest.tsv"),
    output:
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
        fits=out("neumerl/fits.tsv"),
    log:
        log("neumerl"),
    benchmark:
        bench("neumerl")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=lambda wc, input: 1000 + input.size_mb,
        runtime=10,
    script:
        "../scripts/neumerl.py"


rule neumerl_export:
    input:
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        out("neumerl/merl/{augmerl}.binary"),
    params:
        activation=FIT["activation"],
    log:
        log("neumerl_export/{augmerl}"),
    benchmark:
        bench("neumerl_export/{augmerl}")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/neumerl_export.py"


rule neumerl_section:
    input:
        fits=out("neumerl/fits.tsv"),
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
        shards=expand(out("neumerl/shards/{shard}.npz"), shard=AUG_SHARDS),
        template=out("neumerl/template.npz"),
        recipe=out("augmerl/recipe.npz"),
        log_tables=out("augmerl/log_tables.npy"),
        log_index=out("augmerl/log_tables_index.npz"),
        exports=expand(out("neumerl/merl/{augmerl}.binary"), augmerl=FIT["export"]),
    output:
        section=out("report/sections/20_neumerl.md"),
        quality=report(out("report/figures/neumerl_quality.png"), category="NeuMERL",
                       caption="../report/neumerl_quality.rst"),
        best=report(out("report/figures/neumerl_best.png"), category="NeuMERL",
                    caption="../report/neumerl_best.rst"),
        worst=report(out("report/figures/neumerl_worst.png"), category="NeuMERL",
                     caption="../report/neumerl_worst.rst"),
    params:
        cfg=settings("fit", ["report_examples", "activation", "batch", "lr", "lr_final", "steps",
                             "template_steps", "val_fraction", "render_resolution"]),
        resolution=config["report"]["sphere_resolution"],
    log:
        log("neumerl_section"),
    benchmark:
        bench("neumerl_section")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=2500 + 15 * len(MERL_NAMES),
        runtime=20,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/neumerl_section.py"
