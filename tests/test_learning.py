"""benchmarks/learning.py and what it reads beside the final policies (references.py): curves from event files
over resumed sittings (runs.py), diagnostics, the references, a saved policy's summary, and the command line."""

import csv
import importlib
import json
import os

import numpy as np
import pytest
from torch.utils.tensorboard import SummaryWriter

import learning
import references
import runs
from conftest import as_process, write_sitting


@pytest.fixture
def runs_dir(tmp_path):
    return str(tmp_path / "runs")


def test_eval_curve_adds_up_sittings_not_the_gap_between_them(runs_dir):
    run_dir = os.path.join(runs_dir, "multi_car_racing__learning_gru__1__1700000000")
    write_sitting(run_dir, [(500, -80.0, 0.02, 0), (1000, 50.0, 0.2, 300)], wall_start=1_000_000.0, pid=101)
    # the second sitting (another process) starts a day later: its hours continue from the first sitting's 1000 s
    write_sitting(run_dir, [(1000, 50.0, 0.2, 300), (2000, 310.0, 0.45, 800)], wall_start=1_086_400.0, pid=202)
    rows = runs.eval_curve(run_dir)
    assert [r["env_steps"] for r in rows] == [500, 1000, 2000]  # the repeated point once
    assert [r["updates"] for r in rows] == [0, 300, 800]
    assert rows[-1]["wall_hours"] == pytest.approx(2000 / 3600, abs=1e-4)
    assert rows[-1]["eval_progress"] == pytest.approx(0.45, abs=1e-6)
    assert runs.training_hours(run_dir) == pytest.approx(2000 / 3600, abs=1e-4)


def test_event_files_of_one_process_are_one_sitting_and_the_time_between_them_counts(runs_dir):
    """An experiment trial calls a script's main every few hundred updates in one process, each call with a new
    event file: the training between the last scalar of one and the first of the next is training time."""
    run_dir = os.path.join(runs_dir, "multi_car_racing__learning_lstm__1__1700000000")
    write_sitting(run_dir, [(500, -80.0, 0.02, 0), (1000, 50.0, 0.2, 300)], wall_start=1_000_000.0, pid=303)
    write_sitting(run_dir, [(1500, 90.0, 0.3, 500), (2000, 310.0, 0.45, 800)], wall_start=1_002_500.0, pid=303)
    # a later sitting, another process, two days on
    write_sitting(run_dir, [(2500, 400.0, 0.5, 1000)], wall_start=1_172_800.0, pid=404)
    write_sitting(run_dir, [(3000, 450.0, 0.55, 1200)], wall_start=1_173_400.0, pid=404)
    rows = runs.eval_curve(run_dir)
    # 0, 1000 s; 2500, 3500 s (the 1500 s between the files count); then 3500 + 0 and 3500 + 600 s
    assert [r["wall_hours"] for r in rows] == pytest.approx([0, 1000 / 3600, 2500 / 3600, 3500 / 3600,
                                                            3500 / 3600, 4100 / 3600], abs=1e-4)  # fmt: skip
    assert runs.training_hours(run_dir) == pytest.approx(4100 / 3600, abs=1e-4)
    # a host name may hold dots and digits: the process is the host and the pid before the file's counter
    name = "events.out.tfevents.1796255072.node.12.example.24779.3"
    assert runs.EVENT_FILE_PROCESS.fullmatch(name)["process"] == "node.12.example.24779"


