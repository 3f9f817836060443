# BTF branch (dynamic BTF synthesis paper, issue 6): UBO2014 or synthetic DFMF files ->
# Triple Plane and baselines per material -> texture / tiling figures, metrics -> report.
# Helpers (BTF_NAMES, btf_file, btf_roi, btf_seed) live at the end of common.smk.

if UBO["source"] == "synthetic":

    rule synthetic_btf:
        output:
            out("btf/data/{material}.btf"),
        params:
            kind=lambda w: w.material.removeprefix("synthetic_"),
            size=UBO["synthetic"]["size"],
            components=UBO["synthetic"]["components"],
            seed=lambda w: btf_seed(w.material, "data"),
        log:
            log("synthetic_btf/{material}"),
        benchmark:
            bench("synthetic_btf/{material}")
        conda:
            CONDA_ENV
        threads: 1
        resources:
            mem_mb=synthetic_btf_mem_mb(),
            runtime=synthetic_btf_runtime(),
        script:
            "../scripts/synthetic_btf.py"

else:
    if UBO["source"] == "local":  # fail when the DAG is built, naming the files
        _ubo2014.check_local_dir(UBO["local_dir"], [f"{n}{BTF_SUFFIX}" for n in BTF_NAMES])

    rule ubo2014_fetch:
        output:
            f"resources/ubo2014/{{material}}{BTF_SUFFIX}",
        params:
            # no url: the lock file pins each BTF's sha256 from its first good copy, so a new
            # mirror gives the same file and must not rerun (so delete) a good download.
            # local_dir and lock_file stay, though they change no byte either: taking them out
            # would rerun, so delete, every existing download once (README, Known limits)
            local_dir=UBO["local_dir"] if UBO["source"] == "local" else None,
            lock_file=UBO["lock_file"],
        log:
            log("ubo2014_fetch/{material}"),
        benchmark:
            bench("ubo2014_fetch/{material}")
        conda:
            CONDA_ENV
        threads: 1
        resources:
            mem_mb=1000,
            runtime=120,
        script:
            "../scripts/ubo2014_fetch.py"


# One rule per representation (same thin script); neural ones checkpoint beside the output.
# Rules btf_triple_plane, btf_neumip, btf_pca, btf_sh, btf_td (named in the loop, so a search
# for "rule btf_pca" finds only this comment).
for _method, _mem, _time in (("triple_plane", 3000, btf_fit_runtime("triple_plane")),
                             ("neumip", 3000, btf_fit_runtime("neumip")),
                             ("pca", 6000, 120), ("sh", 8000, 120), ("td", 8000, 120)):

    rule:
        name:
            f"btf_{_method}"
        input:
            lambda w: btf_file(w.material),
        output:
            out(f"btf/models/{{material}}/{_method}.pt"),
        params:
            **_btf_fit_rule_params(_method),
        log:
            log(f"btf_{_method}/{{material}}"),
        benchmark:
            bench(f"btf_{_method}/{{material}}")
        conda:
            CONDA_ENV
        threads: BTF["threads"]
        resources:
            mem_mb=_mem,
            runtime=_time,
        script:
            "../scripts/btf_fit.py"


rule btf_eval:
    input:
        data=lambda w: btf_file(w.material),
        models=expand(out("btf/models/{{material}}/{method}.pt"), method=BTF["methods"]),
    output:
        metrics=out("btf/eval/{material}/metrics.tsv"),
        textures=report(out("report/figures/btf_{material}_textures.png"),
                        caption="../report/btf_textures.rst", category="BTF"),
        tiling=report(out("report/figures/btf_{material}_tiling.png"),
                      caption="../report/btf_tiling.rst", category="BTF"),
    params:
        methods=BTF["methods"],
        roi=lambda w: btf_roi(w.material),
        pairs=BTF["eval_pairs"],
        tiling=canon(BTF["tiling"]),
    log:
        log("btf_eval/{material}"),
    benchmark:
        bench("btf_eval/{material}")
    conda:
        CONDA_ENV
    threads: BTF["threads"]
    resources:
        mem_mb=btf_eval_mem_mb(),
        runtime=60,
    script:
        "../scripts/btf_eval.py"


rule btf_section:
    input:
        metrics=expand(out("btf/eval/{material}/metrics.tsv"), material=BTF_NAMES),
        figures=expand(out("report/figures/btf_{material}_{kind}.png"), material=BTF_NAMES,
                       kind=["textures", "tiling"]),
    output:
        md=out("report/sections/60_btf.md"),
        table=out("btf/quality.tsv"),
    params:
        source=UBO["source"],
        crop=btf_crop(),  # as applied: a crop as large as the texture is none
    log:
        log("btf_section"),
    benchmark:
        bench("btf_section")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=500,
        runtime=5,
    script:
        "../scripts/btf_section.py"
