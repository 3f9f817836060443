# Dynamic BTF synthesis on the positional plane (issue 18): per material and method, the
# synthesis state of every plane model (Triple Plane, NeuMIP) -> renders at several UV
# scales, measurements against plain tiling, figures -> report fragment 61 (after 60_btf).

SYN = config["btf_synthesis"]
SYN_PLANES = [m for m in ("triple_plane", "neumip") if m in BTF["methods"]]
SYN_METHOD_RE = "|".join(SYN["methods"]) or "^$"
if SYN["methods"] and not SYN_PLANES:
    raise ValueError("config btf_synthesis.methods needs a plane model (triple_plane or neumip) "
                     "in btf.methods; add one or set btf_synthesis.methods: []")


rule btf_synthesize:
    wildcard_constraints:
        method=SYN_METHOD_RE,
    input:
        _syn_models,
    output:
        out("btf_synthesize/{material}/{method}.pt"),
    params:
        planes=SYN_PLANES,
        seed=lambda w: syn_seed(w.material, w.method),
        settings=lambda w: settings(f"btf_synthesis.{w.method}"),
    log:
        log("btf_synthesize/{material}/{method}"),
    benchmark:
        bench("btf_synthesize/{material}/{method}")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        # quilting holds scale^2 x the plane in float64 while it works (400^2 x 8 at x15: 2.3 GB)
        mem_mb=lambda w: 12000 if w.method == "quilting" else 2000,
        runtime=lambda w: 240 if w.method == "quilting" else 10,
    script:
        "../scripts/btf_synthesize.py"


rule btf_synthesis_eval:
    input:
        models=_syn_models,
        synth=expand(out("btf_synthesize/{{material}}/{method}.pt"), method=SYN["methods"]),
    output:
        metrics=out("btf_synthesize/{material}/metrics.tsv"),
        methods=report(out("report/figures/btf_{material}_synthesis.png"),
                       caption="../report/btf_synthesis.rst", category="BTF"),
        models=report(out("report/figures/btf_{material}_synthesis_models.png"),
                      caption="../report/btf_synthesis_models.rst", category="BTF"),
        planes=report(out("report/figures/btf_{material}_synthesis_planes.png"),
                      caption="../report/btf_synthesis_planes.rst", category="BTF"),
    params:
        planes=SYN_PLANES,
        methods=SYN["methods"],
        render=settings("btf_synthesis.render"),
        measure=settings("btf_synthesis.measure"),
        lights=BTF["tiling"]["lights"],
        intensity=BTF["tiling"]["intensity"],
        seed=lambda w: syn_seed(w.material, "linear"),
        patch_seed=lambda w: syn_seed(w.material, "hpb"),  # linear blends HPB's patches
    log:
        log("btf_synthesis_eval/{material}"),
    benchmark:
        bench("btf_synthesis_eval/{material}")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=6000,
        runtime=120,
    script:
        "../scripts/btf_synthesis_eval.py"


rule btf_synthesis_section:
    input:
        metrics=expand(out("btf_synthesize/{material}/metrics.tsv"), material=BTF_NAMES),
    output:
        md=out("report/sections/61_btf_synthesis.md"),
        table=out("btf_synthesize/synthesis.tsv"),
    params:
        render=settings("btf_synthesis.render"),
        measure=settings("btf_synthesis.measure"),
        quilt_scale=SYN["quilting"]["scale"],
        channels=BTF["triple_plane"]["u_channels"],
    log:
        log("btf_synthesis_section"),
    benchmark:
        bench("btf_synthesis_section")
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=500,
        runtime=5,
    script:
        "../scripts/btf_synthesis_section.py"
