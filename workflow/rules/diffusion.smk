# Hyperdiffusion (paper §3.3, §4.3, §4.6): train `ours` (NeuMERL train split) and `merl100`
# (train-split fits of the original MERL materials), sample unconditionally (as many as the
# test reference set) and per material type, export a few samples as MERL .binary, check
# physical plausibility, find each sample's nearest training material, write the report section.
#   neumerl -> train_diffusion -> sample_uncond / sample_type (/ sample_plain) -> diffusion_nearest,
#   diffusion_plausibility, export_samples -> diffusion_section

DIFF = config["diffusion"]
from neumat.diffusion.schedule import check_pairing as _check_pairing  # noqa: E402

_check_pairing(DIFF["schedule"]["prediction"], DIFF["schedule"]["loss"])  # before any job runs
DIFF_MODELS = ["ours", "merl100"]
# Class names of the type condition: every type of this run's MERL catalogue (48 for MERL).
DIFF_CLASSES = sorted(set(MERL["type"]))
DIFF_ACTIVATION = config["fit"]["activation"]
# the training loss's field term (diffusion.train.field_loss) evaluates the NBRDF: its
# activation is a param of the trainings only where the term is on
FIELD_PARAMS = {"activation": DIFF_ACTIVATION} if DIFF["train"]["field_loss"] else {}
# diffusion.sample keys for the unconditional draws of `ours` alone (and ours_plain): merl100's
# rows are not closed under channel permutation and are all typed, and conditioned draws keep
# their channel order, their condition, and draws independent of one another
OURS_UNCOND_ONLY = ["rgb_permute", "type_prior", "keep_look", "particle_step", "temperature"]
# diffusion.sample.batch_size is a memory knob: each 64-row block of sampling noise has its own
# stream, so samples are the same at any batch size to float rounding (with the clamp step,
# refit, types and category guidance too; tests/test_diffusion.py), and scripts read it from
# the config. Particle guidance repels the samples of one batch, so it is a param of the draws
# that use it (`ours`' unconditional ones and ours_plain) while particle_step > 0.
BATCH_UNLESS_PARTICLES = [] if DIFF["sample"]["particle_step"] else ["batch_size"]
# diffusion.sample keys that no other draw depends on: merl100's, the type-conditioned, the
# multimodal and the constrained ones
NOT_OF_OTHER_DRAWS = [*OURS_UNCOND_ONLY, "batch_size"]
# Sets under samples/: the models' samples, the Table 2 'Training set' subset, and the test
# split ('reference', for the distance of unseen real materials to their nearest training one).
# With the clamp constraint or the clamp refit on (diffusion.sample.negative_step,
# refit_steps > 0), `ours_plain` is `ours` sampled with the same seeds without them: the
# before/after of plausibility and novelty.
PLAIN_SETS = ["ours_plain"] if DIFF["sample"]["negative_step"] or DIFF["sample"]["refit_steps"] else []
DIFF_SETS = ["training", "ours", "merl100", "ours_type"] + PLAIN_SETS
NEAREST_SETS = ["reference", "ours", "merl100", "ours_type"] + PLAIN_SETS


rule train_diffusion:
    input:
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        model=out("diffusion/{model}/model.pt"),
        history=out("diffusion/{model}/history.tsv"),
    params:
        cfg=canon({**settings("diffusion", ["model", "schedule"]),  # not train.checkpoint_every
                   "train": train_settings()}),
        class_names=DIFF_CLASSES,
        seed=seed_for("train_diffusion"),
        checkpoint=out("diffusion/{model}/checkpoint.pt"),
        **FIELD_PARAMS,
    wildcard_constraints:
        model="|".join(DIFF_MODELS),
    log:
        log("train_diffusion/{model}"),
    benchmark:
        bench("train_diffusion/{model}")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=diffusion_mem_mb(2500),
        runtime=diffusion_runtime(),
        gpu=1 if config["device"] == "cuda" else 0,
    script:
        "../scripts/train_diffusion.py"


