"""Atomic writes: a temporary name beside the target, then os.replace, so a killed job never
leaves a truncated output or checkpoint behind."""

import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

# what np.load, and reading its members, raise on a damaged, truncated or foreign .npz (a
# killed writer's file, a disk error): callers turn it into an error naming the file and rule
NPZ_ERRORS = (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error)


def save_npz(path: str | Path, **arrays) -> None:
    """Atomic np.savez."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def save_torch(path: str | Path, obj) -> None:
    """Atomic torch.save (model files, checkpoints: tensors and plain values, so that they load
    with weights_only=True)."""
    import torch  # here: the numpy writers above serve scripts that never import torch

    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def save_npy(path: str | Path, array: np.ndarray) -> None:
    """Atomic np.save."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part.npy")
    np.save(tmp, array)
    os.replace(tmp, path)
