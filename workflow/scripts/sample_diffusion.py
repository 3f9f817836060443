"""Sample weight vectors from a trained model: unconditional (one draw as large as the test
reference set per seed in `seeds`, draw-major, for Table 2's mean ± std) or type-conditioned
(`per_type` for each requested type, classifier-free guidance). diffusion.sample.negative_step
turns on the clamp-aware constraint (neumat.diffusion.constraints.NegativeConstraint) and
diffusion.sample.refit_steps the clamp-aware refit (neumat.diffusion.refit); rule sample_plain
drops those keys: the same draws without them. diffusion.sample.rgb_permute (unconditional
draws of `ours` and `ours_plain`) gives each sample a random channel order from its draw's
stream "rgb_permute" (neumat.diffusion.symmetry), and diffusion.sample.type_prior draws each
with a type picked as in training from the stream "type_prior", unguided
(neumat.diffusion.dataset.prior_types; column `prior_type` of samples.tsv).
diffusion.sample.keep_look (dB, unconditional draws of `ours`, with the clamp step on) draws each
sample again from its seed without the step and keeps that draw where the step moved its
metric-view render by more (neumat.diffusion.sample.keep_look; column `kept_look`).
diffusion.sample.particle_step (unconditional draws of `ours` and `ours_plain`) draws the samples
of each DDIM batch jointly, pushed apart in look (neumat.diffusion.constraints.ParticleGuidance),
and diffusion.sample.temperature (the same draws) scales their DDIM start x_T
(neumat.diffusion.schedule.RowNoise).
Unconditional draws are kept one by one in draws.partial/ beside the output
(neumat.diffusion.draws), each with its sampling time: a killed job resumes at its next draw,
timing.tsv counts every draw, and the folder goes once the output is written."""
import time
from pathlib import Path

import numpy as np
import pandas as pd

from neumat.diffusion import Sampler, dataset, draws, symmetry
from neumat.diffusion.sample import draw_keeping_look
from neumat.io.atomic import save_npy
from neumat.logs import script_logging
from neumat.seeds import seed_for

with script_logging(snakemake) as log:
    p, out = snakemake.params, snakemake.output
    # sample_plain: constraint and refit off; refit_steps at its neutral 0 is not in params
    # batch_size: a param only with particle guidance (BATCH_UNLESS_PARTICLES), else read here
    s = {"negative_step": 0.0, "refit_steps": 0,
         "batch_size": snakemake.config["diffusion"]["sample"]["batch_size"], **p.cfg["sample"]}
    sampler = Sampler(snakemake.input.model, snakemake.config["device"])
    man = dataset.read_manifest(snakemake.input.manifest)
    draw, prior, kept = None, None, []
    look = s.get("keep_look", 0.0) if s["negative_step"] else 0.0  # neutral 0: absent from params
    if p.mode == "uncond":
        n_ref, types, guidance = len(dataset.reference_rows(man)), None, 1.0
        n, requested = n_ref * len(p.seeds), [""] * (n_ref * len(p.seeds))
        draw = np.repeat(np.arange(len(p.seeds)), n_ref)
    else:
        wanted = p.cfg["types"] or sorted(dataset.training_types(man))
        dataset.require_trained(wanted, man, "config diffusion.types asks for")
        requested = [t for t in wanted for _ in range(p.cfg["per_type"])]
        n, types, guidance = len(requested), requested, s["guidance"]
    t0 = time.perf_counter()
    if draw is None:
        w = sampler.sample(n, p.seed, types, s["steps"], s["eta"], guidance, s["batch_size"],
                           s["clip"], s["negative_step"], p.activation,
                           refit_steps=s["refit_steps"])
    else:
        if s.get("type_prior"):  # neutral false: absent from params
            prior = {seed: dataset.prior_types(man, n_ref, seed_for(seed, "type_prior"))
                     for seed in p.seeds}
            log.info("each sample with a type drawn as in training, unguided "
                     "(diffusion.sample.type_prior): %d of %d typed",
                     sum(bool(t) for ts in prior.values() for t in ts), n)

        def one_draw(seed):
            t = time.perf_counter()
            # look: the same seed without the clamp step, kept where the step moved the look
            w, k = draw_keeping_look(sampler, n_ref, seed, s, p.activation,
                                     prior[seed] if prior else None, guidance, look,
                                     p.cfg.get("look_resolution"))
            if s.get("rgb_permute"):  # neutral false: absent from params
                w = symmetry.random_channels(w, seed_for(seed, "rgb_permute"))
            # its own sampling time, kept with it: timing.tsv then counts every draw the
            # output holds, those a resumed job read back included
            d = {"w": w, "seconds": np.array(time.perf_counter() - t)}
            return d if k is None else {**d, "kept": k}

        # a draw depends on its seed, the model, the manifest (its reference size, the types
        # drawn as in training) and the settings
        cache = draws.DrawCache(Path(out.weights).with_name("draws.partial"), draws.fingerprint(
            [snakemake.input.model, snakemake.input.manifest],
            {"sample": s, "look": look, "look_resolution": p.cfg.get("look_resolution"),
             "activation": p.activation, "device": str(sampler.device)}))  # resolved: auto
        done = [cache.get(seed, lambda seed=seed: one_draw(seed)) for seed in p.seeds]
        w = np.concatenate([d["w"] for d in done])
        kept = [d["kept"] for d in done if "kept" in d]
        if s.get("rgb_permute"):
            log.info("each sample in a random RGB channel order (diffusion.sample.rgb_permute)")
        if s.get("particle_step"):  # neutral 0: absent from params
            log.info("particle guidance (diffusion.sample.particle_step %g) over batches of %d",
                     s["particle_step"], s["batch_size"])
        if s.get("temperature", 1.0) != 1.0:  # neutral 1: absent from params
            log.info("DDIM start x_T scaled by diffusion.sample.temperature %g", s["temperature"])
        if look:
            log.info("keep look (diffusion.sample.keep_look %g dB): %d of %d samples keep "
                     "their draw without the clamp step (each drawn again from its seed)", look,
                     int(np.sum(kept)), n)
    dt = time.perf_counter() - t0
    if draw is not None:  # every draw's own time, resumed ones included
        dt = draws.seconds(done, dt)
    save_npy(out.weights, w.astype(np.float32))
    table = pd.DataFrame({"sample": np.arange(n), "type": requested})
    if draw is not None:
        table["draw"] = draw
    if prior is not None:
        table["prior_type"] = [t for seed in p.seeds for t in prior[seed]]
    if kept:
        table["kept_look"] = np.concatenate(kept)
    table.to_csv(out.table, sep="\t", index=False)
    pd.DataFrame([{"samples": n, "seconds": dt, "samples_per_second": n / max(dt, 1e-9),
                   "steps": s["steps"], "eta": s["eta"], "guidance": guidance,
                   "negative_step": s["negative_step"], "refit_steps": s["refit_steps"]}]).to_csv(
        out.timing, sep="\t", index=False, float_format="%.6g")
    log.info("%d samples (%s) in %.2f s: %.1f samples/s", n, p.mode, dt, n / max(dt, 1e-9))
    if draw is not None:
        cache.clear()  # written: the kept draws are no longer needed
