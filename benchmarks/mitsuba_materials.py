"""What a material costs the first time Mitsuba renders it (`neumat.render.mitsuba_bsdf`).

Renders --materials new neural fields (seeded random NBRDF inits), one sphere each at --res and
--spp under the generated sky, in a fresh process whose Dr.Jit kernel cache (~/.drjit, under a
temporary HOME) starts empty; then renders other new materials in a second fresh process on the
cache the first one filled. Each pass prints the seconds of every material and the kernels in
the cache. The bound is the second pass: a material that needs no compile costs its render.

When a material's weights were literals of the traced kernel (up to commit 5f49622), every new
material was a new LLVM compile: on AMD EPYC (AVX-512, 2 cores) this script there gave 0.25 s a
material in both passes and a cache grown by one kernel a material (10, then 16 kernels);
with opaque weights, 0.010-0.014 s a material after the first and 5 kernels whatever the
count (the first compile 1.07 s, once per cache).

    python benchmarks/mitsuba_materials.py --materials 6 --res 48 --spp 4
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PASS = """
import json, sys, time
import numpy as np, torch
from neumat import nbrdf
from neumat.render import mitsuba_bsdf as mb, scenes
variant = mb.select_variant("auto")
n, res, spp, seed = map(int, sys.argv[1:5])
w = nbrdf.init_weights(n, torch.Generator().manual_seed(seed)).numpy()
cfg = {"resolution": res, "spp": spp, "envmap_size": 16}
times = []
for i in range(n):
    t0 = time.perf_counter()
    scenes.render_spheres(w[i:i + 1], [f"bench{seed}-{i}"], cfg)
    times.append(time.perf_counter() - t0)
print(json.dumps({"variant": variant, "seconds": times}))
"""


def run_pass(home: Path, n: int, res: int, spp: int, seed: int) -> dict:
    env = dict(os.environ, HOME=str(home))
    out = subprocess.run([sys.executable, "-c", PASS, str(n), str(res), str(spp), str(seed)],
                         env=env, capture_output=True, text=True, check=True)
    rec = json.loads(out.stdout.strip().splitlines()[-1])
    rec["kernels"] = len(list((home / ".drjit").glob("*")))
    return rec


def main() -> None:
    from neumat import machine

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--materials", type=int, default=6)
    ap.add_argument("--res", type=int, default=48)
    ap.add_argument("--spp", type=int, default=4)
    a = ap.parse_args()
    print(f"machine: {machine.describe()}")
    with tempfile.TemporaryDirectory() as d:
        home = Path(d)
        t0 = time.perf_counter()
        cold = run_pass(home, a.materials, a.res, a.spp, seed=0)
        warm = run_pass(home, a.materials, a.res, a.spp, seed=1)  # other new materials
        total = time.perf_counter() - t0
    if cold["variant"].startswith("scalar"):
        print(f"variant {cold['variant']}: no LLVM backend here, no kernels to compile")
    bound = sorted(warm["seconds"])[len(warm["seconds"]) // 2]
    for name, rec in (("empty cache", cold), ("filled cache", warm)):
        s = rec["seconds"]
        rest = sorted(s[1:])[len(s[1:]) // 2] if len(s) > 1 else float("nan")
        print(f"{name:>12}: first material {s[0]:.3f} s, median of the other {len(s) - 1} "
              f"{rest:.3f} s ({rest / bound:.2f}x the bound); {rec['kernels']} kernels in the "
              f"cache after it; seconds {[round(x, 3) for x in s]}")
    print(f"bound (median material, filled cache): {bound:.3f} s; {a.materials} x 2 materials "
          f"at {a.res} px, {a.spp} spp, variant {cold['variant']}; {total:.1f} s in all")


if __name__ == "__main__":
    main()
