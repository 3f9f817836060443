"""Measures of the conditioned sample sets of the multimodal model (text, image) and its
same-run baselines (type-conditioned, unconditional): type hits (nearest typed training
material, BRDF-L1), colour-word chromaticity, nearest-training distance, negative clamping;
PSNR / SSIM of image-conditioned samples in the conditioning view against unconditional samples
and nearest-embedding retrieval. Reference rows: the real test-split materials and the training
fits."""
import numpy as np
import pandas as pd
import torch

from neumat.conditions import evaluate as ev
from neumat.conditions import image
from neumat.diffusion import dataset
from neumat.logs import script_logging
from neumat.metrics import distances
from neumat.render import sphere
from neumat.seeds import seed_for


def set_name(path):
    return path.split("/")[-2]


def summarise(df, name):
    typed, coloured = df[df["scorable"]], df[df["colour"] != ""]
    return {"set": name, "samples": len(df),
            "type hits": typed["type_hit"].mean() if len(typed) else np.nan,
            "samples with a training type": len(typed),
            "colour match": coloured["colour_match"].mean() if len(coloured) else np.nan,
            "coloured samples": len(coloured),
            "median BRDF-L1 to nearest training": df["brdf_l1"].median(),
            "share clamping negatives": df["negative"].mean()}


with script_logging(snakemake) as log:
    p, inp, out = snakemake.params, snakemake.input, snakemake.output
    weights = np.load(inp.weights)
    man = dataset.read_manifest(inp.manifest, len(weights))
    ts = ev.TrainingSet(weights, man, distances.brdf_sample(p.bins, p.seed), p.activation)
    neg_seed = seed_for(p.seed, "negative_share")
    neg = lambda w: ev.negative_share(w, p.angles, neg_seed, p.activation)  # noqa: E731
    per, rows = [], []
    for wpath, tpath in zip(inp.samples, inp.tables):
        name, w = set_name(wpath), np.load(wpath)
        t = pd.read_csv(tpath, sep="\t", keep_default_na=False, dtype={"type": str})
        for col in ("type", "colour", "kind", "prompt", "source"):
            if col not in t:
                t[col] = ""
        df = pd.concat([t[["sample", "condition", "kind", "prompt", "source", "type", "colour"]],
                        ts.nearest(w)], axis=1)
        df.insert(0, "set", name)
        df["scorable"] = ts.scorable(df["type"])
        df["type_hit"] = (df["type"] == df["nearest_type"]) & df["scorable"]
        rgb = ev.mean_colour(sphere.render_fields(np.nan_to_num(w), p.resolution, p.activation))
        df["colour_match"] = [bool(c) and ev.colour_matches(x, c) for x, c in zip(rgb, df["colour"])]
        df["negative"] = neg(w)
        per.append(df)
        rows.append(summarise(df, name))
        if name in ("text", "mm_type", "mm_uncond"):  # the test-split descriptions alone
            rows.append(summarise(df[df["kind"] == "test"], f"{name} (test descriptions)"))
            if name == "text":
                rows.append(summarise(df[df["kind"] == "unseen"], "text (unseen prompts)"))
    per = pd.concat(per, ignore_index=True)
    per.to_csv(out.per_sample, sep="\t", index=False, float_format="%.6g")

    # reference rows: the real test-split materials and the training fits
    test = dataset.reference_rows(man)
    near = ts.nearest(weights[test])
    own = man["type"].iloc[test].to_numpy()
    ok = ts.scorable(own)
    rows.append({"set": "reference: real test-split materials", "samples": len(test),
                 "type hits": (near["nearest_type"].to_numpy() == own)[ok].mean() if ok.any() else np.nan,
                 "samples with a training type": int(ok.sum()),
                 "median BRDF-L1 to nearest training": near["brdf_l1"].median(),
                 "share clamping negatives": neg(weights[test]).mean()})
    rows.append({"set": "reference: training fits", "samples": len(ts.rows),
                 "share clamping negatives": neg(weights[ts.rows]).mean()})
    summary = pd.DataFrame(rows)
    summary.to_csv(out.summary, sep="\t", index=False, float_format="%.4g")
    log.info("\n%s", summary.to_string())

    # image agreement in the conditioning view
    cond = torch.as_tensor(np.load(inp.conditioning))
    emb = np.load(inp.conditioning_embeddings)
    img = per[per["set"] == "image"]
    w_img = np.load([f for f in inp.samples if set_name(f) == "image"][0])
    w_unc = np.load([f for f in inp.samples if set_name(f) == "mm_uncond"][0])
    retrieved = image.retrieve(emb, np.load(inp.image_embeddings)[ts.rows, 0], ts.rows)  # metric view
    res = []
    for c in range(len(cond)):
        target = cond[c:c + 1]
        mine = img["condition"].to_numpy() == c
        s_cond = ev.image_scores(w_img[mine], target.expand(int(mine.sum()), -1, -1, -1),
                                 p.resolution, p.activation)
        s_unc = ev.image_scores(w_unc, target.expand(len(w_unc), -1, -1, -1), p.resolution,
                                p.activation)
        s_ret = ev.image_scores(weights[retrieved[c:c + 1]], target, p.resolution, p.activation)
        src = img.loc[mine, "source"].iloc[0]
        res.append({"condition": c, "source": src, "psnr_conditioned": s_cond["psnr"].mean(),
                    "ssim_conditioned": s_cond["ssim"].mean(),
                    "psnr_unconditional": s_unc["psnr"].mean(), "ssim_unconditional": s_unc["ssim"].mean(),
                    "psnr_retrieval": s_ret["psnr"].iloc[0], "ssim_retrieval": s_ret["ssim"].iloc[0],
                    "retrieved": man["name"].iloc[retrieved[c]]})
    res = pd.DataFrame(res)
    res.to_csv(out.image, sep="\t", index=False, float_format="%.5g")
    log.info("image agreement (means):\n%s", res.mean(numeric_only=True).to_string())
