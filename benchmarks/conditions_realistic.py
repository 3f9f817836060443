"""Text and image conditioning on realistic weights without the fitting stage: the dataset of
`diffusion_realistic.py` (the 100 published NBRDF fits of MERL, Sztrajman et al. 2021, and
their exact RGB permutations; 95 train / 5 test sources, 570 / 30 fields) with the catalogue's
descriptions (permutations drop their colour words, as AugMERL does).

Differences from the workflow (say so when quoting numbers): no PCA interpolations, fits not
initialised from a common template, 5 test sources only.

Usage (each step its own process):
  python benchmarks/conditions_realistic.py encoder --objective weights --steps 3000
  python benchmarks/conditions_realistic.py encoder --objective text --steps 3000
  python benchmarks/conditions_realistic.py train --objective weights --steps 2000 --batch 64
  python benchmarks/conditions_realistic.py evaluate --objective weights
Outputs under benchmarks/out/conditions_realistic/.
"""

import argparse
import importlib.util
import json
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from neumat.conditions import evaluate as ev
from neumat.conditions import image, text
from neumat.data import catalog
from neumat.diffusion import DenoiserConfig, Sampler, ScheduleConfig, TrainConfig, dataset, train
from neumat.diffusion.sample import sample
from neumat.io import modelfile
from neumat.machine import describe as host_line
from neumat.metrics import distances
from neumat.render import sphere

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks/out/conditions_realistic"
_spec = importlib.util.spec_from_file_location("dr", ROOT / "benchmarks/diffusion_realistic.py")
dr = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(dr)
UNSEEN = ["green metal", "red plastic", "highly specular material", "blue fabric", "white paint",
          "yellow paint", "gold metal"]


def build():
    man, weights = dr.build()
    cat = pd.read_csv(ROOT / "config/merl_materials.tsv", sep="\t", keep_default_na=False)
    cat = cat.set_index("name")
    src = man["name"].str.split("@").str[0]
    desc = cat.loc[src, "description"].to_numpy()
    cols = cat.loc[src, "colours"].to_numpy()
    man["description"] = [d if op == "original" else catalog.drop_colours(d, c)
                          for d, c, op in zip(desc, cols, man["operation"])]
    return man, weights


def machine():
    """The CPU line every benchmark prints (neumat.machine), with the torch threads."""
    return f"{host_line()}, torch threads {torch.get_num_threads()}"


def encoder_cfg(a):
    return image.ImageEncoderConfig(steps=a.steps, objective=a.objective)


def cmd_encoder(a):
    man, weights = build()
    tr, te = dataset.training_rows(man, "ours"), dataset.reference_rows(man)
    cfg = encoder_cfg(a)
    OUT.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    views = image.render_views(weights[tr], cfg.resolution, cfg.n_lights)
    t_render = time.perf_counter() - t0
    txt = text.embed(list(man["description"].iloc[tr])) if cfg.objective == "text" else None
    b = image.train(views, weights[tr], cfg, a.seed, txt)
    torch.save(b, OUT / f"encoder_{cfg.objective}.pt")
    enc = image.load(b)
    e_tr, e_te = image.embed_fields(enc, weights[tr]), image.embed_fields(enc, weights[te])
    types_tr = man["type"].iloc[tr].to_numpy()
    res = {"objective": cfg.objective, "steps": cfg.steps, "render_s": t_render,
           "train_s": b["train_seconds"], "machine": machine()}
    for name, e, rows in (("train", e_tr, tr), ("test", e_te, te)):
        q = e[:, 0]
        for k in range(1, e.shape[1]):  # identification across each other light
            d = ((q[:, None] - e[None, :, k]) ** 2).sum(-1)
            res.setdefault(f"{name}_identification", []).append(float((d.argmin(1) == np.arange(len(q))).mean()))
        res[f"{name}_identification"] = float(np.mean(res[f"{name}_identification"]))
        dt = ((q[:, None] - e_tr[None, :, 0]) ** 2).sum(-1)
        if name == "train":
            np.fill_diagonal(dt, np.inf)
        own = man["type"].iloc[rows].to_numpy()
        ok = np.isin(own, types_tr)  # types some training material has
        res[f"{name}_nearest_type_hit"] = float((types_tr[dt.argmin(1)] == own)[ok].mean())
        res[f"{name}_materials_with_a_training_type"] = int(ok.sum())
    print(json.dumps(res, indent=1))
    json.dump(res, open(OUT / f"encoder_{cfg.objective}.json", "w"), indent=1)


