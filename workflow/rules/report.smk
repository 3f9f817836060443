# The run report: every stage's Markdown fragment -> results/<run>/report/index.{md,html}, each
# figure followed by its report() caption. Included last: figure_captions reads every rule.
FIGURE_CAPTIONS = figure_captions()


rule report:
    input:
        sections=REPORT_SECTIONS,
        captions=sorted(set(FIGURE_CAPTIONS.values())),
        # the MERL .binary exports of samples: made with the report, read by no section (as an
        # input of diffusion_section, diffusion.export_merl reran its gallery renders)
        exports=diffusion_exports(),
    output:
        md=out("report/index.md"),
        html=out("report/index.html"),
    params:
        run=RUN,
        captions=FIGURE_CAPTIONS,  # figure file-name pattern -> caption file
        config=canon(substantive(config, keep=COSMETIC_KEYS)),  # speed-only keys left out
    log:
        log("report"),
    benchmark:
        bench("report")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=1000,
        runtime=10,
    script:
        "../scripts/report.py"
