# Multi-modal conditioning (paper §3.3, §4.4, Figs. 7-9): text and image encoders, one
# diffusion model conditioned on type, text and image (each dropped independently in training),
# text- and image-conditioned sampling, their measures against unconditional, type-conditioned
# and retrieval baselines from the same model, a guidance-scale sweep, Mitsuba figures.
#   neumerl -> text_embeddings, prompt_embeddings, train_image_encoder -> image_embeddings
#   -> train_multimodal
#   -> sample_text / sample_image / sample_multimodal / sample_mm_type -> conditions_eval,
#   guidance_sweep, conditions_mitsuba -> conditions_section

from neumat.conditions import starts as _starts  # noqa: E402

COND = config["conditions"]
COND_MODEL = "multimodal"
# conditions.{image,type,text}.refiner: image (type, text) samples refine their retrieved
# training material (one of their type, the nearest descriptions) with a model that keeps a
# start (prediction v, loss x0: no low-noise floor), trained on ours's rows by rule train_refiner
IMAGE_REFINER = COND["image"]["refiner"]
TYPE_REFINER = COND["type"]["refiner"]
TEXT_REFINER = COND["text"]["refiner"]
_starts.check(COND)  # a refiner or start_match needs strength < 1
TYPE_START = COND["type"]["strength"] < 1  # mm_type from training materials of its types
TEXT_START = COND["text"]["strength"] < 1  # text from the training materials nearest the prompt
# draws per kept image sample: best of n over the constrained and the unconstrained candidates
IMAGE_DRAWS = COND["image"]["candidates"] + COND["image"]["unconstrained_candidates"]
if COND["image"]["images"]:  # a missing or broken image would fail only its job, or, in a run
    # that has sampled before, be skipped without a word (Snakemake does not look upstream)
    from neumat.io import images as _images  # noqa: E402

    _images.check_images(COND["image"]["images"], "conditions.image.images")
COND_SETS = ["text", "image", "mm_type", "mm_uncond"]
# the sampling params every conditioned sampler shares: diffusion.sample's settings without
# its guidance (each sampler takes its own scale of conditions.guidance: cond_guidance)
# and the stage's own clamp step (conditions.negative_step; null: diffusion.sample's, so a run
# that leaves it null keeps the params it had)
COND_NEG = DIFF["sample"]["negative_step"] if COND["negative_step"] is None else COND["negative_step"]
COND_SAMPLE = canon({**settings("diffusion.sample", drop=["guidance", *NOT_OF_OTHER_DRAWS]),
                     "negative_step": COND_NEG})
COND_SAMPLING = dict(sample=COND_SAMPLE, per_prompt=COND["per_condition"])
# `measured`: permuted and mixed materials are described by their own colour (text_embeddings
# then reads the fields and writes the descriptions it embedded); `source`: the paper's words
COND_MEASURED = COND["text"]["colour_words"] == "measured"


rule text_embeddings:
    input:
        # AugMERL's manifest (NeuMERL's is its byte copy, rewritten whenever the fits change);
        # the fits only where the colour words are measured from them
        manifest=out("augmerl/manifest.tsv"),
        **({"weights": out("neumerl/weights.npy")} if COND_MEASURED else {}),
    output:
        text=out("conditions/text.npy"),
        **({"descriptions": out("conditions/descriptions.tsv")} if COND_MEASURED else {}),
    params:
        **neutral_params("conditions.text", ["colour_words"]),
        **({"activation": DIFF_ACTIVATION} if COND_MEASURED else {}),
    log:
        log("text_embeddings"),
    benchmark:
        bench("text_embeddings")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=2000,
        runtime=15,
    script:
        "../scripts/text_embeddings.py"


# The sampling prompts apart from the descriptions: a prompt added to the config re-embeds the
# prompts and reruns the draws that read them, not the image encoder or the multimodal model,
# which train on text.npy alone
rule prompt_embeddings:
    input:
        manifest=out("augmerl/manifest.tsv"),
        # the descriptions as embedded, to mark a prompt training saw word for word
        **({"descriptions": out("conditions/descriptions.tsv")} if COND_MEASURED else {}),
    output:
        prompts=out("conditions/prompts.tsv"),
        prompt_embeddings=out("conditions/prompts.npy"),
    params:
        prompts=COND["text"]["prompts"],
        test_prompts=COND["text"]["test_prompts"],
    log:
        log("prompt_embeddings"),
    benchmark:
        bench("prompt_embeddings")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=2000,
        runtime=15,
    script:
        "../scripts/prompt_embeddings.py"


