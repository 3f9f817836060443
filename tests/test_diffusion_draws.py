"""A sampling job's finished draws are kept and reused only for the same model and settings."""
import numpy as np

from neumat.diffusion import draws


def test_draws_resume_only_for_their_fingerprint(tmp_path, caplog):
    model = tmp_path / "model.pt"
    model.write_bytes(b"model one")
    fp = draws.fingerprint([model], {"steps": 100})
    made = []

    def make(seed):
        made.append(seed)
        return {"w": np.full((3, 2), seed, np.float32), "kept": np.array([True, False, True])}

    cache = draws.DrawCache(tmp_path / "draws.partial", fp)
    first = [cache.get(s, lambda s=s: make(s)) for s in (5, 6)]
    assert made == [5, 6]
    # a killed job's rerun: both draws come back from their files, equal to the bit
    again = [cache.get(s, lambda s=s: make(s)) for s in (5, 6)]
    assert made == [5, 6]
    for a, b in zip(first, again):
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    # another model or other settings draw again
    model.write_bytes(b"model two")
    assert draws.fingerprint([model], {"steps": 100}) != fp
    assert draws.fingerprint([tmp_path / "model.pt"], {"steps": 50}) != fp
    other = draws.DrawCache(tmp_path / "draws.partial", draws.fingerprint([model], {"steps": 100}))
    other.get(5, lambda: make(5))
    assert made == [5, 6, 5]
    # a damaged file is logged and drawn again
    (tmp_path / "draws.partial/draw_6.npz").write_bytes(b"not a zip")
    with caplog.at_level("WARNING"):
        other.get(6, lambda: make(6))
    assert made == [5, 6, 5, 6] and "draw_6.npz: unreadable" in caplog.text
    # a category name as the key (constrained synthesis), resumed with its log line
    caplog.clear()
    with caplog.at_level("INFO"):
        other.get("low-specular", lambda: make(7))
        other.get("low-specular", lambda: make(7))
    assert made == [5, 6, 5, 6, 7] and "draw low-specular: resumed from" in caplog.text
    other.clear()
    assert not (tmp_path / "draws.partial").exists()


def test_a_table_round_trips_through_a_draw_file_with_its_dtypes(tmp_path):
    """Constrained synthesis keeps each category's statistics in its draw file: every column
    comes back with its values and dtype, an empty table's float columns too (as CSV text they
    came back as object columns, which lost the output's float formatting)."""
    import pandas as pd

    from neumat.io.atomic import save_npz
    t = pd.DataFrame({"mean_r": [0.123456789, 2.5], "n_valid": [5, 7], "ok": [True, False],
                      "guide": ["unconditional", "type: fabric"]})
    for part in (t, t.iloc[:0]):
        save_npz(tmp_path / "d.npz", **draws.table_arrays(part))
        with np.load(tmp_path / "d.npz", allow_pickle=False) as z:
            back = draws.table({k: z[k] for k in z.files})
        assert list(back.columns) == list(t.columns)
        for c in ("mean_r", "n_valid", "ok"):
            assert back[c].dtype == part[c].dtype and back[c].tolist() == part[c].tolist()
        assert back["guide"].tolist() == part["guide"].tolist()


def test_a_resumed_job_times_every_draw_it_holds():
    """timing.tsv of a resumed sampling job counted only the draws it made itself; each draw now
    keeps its own time, and a draw file from before that falls back to the job's time."""
    done = [{"w": np.zeros(2), "seconds": np.array(3.5)}, {"w": np.zeros(2), "seconds": np.array(4.0)}]
    assert draws.seconds(done, fallback=4.1) == 7.5
    assert draws.seconds(done + [{"w": np.zeros(2)}], fallback=4.1) == 4.1
