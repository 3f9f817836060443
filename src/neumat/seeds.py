"""Named random streams: every stochastic step draws its seed from (master seed, stage name,
items), so streams never collide by accident (hand-numbered offsets such as `seed + 6000` did:
the metric render and the first BTF's data shared one) and adding a stage moves no other seed.

    seed_for(0, "fit")                       # one stream for a stage
    seed_for(0, "btf_fit", "wood06", "pca")  # one per material and method

Names are hashed with SHA-256 (stable across processes and Python versions, unlike hash()) and
become numpy SeedSequence spawn keys; the result fits in 32 bits, which every consumer accepts
(numpy, torch.manual_seed, Mitsuba)."""

import hashlib
import os

import numpy as np


def _word(item) -> int:
    """A stable 64-bit integer for a name or number."""
    return int.from_bytes(hashlib.sha256(str(item).encode()).digest()[:8], "little")


def seed_for(seed: int, stage: str, *items) -> int:
    """The seed of stream `stage` (a rule or stage name) for `items` (e.g. material, method)."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"config seed must be a non-negative integer, got {seed!r}")
    if not stage:
        raise ValueError("seed_for needs a stage name")
    # spawn_key is SeedSequence's own way to name child streams (kept apart from the entropy)
    ss = np.random.SeedSequence(int(seed), spawn_key=(_word(stage), *map(_word, items)))
    out = int(ss.generate_state(1, np.uint32)[0])
    if os.environ.get("NEUMAT_SEED_LOG"):  # tests/test_seeds.py lists the streams of a DAG
        with open(os.environ["NEUMAT_SEED_LOG"], "a") as f:
            f.write("\t".join(map(str, (stage, *items, out))) + "\n")
    return out
