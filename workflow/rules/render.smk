# Renders (issue 4): Mitsuba 3 figures of reference materials (neural fields in the
# `neumat_brdf` plugin) and the rendering report section with metric-renderer galleries.
#   samples/reference/weights.npy -> render/mitsuba/{scene}.{exr,png,json} -> 30_rendering.md

RENDER = config["render"]
MITSUBA_SCENES = ["sphere", "mixed_plane", "normal_mapped"]
RENDER_MERL = MERL_NAMES[: min(4, len(MERL_NAMES))]  # tables shown next to the fields


rule mitsuba_figure:
    input:
        weights=REFERENCE_WEIGHTS,
        table=out("samples/reference/samples.tsv"),
    output:
        exr=out("render/mitsuba/{scene}.exr"),
        png=out("render/mitsuba/{scene}.png"),
        info=out("render/mitsuba/{scene}.json"),
    wildcard_constraints:
        scene="|".join(MITSUBA_SCENES),
    params:
        cfg=settings("render.mitsuba", ["variant", "resolution", "spp", "envmap_size", "materials"]),
        activation=config["fit"]["activation"],
        seed=seed_for("mitsuba_figure"),
    log:
        log("mitsuba_figure/{scene}"),
    benchmark:
        bench("mitsuba_figure/{scene}")
    conda:
        CONDA_ENV
    threads: 2
    resources:
        mem_mb=4000,
        runtime=60,
    script:
        "../scripts/mitsuba_figure.py"


rule render_section:
    input:
        weights=REFERENCE_WEIGHTS,
        table=out("samples/reference/samples.tsv"),
        merl=[merl_table(n) for n in RENDER_MERL],
        figures=expand(out("render/mitsuba/{scene}.png"), scene=MITSUBA_SCENES),
        infos=expand(out("render/mitsuba/{scene}.json"), scene=MITSUBA_SCENES),
    output:
        section=out("report/sections/30_rendering.md"),
        fields=report(out("report/figures/render_reference_fields.png"), category="Rendering",
                      caption="../report/render_reference_fields.rst"),
        tables=report(out("report/figures/render_merl_tables.png"), category="Rendering",
                      caption="../report/render_merl_tables.rst"),
        mitsuba=report(out("report/figures/render_mitsuba.png"), category="Rendering",
                       caption="../report/render_mitsuba.rst"),
    params:
        **named(dict(
            names=RENDER_MERL,
            resolution=RENDER["resolution"],
            figure_resolution=config["report"]["sphere_resolution"],
            n_gallery=RENDER["gallery_count"],
            activation=config["fit"]["activation"],
        )),
    log:
        log("render_section"),
    benchmark:
        bench("render_section")
    conda:
        CONDA_ENV
    threads: 2
    resources:
        mem_mb=lambda wc, input: 2000 + 60 * len(input.merl),
        runtime=15,
    script:
        "../scripts/render_section.py"
