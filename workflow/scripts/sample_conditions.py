"""Sample the multimodal model under one condition: text prompts ('text'), conditioning images
('image': test-split metric-view renders and config images), or the same-run baselines for the
test prompts: their types ('mm_type') and no condition ('mm_uncond'). Images with
`conditions.image.strength` < 1 start from their retrieved training material (nearest
metric-view embedding) noised to that fraction of the schedule; with
`conditions.image.render_step` > 0 each image's samples are also pulled toward its metric-view
render (render guidance); with `conditions.image.refiner` the retrieved material is refined by
the refiner model (rule train_refiner), without the image condition. `mm_type` draws the test prompts
whose type some training material has (guidance_sweep's choice): the model never saw the other
types, so their class embeddings are untrained and no such type can be asked of it (when no
prompt's type is in training, e.g. a tiny split, all of them, from noise, with a warning). With
`conditions.type.strength` < 1 each sample starts from a training material of its type (drawn
with the seed's stream "type_start"), refined by the refiner with `conditions.type.refiner`. Text prompts with
`conditions.text.strength` < 1 start from the training materials whose descriptions are nearest
(sample i of a prompt from the i-th nearest; with `conditions.text.start_match` only those of the
type the nearest descriptions vote for, those of the prompt's colour first), refined with
`conditions.text.refiner`. Images with `conditions.image.candidates` n > 1 draw n times their
samples and keep, per image, the best by the PSNR of their metric-view render against it, less
`conditions.image.clamp_penalty` dB where the field clamps negatives (best of n). With
`conditions.image.unconstrained_candidates` m > 0 each image draws m times its samples more
without the clamp constraint (`diffusion.sample.negative_step` 0, seed stream "unconstrained"),
and best of n chooses among all: materials that clamp by nature (chrome) keep their look, at the
clamp penalty. samples.tsv names each kept draw (`candidate`, the constrained draws first),
whether it was `constrained`, its `render_psnr` and whether it `clamps`. The conditions and
starts: `neumat.conditions.sampling`; best of n: `neumat.conditions.image`; the draws:
`neumat.diffusion.sample.sample`."""
import time

import numpy as np
import pandas as pd
import torch

from neumat.conditions import image, sampling
from neumat.diffusion import Sampler, dataset
from neumat.diffusion.sample import sample
from neumat.io.atomic import save_npy
from neumat.logs import script_logging
from neumat.seeds import seed_for


def training_set(inp):
    """(weights, manifest, rows): the NeuMERL fields and ours's training rows, conditions_eval's
    retrieval set, from which the type and text starts are drawn."""
    weights = np.load(inp.weights)
    man = dataset.read_manifest(inp.manifest, len(weights))
    return weights, man, dataset.training_rows(man, "ours")


