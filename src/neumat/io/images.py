"""Image files: OpenEXR (linear radiance) and what Pillow reads (sRGB), as linear float32 RGB.

No torch and no Mitsuba here: the workflow checks the user's conditioning images with this
module when it builds the DAG (`check_images`), and every Snakemake start, a Slurm job's
included, would pay for those imports.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

FORMATS = "PNG (or another format Pillow reads; sRGB) or OpenEXR (.exr; linear radiance)"


def write_exr(path: str | os.PathLike, img: np.ndarray) -> None:
    """Linear float32 RGB -> OpenEXR (ZIP), written to a temporary name and renamed."""
    import OpenEXR

    path = Path(path)
    tmp = path.with_name(path.stem + ".part.exr")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB": np.ascontiguousarray(img[..., :3], dtype=np.float32)}).write(str(tmp))
    os.replace(tmp, path)


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) float32 of an OpenEXR file's RGB layer; of RGBA without its alpha (renderers and
    compositors often write one); a luminance-only (Y) file as grey."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        layers = f.channels()
        for name in ("RGB", "RGBA"):
            if name in layers:
                return np.asarray(layers[name].pixels[..., :3], dtype=np.float32)
        if "Y" in layers:
            return np.repeat(np.asarray(layers["Y"].pixels, dtype=np.float32)[..., None], 3, -1)
        names = ", ".join(sorted(layers)) or "none"  # inside: closing the file empties `layers`
    raise ValueError(f"{path}: no RGB, RGBA or Y channels in this OpenEXR file (it has {names})")


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """The sRGB transfer function inverted (IEC 61966-2-1), values in [0, 1]."""
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def read_linear(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) float32 linear RGB: an .exr as stored, any other file decoded by Pillow as
    8-bit sRGB."""
    p = Path(path)
    if p.suffix.lower() == ".exr":
        return read_exr(p)
    from PIL import Image

    with Image.open(p) as im:
        srgb = np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0
    return srgb_to_linear(srgb).astype(np.float32)


def check_images(paths, key: str) -> None:
    """Before any job runs: each path of config `key` is a file, decodes as an image and holds
    only finite pixels. Otherwise an error naming the key, the file and what to give instead."""
    for path in paths:
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"config {key}: {p} is not a file (relative paths start at "
                                    f"{Path.cwd()}); give a {FORMATS} image")
        try:
            img = read_linear(p)
        except Exception as e:  # Pillow and OpenEXR raise several kinds for a damaged file
            raise ValueError(f"config {key}: {p} cannot be read as an image "
                             f"({type(e).__name__}: {e}); give a {FORMATS} image") from e
        bad = int((~np.isfinite(img)).any(-1).sum())
        if bad:
            raise ValueError(f"config {key}: {p} has {bad} of {img.shape[0] * img.shape[1]} pixels "
                             f"NaN or infinite; give an image of finite radiance")
