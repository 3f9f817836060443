"""Material names -> type, text description and colour words (no I/O, no other neumat imports,
so the catalogue and the synthetic materials can both use it).

The type is the name without colour words and numeric suffixes ("blue-metallic-paint2" ->
"metallic-paint"), with three merges that bring the 51 raw stems to the 48 types the M3ashy
paper uses: neoprene-rubber and pure-rubber -> rubber, ss440 (stainless steel) -> steel.
The description is the name in words ("blue metallic paint"); colour words are kept separately
so RGB-permuted copies can drop them (paper §4.4).
"""

from __future__ import annotations

import re

COLOUR_WORDS = {
    "beige", "black", "blue", "brown", "dark", "light", "gold", "green", "gray", "maroon",
    "orange", "pink", "purple", "red", "silver", "violet", "white", "yellow",
}
TYPE_MERGES = {"neoprene-rubber": "rubber", "pure-rubber": "rubber", "ss440": "steel"}


def material_type(name: str) -> str:
    """'blue-metallic-paint2' -> 'metallic-paint'; 'cherry-235' -> 'cherry'."""
    if name in TYPE_MERGES:
        return TYPE_MERGES[name]
    words = [w for w in name.split("-") if w not in COLOUR_WORDS and not w.isdigit()]
    stem = "-".join(words)
    return TYPE_MERGES.get(stem, re.sub(r"(?<=[a-z])\d+$", "", stem))


def colour_words(name: str) -> list[str]:
    return [w for w in name.split("-") if w in COLOUR_WORDS]


def description(name: str) -> str:
    """'blue-metallic-paint2' -> 'blue metallic paint' (numbers dropped)."""
    words = [re.sub(r"\d+$", "", w) for w in name.split("-")]
    return " ".join(w for w in words if w)


def drop_colours(text: str, colours: list[str] | str) -> str:
    """Remove colour words from a description ('red metallic paint' -> 'metallic paint')."""
    if isinstance(colours, str):
        colours = colours.split() if colours else []
    return " ".join(w for w in text.split() if w not in set(colours))
