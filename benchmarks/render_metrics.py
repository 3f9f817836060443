"""Renderer and Table-2 metric speed, on realistic materials: the 100 published NBRDF fits of
MERL (Sztrajman et al. 2021; unzip ../shared/data/merl_nbrdf.zip, or set NBRDF_DIR) and their
RGB permutations. Baselines run in the same process:

  renders   : batched `render_fields` vs one material per call; each one's NBRDF matmul FLOP
              per wall second as a fraction of the fp32 sgemm rate measured here (as
              plausibility.py counts them)
  distances : the vectorised pairwise matrices vs a naive per-pair loop (numpy for BRDF-L1,
              RMSE, NegPSNR; scikit-image `structural_similarity` for NegSSIM) on a subset of
              pairs, extrapolated to the 3 x n^2 pairs the evaluation needs; values compared
  evaluation: wall time of the 12 set metrics (MMD/COV/1-NNA x 4 distances) for n x n materials
  mitsuba   : seconds per figure (sphere / mixed plane / normal-mapped) at --mi-res, --mi-spp

  OMP_NUM_THREADS=2 python benchmarks/render_metrics.py --n 120 --resolution 128
Writes benchmarks/out/render_metrics/<resolution>.json (with the machine line) and a gallery PNG.
"""

import argparse
import glob
import itertools
import json
import os
import time
from pathlib import Path

import numpy as np
import torch
from skimage.metrics import structural_similarity

from neumat import machine, nbrdf
from neumat.metrics import distances as D
from neumat.metrics import evaluate, sets
from neumat.render import gallery, sphere

ROOT = Path(__file__).resolve().parents[1]
NBRDF_DIR = Path(os.environ.get("NBRDF_DIR", "/tmp/nbrdfzip/merl_nbrdf"))


def load_fits():
    """(names, (100, 675) float32) from the Keras .h5 files (kernels are (in, out): transpose)."""
    import h5py
    files = sorted(glob.glob(str(NBRDF_DIR / "*.h5")))
    if not files:
        raise FileNotFoundError(f"{NBRDF_DIR}: no .h5 NBRDF files (unzip merl_nbrdf.zip, set NBRDF_DIR)")
    ws = []
    for f in files:
        with h5py.File(f, "r") as h:
            parts = []
            for n in ("dense_1", "dense_2", "dense_3"):
                g = h[n][n]
                parts += [g["kernel:0"][()].T.ravel(), g["bias:0"][()].ravel()]
        ws.append(np.concatenate(parts).astype(np.float32))
    return [Path(f).stem for f in files], np.stack(ws)


def permuted(w, perm):
    """The field of the RGB-permuted material: permute the rows of W3 and b3."""
    w = w.copy()
    W3 = w[:, -66:-3].reshape(-1, 3, 21)
    w[:, -66:-3] = W3[:, list(perm)].reshape(-1, 63)
    w[:, -3:] = w[:, -3:][:, list(perm)]
    return w


def timed(fn, *args, **kw):
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    return out, time.perf_counter() - t0


def naive_pairs(rv, sv, ri, si, pairs):
    """Per-pair loop over `pairs` (i, j) -> {distance: (values, seconds)}."""
    out = {}
    a, b = rv.numpy(), sv.numpy()
    x, y = ri.numpy(), si.numpy()
    fns = {"BRDF-L1": lambda i, j: np.abs(a[i] - b[j]).mean(),
           "RMSE": lambda i, j: np.sqrt(((x[i] - y[j]) ** 2).mean()),
           "NegPSNR": lambda i, j: 10 * np.log10(max(((x[i] - y[j]) ** 2).mean(), D.PSNR_FLOOR_MSE)),
           "NegSSIM": lambda i, j: -structural_similarity(x[i], y[j], channel_axis=-1, data_range=1)}
    for name, f in fns.items():
        t0 = time.perf_counter()
        vals = np.array([f(i, j) for i, j in pairs])
        out[name] = (vals, time.perf_counter() - t0)
    return out


