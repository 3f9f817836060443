"""Table 3 (CSV, Markdown, HTML), its report section and the reconstruction figure."""
from pathlib import Path

import numpy as np
import pandas as pd

from neumat import report
from neumat.baselines import hyperbrdf as hb
from neumat.io import modelfile
from neumat.logs import script_logging
from neumat.metrics import reconstruction as rec
from neumat.render.gallery import gallery


with script_logging(snakemake) as log:
    inp, out, p = snakemake.input, snakemake.output, snakemake.params
    scores = pd.read_csv(inp.scores, sep="\t", keep_default_na=False)
    hyper = [f"HyperBRDF ({m})" for m in p.models]
    methods = ["mean training material", *hyper, "NeuMERL fit"]
    table = rec.table3(scores, methods, list(hb.TASKS))
    table.to_csv(out.csv, index=False, float_format="%.6g")
    md_table = report.md_table(table, floatfmt=".4g")
    Path(out.md).write_text(md_table + "\n")
    Path(out.html).write_text(table.to_html(index=False, float_format=lambda x: f"{x:.4g}") + "\n")
    wins = rec.wins(table, hyper[1], hyper[0])
    paired = rec.paired(scores, hyper[1], hyper[0], list(hb.TASKS), p.seed)
    paired.to_csv(out.paired, index=False, float_format="%.6g")
    n_mat = scores["material"].nunique()
    judged = rec.min_p(n_mat) < rec.ALPHA  # else every verdict is rec.TOO_FEW
    firm = int((paired["beyond noise"] == True).sum())  # noqa: E712 (True, not a truthy string)
    bundles = [modelfile.load(f) for f in inp.models]  # an error naming a damaged file

    r = np.load(inp.renders)
    names = [str(n) for n in r["names"]][:p.examples]
    cols = [("truth", "-"), ("NeuMERL fit", "any")] + [(h, t) for t in hb.TASKS for h in hyper]
    imgs, labels = [], []
    for i, n in enumerate(names):
        for m, t in cols:
            imgs.append(r[f"{m}|{t}|metric"][i])
            short = m.removeprefix("HyperBRDF (").removesuffix(")").replace("merl", "MERL")
            labels.append(n if m == "truth" else (m if t == "any" else f"{short.replace('augMERL', 'AugMERL')}, {t}"))
    gallery(imgs, labels, out.figure, ncols=len(cols), min_cell=110,
            title="Table 3 test materials: ground truth, NeuMERL fit, HyperBRDF trained on MERL / AugMERL")

    t = p.train
    cost = ", ".join(f"{m}: {b['n_train']} materials, {report.duration(b['train_seconds'])}"
                     for m, b in zip(p.models, bundles))
    md = [
        "## Table 3: HyperBRDF trained on MERL vs AugMERL",
        f"The hypernetwork BRDF model (Gokbudak et al. 2023; set encoder → {p.latent}-d "
        f"latent → one head per target tensor → NBRDF) trained on the MERL train split and on "
        f"the AugMERL train split, {t['steps']} steps each of {t['materials_per_step']} "
        f"material(s), Adam lr {t['lr']:g} ({cost}). Scored on the {n_mat} test-split source "
        f"materials, which neither model saw: **sparse** = {p.sparse_samples} random stored "
        f"samples into the encoder, **compression** = all stored samples through the latent. "
        f"Metrics on {p.resolution}² sRGB sphere renders under the metric light and a "
        f"grazing light, mean over materials and both views: PSNR (dB, peak 1), ΔE = mean "
        f"CIEDE2000 over sphere pixels (lower is better), SSIM. Anchors: the per-material "
        f"NeuMERL fit (upper bound) and the mean train-split source material (floor); they do "
        f"not depend on the task.",
        md_table,
        f"AugMERL beats MERL in **{sum(wins.values())} of {len(wins)}** cells"
        + (f" (not: {', '.join(c for c, w in wins.items() if not w)})." if not all(wins.values())
           else "."),
        f"**Paired, per cell** ({hyper[1]} minus {hyper[0]} on the same {n_mat} materials and "
        f"both views; the views of a material averaged first): a win is beyond "
        f"material-to-material noise when a two-sided sign-flip permutation test over the "
        f"{n_mat} per-material differences gives p < {rec.ALPHA:g} ("
        + (f"exact: all 2^{n_mat} sign patterns" if n_mat <= rec.EXACT_MAX else
           f"{rec.N_MC:,} seeded random sign patterns") + "). "
        + (f"AugMERL's win is beyond noise in **{firm} of {len(paired)}** cells." if judged else
           f"With {n_mat} materials the smallest attainable p is 2 / 2^{n_mat} = "
           f"{rec.min_p(n_mat):.3g}, not below {rec.ALPHA:g}: **too few materials to judge** "
           f"any cell (`augmerl.test_fraction`; 6 or more test sources needed).")
        + " `pairs won` counts material-and-view pairs (each view on its own, so twice the "
        "materials), the test the per-material differences: the two can disagree. The 95 % "
        "bootstrap interval (resampling materials) is descriptive only: with few "
        "materials it is too narrow to decide on. The table has one row per method (the two "
        "HyperBRDF trainings, MERL and AugMERL, as two rows) and task x metric as columns, "
        "the paper's Table 3 turned round; PSNR and SSIM: higher is better, ΔE: lower.",
        report.md_table(paired, floatfmt=".4g"),
        "![Table 3 reconstructions](figures/hyperbrdf_reconstructions.png)",
        "Files: `hyperbrdf/table3.{csv,md,html}`, `hyperbrdf/table3_paired.csv`, per material "
        "and view `hyperbrdf/scores.tsv`.",
    ]
    Path(out.section).write_text("\n\n".join(md) + "\n")
    log.info("Table 3: AugMERL beats MERL in %d of %d cells; beyond noise (%d materials): %s",
             sum(wins.values()), len(wins), n_mat, firm if judged else rec.TOO_FEW)
