"""race.py: Wilson intervals, races with a known winner, checkpoint errors."""

import json
import math

import pytest

import race


def test_wilson_interval_against_published_values():
    # Wilson 95% intervals as tabulated (e.g. Newcombe 1998, Table I): 7/10 and 0/10, 15/148
    lo, hi = race.wilson_interval(7, 10)
    assert (round(lo, 4), round(hi, 4)) == (0.3968, 0.8922)
    lo, hi = race.wilson_interval(0, 10)
    assert lo == 0.0 and round(hi, 4) == 0.2775
    lo, hi = race.wilson_interval(15, 148)
    assert (round(lo, 4), round(hi, 4)) == (0.0624, 0.1605)


def test_schedule_rotates_the_grid_on_each_track():
    plans = [race.schedule(1, r, 2) for r in range(4)]
    assert plans[0][0] == plans[1][0] != plans[2][0] == plans[3][0]
    assert [p[1] for p in plans] == [[0, 1], [1, 0], [0, 1], [1, 0]]


def test_faster_pursuit_driver_wins_every_race(tmp_path):
    rows = race.main(
        ["--opponent", "pursuit:70", "--opponent", "pursuit:40", "--races", "4", "--max-steps", "3000", "--out", str(tmp_path)]
    )
    fast, slow = rows
    assert fast["wins"] == 4 and slow["wins"] == 0
    assert (fast["win_rate_ci_low"], fast["win_rate_ci_high"]) == pytest.approx(race.wilson_interval(4, 4))
    z = race.WILSON_Z
    assert fast["win_rate_ci_low"] == pytest.approx(1 / (1 + z * z / 4))  # p = 1: lower bound n / (n + z^2)
    assert fast["mean_finish_step"] < slow["mean_finish_step"]
    assert fast["mean_progress"] == slow["mean_progress"] == 1.0
    assert json.loads((tmp_path / "results.json").read_text())[0]["wins"] == 4
    assert (tmp_path / "results.csv").read_text().startswith("racer,races,wins")
    assert (tmp_path / "race.mp4").stat().st_size > 10_000


def test_truncated_and_foreign_checkpoints_get_one_line_errors(tmp_path):
    foreign = tmp_path / "foreign.pt"
    import torch

    torch.save({"weights": torch.zeros(3)}, foreign)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(foreign.read_bytes()[:40])
    for path, message in [
        (foreign, "not a DLC checkpoint"),
        (truncated, "not a readable checkpoint"),
        (tmp_path / "missing.pt", "no such checkpoint file"),
    ]:
        with pytest.raises(SystemExit) as exit_info:
            race.main([str(path), "--opponent", "pursuit"])
        text = str(exit_info.value)
        assert str(path) in text and message in text and "\n" not in text


def test_bad_arguments():
    with pytest.raises(SystemExit):
        race.main(["--opponent", "pursuit"])  # one racer
    with pytest.raises(SystemExit):
        race.main(["--opponent", "pursuit:fast", "--opponent", "pursuit"])
    assert math.isclose(race.wilson_interval(0, 0)[1], 1.0)
