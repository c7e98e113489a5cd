"""benchmarks/sweep.py and readings.py: screens as a Ray Tune sweep of flag sets x seeds, and their readings.

A tiny sweep of two flag sets runs to completion on a local Ray, each trial in its own run directory with its own
flags; the same command again trains nothing; another grid under the same name and an unknown flag are refused
before Ray starts; the report measures each finished trial once."""

import csv
import dataclasses
import json
import math
import os

import pytest
from conftest import TINY, TINY_TRIAL

import readings
import runs
import sweep as sweeps

TINY_FLAGS = " ".join(f"{k}={v}" for k, v in TINY_TRIAL.items())
GRID = (TINY_FLAGS, TINY_FLAGS + " entropy_coef=0.3")


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    pytest.importorskip("ray")
    import ray

    root = tmp_path_factory.mktemp("sweep")
    sweep = sweeps.Sweep(name="tiny", grid=GRID, seeds=(3,), updates=2, report_every=1, storage=str(root / "runs"),
                         results=str(root / "results"), tracks=1)  # fmt: skip
    try:
        sweeps.main(sweep)
        yield sweep
    finally:
        ray.shutdown()


def trial_args(sweep, flags):
    import dreamer_lstm

    config = {"tag": sweeps.tag_of(flags), "variant": "lstm", "seed": 3}
    spec = sweeps.trial_spec(sweep, flags, "lstm", 3)
    run = runs.run_of(sweeps.experiment.trial_dir(spec, "single", "lstm", 3))
    return config, dreamer_lstm.load_checkpoint(os.path.join(run, "checkpoints", "latest.pt"))


def test_every_trial_runs_with_its_own_flags_to_its_updates(finished):
    plain, lower = (trial_args(finished, flags)[1] for flags in GRID)
    assert plain["args"]["entropy_coef"] == 1.0 and lower["args"]["entropy_coef"] == 0.3
    for checkpoint in (plain, lower):
        assert checkpoint["args"]["preset"] == "cpu" and checkpoint["args"]["stage"] == "single"
        assert checkpoint["args"]["cnn_depth"] == TINY["cnn_depth"] and checkpoint["args"]["seed"] == 3
        assert checkpoint["agents"][0]["num_updates"] == 2
    assert sweeps.status_text(finished).count(": done") == 2


def test_the_same_command_again_trains_nothing(finished):
    import glob

    import ray

    files = glob.glob(os.path.join(finished.storage, "**", "*.pt"), recursive=True)
    before = {path: os.path.getmtime(path) for path in files}
    ray.shutdown()
    sweeps.main(finished)
    assert {path: os.path.getmtime(path) for path in glob.glob(os.path.join(finished.storage, "**", "*.pt"),
                                                               recursive=True)} == before  # fmt: skip


def test_another_grid_under_the_same_name_or_an_unknown_flag_is_refused(finished):
    with pytest.raises(SystemExit, match="was started with other grid"):
        sweeps.check(dataclasses.replace(finished, grid=GRID[:1]))
    with pytest.raises(SystemExit, match="no_such_flag"):
        sweeps.check(dataclasses.replace(finished, name="other", grid=("no_such_flag=1",)))
    with pytest.raises(SystemExit, match="same tag"):
        sweeps.check(dataclasses.replace(finished, name="other", grid=("default", "default")))
    with pytest.raises(SystemExit, match="^sweep.py: --report-every must be >= 1, got 0$"):
        sweeps.check(dataclasses.replace(finished, name="other", report_every=0))


