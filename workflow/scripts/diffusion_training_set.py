"""Table 2's 'Training set' column - `draws` disjoint random NeuMERL train-split subsets, each
as large as the test split (draw-major) - and the test split itself ('reference'), written
like a model's samples."""
import numpy as np
import pandas as pd

from neumat.diffusion import dataset
from neumat.io.atomic import save_npy
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    out = snakemake.output
    weights = np.load(snakemake.input.weights)
    man = dataset.read_manifest(snakemake.input.manifest, len(weights))
    for rows, w_path, t_path in ((dataset.training_subset(man, snakemake.params.seed,
                                                          snakemake.params.draws),
                                  out.weights, out.table),
                                 (dataset.reference_rows(man), out.ref_weights, out.ref_table)):
        save_npy(w_path, weights[rows])
        pd.DataFrame({"sample": np.arange(len(rows)), "id": man["id"].iloc[rows].to_numpy(),
                      "name": man["name"].iloc[rows].to_numpy(),
                      "type": man["type"].iloc[rows].to_numpy()}).to_csv(t_path, sep="\t", index=False)
    log.info("training subset: %d draws; reference: %d materials (of %d train-split)",
             snakemake.params.draws, len(dataset.reference_rows(man)),
             int((man["split"] == "train").sum()))
