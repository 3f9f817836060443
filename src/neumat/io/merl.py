"""MERL `.binary` BRDF tables and Rusinkiewicz coordinates.

File layout (Matusik et al. 2003): 3 x int32 header (90, 90, 180) = (theta_h, theta_d, phi_d)
bins, then 3 planes (R, G, B) of 1,458,000 float64 each, index phi_d + 180*(theta_d + 90*theta_h).
Physical BRDF = stored value * SCALE[channel]. Bins below the horizon hold negative values.

Tables in memory are float arrays of shape (3, 90, 90, 180) holding the *physical* BRDF.
"""

from __future__ import annotations

import functools
import logging
import os
from pathlib import Path

import numpy as np

from neumat.logs import InputError

log = logging.getLogger(__name__)

N_TH, N_TD, N_PD = 90, 90, 180
N_BINS = N_TH * N_TD * N_PD
SHAPE = (3, N_TH, N_TD, N_PD)
SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
HEADER = np.array([N_TH, N_TD, N_PD], dtype="<i4")
FILE_SIZE = 12 + 3 * N_BINS * 8  # 34,992,012 bytes
HALF_PI = np.pi / 2


class MerlFormatError(InputError, ValueError):
    """A file that is not a valid MERL .binary table."""


# ----------------------------------------------------------------------------- file I/O


def read_merl(path: str | os.PathLike) -> np.ndarray:
    """Read a MERL .binary file -> physical BRDF, float64 array (3, 90, 90, 180).

    Below-horizon bins keep their (negative) stored value times the scale."""
    path = Path(path)
    size = path.stat().st_size
    if size != FILE_SIZE:
        raise MerlFormatError(
            f"{path}: {size} bytes, a MERL .binary file has {FILE_SIZE} "
            "(truncated or not a MERL table)")
    with open(path, "rb") as f:
        header = np.frombuffer(f.read(12), dtype="<i4")
        if not np.array_equal(header, HEADER):
            raise MerlFormatError(f"{path}: header {header.tolist()}, expected [90, 90, 180]")
        data = np.fromfile(f, dtype="<f8").reshape(SHAPE)  # writable: scaled in place, with
        # no second 35 MB array
    if not np.isfinite(data).all():
        raise MerlFormatError(f"{path}: contains NaN or inf values")
    return np.multiply(data, SCALE[:, None, None, None], out=data)


def write_merl(path: str | os.PathLike, brdf: np.ndarray) -> None:
    """Write a physical BRDF (3, 90, 90, 180) as a MERL .binary file.

    Written to a temporary name and renamed, so a killed writer never leaves a
    file that looks complete."""
    brdf = np.asarray(brdf)
    if brdf.shape != SHAPE:
        raise ValueError(f"MERL table must have shape {SHAPE}, got {brdf.shape}")
    if not np.isfinite(brdf).all():
        raise ValueError(f"{path}: refusing to write a table with NaN or inf values")
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "wb") as f:
        f.write(HEADER.tobytes())
        # one theta_h row (130 kB) at a time: scaled and written from a buffer the allocator
        # reuses, not three 35 MB copies of the table (benchmarks/merl_export.py)
        row = np.empty((N_TD, N_PD), dtype="<f8")
        for c in range(3):
            for i in range(N_TH):
                np.divide(brdf[c, i], SCALE[c], out=row)
                f.write(row.data)
    os.replace(tmp, path)


# ----------------------------------------------------------------------------- grid


def bin_centers() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angles (rad) at the centre of each bin along theta_h (non-linear), theta_d, phi_d."""
    th = ((np.arange(N_TH) + 0.5) / N_TH) ** 2 * HALF_PI
    td = (np.arange(N_TD) + 0.5) / N_TD * HALF_PI
    pd = (np.arange(N_PD) + 0.5) / N_PD * np.pi
    return th, td, pd


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False  # a cached array is shared: writing to it raises
    return a


@functools.cache
def grid_angles() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta_h, theta_d, phi_d) of every bin centre, each flat of length N_BINS in file order
    (computed once per process, read-only)."""
    th, td, pd = bin_centers()
    TH, TD, PD = np.meshgrid(th, td, pd, indexing="ij")
    return tuple(_frozen(a.ravel()) for a in (TH, TD, PD))


