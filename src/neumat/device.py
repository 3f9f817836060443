"""The torch device named by the config key `device` (auto | cpu | cuda)."""

from __future__ import annotations

import logging

import torch

log = logging.getLogger("neumat.device")


def resolve_device(name: str) -> torch.device:
    """`auto` -> cuda when torch sees a GPU, else cpu; `cuda` without a GPU is an error. The
    choice goes to the job's log: under `auto`, a node whose CUDA is broken (a driver mismatch,
    a CPU-only torch) falls back to the CPU, and the log is where that shows."""
    if name == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("config device: cuda, but torch sees no CUDA device (torch "
                           f"{torch.__version__}, built for CUDA {torch.version.cuda}); run on a "
                           "GPU node, or set device: auto or cpu")
    dev = torch.device(("cuda" if torch.cuda.is_available() else "cpu") if name == "auto" else name)
    where = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "no GPU in use"
    log.info("device %s -> %s (%s; torch %s)", name, dev, where, torch.__version__)
    return dev


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
