"""`neumat render`, and the Mitsuba 3 scene that `sample` writes."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from neumat.cli.run import CLIError, _progress, check_out_dir

def _write_scene(out: Path, n: int, activation: str, resolution: int = 512, spp: int = 64) -> Path:
    """scene.xml: the samples as spheres in a grid under sky.exr, each loading its row of
    weights.npy through the neumat_brdf plugin."""
    from neumat.io.images import write_exr
    from neumat.render import scenes
    write_exr(out / "sky.exr", scenes.sky_envmap(128))
    cols = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    shapes = []
    for i in range(n):
        r, c = divmod(i, cols)
        x, y = 2.4 * (c - (cols - 1) / 2), -2.4 * (r - (rows - 1) / 2)
        shapes.append(f"""    <shape type="sphere">
        <point name="center" x="{x:.3f}" y="{y:.3f}" z="0"/>
        <float name="radius" value="1"/>
        <bsdf type="neumat_brdf">
            <string name="filename" value="weights.npy"/>
            <integer name="index" value="{i}"/>
            <string name="activation" value="{activation}"/>
        </bsdf>
    </shape>""")
    dist = 4.2 * max(cols, rows)
    xml = f"""<?xml version="1.0"?>
<!-- neumat samples: load with neumat.render.mitsuba_bsdf.select_variant() (registers the
     neumat_brdf plugin) then mitsuba.load_file(this file), or `neumat render scene.xml --out x.png` -->
