"""NBRDF passes over many materials at shared points, in the library's blocks
(`nbrdf.materials_per_pass`, about 2^15 points a pass) against 64 materials a pass (the
baseline, in the same run):
(1) the plausibility checks of synthesised NBRDFs (`neumat.diffusion.plausibility`: clamped
    negatives and largest value at 20,000 MERL bins, directional albedo on 8 x 64 x 64
    directions; rules `diffusion_plausibility`, `conditions_eval`), whose value checks took all
    materials in one pass and the albedo 64 before 2026-11-26;
(2) Table 2's BRDF values of the same materials at 20,000 bins
    (`neumat.metrics.distances.field_values`), 64 a pass before;
(3) the category statistics of the same materials at 65,536 bins (`neumat.constrained.
    field_stats`: `neumat sample --category`'s and rule `constrained_classify`'s), 2^22
    field-bin pairs a pass before 2026-11-26 (here: all 64 materials at once);
(4) metric-view renders of the same materials at 128^2 (`neumat.render.sphere.render_fields`,
    every metric, figure and conditioning render), 2^24 floats of activations a pass before
    2026-11-26 (51 materials); a material's pixels then move by float32 rounding, as they do
    with its place in a batch (the shared-input product's column blocking).
Prints the best wall time, CPU seconds split user/system, the minor page faults, the ratio, the
passes' rate as a fraction of this machine's fp32 sgemm rate, and the largest difference
between the two results (float64 rounding in the albedo sums and the statistics' sums; the BRDF
values must be equal),
with the ISA and the CPU model.

    OMP_NUM_THREADS=1 python benchmarks/plausibility.py [--materials 64] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(__file__))
from merl_export import header, machine_line, measure, row  # noqa: E402

from neumat import constrained, nbrdf  # noqa: E402
from neumat.render import sphere  # noqa: E402
from neumat.metrics import distances  # noqa: E402
from neumat.diffusion import plausibility as P  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--materials", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    peak = machine_line()
    w = nbrdf.init_weights(a.materials, torch.Generator().manual_seed(1)).numpy() * 2
    n_points = 20000 + 8 * 64 * 64
    flop = a.materials * n_points * 2 * sum(i * o for i, o in nbrdf.LAYERS)
    print(f"{a.materials} materials x {n_points} points, {flop / 1e9:.2f} GFLOP in NBRDF passes")
    header()
    base, t_base = measure(lambda: P.plausibility(w, reference_max=1.0, block=64), a.repeat)
    new, t_new = measure(lambda: P.plausibility(w, reference_max=1.0), a.repeat)
    row("64 materials a pass", base, rate=flop / base[0] / peak)
    row("library blocks", new, base, rate=flop / new[0] / peak)
    num = t_base.select_dtypes("number")
    diff = (num - t_new[num.columns]).abs().max()
    same = t_base.select_dtypes("bool").equals(t_new[t_base.select_dtypes("bool").columns])
    print(f"largest difference: {diff.max():.1e} ({diff.idxmax()}); flags equal: {same}")
    bins = distances.brdf_sample(20000, 0)
    flop = a.materials * len(bins) * 2 * sum(i * o for i, o in nbrdf.LAYERS)
    base, v_base = measure(lambda: distances.field_values(w, bins, chunk=64), a.repeat)
    new, v_new = measure(lambda: distances.field_values(w, bins), a.repeat)
    row("field_values, 64 materials a pass", base, rate=flop / base[0] / peak)
    row("field_values, library blocks", new, base, rate=flop / new[0] / peak)
    print(f"field values equal: {torch.equal(v_base, v_new)}")
    bins = constrained.grid_bins(65536, 0)
    flop = a.materials * len(bins) * 2 * sum(i * o for i, o in nbrdf.LAYERS)
    base, s_base = measure(lambda: constrained.field_stats(w, bins=bins, points_per_pass=1 << 22),
                           a.repeat)
    new, s_new = measure(lambda: constrained.field_stats(w, bins=bins), a.repeat)
    row("field_stats, 2^22 pairs a pass", base, rate=flop / base[0] / peak)
    row("field_stats, library blocks", new, base, rate=flop / new[0] / peak)
    cols = list(constrained.STAT_COLUMNS)
    rel = ((s_base[cols] - s_new[cols]).abs() / s_base[cols].abs().clip(lower=1e-300)).max().max()
    print(f"statistics: largest relative difference {rel:.1e}; counts above the diffuse "
          f"bound equal: {s_base['n_above'].equals(s_new['n_above'])}")
    view = len(sphere.sphere_view(128))
    flop = a.materials * view * 2 * sum(i * o for i, o in nbrdf.LAYERS)
    old = max(1, sphere._CHUNK_FLOATS // (view * 21))
    base, r_base = measure(lambda: sphere.render_fields(w, 128, chunk=old), a.repeat)
    new, r_new = measure(lambda: sphere.render_fields(w, 128), a.repeat)
    row(f"renders, {old} materials a pass", base, rate=flop / base[0] / peak)
    row("renders, library blocks", new, base, rate=flop / new[0] / peak)
    print(f"renders: largest difference {(r_base - r_new).abs().max().item():.1e} "
          f"(pixel values up to {r_base.abs().max().item():.2g})")


if __name__ == "__main__":
    main()
