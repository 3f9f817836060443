"""Embed the sampling prompts (conditions/prompts.{tsv,npy}): test-split descriptions of typed
materials (conditions.text.test_prompts of them) plus the config's prompts, meant to be unseen.
prompts.tsv's in_training marks any prompt that is word for word a training description as
rule text_embeddings embedded it (measured colour words: its descriptions.tsv). Fails naming
the package when the offline text encoder is not installed."""
import numpy as np
import pandas as pd

from neumat.conditions import evaluate, text
from neumat.diffusion import dataset
from neumat.io.atomic import save_npy
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p, inp, out = snakemake.params, snakemake.input, snakemake.output
    man = dataset.read_manifest(inp.manifest)
    descriptions = list(man["description"])
    if hasattr(inp, "descriptions"):  # measured colour words: as text_embeddings embedded them
        emb = pd.read_csv(inp.descriptions, sep="\t", keep_default_na=False)
        if list(emb["id"]) != list(man["id"]):
            raise ValueError(f"{inp.descriptions}: its rows are not {inp.manifest}'s; rebuild it "
                             f"with rule text_embeddings")
        descriptions = list(emb["embedded"])
    text.load_encoder()

    test = man[(man["split"] == "test") & (man["type"] != "")].drop_duplicates("description")
    k = p.test_prompts or len(test)
    pick = np.unique(np.linspace(0, len(test) - 1, min(k, len(test))).round().astype(int)) \
        if len(test) else []
    test = test.iloc[pick]
    # the descriptions training saw, as embedded (measured colour words included): a prompt
    # word for word among them is not held out as text, whatever its kind
    seen = {d for d, s in zip(descriptions, man["split"]) if s == "train"}
    prompts = pd.DataFrame({
        "prompt": list(test["description"]) + list(p.prompts),
        "kind": ["test"] * len(test) + ["unseen"] * len(p.prompts),
        "type": list(test["type"]) + [""] * len(p.prompts)})
    prompts["colour"] = [evaluate.colour_of(q) for q in prompts["prompt"]]
    prompts["in_training"] = [q in seen for q in prompts["prompt"]]
    for kind, g in prompts[prompts["in_training"]].groupby("kind"):
        log.warning("%d %s prompt(s) occur word for word as training descriptions (scored "
                    "apart in conditions/eval_summary.tsv): %s", len(g), kind, list(g["prompt"]))
    prompts.to_csv(out.prompts, sep="\t", index=False)
    save_npy(out.prompt_embeddings, text.embed(list(prompts["prompt"])))
    log.info("%d prompts (%d test-split descriptions)", len(prompts), len(test))
