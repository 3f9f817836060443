"""Measures of the conditioned sample sets of the multimodal model (text, image) and its
same-run baselines (type-conditioned, unconditional): type hits (nearest typed training
material, BRDF-L1), colour-word chromaticity, nearest-training distance, negative clamping;
PSNR / SSIM of image-conditioned samples in the conditioning view against unconditional samples
and nearest-embedding retrieval. Reference rows: the real test-split materials and the training
fits. The measures are neumat.conditions.evaluate's."""
import numpy as np
import pandas as pd
import torch

from neumat.conditions import evaluate as ev
from neumat.conditions import image
from neumat.diffusion import dataset
from neumat.logs import script_logging
from neumat.metrics import distances
from neumat.seeds import seed_for


def set_name(path):
    return path.split("/")[-2]


with script_logging(snakemake) as log:
    p, inp, out = snakemake.params, snakemake.input, snakemake.output
    weights = np.load(inp.weights)
    man = dataset.read_manifest(inp.manifest, len(weights))
    ts = ev.TrainingSet(weights, man, distances.brdf_sample(p.bins, p.seed), p.activation)
    neg_seed = seed_for(p.seed, "negative_share")
    neg = lambda w: ev.negative_share(w, p.angles, neg_seed, p.activation)  # noqa: E731
    prompts = pd.read_csv(inp.prompts, sep="\t", keep_default_na=False)
    in_training = set(prompts.loc[prompts["in_training"].astype(str) == "True", "prompt"])
    per, rows, sets = [], [], {}
    for wpath, tpath in zip(inp.samples, inp.tables):
        name = set_name(wpath)
        sets[name] = np.load(wpath)
        t = pd.read_csv(tpath, sep="\t", keep_default_na=False, dtype={"type": str})
        df = ev.score_set(ts, sets[name], t, neg, p.resolution, p.activation)
        df.insert(0, "set", name)
        per.append(df)
        rows.append(ev.summarise(df, name))
        if name in ("text", "mm_type", "mm_uncond"):  # the test-split descriptions alone
            rows.append(ev.summarise(df[df["kind"] == "test"], f"{name} (test descriptions)"))
            if name == "text":  # and the prompts held out as text: none a training description
                held = ~df["prompt"].isin(in_training)
                rows.append(ev.summarise(df[(df["kind"] == "test") & held],
                                         "text (test descriptions, none a training description)"))
                rows.append(ev.summarise(df[(df["kind"] == "unseen") & held],
                                         "text (unseen prompts)"))
    per = pd.concat(per, ignore_index=True)
    per.to_csv(out.per_sample, sep="\t", index=False, float_format="%.6g")

    img = per[per["set"] == "image"]
    conditions = img["condition"].to_numpy()
    first = img.groupby("condition").first()  # per conditioning image: its source and type
    sources = first["source"].tolist()
    retrieved = image.retrieve(np.load(inp.conditioning_embeddings),
                               np.load(inp.image_embeddings)[ts.rows, 0], ts.rows)  # metric view
    # the image modality's yardsticks, over the images of test-split materials (not users')
    row_of = pd.Series(np.arange(len(man)), index=man["name"])
    own = first["source"].map(row_of)
    known = own.notna().to_numpy()
    if known.any():
        rows += ev.image_yardsticks(ts, weights, own[known].astype(int).to_numpy(), retrieved[known],
                                    first["type"][known], neg, p.resolution, p.activation)
    summary = pd.DataFrame(rows + ev.reference_summaries(ts, weights, man, neg))
    summary.to_csv(out.summary, sep="\t", index=False, float_format="%.4g")
    log.info("\n%s", summary.to_string())

    # image agreement in the conditioning view
    res = ev.image_agreement(torch.as_tensor(np.load(inp.conditioning)), conditions,
                             sets["image"], sets["mm_uncond"], retrieved, weights, sources,
                             man["name"].to_numpy(), p.resolution, p.activation)
    res.to_csv(out.image, sep="\t", index=False, float_format="%.5g")
    log.info("image agreement (means):\n%s", res.mean(numeric_only=True).to_string())