def test_a_cpu_budget_ends_each_trial_and_the_report_reads_its_last_policy(finished, monkeypatch, capsys):
    """--cpu-hours: a budget of 1e-6 CPU-hours (3.6 ms) is spent by the first race, so the trial stops at its first
    check (however many updates that is on this machine), far short of --updates 50, and the report measures the
    latest.pt it stopped at. A sweep.json written before the budget existed reads as no budget."""
    import ray

    budget = dataclasses.replace(finished, name="budget", grid=GRID[:1], updates=50, cpu_hours=1e-6)
    ray.shutdown()
    try:
        sweeps.main(budget)
    finally:
        ray.shutdown()
    [(config, run, done, hours, ended, stopped)] = sweeps.trial_status(budget)
    assert ended and not stopped and done < 50 and hours >= budget.cpu_hours
    assert f": done ({hours:.3f} of 1e-06 CPU-hours, {done} updates)" in sweeps.status_text(budget)
    unfinished = sweeps.status_text(dataclasses.replace(budget, cpu_hours=0.0))  # (the same trial: short of 50)
    assert unfinished.endswith(f": {done} of 50 updates, {hours:.3f} CPU-hours") and ": done" not in unfinished
    every = dict.fromkeys((*readings.MODEL, *readings.PEDAL), float("nan"))  # (nothing left to add later)
    monkeypatch.setattr(readings, "measure", lambda path, run_dir, updates, *a: {
        p: {"updates_measured": updates, **every} for p in readings.POLICIES})  # fmt: skip
    monkeypatch.setattr(readings, "COLUMNS", (*readings.COLUMNS, "updates_measured"))
    monkeypatch.setattr(sweeps, "report_table", lambda *a: "")
    sweeps.report(budget)
    with open(os.path.join(budget.results, "sweep_budget.csv")) as f:
        rows = list(csv.DictReader(f))
    assert [(r["updates"], r["updates_measured"], r["checkpoint"].endswith("latest.pt")) for r in rows] == [
        (str(done), str(done), True)] * 2  # fmt: skip
    path = os.path.join(budget.storage, "budget", "sweep.json")
    with open(path) as f:
        saved = json.load(f)
    del saved["cpu_hours"]
    with open(path, "w") as f:
        json.dump(saved, f)
    old = dataclasses.replace(budget, cpu_hours=0.0)  # the sweep as a command line of before the budget gives it
    assert sweeps.saved_fields(budget)["cpu_hours"] == 0.0
    sweeps.check(old)  # continued with the same command: not refused
    with pytest.raises(SystemExit, match="other cpu_hours"):
        sweeps.check(budget)
    sweeps.main(dataclasses.replace(old, status=True))
    assert "budget), 50 updates per trial:" in capsys.readouterr().out


def test_tags_name_flag_sets_and_stay_short():
    assert sweeps.tag_of("default") == "default" and sweeps.flag_set("default") == ()
    assert sweeps.tag_of("entropy_coef=0.3 return_norm=true") == "entropy-coef-0.3_return-norm-true"
    long_a, long_b = sweeps.tag_of(TINY_FLAGS), sweeps.tag_of(TINY_FLAGS + " gamma=0.9")
    assert len(long_a) == len(long_b) == sweeps.TAG_LENGTH and long_a != long_b


def test_the_report_measures_each_finished_trial_once_with_both_policies(finished, monkeypatch):
    text = sweeps.report(finished)
    with open(os.path.join(finished.results, "sweep_tiny.csv")) as f:
        rows = list(csv.DictReader(f))
    assert [(r["tag"], r["policy"]) for r in rows] == [
        (sweeps.tag_of(flags), policy) for flags in GRID for policy in readings.POLICIES
    ]
    assert all(0 <= float(r["gas"]) <= 1 and float(r["speed"]) >= 0 for r in rows)
    for flags in GRID:  # the training readings: the trial's own logged actor sigma, averaged over its 2 updates
        spec = sweeps.trial_spec(finished, flags, "lstm", 3)
        run = runs.run_of(sweeps.experiment.trial_dir(spec, "single", "lstm", 3))
        with open(os.path.join(run, "progress.csv")) as f:
            logged = [float(r["car_0/losses/actor_std"]) for r in csv.DictReader(f) if r.get("car_0/losses/actor_std")]
        assert len(logged) >= 1
        for r in (r for r in rows if r["tag"] == sweeps.tag_of(flags)):
            assert float(r["actor_sigma"]) == pytest.approx(sum(logged) / len(logged), abs=1e-4)
    assert "| tag | variant | seed | policy | return |" in text
    # the tiny car leaves the road before the 40 decisions a pedal reading needs: NaN, not a made-up number
    assert all(math.isnan(float(r["pedal_range_real"])) for r in rows)
    monkeypatch.setattr(readings, "measure", lambda *a: pytest.fail("measured again"))
    assert sweeps.report(finished) == text  # from readings.json
    cache_path = os.path.join(finished.storage, finished.name, "readings.json")
    with open(cache_path) as f:
        cache = json.load(f)
    for values in (v for per_policy in cache.values() for v in per_policy.values()):
        del values["pedal_range_imagined"], values["pedal_range_real"]  # as kept before the PEDAL columns
    with open(cache_path, "w") as f:
        json.dump(cache, f)
    calls = []
    monkeypatch.setattr(readings, "pedal", lambda path, first: calls.append(path) or {
        "pedal_range_imagined": 1.5, "pedal_range_real": 80.0})  # fmt: skip
    sweeps.report(finished)
    with open(os.path.join(finished.results, "sweep_tiny.csv")) as f:
        assert {(r["pedal_range_imagined"], r["pedal_range_real"]) for r in csv.DictReader(f)} == {("1.5", "80.0")}
    assert len(calls) == len(GRID)  # once per trial, for both policies


