"""Stage entry points of BTF synthesis (called by workflow scripts): synthesise, evaluate a
material (renders, figures, measurements), write the report fragment.

No ground truth exists for a synthesised BTF, so the evaluation measures what synthesis
promises, each against plain tiling (the repeating exemplar) in the same run:
- histogram: per-channel 1-D Wasserstein distance between f_U sampled over a `measure.scale`
  area and the exemplar plane, divided by the exemplar channel's std, mean over channels;
- repetition: normalised autocorrelation (Pearson correlation of the image with itself
  shifted by one exemplar period, max of the x and y shifts) of an orthographic top-down
  render of the `measure.scale` area at `px_per_tile` pixels per exemplar, luminance;
- appearance: FLIP and PSNR of perspective renders against plain tiling at each UV scale
  (display images, plain tiling's exposure), and the relative deviation of the mean colour
  of the orthographic render per light from plain tiling's (max over RGB)."""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np
import pandas as pd
import torch

import neumat.btf.synthesis as syn
from neumat.btf import evaluate as ev
from neumat.btf import figures, models
from neumat.btf.synthesis.hextile import HexTile
from neumat.btf.synthesis.quilting import Quilting
from neumat.seeds import seed_for

log = logging.getLogger(__name__)
FIG_METHODS = ["tiling", "hpb", "hextile", "quilting"]
PLANE_LABELS = {"triple_plane": "Triple Plane", "neumip": "NeuMIP"}


def synthesize(model_paths: dict, method: str, seed: int, settings: dict, out_path) -> None:
    """Synthesis state of `method` for every plane model in model_paths, one file."""
    synths = {}
    for name, path in model_paths.items():
        m = models.load(path)
        if not hasattr(m, "f_u"):
            raise ValueError(f"{path}: {m.method} has no positional feature plane f_U; "
                             "synthesis applies to triple_plane and neumip")
        synths[name] = syn.build(m, method, seed, settings)
        extra = sum(v.numel() * v.element_size() for v in synths[name].state().values()
                    if torch.is_tensor(v))
        log.info("%s on %s (%s): state %.3f MB beyond the model", method, name,
                 tuple(m.f_u.shape), extra / 1e6)
        if isinstance(synths[name], HexTile):  # how linear the luminance is in f_U
            log.info("hex-tiling's luminance fit on %s: R^2 %.3f", name, synths[name].lum_r2)
    syn.save(out_path, method, seed, settings, synths)


def _unit(x):
    x = np.asarray(x, np.float64)
    return x / np.linalg.norm(x)


def perspective_queries(width, height, scale, light, spp):
    """plane_queries of the BTF evaluation (same camera and plane) with u unwrapped in float64
    (synthesis needs the absolute position), supersampled spp x spp per pixel."""
    k = int(spp)
    u, wi, wo, mask, fall = ev.plane_queries(width * k, height * k, scale, light, wrap=False)
    return u, wi, wo, mask, fall, k


@torch.no_grad()
def _query(model, u, wi, wo, chunk=1 << 16):
    return torch.cat([model(u[s:s + chunk], wi[s:s + chunk], wo[s:s + chunk])
                      for s in range(0, len(u), chunk)]) if len(u) else torch.zeros(0, 3)


def render_perspective(model, width, height, scale, light, intensity, spp=1) -> np.ndarray:
    u, wi, wo, mask, fall, k = perspective_queries(width, height, scale, light, spp)
    img = np.zeros((height * k, width * k, 3), np.float32)
    img[mask] = _query(model, u, wi, wo).numpy() * (intensity * fall)[:, None]
    return img.reshape(height, k, width, k, 3).mean((1, 3))


def ortho_u(scale: int, px: int) -> torch.Tensor:
    """Pixel centres of a top-down view of [0, scale)^2, px pixels per exemplar (float64)."""
    n = int(scale) * int(px)
    t = (torch.arange(n, dtype=torch.float64) + 0.5) / px
    ys, xs = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)


