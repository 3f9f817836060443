"""Merge the shard fits into NeuMERL: weights.npy (manifest order), manifest copy, fits.tsv."""
import shutil

import pandas as pd

from neumat import fit
from neumat.io.atomic import save_npy
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    out = snakemake.output
    man = pd.read_csv(snakemake.input.manifest, sep="\t", dtype={"shard": str},
                      keep_default_na=False)
    weights, res = fit.merge_fits([fit.load_fits(f) for f in snakemake.input.fits],
                                  [pd.read_csv(e, sep="\t") for e in snakemake.input.evals], man)
    save_npy(out.weights, weights)
    shutil.copyfile(snakemake.input.manifest, out.manifest)
    res.to_csv(out.fits, sep="\t", index=False, float_format="%.6g")
    log.info("NeuMERL: %d fields; render PSNR median %.2f dB, 10th percentile %.2f dB; "
             "val loss median %.4g", len(res), res["render_psnr"].median(),
             res["render_psnr"].quantile(0.1), res["val_loss"].median())
