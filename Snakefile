# neumat: measured-material synthesis workflow.
# Entry points (targets before --configfile: it takes every following word as a file):
#   snakemake --cores 2 report
#   snakemake --cores 2 report --configfile config/tiny.yaml
from snakemake.exceptions import WorkflowError
from snakemake.utils import min_version, validate

min_version("9.0")


configfile: "config/config.yaml"


try:
    validate(config, "config/schema.yaml")
except WorkflowError as e:
    # jsonschema's error as one line: Snakemake's own message is followed by a dump of the whole
    # schema and config (thousands of lines), whose tail shows the defaults, not the mistake
    err = e.__cause__ or e.__context__  # WorkflowError keeps only the text of its arguments
    if not hasattr(err, "absolute_path"):
        raise
    key = ".".join(map(str, err.absolute_path)) or "top level"
    what = err.message
    if err.validator in ("anyOf", "oneOf") and "description" in err.schema:
        what += f": {err.schema['description']}"  # jsonschema names none of the alternatives
    raise WorkflowError(
        f"bad config ({key}): {what}. Every key, its type and default are in "
        f"config/schema.yaml; fix it in the file given with --configfile, or in --config."
    ) from None


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


# On a cluster (profiles/slurm) these run on the submit host instead of as batch jobs: they
# gather finished results into tables, Markdown and a few MERL exports, in seconds (measured on
# the 100-material run: neumerl 5 s / 0.27 GB, diffusion_training_set 4 s, hyperbrdf_table
# 5 s / 0.30 GB), while a batch job costs two Snakemake starts and a queue wait (README
# "Running on Slurm"). Rules that fit, train, sample, render or read the raw data stay batch jobs.
localrules:
    report,
    dataset_section,
    conditions_section,
    btf_section,
    btf_synthesis_section,
    metrics_table,
    hyperbrdf_table,
    neumerl,
    neumerl_export,
    diffusion_training_set,
    export_samples,


rule all:
    input:
        report_inputs(),
    default_target: True
