"""What a material costs Mitsuba (`neumat.render.mitsuba_bsdf`): its numbers as opaque inputs
of a kernel shared by every material, against literals baked into a kernel of its own.

New materials: --materials seeded random NBRDF inits, one sphere each at --res and --spp under
the generated sky, each mode in a fresh process whose Dr.Jit kernel cache (~/.drjit, under a
temporary HOME) starts empty; the seconds of every material and the kernels in the cache after.
Large renders: one material at --big-res and --big-spp in each mode, timed once its kernel is
compiled; nanoseconds per camera sample, and the sample count from which a literal kernel's
compile pays for itself (`mitsuba_bsdf.INLINE_SAMPLES` picks the mode by it). The bound: no
FLOP count applies (Mitsuba's LLVM JIT fuses the NBRDF into the path tracer's kernel), so each
mode's sample rate is put against the same large render with Mitsuba's `diffuse` BSDF in the same
run, the renderer's cost without the NBRDF (a material renders no faster than that).

    python benchmarks/mitsuba_materials.py --materials 6 --res 48 --spp 4 --big-res 256 --big-spp 64
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

PASS = """
import json, sys, time
import numpy as np, torch
from neumat import nbrdf
from neumat.render import mitsuba_bsdf as mb, scenes
variant = mb.select_variant("auto")
n, res, spp, seed, inline, repeat, diffuse = map(int, sys.argv[1:8])
w = nbrdf.init_weights(n, torch.Generator().manual_seed(seed)).numpy()
env = scenes.sky_envmap(16)
times = []
for i in range(n):
    s = scenes.sphere_scene(mb.Material(f"bench{seed}-{i}", weights=w[i]), res, spp, env)
    s["object"]["bsdf"]["inline"] = bool(inline)
    if diffuse:  # the floor: the same scene with Mitsuba's cheapest BSDF
        s["object"]["bsdf"] = {"type": "diffuse"}
    for _ in range(repeat):
        t0 = time.perf_counter()
        scenes.render(s)
        times.append(time.perf_counter() - t0)
print(json.dumps({"variant": variant, "seconds": times}))
"""


def run(home: Path, n: int, res: int, spp: int, inline: bool, repeat: int = 1,
        diffuse: bool = False) -> dict:
    env = dict(os.environ, HOME=str(home))
    args = (n, res, spp, 0, int(inline), repeat, int(diffuse))
    out = subprocess.run([sys.executable, "-c", PASS, *map(str, args)],
                         env=env, capture_output=True, text=True, check=True)
    rec = json.loads(out.stdout.strip().splitlines()[-1])
    rec["kernels"] = len(list((home / ".drjit").glob("*")))
    return rec


def median(xs):
    return sorted(xs)[len(xs) // 2]


def main() -> None:
    from neumat import machine
    from neumat.render import mitsuba_bsdf as mb

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--materials", type=int, default=6)
    ap.add_argument("--res", type=int, default=48)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--big-res", type=int, default=256)
    ap.add_argument("--big-spp", type=int, default=64)
    a = ap.parse_args()
    print(f"machine: {machine.describe()}")
    small, big = {}, {}
    for inline in (False, True):
        with tempfile.TemporaryDirectory() as d:
            small[inline] = run(Path(d), a.materials, a.res, a.spp, inline)
            big[inline] = run(Path(d), 1, a.big_res, a.big_spp, inline, repeat=3)
    with tempfile.TemporaryDirectory() as d:
        floor = run(Path(d), 1, a.big_res, a.big_spp, False, repeat=3, diffuse=True)
    print(f"variant {small[False]['variant']}")
    name = {False: "opaque (shared kernel)", True: "literals (kernel each)"}
    print(f"{a.materials} new materials at {a.res} px, {a.spp} spp, empty kernel cache:")
    for inline in (False, True):
        s = small[inline]["seconds"]
        print(f"  {name[inline]:>23}: first {s[0]:.3f} s, median of the rest {median(s[1:]):.3f} s; "
              f"{small[inline]['kernels']} kernels in the cache; {[round(x, 3) for x in s]}")
    n = a.big_res ** 2 * a.big_spp
    ns = {k: median(big[k]["seconds"][1:]) / n * 1e9 for k in big}
    ns_floor = median(floor["seconds"][1:]) / n * 1e9
    print(f"one material at {a.big_res} px, {a.big_spp} spp ({n} samples), compiled:")
    for inline in (False, True):
        print(f"  {name[inline]:>23}: {median(big[inline]['seconds'][1:]):.3f} s, {ns[inline]:.0f} ns "
              f"a sample ({ns[inline] / ns[True]:.2f}x literals); first render "
              f"{big[inline]['seconds'][0]:.3f} s; {ns_floor / ns[inline]:.0%} of the diffuse "
              "BSDF's sample rate")
    print(f"  {'diffuse BSDF (bound)':>23}: {median(floor['seconds'][1:]):.3f} s, "
          f"{ns_floor:.0f} ns a sample; no FLOP bound: Mitsuba's LLVM JIT fuses the NBRDF into "
          "the path tracer's kernel")
    compile_s = median(small[True]["seconds"][1:]) - median(small[False]["seconds"][1:])
    if ns[False] > ns[True]:
        print(f"a literal kernel's compile ({compile_s:.3f} s, from the small renders) pays for "
              f"itself from {compile_s / ((ns[False] - ns[True]) * 1e-9):.3g} samples; "
              f"mitsuba_bsdf.INLINE_SAMPLES = {mb.INLINE_SAMPLES}")


if __name__ == "__main__":
    main()