def cmd_train(a):
    man, weights = build()
    names = dataset.class_names(man["type"])
    rows = dataset.training_rows(man, "ours")
    enc = image.load(torch.load(OUT / f"encoder_{a.objective}.pt", weights_only=True))
    t0 = time.perf_counter()
    txt = text.embed(list(man["description"]))
    img = image.embed_fields(enc, weights)
    t_emb = time.perf_counter() - t0
    np.save(OUT / "text.npy", txt)
    np.save(OUT / f"image_{a.objective}.npy", img)
    m, s, t, _ = dr.settings(a.steps, a.batch)
    t["cond_drop"] = a.cond_drop
    mcfg = DenoiserConfig(**m, n_classes=len(names), vector_conditions={"text": 384, "image": img.shape[-1]})
    b = train(weights[rows], dataset.labels(man["type"].iloc[rows], names), names, mcfg,
              ScheduleConfig(**s), TrainConfig(**t), OUT / f"multimodal_{a.objective}.pt",
              OUT / "mm.ckpt.pt", a.seed, "cpu", vectors={"text": txt[rows], "image": img[rows]})
    print(json.dumps({"embed_s": t_emb, "train_s": b["train_seconds"], "steps": a.steps,
                      "batch": t["batch_size"], "n_train": len(rows), "machine": machine()}))


def summarise(name, want, colours, samples, ts, seed):
    near = ts.nearest(samples)
    hit = near["nearest_type"].to_numpy() == want
    typed = ts.scorable(want)
    rgb = ev.mean_colour(sphere.render_fields(np.nan_to_num(samples), 64))
    cm = np.array([bool(c) and ev.colour_matches(x, c) for x, c in zip(rgb, colours)])
    has_c = np.array([bool(c) for c in colours])
    return {"set": name, "samples": len(samples),
            "type hits": float(hit[typed].mean()) if typed.any() else np.nan,
            "samples with a training type": int(typed.sum()),
            "colour match": float(cm[has_c].mean()) if has_c.any() else np.nan,
            "coloured samples": int(has_c.sum()),
            "median BRDF-L1 to nearest training": float(near["brdf_l1"].median()),
            "share clamping negatives": float(ev.negative_share(samples, 20000, seed, "relu").mean())}


