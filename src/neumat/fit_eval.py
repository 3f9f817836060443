"""Evaluating fitted NBRDF fields: render PSNR against their tables in the metric view, and
export to MERL tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from neumat import nbrdf
from neumat.io import merl


def export_merl(weights, path: str | Path, activation: str = "relu") -> None:
    """One fitted field (675,) -> MERL .binary (evaluated at the 90x90x180 bin centres)."""
    # a copy: `weights` is often a row of a read-only memory map (torch warns on those)
    w = torch.tensor(np.asarray(weights, dtype=np.float32)).reshape(1, nbrdf.N_PARAMS)
    merl.write_merl(path, nbrdf.evaluate_grid(w, activation)[0])


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """PSNR (dB, peak 1) per image of two batches (B, H, W, C) of values in [0, 1]."""
    d2 = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    mse = d2[:, mask].mean((1, 2)) if mask is not None else d2.mean((1, 2, 3))
    return 10 * np.log10(1.0 / np.maximum(mse, 1e-20))


def display(img) -> np.ndarray:
    """Linear HDR renders -> display values in [0, 1] (the metric renderer's sRGB tone map)."""
    from neumat.render import sphere
    x = img.numpy() if torch.is_tensor(img) else np.asarray(img)
    return sphere.srgb_encode(x * 2.0 ** sphere.EXPOSURE)


def render_psnr(weights, tables=None, resolution: int = 128, activation: str = "relu",
                device: str = "cpu", view_values=None) -> np.ndarray:
    """Render PSNR of fitted fields (B, 675) against their tabulated materials in the fixed
    metric view (`neumat.render.sphere`): sRGB display values, sphere pixels only. The
    materials are full tables (B, 3, 90, 90, 180) or, cheaper, `view_values` (B, 3, N): their
    values at `sphere.sphere_view(resolution).bins`."""
    from neumat.render import sphere
    fit_img = display(sphere.render_fields(weights, resolution, activation, device))
    ref_img = display(sphere.render_tables(tables, resolution, device) if view_values is None
                      else sphere.render_view_values(view_values, resolution, device))
    mask = sphere.sphere_view(resolution, str(device)).mask.cpu().numpy()
    return psnr(fit_img, ref_img, mask)