def test_diagnostics_average_each_bucket_of_updates(tmp_path):
    tags = dict(learning.DIAGNOSTICS)
    columns = ["charts/episode", "car_0/perf/updates", *tags.values()]
    logged = [  # (episode, updates, training return, actor sigma, eval return)
        (1, "", -80.0, "", ""), (2, "", -60.0, "", ""),  # prefill races: bucket 0
        (3, 100, 10.0, 0.9, ""), (4, 400, 30.0, 0.7, 50.0),  # bucket 0 (updates 0-499)
        (5, 500, 100.0, 0.6, ""), (6, 900, 300.0, 0.5, 250.0), (7, 999, 200.0, "", ""),  # bucket 1
        (8, 1500, 400.0, 0.4, ""),  # bucket 3 (no row in 1000-1499: no bucket 2)
    ]
    with open(tmp_path / "progress.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        for episode, updates, ret, sigma, evaluation in logged:
            writer.writerow({"charts/episode": episode, "car_0/perf/updates": updates, tags["training return"]: ret,
                             tags["actor sigma"]: sigma, tags["eval return"]: evaluation})  # fmt: skip
    rows = learning.diagnostics(str(tmp_path), bucket=500)
    assert [(r["updates"], r["races"]) for r in rows] == [("0-499", 4), ("500-999", 3), ("1500-1999", 1)]
    assert [r["training return"] for r in rows] == pytest.approx([(-80 - 60 + 10 + 30) / 4, 200.0, 400.0])
    assert [r["actor sigma"] for r in rows] == pytest.approx([0.8, 0.55, 0.4])
    assert rows[0]["eval return"] == 50.0 and rows[1]["eval return"] == 250.0 and np.isnan(rows[2]["eval return"])
    table = learning.diagnostics_table(rows).splitlines()
    assert table[0].startswith("| updates | races | training return |") and len(table) == 2 + 3
    assert table[2].startswith("| 0-499 | 4 | -25.00 |") and table[4].endswith("|  |  |  |")


def test_diagnose_reads_a_final_protocol_trial_when_no_learning_run_has_the_seed(tmp_path):
    tags = dict(learning.DIAGNOSTICS)
    run = tmp_path / "trials" / "single_gru_seed21" / "multi_car_racing__gru_single__21__1700000000"
    run.mkdir(parents=True)
    with open(run / "progress.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["charts/episode", "car_0/perf/updates", tags["actor sigma"]])
        writer.writeheader()
        writer.writerow({"charts/episode": 1, "car_0/perf/updates": 100, tags["actor sigma"]: 0.3})
    learning.run_mode(learning.Args(diagnose=True, variant="gru", seed=21, runs_dir=str(tmp_path / "trials"),
                                    results_dir=str(tmp_path / "mine")))  # fmt: skip
    written = (tmp_path / "mine" / "gru_single_seed21_diagnostics.md").read_text()
    assert written.startswith(run.name) and "| 0-499 | 0 |  |  | 0.30 |" in written  # no race logged a return


def test_calibrate_writes_its_row_into_the_results_dir(tmp_path, monkeypatch):
    """--calibrate's row goes to calibration.csv in --results-dir (a user's), not into the reported one."""
    import calibration

    row = {column: 1.0 for column in calibration.CALIBRATION_COLUMNS} | {"checkpoint": "x.pt", "tracks": "10100..10104"}
    monkeypatch.setattr(learning, "calibrate_checkpoint", lambda *args: dict(row))
    reported = os.path.join(learning.RESULTS, "calibration.csv")
    before = os.path.getmtime(reported) if os.path.exists(reported) else None
    learning.run_mode(learning.Args(calibrate="x.pt", results_dir=str(tmp_path / "mine")))
    with open(tmp_path / "mine" / "calibration.csv", newline="") as f:
        assert [r["checkpoint"] for r in csv.DictReader(f)] == ["x.pt"]
    assert (os.path.getmtime(reported) if os.path.exists(reported) else None) == before


def test_diagnose_refuses_to_guess_among_several_trials_of_the_seed(tmp_path):
    for tag in ("a", "b"):  # a sweep's flag sets: one trial each, the same variant and seed
        (tmp_path / tag / "trials" / "single_lstm_seed11" / "multi_car_racing__lstm_single__11__1700000000").mkdir(
            parents=True)  # fmt: skip
    with pytest.raises(ValueError, match=r"^2 trials of lstm_single seed 11 under .*: give --runs-dir one of them"):
        learning.run_mode(learning.Args(diagnose=True, variant="lstm", seed=11, runs_dir=str(tmp_path)))


def test_the_references_are_measured_once_for_their_tracks_and_refuse_others(tmp_path):
    base = references.baselines(10_000, 1, results_dir=str(tmp_path))
    assert base["pursuit@70"]["eval_progress"] > 0.95 and base["pursuit@70"]["eval_return"] > 800
    assert base["random"]["eval_progress"] < 0.2 and base["random"]["eval_return"] < 0
    with open(tmp_path / "references.json") as f:  # what was measured is kept, with its tracks
        assert json.load(f) == {**base, "tracks": "10000..10000"}
    with open(tmp_path / "references.json", "w") as f:  # read back, not recomputed
        json.dump({"random": {"eval_return": -1.0, "eval_progress": 0.01},
                   "pursuit@70": {"eval_return": 2.0, "eval_progress": 1.0}, "tracks": "10000..10000"}, f)  # fmt: skip
    assert references.baselines(10_000, 1, results_dir=str(tmp_path))["random"]["eval_return"] == -1.0
    with pytest.raises(ValueError, match=r"references.json holds the references on tracks 10000..10000, not "
                                         r"10000..10009: give another results_dir"):  # fmt: skip
        references.baselines(10_000, 10, results_dir=str(tmp_path))


@pytest.mark.parametrize("variant", ["lstm", "gru"])
def test_policy_summary_reproduces_the_runs_own_evaluation(tmp_path, variant):
    """policy_summary on the run's held-out tracks gives exactly the return and progress the run logged for
    the agent it saved as best.pt (deterministic actions, the run's env settings)."""
    script = importlib.import_module(f"dreamer_{variant}")
    tiny = dict(
        cnn_depth=4, deter_size=16, hidden_size=16, mlp_size=16, latent_size=4, image_size=64, batch_size=2, seq_len=8,
        imagination_horizon=3, max_steps=40, train_steps_per_episode=1, prefill_episodes=1, replay_capacity=500,
        total_episodes=2, eval_every=2, eval_episodes=2, eval_seed=10_000, video_every=0, action_repeat=2,
        eval_policy="deterministic",
    )  # fmt: skip
    run_dir = script.main(script.Args(stage="single", runs_dir=str(tmp_path), **tiny))
    (logged,) = runs.eval_curve(run_dir)
    result = learning.policy_summary(os.path.join(run_dir, "checkpoints", "best.pt"), 10_000, 2, "deterministic")
    assert result["variant"] == variant and result["tracks"] == "10000..10001"
    assert result["eval_return"] == pytest.approx(logged["eval_return"], abs=0.01)  # the CSV keeps 2 decimals
    assert result["eval_progress"] == pytest.approx(logged["eval_progress"], abs=1e-4)
    assert len(result["returns"]) == len(result["progress"]) == 2
    sampled = learning.policy_summary(os.path.join(run_dir, "checkpoints", "best.pt"), 10_000, 2)  # default
    assert sampled["policy"] == "stochastic" and sampled["returns"] != result["returns"]  # sampled actions differ
    again = learning.policy_summary(os.path.join(run_dir, "checkpoints", "best.pt"), 10_000, 2)
    assert again["returns"] == sampled["returns"]  # seeded: the same command, the same numbers


def test_policy_summary_refuses_bad_input_naming_it(tmp_path):
    with pytest.raises(ValueError, match=r"^tracks must be >= 1, got 0$"):
        learning.policy_summary(str(tmp_path / "best.pt"), 10_000, 0)
    with pytest.raises(ValueError, match=r"best\.pt: no such checkpoint file$"):
        learning.policy_summary(str(tmp_path / "best.pt"))
    (tmp_path / "notes.pt").write_text("not a checkpoint")
    with pytest.raises(ValueError, match=r"notes\.pt: not a readable checkpoint"):
        learning.policy_summary(str(tmp_path / "notes.pt"))


def test_a_runs_hours_and_evaluations_count_every_sitting_to_its_last_scalar(tmp_path):
    """A run's hours (training_hours, a protocol row's wall_hours) are the whole run's, to the last logged scalar of
    each sitting, not to its last evaluation, which can lie hundreds of updates before the end; eval_summary gives
    its best evaluation and the mean of its last three."""
    run = tmp_path / "multi_car_racing__learning_lstm__12__1700000000"
    (run / "checkpoints").mkdir(parents=True)
    write_sitting(str(run), [(500, -80.0, 0.02, 100), (1000, 50.0, 0.2, 300)], wall_start=1_000_000.0, pid=101)
    before = set(os.listdir(run))
    writer = SummaryWriter(str(run))  # a later sitting: training only, no evaluation
    writer.add_scalar("car_0/perf/updates", 350, 1100, walltime=2_000_000.0)
    writer.add_scalar("car_0/perf/updates", 400, 1234, walltime=2_000_000.0 + 1800.0)
    writer.close()
    as_process(str(run), before, pid=202)
    assert runs.training_hours(str(run)) == pytest.approx((1000 + 1800) / 3600, abs=1e-4)  # not the gap
    assert runs.eval_summary(runs.eval_curve(str(run))) == (50.0, pytest.approx(-15.0))
    assert np.isnan(runs.eval_summary([])).all()  # a run without evaluations


@pytest.mark.parametrize("argv, message", [
    (["--diagnose", "--protocol-report"], "--protocol-report and --diagnose are separate modes: give one"),
    (["--diagnose", "--protocol-ship", "--calibrate", "x.pt"],
     "--protocol-ship and --diagnose and --calibrate are separate modes"),
    ([], "give a mode: --protocol-row, --protocol-report, --protocol-ship, --diagnose, --calibrate (the runs "
         "themselves are benchmarks/experiment.py's single stage)"),
    (["--variant", "gru", "--seed", "11"], "give a mode: --protocol-row,"),  # the training mode is gone
    (["--horizon", "5"], "--horizon is the imagination horizon of --calibrate; give --calibrate CHECKPOINT"),
    (["--calibrate", "x.pt", "--tracks", "0"], "--tracks and --horizon must be >= 1, got 0 and None"),
])  # fmt: skip
def test_the_command_line_refuses_bad_input_in_one_line_before_any_work(argv, message, tmp_path):
    with pytest.raises(SystemExit) as exit_info:
        learning.cli([*argv, "--runs-dir", str(tmp_path / "runs")])
    text = str(exit_info.value)
    assert text.startswith("learning.py: error: ") and message in text and "\n" not in text
    assert not os.path.exists(tmp_path / "runs")  # nothing was trained or written


def test_a_mode_without_its_run_or_checkpoint_names_it_in_one_line(tmp_path):
    for argv, message in [
        (["--diagnose", "--seed", "3"], f"no run of learning_lstm or lstm_single seed 3 in {tmp_path}"),
        (["--diagnose", "--variant", "gru"], f"no run of learning_gru or gru_single seed 1 in {tmp_path}"),
        (["--calibrate", str(tmp_path / "none.pt")], "none.pt: no such checkpoint file"),
    ]:
        with pytest.raises(SystemExit, match=r"^learning\.py: error: ") as exit_info:
            learning.cli([*argv, "--runs-dir", str(tmp_path)])
        assert message in str(exit_info.value) and "\n" not in str(exit_info.value)


@pytest.mark.parametrize("argv", [
    ["--evaluate", "x.pt"], ["--export", "x.pt", "out.pt"],  # user operations: python evaluate.py now
    ["--variant", "transformer"], ["--final"], ["--return-norm"],  # the 8,000-update protocol's modes, ablations
    ["--report"], ["--resume"], ["--hours", "3"], ["--updates", "10"],  # its training mode (experiment.py's now)
])  # fmt: skip
def test_the_parser_refuses_removed_modes_and_bad_values(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        learning.cli(argv)
    assert exit_info.value.code == 2 and argv[0] in capsys.readouterr().err  # tyro's message names the flag
