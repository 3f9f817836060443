"""`neumat sample --image` from noise against `--start S --refiner` (the retrieved training
material, refined), on a finished run's test-split conditioning images.

Every `--every`-th image of `samples/image/conditioning.npy` (linear HDR, the metric view) is
written as EXR and sampled twice with the same flags (render guidance and best of n as given):
from noise, and with `--start S --refiner`. Per image: the mean render PSNR of the kept draws
(`samples.tsv` `render_psnr`, the PSNR of the metric-view render against the image), the wall
time of each command, and the retrieved material's own PSNR (`conditions.image.score_draws`,
the retrieval baseline the start refines).

    OMP_NUM_THREADS=2 python benchmarks/cli_image_start.py --run results/real40 \\
        --render-step 0.5 --candidates 8 --unconstrained-candidates 8
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from neumat import cli, machine
from neumat.cli.run import Run
from neumat.conditions import image
from neumat.diffusion import dataset
from neumat.io import images


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, help="results/<run> with samples/image/ and the models")
    p.add_argument("--every", type=int, default=4, help="every k-th conditioning image (default 4)")
    p.add_argument("--start", type=float, default=0.05)
    p.add_argument("-n", type=int, default=4, help="samples per image")
    p.add_argument("--render-step", type=float, default=0.5)
    p.add_argument("--candidates", type=int, default=8)
    p.add_argument("--unconstrained-candidates", type=int, default=8)
    p.add_argument("--angles", type=int, default=16, help="bins for the retrieved material's clamp check")
    a = p.parse_args()
    run = Path(a.run)
    cond = np.load(run / "samples/image/conditioning.npy")
    source = pd.read_csv(run / "samples/image/samples.tsv", sep="\t").groupby("condition")["source"].first()
    w = np.load(run / "neumerl/weights.npy")
    activation = Run(run).activation()  # the run's NBRDF activation, as the CLI's
    names = dataset.read_manifest(run / "neumerl/manifest.tsv", len(w))["name"].to_numpy()
    flags = ["--render-step", a.render_step, "--candidates", a.candidates,
             "--unconstrained-candidates", a.unconstrained_candidates, "-n", a.n, "--no-binary"]
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for c in range(0, len(cond), a.every):
            exr = Path(d) / f"c{c:02d}.exr"
            images.write_exr(exr, cond[c])
            row = {"image": source[c]}
            for mode, extra in [("noise", []), ("start", ["--start", a.start, "--refiner"])]:
                out = Path(d) / f"{c}_{mode}"
                t0 = time.perf_counter()
                if cli.main([str(x) for x in ["sample", "--run", run, "--image", exr, *extra, *flags,
                                              "--out", out]]) != 0:
                    raise SystemExit(f"neumat sample failed on image {c} ({mode})")
                row[f"{mode} s"] = time.perf_counter() - t0
                t = pd.read_csv(out / "samples.tsv", sep="\t", keep_default_na=False)
                row[f"{mode} dB"] = t["render_psnr"].mean()
                if mode == "start":
                    row["retrieved"] = t["start"].iloc[0]
                    got = int(np.flatnonzero(names == row["retrieved"])[0])
                    psnr, _ = image.score_draws(w[got][None], image.load_image(exr, cond.shape[1])[None],
                                                a.angles, 0, activation)
                    row["retrieval dB"] = float(psnr[0])
            rows.append(row)
    df = pd.DataFrame(rows)
    print(df.to_string(index=False, float_format="%.2f"))
    print(f"mean: from noise {df['noise dB'].mean():.2f} dB, --start {a.start:g} --refiner "
          f"{df['start dB'].mean():.2f} dB, retrieval {df['retrieval dB'].mean():.2f} dB; start better "
          f"than noise on {(df['start dB'] > df['noise dB']).sum()} of {len(df)}, than retrieval on "
          f"{(df['start dB'] > df['retrieval dB']).sum()}; time {df['start s'].sum() / df['noise s'].sum():.3f}x "
          f"of from noise")
    print(f"[{machine.describe()}]")


if __name__ == "__main__":
    main()
