"""Report section: hyperdiffusion settings and training cost, loss curves, sampling speed,
plausibility, novelty (distance to the nearest training material), galleries of samples next to
their nearest training materials, type-conditioned gallery and type-match share."""
import json
from pathlib import Path

import numpy as np
import pandas as pd

from neumat import report
from neumat.device import resolve_device
from neumat.diffusion import dataset, summary
from neumat.diffusion.constraints import CONSTRAINT_DIRECTIONS
from neumat.diffusion.refit import FLOOR
from neumat.diffusion.model import token_sizes
from neumat.io import modelfile
from neumat.logs import script_logging
from neumat.render import sphere


def sets_by_name(paths, kind):
    """{set name: path} from paths .../samples/<set>/<file>."""
    return {Path(f).parent.name: f for f in paths if Path(f).name == kind}


def render(w):
    """Tonemapped metric-view spheres of weight vectors (NaN weights render as 0)."""
    p = snakemake.params
    return sphere.tonemap(sphere.render_fields(np.nan_to_num(w), p.resolution, p.activation,
                                               str(resolve_device(snakemake.config["device"]))))


def clamp_note(s: dict) -> str:
    step, refit = s["negative_step"], s.get("refit_steps", 0)  # refit: neutral 0, absent from params
    if not step and not refit:
        return ("Clamp-aware constraint and refit off (diffusion.sample.negative_step = 0, "
                "refit_steps = 0).")
    parts = []
    if step:
        parts.append(f"Clamp-aware constraint: at every DDIM step the predicted x0 takes one "
                     f"gradient step of size {step:g} down mean(relu(-x)), x the NBRDF's "
                     f"log-space output at {CONSTRAINT_DIRECTIONS} seeded valid MERL bins (the "
                     f"values the output max(exp(x) - 1, 0) clamps).")
    if refit:
        parts.append(f"Clamp-aware refit: each sample's NBRDF refitted from its own weights by "
                     f"{refit} Adam steps to its own log-space output raised to {FLOOR:g} "
                     f"(neumat.diffusion.refit).")
    return " ".join(parts) + (" `ours_plain` is `ours` drawn with the same seeds without them "
                              "(before/after below).")


def split_note(token_values: int) -> str:
    """How the tensors are tokenised; diffusion.model.token_values is absent from params at 0
    (a neutral key: config/speed_keys.yaml)."""
    if not token_values:
        return ""
    return (f", a tensor of more than {token_values} weights split into near-equal pieces "
            f"({len(token_sizes(token_values))} tensor tokens),")