rule sample_uncond:
    input:
        model=out("diffusion/{model}/model.pt"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        weights=out("samples/{model}/weights.npy"),
        table=out("samples/{model}/samples.tsv"),
        timing=out("samples/{model}/timing.tsv"),
    params:
        # unguided; diffusion.sample.rgb_permute, type_prior, keep_look, particle_step and
        # temperature for `ours` only (OURS_UNCOND_ONLY)
        # keep_look compares metric-view renders: their size, only where it is on; it acts
        # only with the clamp step (negative_step), so without it keep_look is no param either
        cfg=lambda wc: {"sample": settings("diffusion.sample", drop=["guidance"] + (
            BATCH_UNLESS_PARTICLES if wc.model == "ours" else NOT_OF_OTHER_DRAWS) + (
            [] if DIFF["sample"]["negative_step"] else ["keep_look"])),
            **({"look_resolution": config["render"]["resolution"]} if wc.model == "ours"
               and DIFF["sample"]["keep_look"] and DIFF["sample"]["negative_step"] else {})},
        mode="uncond",
        seeds=lambda wc: draw_seeds("sample", wc.model),  # one per Table-2 draw
        activation=DIFF_ACTIVATION,  # decodes x0 for the clamp constraint (negative_step)
    wildcard_constraints:
        model="|".join(DIFF_MODELS),
    log:
        log("sample_uncond/{model}"),
    benchmark:
        bench("sample_uncond/{model}")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=2500,
        runtime=30,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/sample_diffusion.py"


rule sample_plain:
    input:
        model=out("diffusion/ours/model.pt"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        weights=out("samples/ours_plain/weights.npy"),
        table=out("samples/ours_plain/samples.tsv"),
        timing=out("samples/ours_plain/timing.tsv"),
    params:
        cfg={"sample": settings("diffusion.sample", drop=["guidance", "negative_step", "refit_steps",
                                                          "keep_look", *BATCH_UNLESS_PARTICLES])},
        mode="uncond",
        seeds=draw_seeds("sample", "ours"),  # the seeds of `ours`: paired samples
        activation=DIFF_ACTIVATION,
    log:
        log("sample_plain"),
    benchmark:
        bench("sample_plain")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=2500,
        runtime=30,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/sample_diffusion.py"


rule sample_type:
    input:
        model=out("diffusion/ours/model.pt"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        weights=out("samples/ours_type/weights.npy"),
        table=out("samples/ours_type/samples.tsv"),
        timing=out("samples/ours_type/timing.tsv"),
    params:
        cfg=canon({**settings("diffusion", ["types", "per_type"]),  # conditioned: no rgb_permute
                   "sample": settings("diffusion.sample",
                                      drop=NOT_OF_OTHER_DRAWS)}),
        mode="type",
        seed=seed_for("sample_type"),
        activation=DIFF_ACTIVATION,
    log:
        log("sample_type"),
    benchmark:
        bench("sample_type")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=2500,
        runtime=30,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/sample_diffusion.py"


rule diffusion_training_set:
    input:
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        weights=out("samples/training/weights.npy"),
        table=out("samples/training/samples.tsv"),
        ref_weights=out("samples/reference/weights.npy"),
        ref_table=out("samples/reference/samples.tsv"),
    params:
        seed=seed_for("diffusion_training_set"),
        draws=DRAWS,
    log:
        log("diffusion_training_set"),
    benchmark:
        bench("diffusion_training_set")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    script:
        "../scripts/diffusion_training_set.py"


rule diffusion_nearest:
    input:
        samples=expand(out("samples/{set}/weights.npy"), set=NEAREST_SETS),
        tables=expand(out("samples/{set}/samples.tsv"), set=NEAREST_SETS),
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        expand(out("samples/{set}/nearest.tsv"), set=NEAREST_SETS),
    params:
        bins=DIFF["nn_bins"],
        seed=seed_for("diffusion_nearest"),
        activation=DIFF_ACTIVATION,
    log:
        log("diffusion_nearest"),
    benchmark:
        bench("diffusion_nearest")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=lambda wc, input: 2000 + 2 * input.size_mb,
        runtime=20,
    script:
        "../scripts/diffusion_nearest.py"


rule diffusion_plausibility:
    input:
        samples=expand(out("samples/{set}/weights.npy"), set=DIFF_SETS),
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        summary=out("samples/plausibility.tsv"),
        per_sample=out("samples/plausibility_per_sample.tsv"),
    params:
        names=DIFF_SETS,
        angles=DIFF["plausibility_angles"],
        explode_factor=DIFF["explode_factor"],
        seed=seed_for("diffusion_plausibility"),
        activation=DIFF_ACTIVATION,
    log:
        log("diffusion_plausibility"),
    benchmark:
        bench("diffusion_plausibility")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=3000,
        runtime=30,
    script:
        "../scripts/diffusion_plausibility.py"


rule export_samples:
    input:
        out("samples/{set}/weights.npy"),
    output:
        expand(out("samples/{{set}}/merl/sample_{i:03d}.binary"), i=range(DIFF["export_merl"])),
    params:
        activation=DIFF_ACTIVATION,
    wildcard_constraints:
        set="ours|merl100|ours_type",
    log:
        log("export_samples/{set}"),
    benchmark:
        bench("export_samples/{set}")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=1500 + 300 * DIFF["export_merl"],
        runtime=10,
    script:
        "../scripts/export_samples.py"


rule diffusion_mitsuba:
    input:
        ours=out("samples/ours/weights.npy"),
        ours_nearest=out("samples/ours/nearest.tsv"),
        types=out("samples/ours_type/weights.npy"),
        types_nearest=out("samples/ours_type/nearest.tsv"),
        weights=out("neumerl/weights.npy"),
    output:
        ours=report(out("report/figures/diffusion_mitsuba_ours.png"), category="Diffusion",
                    caption="../report/diffusion_mitsuba_ours.rst"),
        types=report(out("report/figures/diffusion_mitsuba_types.png"), category="Diffusion",
                     caption="../report/diffusion_mitsuba_types.rst"),
        info=out("render/mitsuba/diffusion.json"),
    params:
        **named(dict(
            cfg=settings("render.mitsuba", ["variant", "resolution", "spp", "envmap_size"]),
            n_samples=DIFF["gallery_count"],
            n_types=DIFF["gallery_types"],
            per_type=DIFF["per_type"],
            activation=DIFF_ACTIVATION,
            seed=seed_for("diffusion_mitsuba"),
        )),
    log:
        log("diffusion_mitsuba"),
    benchmark:
        bench("diffusion_mitsuba")
    conda:
        CONDA_ENV
    threads: 2
    resources:
        mem_mb=4000,
        runtime=120,
    script:
        "../scripts/diffusion_mitsuba.py"


rule diffusion_section:
    input:
        histories=expand(out("diffusion/{model}/history.tsv"), model=DIFF_MODELS),
        models=expand(out("diffusion/{model}/model.pt"), model=DIFF_MODELS),
        samples=expand(out("samples/{set}/weights.npy"), set=DIFF_SETS),
        nearest=expand(out("samples/{set}/nearest.tsv"), set=NEAREST_SETS),
        timings=expand(out("samples/{set}/timing.tsv"), set=["ours", "merl100", "ours_type"]),
        plausibility=out("samples/plausibility.tsv"),
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
        mitsuba=out("render/mitsuba/diffusion.json"),
    output:
        section=out("report/sections/40_diffusion.md"),
        loss=report(out("report/figures/diffusion_loss.png"), category="Diffusion",
                    caption="../report/diffusion_loss.rst"),
        gallery=report(out("report/figures/diffusion_gallery.png"), category="Diffusion",
                       caption="../report/diffusion_gallery.rst"),
        gallery_merl100=report(out("report/figures/diffusion_gallery_merl100.png"),
                               category="Diffusion",
                               caption="../report/diffusion_gallery_merl100.rst"),
        types=report(out("report/figures/diffusion_types.png"), category="Diffusion",
                     caption="../report/diffusion_types.rst"),
    params:
        cfg=canon({**settings("diffusion", ["model", "schedule", "sample", "per_type", "gallery_types",
                                            "gallery_count", "explode_factor"]),
                   "train": train_settings()}),
        resolution=config["report"]["sphere_resolution"],
        activation=DIFF_ACTIVATION,
    log:
        log("diffusion_section"),
    benchmark:
        bench("diffusion_section")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=3000,
        runtime=20,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/diffusion_section.py"
