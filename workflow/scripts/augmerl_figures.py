"""Paper Figs. 3 and 4: six RGB permutations of one material; a PCA interpolation strip."""
import numpy as np

from neumat import augment
from neumat.logs import script_logging
from neumat.render import sphere
from neumat.render.gallery import gallery

with script_logging(snakemake) as log:
    p = snakemake.params
    inp = snakemake.input
    aug = augment.AugMERL(inp.recipe, inp.log_tables, inp.log_index)
    src = aug.source_names

    def row(name, perm="rgb"):
        hit = np.flatnonzero((aug.row_src == src.index(name)) &
                             (aug.row_perm == augment.PERMS.index(perm)))
        if not len(hit):
            raise ValueError(f"augmerl figure: no row for material {name!r} "
                             f"(config augmerl.figure_material / figure_pair)")
        return int(hit[0])

    for name in [p.material, *p.pair]:
        if name not in src:
            raise ValueError(f"config augmerl.figure_material/figure_pair: {name!r} is not one "
                             f"of this run's materials")
    P = len(aug.row_src)
    perm_rows = [row(p.material, q) for q in augment.PERMS if (aug.row_perm == augment.PERMS.index(q)).any()]
    tables = aug.tables_from_coefs(np.eye(P)[perm_rows])
    imgs = sphere.tonemap(sphere.render_tables(tables, resolution=p.resolution))
    labels = [augment.PERMS[aug.row_perm[r]] for r in perm_rows]
    gallery(imgs, labels, snakemake.output.permutations, ncols=len(imgs), min_cell=96,
            title=f"RGB permutations of {p.material}")

    # The figure interpolates in a PCA of all rows of both materials' splits together.
    weights = np.linspace(1, 0, 5)
    a, b = row(p.pair[0]), row(p.pair[1])
    k = min(p.pca_dims, P - 1)
    coefs, kept = augment.interpolation_coefs(aug.logs, aug.row_src, aug.row_perm, a, b, weights,
                                              k, return_k=True)
    # the components used: a tie of eigenvalues across the cut at k is kept whole
    k_text = f"k = {kept}" + (f", {k} asked, widened over tied eigenvalues" if kept != k else "")
    imgs = sphere.tonemap(sphere.render_tables(aug.tables_from_coefs(coefs),
                                               resolution=p.resolution))
    gallery(imgs, [f"{w:.2f} / {1 - w:.2f}" for w in weights], snakemake.output.interpolation,
            ncols=len(imgs), min_cell=96, title=f"PCA interpolation {p.pair[0]} -> {p.pair[1]} ({k_text})")
    log.info("figures written")
