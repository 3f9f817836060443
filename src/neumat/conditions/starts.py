"""Training-material starts (SDEdit, strength < 1) shared by the workflow's sample_conditions
and `neumat sample --start`: the type picks here (the text starts are
`neumat.conditions.text.training_starts`, the image start `neumat.conditions.image.retrieve`),
and which `conditions` keys need a start: checked when the DAG is built
(workflow/rules/conditions.smk), so a config that asks to refine or match a start that is never
drawn stops before any job, naming both keys."""

import numpy as np

# (modality, key, what the key does with the start)
NEEDS_START = (
    ("image", "refiner", "refines each image's retrieved training material"),
    ("type", "refiner", "refines a training material of each sample's type"),
    ("text", "refiner", "refines the training materials nearest each prompt"),
    ("text", "start_match", "picks each prompt's starting materials by type"),
)


def check(conditions: dict) -> None:
    """ValueError for the first key of NEEDS_START set true while its modality's strength is 1
    (its samples start from noise)."""
    for modality, key, does in NEEDS_START:
        section = conditions[modality]
        if section.get(key) and section["strength"] >= 1:
            raise ValueError(f"config conditions.{modality}.{key}: true {does} and needs "
                             f"conditions.{modality}.strength < 1 (e.g. 0.05); at 1 the samples "
                             f"would start from noise")


def type_picks(types, rows: np.ndarray, row_types: np.ndarray, k: int,
               rng: np.random.Generator) -> np.ndarray:
    """(len(types), k) training rows: for each asked type, k draws with replacement among
    `rows` whose type (`row_types`, aligned with rows) it is, in the order asked, from one
    generator; a row of -1 (start from noise) for '' or a type no row has."""
    picks = [rng.choice(rows[row_types == t], k) if t and (row_types == t).any()
             else np.full(k, -1) for t in types]
    return np.stack(picks) if picks else np.zeros((0, k), int)