rule train_image_encoder:
    input:
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
        # the description embeddings are its targets only with the contrastive objective
        **({"text": out("conditions/text.npy")}
           if config["conditions"]["image"]["encoder"]["objective"] == "text" else {}),
    output:
        model=out("conditions/image_encoder.pt"),
        history=out("conditions/image_encoder_history.tsv"),
        evaluation=out("conditions/image_encoder_eval.tsv"),
    params:
        cfg=settings("conditions.image.encoder"),
        seed=cond_seed("image_encoder"),
        activation=DIFF_ACTIVATION,
        # resumable training state after a kill, removed once trained
        checkpoint=out("conditions/image_encoder_checkpoint.pt"),
    log:
        log("train_image_encoder"),
    benchmark:
        bench("train_image_encoder")
    conda:
        CONDA_ENV
    threads: COND["threads"]
    resources:
        mem_mb=4000,
        runtime=120,
    script:
        "../scripts/train_image_encoder.py"


rule image_embeddings:
    input:
        model=out("conditions/image_encoder.pt"),
        weights=out("neumerl/weights.npy"),
    output:
        out("conditions/image.npy"),
    params:
        activation=DIFF_ACTIVATION,
    log:
        log("image_embeddings"),
    benchmark:
        bench("image_embeddings")
    conda:
        CONDA_ENV
    threads: COND["threads"]
    resources:
        mem_mb=3000,
        runtime=20,
    script:
        "../scripts/image_embeddings.py"


rule train_multimodal:
    input:
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
        text=out("conditions/text.npy"),
        image=out("conditions/image.npy"),
    output:
        model=out(f"diffusion/{COND_MODEL}/model.pt"),
        history=out(f"diffusion/{COND_MODEL}/history.tsv"),
    params:
        # ours's model, schedule and training, with the conditions' dropout (the one used:
        # diffusion.train.cond_drop is ours's and reruns nothing here)
        cfg=canon({**settings("diffusion", ["model", "schedule"]),
                   "train": {**train_settings(), "cond_drop": COND["cond_drop"]}}),
        class_names=DIFF_CLASSES,
        seed=cond_seed("train"),
        checkpoint=out(f"diffusion/{COND_MODEL}/checkpoint.pt"),
        **FIELD_PARAMS,
    log:
        log("train_multimodal"),
    benchmark:
        bench("train_multimodal")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=diffusion_mem_mb(3000),
        runtime=diffusion_runtime(),
        gpu=1 if config["device"] == "cuda" else 0,
    script:
        "../scripts/train_multimodal.py"


rule train_refiner:
    input:
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        model=out("diffusion/{model}/model.pt"),
        history=out("diffusion/{model}/history.tsv"),
    params:
        # ours's model and training; the schedule's prediction and loss set to v / x0
        cfg=canon({**settings("diffusion", ["model"]), "train": train_settings(),
                   "schedule": {**settings("diffusion.schedule"), "prediction": "v", "loss": "x0"}}),
        class_names=DIFF_CLASSES,
        seed=cond_seed("train_refiner"),
        checkpoint=out("diffusion/{model}/checkpoint.pt"),
        **FIELD_PARAMS,
    wildcard_constraints:
        model="refiner",
    log:
        log("train_refiner/{model}"),
    benchmark:
        bench("train_refiner/{model}")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=diffusion_mem_mb(2500),
        runtime=diffusion_runtime(),
        gpu=1 if config["device"] == "cuda" else 0,
    script:
        "../scripts/train_diffusion.py"


rule sample_text:
    """Samples of the text prompts, from noise or (conditions.text.strength < 1) from the
    training materials whose descriptions are nearest each prompt, refined by the refiner with
    conditions.text.refiner."""
    input:
        # the refiner draws in place of the multimodal model, which is then not read
        model=[] if TEXT_REFINER else out(f"diffusion/{COND_MODEL}/model.pt"),
        prompts=out("conditions/prompts.tsv"),
        prompt_embeddings=out("conditions/prompts.npy"),
        **({"weights": out("neumerl/weights.npy"), "manifest": out("neumerl/manifest.tsv"),
            "text": out("conditions/text.npy")} if TEXT_START else {}),
        refiner=[out("diffusion/refiner/model.pt")] if TEXT_REFINER else [],
    output:
        weights=out("samples/text/weights.npy"),
        table=out("samples/text/samples.tsv"),
        timing=out("samples/text/timing.tsv"),
    params:
        **named(dict(
            **COND_SAMPLING,
            guidance=cond_guidance("text", TEXT_REFINER),
            mode="text",
            seed=cond_seed("text"),
            activation=DIFF_ACTIVATION,
            **neutral_params("conditions.text", ["strength", "refiner", "start_match"]),
        )),
    log:
        log("sample_text"),
    benchmark:
        bench("sample_text")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=2500,
        runtime=30,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/sample_conditions.py"


