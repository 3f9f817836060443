"""Report section 'Rendering': metric-renderer galleries of reference fields and MERL tables,
the Mitsuba figures, and render timings."""
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image

from neumat.io import merl
from neumat.logs import script_logging
from neumat.render import gallery, sphere

with script_logging(snakemake) as log:
    p, out = snakemake.params, snakemake.output
    weights = np.load(snakemake.input.weights)
    names = pd.read_csv(snakemake.input.table, sep="\t", keep_default_na=False)["name"]
    k = min(p.n_gallery, len(weights))
    sphere.render_fields(weights[:1], p.resolution, p.activation)  # geometry + warm-up
    t0 = time.time()
    imgs = sphere.render_fields(weights, p.resolution, p.activation)
    rate = len(weights) / (time.time() - t0)
    pick = np.unique(np.linspace(0, len(weights) - 1, k).round().astype(int))  # spread over the set
    shown = sphere.render_fields(weights[pick], p.figure_resolution, p.activation)
    gallery.gallery(list(shown.numpy()), list(names[pick]), out.fields, min_cell=96)
    tables = np.stack([merl.read_merl(f).astype(np.float32) for f in snakemake.input.merl])
    gallery.gallery(list(sphere.render_tables(tables, p.figure_resolution).numpy()), p.names,
                    out.tables, min_cell=96)
    infos = [json.loads(Path(f).read_text()) for f in snakemake.input.infos]
    figs = [np.asarray(Image.open(f).convert("RGB"))
            for f in snakemake.input.figures]
    gallery.gallery(figs, [f"{i['scene']} ({i['seconds_per_image']} s/image)" for i in infos],
                    out.mitsuba, ncols=1, min_cell=160)
    timing = pd.DataFrame(infos)[["scene", "variant", "images", "resolution", "spp", "seconds",
                                  "seconds_per_image"]]
    md = [
        "## Rendering",
        f"**Metric renderer** (`neumat.render.sphere`): unit sphere, orthographic view, one point "
        f"light at {tuple(float(v) for v in sphere.LIGHT_POS)} (upper left, front) plus a dim uniform environment "
        f"(radiance {sphere.AMBIENT}, integrated on a fixed numerical quadrature) - no Monte "
        f"Carlo noise; sRGB curve, exposure 0 (shown at {p.figure_resolution}², metrics use "
        f"{p.resolution}²). Rendered the {len(weights)} reference (test-split) fields at **{rate:.0f} renders/s** "
        f"at {p.resolution}² ({snakemake.threads} threads, in chunks).",
        f"![reference fields](figures/{Path(out.fields).name})",
        "MERL-format tables of this run through the same renderer (nearest-bin lookup):",
        f"![MERL tables](figures/{Path(out.tables).name})",
        "**Mitsuba 3** (`neumat.render.mitsuba_bsdf`, plugin `neumat_brdf`): a sphere under a "
        "generated HDR sky, a plane mixing two materials through a mask texture (`blendbsdf`), "
        "and a normal-mapped sphere; path tracing with GGX + cosine importance sampling fitted "
        "to each material. EXR files in `render/mitsuba/`.",
        f"![Mitsuba figures](figures/{Path(out.mitsuba).name})",
        timing.to_markdown(index=False),
    ]
    Path(out.section).write_text("\n\n".join(md) + "\n")
    log.info("metric renders: %.1f/s at %d px", rate, p.resolution)
