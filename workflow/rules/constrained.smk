# Constrained synthesis (M3ashy §4.5, Fig. 6): derive the seven category rules' thresholds from
# the source materials, classify every source and NeuMERL material, rejection-sample the `ours`
# model into each category, and report it with a Mitsuba gallery.
#   source tables -> constrained_rules -> constrained_classify (+ neumerl)
#   -> sample_constrained (+ diffusion/ours) -> constrained_section

CONS = config["constrained"]


rule constrained_rules:
    input:
        tables=[merl_table(n) for n in MERL_NAMES],
    output:
        stats=out("constrained/source_stats.tsv"),
        rules=out("constrained/rules.tsv"),
    params:
        names=MERL_NAMES,
        types=list(MERL["type"]),
        derive=canon(CONS["derive"]),
        thresholds=canon(CONS["thresholds"]),
    log:
        log("constrained_rules"),
    benchmark:
        bench("constrained_rules")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=1500,
        runtime=10 + len(MERL_NAMES) // 10,
    script:
        "../scripts/constrained_rules.py"


rule constrained_classify:
    input:
        stats=out("constrained/source_stats.tsv"),
        rules=out("constrained/rules.tsv"),
        weights=out("neumerl/weights.npy"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        classes=out("constrained/classes.tsv"),
        purity=out("constrained/purity.tsv"),
    params:
        thresholds=canon(CONS["thresholds"]),
        bins=CONS["bins"],
        # the bins the statistics read: the same for the fields here and the samples in
        # sample_constrained, so the section compares the two on one set of bins
        seed=seed_for("constrained_bins"),
        activation=config["fit"]["activation"],
    log:
        log("constrained_classify"),
    benchmark:
        bench("constrained_classify")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=2500,
        runtime=lambda wc, input: 10 + int(input.size_mb),
    script:
        "../scripts/constrained_classify.py"


# guidance_step acts only where category guidance can (guide auto, diffuse or metallic among
# the categories: neumat.diffusion.constraints.GUIDED_CATEGORIES), diffusion.sample.guidance only
# with guide types (guide auto): elsewhere a change of either reran sampling to the same samples
CON_GUIDE = config["constrained"]["guide"] == "auto"
CON_STEP = CON_GUIDE and bool({"diffuse", "metallic"} & set(config["constrained"]["categories"]))


rule sample_constrained:
    input:
        model=out("diffusion/ours/model.pt"),
        rules=out("constrained/rules.tsv"),
        classes=out("constrained/classes.tsv"),
        manifest=out("neumerl/manifest.tsv"),
    output:
        weights=out("samples/constrained/weights.npy"),
        table=out("samples/constrained/samples.tsv"),
        acceptance=out("constrained/acceptance.tsv"),
    params:
        cfg=settings("constrained", ["categories", "per_category", "budget", "batch", "guide",
                                     *(["guidance_step"] if CON_STEP else []), "bins",
                                     "thresholds"]),
        # its draws keep their channel order
        sample=settings("diffusion.sample",
                        drop=NOT_OF_OTHER_DRAWS + ([] if CON_GUIDE else ["guidance"])),
        seed=seed_for("sample_constrained"),
        bins_seed=seed_for("constrained_bins"),  # constrained_classify's bins
        activation=config["fit"]["activation"],
    log:
        log("sample_constrained"),
    benchmark:
        bench("sample_constrained")
    conda:
        CONDA_ENV
    threads: DIFF["threads"]
    resources:
        mem_mb=3000,
        runtime=60,
        gpu=GPU,  # its script runs torch on config device
    script:
        "../scripts/sample_constrained.py"


rule constrained_section:
    input:
        stats=out("constrained/source_stats.tsv"),
        rules=out("constrained/rules.tsv"),
        classes=out("constrained/classes.tsv"),
        purity=out("constrained/purity.tsv"),
        weights=out("samples/constrained/weights.npy"),
        table=out("samples/constrained/samples.tsv"),
        acceptance=out("constrained/acceptance.tsv"),
    output:
        section=out("report/sections/45_constrained.md"),
        gallery=report(out("report/figures/constrained_gallery.png"),
                       caption="../report/constrained_gallery.rst", category="Diffusion"),
    params:
        mitsuba=settings("render.mitsuba", ["variant", "resolution", "spp", "envmap_size"]),
        gallery_count=CONS["gallery_count"],
        categories=CONS["categories"],
        activation=config["fit"]["activation"],
        seed=seed_for("constrained_section"),
    log:
        log("constrained_section"),
    benchmark:
        bench("constrained_section")
    conda:
        CONDA_ENV
    threads: 2
    resources:
        mem_mb=4000,
        runtime=60,
    script:
        "../scripts/constrained_section.py"

