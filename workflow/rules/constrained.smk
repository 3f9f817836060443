# Constrained synthesis (M3ashy §4.5, Fig. 6): derive the seven category rules' thresholds from
# the source materials, classify every source and NeuMERL material, rejection-sample the `ours`
# model into each category, and report it with a Mitsuba gallery.
#   source tables -> constrained_rules -> constrained_classify (+ neumerl)
#   -> sample_constrained (+ diffusion/ours) -> constrained_section

CONS = config["constrained"]
CONS_STAGE = 7  # seed stream of this stage


def constrained_seed(*items):
    """Seed of one stochastic step of this stage (one place to switch to common.smk's
    seed_for("constrained", ...) once it lands)."""
    return SEED + 1000 * CONS_STAGE + sum(100 ** k * int(i) for k, i in enumerate(items))


rule constrained_rules:
    input:
        tables=[merl_table(n) for n in MERL_NAMES],
    output:
        stats=out("constrained/source_stats.tsv"),
        rules=out("constrained/rules.tsv"),
    params:
        names=MERL_NAMES,
        types=list(MERL["type"]),
        derive=CONS["derive"],
        e=CONS["thresholds"]["e"],
        metallic_exceptions=CONS["thresholds"]["metallic_exceptions"],
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
        thresholds=CONS["thresholds"],
        bins=CONS["bins"],
        seed=constrained_seed(1),
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


rule sample_constrained:
    input:
        model=out("diffusion/ours/model.pt"),
        rules=out("constrained/rules.tsv"),
        classes=out("constrained/classes.tsv"),
    output:
        weights=out("samples/constrained/weights.npy"),
        table=out("samples/constrained/samples.tsv"),
        acceptance=out("constrained/acceptance.tsv"),
    params:
        cfg={k: CONS[k] for k in ("categories", "per_category", "budget", "batch", "guide", "bins",
                                  "thresholds")},
        sample=DIFF["sample"],
        seed=constrained_seed(2),
        activation=config["fit"]["activation"],
        device=config["device"],
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
        mitsuba=config["render"]["mitsuba"],
        gallery_count=CONS["gallery_count"],
        categories=CONS["categories"],
        activation=config["fit"]["activation"],
        seed=constrained_seed(3),
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


REPORT_SECTIONS.append(out("report/sections/45_constrained.md"))