rule sample_image:
    input:
        # the refiner draws in place of the multimodal model, which is then not read
        model=[] if IMAGE_REFINER else out(f"diffusion/{COND_MODEL}/model.pt"),
        encoder=out("conditions/image_encoder.pt"),
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
        image_embeddings=out("conditions/image.npy"),
        images=COND["image"]["images"],
        refiner=[out("diffusion/refiner/model.pt")] if IMAGE_REFINER else [],
    output:
        weights=out("samples/image/weights.npy"),
        table=out("samples/image/samples.tsv"),
        timing=out("samples/image/timing.tsv"),
        conditioning=out("samples/image/conditioning.npy"),
        embeddings=out("samples/image/conditioning_embeddings.npy"),
    params:
        **named(dict(
            **COND_SAMPLING,
            guidance=cond_guidance("image", IMAGE_REFINER),
            test_images=COND["image"]["test_images"],
            strength=COND["image"]["strength"],
            **neutral_params("conditions.image", ["render_step", "refiner", "candidates",
                                                  "unconstrained_candidates"]),
            # best of n's penalty and the bins it checks for clamping: params only where used
            **({"clamp_penalty": COND["image"]["clamp_penalty"], "angles": DIFF["plausibility_angles"]}
               if IMAGE_DRAWS > 1 else {}),
            resolution=config["render"]["resolution"],  # the metric render's, as Table 2's
            activation=DIFF_ACTIVATION,
            mode="image",
            seed=cond_seed("image"),
        )),
    log:
        log("sample_image"),
    benchmark:
        bench("sample_image")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=2500,
        runtime=30,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/sample_conditions.py"


rule sample_multimodal:
    """Same-run baseline from the multimodal model: unconditional samples (`mm_uncond`),
    conditions.per_condition for each test prompt."""
    input:
        model=out(f"diffusion/{COND_MODEL}/model.pt"),
        prompts=out("conditions/prompts.tsv"),
    output:
        weights=out("samples/mm_uncond/weights.npy"),
        table=out("samples/mm_uncond/samples.tsv"),
        timing=out("samples/mm_uncond/timing.tsv"),
    params:
        **COND_SAMPLING,
        guidance=cond_guidance(None),
        mode="mm_uncond",
        seed=cond_seed("mm_uncond"),
        activation=DIFF_ACTIVATION,
    log:
        log("sample_multimodal/mm_uncond"),
    benchmark:
        bench("sample_multimodal/mm_uncond")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=2500,
        runtime=30,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/sample_conditions.py"


rule sample_mm_type:
    """Same-run baseline from the multimodal model: samples of the test prompts' types
    (`mm_type`), of the types some training material has, from noise or
    (conditions.type.strength < 1) from a training material of the type, refined by the
    refiner with conditions.type.refiner."""
    input:
        # the refiner draws in place of the multimodal model, which is then not read
        model=[] if TYPE_REFINER else out(f"diffusion/{COND_MODEL}/model.pt"),
        prompts=out("conditions/prompts.tsv"),
        manifest=out("neumerl/manifest.tsv"),
        **({"weights": out("neumerl/weights.npy")} if TYPE_START else {}),
        refiner=[out("diffusion/refiner/model.pt")] if TYPE_REFINER else [],
    output:
        weights=out("samples/mm_type/weights.npy"),
        table=out("samples/mm_type/samples.tsv"),
        timing=out("samples/mm_type/timing.tsv"),
    params:
        **COND_SAMPLING,
        guidance=cond_guidance("type", TYPE_REFINER),
        mode="mm_type",
        seed=cond_seed("mm_type"),
        activation=DIFF_ACTIVATION,
        **neutral_params("conditions.type", ["strength", "refiner"]),
    log:
        log("sample_multimodal/mm_type"),
    benchmark:
        bench("sample_multimodal/mm_type")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=2500,
        runtime=30,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/sample_conditions.py"


