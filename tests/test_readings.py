"""benchmarks/readings.py: a screen reads the policy a run kept at exactly the update count asked for (its latest.pt
or an evaluation's eval_<race>.pt), and names the counts it kept when it has none there."""

import os

import pytest

import readings


def fake_run(root, kept):
    """A run directory with (empty) checkpoints named in `kept` ({file: updates})."""
    run = root / "multi_car_racing__lstm_single__11__1700000000"
    (run / "checkpoints").mkdir(parents=True)
    for name in kept:
        (run / "checkpoints" / name).write_bytes(b"")
    return run


def test_a_screen_picks_the_policy_each_run_kept_at_the_same_update_count(tmp_path, monkeypatch):
    import utils.checkpoint

    kept = {"latest.pt": 8000, "eval_000045.pt": 2600, "eval_000050.pt": 3100}
    short_kept = {"latest.pt": 3100, "eval_000045.pt": 2600}
    long_run, short_run = fake_run(tmp_path / "long", kept), fake_run(tmp_path / "short", short_kept)
    counts = {os.path.join(long_run, "checkpoints", k): v for k, v in kept.items()}
    counts |= {os.path.join(short_run, "checkpoints", k): v for k, v in short_kept.items()}
    monkeypatch.setattr(utils.checkpoint, "read_checkpoint",
                        lambda path: (None, {"agents": [{"num_updates": counts[path]}]}))  # fmt: skip
    assert readings.checkpoint_at(str(long_run), 3100).endswith("eval_000050.pt")
    assert readings.checkpoint_at(str(short_run), 3100).endswith("latest.pt")
    with pytest.raises(ValueError, match=r"kept no policy at 3000 updates \(it kept: 2600, 3100, 8000\); it passed"):
        readings.checkpoint_at(str(long_run), 3000)
    with pytest.raises(ValueError, match=r"\(it kept: 2600, 3100\); resume it with --updates"):
        readings.checkpoint_at(str(short_run), 4000)