<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="4"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="30"/>
        <transform name="to_world"><lookat origin="0, {0.15 * dist:.3f}, {dist:.3f}" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="{resolution}"/><integer name="height" value="{resolution}"/></film>
        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
    </sensor>
    <emitter type="envmap"><string name="filename" value="sky.exr"/></emitter>
{chr(10).join(shapes)}
</scene>
"""
    path = out / "scene.xml"
    path.write_text(xml)
    return path


def inline_if_large(text: str, threshold: int) -> str:
    """The scene XML with its `neumat_brdf` materials baked into the kernel (their `inline`
    property) when the render has `threshold` camera samples or more, as the workflow's scenes do
    (`mitsuba_bsdf.INLINE_SAMPLES`); a file that sets `inline` itself is left as it is."""
    def first(name):
        m = re.search(rf'name="{name}" value="(\d+)"', text)
        return int(m.group(1)) if m else 0
    if 'name="inline"' in text or first("width") * first("height") * first("sample_count") < threshold:
        return text
    return re.sub(r'(<bsdf type="neumat_brdf"\s*>)', r'\1<boolean name="inline" value="true"/>', text)


def _render_scene(xml: Path, png: Path, variant: str, resolution: int | None, spp: int | None):
    from neumat.render import mitsuba_bsdf as mb  # before mitsuba: it points Dr.Jit at libLLVM
    from neumat.render import scenes
    mb.select_variant(variant)
    import mitsuba as mi
    text = xml.read_text()
    if resolution:  # another size or sample count than the file's: a modified copy beside it
        text = re.sub(r'(name="(?:width|height)" value=")\d+', rf"\g<1>{resolution}", text)
    if spp:
        text = re.sub(r'(name="sample_count" value=")\d+', rf"\g<1>{spp}", text)
    tmp = xml.with_name(f".{xml.stem}.render.xml")  # beside it: relative file names resolve
    tmp.write_text(inline_if_large(text, mb.INLINE_SAMPLES))
    try:
        scene = mi.load_file(str(tmp))
    except Exception as e:
        raise CLIError(f"{xml}: Mitsuba could not load the scene ({e})")
    finally:
        tmp.unlink()
    sensor = scene.sensors()[0]
    img = np.asarray(mi.render(scene, sensor=sensor, seed=0), dtype=np.float32)[..., :3]
    scenes.write_png(png, img)


def _check_out(path: str) -> Path:
    """--out: a .png whose directory can be made (checked before rendering)."""
    out = Path(path)
    if out.suffix.lower() != ".png":
        raise CLIError(f"--out {path}: give a PNG file name, ending in .png")
    if out.is_dir():
        raise CLIError(f"--out {path}: a directory; give a PNG file name, e.g. {out / 'render.png'}")
    check_out_dir(out.parent, f"--out {path}")
    return out


def _read_weights(f: Path) -> np.ndarray:
    """(N, 675) NBRDF weights from a .npy file (no pickled objects), or a CLIError."""
    from neumat import nbrdf
    want = (f"expected NBRDF weights (N, {nbrdf.N_PARAMS}) or ({nbrdf.N_PARAMS},) of numbers, "
            f"e.g. samples/<set>/weights.npy or neumerl/weights.npy")
    try:
        w = np.load(f)  # allow_pickle=False: a pickle would run code
    except (OSError, ValueError, EOFError) as e:
        why = ("not an array numpy can read without unpickling (neumat loads no pickles: they "
               "can run code)" if "pickle" in str(e) else f"not a .npy array ({type(e).__name__}: {e})")
        raise CLIError(f"{f}: {why}; {want}") from None
    if not isinstance(w, np.ndarray) or w.dtype.kind not in "fiu":
        raise CLIError(f"{f}: holds {getattr(w, 'dtype', type(w).__name__)}, not numbers; {want}")
    if w.ndim not in (1, 2) or w.shape[-1] != nbrdf.N_PARAMS or w.size == 0:
        raise CLIError(f"{f}: shape {w.shape}; {want}")
    w = w.reshape(-1, nbrdf.N_PARAMS)
    bad = np.flatnonzero(~np.isfinite(w).all(1))
    if len(bad):  # they rendered as black spheres, and the command succeeded
        raise CLIError(f"{f}: rows {bad[:5].tolist()}{' ...' if len(bad) > 5 else ''} hold NaN "
                       f"or inf ({len(bad)} of {len(w)}); {want}")
    return w


def cmd_render(args) -> int:
    import torch

    from neumat.render import sphere
    from neumat.render.gallery import gallery

    f = Path(args.file)
    if not f.exists():
        raise CLIError(f"{f}: no such file (give a MERL .binary, a weights .npy or a scene .xml)")
    out = _check_out(args.out)
    if f.suffix == ".xml":  # the file's own size and sample count unless asked
        out.parent.mkdir(parents=True, exist_ok=True)
        _render_scene(f, out, args.variant, args.resolution, args.spp)
        print(f"wrote {out} (Mitsuba)")
        return 0
    args.resolution = 128 if args.resolution is None else args.resolution
    args.spp = 32 if args.spp is None else args.spp
    if f.suffix == ".binary":
        from neumat.io import merl
        try:
            table = merl.read_merl(f)
        except merl.MerlFormatError as e:
            raise CLIError(f"{e}; a MERL .binary has a 12-byte header (90, 90, 180) and 3 float64 planes")
        materials, labels = [("table", table)], [f.stem]
    elif f.suffix == ".npy":
        w = _read_weights(f)
        idx = [args.index] if args.index is not None else list(range(min(len(w), args.max)))
        if any(not 0 <= i < len(w) for i in idx):
            raise CLIError(f"--index {args.index}: {f} holds {len(w)} samples (0..{len(w) - 1})")
        materials, labels = [("weights", w[i]) for i in idx], [f"{f.stem}[{i}]" for i in idx]
    else:
        raise CLIError(f"{f}: unknown kind {f.suffix!r}; give a MERL .binary, a weights .npy or a scene .xml")
    act = args.activation or "relu"
    if args.mitsuba:
        from neumat.render import mitsuba_bsdf as mb
        from neumat.render import scenes
        mb.select_variant(args.variant)
        env = scenes.sky_envmap(128)
        imgs = []
        with _progress(len(materials), "Mitsuba") as bar:
            for k, (kind, v) in enumerate(materials):
                m = mb.Material(f"cli{k}", activation=act, **{kind: v})
                imgs.append(scenes.render(scenes.sphere_scene(m, args.resolution, args.spp, env)))
                bar.update(1)
    else:
        if materials[0][0] == "table":
            imgs = sphere.render_tables(materials[0][1][None], args.resolution)
        else:
            imgs = sphere.render_fields(np.stack([v for _, v in materials]), args.resolution, act)
        imgs = list(sphere.tonemap(imgs))
    out.parent.mkdir(parents=True, exist_ok=True)
    if len(imgs) == 1:
        from PIL import Image
        img = imgs[0] if imgs[0].dtype == np.uint8 else sphere.tonemap(torch.as_tensor(imgs[0])[None])[0]
        Image.fromarray(img).save(out)
    else:
        gallery(imgs, labels, out, ncols=min(len(imgs), 8))
    print(f"wrote {out} ({'Mitsuba' if args.mitsuba else 'metric view'}, {len(imgs)} material(s))")
    return 0
