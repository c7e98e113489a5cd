"""benchmarks/experiment.py: the paper's three stages as Ray Tune trials on a local Ray, at a tiny size.

One spec of 2 variants x 1 seed x all three stages runs to completion; a dreamer trial whose worker is killed
(SIGKILL) is retried by Ray and resumes from its latest.pt with its counters intact while the other trials are
untouched; the same spec run again does nothing; the aggregation matches hand-computed numbers."""

import csv
import dataclasses
import glob
import importlib
import json
import os
import shutil
import sys

import numpy as np
import pytest
import scipy.stats
from conftest import TINY_TRIAL

import experiment
import experiment_report
import race
import runs
import utils.checkpoint
import stats

TINY_FLAGS = {**TINY_TRIAL, "ghost_tracks": 1, "action_repeat": 2}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """The tiny spec, run once to the end (each single-stage trial is killed once after its first update)."""
    pytest.importorskip("ray")
    import ray

    root = tmp_path_factory.mktemp("experiment")
    spec = experiment.Spec(
        seeds=(3,), preset="paper", overrides=tuple(f"{k}={v}" for k, v in TINY_FLAGS.items()), single_updates=2,
        ghost_updates=1, race_episodes=2, tournament_every=1, tournament_races=2, race_train_steps=1,
        report_every=1, fresh_tracks=1, storage=str(root / "storage"), results=str(root / "results"),
        max_failures=2, chaos_kill_after_updates=1,
    )  # fmt: skip
    try:
        experiment.main(spec)  # (its own ray.init: a local Ray on this machine)
        yield spec
    finally:
        ray.shutdown()


def latest(spec, stage, variant):
    run = runs.run_of(experiment.trial_dir(dataclasses.asdict(spec), stage, variant, 3))
    return run, dreamer_lstm_or_gru(variant).load_checkpoint(os.path.join(run, "checkpoints", "latest.pt"))


def dreamer_lstm_or_gru(variant):
    return __import__(f"dreamer_{variant}")


def test_every_stage_runs_to_completion_and_writes_the_tables(finished):
    spec = finished
    for variant in ("lstm", "gru"):
        _, single = latest(spec, "single", variant)
        assert single["agents"][0]["num_updates"] == 2
        for kind in ("ghost", "control"):
            run, checkpoint = latest(spec, kind, variant)
            start = checkpoint["args"]["checkpoint"]
            assert start.endswith("best.pt") and f"single_{variant}_seed3" in start  # from the single trial's best.pt
            best_updates = runs.updates_of(start, __import__(f"dreamer_{variant}"))
            assert checkpoint["agents"][0]["num_updates"] == best_updates + 1  # as many updates, ghost and control
        assert latest(spec, "ghost", variant)[1]["args"]["stage"] == "ghost"
        assert latest(spec, "control", variant)[1]["args"]["stage"] == "single"
    with open(os.path.join(spec.results, "head_to_head.csv")) as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert tuple(reader.fieldnames) == experiment_report.HEAD_COLUMNS
    assert [int(r["races_trained"]) for r in rows] == [0, 1, 2] and all(r["seed_pair"] == "3,3" for r in rows)
    for r in rows:
        wins, races = int(r["lstm_wins"]), int(r["eval_races"])
        assert races == 2 and wins + int(r["gru_wins"]) + int(r["no_winner"]) - int(r["dead_heats"]) == races
        low, high = race.wilson_interval(wins, races)
        assert np.isclose(float(r["lstm_win_rate_ci_low"]), low, atol=1e-4)
        assert np.isclose(float(r["lstm_win_rate_ci_high"]), high, atol=1e-4)
    with open(os.path.join(spec.results, "ghost_vs_control.csv")) as f:
        reader = csv.DictReader(f)
        ghost = list(reader)
    assert tuple(reader.fieldnames) == experiment_report.GHOST_COLUMNS
    assert [(r["variant"], int(r["updates"])) for r in ghost] == [("lstm", 1), ("gru", 1)]
    summary = open(os.path.join(spec.results, "experiment.md")).read()
    assert "P(LSTM win rate > GRU win rate)" in summary
    assert "| the LSTM-Dreamer beats the GRU-Dreamer head to head | last tournament (after 2 races)" in summary


def test_status_names_every_trial_with_how_far_it_got(finished, tmp_path, capsys):
    spec = finished
    experiment.main(experiment.Spec(storage=spec.storage, status=True))  # the experiment's own spec, not the flags'
    lines = capsys.readouterr().out.splitlines()
    ghost = {}  # per variant: its single trial's best.pt's updates and the ghost stage's (the control's as many)
    for variant in ("lstm", "gru"):
        start = latest(spec, "ghost", variant)[1]["args"]["checkpoint"]
        ghost[variant] = runs.updates_of(start, __import__(f"dreamer_{variant}")) + spec.ghost_updates
    assert lines[:3] == ["single:", "  single_lstm_seed3 (2 of 2 updates)", "  single_gru_seed3 (2 of 2 updates)"]
    assert lines[3:8] == ["ghost:"] + [f"  {kind}_{v}_seed3 ({ghost[v]} of {ghost[v]} updates)"
                                       for kind in ("ghost", "control") for v in ("lstm", "gru")]  # fmt: skip
    assert lines[8:] == ["race:", "  race_lstm_gru_seed3 (2 of 2 races; tournaments after 0, 1, 2 races)"]
    with pytest.raises(SystemExit, match="--status: no experiment in .*nothing"):
        experiment.main(experiment.Spec(storage=str(tmp_path / "nothing"), status=True))
    assert not os.path.exists(tmp_path / "nothing")  # nothing written


def test_a_killed_trial_resumes_its_own_run_with_its_counters_and_replay(finished):
    spec = finished
    plain = dataclasses.asdict(spec)
    for variant in ("lstm", "gru"):  # every dreamer trial was killed once (chaos), retried and resumed
        directory = experiment.trial_dir(plain, "single", variant, 3)
        assert os.path.exists(os.path.join(directory, "chaos_killed"))
        assert len(glob.glob(os.path.join(directory, "*", "checkpoints"))) == 1  # one run, continued, not restarted
        run, checkpoint = latest(spec, "single", variant)
        assert checkpoint["agents"][0]["num_updates"] == 2
        assert checkpoint["extra"]["replays"][0]["episodes"] == checkpoint["counters"]["episode"]  # replay intact


def test_the_same_spec_again_does_nothing(finished):
    """Run again, a finished experiment trains nothing and races no tournament again: every checkpoint and every
    tournament's results file keeps its time."""
    spec = finished

    def written() -> dict:
        patterns = ("*.pt", "results.json", "results.csv")  # checkpoints; the race trial's tournaments
        paths = [p for pattern in patterns for p in glob.glob(os.path.join(spec.storage, "trials", "**", pattern),
                                                               recursive=True)]  # fmt: skip
        return {path: os.path.getmtime(path) for path in paths}

    before = written()
    assert any(path.endswith("results.json") for path in before)  # (the tournaments are among them)
    import ray

    ray.shutdown()
    experiment.main(dataclasses.replace(spec, chaos_kill_after_updates=0))
    assert written() == before


def test_a_rerun_with_other_trials_or_a_missing_stage_is_refused_before_ray_starts(finished, tmp_path):
    with pytest.raises(SystemExit, match="holds an experiment with other single_updates"):
        experiment.check_spec(dataclasses.replace(finished, single_updates=5))
    with pytest.raises(SystemExit, match=r"needs the single trials finished: single_lstm_seed1 \(not started\)"):
        experiment.check_spec(experiment.Spec(seeds=(1,), stages=("ghost",), storage=str(tmp_path)))
    with pytest.raises(SystemExit, match=r"needs the ghost trials finished: ghost_lstm_seed1 \(not started\)"):
        experiment.check_spec(experiment.Spec(seeds=(1,), stages=("race",), storage=str(tmp_path)))  # nothing ran
    with pytest.raises(ValueError, match="not name=value"):
        experiment.check_spec(experiment.Spec(overrides=("no_such_flag=1",), storage=str(tmp_path)))
    # a count below 1 reads as "no limit" to the scripts: its trial would never end (a resumed one, report forever)
    for name, value in (("report_every", 0), ("single_updates", -1), ("ghost_updates", 0), ("tournament_every", 0)):
        with pytest.raises(SystemExit, match=f"^experiment.py: --{name.replace('_', '-')} must be >= 1, got {value}$"):
            experiment.check_spec(experiment.Spec(storage=str(tmp_path / "new"), **{name: value}))
    with pytest.raises(SystemExit, match="--single-cpu-hours must be >= 0, got nan"):
        experiment.check_spec(experiment.Spec(single_cpu_hours=float("nan"), storage=str(tmp_path / "new")))
    assert not os.path.exists(tmp_path / "new")  # refused before its spec.json
    # Ray's "retry forever" and an experiment without head-to-head training are no bad counts
    experiment.check_spec(experiment.Spec(stages=("single",), max_failures=-1, race_episodes=0,
                                          storage=str(tmp_path / "new")))  # fmt: skip