def test_a_model_reading_added_later_is_measured_on_the_same_drive_as_the_kept_ones(finished, monkeypatch, tmp_path):
    """Readings kept before terminal_continue was read get it: only the MODEL readings are measured again, once, by
    the same seeded drive (calibrate_checkpoint with the same checkpoint and tracks), and the kept ones must come
    back; where they do not (here: an elimination count kept otherwise), the report refuses, naming it."""
    drives = []
    calibrate = readings.calibrate_checkpoint
    monkeypatch.setattr(readings, "calibrate_checkpoint", lambda *a: drives.append(a) or calibrate(*a))
    cache_path = os.path.join(finished.storage, finished.name, "readings.json")
    os.replace(cache_path, tmp_path / "kept.json")  # measured anew here, with the drives recorded
    try:
        sweeps.report(finished)
        with open(cache_path) as f:
            kept = json.load(f)
        measured, drives[:] = list(drives), []
        old = json.loads(json.dumps(kept))
        for values in (v for per_policy in old.values() for v in per_policy.values()):
            del values["terminal_continue"]  # as kept before the column
        with open(cache_path, "w") as f:
            json.dump(old, f)
        monkeypatch.setattr(readings, "measure", lambda *a: pytest.fail("measured again"))
        monkeypatch.setattr(readings, "pedal", lambda *a: pytest.fail("the pedal read again"))
        sweeps.report(finished)
        assert drives == measured and len(drives) == len(GRID)  # the same drives, once per trial
        sweeps.report(finished)
        assert len(drives) == len(GRID)  # added once, kept since
        with open(cache_path) as f:
            again = json.load(f)
        for key, per_policy in kept.items():
            for policy, values in per_policy.items():
                assert again[key][policy].keys() == values.keys()
                assert all(math.isclose(again[key][policy][c], v) or (math.isnan(v) and math.isnan(
                    again[key][policy][c])) if isinstance(v, float) else again[key][policy][c] == v
                    for c, v in values.items())  # fmt: skip
        with open(os.path.join(finished.results, "sweep_tiny.csv")) as f:
            rows = list(csv.DictReader(f))
        for row in rows:  # a probability on the frames where the car left the road, or NaN where it never did
            value = float(row["terminal_continue"])
            assert math.isnan(value) if row["eliminations"] == "0" else 0.0 <= value <= 1.0
        first = next(iter(old))
        for values in old[first].values():
            values["eliminations"] = 99  # kept from another drive
        with open(cache_path, "w") as f:
            json.dump(old, f)
        with pytest.raises(SystemExit, match=r"do not come back on the same tracks \(eliminations kept 99, now "):
            sweeps.main(dataclasses.replace(finished, report=True))
    finally:
        os.replace(tmp_path / "kept.json", cache_path)


def test_training_readings_average_the_last_window_of_updates(tmp_path):
    """Rows logged at 400, 600 and 1000 updates: the window (500, 1000] holds the last two."""
    rows = [
        {"car_0/perf/updates": 400, "car_0/losses/actor_std": 9.0, "charts/cpu_hours": 0.1},
        {"car_0/perf/updates": 600, "car_0/losses/actor_std": 0.5, "charts/cpu_hours": 0.2},
        {"car_0/perf/updates": 1000, "car_0/losses/actor_std": 0.3, "car_0/losses/alpha": 0.2, "charts/cpu_hours": 0.4},
    ]
    columns = sorted({key for row in rows for key in row})
    with open(tmp_path / "progress.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    out = readings.training(str(tmp_path), 1000)
    assert out["actor_sigma"] == pytest.approx(0.4) and out["alpha"] == pytest.approx(0.2)
    assert out["cpu_hours"] == pytest.approx(0.4) and out["entropy"] != out["entropy"]  # NaN: not logged
    json.dumps(out)  # the cache holds it
