"""One Mitsuba 3 figure of reference materials: EXR (linear) + PNG preview + timing JSON."""
import json
import time

import numpy as np
import pandas as pd

from neumat.logs import script_logging
from neumat.render import mitsuba_bsdf as mb
from neumat.io.images import write_exr
from neumat.render import scenes

with script_logging(snakemake) as log:
    cfg, scene, out = snakemake.params.cfg, snakemake.wildcards.scene, snakemake.output
    t0 = time.time()
    variant = mb.select_variant(cfg["variant"])
    weights = np.load(snakemake.input.weights)
    names = pd.read_csv(snakemake.input.table, sep="\t", keep_default_na=False)["name"]
    # one material per source: the reference set lists each source's RGB permutations
    # (name@rbg, ...) after it, which look alike (a review found the two-material plane mixing
    # gray-acrylic with gray-acrylic@rbg, its mask invisible)
    seen, pick = set(), []
    for i, name in enumerate(names):
        if name.split("@")[0] not in seen:
            seen.add(name.split("@")[0])
            pick.append(i)
    pick = pick[:cfg["materials"]]
    mats = [mb.Material(f"{names[i]}#{i}", weights=weights[i],
                        activation=snakemake.params.activation) for i in pick]
    k = len(mats)
    env = scenes.sky_envmap(cfg["envmap_size"])
    res, spp = cfg["resolution"], cfg["spp"]
    if scene == "sphere":
        dicts = [scenes.sphere_scene(m, res, spp, env) for m in mats]
    elif scene == "normal_mapped":
        dicts = [scenes.normal_mapped_scene(m, res, spp, env, scenes.ripple_normals(2 * res))
                 for m in mats]
    else:  # two materials mixed by a mask; with one material mix it with itself
        dicts = [scenes.mixed_plane_scene(mats[0], mats[min(1, k - 1)], res, spp, env,
                                          scenes.blend_mask(2 * res))]
    imgs = [scenes.render(d, seed=snakemake.params.seed) for d in dicts]
    img = np.concatenate(imgs, axis=1)
    write_exr(out.exr, img)
    scenes.write_png(out.png, img)
    seconds = time.time() - t0
    info = {"scene": scene, "variant": variant, "materials": [m.name for m in mats],
            "images": len(imgs), "resolution": res, "spp": spp, "seconds": round(seconds, 2),
            "seconds_per_image": round(seconds / len(imgs), 2)}
    with open(out.info, "w") as f:
        json.dump(info, f, indent=1)
    log.info("%s", info)