def mitsuba_figures(w, names, res, spp):
    from neumat.render import mitsuba_bsdf as mb
    from neumat.render import scenes
    variant = mb.select_variant("auto")
    mats = [mb.Material(n, weights=w[i]) for i, n in enumerate(names)]
    env = scenes.sky_envmap(128)
    out, imgs = {"variant": variant, "resolution": res, "spp": spp}, []
    for name, scene in [("sphere", scenes.sphere_scene(mats[0], res, spp, env)),
                        ("mixed_plane", scenes.mixed_plane_scene(mats[0], mats[1], res, spp, env,
                                                                 scenes.blend_mask(2 * res))),
                        ("normal_mapped", scenes.normal_mapped_scene(mats[1], res, spp, env,
                                                                     scenes.ripple_normals(2 * res)))]:
        img, sec = timed(scenes.render, scene)
        out[f"{name}_s"] = round(sec, 2)
        imgs.append(img)
    return out, imgs


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=120)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--brdf-samples", type=int, default=65536)
    ap.add_argument("--naive-rows", type=int, default=4, help="reference rows of the naive loop")
    ap.add_argument("--mi-res", type=int, default=256)
    ap.add_argument("--mi-spp", type=int, default=64)
    ap.add_argument("--no-mitsuba", action="store_true")
    args = ap.parse_args()
    print(f"machine: {machine.describe()}", flush=True)
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    peak = machine.sgemm_peak()[0]  # at these threads, per wall second as the renders are timed
    outdir = ROOT / "benchmarks/out/render_metrics"
    outdir.mkdir(parents=True, exist_ok=True)

    names, w = load_fits()
    perms = list(itertools.permutations(range(3)))[1:]
    pool = np.concatenate([w] + [permuted(w, p) for p in perms])  # 600 realistic fields
    order = np.random.default_rng(0).permutation(len(pool))
    ref, smp = pool[order[:args.n]], pool[order[args.n:2 * args.n]]
    res = {"n": args.n, "resolution": args.resolution, "threads": torch.get_num_threads(),
           "machine": machine.describe(), "sgemm_flop_per_s": peak}

    # renders: batched vs one at a time
    sphere.sphere_view(args.resolution)
    imgs, t_batch = timed(sphere.render_fields, np.concatenate([ref, smp]), args.resolution)
    k = 16
    _, t_loop = timed(lambda: [sphere.render_fields(ref[i:i + 1], args.resolution) for i in range(k)])
    res["renders_per_s"] = 2 * args.n / t_batch
    res["renders_per_s_one_at_a_time"] = k / t_loop
    flop = len(sphere.sphere_view(args.resolution)) * 2 * sum(i * o for i, o in nbrdf.LAYERS)
    res["renders_of_sgemm"] = res["renders_per_s"] * flop / peak
    res["renders_of_sgemm_one_at_a_time"] = res["renders_per_s_one_at_a_time"] * flop / peak
    gallery.gallery(list(imgs[:16].numpy()), [names[i % 100] if i < 100 else f"perm of {names[i % 100]}"
                                             for i in order[:16]], outdir / f"gallery_{args.resolution}.png")

    # the full evaluation (12 set metrics, no FID)
    bins = D.brdf_sample(args.brdf_samples, 0)
    t0 = time.perf_counter()
    vals = [D.field_values(x, bins) for x in (ref, smp)]
    srgb = [sphere.to_srgb(sphere.render_fields(x, args.resolution)) for x in (ref, smp)]
    t_inputs = time.perf_counter() - t0
    mats, t_dist = timed(evaluate.distance_matrices, *vals, *srgb)
    table, t_sets = timed(evaluate.set_metric_rows, mats)
    res["eval_inputs_s"], res["eval_distances_s"], res["eval_set_metrics_s"] = t_inputs, t_dist, t_sets
    res["eval_total_s"] = t_inputs + t_dist + t_sets
    res["table"] = {f"{r.metric} {r.distance}": r.value for r in table.itertuples()}

    # naive per-pair loop on a subset of the R x S pairs, extrapolated to 3 n^2 pairs
    pairs = [(i, j) for i in range(args.naive_rows) for j in range(args.n)]
    naive = naive_pairs(vals[0], vals[1], srgb[0], srgb[1], pairs)
    n_pairs = 3 * args.n ** 2
    res["naive"] = {}
    for name, (v, sec) in naive.items():
        vec = mats[name][2][:args.naive_rows].numpy().ravel()
        est = sec / len(pairs) * n_pairs
        res["naive"][name] = {"pairs": len(pairs), "seconds": sec, "extrapolated_s": est,
                              "max_abs_diff": float(np.abs(vec - v).max())}
    res["naive_total_extrapolated_s"] = sum(v["extrapolated_s"] for v in res["naive"].values())
    res["speedup_distances"] = res["naive_total_extrapolated_s"] / t_dist

    # set metrics: vectorised vs Python loops on the same matrices
    d_rr, d_ss, d_rs = (m.numpy() for m in mats["RMSE"])
    t0 = time.perf_counter()
    mmd = np.mean([min(d_rs[i]) for i in range(len(d_rs))])
    cov = len({int(np.argmin(d_rs[:, j])) for j in range(d_rs.shape[1])}) / len(d_rs)
    full = np.block([[d_rr, d_rs], [d_rs.T, d_ss]])
    hits = 0
    for i in range(len(full)):
        row = [full[i, j] if j != i else np.inf for j in range(len(full))]
        hits += (int(np.argmin(row)) >= args.n) == (i >= args.n)
    nna = hits / len(full)
    t_naive_sets = time.perf_counter() - t0
    vec_sets, t_vec_sets = timed(sets.set_metrics, *mats["RMSE"])
    assert np.allclose([mmd, cov, nna], [vec_sets["MMD"], vec_sets["COV"], vec_sets["1-NNA"]])
    res["set_metrics_naive_s"], res["set_metrics_vectorised_s"] = t_naive_sets, t_vec_sets

    if not args.no_mitsuba:
        res["mitsuba"], figs = mitsuba_figures(w, names, args.mi_res, args.mi_spp)
        gallery.gallery(figs, ["sphere", "mixed plane", "normal-mapped"],
                        outdir / f"mitsuba_{args.mi_res}.png", ncols=3)

    (outdir / f"{args.resolution}.json").write_text(json.dumps(res, indent=1))
    print(json.dumps({k: v for k, v in res.items() if k != "table"}, indent=1))
    print(f"renders/s batched {res['renders_per_s']:.1f} vs one at a time "
          f"{res['renders_per_s_one_at_a_time']:.1f} (x{res['renders_per_s'] / res['renders_per_s_one_at_a_time']:.1f})")
    print(f"renders' NBRDF FLOP/s of the fp32 sgemm rate ({peak / 1e9:.0f} GFLOP/s, "
          f"{res['threads']} threads): batched {res['renders_of_sgemm']:.1%}, one at a time "
          f"{res['renders_of_sgemm_one_at_a_time']:.1%}  [{res['machine']}]")
    print(f"distance matrices {t_dist:.1f}s vs naive per-pair loop ~{res['naive_total_extrapolated_s']:.0f}s "
          f"(x{res['speedup_distances']:.1f}); full 12-metric evaluation {res['eval_total_s']:.1f}s")


if __name__ == "__main__":
    main()
