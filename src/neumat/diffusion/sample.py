"""Sampling with any subset of the type, text and image conditions (M3ashy §3.3, §4.4).

Guidance with several conditions is compositional classifier-free guidance (Liu et al. 2022,
"Compositional Visual Generation with Composable Diffusion Models"):
    out = u + sum_m s_m (c_m - u),
with u the all-null output and c_m the output given condition m alone. Each modality has its
own scale; with one modality this is ordinary CFG (`schedule.guided`). All passes run as one
batch. Every scale 1 means no guidance: one pass of the model given all the conditions. The model was trained with every condition dropped independently, so each c_m and u are
in-distribution.

Library entry point for the workflow and the CLI:
    sample(sampler, n, seed, conditions={"type": "metal", "text": "red plastic",
                                        "image": "ref.png"}, guidance={"type": 2, ...},
           image_encoder="conditions/image_encoder.pt")

The clamp-aware constraint of every DDIM step (diffusion.sample.negative_step) is in
`neumat.diffusion.constraints`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from neumat import nbrdf
from neumat.diffusion.constraints import RenderConstraint, chain, constraint_for
from neumat.diffusion.refit import clamp_refit
from neumat.diffusion.schedule import RowNoise
from neumat.diffusion.train import Sampler
from neumat.seeds import seed_for

def guided_multi(model, cond: dict, scales: dict) -> Callable:
    """Per-modality classifier-free guidance: predict(x_t, t) -> guided model output."""
    names = [k for k in cond if scales.get(k, 1.0) != 0.0]
    if not names:
        return lambda x, t: model(x, t, None)
    if all(scales.get(k, 1.0) == 1.0 for k in names):  # no guidance: the joint conditional
        # model p(x | c_1, ..., c_m), not the product of the single-condition models that the
        # composition gives at scale 1 when m > 1
        return lambda x, t: model(x, t, {k: cond[k] for k in names})

    def predict(x, t):
        b, m = x.shape[0], len(names)
        both = {k: torch.cat([cond[k]] * (m + 1)) for k in names}
        # block j < m keeps only condition names[j]; the last block is all-null
        drop = {k: torch.ones((m + 1) * b, dtype=torch.bool, device=x.device) for k in names}
        for j, k in enumerate(names):
            drop[k][j * b:(j + 1) * b] = False
        out = model(x.repeat(m + 1, 1), t.repeat(m + 1), both, drop)
        u = out[m * b:]
        return u + sum(scales.get(k, 1.0) * (out[j * b:(j + 1) * b] - u)
                       for j, k in enumerate(names))

    return predict


def keep_look(stepped: np.ndarray, free: np.ndarray, db: float, resolution: int,
              activation: str = "relu") -> tuple[np.ndarray, np.ndarray]:
    """(weights, kept free): each sample's draw under the clamp step (`stepped`) unless the step
    changed its look, i.e. unless the PSNR (sRGB, data range 1) between the metric-view renders
    of it and of the draw from the same seed without the step (`free`) is below `db`; then the
    free draw (diffusion.sample.keep_look). Fields that clamp by nature (mirrors) are pulled to
    another look by the step; the others lose only their spurious negative values."""
    from neumat.conditions.evaluate import render_psnr
    from neumat.render import sphere
    if stepped.shape != free.shape:
        raise ValueError(f"keep_look: {stepped.shape} stepped draws against {free.shape} free ones")
    kept = render_psnr(stepped, sphere.render_fields(free, resolution, activation), resolution,
                       activation) < db
    return np.where(kept[:, None], free, stepped), kept


def draw_keeping_look(sampler, n: int, seed: int, s: dict, activation: str = "relu",
                      types: list[str] | None = None, guidance: float = 1.0, look: float = 0.0,
                      look_resolution: int | None = None,
                      offset: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
    """(weights, kept or None): n draws of `sampler` (a Sampler, or anything with its `sample`)
    from `seed`, rows offset ... offset + n - 1, under the diffusion.sample settings `s` (steps,
    eta, batch_size, clip, negative_step; refit_steps and particle_step 0, temperature 1 where
    absent). With `look` > 0 and the clamp step on, keep_look: the same rows drawn again without
    the step, kept where the step moved the metric-view render by more than `look` dB. Shared by rule
    sample_uncond and `neumat sample`, so the command draws as the workflow does."""
    def at(step):
        return sampler.sample(n, seed, types, s["steps"], s["eta"], guidance, s["batch_size"],
                              s["clip"], step, activation, refit_steps=s.get("refit_steps", 0),
                              particle_step=s.get("particle_step", 0.0), offset=offset,
                              temperature=s.get("temperature", 1.0))
    w = at(s["negative_step"])
    if not (look and s["negative_step"]):
        return w, None
    return keep_look(w, at(0.0), look, look_resolution, activation)


def _per_sample(value, n: int, what: str) -> list:
    values = [value] * n if isinstance(value, (str, type(None))) else list(value)
    if len(values) != n:
        raise ValueError(f"{len(values)} {what} values for {n} samples")
    return values


def encode_conditions(sampler: Sampler, n: int, conditions: dict,
                      image_encoder=None) -> dict[str, torch.Tensor]:
    """Condition values -> the model's tensors (n rows each).

    'type': a type name or n of them; 'text': a prompt, n prompts, or (n, 384) embeddings;
    'image': an image path, (D,) / (n, D) embeddings, or (n, H, W, 3) linear HDR renders at
    the encoder's resolution (paths and renders need `image_encoder`, a bundle or its file)."""
    have = set(sampler.model.cond_names)
    unknown = set(conditions) - have
    if unknown:
        raise ValueError(f"condition(s) {sorted(unknown)} not in this model ({sorted(have)})")
    out = {}
    for name, value in conditions.items():
        if value is None:
            continue
        if name == "type":
            out[name] = sampler.labels_of(_per_sample(value, n, "type"))
        elif name == "text" and (isinstance(value, str) or
                                 (len(value) and isinstance(value[0], str))):
            from neumat.conditions import text
            out[name] = torch.from_numpy(text.embed(_per_sample(value, n, "text")))
        elif name == "image" and (isinstance(value, (str, bytes)) or hasattr(value, "__fspath__")):
            out[name] = torch.from_numpy(_image_embedding(image_encoder, value, n))
        else:
            arr = np.asarray(value, dtype=np.float32)
            if name == "image" and arr.ndim == 4:
                from neumat.conditions import image
                arr = image.embed(_encoder(image_encoder), arr)
            if arr.ndim == 1:
                arr = np.broadcast_to(arr, (n, arr.shape[0]))
            if arr.shape[0] != n:
                raise ValueError(f"{arr.shape[0]} {name} embeddings for {n} samples")
            out[name] = torch.from_numpy(np.ascontiguousarray(arr))
    return out


