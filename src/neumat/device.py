"""The torch device named by the config key `device` (auto | cpu | cuda)."""

from __future__ import annotations

import torch


def resolve_device(name: str) -> torch.device:
    """`auto` -> cuda when torch sees a GPU, else cpu; `cuda` without a GPU is an error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("config device: cuda, but torch sees no CUDA device")
    return torch.device(name)


def to_device(t: torch.Tensor, device: torch.device | str, dtype: torch.dtype | None = None
              ) -> torch.Tensor:
    """A CPU tensor (e.g. randomness drawn from a CPU generator, which keeps results the same on
    every device) moved to `device` without a host sync: a copy from pageable memory waits for
    the GPU stream, a copy from pinned memory with non_blocking does not. On the CPU, t itself
    (or t cast to dtype)."""
    device = torch.device(device)
    if device.type == "cuda":
        t = t.pin_memory().to(device, non_blocking=True)
    return t.to(device, dtype) if dtype is not None else t.to(device)
