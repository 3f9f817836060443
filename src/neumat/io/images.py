"""Image files: OpenEXR (linear radiance) and what Pillow reads (sRGB), as linear float32 RGB.

No torch and no Mitsuba here: the workflow checks the user's conditioning images with this
module when it builds the DAG (`check_images`), and every Snakemake start, a Slurm job's
included, would pay for those imports.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

FORMATS = ("PNG (8- or 16-bit, or another format Pillow reads as 8-bit colour; sRGB) or OpenEXR "
           "(.exr; linear radiance)")


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
    compositors often write one); a luminance-only (Y) file as grey. A luminance/chroma file
    (Y, RY, BY) is refused: read as grey, its colour would be lost silently."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        layers = f.channels()
        for name in ("RGB", "RGBA"):
            if name in layers:
                return np.asarray(layers[name].pixels[..., :3], dtype=np.float32)
        if "Y" in layers and ("RY" in layers or "BY" in layers):
            raise ValueError(f"{path}: a luminance/chroma (Y, RY, BY) OpenEXR file; write it as "
                             f"RGB (e.g. `exrmultipart` or any compositor) and give that")
        if "Y" in layers:
            return np.repeat(np.asarray(layers["Y"].pixels, dtype=np.float32)[..., None], 3, -1)
        names = ", ".join(sorted(layers)) or "none"  # inside: closing the file empties `layers`
    raise ValueError(f"{path}: no RGB, RGBA or Y channels in this OpenEXR file (it has {names})")


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """The sRGB transfer function inverted (IEC 61966-2-1), values in [0, 1]."""
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def read_linear(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) float32 linear RGB: an .exr as stored; any other file decoded by Pillow as sRGB,
    8-bit colour or 16-bit grey (Pillow's convert("RGB") clips 16-bit values to 0..255: mid-grey
    read as white), with an alpha channel composited over black, the metric view's background
    (dropped, a cut-out's transparent pixels kept whatever colour they were stored with).
    Float images other than EXR (a float TIFF) are refused: their encoding is not known."""
    p = Path(path)
    if p.suffix.lower() == ".exr":
        return read_exr(p)
    from PIL import Image

    with Image.open(p) as im:
        if im.mode.startswith("I"):  # 16- (I;16*) or 32-bit (I) integer grey
            a = np.asarray(im, dtype=np.float64)
            if a.min() < 0 or a.max() > 65535:
                raise ValueError(f"{p}: a {im.mode} image with values outside 0..65535; give "
                                 f"an 8- or 16-bit sRGB image or an OpenEXR file")
            srgb, alpha = np.repeat(a[..., None] / 65535.0, 3, -1), None
        elif im.mode == "F":
            raise ValueError(f"{p}: a floating-point {p.suffix} image, whose encoding (linear "
                             f"or sRGB) is unknown; give linear radiance as OpenEXR (.exr)")
        else:
            has_alpha = "A" in im.getbands() or "transparency" in im.info
            rgba = np.asarray(im.convert("RGBA" if has_alpha else "RGB"), dtype=np.float64) / 255.0
            srgb, alpha = rgba[..., :3], (rgba[..., 3:] if has_alpha else None)
    lin = srgb_to_linear(srgb)
    if alpha is not None:  # straight alpha: over black in linear light
        lin = lin * alpha
    return lin.astype(np.float32)


def fault(img: np.ndarray) -> str | None:
    """What makes (H, W, 3) linear RGB unusable as a conditioning image, or None: NaN or infinite
    pixels, negative radiance (an EXR from a denoiser or a difference; clamp it at 0), or one
    value everywhere (a blank or 1-pixel file: no material to see). The messages start with
    what the image has, for a caller to put the file's name before."""
    n = img.shape[0] * img.shape[1]
    bad = int((~np.isfinite(img)).any(-1).sum())
    if bad:
        return f"has {bad} of {n} pixels NaN or infinite; give an image of finite radiance"
    neg = int((img < 0).any(-1).sum())
    if neg:
        return (f"has {neg} of {n} pixels with negative radiance (down to {float(img.min()):.3g}); "
                f"clamp them at 0 and give that")
    if n and bool((img == img.reshape(-1, 3)[0]).all()):
        return (f"has one value in all {n} pixels, so it shows no material; give a render of one "
                f"sphere filling the frame")
    return None


def check_images(paths, key: str) -> None:
    """Before any job runs: each path of config `key` is a file, decodes as an image and has no
    `fault`. Otherwise an error naming the key, the file and what to give instead."""
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
        why = fault(img)
        if why:
            raise ValueError(f"config {key}: {p} {why}")