def _encoder(image_encoder):
    from neumat.conditions import image
    if image_encoder is None:
        raise ValueError("image conditions given as images need the image encoder "
                         "(conditions/image_encoder.pt)")
    return image_encoder if isinstance(image_encoder, torch.nn.Module) else image.load(image_encoder)


def _image_embedding(image_encoder, path, n: int) -> np.ndarray:
    from neumat.conditions import image
    enc = _encoder(image_encoder)
    e = image.embed(enc, image.load_image(path, enc.cfg.resolution)[None])
    return np.repeat(e, n, 0)


@torch.no_grad()
def sample(sampler: Sampler | str, n: int, seed: int, conditions: dict | None = None,
           guidance: dict | float | None = None, steps: int = 50, eta: float = 0.0,
           batch_size: int = 256, clip: float | None = None, image_encoder=None,
           negative_step: float = 30.0, activation: str = "relu", start: np.ndarray | None = None,
           strength: float = 1.0, category: str | None = None,
           category_step: float = 0.0, render_targets: torch.Tensor | None = None,
           render_step: float = 0.0, refit_steps: int = 0, offset: int = 0) -> np.ndarray:
    """n weight vectors (n, 675) float32 under `conditions` (see `encode_conditions`; none =
    unconditional) with per-modality guidance scales (`guidance`: name -> scale, or one scale
    for all; default 1 = conditional model without guidance). `negative_step` > 0 applies
    the clamp-aware `NegativeConstraint` (NBRDF `activation`) at every DDIM step, and
    `category` with `category_step` > 0 category guidance after it (`CategoryConstraint`). `start`
    (n, 675) weight vectors and `strength` < 1: each sample starts from its start vector
    noised to strength (T - 1) (`Diffusion.ddim_sample`'s x0_start), e.g. the retrieved
    training material of an image condition. `render_targets` (n, H, H, 3) metric-view images
    and `render_step` > 0: render guidance toward each sample's image (`RenderConstraint`).
    `refit_steps` > 0: the clamp-aware refit of the samples (`neumat.diffusion.refit`).
    `offset`: rows offset ... offset + n - 1 of the draw of `seed` (`Sampler.sample`)."""
    if not isinstance(sampler, Sampler):
        sampler = Sampler(sampler)
    cond = encode_conditions(sampler, n, conditions or {}, image_encoder)
    if start is not None and len(start) != n:
        raise ValueError(f"{len(start)} start vectors for {n} samples")
    if not isinstance(guidance, dict):
        guidance = {k: 1.0 if guidance is None else float(guidance) for k in cond}
    rows = RowNoise(seed_for(seed, "ddim"), nbrdf.N_PARAMS)  # the same draws at any batch_size

    def render_hook(s, b):  # per batch: its samples' target images
        if render_targets is None or not render_step:
            return None
        return RenderConstraint(sampler.norm, render_targets[s:s + b], render_step, activation)

    constrain = constraint_for(sampler, negative_step, seed, activation, category, category_step)
    if render_targets is not None and len(render_targets) != n:
        raise ValueError(f"{len(render_targets)} render targets for {n} samples")
    out = []
    for s in range(0, n, batch_size):
        b = min(batch_size, n - s)
        c = {k: v[s:s + b].to(sampler.device) for k, v in cond.items()}
        x0 = None if start is None else sampler.norm.encode(
            torch.as_tensor(np.asarray(start[s:s + b], np.float32)).to(sampler.device))
        z = sampler.diffusion.ddim_sample(guided_multi(sampler.model, c, guidance),
                                          (b, nbrdf.N_PARAMS), steps, eta, None, sampler.device,
                                          clip=clip, x0_start=x0, constrain=chain(
                                              constrain, render_hook(s, b)),
                                          strength=strength, noise=rows.batch(offset + s, b))
        out.append(sampler.norm.decode(z).float().cpu().numpy())
    w = np.concatenate(out) if out else np.zeros((0, nbrdf.N_PARAMS), np.float32)
    return clamp_refit(w, refit_steps, seed, activation=activation, device=sampler.device)
