"""Bonn University DFMF BTF files (UBO2014 `*_resampled_W400xH400_L151xV151.btf`).

Layout (little endian), after the 10-byte signature "!DFMF08FCR":

    meta block   uint32 size (counted from the size field itself), uint32 version,
                 char[80] x 3 (setup, sensor, light source), float32 ppmm, float32[3] rgb scale,
                 version > 1: uint32 cosine flag; > 2: uint32 n + n bytes XML;
                 > 3: uint32 channels + per channel (uint32 n + n bytes name)
    sampling     uint32 views; per view: float32 (theta, phi) in radians, uint32 lights,
                 lights x float32 (theta, phi) - every view repeats the same light list
    extents      uint32 width, uint32 height; signature ending in 'R': uint32 n + n x 3x3 float32
    DFMF block   uint32 max components, int32 colour model, float32[3] mean, float32[3x3] matrix
    per channel  uint8 scalar size (2 half, 4 float, 8 double), uint32 components K,
                 uint32 rows, uint32 cols, K scalars S, rows x K scalars U, cols x K scalars S*V

Rows index (view, light) as view * lights + light, columns index texels as y * width + x;
channel value = U_c[row] . SV_c[texel]. Colour model 0 is plain RGB; 11 stores
(log(Y + eps), U / (Y + eps), V / (Y + eps)) in YUV with eps = 1e-5 (btflib `undecorrelate`).

`DFMF` memory-maps the file and decodes any batch of (texel, light, view) samples by reading
only the rows it needs, so a 1.3 GB UBO2014 file is never decompressed as a whole.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from neumat.logs import InputError

SIGNATURE = b"!DFMF08FCR"
DRR_EPS = 1e-5  # dynamic-range epsilon, hard-coded in every Bonn reader (not stored in the file)
YUV2RGB = np.array([[1.0, 0.0, 1.13983], [1.0, -0.39465, -0.5806], [1.0, 2.03211, 0.0]])
COLOR_MODELS = {0: "rgb", 11: "ylog_udivy_vdivy"}
SCALARS = {2: np.float16, 4: np.float32, 8: np.float64}


class DFMFError(InputError, ValueError):
    """A file that is not a readable DFMF BTF (message names the file)."""


@dataclass
class Channel:
    U: np.ndarray    # (rows, K) memmap
    SV: np.ndarray   # (cols, K) memmap
    S: np.ndarray    # (K,)


@dataclass
class Header:
    version: int
    views: np.ndarray        # (V, 2) float32 theta, phi (radians)
    lights: np.ndarray       # (L, 2)
    width: int
    height: int
    color_model: int
    color_mean: np.ndarray
    color_matrix: np.ndarray
    channel_names: list[str] = field(default_factory=lambda: ["R", "G", "B"])
    cosine_flag: int = 0
    data_offset: int = 0     # first byte of the per-channel blocks


class _Cursor:
    """Bounds-checked little-endian reads from a byte buffer; truncation names the file."""

    def __init__(self, buf, path):
        self.buf, self.path, self.pos = buf, path, 0

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.buf):
            raise DFMFError(f"{self.path}: truncated at byte {self.pos} (needs {n} more bytes, "
                            f"file has {len(self.buf)})")
        b = bytes(self.buf[self.pos:self.pos + n])
        self.pos += n
        return b

    def unpack(self, fmt: str):
        return struct.unpack("<" + fmt, self.take(struct.calcsize("<" + fmt)))

    def u32(self) -> int:
        return self.unpack("I")[0]

    def floats(self, n: int) -> np.ndarray:
        return np.frombuffer(self.take(4 * n), "<f4").copy()


def _read_header(cur: _Cursor) -> Header:
    sig = cur.take(len(SIGNATURE))
    if sig != SIGNATURE:
        raise DFMFError(f"{cur.path}: not a DFMF BTF (signature {sig!r}, expected {SIGNATURE!r})")
    start = cur.pos
    size, version = cur.unpack("II")
    cur.take(240)                          # setup, sensor, light source strings
    cur.unpack("4f")                       # ppmm, rgb scale
    cosine = cur.u32() if version > 1 else 0
    if version > 2:
        cur.take(cur.u32())                # measurement XML
    names = ["R", "G", "B"]
    if version > 3:
        names = [cur.take(cur.u32()).decode("latin-1") for _ in range(cur.u32())]
    if cur.pos - start != size:
        raise DFMFError(f"{cur.path}: inconsistent meta block (size field {size}, "
                        f"read {cur.pos - start} bytes)")
    n_views = cur.u32()
    if 12 * n_views > len(cur.buf) - cur.pos:  # each view: 2 floats and a light count at least
        raise DFMFError(f"{cur.path}: corrupt header: {n_views} views cannot fit in the "
                        f"{len(cur.buf) - cur.pos} bytes left")
    views, lights = np.zeros((n_views, 2), np.float32), None
    for v in range(n_views):
        views[v] = cur.floats(2)
        n_lights = cur.u32()
        ls = cur.floats(2 * n_lights).reshape(n_lights, 2)
        if lights is None:
            lights = ls
        elif len(ls) != len(lights):
            raise DFMFError(f"{cur.path}: view {v} has {len(ls)} lights, view 0 has {len(lights)}")
    for what, a in (("view", views), ("light", lights if lights is not None else views[:0])):
        if not np.isfinite(a).all():  # a NaN angle failed later, deep in a fit's fetch
            raise DFMFError(f"{cur.path}: corrupt header: {what} angles hold NaN or inf; the "
                            f"file is damaged: delete it and fetch it again")
    width, height = cur.unpack("II")
    n_rot = cur.u32()                      # signature ends in 'R': local-frame rotations
    cur.take(36 * n_rot)
    cur.u32()                              # max components over channels
    (model,) = cur.unpack("i")
    mean, matrix = cur.floats(3), cur.floats(9).reshape(3, 3)
    return Header(version, views, lights if lights is not None else np.zeros((0, 2), np.float32),
                  width, height, model, mean, matrix, names, cosine, cur.pos)


class DFMF:
    """Random-access reader. `decode(texel, light, view)` -> (N, 3) float32 RGB.

    roi = (x0, y0, w, h) restricts texel indices to a window (texel = y * w + x inside it)."""

    def __init__(self, path: str | os.PathLike, roi: tuple[int, int, int, int] | None = None):
        self.path = Path(path)
        if not self.path.is_file():
            raise DFMFError(f"{self.path}: no such BTF file")
        buf = np.memmap(self.path, np.uint8, mode="r")
        cur = _Cursor(buf, self.path)
        self.header = h = _read_header(cur)
        if h.color_model not in COLOR_MODELS:
            raise DFMFError(f"{self.path}: colour model {h.color_model} unsupported "
                            f"(supported: {sorted(COLOR_MODELS)})")
        self.n_views, self.n_lights = len(h.views), len(h.lights)
        self.channels = []
        for c in range(len(h.channel_names)):
            (scalar,) = cur.unpack("B")
            if scalar not in SCALARS:
                raise DFMFError(f"{self.path}: channel {c} has scalar size {scalar} (expected 2, 4, 8)")
            k, rows, cols = cur.unpack("III")
            if rows != self.n_views * self.n_lights or cols != h.width * h.height:
                raise DFMFError(
                    f"{self.path}: channel {c} matrix is {rows} x {cols}, expected "
                    f"{self.n_views * self.n_lights} (views x lights) x {h.width * h.height} texels")
            dt = np.dtype(SCALARS[scalar]).newbyteorder("<")
            arrays = []
            for shape in ((k,), (rows, k), (cols, k)):
                n = int(np.prod(shape)) * scalar
                if cur.pos + n > len(buf):
                    raise DFMFError(f"{self.path}: truncated in channel {c} (needs {cur.pos + n} "
                                    f"bytes, file has {len(buf)})")
                arrays.append(np.ndarray(shape, dt, buffer=buf, offset=cur.pos))
                cur.pos += n
            S, U, SV = arrays
            self.channels.append(Channel(U, SV, S))
        if len(self.channels) != 3:
            raise DFMFError(f"{self.path}: {len(self.channels)} channels, only RGB (3) supported")
        if cur.pos != len(buf):
            raise DFMFError(f"{self.path}: {len(buf) - cur.pos} unexpected trailing bytes")
        x0, y0, w, hh = roi if roi is not None else (0, 0, h.width, h.height)
        if x0 < 0 or y0 < 0 or x0 + w > h.width or y0 + hh > h.height or w < 1 or hh < 1:
            raise DFMFError(f"{self.path}: roi {roi} outside the {h.width} x {h.height} texels")
        self.roi, self.width, self.height = (x0, y0, w, hh), w, hh

    # -------------------------------------------------------------- geometry
    @property
    def n_texels(self) -> int:
        return self.width * self.height

    def file_texel(self, texel: np.ndarray) -> np.ndarray:
        """Texel index inside the roi -> column of the file's SV matrices."""
        x0, y0, w, _ = self.roi
        texel = np.asarray(texel, np.int64)
        return (y0 + texel // w) * self.header.width + x0 + texel % w

    def light_dirs(self) -> np.ndarray:
        return spherical_to_cartesian(self.header.lights)

    def view_dirs(self) -> np.ndarray:
        return spherical_to_cartesian(self.header.views)

    # -------------------------------------------------------------- decoding
    def decode(self, texel, light, view) -> np.ndarray:
        """RGB of N samples; texel, light, view broadcastable integer arrays -> (N, 3) float32."""
        texel, light, view = np.broadcast_arrays(*(np.asarray(a, np.int64).ravel()
                                                   for a in (texel, light, view)))
        for name, a, n in (("texel", texel, self.n_texels), ("light", light, self.n_lights),
                           ("view", view, self.n_views)):
            if a.size and (a.min() < 0 or a.max() >= n):
                raise IndexError(f"{self.path}: {name} index out of range [0, {n})")
        row, col = view * self.n_lights + light, self.file_texel(texel)
        # Sorted unique reads touch each needed file row once, in file order.
        ur, ir = np.unique(row, return_inverse=True)
        uc, ic = np.unique(col, return_inverse=True)
        raw = np.stack([np.einsum("nk,nk->n", ch.U[ur].astype(np.float32)[ir],
                                  ch.SV[uc].astype(np.float32)[ic]) for ch in self.channels], -1)
        self._finite(raw, "decoded values")
        return to_rgb(raw, self.header.color_model)

    def _finite(self, a: np.ndarray, what: str, rows: int | None = None) -> None:
        """Refuse NaN or inf in the factors: a fit would train on NaN loss and save the model.
        `rows`: counted in blocks of that many rows (a memory-mapped factor, not copied whole)."""
        step = rows or max(len(a), 1)
        bad = sum(int(np.size(a[s:s + step]) - np.isfinite(a[s:s + step]).sum())
                  for s in range(0, len(a), step))
        if bad:
            raise DFMFError(f"{self.path}: {what} hold NaN or inf ({bad} of {np.size(a)}); the "
                            f"file is damaged: delete it and fetch it again")

    def image(self, light: int, view: int) -> np.ndarray:
        """(height, width, 3) RGB texture for one light/view pair."""
        t = np.arange(self.n_texels)
        return self.decode(t, light, view).reshape(self.height, self.width, 3)

    def check_finite(self, rows: int = 1 << 16) -> None:
        """factors()' NaN / inf check on the whole file's memory-mapped factors, in blocks of
        rows: no float32 copy of a 400 x 400 texture's SV (the check of a fetched file)."""
        for c, ch in enumerate(self.channels):
            for what, a in (("U", ch.U), ("SV", ch.SV)):
                self._finite(a, f"channel {c}'s {what} factor", rows)

    def factors(self, dtype=np.float32):
        """In-memory (U list, SV list) restricted to the roi, for fast batched decoding."""
        cols = self.file_texel(np.arange(self.n_texels))
        U = [np.asarray(ch.U, dtype) for ch in self.channels]
        SV = [np.asarray(ch.SV[cols], dtype) for ch in self.channels]
        for c, (u, sv) in enumerate(zip(U, SV)):
            self._finite(u, f"channel {c}'s U factor")
            self._finite(sv, f"channel {c}'s SV factor")
        return U, SV


def to_rgb(raw: np.ndarray, model: int) -> np.ndarray:
    """Decorrelated channel values (..., 3) -> linear RGB (btflib `undecorrelate`)."""
    if model == 0:
        return raw.astype(np.float32)
    if model == 11:
        y = np.exp(raw[..., 0:1].astype(np.float64)) - DRR_EPS
        yuv = np.concatenate([y, raw[..., 1:3] * (y + DRR_EPS)], -1)
        return (yuv @ YUV2RGB.T).astype(np.float32)
    raise DFMFError(f"colour model {model} unsupported")


def from_rgb(rgb: np.ndarray, model: int) -> np.ndarray:
    """Inverse of `to_rgb` (for writing): RGB must be > -eps in luminance for model 11."""
    if model == 0:
        return rgb.astype(np.float32)
    if model == 11:
        yuv = rgb.astype(np.float32) @ np.linalg.inv(YUV2RGB).T.astype(np.float32)
        y = np.maximum(yuv[..., 0:1], 0.0) + np.float32(DRR_EPS)
        return np.concatenate([np.log(y), yuv[..., 1:3] / y], -1)
    raise DFMFError(f"colour model {model} unsupported")


def spherical_to_cartesian(tp: np.ndarray) -> np.ndarray:
    """(N, 2) theta, phi (radians) -> (N, 3) unit vectors, z up."""
    t, p = tp[:, 0].astype(np.float64), tp[:, 1].astype(np.float64)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)