rule conditions_eval:
    input:
        samples=expand(out("samples/{set}/weights.npy"), set=COND_SETS),
        tables=expand(out("samples/{set}/samples.tsv"), set=COND_SETS),
        conditioning=out("samples/image/conditioning.npy"),
        conditioning_embeddings=out("samples/image/conditioning_embeddings.npy"),
        image_embeddings=out("conditions/image.npy"),
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
        prompts=out("conditions/prompts.tsv"),
    output:
        per_sample=out("conditions/eval_per_sample.tsv"),
        image=out("conditions/eval_image.tsv"),
        summary=out("conditions/eval_summary.tsv"),
    params:
        **named(dict(
            bins=DIFF["nn_bins"],
            angles=DIFF["plausibility_angles"],
            resolution=config["render"]["resolution"],  # the metric render's, as Table 2's
            seed=cond_seed("eval"),
            activation=DIFF_ACTIVATION,
        )),
    log:
        log("conditions_eval"),
    benchmark:
        bench("conditions_eval")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=3000,
        runtime=30,
    script:
        "../scripts/conditions_eval.py"


rule guidance_sweep:
    input:
        model=out(f"diffusion/{COND_MODEL}/model.pt"),
        prompts=out("conditions/prompts.tsv"),
        prompt_embeddings=out("conditions/prompts.npy"),
        image_embeddings=out("conditions/image.npy"),
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        out("conditions/guidance_sweep.tsv"),
    params:
        **named(dict(
            sample=COND_SAMPLE,  # conditions.guidance instead of its guidance
            scales=COND["sweep"]["scales"],
            per_prompt=COND["sweep"]["per_condition"],
            bins=DIFF["nn_bins"],
            angles=DIFF["plausibility_angles"],
            seed=cond_seed("sweep"),
            activation=DIFF_ACTIVATION,
        )),
    log:
        log("guidance_sweep"),
    benchmark:
        bench("guidance_sweep")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=3000,
        runtime=120,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/guidance_sweep.py"


rule conditions_mitsuba:
    input:
        text=out("samples/text/weights.npy"),
        text_table=out("samples/text/samples.tsv"),
        image=out("samples/image/weights.npy"),
        image_table=out("samples/image/samples.tsv"),
        conditioning=out("samples/image/conditioning.npy"),
    output:
        text=report(out("report/figures/conditions_text.png"), category="Conditioning",
                    caption="../report/conditions_text.rst"),
        image=report(out("report/figures/conditions_image.png"), category="Conditioning",
                     caption="../report/conditions_image.rst"),
        info=out("render/mitsuba/conditions.json"),
    params:
        **named(dict(
            cfg=settings("render.mitsuba", ["variant", "resolution", "spp", "envmap_size"]),
            rows=COND["figure_rows"],
            per_row=COND["figure_samples"],
            activation=DIFF_ACTIVATION,
            seed=cond_seed("mitsuba"),
        )),
    log:
        log("conditions_mitsuba"),
    benchmark:
        bench("conditions_mitsuba")
    conda:
        CONDA_ENV
    threads: 2
    resources:
        mem_mb=4000,
        runtime=120,
    script:
        "../scripts/conditions_mitsuba.py"


COND_REFINED = [m for m, on in (("type", TYPE_REFINER), ("text", TEXT_REFINER),
                                ("image", IMAGE_REFINER)) if on]


rule conditions_section:
    input:
        per_sample=out("conditions/eval_per_sample.tsv"),
        image=out("conditions/eval_image.tsv"),
        summary=out("conditions/eval_summary.tsv"),
        sweep=out("conditions/guidance_sweep.tsv"),
        encoder_eval=out("conditions/image_encoder_eval.tsv"),
        encoder=out("conditions/image_encoder.pt"),
        history=out(f"diffusion/{COND_MODEL}/history.tsv"),
        model=out(f"diffusion/{COND_MODEL}/model.pt"),
        timings=expand(out("samples/{set}/timing.tsv"), set=COND_SETS),
        benchmarks=[bench("text_embeddings"), bench("prompt_embeddings"), bench("train_image_encoder"),
                    bench("image_embeddings"), bench("train_multimodal")],
        figures=[out("report/figures/conditions_text.png"),
                 out("report/figures/conditions_image.png")],
        # measured colour words: the embedded descriptions are shown (and so required: a run
        # switched to `measured` re-embeds them)
        **({"descriptions": out("conditions/descriptions.tsv")} if COND_MEASURED else {}),
    output:
        section=out("report/sections/42_conditions.md"),
        sweep=report(out("report/figures/conditions_guidance.png"), category="Conditioning",
                     caption="../report/conditions_guidance.rst"),
    params:
        # modalities whose samples the refiner drew (no condition, so no guidance scale: only
        # the others' scales are params, so a refined modality's scale reruns nothing here)
        refined=COND_REFINED,
        guidance={k: v for k, v in settings("conditions.guidance").items() if k not in COND_REFINED},
        image_sampling=image_sampling(),
    log:
        log("conditions_section"),
    benchmark:
        bench("conditions_section")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=1500,
        runtime=10,
    script:
        "../scripts/conditions_section.py"
