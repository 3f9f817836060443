"""Report section: the seven category rules with their thresholds, the classification of the
source and NeuMERL materials (counts, MERL names, type purity), the acceptance rate per
category, and the Fig. 6 gallery of accepted samples rendered with Mitsuba 3."""

import numpy as np
import pandas as pd

from neumat import constrained, report
from neumat.logs import script_logging
from neumat.render import mitsuba_bsdf as mb
from neumat.render import scenes
from neumat.render.gallery import gallery


with script_logging(snakemake) as log:
    inp, out, p = snakemake.input, snakemake.output, snakemake.params
    rules = pd.read_csv(inp.rules, sep="\t", keep_default_na=False)
    classes = pd.read_csv(inp.classes, sep="\t", keep_default_na=False)
    purity = pd.read_csv(inp.purity, sep="\t", keep_default_na=False)
    acc = pd.read_csv(inp.acceptance, sep="\t", keep_default_na=False)
    table = pd.read_csv(inp.table, sep="\t", keep_default_na=False)
    weights = np.load(inp.weights)

    counts = (classes.groupby(["category", "set"]).size().unstack(fill_value=0)
              .reindex(constrained.CATEGORIES, fill_value=0).reset_index())
    src = classes[classes["set"] == "source"]
    names = pd.DataFrame({"category": constrained.CATEGORIES,
                          "source materials": [", ".join(src.loc[src["category"] == c, "name"]) or "-"
                                               for c in constrained.CATEGORIES]})
    pur = purity.pivot_table(index="set", values="purity", aggfunc="mean")
    missing = acc.loc[~acc["complete"].astype(str).isin(["True", "true"]), "category"].tolist()
    # incomplete categories: none accepted, or fewer than requested (shown, not padded)
    accepted = dict(zip(acc["category"], acc["accepted"].astype(int)))
    none = [c for c in missing if accepted.get(c, 0) == 0]
    part = [c for c in missing if accepted.get(c, 0) > 0]

    # Fig. 6: a row per produced category
    variant = mb.select_variant(p.mitsuba["variant"])
    picks, rows = [], []
    for cat in p.categories:
        idx = np.flatnonzero(table["category"] == cat)[:p.gallery_count]
        picks += idx.tolist()
        if len(idx):
            rows.append((cat, idx))
    if picks:
        imgs = dict(zip(picks, scenes.render_spheres(weights[picks], [f"c{i}" for i in picks],
                                                     p.mitsuba, p.activation, p.seed)))
        blank = np.full_like(next(iter(imgs.values())), 255)
        cells, labels = [], []
        for cat, idx in rows:  # a row per category, a short one padded with blank cells
            cells += [imgs[i] for i in idx] + [blank] * (p.gallery_count - len(idx))
            labels += [f"{cat} #{i}" for i in idx] + [""] * (p.gallery_count - len(idx))
        title = "not produced within budget: " + (", ".join(none) or "none") + (
            "; fewer than asked: " + ", ".join(part) if part else "")
        gallery(cells, labels, out.gallery, ncols=p.gallery_count, title=title)
        fig = "![Constrained synthesis gallery](figures/constrained_gallery.png)"
    else:
        gallery([np.full((32, 32, 3), 255, np.uint8)], ["no category produced"], out.gallery)
        fig = "No category was produced within the budget, so there is no gallery."

    md = ["## Constrained synthesis (M³ashy §4.5, Fig. 6)", constrained.rules_markdown(),
          "Thresholds in use (`constrained/rules.tsv`: derived from the source materials, or "
          "set by config `constrained.thresholds`, as `derived_from` says):",
          report.md_table(rules), "Materials per category:", report.md_table(counts),
          "Source materials per category:", report.md_table(names),
          "How cleanly each type falls into one category (purity = share of the type's "
          "materials in its most common category; mean purity per set: "
          + ", ".join(f"{s} {v:.2f}" for s, v in pur["purity"].items()) + "):",
          report.md_table(purity[purity["set"] == "source"].drop(columns="set")),
          "Acceptance per category (rejection sampling of `ours`: every draw is judged by the "
          "rules above. `guide` is how the draws after the pilot batch were made: "
          "unconditionally, guided by type, or with category guidance toward eq. 9 or 10 "
          "(`constrained.guidance_step`); `pilot` gives each mode's acceptance in its first "
          "batch. A category with complete = False reached fewer accepted samples than requested "
          "within the budget (none, or some) and is not padded. Metallic samples, however drawn, reflect more energy than they receive: "
          "eq. 10 admits no passive BRDF):",
          report.md_table(acc),
          "Not produced within the budget: " + (", ".join(none) or "none") + "."
          + (" Fewer than requested: " + ", ".join(part) + "." if part else ""), fig,
          f"Rendered with Mitsuba 3 ({variant})."]
    with open(out.section, "w") as f:
        f.write("\n\n".join(md) + "\n")
    log.info("section written; %d gallery images, missing: %s", len(picks), missing)
