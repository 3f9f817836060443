"""Report section: hyperdiffusion settings and training cost, loss curves, sampling speed,
plausibility, novelty (distance to the nearest training material), galleries of samples next to
their nearest training materials, type-conditioned gallery and type-match share."""
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from neumat import report  # noqa: E402
from neumat.device import resolve_device  # noqa: E402
from neumat.diffusion import dataset  # noqa: E402
from neumat.diffusion.constraints import CONSTRAINT_DIRECTIONS  # noqa: E402
from neumat.diffusion.refit import FLOOR  # noqa: E402
from neumat.diffusion.model import token_sizes  # noqa: E402
from neumat.io import modelfile  # noqa: E402
from neumat.logs import script_logging  # noqa: E402
from neumat.render import sphere  # noqa: E402
from neumat.render.gallery import gallery as image_grid  # noqa: E402


def sets_by_name(paths, kind):
    """{set name: path} from paths .../samples/<set>/<file>."""
    return {Path(f).parent.name: f for f in paths if Path(f).name == kind}


def render(w, p):
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


def gallery(samples, near, weights, n, p, path, title):
    """Top row: samples; bottom row: their nearest training materials (BRDF-L1)."""
    k = min(n, len(samples))
    pick = np.linspace(0, len(samples) - 1, k).round().astype(int)
    rows = near.iloc[pick]
    top, bottom = render(samples[pick], p), render(weights[rows["nearest_id"].to_numpy()], p)
    labels = [f"sample {i}" for i in pick] + \
             [f"{r.nearest_name}\nL1 {r.brdf_l1:.3g}" for r in rows.itertuples()]
    image_grid(np.concatenate([top, bottom]), labels, path, ncols=k, min_cell=96, title=title)


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

    # loss curves
    fig, ax = plt.subplots(figsize=(5, 3))
    for f in inp.histories:
        h = pd.read_csv(f, sep="\t")
        ax.plot(h["step"], h["loss"], label=Path(f).parent.name)
    ax.set(xlabel="step", ylabel="training loss (MSE, normalised)", yscale="log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out.loss, dpi=100)
    plt.close(fig)

    n = cfg["gallery_count"]
    gallery(samples["ours"], nearest["ours"], weights, n, p, out.gallery,
            "ours: samples (top) and their nearest training materials (bottom, BRDF-L1)")
    gallery(samples["merl100"], nearest["merl100"], weights, n, p, out.gallery_merl100,
            "MERL100: samples (top) and their nearest training materials (bottom, BRDF-L1)")

    # type-conditioned gallery: one row per type, up to 6 samples each
    nt = nearest["ours_type"]
    shown = list(dict.fromkeys(nt["type"]))[:cfg["gallery_types"]]
    per_row = min(cfg["per_type"], 6)
    pick = np.concatenate([np.flatnonzero(nt["type"] == t)[:per_row] for t in shown])
    labels = [f"{r.type}\n(nn: {r.nearest_typed_type})" for r in nt.iloc[pick].itertuples()]
    image_grid(render(samples["ours_type"][pick], p), labels, out.types, ncols=per_row, min_cell=96,
               title="type-conditioned samples (label: requested type, and the type "
                     "of the nearest typed training material)")

    # numbers
    match = (nt["type"] == nt["nearest_typed_type"])
    ref = nearest["reference"]
    ref_match = (ref["type"] == ref["nearest_typed_type"])[ref["type"] != ""]
    train_types = set(man.loc[man["split"] == "train", "type"]) - {""}
    ref_known = ref.loc[ref["type"] != "", "type"].isin(train_types)  # index as ref_match
    per_type = nt.assign(match=match).groupby("type")["match"].mean().mul(100).rename("match %")
    novelty = pd.DataFrame([{"set": k, "median BRDF-L1 to nearest training": v["brdf_l1"].median(),
                             "share closer than 10 % of the reference median":
                                 (v["brdf_l1"] < 0.1 * ref["brdf_l1"].median()).mean()}
                            for k, v in nearest.items()])
    train_rows = pd.DataFrame([{
        "model": k, "training materials": b["n_train"], "steps": b["train_cfg"]["steps"],
        "batch": b["train_cfg"]["batch_size"], "train wall time (s)": b["train_seconds"],
        "final loss": b["history"][-1][1]} for k, b in bundles.items()])
    speed = pd.DataFrame([{"set": k, "samples": int(t["samples"]), "seconds": t["seconds"],
                           "samples / s": t["samples_per_second"], "guidance": t["guidance"]}
                          for k, t in timing.items()])
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
        report.md_table(per_type.reset_index()),
    ]
    Path(out.section).write_text("\n\n".join(md) + "\n")
    log.info("type match %.1f %% (reference %.1f %%)", 100 * match.mean(), 100 * ref_match.mean())