def write_dfmf(path, U: list[np.ndarray], SV: list[np.ndarray], views: np.ndarray,
               lights: np.ndarray, width: int, height: int, color_model: int = 11,
               scalar: int = 2, S: list[np.ndarray] | None = None) -> None:
    """Write a DFMF file (version-3 meta block, no rotations). U[c] (V*L, K_c), SV[c] (W*H, K_c)."""
    if scalar not in SCALARS:
        raise ValueError(f"scalar size must be one of {sorted(SCALARS)}, got {scalar}")
    dt = np.dtype(SCALARS[scalar]).newbyteorder("<")
    meta = struct.pack("<I", 3) + b"neumat".ljust(80, b"\0") + b"synthetic".ljust(80, b"\0") \
        + b"analytic".ljust(80, b"\0") + struct.pack("<4f", 1.0, 1.0, 1.0, 1.0) \
        + struct.pack("<I", 0) + struct.pack("<I", 0)
    out = [SIGNATURE, struct.pack("<I", 4 + len(meta)), meta, struct.pack("<I", len(views))]
    light_block = struct.pack("<I", len(lights)) + np.asarray(lights, "<f4").tobytes()
    for v in np.asarray(views, "<f4"):
        out += [v.tobytes(), light_block]
    out += [struct.pack("<III", width, height, 0),
            struct.pack("<Ii", max(u.shape[1] for u in U), color_model),
            np.zeros(3, "<f4").tobytes(), np.eye(3, dtype="<f4").tobytes()]
    for c, (u, sv) in enumerate(zip(U, SV)):
        if u.shape[0] != len(views) * len(lights) or sv.shape[0] != width * height \
                or u.shape[1] != sv.shape[1]:
            raise ValueError(f"channel {c}: U {u.shape} / SV {sv.shape} do not match "
                             f"{len(views)} views x {len(lights)} lights x {width * height} texels")
        s = np.ones(u.shape[1]) if S is None else S[c]
        out += [struct.pack("<BIII", scalar, u.shape[1], u.shape[0], sv.shape[0]),
                np.asarray(s, dt).tobytes(), np.ascontiguousarray(u, dt).tobytes(),
                np.ascontiguousarray(sv, dt).tobytes()]
    tmp = Path(f"{path}.tmp")
    tmp.write_bytes(b"".join(out))
    tmp.replace(path)
