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
whether it was `constrained`, its `render_psnr` and whether it `clamps`."""
import time

import numpy as np
import pandas as pd
import torch

from neumat.conditions import image, starts, text
from neumat.diffusion import Sampler, dataset
from neumat.diffusion.sample import sample
from neumat.io.atomic import save_npy
from neumat.logs import script_logging
from neumat.render import sphere
from neumat.seeds import seed_for


def image_conditions(inp, p, enc, weights, man):
    """Test-split typed materials (evenly picked) and user images -> table, embeddings (M, D),
    conditioning images (M, R, R, 3) linear HDR in the metric view."""
    test = dataset.reference_rows(man)
    test = test[man["type"].iloc[test].to_numpy() != ""]
    k = p.test_images or len(test)
    test = test[np.unique(np.linspace(0, len(test) - 1, min(k, len(test))).round().astype(int))]
    emb = [image.embed(enc, sphere.render_fields(weights[test], enc.cfg.resolution, p.activation))]
    imgs = [sphere.render_fields(weights[test], p.resolution, p.activation).numpy()]
    table = pd.DataFrame({"source": man["name"].iloc[test].to_numpy(), "id": test,
                          "type": man["type"].iloc[test].to_numpy()})
    paths = list(inp.images)
    if paths:
        emb.append(np.concatenate([image.embed(enc, image.load_image(f, enc.cfg.resolution)[None])
                                   for f in paths]))
        imgs.append(np.stack([image.load_image(f, p.resolution) for f in paths]))
        table = pd.concat([table, pd.DataFrame({"source": paths, "id": -1, "type": ""})],
                          ignore_index=True)
    return table, np.concatenate(emb), np.concatenate(imgs).astype(np.float32)


def training_set(inp):
    """(weights, manifest, rows): the NeuMERL fields and ours's training rows, conditions_eval's
    retrieval set, from which the type and text starts are drawn."""
    weights = np.load(inp.weights)
    man = dataset.read_manifest(inp.manifest, len(weights))
    return weights, man, dataset.training_rows(man, "ours")


def trained_types(inp, conds, log):
    """The rows of `conds` whose type some training material (training_set's rows) has; all of
    them, with a warning, when none has."""
    have = dataset.training_types(dataset.read_manifest(inp.manifest))
    ok = conds["type"].isin(have).to_numpy()
    if not ok.any():
        log.warning("mm_type: no test prompt's type is among the training materials' types: "
                    "all %d drawn from noise, their class embeddings untrained", len(conds))
        return conds
    if not ok.all():
        log.info("mm_type: %d of %d test prompts have a type no training material has (%s): not "
                 "drawn, the model never saw it", int((~ok).sum()), len(conds),
                 ", ".join(sorted(set(conds["type"][~ok]))))
    return conds[ok]


def type_starts(inp, conds, k, seed, log):
    """(start vectors (len(conds) k, 675), conds with a `start` column): for each of a
    condition's k samples a training material of its type (training_set), drawn with `seed`;
    NaN rows (from noise) where training has no such type."""
    weights, man, rows = training_set(inp)
    picks = starts.type_picks(conds["type"], rows, man["type"].iloc[rows].to_numpy(), k,
                              np.random.default_rng(seed))
    got = picks.reshape(-1)
    start = np.where(got[:, None] >= 0, weights[np.maximum(got, 0)], np.nan)
    conds = conds.assign(start=[",".join(man["name"].iloc[r] for r in g) if (g >= 0).all() else ""
                                for g in picks])
    log.info("mm_type: %d of %d samples start from a training material of their type",
             int((got >= 0).sum()), len(got))
    return start, conds


def text_starts(inp, conds, emb, k, vote, activation, log):
    """(start vectors (len(conds) k, 675), conds with `start` (and `voted_type`) columns): for
    each prompt embedding (rows of `emb`) its k nearest training materials (training_set) by
    description embedding (cosine: text.embed writes unit vectors; conditions/text.npy is in
    manifest order), sample i from the i-th nearest; ties (shared descriptions) in row order.
    With `vote` (conditions.text.start_match) only materials of the type voted by the prompt's
    nearest typed descriptions (text.vote_types, vote size by text.choose_votes) are drawn,
    those whose metric-view colour matches the prompt's colour word first."""
    weights, man, rows = training_set(inp)
    library = np.load(inp.text)[rows]
    if vote:
        got, voted, size, acc = text.training_starts(emb, library, weights, man, rows,
                                                     list(conds["colour"]), k, activation)
        log.info("text: type vote over the %d nearest typed descriptions (leave-source-out "
                 "accuracy on the training originals by vote size: %s)", size,
                 ", ".join(f"{n}: {a:.3f}" for n, a in acc.items()))
        conds = conds.assign(voted_type=voted)
    else:  # the nearest of any type; fewer rows than k: cycled
        sim = emb.astype(np.float64) @ library.astype(np.float64).T
        got = rows[text.typed_starts(sim, np.full(len(rows), ""), np.full(len(sim), ""), k)]
    conds = conds.assign(start=[",".join(man["name"].iloc[g]) for g in got])
    log.info("text: each prompt's %d samples start from its %d nearest training descriptions%s",
             k, k, " of its voted type, those of its colour word first" if vote else "")
    return weights[got.reshape(-1)], conds


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
        weights = np.load(inp.weights)
        man = dataset.read_manifest(inp.manifest, len(weights))
        conds, emb, imgs = image_conditions(inp, p, image.load(inp.encoder), weights, man)
        save_npy(out.conditioning, imgs)
        save_npy(out.embeddings, emb.astype(np.float32))
        conditions = {"image": np.repeat(emb, kd, 0)}
        if strength < 1:  # start from the retrieved training material (SDEdit)
            rows = dataset.training_rows(man, "ours")  # conditions_eval's retrieval set
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
                start, conds = text_starts(inp, conds, emb, k, getattr(p, "start_match", False),
                                           p.activation, log)
        elif p.mode == "mm_type":
            conds = trained_types(inp, conds, log)
            conditions = {"type": list(np.repeat(conds["type"].to_numpy(), k))}
            if strength < 1:
                start, conds = type_starts(inp, conds, k, seed_for(p.seed, "type_start"), log)
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
