"""Paper Table 2 over all models (CSV, Markdown, HTML; mean ± std over draws), the sanity rows,
and the report section."""
from pathlib import Path

import pandas as pd

from neumat import report
from neumat.logs import script_logging
from neumat.metrics import evaluate


def read(f):
    return pd.read_csv(f, keep_default_na=False, na_values=[""])


with script_logging(snakemake) as log:
    p, out = snakemake.params, snakemake.output
    results = {m: read(f) for m, f in zip(p.models, snakemake.input.models)}
    halves = read(snakemake.input.sanity)
    checks, problems = evaluate.sanity(halves, results.get("training_set"))
    evaluate.write_table2(results, out.csv, out.md, out.html,
                          sources=dict(zip(p.models, snakemake.input.models)))
    notes = sorted({n for df in results.values() for n in df.loc[df["metric"] == "FID", "note"]})
    draws = int(halves["draw"].nunique())
    verdict = ("**Protocol check failed** - " + "; ".join(problems) + ". The table below cannot "
               "be trusted to rank models." if problems else
               "Protocol check passed: random halves of the reference set are told apart no "
               "better than chance would allow (1-NNA inside 30-70 %).")
    md = [
        "## Table 2: unconditional synthesis metrics",
        f"Each model's samples against the NeuMERL test split (reference set; split by source "
        f"material). Every cell is the mean ± std over {draws} sample draws, each as large as "
        f"the reference set and from its own seed. Distances: BRDF-L1 = mean |f - f'| of the "
        f"physical BRDF over {p.brdf_samples} valid MERL bins (fixed sample); RMSE, NegPSNR "
        f"(= -PSNR), NegSSIM (= -SSIM) between {p.resolution}² sRGB metric sphere renders. "
        "COV and 1-NNA in %; the MMD RMSE and NegSSIM rows show value × the factor in their "
        "label, as in the paper; MMD BRDF-L1 is shown unscaled (the paper's ×10⁻³ is on "
        "another BRDF scale and would leave no digits here). "
        "1-NNA: 50 % is ideal. PCA-A samples are tables (rendered from the table); all other "
        "columns are neural fields.",
        Path(out.md).read_text(),
        "FID: " + "; ".join(n for n in notes if n) + ". The 64-d row is the variant of the "
        "released M³ashy code (`pytorch_fid --dims 64`), the only one comparable with the "
        "paper's FID values.",
        "### Novelty",
        f"Median BRDF-L1 (over {p.novelty_bins} of the BRDF-L1 bins) from each sample to its "
        "nearest NeuMERL training material, mean over draws, against the same for the "
        "reference set (real materials the models never saw). Ratio near 1: new materials as "
        "far from the training set as real unseen ones; near 0: near-copies; far above 1: "
        "off the training manifold." + report.nn_bins_note("Table 2's novelty table"),
        evaluate.novelty_table(results).to_markdown(index=False, floatfmt=".4g"),
        "### Sanity rows",
        "Reference halves: random halves of the reference set scored against each other "
        "(1-NNA should be near 50 %). Training set: train-split materials against the test "
        "split; above 50 % means held-out sources differ from training ones.",
        checks.to_markdown(index=False, floatfmt=".1f"),
        verdict,
        "Files: `metrics/table2.csv`, `metrics/table2.html`, per model `metrics/<model>.csv` "
        "(one row per draw), `metrics/reference_halves.csv`.",
    ]
    Path(out.section).write_text("\n\n".join(md) + "\n")
    log.info("Table 2 over %d models; sanity problems: %s", len(results), problems or "none")