@functools.cache
def valid_mask() -> np.ndarray:
    """Bins whose centre has both directions above the horizon, flat bool (N_BINS,), read-only,
    computed once per process: writing or evaluating a table needs it every time. cos(theta_i)
    and cos(theta_o) in closed form (wo is wi mirrored about h: phi_d + pi), equal on every bin
    to the z of half_diff_to_dirs' directions (tests/test_merl_io.py), from the 1-D bin centres
    broadcast over the (theta_h, theta_d, phi_d) grid: 0.018 CPU-s against 0.58 for the
    directions (AMD EPYC, AVX-512)."""
    th, td, pd = bin_centers()
    th, td, pd = th[:, None, None], td[None, :, None], pd[None, None, :]
    a, b = np.cos(td) * np.cos(th), np.sin(td) * np.cos(pd) * np.sin(th)
    return _frozen(((a - b > 0) & (a + b > 0)).ravel())


@functools.cache
def grid_inputs() -> np.ndarray:
    """half_diff_cartesian of every bin centre, (N_BINS, 6) float32, read-only: the neural-field
    input of a whole table, computed once per process."""
    return _frozen(half_diff_cartesian(*grid_angles()).astype(np.float32))


@functools.cache
def valid_grid_inputs_t() -> np.ndarray:
    """grid_inputs at the valid bins (valid_mask), in file order, transposed: (6, valid bins)
    float32, read-only. The only bins whose values a field decides (the others are -1 in every
    file), channel-major for nbrdf.forward_channels."""
    angles = (a[valid_mask()] for a in grid_angles())  # elementwise: grid_inputs' values
    return _frozen(np.ascontiguousarray(half_diff_cartesian(*angles).astype(np.float32).T))


# Negative above-horizon bins: AugMERL drops such a bin from every material. Real MERL tables
# store -1 below the horizon only; measured on the 100 published NBRDF fits decoded to MERL
# (benchmarks/merl_negative_bins.py), each has 45 of 1,096,216 (0.0041 %): bins whose centre is
# above the horizon but whose lower edge is not. Above WARN a table gets a warning with the
# count (~12x the real share); above MAX (~240x) it is refused.
WARN_NEGATIVE_SHARE = 0.0005
MAX_NEGATIVE_SHARE = 0.01


def negative_bins(table: np.ndarray) -> tuple[int, int]:
    """(negative, total) counts over the above-horizon bins (valid_mask) of a table
    (3, 90, 90, 180) or (3, N_BINS); a bin is negative when any channel is."""
    t = np.asarray(table).reshape(3, -1)[:, _valid_flat()]
    return int((t < 0).any(0).sum()), t.shape[1]


@functools.cache
def _valid_flat() -> np.ndarray:
    return _frozen(np.flatnonzero(valid_mask()))


def check_negative(path, table: np.ndarray, max_share: float = MAX_NEGATIVE_SHARE) -> int:
    """Negative above-horizon bins of the table read from `path`; logs a warning with the count
    above WARN_NEGATIVE_SHARE, raises MerlFormatError naming the file and the share above
    `max_share`."""
    count, n = negative_bins(table)
    if count > WARN_NEGATIVE_SHARE * n:
        log.warning("%s: %d of %d above-horizon bins (%.3f %%) are negative; AugMERL leaves them "
                    "out of every material", path, count, n, 100 * count / n)
    if count > max_share * n:
        raise MerlFormatError(
            f"{path}: {count / n:.1%} of its above-horizon bins are negative ({count} of {n}); "
            f"real MERL tables have 0.0041 %, the limit is {max_share:.0%} "
            "(neumat.io.merl.MAX_NEGATIVE_SHARE). A sign-flipped or corrupt table? Replace it, "
            "or leave the material out with merl.subset.")
    return count


def angles_to_index(theta_h, theta_d, phi_d):
    """Bin indices (flat, file order) of Rusinkiewicz angles; phi_d folded to [0, pi)."""
    theta_h = np.asarray(theta_h, dtype=np.float64)
    theta_d = np.asarray(theta_d, dtype=np.float64)
    phi_d = np.asarray(phi_d, dtype=np.float64)
    ih = np.floor(np.sqrt(np.clip(theta_h, 0, None) / HALF_PI) * N_TH)
    idd = np.floor(np.clip(theta_d, 0, None) / HALF_PI * N_TD)
    # isotropy + reciprocity: f(phi_d) = f(phi_d + pi)
    phi_d = np.mod(phi_d, np.pi)
    ip = np.floor(phi_d / np.pi * N_PD)
    ih = np.clip(ih, 0, N_TH - 1).astype(np.int64)
    idd = np.clip(idd, 0, N_TD - 1).astype(np.int64)
    ip = np.clip(ip, 0, N_PD - 1).astype(np.int64)
    return ip + N_PD * (idd + N_TD * ih)


