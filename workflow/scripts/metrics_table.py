"""Paper Table 2 over all models (CSV, Markdown, HTML) and its report section."""
from pathlib import Path

import pandas as pd

from neumat.logs import script_logging
from neumat.metrics import evaluate

with script_logging(snakemake) as log:
    p, out = snakemake.params, snakemake.output
    results = {m: pd.read_csv(f, keep_default_na=False, na_values=[""])
               for m, f in zip(p.models, snakemake.input)}
    evaluate.write_table2(results, out.csv, out.md, out.html)
    notes = sorted({n for df in results.values() for n in df.loc[df["metric"] == "FID", "note"]})
    md = [
        "## Table 2: unconditional synthesis metrics",
        f"Each model's samples against the NeuMERL test split (reference set). Distances: "
        f"BRDF-L1 = mean |f - f'| of the physical BRDF over {p.brdf_samples} valid MERL bins "
        f"(fixed sample); RMSE, NegPSNR (= -PSNR), NegSSIM (= -SSIM) between {p.resolution}² "
        "sRGB metric sphere renders. COV and 1-NNA in %; MMD rows show value × the factor in "
        "their label, as in the paper. 1-NNA: 50 % is ideal.",
        Path(out.md).read_text(),
        "FID: " + "; ".join(n for n in notes if n) + ".",
        "Files: `metrics/table2.csv`, `metrics/table2.html`, per model `metrics/<model>.csv`.",
    ]
    Path(out.section).write_text("\n\n".join(md) + "\n")
    log.info("Table 2 over %d models", len(results))
