"""The hyperdiffusion report section's numbers (neumat.diffusion.summary), on hand-made tables
with known answers."""

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from neumat.diffusion import summary


def _near(l1, types=None, nearest_types=None, ids=None, relative=None):
    n = len(l1)
    return pd.DataFrame({"brdf_l1": l1, "relative_l1": relative or [0.0] * n,
                         "type": types or [""] * n,
                         "nearest_typed_type": nearest_types or [""] * n,
                         "nearest_id": ids or list(range(n)),
                         "nearest_name": [f"m{i}" for i in (ids or range(n))]})


def test_novelty_is_the_median_distance_and_the_share_of_near_copies():
    t = summary.novelty({"reference": _near([1.0, 2, 3, 4, 5], relative=[0.5, 0.1, 0.2, 0.3, 0.4]),
                         "ours": _near([0.1, 0.2, 0.5, 2.0], relative=[0.4, 0.1, 0.2, 0.3])})
    got = t.set_index("set")
    assert got.loc["reference", summary.NOVELTY] == 3.0
    assert got.loc["ours", summary.NOVELTY] == 0.35
    # the relative distance's own median, not the absolute one's row
    assert got.loc["reference", summary.RELATIVE] == 0.3
    assert got.loc["ours", summary.RELATIVE] == 0.25
    # near-copy: closer than a tenth of the reference median, 0.3
    assert got.loc["ours", "share closer than 10 % of the reference median"] == 0.5
    assert got.loc["reference", "share closer than 10 % of the reference median"] == 0.0


def test_type_match_counts_hits_per_type_and_the_test_split_yardstick():
    typed = _near([0.1] * 3, ["a", "a", "b"], ["a", "b", "b"], relative=[0.2, 0.4, 0.5])
    ref = _near([0.1] * 4, ["a", "", "c", "b"], ["b", "a", "c", "b"])
    man = pd.DataFrame({"split": ["train", "train", "train", "test"], "type": ["a", "b", "", "c"]})
    tm = summary.type_match(typed, ref, man)
    assert tm.hits.tolist() == [True, False, True]
    assert tm.per_type["match %"].to_dict() == {"a": 50.0, "b": 100.0}
    assert tm.per_type[summary.RELATIVE].to_dict() == pytest.approx({"a": 0.3, "b": 0.5})
    # the untyped reference is left out; "c" is a type no training material has
    assert tm.ref_hits.index.tolist() == [0, 2, 3] and tm.ref_hits.tolist() == [False, True, True]
    assert tm.ref_known.index.tolist() == [0, 2, 3] and tm.ref_known.tolist() == [True, False, True]


def test_training_and_speed_tables_take_what_the_files_hold():
    b = {"n_train": 80, "train_cfg": {"steps": 500, "batch_size": 32}, "train_seconds": 12.5,
         "history": [[0, 1.0], [500, 0.25]]}
    t = summary.training_table({"ours": b})
    assert t.to_dict("records") == [{"model": "ours", "training materials": 80, "steps": 500,
                                     "batch": 32, "train wall time (s)": 12.5, "final loss": 0.25}]
    timing = pd.Series({"samples": 64.0, "seconds": 2.0, "samples_per_second": 32.0,
                        "guidance": 1.0})
    s = summary.speed_table({"ours": timing})
    assert s.to_dict("records") == [{"set": "ours", "samples": 64, "seconds": 2.0,
                                     "samples / s": 32.0, "guidance": 1.0}]
    assert isinstance(s.loc[0, "samples"], (int, np.integer))


def test_spread_keeps_both_ends_and_never_more_than_there_are():
    assert summary.spread(5, 3).tolist() == [0, 2, 4]
    assert summary.spread(2, 5).tolist() == [0, 1]
    assert summary.spread(7, 1).tolist() == [0]


def _fake_render(calls):
    def render(w):
        calls.append(np.asarray(w).copy())
        return np.zeros((len(w), 8, 8, 3), np.float32)
    return render


def test_nearest_gallery_renders_the_picked_samples_over_their_nearest_materials(tmp_path):
    samples = np.arange(5, dtype=np.float32)[:, None] * np.ones((1, 4), np.float32)
    weights = 100 + np.arange(10, dtype=np.float32)[:, None] * np.ones((1, 4), np.float32)
    near = _near([0.5] * 5, ids=[9, 8, 7, 6, 5])
    calls, path = [], tmp_path / "g.png"
    summary.nearest_gallery(samples, near, weights, 3, _fake_render(calls), path, "t")
    assert [c[:, 0].tolist() for c in calls] == [[0, 2, 4], [109, 107, 105]]
    assert Image.open(path).size[0] > 0


def test_nearest_gallery_labels_samples_and_their_neighbours(monkeypatch):
    grids = []
    monkeypatch.setattr(summary, "image_grid",
                        lambda imgs, labels, path, **kw: grids.append((len(imgs), labels, kw)))
    samples = np.zeros((4, 2), np.float32)
    near = _near([0.5, 0.25, 0.125, 1.0], ids=[3, 2, 1, 0])
    summary.nearest_gallery(samples, near, np.zeros((4, 2), np.float32), 9,
                            _fake_render([]), "unused.png", "t")
    n, labels, kw = grids[0]
    assert n == 8 and kw["ncols"] == 4 and kw["title"] == "t"
    assert labels == ["sample 0", "sample 1", "sample 2", "sample 3",
                      "m3\nL1 0.5", "m2\nL1 0.25", "m1\nL1 0.125", "m0\nL1 1"]


def test_type_gallery_shows_each_asked_type_in_order_at_most_six_a_row(tmp_path):
    types = ["b"] * 8 + ["a"] * 2 + ["c"] * 3
    typed = _near([0.1] * len(types), types, types)
    samples = np.arange(len(types), dtype=np.float32)[:, None] * np.ones((1, 4), np.float32)
    calls = []
    summary.type_gallery(samples, typed, 2, 9, _fake_render(calls), tmp_path / "t.png")
    # the first two types asked (b, then a); b's first six samples, then a's two
    assert calls[0][:, 0].tolist() == [0, 1, 2, 3, 4, 5, 8, 9]


def test_relative_distance_divides_by_the_nearest_rows_mean():
    from neumat.diffusion import dataset
    got = dataset.relative(np.array([1.0, 4.0, 3.0]), np.array([1, 0, 1]), np.array([2.0, 0.5]))
    assert got.tolist() == [2.0, 2.0, 6.0]