with script_logging(snakemake) as log:
    inp, out, p = snakemake.input, snakemake.output, snakemake.params
    cfg = p.cfg
    weights = np.load(inp.weights)
    man = dataset.read_manifest(inp.manifest, len(weights))
    samples = {k: np.load(f) for k, f in sets_by_name(inp.samples, "weights.npy").items()}
    nearest = {k: pd.read_csv(f, sep="\t", keep_default_na=False)
               for k, f in sets_by_name(inp.nearest, "nearest.tsv").items()}
    timing = {k: pd.read_csv(f, sep="\t").iloc[0] for k, f in sets_by_name(inp.timings, "timing.tsv").items()}
    bundles = {Path(f).parent.name: modelfile.load(f)
               for f in inp.models}

    summary.plot_losses(inp.histories, out.loss)
    n = cfg["gallery_count"]
    summary.nearest_gallery(samples["ours"], nearest["ours"], weights, n, render, out.gallery,
                            "ours: samples (top) and their nearest training materials (bottom, "
                            "BRDF-L1)")
    summary.nearest_gallery(samples["merl100"], nearest["merl100"], weights, n, render,
                            out.gallery_merl100, "MERL100: samples (top) and their nearest "
                            "training materials (bottom, BRDF-L1)")
    nt = nearest["ours_type"]
    summary.type_gallery(samples["ours_type"], nt, cfg["gallery_types"], cfg["per_type"], render,
                         out.types)

    tm = summary.type_match(nt, nearest["reference"], man)
    match, ref_match, ref_known = tm.hits, tm.ref_hits, tm.ref_known
    novelty = summary.novelty(nearest)
    train_rows = summary.training_table(bundles)
    speed = summary.speed_table(timing)
    plaus = pd.read_csv(inp.plausibility, sep="\t")
    mitsuba = json.loads(Path(inp.mitsuba).read_text())
    m, s = cfg["model"], cfg["schedule"]
    b0 = next(iter(bundles.values()))
    n_params = sum(v.numel() for k, v in b0["ema"].items())
    md = [
        "## Hyperdiffusion",
        f"Transformer denoiser over the 675 NBRDF weights: one token per layer tensor "
        f"(W1, b1, W2, b2, W3, b3){split_note(m.get('token_values', 0))} "
        f"plus a timestep token and a material-type token "
        f"({len(b0['class_names'])} classes + null), width {m['width']}, depth {m['depth']}, "
        f"{m['heads']} heads ({n_params / 1e6:.2f} M parameters); weights standardised per "
        f"coordinate. DDPM with T = {s['timesteps']}, {s['kind']} schedule, "
        f"{s['prediction']}-prediction; EMA {cfg['train']['ema_decay']}; type labels dropped "
        f"with p = {cfg['train']['cond_drop']} for classifier-free guidance. Sampling: DDIM, "
        f"{cfg['sample']['steps']} steps, eta = {cfg['sample']['eta']}; type-conditioned "
        f"samples use guidance scale {cfg['sample']['guidance']}. " + clamp_note(cfg["sample"]),
        "### Training", report.md_table(train_rows),
        "![diffusion training loss](figures/diffusion_loss.png)",
        "### Sampling speed", report.md_table(speed),
        "### Physical plausibility",
        "Shares of materials with non-finite weights or values, with any value clamped from "
        "negative (exp(x) - 1 < 0) on a random sample of valid MERL bins, exploding (largest value "
        f"above {cfg['explode_factor']} x the training split's largest) and violating energy "
        "passivity (directional albedo > 1.01 for some outgoing direction and channel).",
        report.md_table(plaus),
        "### Novelty",
        "BRDF-L1 from each material to its nearest NeuMERL training material; `reference` is the "
        "test split (real materials never seen in training): samples much closer than that are "
        "near-copies." + report.nn_bins_note("the diffusion section"),
        report.md_table(novelty),
        "The BRDF-L1 is absolute, and a specular material's values run tens of times a diffuse "
        f"one's, so a set's median depends on its mix: `ours_type` holds {cfg['per_type']} "
        "samples of every type asked, the specular ones included, where the test split is "
        "mostly interpolations. The relative column divides each distance by the nearest "
        "training material's mean value on the same bins: it compares sets of other mixes.",
        "### Unconditional samples",
        f"Mitsuba 3 ({mitsuba['variant']}, {mitsuba['resolution']} px, {mitsuba['spp']} spp, "
        f"{mitsuba['images']} images in {mitsuba['seconds']:.0f} s): samples of `ours` (top) and "
        f"their nearest training materials by BRDF-L1 (bottom).",
        "![ours: Mitsuba renders of samples and nearest training materials]"
        "(figures/diffusion_mitsuba_ours.png)",
        "Metric-renderer view of the same comparison, for ours and MERL100:",
        "![ours: samples and nearest training materials](figures/diffusion_gallery.png)",
        "![MERL100: samples and nearest training materials](figures/diffusion_gallery_merl100.png)",
        "### Type-conditioned samples",
        f"Share of type-conditioned samples whose nearest typed training material (BRDF-L1; "
        f"interpolations carry no type) has the requested type: **{100 * match.mean():.1f} %** "
        f"({len(nt)} samples, {nt['type'].nunique()} types). For comparison, the same share for "
        f"the test-split materials and their own types: {100 * ref_match.mean():.1f} % "
        f"({len(ref_match)} typed test materials, {int(ref_known.sum())} of them of a type "
        f"some training material has, {int(ref_match[ref_known].sum())} of those a hit). Test "
        f"materials come from MERL materials never seen in training: some have a type no "
        f"training material has, and under the split by source a held-out material's nearest "
        f"typed training material often has another type even where training has its type.",
        "![type-conditioned samples, Mitsuba](figures/diffusion_mitsuba_types.png)",
        "![type-conditioned samples](figures/diffusion_types.png)",
        report.md_table(tm.per_type.reset_index()),
    ]
    Path(out.section).write_text("\n\n".join(md) + "\n")
    log.info("type match %.1f %% (reference %.1f %%)", 100 * match.mean(), 100 * ref_match.mean())