def test_a_local_ray_offers_the_cpus_asked_for_and_a_rerun_may_change_them(finished, tmp_path, monkeypatch):
    import ray

    experiment.check_spec(dataclasses.replace(finished, num_cpus=3))  # not a trial setting: the same experiment
    with pytest.raises(SystemExit, match="--num-cpus is for a local Ray"):
        experiment.check_spec(experiment.Spec(num_cpus=3, address="auto", storage=str(tmp_path)))
    with pytest.raises(SystemExit, match=r"--num-cpus \(1\) must be at least --torch-threads \(2\)"):
        experiment.check_spec(experiment.Spec(num_cpus=1, torch_threads=2, storage=str(tmp_path)))

    class Started(Exception):
        pass

    asked = {}

    def init(**kwargs):
        asked.update(kwargs)
        raise Started

    monkeypatch.setattr(ray, "init", init)
    with pytest.raises(Started):
        experiment.main(dataclasses.replace(finished, num_cpus=3))
    assert asked["num_cpus"] == 3 and asked["address"] is None


def test_a_spec_saved_before_a_field_existed_means_the_value_it_ran_with(tmp_path):
    assert experiment.Spec().eval_policy == "mean-action"  # today's default, not what older experiments ran with
    spec = experiment.Spec(stages=("single",), storage=str(tmp_path), eval_policy="stochastic")
    saved = experiment.trial_fields(spec)
    del saved["eval_policy"]  # an experiment started before the tournaments' policy was a field
    with open(tmp_path / "spec.json", "w") as f:
        json.dump(saved, f)
    experiment.main(experiment.Spec(storage=str(tmp_path), status=True))  # --status reads it as it ran ...
    with open(tmp_path / "spec.json") as f:
        assert "eval_policy" not in json.load(f)  # ... and writes nothing
    experiment.check_spec(spec)  # it ran with the sampled policy: the same experiment
    with open(tmp_path / "spec.json") as f:
        assert json.load(f)["eval_policy"] == "stochastic"  # written down: a later default cannot change it
    with pytest.raises(SystemExit, match="measures its agents with --eval-policy stochastic"):
        experiment.main(dataclasses.replace(spec, eval_policy="mean-action", aggregate_only=True))


def test_every_entry_point_evaluates_with_the_same_policy_by_default():
    import dreamer_gru
    import dreamer_lstm

    # the rule of docs/learning.md chose one evaluation policy: the scripts, race.py and the experiment agree on it
    defaults = [dreamer_lstm.Args().eval_policy, dreamer_gru.Args().eval_policy, race.Args().policy,
                experiment.Spec().eval_policy]  # fmt: skip
    assert defaults == ["mean-action"] * 4


def test_a_restored_trial_that_predates_a_field_takes_the_value_it_ran_with():
    saved = experiment.trial_fields(experiment.Spec())
    del saved["eval_policy"]  # a Tune trial created before the field existed ran with the sampled policy
    assert experiment.restored_spec(saved)["eval_policy"] == "stochastic" != experiment.Spec().eval_policy
    assert experiment.restored_spec({**saved, "eval_policy": "mean-action"})["eval_policy"] == "mean-action"
    assert experiment.restored_spec(saved)["ghost_updates"] == experiment.Spec().ghost_updates  # others: defaults


def test_the_evaluation_policy_may_change_until_the_race_stage_has_begun(tmp_path):
    spec = experiment.Spec(stages=("single",), storage=str(tmp_path), eval_policy="stochastic")
    experiment.check_spec(spec)
    mean_action = dataclasses.replace(spec, eval_policy="mean-action")
    experiment.check_spec(mean_action)  # no tournament has used it yet: chosen now, and written down
    with open(tmp_path / "spec.json") as f:
        assert json.load(f)["eval_policy"] == "mean-action"
    with pytest.raises(SystemExit, match="holds an experiment with other eval_policy, single_updates"):
        experiment.check_spec(dataclasses.replace(spec, single_updates=5))  # with another field: refused as a whole
    os.makedirs(tmp_path / "trials" / "race_lstm_gru_seed11")  # the race stage has begun
    with pytest.raises(SystemExit, match="holds an experiment with other eval_policy;"):
        experiment.check_spec(spec)
    with open(tmp_path / "spec.json") as f:
        assert json.load(f)["eval_policy"] == "mean-action"  # unchanged by the refused run


def test_the_summary_matches_hand_computed_numbers():
    summary = experiment_report.summarize({"lstm": [100.0, 200.0, 300.0], "gru": [1.0, 2.0, 3.0, 10.0]},
                                   {"lstm": [0.6, 0.7], "gru": [0.4, 0.3]}, reps=300)  # fmt: skip
    lines = summary.splitlines()
    assert lines[2].startswith("| lstm | 3 | 200.0 [")  # IQM of 3 = mean
    assert lines[2].split("|")[4].strip().startswith("200.0 [")  # the mean's own cell
    assert lines[3].startswith("| gru | 4 | 2.5 [") and "| 4.0 [" in lines[3]  # IQM = mean(2, 3)
    # the IQM's and the mean's intervals lie within the scores (a bootstrap of them), around the point
    for line, lowest, highest in ((lines[2], 100.0, 300.0), (lines[3], 1.0, 10.0)):
        for cell in line.split("|")[3:5]:  # IQM, mean
            point, interval = cell.split("[")
            low, high = (float(v) for v in interval.rstrip("] ").split(","))
            assert lowest <= low < float(point) < high <= highest
    # the LSTM wins both pairs: P = 1, and every bootstrap of the pairs gives 1
    assert "the share of 2 seed pair(s)" in lines[-1] and lines[-1].endswith(": 1.00 [1.00, 1.00]")
    tie = experiment_report.summarize({}, {"lstm": [0.5], "gru": [0.5]}, reps=100)
    assert tie.splitlines()[-1].endswith(": 0.50 [0.50, 0.50]")  # a tie counts one half
    # paired, not rliable's independent samples: the LSTM wins 2 pairs of 3 -> 2/3 (comparing every LSTM rate
    # with every GRU rate would give 4/9); a bootstrap of 3 pairs can draw 0, 1, 2 or 3 wins: [0, 1]
    three = experiment_report.summarize({}, {"lstm": [0.55, 0.35, 0.60], "gru": [0.45, 0.65, 0.40]}, reps=2000)
    assert three.splitlines()[-1].endswith(": 0.67 [0.00, 1.00]")
    with pytest.raises(ValueError, match="two non-empty arrays of one length, got 1 and 2"):
        stats.paired_probability_of_improvement([0.5], [0.5, 0.4])  # rates of different pairs cannot be paired


def test_the_default_single_stage_is_the_cpu_preset_with_one_car_and_kept_evaluations(tmp_path):
    """At the default spec (CPU preset, no overrides) a single-stage trial is the CPU preset with one car, its
    evaluations on the 10 held-out tracks kept, one thread, 8,000 updates, named learning_<variant> as the
    8,000-update protocol's runs were (so runs.find_run and an earlier storage find it); a spec that changes a flag
    names its trials apart."""
    import dreamer_gru
    import dreamer_lstm

    spec = dataclasses.asdict(experiment.Spec(storage=str(tmp_path)))
    for script in (dreamer_lstm, dreamer_gru):
        variant = script.VARIANT
        _, args, first, target = experiment.trial_args(spec, "single", variant, 12)
        reference = script.preset_args("cpu", seed=12, exp_name=f"learning_{variant}", stage="single", num_agents=1,
                                       eval_episodes=10, eval_checkpoints=True, torch_threads=1)  # fmt: skip
        differ = {f.name for f in dataclasses.fields(args) if getattr(args, f.name) != getattr(reference, f.name)}
        assert differ == {"runs_dir", "total_episodes"}  # the trial's directory; its chunks end it, not races
        assert (first, target) == (None, 8000)
        os.makedirs(os.path.join(args.runs_dir, f"multi_car_racing__{args.exp_name}__12__1700000000"))
        assert runs.find_run(runs.experiment_name(variant), 12, str(tmp_path / "trials")) is not None
    for change in ({"overrides": ("entropy_coef=0.5",)}, {"single_updates": 2000}, {"torch_threads": 2},
                   {"eval_policy": "deterministic"}):  # fmt: skip
        changed = dataclasses.asdict(experiment.Spec(storage=str(tmp_path), **change))
        assert experiment.trial_args(changed, "single", "gru", 12)[1].exp_name == "gru_single"
    # sampled evaluations, as the 8,000-update protocol's runs were made: still named as they were
    sampled = dataclasses.asdict(experiment.Spec(storage=str(tmp_path), eval_policy="stochastic"))
    assert experiment.trial_args(sampled, "single", "gru", 12)[1].exp_name == "learning_gru"


