# neumat: measured-material synthesis workflow.
# Entry points (targets before --configfile: it takes every following word as a file):
#   snakemake --cores 2 report
#   snakemake --cores 2 report --configfile config/tiny.yaml
from snakemake.utils import min_version, validate

min_version("9.0")


configfile: "config/config.yaml"


validate(config, "config/schema.yaml")


include: "workflow/rules/common.smk"
include: "workflow/rules/data.smk"
include: "workflow/rules/augment.smk"
include: "workflow/rules/fit.smk"
include: "workflow/rules/diffusion.smk"
include: "workflow/rules/conditions.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/constrained.smk"
include: "workflow/rules/metrics.smk"
include: "workflow/rules/hyperbrdf.smk"
include: "workflow/rules/baselines.smk"
include: "workflow/rules/btf.smk"
include: "workflow/rules/btf_synthesis.smk"
include: "workflow/rules/report.smk"


rule all:
    input:
        report_inputs(),
    default_target: True