def texel_centres(W: int, H: int, scale: int, seed: int, n: int = 1 << 18) -> torch.Tensor:
    """Texel-centre positions in [0, scale)^2 on which every exemplar texel falls equally
    often: k = min(scale^2, max(1, n // (W H))) copies of each, in k random tiles of the
    area (all scale^2 tiles when k = scale^2, i.e. every texel centre of the area). Plain
    tiling returns there each exemplar texel k times, so its histogram is the exemplar's and
    its W1 is 0 but for the float32 rounding of its fetch coordinates (~4e-6; a random draw
    of positions left a sampling floor of ~0.003 for every method); the others are read at
    the same positions. (W H k, 2) float64."""
    k = min(scale * scale, max(1, n // (W * H)))
    if k == scale * scale:
        tiles = torch.arange(k)[:, None].expand(k, W * H)
    else:
        g = torch.Generator().manual_seed(int(seed))
        tiles = torch.randint(0, scale * scale, (k, W * H), generator=g)
    iy, ix = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    ix = ix.reshape(-1) + W * (tiles % scale)
    iy = iy.reshape(-1) + H * (tiles // scale)
    return torch.stack([(ix.reshape(-1) + 0.5) / W, (iy.reshape(-1) + 0.5) / H], -1).double()


def random_positions(scale: int, n: int, seed: int) -> torch.Tensor:
    """n positions uniform in [0, scale)^2, (n, 2) float64, from the stream "w1_random" of
    `seed`. Every method's W1 is read here too: at texel centres plain tiling and quilting
    return exemplar texels themselves, while HPB's, hex-tiling's and linear blending's offsets
    are no whole texels, so each of their values is a bilinear mix of four, whose narrower
    histogram W1 at centres counts against them (a review, 2026-11-29: on the tiny run's
    plane, HPB 0.132 at centres, 0.040 with its offsets snapped to whole texels, and plain
    tiling 0.154 at random positions). Here tiling's W1 is that bilinear floor."""
    g = torch.Generator().manual_seed(seed_for(int(seed), "w1_random"))
    return torch.rand(n, 2, generator=g, dtype=torch.float64) * scale


def _features(synth, u: torch.Tensor) -> torch.Tensor:
    """synth(u) in chunks of 2^16 positions."""
    return torch.cat([synth(u[s:s + (1 << 16)]) for s in range(0, len(u), 1 << 16)])


def render_ortho(model, u, light, intensity) -> np.ndarray:
    """Directional light from `light` towards the plane centre, view from the evaluation
    camera's direction: the image depends on u only (no falloff, no perspective)."""
    n = int(round(math.sqrt(len(u))))
    wi = torch.tensor(_unit(light), dtype=torch.float32).expand(len(u), 3)
    wo = torch.tensor(_unit([0.0, -2.4, 1.9]), dtype=torch.float32).expand(len(u), 3)
    r2 = float(np.sum(np.square(light)))
    return _query(model, u, wi, wo).numpy().reshape(n, n, 3) * intensity / r2


def autocorrelation_at(img: np.ndarray, period: int) -> float:
    """max over x, y of corr(L(p), L(p + period)), L = Rec. 709 luminance; a direction whose
    shifted slices do not vary has none and is left out, and with neither the result is NaN
    (a black render). Python's max had returned NaN or the other direction's value by the
    order of the two (a review, 2026-11-29)."""
    L = img @ np.array([0.2126, 0.7152, 0.0722])
    c = []
    for a, b in ((L[:, :-period], L[:, period:]), (L[:-period], L[period:])):
        a, b = a.reshape(-1), b.reshape(-1)
        if a.std() > 0 and b.std() > 0:
            c.append(np.corrcoef(a, b)[0, 1])
    return float(max(c)) if c else math.nan


def histogram_distance(feat: np.ndarray, exemplar: np.ndarray) -> float:
    # lazily: scipy.stats costs ~0.6 s to import (AMD EPYC)
    from scipy.stats import wasserstein_distance

    return float(np.mean([wasserstein_distance(feat[:, c], exemplar[:, c]) / exemplar[:, c].std()
                          for c in range(exemplar.shape[1])]))


def references(model, patch_seed: int) -> dict:
    """The two syntheses every method is measured beside, built here (no state): plain tiling,
    and linear blending of HPB's patches (HPB's grid and offsets, seed `patch_seed`), naively
    blended."""
    return {"tiling": syn.Synthesized(model, syn.build(model, "tiling", patch_seed)),
            "linear": syn.Synthesized(model, syn.build(model, "linear", patch_seed))}


def evaluate(material, model_paths: dict, synth_paths: dict, render: dict, measure: dict,
             lights, intensity, seed: int, patch_seed: int, metrics_out, methods_png, planes_png,
             neumip_png):
    """All measurements and figures of one material. model_paths: {plane model: file};
    synth_paths: {method: synthesis file}; `linear` and `tiling` need no state and are built
    here, linear with `patch_seed`, HPB's synthesis seed: HPB's patches, naively blended.
    `seed`: the draw of the histogram's texel positions."""
    loaded = {k: models.load(p) for k, p in model_paths.items()}
    wrapped = {k: references(m, patch_seed) for k, m in loaded.items()}
    for method, path in synth_paths.items():
        for k, w in syn.load(path, loaded).items():
            wrapped[k][method] = w
    u_meas = ortho_u(measure["scale"], measure["px_per_tile"])
    rows, persp, exposure = [], {}, {}
    for k, ws in wrapped.items():
        m = loaded[k]
        ex = m.f_u.detach().reshape(-1, m.f_u.shape[-1]).numpy()
        u_hist = texel_centres(m.f_u.shape[1], m.f_u.shape[0], measure["scale"], seed)
        u_rand = random_positions(measure["scale"], len(u_hist), seed)
        base_ortho = None
        for method, w in ws.items():
            feat, feat_rand = _features(w.synth, u_hist), _features(w.synth, u_rand)
            ortho = [render_ortho(w, u_meas, li, intensity) for li in lights]
            if method == "tiling":
                base_ortho = ortho
            imgs = {(s, j): render_perspective(w, render["width"], render["height"], s, li,
                                               intensity, render["spp"])
                    for s in render["scales"] for j, li in enumerate(lights)}
            if method == "tiling":
                exposure[k] = ev.exposure_for(np.stack(list(imgs.values())))
            persp[(k, method)] = {key: ev.display(im, exposure[k]) for key, im in imgs.items()}
            st = w.synth.state()
            row = {"material": material, "model": k, "method": method,
                   "dynamic": bool(w.synth.dynamic),
                   "w1": histogram_distance(feat.numpy(), ex),
                   "w1_random": histogram_distance(feat_rand.numpy(), ex),
                   "acf": autocorrelation_at(sum(ortho), int(measure["px_per_tile"])),
                   "state_mb": sum(v.numel() * v.element_size() for v in st.values()
                                   if torch.is_tensor(v)) / 1e6}
            for j, (o, b) in enumerate(zip(ortho, base_ortho)):
                mo, mb = o.mean((0, 1)), b.mean((0, 1))
                row[f"dmean_l{j + 1}"] = float(np.max(np.abs(mo - mb)) / max(mb.mean(), 1e-12))
            for s in render["scales"]:  # plain tiling against itself: none (PSNR infinite)
                mets = [ev.image_metrics(persp[(k, "tiling")][(s, j)], persp[(k, method)][(s, j)])
                        for j in range(len(lights))] if method != "tiling" else []
                row[f"flip_x{s}"] = float(np.mean([q["flip"] for q in mets])) if mets else math.nan
                row[f"psnr_x{s}"] = float(np.mean([q["psnr"] for q in mets])) if mets else math.nan
            if isinstance(w.synth, Quilting):
                row["seam_ssd"] = float(w.synth.seam_ssd)
            if isinstance(w.synth, HexTile) and w.synth.lum_r2 is not None:
                row["lum_r2"] = w.synth.lum_r2
            rows.append(row)
            log.info("%s %s %s: %s", material, k, method,
                     {a: round(b, 4) for a, b in row.items() if isinstance(b, float)})
    df = pd.DataFrame(rows)
    tmp = f"{metrics_out}.tmp"
    df.to_csv(tmp, sep="\t", index=False, float_format="%.6g")
    os.replace(tmp, metrics_out)

    cols = [(s, j) for s in render["scales"] for j in range(len(lights))]
    col_names = [f"x{s}, light {j + 1}" for s, j in cols]
    first = next(iter(wrapped))
    meths = [m for m in FIG_METHODS if m in wrapped[first]]
    _grid(methods_png, df, first, meths, cols, col_names, persp, material,
          f"{PLANE_LABELS.get(first, first)}: plain tiling vs synthesis")
    pairs = [(k, m) for k in ("neumip", "triple_plane") if k in wrapped
             for m in ("tiling", "hpb") if m in wrapped[k]]
    _grid(neumip_png, df, None, pairs, cols, col_names, persp, material,
          "NeuMIP and Triple Plane, plain tiling and HPB")
    _planes(planes_png, wrapped[first], material, loaded[first])


def _grid(path, df, model, rows, cols, col_names, persp, material, title):
    keyed = [(model, r) if model else r for r in rows]
    labels = [f"{PLANE_LABELS.get(k, k)} {syn.LABELS[m]}" if not model else syn.LABELS[m]
              for k, m in keyed]
    notes = []
    for k, m in keyed:
        sel = df[(df.model == k) & (df.method == m)].iloc[0]
        notes.append(["" if m == "tiling" else f"FLIP {sel[f'flip_x{s}']:.3f}" for s, _ in cols])
    figures.texture_grid(path, labels, col_names, [[persp[(k, m)][c] for c in cols] for k, m in keyed],
                         notes, f"{material}: {title} (FLIP vs plain tiling, mean over the lights)")


def _planes(path, ws, material, model):
    """First three principal components of f_U over a 3 x 3 exemplar area, per method."""
    ex = model.f_u.detach().reshape(-1, model.f_u.shape[-1])
    mean = ex.mean(0)
    _, _, V = torch.linalg.svd(ex - mean, full_matrices=False)
    proj = (ex - mean) @ V[:3].T
    lo, hi = proj.quantile(0.01, 0), proj.quantile(0.99, 0)
    H = model.f_u.shape[0]
    u = ortho_u(3, max(H, 32))
    n = int(round(math.sqrt(len(u))))
    imgs = []
    for m in ["tiling", "linear", "hpb", "hextile", "quilting"]:
        if m in ws:
            p = ((ws[m].synth(u) - mean) @ V[:3].T - lo) / (hi - lo)
            imgs.append((m, p.clamp(0, 1).reshape(n, n, 3).numpy()))
    figures.texture_grid(path, ["f_U"], [syn.LABELS[m] for m, _ in imgs], [[i for _, i in imgs]],
                         title=f"{material}: positional features over a 3 x 3 exemplar area "
                               "(first 3 principal components as RGB)")


def quilting_storage_note(scale: int, side: int = 400, channels: int = 8) -> str:
    b = (scale * side) ** 2 * channels * 4
    return (f"A quilted plane is stored: at x{scale} a {side} x {side}, {channels}-channel float32 "
            f"f_U becomes {scale * side} x {scale * side} x {channels} = {b / 1e9:.2f} GB "
            f"(paper, Sec. 4: 'about 2GB' at x15); HPB and hex-tiling store only exemplar-sized "
            "tables.")


def tile_span_px(width: int, height: int, scale: float) -> float:
    """Median width in pixels of one tile (one exemplar period) over the plane's pixels in the
    perspective render (plane_queries' camera): at each pixel, one over the larger of the u
    steps to its right and lower neighbours."""
    u, _, _, mask, _ = ev.plane_queries(width, height, 1.0, (0.0, 0.0, 1.0), wrap=False)
    U = np.full((height, width, 2), np.nan)
    U[mask] = u.numpy()
    dx = np.linalg.norm(np.diff(U, axis=1), axis=-1)[:-1]
    dy = np.linalg.norm(np.diff(U, axis=0), axis=-1)[:, :-1]
    step = np.fmax(dx, dy)
    step = step[np.isfinite(step) & (step > 0)]
    return float(np.median(1 / step)) / scale if len(step) else float("nan")


def subpixel_note(render) -> str:
    """A sentence where the render is so small that at some UV scale a tile is narrower than a
    pixel (then FLIP and PSNR there measure mostly aliasing); '' where none is."""
    span = tile_span_px(render["width"], render["height"], 1.0)  # at x s: span / s
    spans = {s: span / s for s in render["scales"]}
    small = [s for s, v in spans.items() if v < 1]
    if not small:
        return ""
    return (f"At this render size ({render['width']} x {render['height']}, {render['spp']}^2 "
            f"samples per pixel) a tile (one exemplar) spans a median "
            + ", ".join(f"{v:.2g} pixels at x{s}" for s, v in spans.items())
            + ": less than a pixel at " + ", ".join(f"x{s}" for s in small)
            + ", so FLIP and PSNR there mostly measure aliasing (which exemplar texels the "
              "samples happen to hit), not the synthesis.")


def write_section(metric_files, md_out, table_out, measure, render, quilt_scale, channels):
    df = pd.concat([pd.read_csv(f, sep="\t") for f in metric_files], ignore_index=True)
    tmp = f"{table_out}.tmp"
    df.to_csv(tmp, sep="\t", index=False, float_format="%.5g")
    os.replace(tmp, table_out)
    S = measure["scale"]
    nl = len([c for c in df.columns if c.startswith("dmean_l")])
    lights = "both lights" if nl == 2 else f"the {nl} lights" if nl > 1 else "the light"
    lines = ["### Dynamic synthesis on the positional plane", "",
             f"Synthesis replaces the fetch of f_U by a synthesised plane (Xu et al. 2024); "
             f"no ground truth exists, so each method is measured against plain tiling. "
             f"W1: per-channel 1-D Wasserstein distance of f_U at texel centres of a x{S} area, "
             f"each exemplar texel equally often (in random tiles; up to 2^18 positions), to "
             f"the exemplar plane, in exemplar standard deviations (lower = histogram kept; "
             f"plain tiling's is 0 but for float32 rounding). W1 random: the same at as many "
             f"uniformly random positions, where every method's values are bilinear mixes "
             f"(at texel centres tiling and quilting return exemplar texels, the dynamic "
             f"methods mixes); plain tiling's is then what bilinear filtering of the exemplar "
             f"costs, not a floor: HPB can go below it, as it blends in its Gaussianised space "
             f"and its inverse LUT maps the blend back onto the exemplar's histogram. ACF: "
             f"normalised autocorrelation of a top-down x{S} render (sum of the lights) at the "
             f"exemplar period (1 = strict repetition). dmean: largest deviation of a mean RGB "
             f"channel from plain tiling's, over plain tiling's mean over RGB, per light. "
             f"FLIP / PSNR: perspective renders ({render['width']} x "
             f"{render['height']}, {render['spp']}^2 samples per pixel) against plain tiling, "
             f"mean of {lights}. State: stored floats beyond the model (MB).", ""]
    note = subpixel_note(render)
    if note:
        lines[-2] += " " + note
    scales = render["scales"]
    head = ("| material | model | method | W1 | W1 random | ACF | "
            + "".join(f"dmean L{j + 1} | " for j in range(nl))
            + " | ".join(f"FLIP x{s} | PSNR x{s}" for s in scales) + " | state MB |")
    lines += [head, "|" + " --- |" * (6 + nl + 2 * len(scales) + 1)]
    for r in df.itertuples():
        cells = [r.material, PLANE_LABELS.get(r.model, r.model), syn.LABELS.get(r.method, r.method),
                 f"{r.w1:.3f}", f"{r.w1_random:.3f}", f"{r.acf:.3f}"]
        cells += [f"{100 * getattr(r, f'dmean_l{j + 1}'):.1f}%" for j in range(nl)]
        for s in scales:
            f, p = getattr(r, f"flip_x{s}"), getattr(r, f"psnr_x{s}")
            cells += ["-", "-"] if r.method == "tiling" else [f"{f:.3f}", f"{p:.1f}"]
        cells.append(f"{r.state_mb:.3f}")
        lines.append("| " + " | ".join(map(str, cells)) + " |")
    lines += ["", quilting_storage_note(quilt_scale, 400, channels), ""]
    if "seam_ssd" in df:
        q = df.dropna(subset=["seam_ssd"])
        lines += ["Quilting: mean squared feature difference over the overlaps of the chosen "
                  "blocks: " + ", ".join(f"{r.material}/{r.model} {r.seam_ssd:.3g}"
                                         for r in q.itertuples()) + ".", ""]
    if "lum_r2" in df:
        h = df.dropna(subset=["lum_r2"])
        lines += ["Hex-tiling weights its blend by a luminance linear in the features (as the "
                  "shader's is in the colour), fitted by least squares to the decoded BTF's "
                  "luminance at head-on light and view; R^2 of that fit: "
                  + ", ".join(f"{r.material}/{r.model} {r.lum_r2:.3f}" for r in h.itertuples())
                  + ".", ""]
    for m in dict.fromkeys(df.material):
        lines += [f"![{m}: synthesis methods](figures/btf_{m}_synthesis.png)", "",
                  f"![{m}: NeuMIP and Triple Plane with HPB](figures/btf_{m}_synthesis_models.png)", "",
                  f"![{m}: synthesised feature planes](figures/btf_{m}_synthesis_planes.png)", ""]
    Path(md_out).write_text("\n".join(lines))