def cmd_evaluate(a):
    man, weights = build()
    OUT.mkdir(parents=True, exist_ok=True)
    ts = ev.TrainingSet(weights, man, distances.brdf_sample(20000, a.seed), "relu")
    smp = dict(dr.settings(1)[3])
    smp["steps"] = a.sample_steps or smp["steps"]
    sampler = Sampler(modelfile.load(OUT / f"multimodal_{a.objective}.pt"), "cpu")
    img = np.load(OUT / f"image_{a.objective}.npy")
    te = dataset.reference_rows(man)
    tests = man.iloc[te].drop_duplicates("description")
    # descriptions whose type some training material has first: only they can score a hit
    tests = tests.iloc[np.argsort(~ts.scorable(tests["type"]), kind="stable")]
    ns = int(ts.scorable(tests["type"]).sum())
    prompts = list(tests["description"]) + UNSEEN
    ptypes = np.array(list(tests["type"]) + [""] * len(UNSEEN))
    pcols = [ev.colour_of(q) for q in prompts]
    k, g = a.per, a.guidance
    rep = lambda x: np.repeat(np.asarray(x), k, 0)  # noqa: E731
    nt = len(tests)
    print(f"{len(prompts)} prompts; {nt} test descriptions, {ns} with a type in training: "
          f"{list(tests['description'][:ns])}")
    rows, t0 = [], time.perf_counter()
    ptxt = text.embed(prompts)
    s_text = sample(sampler, len(prompts) * k, a.seed, {"text": rep(ptxt)}, {"text": g}, smp["steps"])
    rows.append(summarise("text (all prompts)", rep(ptypes), rep(pcols), s_text, ts, a.seed))
    rows.append(summarise("text (test descriptions, type in training)", rep(ptypes[:ns]),
                          rep(pcols[:ns]), s_text[:ns * k], ts, a.seed))
    rows.append(summarise("text (unseen prompts)", rep(ptypes[nt:]), rep(pcols[nt:]), s_text[nt * k:], ts, a.seed))
    s_type = sample(sampler, ns * k, a.seed + 1, {"type": list(rep(ptypes[:ns]))}, {"type": g}, smp["steps"])
    rows.append(summarise("type (same descriptions' types)", rep(ptypes[:ns]), rep(pcols[:ns]), s_type, ts, a.seed))
    s_unc = sample(sampler, len(prompts) * k, a.seed + 2, {}, {}, smp["steps"])
    rows.append(summarise("unconditional vs the same descriptions", rep(ptypes[:ns]), rep(pcols[:ns]),
                          s_unc[:ns * k], ts, a.seed))
    rows.append(summarise("unconditional vs all prompts", rep(ptypes), rep(pcols), s_unc, ts, a.seed))
    # image: every test-split field (5 sources x 6 permutations) in the metric view
    s_img = sample(sampler, len(te) * k, a.seed + 3, {"image": rep(img[te, 0])}, {"image": g}, smp["steps"])
    rows.append(summarise("image (test split)", rep(man["type"].iloc[te]), [""] * len(te) * k, s_img, ts, a.seed))
    ref_near = ts.nearest(weights[te])
    own = man["type"].iloc[te].to_numpy()
    ok = ts.scorable(own)
    rows.append({"set": "reference: real test split", "samples": len(te),
                 "type hits": float((ref_near["nearest_type"].to_numpy() == own)[ok].mean()),
                 "samples with a training type": int(ok.sum()),
                 "median BRDF-L1 to nearest training": float(ref_near["brdf_l1"].median()),
                 "share clamping negatives": float(ev.negative_share(weights[te], 20000, a.seed, "relu").mean())})
    rows.append({"set": "reference: training fits", "samples": len(ts.rows),
                 "share clamping negatives": float(ev.negative_share(weights[ts.rows], 20000, a.seed, "relu").mean())})
    summ = pd.DataFrame(rows)
    print(summ.to_markdown(index=False, floatfmt=".3g"))
    summ.to_csv(OUT / f"summary_{a.objective}.tsv", sep="\t", index=False)

    # image agreement in the metric view: conditioned vs unconditional vs retrieval
    R = 64
    targets = sphere.render_fields(weights[te], R)
    retrieved = ts.rows[((img[te, 0][:, None] - img[ts.rows, 0][None]) ** 2).sum(-1).argmin(1)]
    res = []
    for i in range(len(te)):
        tgt = targets[i:i + 1]
        c = ev.image_scores(s_img[i * k:(i + 1) * k], tgt.expand(k, -1, -1, -1), R, "relu")
        u = ev.image_scores(s_unc, tgt.expand(len(s_unc), -1, -1, -1), R, "relu")
        r = ev.image_scores(weights[retrieved[i:i + 1]], tgt, R, "relu")
        res.append({"psnr_conditioned": c["psnr"].mean(), "psnr_retrieval": r["psnr"][0],
                    "psnr_unconditional": u["psnr"].mean(), "ssim_conditioned": c["ssim"].mean(),
                    "ssim_retrieval": r["ssim"][0], "ssim_unconditional": u["ssim"].mean()})
    res = pd.DataFrame(res)
    print(res.mean().to_frame("mean over 30 test fields").T.to_markdown(floatfmt=".4g"))
    res.to_csv(OUT / f"image_{a.objective}.tsv", sep="\t", index=False)

    # guidance sweep
    k = a.sweep_per
    sweep = []
    te_ok = te[ts.scorable(man["type"].iloc[te])]
    for name, cond, want in (("type", {"type": list(rep(ptypes[:ns]))}, rep(ptypes[:ns])),
                             ("text", {"text": rep(ptxt[:ns])}, rep(ptypes[:ns])),
                             ("image", {"image": rep(img[te_ok, 0])}, rep(man["type"].iloc[te_ok]))):
        for sc in a.scales:
            w = sample(sampler, len(want), a.seed + 4, cond, {name: sc}, smp["steps"])
            near = ts.nearest(w)
            ok = ts.scorable(want)
            sweep.append({"modality": name, "scale": sc, "samples": len(w),
                          "samples with a training type": int(ok.sum()),
                          "type hits": float((near["nearest_type"].to_numpy() == want)[ok].mean()),
                          "median BRDF-L1": float(near["brdf_l1"].median()),
                          "share clamping negatives": float(ev.negative_share(w, 20000, a.seed, "relu").mean())})
    sweep = pd.DataFrame(sweep)
    print(sweep.to_markdown(index=False, floatfmt=".3g"))
    sweep.to_csv(OUT / f"sweep_{a.objective}.tsv", sep="\t", index=False)
    print(f"evaluation {time.perf_counter() - t0:.0f} s ({smp['steps']} DDIM steps, guidance {g}) "
          f"on {machine()}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd", choices=["encoder", "train", "evaluate"])
    ap.add_argument("--objective", choices=image.OBJECTIVES, default="weights")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=None)
    ap.add_argument("--seed", type=int, default=7000)
    ap.add_argument("--per", type=int, default=8, help="samples per condition")
    ap.add_argument("--guidance", type=float, default=2.0)
    ap.add_argument("--cond-drop", type=float, default=0.5,
                    help="per-modality dropout in training (the measured run used 0.1)")
    ap.add_argument("--sample-steps", type=int, default=None, help="DDIM steps (default: config)")
    ap.add_argument("--sweep-per", type=int, default=2, help="samples per condition in the sweep")
    ap.add_argument("--scales", type=float, nargs="+", default=[0.0, 1.0, 2.0, 4.0])
    a = ap.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    {"encoder": cmd_encoder, "train": cmd_train, "evaluate": cmd_evaluate}[a.cmd](a)
