"""Which `conditions` keys need a training-material start (strength < 1): checked when the DAG
is built (workflow/rules/conditions.smk), so a config that asks to refine or match a start that
is never drawn stops before any job, naming both keys."""

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
