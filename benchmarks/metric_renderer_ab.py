"""Table 2's image rows (RMSE, NegSSIM) of draw 0 of a finished run's `ours`, MERL100 and VAE-N
(and PCA-A, whose tables hold the current view's bins only, under the current renderer alone)
against its reference set, under the metric renderer's environment quadrature before 503d7e9
(a cosine-weighted 16 x 16 grid of directions, the baseline, kept below) and now (half
vectors, `sphere.albedo_quadrature`), in the same run. Whether a renderer change reorders the
columns: the same samples rendered both ways.

First, with no run needed, each quadrature's directional albedo of isotropic GGX lobes (no
Fresnel; `neumat.data.synthetic_merl.evaluate`) and of a Lambertian BRDF at its 24 view angles,
against a 400 x 400 half-vector grid: the largest absolute error over the angles
(`--albedo-only` stops there).

    OMP_NUM_THREADS=2 python benchmarks/metric_renderer_ab.py [--results results/real40]
                                                              [--albedo-only]
"""
import argparse
import time

import numpy as np
import pandas as pd

from neumat import machine, seeds
from neumat.data import synthetic_merl
from neumat.metrics import distances, evaluate, materials
from neumat.render import sphere


def old_quadrature(n_theta=24, n_u=16, n_phi=16):
    """The environment term's nodes before 503d7e9: cosine-weighted (sin^2 theta_i, phi)."""
    theta_o = (np.arange(n_theta) + 0.5) / n_theta * np.pi / 2
    u = (np.arange(n_u) + 0.5) / n_u
    phi = (np.arange(n_phi) + 0.5) / n_phi * np.pi
    T, U, P = np.meshgrid(theta_o, u, phi, indexing="ij")
    s = np.sqrt(U)
    wi = np.stack([s * np.cos(P), s * np.sin(P), np.sqrt(1 - U)], -1).reshape(-1, 3)
    wo = np.stack([np.sin(T), np.zeros_like(T), np.cos(T)], -1).reshape(-1, 3)
    return theta_o, wi, wo, np.full(len(wi), np.pi / (n_u * n_phi))


def ggx(alpha):
    """BRDF (N,) of a GGX lobe without Fresnel (the project's synthetic MERL conductor with
    F0 = 1: height-correlated Smith G2) at direction pairs (..., 3)."""
    spec = synthetic_merl.Spec("ggx", "ggx", "metal", alpha=alpha, f0=(1.0, 1.0, 1.0))
    return lambda wi, wo: synthetic_merl.evaluate(spec, wi.reshape(-1, 3), wo.reshape(-1, 3))[
        :, 0].reshape(wi.shape[:-1])


def albedo_errors():
    """Largest |albedo - dense albedo| over the view angles, per BRDF and quadrature."""
    theta_o = sphere.albedo_quadrature()[0]
    dwi, dwo, dw = sphere.half_vector_nodes(theta_o, 400, 400, half=True)
    brdfs = {f"GGX {a:g}": ggx(a) for a in (0.02, 0.05, 0.1, 0.3, 0.5)}
    brdfs["Lambertian"] = lambda wi, wo: np.full(wi.shape[:-1], 1 / np.pi)
    rows = {}
    for name, f in brdfs.items():
        ref = (f(dwi, dwo) * dw).sum(1)
        for label, q in [("old (cosine 16x16)", old_quadrature), ("new (half vectors 32x16)",
                                                                   sphere.albedo_quadrature)]:
            t, wi, wo, w = q()
            got = (f(wi, wo) * w).reshape(len(t), -1).sum(1)
            rows.setdefault(name, {})[label] = np.abs(got - ref).max()
    return pd.DataFrame(rows).T


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", default="results/real40", help="a finished run")
    ap.add_argument("--albedo-only", action="store_true",
                    help="the albedo errors alone (no run needed)")
    a = ap.parse_args()
    print(f"machine: {machine.describe()}")
    print("directional albedo, largest absolute error over the 24 view angles against a 400 x 400 "
          f"half-vector grid:\n{albedo_errors().round(4).to_string()}\n", flush=True)
    if a.albedo_only:
        return
    run = a.results
    ref = materials.load(f"{run}/samples/reference/weights.npy")
    n = len(ref)
    sets = {m: materials.rows(materials.load(f"{run}/{p}"), slice(0, n)) for m, p in
            [("ours", "samples/ours/weights.npy"), ("pca_a", "samples/pca_a/tables.npz"),
             ("merl100", "samples/merl100/weights.npy"), ("vae_n", "samples/vae_n/weights.npy")]}
    bins = distances.brdf_sample(65536, seeds.seed_for(0, "metrics"))
    print(f"{run}: draw 0, {n} samples per column against {n} references")
    new_q = sphere.albedo_quadrature
    for label, q in [("new (half vectors)", new_q), ("old (cosine 16x16)", old_quadrature)]:
        sphere.albedo_quadrature = q
        sphere.sphere_view.cache_clear()
        t = time.time()
        rows = []
        for m, s in sets.items():
            if m == "pca_a" and q is not new_q:  # its tables hold the new view's bins only
                continue
            tab = evaluate.evaluate_draws(ref, [s], resolution=128, bins=bins, activation="relu")
            tab = tab[tab.distance.isin(["RMSE", "NegSSIM"])]
            tab["model"] = m
            rows.append(tab)
        tab = pd.concat(rows).pivot_table(index=["metric", "distance"], columns="model",
                                          values="value")
        print(f"renderer {label} ({time.time() - t:.0f} s):\n{tab.round(4).to_string()}\n",
              flush=True)


if __name__ == "__main__":
    main()