def test_a_stage_missing_the_checkpoint_it_starts_from_says_which(tmp_path):
    """A ghost trial whose single trial it cannot see (on a cluster: a node without the driver's --storage) stops
    with an error naming the trial and the checkpoint, not a TypeError from a path of None."""
    spec = dataclasses.asdict(experiment.Spec(storage=str(tmp_path)))
    with pytest.raises(FileNotFoundError, match="the single trial of gru seed 12 has no checkpoints/best.pt"):
        experiment.trial_args(spec, "ghost", "gru", 12)
    run = os.path.join(experiment.trial_dir(spec, "single", "gru", 12), "run", "checkpoints")
    os.makedirs(run)
    open(os.path.join(run, "latest.pt"), "w").close()  # a run with a latest.pt but no best.pt yet
    with pytest.raises(FileNotFoundError, match="shared filesystem"):
        experiment.trial_args(spec, "ghost", "gru", 12)
    assert experiment.start_checkpoint(spec, "single", "gru", 12, "latest.pt") == os.path.join(run, "latest.pt")


def test_a_whole_experiment_killed_mid_trial_resumes_on_the_same_command(tmp_path):
    """What the end of a sitting does: the driver, Ray and the trials' workers all killed at once (SIGKILL to the
    process group), here in the ghost stage, after the single stage has finished. The same command then skips the
    finished single trial, leaving every file of it as it was, and continues the ghost trial and its control from
    their latest.pt: one run directory each, every update counted once, the replay whole."""
    pytest.importorskip("ray")
    import signal
    import subprocess
    import time

    storage = tmp_path / "storage"
    command = [
        sys.executable, os.path.join(experiment.ROOT, "benchmarks", "experiment.py"), "--stages", "single", "ghost",
        "--variants", "lstm", "--seeds", "3", "--preset", "paper", "--overrides",
        *(f"{k}={v}" for k, v in TINY_FLAGS.items()), "--single-updates", "2", "--ghost-updates", "8",
        "--report-every", "1", "--storage", str(storage), "--results", str(tmp_path / "results"),
    ]  # fmt: skip
    plain = dataclasses.asdict(experiment.Spec(seeds=(3,), storage=str(storage)))
    script = dreamer_lstm_or_gru("lstm")

    def updates(kind):
        run = runs.run_of(experiment.trial_dir(plain, kind, "lstm", 3))
        return runs.updates_of(os.path.join(run, "checkpoints", "latest.pt"), script)

    driver = subprocess.Popen(command, cwd=experiment.ROOT, start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        done, deadline = 0, time.time() + 900  # (a guard against a hang; a loaded machine needs minutes)
        while done < 2 and time.time() < deadline and driver.poll() is None:  # a few ghost updates in, short of 8
            time.sleep(0.5)
            try:
                best = experiment.start_checkpoint(plain, "single", "lstm", 3, "best.pt")
                start = runs.updates_of(best, script)
                updates("control")  # the control has its latest.pt too (a run killed before it starts anew)
                done = updates("ghost") - start
            except (TypeError, OSError, EOFError, RuntimeError):
                done = 0  # no ghost or control run yet, or a checkpoint being replaced
    finally:
        os.killpg(driver.pid, signal.SIGKILL)
        driver.wait()
    assert 2 <= done < 8, f"the ghost trial was {done} updates in when the experiment was killed"
    single = experiment.trial_dir(plain, "single", "lstm", 3)

    def files(directory):
        return {p: (os.path.getsize(p), os.path.getmtime(p)) for p in glob.glob(f"{directory}/**", recursive=True)}

    before = files(single)
    assert updates("single") == 2 and any(p.endswith("best.pt") for p in before)
    kept = script.load_checkpoint(os.path.join(runs.run_of(single), "checkpoints", "latest.pt"))
    kept = kept["extra"]["replays"][0]["episodes"]  # the single run's replay, where ghost and control begin
    subprocess.run(command, cwd=experiment.ROOT, check=True, capture_output=True, timeout=600)
    assert files(single) == before  # the finished trial: skipped, not a file touched
    for kind in ("ghost", "control"):
        directory = experiment.trial_dir(plain, kind, "lstm", 3)
        assert len(glob.glob(os.path.join(directory, "*", "checkpoints"))) == 1
        checkpoint = script.load_checkpoint(os.path.join(runs.run_of(directory), "checkpoints", "latest.pt"))
        assert checkpoint["agents"][0]["num_updates"] == start + 8
        assert checkpoint["extra"]["replays"][0]["episodes"] == kept + checkpoint["counters"]["episode"]


def tournament(pair, races, lstm, gru, low=0.5, progress=(0.5, 0.5)):
    """A head_to_head.csv row: 100 evaluation races, `lstm` and `gru` wins."""
    return {"seed_pair": pair, "races_trained": races, "eval_races": 100, "lstm_wins": lstm, "gru_wins": gru,
            "lstm_win_rate_ci_low": low, "lstm_progress": progress[0], "gru_progress": progress[1]}  # fmt: skip


def test_the_claims_table_answers_each_claim_from_hand_made_results():
    """Numbers whose verdicts are known by hand, each judged by its exact test and t interval: the solo gap is
    large and consistent over 4 and 3 seeds (supported), head to head over 5 seed pairs the GRU wins every final
    tournament (contradicted), both agents lose progress when head-to-head training begins (supported for each),
    the LSTM's win rate changes little and either way after it (weak), and the ghost helps by exactly 50 in each of
    6 runs (supported, interval 50). Over 2 seed pairs the same kind of numbers are at best weak."""
    single = {"lstm": [600.0, 700.0, 800.0, 900.0], "gru": [100.0, 200.0, 300.0]}
    ghost = [{"return_after_ghost": 350.0 + k, "return_after_control": 300.0 + k} for k in range(6)]
    head = [tournament("16,16", 0, 100, 0, 0.95),  # a pair whose training has not begun: not a result yet
            tournament("17,17", 0, 0, 100, 0.0, (0.9, 0.9)), tournament("17,17", 50, 100, 0, 0.95, (0.1, 0.1))]
    #         (a pair stopped at 50 of 150 races: not a result yet either)
    for pair, progress0, at50, (lstm, gru) in [("11,11", 0.8, 20, (30, 60)), ("12,12", 0.7, 25, (20, 70)),
                                               ("13,13", 0.9, 15, (25, 65)), ("14,14", 0.6, 45, (35, 55)),
                                               ("15,15", 0.8, 25, (30, 60))]:  # fmt: skip
        head += [tournament(pair, 0, 90, 10, 0.8, (progress0, 0.6)), tournament(pair, 50, at50, 30, 0.1),
                 tournament(pair, 150, lstm, gru, 0.2)]  # fmt: skip
    table = experiment_report.claims_table(single, ghost, head, race_episodes=150).splitlines()
    assert table[0].split(" | ")[2:] == ["estimate", "test (one-sided p of the claim)", "verdict |"]
    solo, versus, lstm_perturbed, gru_perturbed, recovery, ghost_row = (line.split(" | ") for line in table[2:8])
    # solo: 750 - 200 = +550; the LSTM's four are the top four of seven in 1 of the C(7, 4) = 35 splits. Welch:
    # se^2 = (50000 / 3) / 4 + (20000 / 2) / 3 = 7500, df = 7500^2 / (4166.7^2 / 3 + 3333.3^2 / 2) = 4.96, so t is
    # between t_5 = 2.571 and t_4 = 2.776: the interval 550 +- (222.6 .. 240.4)
    assert solo[2] == "550.0" and solo[3].startswith("permutation p=0.029, Welch t 95% [+3")
    welch = scipy.stats.ttest_ind(single["lstm"], single["gru"], equal_var=False).confidence_interval(0.95)
    assert f"[{welch.low:+.1f}, {welch.high:+.1f}]" in solo[3] and 309.6 < welch.low < 327.4  # scipy's, as above
    assert solo[3].endswith("n=4+3")
    assert solo[4] == "supported |"
    # last tournaments: -0.30, -0.50, -0.40, -0.20, -0.30, mean -0.34, sd sqrt(0.052 / 4) = 0.1140, t_4 = 2.7764:
    # -0.34 +- 0.1416; all five negative: the opposite's p = 1/32
    assert versus[2] == "-0.34" and versus[3] == "sign-flip p=1.000, t 95% [-0.48, -0.20], n=5"
    assert versus[4].startswith("contradicted") and "above 0.5 in 0 of 5" in versus[1]
    # progress from race 0 to race 50: LSTM 0.3, 0.2, 0.4, 0.1, 0.3 (the same spread: 0.26 +- 0.1416), GRU 0.1 each
    assert lstm_perturbed[2] == "0.26" and lstm_perturbed[3] == "sign-flip p=0.031, t 95% [+0.12, +0.40], n=5"
    assert lstm_perturbed[4] == "supported |" and "(races 0 to 50), mean over 5 seed pairs" in lstm_perturbed[1]
    assert gru_perturbed[2] == "0.10" and gru_perturbed[3] == "sign-flip p=0.031, t 95% [+0.10, +0.10], n=5"
    assert gru_perturbed[4] == "supported |" and "the GRU's mean progress" in gru_perturbed[1]
    # the LSTM's rate from the first tournament after training began: +0.10, -0.05, +0.10, -0.10, +0.05, mean 0.02;
    # in units of 0.05 |d| = 2, 1, 2, 2, 1 sum to 8 and the observed sum is 2: an assignment reaches it when its
    # negated part sums to 3 or less: {}, 5 singletons, {1, 1}, 6 of {2, 1}: 13/32 = 0.406. sd
    # sqrt(0.033 / 4) = 0.0908: 0.02 +- 0.1128 (from the tournaments before training, at 0.90, it would be -0.62)
    assert recovery[2] == "0.02" and recovery[3] == "sign-flip p=0.406, t 95% [-0.09, +0.13], n=5"
    assert recovery[4] == "weak (positive, but the exact test's p = 0.406 is not below 0.05) |"
    assert ghost_row[2] == "50.0" and ghost_row[3] == "sign-flip p=0.016, t 95% [+50.0, +50.0], n=6"
    assert ghost_row[4] == "supported |" and len(table) == 8  # no floor note: every row can reach 0.05
    # the same kind of numbers over 2 pairs: last tournaments 0.30 - 0.60 and 0.20 - 0.70, progress drops of 0.3 and
    # 0.1 (LSTM) and 0.1 (GRU): 1/4 is the sign-flip test's floor, so nothing is supported or contradicted
    two = [tournament("11,11", 0, 90, 10, 0.8, (0.8, 0.7)), tournament("11,11", 50, 20, 70, 0.13, (0.5, 0.6)),
           tournament("11,11", 150, 30, 60, 0.22), tournament("12,12", 0, 90, 10, 0.8, (0.6, 0.6)),
           tournament("12,12", 50, 40, 50, 0.31), tournament("12,12", 150, 20, 70, 0.13)]  # fmt: skip
    table = experiment_report.claims_table({}, [], two, race_episodes=150).splitlines()
    versus, lstm_perturbed, gru_perturbed, recovery = (line.split(" | ") for line in table[2:6])
    assert versus[4] == "not supported (the estimate is negative; the opposite's p = 0.250) |"
    # LSTM drops 0.3 and 0.1: 0.2 +- t_1 * 0.1 = 0.2 +- 12.706 * 0.1414 / sqrt(2)
    assert lstm_perturbed[3] == "sign-flip p=0.250, t 95% [-1.07, +1.47], n=2"
    assert lstm_perturbed[4].startswith("weak") and gru_perturbed[4].startswith("weak")
    assert recovery[2] == "-0.05" and recovery[4].startswith("not supported")
    assert table[-1] == stats.SMALL_SAMPLE_NOTE and "1/8 for 3 pairs" in table[-1]


def test_a_claim_on_one_run_is_not_judged_and_one_agent_gaining_is_not_both_perturbed():
    head = [tournament("11,11", 0, 50, 50, progress=(0.4, 0.9)),
            tournament("11,11", 50, 60, 40, progress=(0.6, 0.5))]
    table = experiment_report.claims_table({"lstm": [600.0], "gru": [100.0]}, [], head, race_episodes=50)
    solo, versus, lstm_perturbed, gru_perturbed, recovery = (line.split(" | ") for line in table.splitlines()[2:7])
    for row in (solo, versus, lstm_perturbed, gru_perturbed, recovery):  # one pair, one seed: no spread, no interval
        assert row[4].startswith("too few runs to judge (n = 1)") and ", no interval, n=1" in row[3]
    assert lstm_perturbed[2] == "-0.20" and gru_perturbed[2] == "0.40"
    # one difference: its two signs are the whole null; -0.20 is the lower (p 1), 0.40 the higher (p 1/2)
    assert lstm_perturbed[3].startswith("sign-flip p=1.000") and gru_perturbed[3].startswith("sign-flip p=0.500")
    assert solo[3] == "permutation p=0.500, no interval, n=1+1"
    assert stats.SMALL_SAMPLE_NOTE not in table  # no row of 2 runs or more


def results_json(directory, lstm_wins, gru_wins, races=10, progress=(0.5, 0.5)):
    """A tournament's results.json as race.py writes it: LSTM then GRU."""
    os.makedirs(directory)
    shared = {"races": races, "all_eliminated": 1, "no_winner": races - lstm_wins - gru_wins, "dead_heats": 0,
              "collision_steps": 3}  # fmt: skip
    rows = [{**shared, "racer": f"{v}:x.pt:0", "wins": w, "win_rate": w / races, "mean_progress": p,
             "win_rate_ci_low": 0.0, "win_rate_ci_high": 1.0, "eliminations": 1}
            for v, w, p in (("lstm", lstm_wins, progress[0]), ("gru", gru_wins, progress[1]))]
    with open(os.path.join(directory, "results.json"), "w") as f:
        json.dump(rows, f)


def test_the_aggregation_counts_finished_trials_only_and_replaces_old_tables(tmp_path, monkeypatch):
    """Fake trials (their progress and fresh-track returns given): an unfinished single trial, a ghost trial short
    of its updates and a race pair short of its races are named and left out; the ghost and control returns land in
    their own columns; tables of an earlier experiment do not survive."""
    spec = experiment.Spec(seeds=(11, 12), race_episodes=100, tournament_every=50, storage=str(tmp_path / "s"),
                           results=str(tmp_path / "results"))  # fmt: skip
    plain = dataclasses.asdict(spec)
    progress = {("single", "lstm", 11): 8000, ("single", "lstm", 12): 5000, ("single", "gru", 11): 8000,
                ("single", "gru", 12): 6000, ("ghost", "lstm", 11): 9000, ("control", "lstm", 11): 9000,
                ("ghost", "gru", 11): 9000, ("control", "gru", 11): 9000, ("ghost", "gru", 12): 7500,
                ("control", "gru", 12): 9000}  # fmt: skip
    stopped = {("single", "gru", 12)}  # the non-finite guard stopped it at 6,000 updates: finished, counted
    returns = {"single": 100.0, "ghost": 300.0, "control": 200.0}

    def trial_progress(spec, *trial):
        done, target = progress.get(trial, 0), 8000 if trial[0] == "single" else 9000
        return experiment.Progress(f"/runs/{'_'.join(map(str, trial))}" if trial in progress else None, done,
                                   done if trial in stopped else target, None, trial in stopped)  # fmt: skip

    monkeypatch.setattr(experiment_report, "trial_progress", trial_progress)
    monkeypatch.setattr(experiment_report, "updates_of", lambda path, script: 7000)  # every best.pt at 7,000 updates

    def fresh_return(spec, path, first):
        stage = path.split("/")[2].split("_")[0]
        return returns[stage] + (1.0 if path.endswith("best.pt") else 0.0) + (10.0 if "_gru_" in path else 0.0)

    monkeypatch.setattr(experiment_report, "fresh_return", fresh_return)
    os.makedirs(spec.results)
    for name in ("ghost_vs_control.csv", "head_to_head.csv"):
        with open(os.path.join(spec.results, name), "w") as f:
            f.write("an,earlier,experiment\n1,2,3\n")
    pair = lambda seed, races: os.path.join(experiment.trial_dir(plain, "race", "lstm_gru", seed),  # noqa: E731
                                            f"tournament_{races:05d}")  # fmt: skip
    results_json(pair(11, 0), 5, 5), results_json(pair(11, 50), 2, 8), results_json(pair(11, 100), 7, 3)
    results_json(pair(12, 0), 5, 5), results_json(pair(12, 50), 9, 0)  # (pair 12 stops at 50 of 100 races)
    summary = experiment_report.aggregate(spec)
    with open(os.path.join(spec.results, "ghost_vs_control.csv")) as f:
        ghost = list(csv.DictReader(f))
    assert [(r["variant"], r["seed"], r["updates_at_start"], r["updates"]) for r in ghost] == [
        ("lstm", "11", "7000", "2000"), ("gru", "11", "7000", "2000")]  # fmt: skip
    assert [(float(r["return_before"]), float(r["return_after_ghost"]), float(r["return_after_control"]))
            for r in ghost] == [(101.0, 300.0, 200.0), (111.0, 310.0, 210.0)]  # fmt: skip
    with open(os.path.join(spec.results, "head_to_head.csv")) as f:
        head = list(csv.DictReader(f))
    assert [(r["seed_pair"], r["races_trained"], r["lstm_wins"], r["no_winner"]) for r in head] == [
        ("11,11", "0", "5", "0"), ("11,11", "50", "2", "0"), ("11,11", "100", "7", "0"),
        ("12,12", "0", "5", "0"), ("12,12", "50", "9", "1")]  # fmt: skip
    assert "| lstm | 1 |" in summary and "| gru | 2 |" in summary  # lstm seed 12 is not finished
    assert "the share of 1 seed pair(s)" in summary and "1.00 [1.00, 1.00]" in summary  # pair 11 only: 0.7 > 0.3
    assert ("Not finished, left out of the statistics: single_lstm_seed12 (5000 of 8000 updates); ghost_gru_seed12 "
            "(7500 of 9000 updates); race pair 12,12 (tournaments up to 50 of 100 races).") in summary
    assert ("Counted with their last policies: single_gru_seed12 (6000 of 6000 updates, stopped by the non-finite "
            "guard).") in summary
    progress.pop(("ghost", "gru", 12))  # trials not started yet are named too: a ghost trial, a race pair
    shutil.rmtree(experiment.trial_dir(plain, "race", "lstm_gru", 12))
    assert "ghost_gru_seed12 (not started); race pair 12,12 (not started)." in experiment_report.aggregate(spec)
    progress.pop(("single", "gru", 12))
    assert "single_gru_seed12 (not started)" in experiment_report.aggregate(spec)
    shutil.rmtree(experiment.trial_dir(plain, "race", "lstm_gru", 11))
    progress.clear()  # nothing finished any more: the headers alone, no earlier rows
    experiment_report.aggregate(spec)
    tables = {"ghost_vs_control.csv": experiment_report.GHOST_COLUMNS,
              "head_to_head.csv": experiment_report.HEAD_COLUMNS}
    for name, columns in tables.items():
        with open(os.path.join(spec.results, name)) as f:
            assert f.read().splitlines() == [",".join(columns)]


def test_the_aggregation_reads_the_experiment_as_it_was_run(tmp_path, monkeypatch):
    spec = experiment.Spec(seeds=(11, 12, 13), stages=("single",), storage=str(tmp_path))
    experiment.check_spec(spec)
    seen = []
    monkeypatch.setattr(experiment_report, "aggregate", lambda spec: seen.append(spec.seeds) or "")
    experiment.main(dataclasses.replace(spec, seeds=(11,), aggregate_only=True))  # the flags' seeds would leave out 2
    assert seen == [(11, 12, 13)]


@pytest.fixture
def fake_race(tmp_path, monkeypatch):
    """A race trial's world without racing: ghost-stage latest.pt files, and a race.main that 'trains' (writes racer
    checkpoints whose race count it records; `cut` ({interval: (races, split)}) stops it in that interval after
    that many races, with racer 0 saved once more if split) or
    runs a tournament (writes results.json), recording every call."""
    pytest.importorskip("ray")
    from ray import tune

    spec = experiment.Spec(seeds=(3,), race_episodes=4, tournament_every=2, tournament_races=2, storage=str(tmp_path))
    plain = dataclasses.asdict(spec)
    races, calls, cut, stamps = {}, [], {}, iter(range(1_700_000_000, 1_800_000_000))
    for variant in ("lstm", "gru"):
        path = os.path.join(experiment.trial_dir(plain, "ghost", variant, 3), "run", "checkpoints", "latest.pt")
        os.makedirs(os.path.dirname(path))
        open(path, "w").close()
        races[path] = 0

    def main(argv):
        calls.append(argv)
        value = lambda flag: argv[argv.index(flag) + 1]  # noqa: E731
        if "--train" in argv:
            run = os.path.join(value("--runs-dir"), f"multi_car_racing__race__3__{next(stamps)}")
            os.makedirs(os.path.join(run, "checkpoints"))
            start, episodes = races[argv[0]], int(value("--episodes"))
            stop, split = cut.pop(os.path.basename(value("--runs-dir")), (episodes, False))
            for i in (0, 1):
                path = os.path.join(run, "checkpoints", f"racer_{i}.pt")
                open(path, "w").close()
                races[path] = start + stop + (1 if split and i == 0 else 0)
            if stop < episodes:
                raise KeyboardInterrupt  # the sitting ends mid-interval
        else:
            os.makedirs(value("--out"))
            won = {"lstm": 1, "gru": 1} if value("--policy") == "mean-action" else {"lstm": 0, "gru": 2}
            rows = [{"racer": f"{v}:{os.sep.join(argv[i].split(os.sep)[-4:])}:{i}", "races": 2, "wins": won[v],
                     "win_rate": won[v] / 2, "win_rate_ci_low": 0.1,
                     "win_rate_ci_high": 0.9, "mean_progress": 0.5, "eliminations": 0, "collision_steps": 0,
                     "all_eliminated": 0, "no_winner": 0, "dead_heats": 0}
                    for i, v in enumerate(("lstm", "gru"))]  # fmt: skip
            with open(os.path.join(value("--out"), "results.json"), "w") as f:
                json.dump(rows, f)

    monkeypatch.setattr(race, "main", main)
    monkeypatch.setattr(utils.checkpoint, "read_checkpoint",
                        lambda p: (None, {"counters": {"race_episodes": races[p]}}))  # fmt: skip
    reported = []
    monkeypatch.setattr(tune, "report", lambda metrics: reported.append(metrics["races_trained"]))
    config = {"trial": {"spec": plain, "seed": 3}}
    return plain, config, calls, cut, reported


def kinds(calls):
    """Each race.main call: ('train', episodes, its first checkpoint's trial/interval) or ('tournament', out)."""
    return [("train", int(c[c.index("--episodes") + 1]), c[0].split(os.sep)[-4]) if "--train" in c
            else ("tournament", os.path.basename(c[c.index("--out") + 1])) for c in calls]  # fmt: skip


def test_a_race_trial_continues_a_cut_interval_and_never_retrains_a_trained_one(fake_race):
    plain, config, calls, cut, reported = fake_race
    directory = experiment.trial_dir(plain, "race", "lstm_gru", 3)
    cut["races_00004"] = (1, False)  # the sitting ends after the first race of the second interval
    with pytest.raises(KeyboardInterrupt):
        experiment.race_trial(config)
    assert kinds(calls) == [
        ("tournament", "tournament_00000.tmp"),  # the ghost-stage agents, before any head-to-head race
        ("train", 2, "ghost_lstm_seed3"), ("tournament", "tournament_00002.tmp"),
        ("train", 2, "races_00002"),  # cut after its first race, both racers saved
    ]  # fmt: skip
    assert experiment.race_progress(plain, 3) == "race_lstm_gru_seed3 (3 of 4 races; tournaments after 0, 2 races)"
    calls.clear()
    experiment.race_trial(config)  # the next sitting: only the race left, from the last pair saved together
    assert kinds(calls) == [("train", 1, "races_00004"), ("tournament", "tournament_00004.tmp")]
    kept = sorted(os.listdir(os.path.join(directory, "races_00004")))
    assert len(kept) == 2  # the cut run and its continuation
    assert reported == [0, 2, 0, 2, 4]
    calls.clear()
    shutil.rmtree(os.path.join(directory, "tournament_00004"))  # a tournament cut short: raced again, alone
    experiment.race_trial(config)
    assert kinds(calls) == [("tournament", "tournament_00004.tmp")]
    calls.clear()
    experiment.race_trial(config)
    assert calls == []  # all done: nothing raced again


def test_a_second_policy_races_each_tournament_again_once_with_its_own_checkpoints(fake_race, tmp_path):
    """--second-policy: every tournament of the trial raced again with the other policy, by the same two checkpoints
    on the same held-out tracks, into its own directory and CSV; a second aggregation races nothing."""
    plain, config, calls, cut, _ = fake_race
    cut["races_00004"] = (1, True)  # a kill between the racers' saves: racer 0 one race ahead, pruned on resume
    with pytest.raises(KeyboardInterrupt):
        experiment.race_trial(config)
    experiment.race_trial(config)
    out = lambda call: os.path.basename(call[call.index("--out") + 1])  # noqa: E731
    flag = lambda call, name: call[call.index(name) + 1]  # noqa: E731
    first = {out(c): c for c in calls if "--train" not in c}
    assert {flag(c, "--policy") for c in first.values()} == {"mean-action"}
    directory = experiment.trial_dir(plain, "race", "lstm_gru", 3)
    held = lambda n: experiment.tournament_metrics(os.path.join(directory, f"tournament_{n:05d}"), n)  # noqa: E731
    head_rows = [experiment_report.head_row(3, held(n)) for n in (0, 2, 4)]
    spec = dataclasses.replace(experiment.Spec(**plain), second_policy="stochastic", results=str(tmp_path / "res"))
    os.makedirs(spec.results)
    calls.clear()
    text = experiment_report.second_policy_claims(spec, head_rows)
    again = {out(c): c for c in calls}
    assert sorted(again) == [f"tournament_{n:05d}_stochastic.tmp" for n in (0, 2, 4)]
    for n in (0, 2, 4):
        call, before = again[f"tournament_{n:05d}_stochastic.tmp"], first[f"tournament_{n:05d}.tmp"]
        assert call[:2] == before[:2]  # the same LSTM and GRU checkpoints: the ghost agents at 0, then each interval's
        assert (flag(call, "--policy"), flag(call, "--seed"), flag(call, "--races")) == (
            "stochastic", str(experiment.TOURNAMENT_SEED), "2")  # fmt: skip
        assert os.path.exists(os.path.join(directory, f"tournament_{n:05d}_stochastic", "results.json"))
    assert first["tournament_00000.tmp"][0].split(os.sep)[-4] == "ghost_lstm_seed3"
    with open(os.path.join(spec.results, "head_to_head_stochastic.csv")) as f:
        rows = list(csv.DictReader(f))
    assert [(r["seed_pair"], r["races_trained"], r["lstm_wins"], r["gru_wins"]) for r in rows] == [
        ("3,3", "0", "0", "2"), ("3,3", "2", "0", "2"), ("3,3", "4", "0", "2")]  # fmt: skip
    assert "raced again with the stochastic policy" in text
    assert ("with the mean-action policy - with the stochastic policy is +0.50 (sign-flip p=1.000 two-sided, no "
            "interval, n=1) over 1 seed pairs (+0.50): too few pairs to judge (n = 1)") in text  # fmt: skip
    assert "| the LSTM-Dreamer beats the GRU-Dreamer head to head |" in text
    assert experiment.race_progress(plain, 3) == "race_lstm_gru_seed3 (4 of 4 races; tournaments after 0, 2, 4 races)"
    calls.clear()
    experiment_report.second_policy_claims(spec, head_rows)
    assert calls == []  # each raced once
    with open(os.path.join(directory, "tournament_00002", "results.json")) as f:
        held = json.load(f)
    held[0]["racer"] = "lstm:another/run/checkpoints/racer_0.pt:0"
    with open(os.path.join(directory, "tournament_00002", "results.json"), "w") as f:
        json.dump(held, f)
    with pytest.raises(ValueError, match="tournament_00002_stochastic raced"):
        experiment_report.second_policy_claims(spec, head_rows)  # not the agents of the tournament it repeats


def test_the_training_races_outcomes_are_read_back_from_the_logged_win_rates(tmp_path):
    """race.py --train logs each racer's win rate over the last 20 races of its sitting; from those alone the
    outcome of every training race is recovered (windows full and not, a sitting cut and continued, a race raced
    again by the next sitting), and the summary counts them per interval."""
    spec = dataclasses.asdict(experiment.Spec(seeds=(3,), race_episodes=60, tournament_every=30, storage=str(tmp_path)))
    rng = np.random.default_rng(0)
    truth, stamp = {}, iter(range(1_800_000_000, 1_900_000_000))

    def sitting(interval, races, force=None):
        run = os.path.join(experiment.trial_dir(spec, "race", "lstm_gru", 3), interval,
                           f"multi_car_racing__race__3__{next(stamp)}")  # fmt: skip
        os.makedirs(run)
        won = {0: [], 1: []}
        with open(os.path.join(run, "progress.csv"), "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["racer_1_gru/charts/win_rate", "charts/race", "racer_0_lstm/charts/win_rate"])
            for k in races:
                outcome = [(1, 0), (0, 1), (0, 0), (1, 1)][rng.choice(4, p=[0.4, 0.4, 0.1, 0.1])]  # last: dead heat
                for i in (0, 1):
                    won[i].append(outcome[i])
                if k not in unlogged:
                    truth[k] = outcome
                    writer.writerow([np.mean(won[1][-20:]), k, np.mean(won[0][-20:])])

    unlogged = {24}  # the sitting killed after race 24's checkpoints, before its row
    sitting("races_00030", range(1, 25))
    sitting("races_00030", range(25, 31))  # the next sitting continues after race 24
    sitting("races_00060", range(31, 61))  # a window that fills after 20 races and slides
    assert experiment_report.training_race_wins(spec, 3) == truth
    blocks = [[truth[k] for k in range(a, a + 30) if k in truth] for a in (1, 31)]
    assert any((1, 1) in b for b in blocks)
    heats = [f", {b.count((1, 1))} dead heats" if (1, 1) in b else "" for b in blocks]
    expected = [f"{b.count((1, 0))}-{b.count((0, 1))} ({b.count((0, 0))}{h})" for b, h in zip(blocks, heats)]
    text = experiment_report.training_wins_text(spec, [3])
    assert f"3,3: {', '.join(expected)}." in text
    assert "The logs lack the outcome of 3,3: 1 of races 1..30." in text


def test_a_race_interval_split_by_a_kill_between_its_saves_continues_from_the_pair_saved_together(
    fake_race, monkeypatch
):
    plain, config, calls, cut, _ = fake_race
    interval = os.path.join(experiment.trial_dir(plain, "race", "lstm_gru", 3), "races_00002")
    cut["races_00002"] = (1, True)
    with pytest.raises(KeyboardInterrupt):
        experiment.race_trial(config)  # racer 0 at 2 races, racer 1 at 1: the only run cannot continue
    assert experiment.race_progress(plain, 3) == "race_lstm_gru_seed3 (0 of 4 races; tournaments after 0 races)"
    calls.clear()
    experiment.race_trial(config)
    assert kinds(calls)[:2] == [("train", 2, "ghost_lstm_seed3"), ("tournament", "tournament_00002.tmp")]
    assert len(os.listdir(interval)) == 1  # the split run was removed with its interval, raced again whole
    (run,) = os.listdir(interval)
    extra = os.path.join(interval, "multi_car_racing__race__3__1800000000", "checkpoints")  # a newer, split run
    os.makedirs(extra)
    for i in (0, 1):
        open(os.path.join(extra, f"racer_{i}.pt"), "w").close()
    table = {os.path.join(extra, "racer_0.pt"): 2, os.path.join(extra, "racer_1.pt"): 1}
    real = utils.checkpoint.read_checkpoint
    monkeypatch.setattr(utils.checkpoint, "read_checkpoint", lambda p: (None, {"counters": {"race_episodes": table[p]}})
                        if p in table else real(p))  # fmt: skip
    assert experiment.race_progress(plain, 3) == "race_lstm_gru_seed3 (4 of 4 races; tournaments after 0, 2, 4 races)"
    assert len(os.listdir(interval)) == 2  # --status only reads: the split newer run is still there
    paths, done = experiment.interval_racers(interval)
    assert done == 2 and os.path.join(interval, run) in paths[0]
    assert os.listdir(interval) == [run]  # the split newer run is gone: its logs would count races twice


def test_a_later_stage_needs_the_earlier_trials_finished(tmp_path, monkeypatch):
    spec = experiment.Spec(seeds=(3,), stages=("ghost",), storage=str(tmp_path))
    plain = dataclasses.asdict(spec)
    done = {"lstm": 8000, "gru": 7500}
    for variant in ("lstm", "gru"):
        path = os.path.join(experiment.trial_dir(plain, "single", variant, 3), "run", "checkpoints", "latest.pt")
        os.makedirs(os.path.dirname(path))
        open(path, "w").close()
    for variant in ("lstm", "gru"):  # what each latest.pt holds
        monkeypatch.setattr(importlib.import_module(f"dreamer_{variant}"), "load_checkpoint",
                            lambda path, v=variant: {"agents": [{"num_updates": done[v]}]})  # fmt: skip
    with pytest.raises(SystemExit, match=r"needs the single trials finished: single_gru_seed3 \(7500 of 8000"):
        experiment.check_spec(spec)
    done["gru"] = 8000
    experiment.check_spec(spec)  # both finished: the ghost stage may start
    race_spec = dataclasses.replace(spec, stages=("race",))
    with pytest.raises(SystemExit, match=r"ghost trials finished: ghost_lstm_seed3 \(not started\), ghost_gru_seed3 "
                                         r"\(not started\)$"):  # the agents it starts from, not the controls
        experiment.check_spec(race_spec)


def test_the_aggregation_measures_each_checkpoint_once(tmp_path, monkeypatch):
    import learning

    spec = experiment.Spec(storage=str(tmp_path / "storage"), fresh_tracks=3, eval_policy="stochastic")
    path = tmp_path / "latest.pt"
    path.write_bytes(b"one")
    calls = []

    def evaluate(p, first, tracks, policy):
        calls.append((p, first, tracks, policy))
        return {"eval_return": 100.0 + len(calls)}

    monkeypatch.setattr(learning, "policy_summary", evaluate)
    assert experiment_report.fresh_return(spec, str(path), 10_100) == 101.0
    assert experiment_report.fresh_return(spec, str(path), 10_100) == 101.0  # read back, not measured again
    assert calls == [(str(path), 10_100, 3, "stochastic")]
    mean_action = dataclasses.replace(spec, eval_policy="mean-action")
    assert experiment_report.fresh_return(mean_action, str(path), 10_100) == 102.0
    path.write_bytes(b"a resumed run's new checkpoint")  # the same path, another file: measured again
    assert experiment_report.fresh_return(spec, str(path), 10_100) == 103.0 and len(calls) == 3


def test_a_race_stage_whose_races_do_not_fill_its_tournaments_or_swap_its_starts_is_refused(tmp_path):
    with pytest.raises(SystemExit, match=r"--race-episodes \(140\) must be a multiple of --tournament-every \(50\)"):
        experiment.check_spec(experiment.Spec(race_episodes=140, storage=str(tmp_path)))
    for races in (99, 0):  # each tournament track is raced twice, the start positions swapped
        with pytest.raises(SystemExit, match=rf"--tournament-races \({races}\) must be a positive even number"):
            experiment.check_spec(experiment.Spec(tournament_races=races, storage=str(tmp_path)))
    assert not os.path.exists(tmp_path / "spec.json")  # refused before anything is written


def test_a_trial_whose_checkpoint_is_done_ends_though_its_csv_is_a_race_behind(tmp_path, monkeypatch):
    """A kill between a race's latest.pt and its progress.csv row leaves the csv behind the checkpoint; the
    retried trial has nothing left to train and must end (its counter is latest.pt's), not report forever."""
    pytest.importorskip("ray")
    from ray import tune

    spec = dataclasses.asdict(experiment.Spec(storage=str(tmp_path), single_updates=1000, report_every=500))
    os.makedirs(os.path.join(experiment.trial_dir(spec, "single", "gru", 12), "run", "checkpoints"))
    open(os.path.join(experiment.trial_dir(spec, "single", "gru", 12), "run", "checkpoints", "latest.pt"), "w").close()
    reports = []

    def report(metrics):
        reports.append(metrics)
        if len(reports) > 3:
            raise RuntimeError("the trial did not end")

    monkeypatch.setattr(tune, "report", report)
    monkeypatch.setattr(dreamer_lstm_or_gru("gru"), "load_checkpoint",
                        lambda path: {"agents": [{"num_updates": 1000}]})  # the checkpoint: done
    monkeypatch.setattr(experiment, "latest_metrics", lambda run: {"updates": 900})  # its csv: a race behind
    monkeypatch.setattr(dreamer_lstm_or_gru("gru"), "main", lambda *a: pytest.fail("nothing is left to train"))
    experiment.dreamer_trial({"trial": {"spec": spec, "stage": "single", "variant": "gru", "seed": 12}})
    assert reports == [{"updates": 900, "numerical_stop": 0}]


def test_a_cpu_hour_budget_ends_a_single_trial_whatever_its_updates(tmp_path, monkeypatch):
    """--single-cpu-hours: the trial's run gets --cpu-hours-limit and the trial ends once its checkpoint has used the
    budget, though it made fewer updates than --single-updates (the final protocol: the policy when the budget ran
    out); without the budget the same checkpoint would be trained further."""
    pytest.importorskip("ray")
    from ray import tune

    spec = dataclasses.asdict(experiment.Spec(storage=str(tmp_path), single_cpu_hours=3.1, report_every=500))
    script, args, _, target = experiment.trial_args(spec, "single", "gru", 12)
    assert args.cpu_hours_limit == 3.1 and target > 10**9 and args.exp_name == "gru_single"
    checkpoints = os.path.join(experiment.trial_dir(spec, "single", "gru", 12), "run", "checkpoints")
    os.makedirs(checkpoints)
    open(os.path.join(checkpoints, "latest.pt"), "w").close()
    spent = {"agents": [{"num_updates": 4321}], "extra": {"cpu_seconds": 3.1 * 3600}}
    monkeypatch.setattr(tune, "report", lambda metrics: None)
    monkeypatch.setattr(experiment, "latest_metrics", lambda run: {})
    monkeypatch.setattr(script, "load_checkpoint", lambda path: spent)
    monkeypatch.setattr(script, "main", lambda *a: pytest.fail("the budget is spent: nothing is left to train"))
    experiment.dreamer_trial({"trial": {"spec": spec, "stage": "single", "variant": "gru", "seed": 12}})

    class Trains(Exception):
        """The trial resumed its run: budget left."""

    def train(*args):
        raise Trains

    assert experiment.unfinished(spec, "single", ["gru"], [12]) == []  # the next stage may start from it
    progress = experiment.trial_progress(spec, "single", "gru", 12)
    assert experiment.progress_text("t", progress) == "t (4321 updates, 3.10 of 3.1 CPU-hours, finished)"
    monkeypatch.setattr(script, "main", train)
    spent["extra"]["cpu_seconds"] = 3.0 * 3600
    with pytest.raises(Trains):
        experiment.dreamer_trial({"trial": {"spec": spec, "stage": "single", "variant": "gru", "seed": 12}})
    assert experiment.unfinished(spec, "single", ["gru"], [12]) == ["single_gru_seed12 (4321 updates, 3.00 of 3.1 "
                                                                    "CPU-hours)"]  # fmt: skip


def test_a_trial_whose_run_the_non_finite_guard_stopped_ends_with_it_and_is_not_resumed(tmp_path, monkeypatch):
    """The scripts' guard stops a run (NumericalFault, latest.pt saved): the trial ends without an error (Tune would
    resume it), counts as finished for the next stage, and a restored trial does not train it again."""
    pytest.importorskip("ray")
    from ray import tune

    from utils.run import NumericalFault

    spec = dataclasses.asdict(experiment.Spec(storage=str(tmp_path), single_cpu_hours=3.1, report_every=500))
    script = experiment.trial_args(spec, "single", "lstm", 12)[0]
    checkpoints = os.path.join(experiment.trial_dir(spec, "single", "lstm", 12), "run", "checkpoints")
    saved = {"args": {"max_nonfinite_updates": 20}, "agents": [{"num_updates": 700, "nonfinite_in_a_row": 3}],
             "extra": {"cpu_seconds": 0.5 * 3600}}  # fmt: skip
    reports, trained = [], []

    def main(*args):  # the guard's stop: 20 faulty updates in a row, latest.pt saved, then the error
        trained.append(args)
        os.makedirs(checkpoints, exist_ok=True)
        open(os.path.join(checkpoints, "latest.pt"), "w").close()
        saved["agents"][0].update(num_updates=740, nonfinite_in_a_row=20)
        raise NumericalFault("car_0: 20 updates in a row had a non-finite loss or gradient")

    monkeypatch.setattr(tune, "report", reports.append)
    monkeypatch.setattr(experiment, "latest_metrics", lambda run: {"run": run})
    monkeypatch.setattr(script, "load_checkpoint", lambda path: saved)
    monkeypatch.setattr(script, "main", main)
    trial = {"trial": {"spec": spec, "stage": "single", "variant": "lstm", "seed": 12}}
    experiment.dreamer_trial(trial)  # returns: the trial ends with the stopped run
    assert len(trained) == 1 and reports == [{"run": os.path.dirname(checkpoints), "numerical_stop": 1}]
    assert experiment.unfinished(spec, "single", ["lstm"], [12]) == []  # finished for the next stage
    progress = experiment.trial_progress(spec, "single", "lstm", 12)
    text = experiment.progress_text("t", progress)
    assert text == "t (740 updates, 0.50 of 3.1 CPU-hours, stopped by the non-finite guard)"
    monkeypatch.setattr(script, "main", lambda *a: pytest.fail("the guard's stop is kept: no more training"))
    experiment.dreamer_trial(trial)  # restored (Tune's retry): nothing trained
    assert len(reports) == 2
    saved["agents"][0]["nonfinite_in_a_row"] = 0  # a NumericalFault that latest.pt does not show: not swallowed
    monkeypatch.setattr(script, "main", lambda *a: (_ for _ in ()).throw(NumericalFault("not saved")))
    with pytest.raises(NumericalFault, match="not saved"):
        experiment.dreamer_trial(trial)


GHOST_TABLE = ("variant,seed,updates_at_start,updates,return_before,return_after_ghost,return_after_control\n"
               "lstm,11,7600,2000,315.1,817.9,812.5\nlstm,12,6100,2000,822.0,789.7,807.7\n"
               "gru,11,6600,2000,576.1,635.0,416.3\ngru,12,7600,2000,539.5,600.2,434.2\n")  # fmt: skip


def test_without_controls_the_ghost_stage_trains_only_the_agents_the_race_stage_starts_from(tmp_path, capsys):
    results = tmp_path / "results"
    spec = experiment.Spec(seeds=(11, 12), stages=("single",), storage=str(tmp_path), results=str(results),
                           eval_policy="stochastic")  # fmt: skip
    assert [(c["stage"], c["variant"], c["seed"]) for c in experiment.stage_configs(spec, "ghost")] == [
        ("ghost", "lstm", 11), ("ghost", "gru", 11), ("control", "lstm", 11), ("control", "gru", 11),
        ("ghost", "lstm", 12), ("ghost", "gru", 12), ("control", "lstm", 12), ("control", "gru", 12)]  # fmt: skip
    without = dataclasses.replace(spec, controls=False)
    assert [(c["stage"], c["variant"], c["seed"]) for c in experiment.stage_configs(without, "ghost")] == [
        ("ghost", "lstm", 11), ("ghost", "gru", 11), ("ghost", "lstm", 12), ("ghost", "gru", 12)]  # fmt: skip
    experiment.check_spec(spec)
    with open(tmp_path / "spec.json") as f:
        saved = json.load(f)
    del saved["controls"]  # an experiment begun before the field existed: it runs its controls
    with open(tmp_path / "spec.json", "w") as f:
        json.dump(saved, f)
    assert experiment.saved_spec(str(tmp_path), write=False)["controls"] is True
    os.makedirs(tmp_path / "trials" / "single_lstm_seed11")  # the single stage has begun: the controls may change
    without = dataclasses.replace(without, eval_policy="mean-action")  # and the policy, each until its stage
    # the table it would keep is refused before Ray starts: none, the header alone (as an aggregation with controls
    # leaves it when their trials are gone), a seed missing
    header = GHOST_TABLE.split("\n")[0] + "\n"
    refused = [(None, "does not exist"),
               (header, "has no row for lstm seed 11, lstm seed 12, gru seed 11, gru seed 12"),
               (GHOST_TABLE.replace("gru,12,", "gru,13,"), "has no row for gru seed 12")]  # fmt: skip
    for table, problem in refused:
        if table is not None:
            results.mkdir(exist_ok=True)
            (results / "ghost_vs_control.csv").write_text(table)
        with pytest.raises(SystemExit, match=f"without controls .*ghost_vs_control.csv {problem}: run the controls"):
            experiment.check_spec(without)
    (results / "ghost_vs_control.csv").write_text(GHOST_TABLE)
    experiment.check_spec(without)
    with open(tmp_path / "spec.json") as f:
        assert {k: v for k, v in json.load(f).items() if k in ("controls", "eval_policy")} == {
            "controls": False, "eval_policy": "mean-action"}  # fmt: skip
    experiment.main(dataclasses.replace(spec, status=True))  # the experiment as saved: without controls
    assert [line for line in capsys.readouterr().out.splitlines() if "seed11" in line] == [
        "  single_lstm_seed11 (not started)", "  single_gru_seed11 (not started)", "  ghost_lstm_seed11 (not started)",
        "  ghost_gru_seed11 (not started)", "  race_lstm_gru_seed11 (not started)"]  # fmt: skip
    os.makedirs(tmp_path / "trials" / "ghost_gru_seed12")  # the ghost stage has begun: they may not
    with pytest.raises(SystemExit, match="holds an experiment with other controls;"):
        experiment.check_spec(dataclasses.replace(without, controls=True))


def test_an_experiment_without_controls_keeps_the_measured_table_and_compares_its_ghosts_made_again(
    tmp_path, monkeypatch
):
    """The ghost_vs_control.csv in --results is kept as it is (the controls that measured it are gone); the summary
    compares each ghost agent made again with its row, and a missing table is refused before anything is measured."""
    spec = experiment.Spec(seeds=(11, 12), controls=False, race_episodes=50, storage=str(tmp_path / "s"),
                           results=str(tmp_path / "results"))  # fmt: skip
    progress = {("single", v, s): 8000 for v in ("lstm", "gru") for s in (11, 12)}
    progress |= {("ghost", "lstm", 11): 9000, ("ghost", "gru", 11): 9000, ("ghost", "lstm", 12): 8500}
    monkeypatch.setattr(experiment_report, "trial_progress", lambda spec, kind, variant, seed: experiment.Progress(
        f"/runs/{kind}_{variant}_{seed}" if (kind, variant, seed) in progress else None,
        progress.get((kind, variant, seed), 0), 8000 if kind == "single" else 9000))  # fmt: skip
    monkeypatch.setattr(experiment_report, "updates_of", lambda path, script: 7000)
    measured = []

    def fresh_return(spec, path, first):
        measured.append(path)
        return {"/runs/single_lstm_11/checkpoints/best.pt": 315.1, "/runs/ghost_lstm_11/checkpoints/latest.pt": 817.9,
                "/runs/single_gru_11/checkpoints/best.pt": 576.1,
                "/runs/ghost_gru_11/checkpoints/latest.pt": 634.75}.get(path, 500.0)  # fmt: skip

    monkeypatch.setattr(experiment_report, "fresh_return", fresh_return)
    with pytest.raises(SystemExit, match=r"without controls .*ghost_vs_control.csv does not exist"):
        experiment_report.aggregate(spec)
    assert measured == [] and not os.path.exists(spec.results)  # refused before measuring or writing anything
    os.makedirs(spec.results)
    table = GHOST_TABLE
    with open(os.path.join(spec.results, "ghost_vs_control.csv"), "w") as f:
        f.write(table)
    summary = experiment_report.aggregate(spec)
    with open(os.path.join(spec.results, "ghost_vs_control.csv")) as f:
        assert f.read() == table  # kept as measured
    ghost_row = next(line for line in summary.splitlines() if line.startswith("| racing a ghost"))
    assert "4 (variant, seed) pairs" in ghost_row  # the kept table's four rows
    # (5.4 - 18.0 + 218.7 + 166.0) / 4 = 93.0, the kept rows; |d| sum to 408.1, the observed sum is 372.1: an
    # assignment reaches it when its negated part sums to 18.0 or less ({}, {5.4}, {18.0}): p = 3/16. sd 117.1,
    # t_3 = 3.1824: 93.0 +- 186.3
    estimate, test, judged = ghost_row.split(" | ")[2:5]
    assert estimate == "93.0" and test.startswith("sign-flip p=0.188, t 95% [-93.") and test.endswith("n=4")
    assert judged.startswith("weak (positive, but the exact test's p = 0.188")
    assert ("Its ghost agents made again, return on the fresh tracks before -> after the ghost stage (the table's in "
            "brackets): lstm seed 11 315.10 (315.10) -> 817.90 (817.90); gru seed 11 576.10 (576.10) -> 634.75 "
            "(635.00). Largest difference: 0.25.") in summary
    assert "ghost_lstm_seed12 (8500 of 9000 updates); ghost_gru_seed12 (not started)" in summary
    assert not any("control" in path for path in measured)


def test_overrides_take_the_type_of_their_field_optional_and_literal_ones_too():
    import dreamer_lstm

    values = experiment.parse_overrides(dreamer_lstm, [
        "entropy_target=0.0", "action_penalty=none", "norm=mixed", "image_size=64", "return_norm=false",
        "entropy_coef=0.3", "batch_size=7",
    ])  # fmt: skip
    assert values == {"entropy_target": 0.0, "action_penalty": None, "norm": "mixed", "image_size": 64,
                      "return_norm": False, "entropy_coef": 0.3, "batch_size": 7}  # fmt: skip
    assert type(values["image_size"]) is int and type(values["batch_size"]) is int
    for bad, message in (("norm=group", "must be one of batch, layer, mixed"), ("return_norm=maybe", "true or false"),
                         ("batch_size=x", "invalid literal"), ("no_such=1", "is not name=value"),
                         ("norm=none", "must be one of"), ("eval_policy=None", "must be one of")):  # fmt: skip
        with pytest.raises(ValueError, match=message):
            experiment.parse_overrides(dreamer_lstm, [bad])