with script_logging(snakemake) as log:
    p, inp, out = snakemake.params, snakemake.input, snakemake.output
    s, k = {**p.sample, "batch_size": snakemake.config["diffusion"]["sample"]["batch_size"]}, p.per_prompt  # batch_size: not a param
    refine = getattr(p, "refiner", False)  # the starts refined by the floor-free model
    sampler = Sampler(inp.refiner[0] if refine else inp.model, snakemake.config["device"])
    start, strength = None, getattr(p, "strength", 1.0)
    targets, render_step = None, getattr(p, "render_step", 0.0)  # absent at its neutral 0
    n_cand = getattr(p, "candidates", 1) if p.mode == "image" else 1
    n_free = getattr(p, "unconstrained_candidates", 0) if p.mode == "image" else 0
    kd = k * (n_cand + n_free)  # draws per condition: the constrained ones first
    if p.mode == "image":
        weights, man, rows = training_set(inp)  # rows: conditions_eval's retrieval set
        conds, emb, imgs = sampling.image_conditions(weights, man, p.test_images, inp.images,
                                                     image.load(inp.encoder), p.resolution,
                                                     p.activation)
        save_npy(out.conditioning, imgs)
        save_npy(out.embeddings, emb.astype(np.float32))
        conditions = {"image": np.repeat(emb, kd, 0)}
        if strength < 1:  # start from the retrieved training material (SDEdit)
            got = image.retrieve(emb, np.load(inp.image_embeddings)[rows, 0], rows)
            conds["start"] = man["name"].iloc[got].to_numpy()
            start = weights[np.repeat(got, kd)]
        if render_step:  # render guidance toward each sample's own conditioning image
            targets = np.repeat(imgs, kd, 0)
            log.info("render guidance, step %g, toward %d conditioning images", render_step,
                     len(imgs))
    else:
        conds = pd.read_csv(inp.prompts, sep="\t", keep_default_na=False)
        if p.mode != "text":  # baselines for the test-split descriptions only
            conds = conds[conds["kind"] == "test"]
        if p.mode == "text":
            emb = np.load(inp.prompt_embeddings)[conds.index.to_numpy()]
            conditions = {"text": np.repeat(emb, k, 0)}
            if strength < 1:
                weights, man, rows = training_set(inp)
                start, conds = sampling.text_starts(weights, man, rows, np.load(inp.text)[rows],
                                                    conds, emb, k,
                                                    getattr(p, "start_match", False), p.activation)
        elif p.mode == "mm_type":
            conds = sampling.trained_conditions(conds, dataset.read_manifest(inp.manifest))
            conditions = {"type": list(np.repeat(conds["type"].to_numpy(), k))}
            if strength < 1:
                start, conds = sampling.type_starts(*training_set(inp), conds, k,
                                                    seed_for(p.seed, "type_start"))
        else:
            conditions = {}
    if refine:  # unconditionally: the refiner takes no condition
        conditions = {}
        log.info("refining the %s with %s",
                 "retrieved materials" if p.mode == "image" else "starts", inp.refiner[0])
    table = conds.reset_index(drop=True).loc[np.repeat(np.arange(len(conds)), k)]
    table.insert(0, "condition", np.repeat(np.arange(len(conds)), k))
    table.insert(0, "sample", np.arange(len(table)))
    name = "type" if p.mode == "mm_type" else p.mode
    guidance = {name: p.guidance[name]} if name in p.guidance and conditions else {}
    t0 = time.perf_counter()

    def draw(idx, seed, start, strength, negative_step=s["negative_step"]):
        """The samples `idx` (a slice of the table's conditions and targets)."""
        cond = {m: (v[idx] if isinstance(v, np.ndarray) else [v[i] for i in idx])
                for m, v in conditions.items()}
        return sample(sampler, len(idx), seed, cond, guidance, s["steps"], s["eta"],
                      s["batch_size"], s["clip"], negative_step=negative_step,
                      activation=p.activation, start=start, strength=strength,
                      refit_steps=s.get("refit_steps", 0),  # neutral 0: not in params
                      render_targets=None if targets is None else torch.as_tensor(targets[idx]),
                      render_step=render_step)

    everyone = np.arange(len(table))
    if n_cand + n_free > 1:  # best of n (image conditions: start is never NaN)
        w, free = image.draw_candidates(
            lambda idx, seed, neg: draw(idx, seed, None if start is None else start[idx],
                                        strength, neg),
            len(conds), k, n_cand, n_free, p.seed, s["negative_step"])
        keep, psnr, clamps = image.choose(w, imgs, k, p.angles, p.seed, p.activation,
                                          p.clamp_penalty)
        w = w[keep]
        table = table.assign(candidate=keep % kd, constrained=~free[keep],
                             render_psnr=psnr[keep].round(3), clamps=clamps[keep])
        log.info("best of %d: kept %d of %d draws by render PSNR (%.2f dB kept, %.2f dB all), "
                 "less %g dB for clamping (%.3f of kept clamp, %.3f of all)", n_cand + n_free,
                 len(w), len(psnr), psnr[keep].mean(), psnr.mean(), p.clamp_penalty,
                 clamps[keep].mean(), clamps.mean())
        if n_free:
            log.info("%d of the %d kept draws (%d of all %d) without the clamp constraint",
                     int(free[keep].sum()), len(keep), int(free.sum()), len(free))
    elif start is None or not np.isnan(start).any():
        w = draw(everyone, p.seed, start, strength)
    else:  # types no training material has: those samples from noise, on their own stream
        noise = np.isnan(start).any(1)
        w = np.zeros((len(table), start.shape[1]), np.float32)
        if (~noise).any():
            w[~noise] = draw(everyone[~noise], p.seed, start[~noise], strength)
        w[noise] = draw(everyone[noise], seed_for(p.seed, "from_noise"), None, 1.0)
    dt = time.perf_counter() - t0
    save_npy(out.weights, w.astype(np.float32))
    table.to_csv(out.table, sep="\t", index=False)
    pd.DataFrame([{"samples": len(table), "draws": len(conds) * kd, "seconds": dt,
                   "samples_per_second": len(table) / max(dt, 1e-9), "steps": s["steps"],
                   "eta": s["eta"], "guidance": guidance.get(name, 1.0),
                   "strength": strength}]).to_csv(
        out.timing, sep="\t", index=False, float_format="%.6g")
    log.info("%d samples (%s) in %.2f s", len(table), p.mode, dt)