def lookup(brdf: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """Nearest-bin lookup of a table (3, 90, 90, 180) for direction pairs (N, 3) -> (N, 3).

    Directions below the horizon give 0."""
    th, td, pd = dirs_to_half_diff(wi, wo)
    idx = angles_to_index(th, td, pd)
    out = brdf.reshape(3, -1)[:, idx].T
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
    return np.where(below[:, None], 0.0, np.maximum(out, 0.0))


# ----------------------------------------------------------------------------- Rusinkiewicz


def _normalize(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rot_z(v, a):
    c, s = np.cos(a), np.sin(a)
    return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], -1)


def _rot_y(v, a):
    c, s = np.cos(a), np.sin(a)
    return np.stack([c * v[:, 0] + s * v[:, 2], v[:, 1], -s * v[:, 0] + c * v[:, 2]], -1)


def dirs_to_half_diff(wi: np.ndarray, wo: np.ndarray):
    """(wi, wo) unit vectors (N, 3) -> (theta_h, theta_d, phi_d), phi_d in (-pi, pi].

    d = R_b(-theta_h) R_n(-phi_h) wi (Rusinkiewicz 1998)."""
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    h = _normalize(wi + wo)
    theta_h = np.arccos(np.clip(h[:, 2], -1, 1))
    phi_h = np.arctan2(h[:, 1], h[:, 0])
    d = _rot_y(_rot_z(wi, -phi_h), -theta_h)
    theta_d = np.arccos(np.clip(d[:, 2], -1, 1))
    phi_d = np.arctan2(d[:, 1], d[:, 0])
    return theta_h, theta_d, phi_d


def half_diff_to_dirs(theta_h, theta_d, phi_d, phi_h=0.0):
    """Inverse of `dirs_to_half_diff`: angles -> (wi, wo), each (N, 3)."""
    theta_h, theta_d, phi_d = (np.asarray(a, dtype=np.float64) for a in (theta_h, theta_d, phi_d))
    phi_h = np.broadcast_to(np.asarray(phi_h, dtype=np.float64), theta_h.shape)
    d = np.stack([np.sin(theta_d) * np.cos(phi_d), np.sin(theta_d) * np.sin(phi_d),
                  np.cos(theta_d)], -1)
    wi = _rot_z(_rot_y(d, theta_h), phi_h)
    h = np.stack([np.sin(theta_h) * np.cos(phi_h), np.sin(theta_h) * np.sin(phi_h),
                  np.cos(theta_h)], -1)
    wo = 2 * np.sum(wi * h, -1, keepdims=True) * h - wi
    return wi, wo


def half_diff_cartesian(theta_h, theta_d, phi_d):
    """Neural-field input: [h_xyz (phi_h = 0), d_xyz] as an (N, 6) array."""
    theta_h, theta_d, phi_d = (np.asarray(a, dtype=np.float64) for a in (theta_h, theta_d, phi_d))
    h = np.stack([np.sin(theta_h), np.zeros_like(theta_h), np.cos(theta_h)], -1)
    d = np.stack([np.sin(theta_d) * np.cos(phi_d), np.sin(theta_d) * np.sin(phi_d),
                  np.cos(theta_d)], -1)
    return np.concatenate([h, d], -1)


def cos_theta_i(theta_h, theta_d, phi_d):
    """cos of the incident elevation for Rusinkiewicz angles (phi_h irrelevant)."""
    return np.cos(theta_d) * np.cos(theta_h) - np.sin(theta_d) * np.cos(phi_d) * np.sin(theta_h)


def dirs_to_half_diff_torch(wi, wo):
    """Torch twin of `dirs_to_half_diff` (differentiable, any device), returns the 6-D
    Cartesian neural-field input [h (phi_h = 0), d] of shape (..., 6)."""
    import torch  # lazily: data jobs that only read/write tables skip torch's import cost

    h = torch.nn.functional.normalize(wi + wo, dim=-1)
    theta_h = torch.acos(h[..., 2].clamp(-1, 1))
    phi_h = torch.atan2(h[..., 1], h[..., 0])
    c, s = torch.cos(-phi_h), torch.sin(-phi_h)
    x = c * wi[..., 0] - s * wi[..., 1]
    y = s * wi[..., 0] + c * wi[..., 1]
    z = wi[..., 2]
    c, s = torch.cos(-theta_h), torch.sin(-theta_h)
    d = torch.stack([c * x + s * z, y, -s * x + c * z], -1)
    hc = torch.stack([torch.sin(theta_h), torch.zeros_like(theta_h), torch.cos(theta_h)], -1)
    return torch.cat([hc, d], -1)
