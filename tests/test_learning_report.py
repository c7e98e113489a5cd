"""benchmarks/learning.py and its reports (learning_report.py): curves from event files over resumed sittings, the
saved CSVs that stand in for runs not on this machine, the bar, the final protocol's table and its rliable summary,
and the command line."""

import csv
import dataclasses
import importlib
import json
import os
import sys

import numpy as np
import pytest
import tyro
from torch.utils.tensorboard import SummaryWriter

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks"))
import learning  # noqa: E402
import learning_report  # noqa: E402
import utils.checkpoint as ckpt  # noqa: E402
import utils.run as run_tools  # noqa: E402

BASELINES = {
    "random": {"eval_return": -76.6, "eval_progress": 0.03},
    "pursuit@70": {"eval_return": 909.0, "eval_progress": 1.0},
}


def write_sitting(run_dir, points, wall_start, pid=None):
    """One event file: eval points (env_steps, return, progress, updates) at 1000 s apart from wall_start, named
    as SB3's logger names a file of process `pid` (this test's own when None)."""
    before = set(os.listdir(run_dir)) if os.path.isdir(run_dir) else set()
    writer = SummaryWriter(run_dir)
    for i, (steps, ret, progress, updates) in enumerate(points):
        wall = wall_start + 1000.0 * i
        writer.add_scalar("car_0/perf/updates", updates, steps, walltime=wall)
        writer.add_scalar("car_0/eval/episodic_return", ret, steps, walltime=wall)
        writer.add_scalar("car_0/eval/progress", progress, steps, walltime=wall)
    writer.close()
    if pid is not None:
        as_process(run_dir, before, pid)


def as_process(run_dir, before, pid):
    """Rename the one event file written to run_dir since `before` (its file names) as process `pid`'s:
    events.out.tfevents.<time>.<host>.<pid>.<n>."""
    (name,) = set(os.listdir(run_dir)) - before
    head, rest = name.split(f".{os.getpid()}.", 1)
    os.rename(os.path.join(run_dir, name), os.path.join(run_dir, f"{head}.{pid}.{rest}"))


@pytest.fixture
def dirs(tmp_path):
    runs, results = tmp_path / "runs", tmp_path / "results"
    results.mkdir()
    with open(results / "baselines.json", "w") as f:
        json.dump(BASELINES, f)
    return str(runs), str(results)


def test_eval_curve_adds_up_sittings_not_the_gap_between_them(dirs):
    runs, _ = dirs
    run_dir = os.path.join(runs, "multi_car_racing__learning_gru__1__1700000000")
    write_sitting(run_dir, [(500, -80.0, 0.02, 0), (1000, 50.0, 0.2, 300)], wall_start=1_000_000.0, pid=101)
    # the second sitting (another process) starts a day later: its hours continue from the first sitting's 1000 s
    write_sitting(run_dir, [(1000, 50.0, 0.2, 300), (2000, 310.0, 0.45, 800)], wall_start=1_086_400.0, pid=202)
    rows = learning.eval_curve(run_dir)
    assert [r["env_steps"] for r in rows] == [500, 1000, 2000]  # the repeated point once
    assert [r["updates"] for r in rows] == [0, 300, 800]
    assert rows[-1]["wall_hours"] == pytest.approx(2000 / 3600, abs=1e-4)
    assert rows[-1]["eval_progress"] == pytest.approx(0.45, abs=1e-6)
    assert learning.training_hours(run_dir) == pytest.approx(2000 / 3600, abs=1e-4)


def test_event_files_of_one_process_are_one_sitting_and_the_time_between_them_counts(dirs):
    """An experiment trial calls a script's main every few hundred updates in one process, each call with a new
    event file: the training between the last scalar of one and the first of the next is training time."""
    runs, _ = dirs
    run_dir = os.path.join(runs, "multi_car_racing__learning_lstm__1__1700000000")
    write_sitting(run_dir, [(500, -80.0, 0.02, 0), (1000, 50.0, 0.2, 300)], wall_start=1_000_000.0, pid=303)
    write_sitting(run_dir, [(1500, 90.0, 0.3, 500), (2000, 310.0, 0.45, 800)], wall_start=1_002_500.0, pid=303)
    # a later sitting, another process, two days on
    write_sitting(run_dir, [(2500, 400.0, 0.5, 1000)], wall_start=1_172_800.0, pid=404)
    write_sitting(run_dir, [(3000, 450.0, 0.55, 1200)], wall_start=1_173_400.0, pid=404)
    rows = learning.eval_curve(run_dir)
    # 0, 1000 s; 2500, 3500 s (the 1500 s between the files count); then 3500 + 0 and 3500 + 600 s
    assert [r["wall_hours"] for r in rows] == pytest.approx([0, 1000 / 3600, 2500 / 3600, 3500 / 3600,
                                                            3500 / 3600, 4100 / 3600], abs=1e-4)  # fmt: skip
    assert learning.training_hours(run_dir) == pytest.approx(4100 / 3600, abs=1e-4)
    # a host name may hold dots and digits: the process is the host and the pid before the file's counter
    name = "events.out.tfevents.1796255072.node.12.example.24779.3"
    assert learning.EVENT_FILE_PROCESS.fullmatch(name)["process"] == "node.12.example.24779"


def test_first_at_bar_needs_return_and_progress_at_the_same_evaluation():
    bar, progress = learning.BAR_RETURN, learning.BAR_PROGRESS
    rows = [
        {"env_steps": 1, "eval_return": bar + 50, "eval_progress": progress - 0.1},  # return only
        {"env_steps": 2, "eval_return": bar - 50, "eval_progress": progress + 0.1},  # progress only
        {"env_steps": 3, "eval_return": bar, "eval_progress": progress},  # both, at the edges
    ]
    assert learning_report.first_at_bar(rows)["env_steps"] == 3
    assert learning_report.first_at_bar(rows[:2]) is None


def test_final_table_rows_replace_their_run_and_the_summary_matches_hand_computed_numbers(tmp_path):
    path = str(tmp_path / "learning_final.csv")
    base = {"updates": 8000, "env_steps": 40000, "hours": 2.5, "best_return": 0.0, "best_progress": 0.0,
            "mean_action_return": 0.0, "mean_action_progress": 0.0, "best_eval_return": 500.0}  # fmt: skip
    for variant, seed, ret, progress, steer in [
        ("lstm", 11, 100.0, 0.2, 0.1), ("lstm", 12, 200.0, 0.4, 0.2), ("lstm", 13, 600.0, 0.9, 0.3),
        ("gru", 11, 1.0, 0.1, 0.5), ("gru", 12, 2.0, 0.1, 0.5), ("gru", 13, 3.0, 0.1, 0.5), ("gru", 14, 10.0, 0.1, 0.5),
        ("lstm", 13, 300.0, 0.6, 0.3),  # the same run measured again: replaces its row
    ]:  # fmt: skip
        learning.write_final_row(
            {"exp_name": f"learning_{variant}", "variant": variant, "seed": seed, "final_return": ret,
             "final_progress": progress, "final_mean_abs_steer": steer, "mean_action_abs_steer": steer / 2,
             "last3_eval_return": 500.0 - 0.6 * ret, **base}, path,
        )  # fmt: skip
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == list(learning.FINAL_COLUMNS)
    assert [(r["variant"], r["seed"]) for r in rows] == [("gru", "11"), ("gru", "12"), ("gru", "13"), ("gru", "14"),
                                                         ("lstm", "11"), ("lstm", "12"), ("lstm", "13")]  # fmt: skip
    ablation = {**rows[0], "exp_name": "learning_gru_alpha0.1", "seed": 11, "final_return": 999.0}
    learning.write_final_row(ablation, path)  # an ablation's row stands beside the baseline's, never replaces it
    with open(path, newline="") as f:
        assert len(list(csv.DictReader(f))) == 8
    table = learning_report.final_summary(path, reps=500).splitlines()
    # lstm: 100, 200, 300 -> mean 200, IQM of 3 trims nothing (200); gru: 1, 2, 3, 10 -> mean 4, IQM mean(2, 3) = 2.5
    lstm = next(line for line in table if line.startswith("| learning_lstm |")).split("|")
    gru = next(line for line in table if line.startswith("| learning_gru |")).split("|")
    assert lstm[2].strip() == "3" and lstm[3].strip().startswith("200.0 [") and lstm[4].strip().startswith("200.0 [")
    assert lstm[5].strip() == "100.0" and lstm[6].strip() == "0.40" and lstm[7].strip() == "0.10 (0.20)"
    # holds: best - last3 = 0.6 ret <= 150 for 100 and 200, not for 300; every part of the bar but steer fails
    assert lstm[8].strip() == "2 of 3"
    assert lstm[9].strip() == "not met: return, every seed, progress, holds"
    assert gru[3].strip().startswith("2.5 [") and gru[4].strip().startswith("4.0 [") and gru[5].strip() == "1.0"
    # the GRU's sampled |steer| is 0.5, its mean action's 0.25: smooth enough (the bar judges the mean action)
    assert gru[8].strip() == "4 of 4" and gru[9].strip() == "not met: return, every seed, progress"
    low, high = (float(x) for x in gru[4].split("[")[1].rstrip("] ").split(","))
    assert 1.0 <= low < 4.0 < high <= 10.0  # a bootstrap interval of the mean lies within the scores
    # driving its mean action (the rule's evaluation policy): that policy's columns, 0.0 and progress 0 in every row
    mean_action = learning_report.final_summary(path, reps=500, policy="mean-action").splitlines()
    assert mean_action[0] == "The final policy driving its mean action:"
    assert table[0].startswith("The final policy sampled")
    lstm = next(line for line in mean_action if line.startswith("| learning_lstm |")).split("|")
    assert lstm[4].strip().startswith("0.0 [") and lstm[5].strip() == "0.0" and lstm[6].strip() == "0.00"
    assert lstm[9].strip() == "not met: return, every seed, progress, holds"  # 0.0 everywhere: below each bar


def test_the_ppo_peer_is_compared_with_each_variants_mean_action_over_seeds(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    with open(results / "baselines_fresh.json", "w") as f:
        json.dump(BASELINES, f)
    base = {"updates": 8000, "env_steps": 40000, "hours": 2.5, "best_return": 0.0, "best_progress": 0.0,
            "final_progress": 0.5, "final_mean_abs_steer": 0.6, "mean_action_abs_steer": 0.2,
            "mean_action_progress": 0.8, "best_eval_return": 600.0, "last3_eval_return": 550.0}  # fmt: skip
    for exp_name, variant, seed, mean_action, sampled in [
        ("learning_lstm", "lstm", 11, 600.0, 1.0), ("learning_lstm", "lstm", 12, 700.0, 1.0),
        ("learning_lstm", "lstm", 13, 800.0, 1.0), ("learning_gru", "gru", 11, 500.0, 1.0),
        ("learning_gru", "gru", 12, 500.0, 1.0), ("learning_gru", "gru", 13, 500.0, 1.0),
        ("learning_gru_alpha0.1", "gru", 11, 5000.0, 1.0),  # an ablation is not the method: left out
    ]:  # fmt: skip
        learning.write_final_row(
            {"exp_name": exp_name, "variant": variant, "seed": seed, "mean_action_return": mean_action,
             "final_return": sampled, **base}, str(results / "learning_final.csv"),
        )  # fmt: skip
    peer = str(results / "ppo_peer.csv")
    final = str(results / "learning_final.csv")
    assert learning_report.peer_summary(final, peer) == ""  # no file yet: nothing
    with open(peer, "w", newline="") as f:
        f.write("variant,seed,cpu_hours,final_return\n")
    assert learning_report.peer_summary(final, peer) == ""  # the header alone: nothing
    with open(peer, "a", newline="") as f:
        f.write("ppo,11,3.1,550.0\n")
    one = learning_report.peer_summary(final, peer, reps=500)  # one PPO seed: no interval of its own, no verdict
    assert "550.0 (one seed: no interval)" in one and "(seed 11: 550.0 at 3.10 CPU-h)" in one
    assert one.count("too few runs to judge (n = 1)") == 2 and "supported" not in one
    with open(peer, "a", newline="") as f:
        f.write("ppo,12,3.1,650.0\n")
    text = learning_report.write_final_report(str(results), reps=500)
    with open(results / "learning_final.md") as f:
        assert f.read() == text
    # PPO: mean 600. lstm 600, 700, 800 - PPO 550, 650 = +100: of the C(5, 3) = 10 splits of the five returns,
    # the LSTM's three sum to 2100 or more in 2 (600 + 700 + 800, 650 + 700 + 800): p = 0.2, weak. Welch: se^2 =
    # 10000 / 3 + 5000 / 2 = 5833.3, df = 5833.3^2 / ((10000 / 3)^2 / 2 + 2500^2 / 1) = 2.88, t = 3.257:
    # +100 +- 248.8. gru 500, 500, 500 - PPO = -100: the GRU's split is the lowest of 10 (the opposite's p = 0.1),
    # Welch's variance PPO's alone, df 1, t = 12.706: -100 +- 12.706 * 50
    assert "2 seeds, its deterministic policy: mean 600.0 [" in text
    assert "(seed 11: 550.0 at 3.10 CPU-h, 12: 650.0 at 3.10 CPU-h)" in text
    rows = {line.split("|")[1].strip(): line.split("|") for line in text.splitlines() if " - ppo |" in line}
    assert set(rows) == {"lstm - ppo", "gru - ppo"}
    for name, diff, p, low, high in [("lstm - ppo", 100.0, 0.2, -148.8, 348.8),
                                     ("gru - ppo", -100.0, 1.0, -100.0 - 635.3, -100.0 + 635.3)]:  # fmt: skip
        assert float(rows[name][2]) == diff
        assert rows[name][3].strip() == f"permutation p={p:.3f}, Welch t 95% [{low:+.1f}, {high:+.1f}], n=3+2"
    assert rows["lstm - ppo"][4].strip() == "weak (positive, but the exact test's p = 0.200 is not below 0.05)"
    assert rows["gru - ppo"][4].strip() == "not supported (the estimate is negative; the opposite's p = 0.100)"
    assert text.index("driving its mean action") < text.index("sampled, as trained") < text.index("SB3 PPO")
    # the LSTM against the GRU (700 - 500 with the mean action) stands between the variants' tables and PPO
    assert text.index("sampled, as trained") < text.index("| mean action | +200.0 |") < text.index("SB3 PPO")
    # PPO's rows of other tracks beside them (ppo_peer.py's writer, keyed by seed and tracks) change nothing: the
    # old rows, without a tracks column, are read and rewritten as the fresh tracks 10100..10119
    import ppo_peer

    ppo_peer.write_row({"variant": "ppo", "seed": 11, "cpu_hours": 3.1, "final_return": 9999.0,
                        "tracks": "10300..10329"}, peer)  # fmt: skip
    with open(peer, newline="") as f:
        assert [(r["seed"], r["final_return"], r["tracks"]) for r in csv.DictReader(f)] == [
            ("11", "550.0", "10100..10119"), ("11", "9999.0", "10300..10329"), ("12", "650.0", "10100..10119")
        ]
    assert learning_report.write_final_report(str(results), reps=500) == text


def test_the_lstm_is_compared_with_the_gru_for_each_policy_over_seeds(tmp_path):
    path = str(tmp_path / "learning_final.csv")
    base = {"updates": 8000, "env_steps": 40000, "hours": 2.5, "best_return": 0.0, "best_progress": 0.0,
            "final_progress": 0.5, "final_mean_abs_steer": 0.6, "mean_action_abs_steer": 0.2,
            "mean_action_progress": 0.8, "best_eval_return": 600.0, "last3_eval_return": 550.0}  # fmt: skip
    rows = [
        ("learning_lstm", "lstm", 11, 600.0, 10.0), ("learning_lstm", "lstm", 12, 700.0, 20.0),
        ("learning_lstm", "lstm", 13, 800.0, 30.0), ("learning_gru", "gru", 11, 500.0, 40.0),
        ("learning_gru", "gru", 12, 500.0, 50.0), ("learning_gru", "gru", 13, 500.0, 60.0),
        ("learning_lstm_alpha0.1", "lstm", 11, -5000.0, -5000.0),  # an ablation is not the method: left out
    ]  # fmt: skip
    for i, (exp_name, variant, seed, mean_action, sampled) in enumerate(rows):
        learning.write_final_row(
            {"exp_name": exp_name, "variant": variant, "seed": seed, "mean_action_return": mean_action,
             "final_return": sampled, **base}, path,
        )  # fmt: skip
        if i == 2:  # the LSTM alone: nothing to compare
            assert learning_report.variant_difference(path) == ""
    text = learning_report.variant_difference(path)
    table = {line.split("|")[1].strip(): line.split("|") for line in text.splitlines() if line.startswith("| ")}
    assert set(table) == {"final policy: LSTM - GRU", "mean action", "sampled"}
    # mean action: 700 - 500 = +200, the LSTM's 600, 700, 800 the top 3 of 6 in the only one of the C(6, 3) = 20
    # splits: p = 1/20 = 0.05, not below 0.05 (3 runs a side can never be); Welch: the GRU has no spread, so
    # +200 +- t_2 * 100 / sqrt(3) = +200 +- 248.4. Sampled: 20 - 50 = -30, every LSTM run below every GRU run (the
    # opposite's p = 0.05 again); Welch: variances 100 and 100, df 4, -30 +- 2.7764 * sqrt(200 / 3) = -30 +- 22.7
    for name, diff, p, low, high, verdict in [
        ("mean action", 200.0, 0.05, -48.4, 448.4, "weak (positive, but the exact test's p = 0.050 is not below"),
        ("sampled", -30.0, 1.0, -52.7, -7.3, "not supported (the estimate is negative; the opposite's p = 0.050)"),
    ]:  # fmt: skip
        assert float(table[name][2]) == diff
        assert table[name][3].strip() == f"permutation p={p:.3f}, Welch t 95% [{low:+.1f}, {high:+.1f}], n=3+3"
        assert table[name][4].strip().startswith(verdict)
    one = str(tmp_path / "one_gru_seed.csv")  # one GRU seed: no spread to measure, no verdict
    for exp_name, variant, seed, mean_action, sampled in rows[:4]:
        learning.write_final_row({"exp_name": exp_name, "variant": variant, "seed": seed,
                                  "mean_action_return": mean_action, "final_return": sampled, **base}, one)  # fmt: skip
    assert learning_report.variant_difference(one).count("too few runs to judge (n = 1)") == 2


def test_the_bar_is_met_only_when_every_part_is(tmp_path):
    def row(ret, progress=0.7, steer=0.2, best=700.0, last3=600.0, sampled_steer=0.6):
        return {"final_return": ret, "final_progress": progress, "final_mean_abs_steer": sampled_steer,
                "mean_action_abs_steer": steer, "best_eval_return": best, "last3_eval_return": last3}  # fmt: skip

    assert all(learning_report.bar_verdict([row(600.0), row(650.0), row(550.0)]).values())  # mean 600, min 550
    assert not learning_report.bar_verdict([row(900.0), row(900.0), row(349.0)])["every seed"]  # mean 716, a seed < 350
    assert not learning_report.bar_verdict([row(600.0), row(599.0)])["return"]
    assert not learning_report.bar_verdict([row(700.0, progress=0.6), row(700.0, progress=0.69)])["progress"]  # 0.645
    assert not learning_report.bar_verdict([row(700.0, steer=0.31, sampled_steer=0.2)])["steer"]  # the mean action's
    assert not learning_report.bar_verdict([row(700.0), row(700.0, best=800.0, last3=649.0)])["holds"]  # 151 below best


def test_diagnostics_average_each_bucket_of_updates(tmp_path):
    tags = dict(learning_report.DIAGNOSTICS)
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
    rows = learning_report.diagnostics(str(tmp_path), bucket=500)
    assert [(r["updates"], r["races"]) for r in rows] == [("0-499", 4), ("500-999", 3), ("1500-1999", 1)]
    assert [r["training return"] for r in rows] == pytest.approx([(-80 - 60 + 10 + 30) / 4, 200.0, 400.0])
    assert [r["actor sigma"] for r in rows] == pytest.approx([0.8, 0.55, 0.4])
    assert rows[0]["eval return"] == 50.0 and rows[1]["eval return"] == 250.0 and np.isnan(rows[2]["eval return"])
    table = learning_report.diagnostics_table(rows).splitlines()
    assert table[0].startswith("| updates | races | training return |") and len(table) == 2 + 3
    assert table[2].startswith("| 0-499 | 4 | -25.00 |") and table[4].endswith("|  |  |  |")


def test_report_keeps_saved_curves_and_never_shrinks_one(dirs):
    runs, results = dirs
    fields = ["env_steps", "updates", "wall_hours", "eval_return", "eval_progress"]
    saved = {
        "learning_lstm_seed1": [[500, 0, 0.1, -80.0, 0.02], [4000, 2000, 1.2, 620.0, 0.71]],  # run not here
        "learning_gru_seed2": [[500, 0, 0.1, -80.0, 0.02], [4000, 2000, 1.2, 40.0, 0.15]],  # restarted here
    }
    for name, rows in saved.items():
        with open(os.path.join(results, name + ".csv"), "w", newline="") as f:
            csv.writer(f).writerows([fields, *rows])
    write_sitting(os.path.join(runs, "multi_car_racing__learning_gru__2__1700000000"), [(500, -80.0, 0.02, 0)], 1e6)
    write_sitting(os.path.join(runs, "multi_car_racing__learning_gru__3__1700000000"), [(700, -60.0, 0.05, 100)], 1e6)
    ablation = learning.experiment_name("lstm", entropy_coef=0.03)  # an entropy-scale ablation is its own curve
    write_sitting(os.path.join(runs, f"multi_car_racing__{ablation}__3__1700000000"), [(900, 10.0, 0.1, 200)], 1e6)

    learning_report.report(runs, results)
    curves = learning_report.load_curves(runs, results)
    assert sorted(curves) == [
        "learning_gru_seed2", "learning_gru_seed3", "learning_lstm_alpha0.03_seed3", "learning_lstm_seed1"
    ]
    assert curves["learning_gru_seed2"][-1]["env_steps"] == 4000  # the restarted run is behind: CSV kept
    assert learning_report.read_curve(os.path.join(results, "learning_gru_seed3.csv"))[-1]["updates"] == 100
    with open(os.path.join(results, "learning.md")) as f:
        table = f.read().splitlines()
    assert "| lstm_seed1 | 4000 | 2000 | 1.20 | 620.0 | 0.71 | 620.0 (0.71) | 4000 steps, 1.20 h |" in table
    assert "| gru_seed2 | 4000 | 2000 | 1.20 | 40.0 | 0.15 | 40.0 (0.15) | not met |" in table
    assert table[-1] == "| pursuit@70 (baseline) | | | | 909.0 | 1.00 | | |"
    assert os.path.getsize(os.path.join(results, "learning.png")) > 0
    assert not any(row.startswith("| lstm_alpha0.03_seed3 ") for row in table)  # the default method's page only
    with open(os.path.join(results, "screening", "ablations.md")) as f:
        runs_there = [row.split(" | ")[0].removeprefix("| ") for row in f.read().splitlines()[2:]]
    assert runs_there[:1] == ["lstm_alpha0.03_seed3"] and "random (baseline)" in runs_there  # no default lstm seed 3
    assert os.path.getsize(os.path.join(results, "screening", "ablations.png")) > 0


def test_an_ablation_is_drawn_beside_the_default_run_of_its_variant_and_seed(dirs):
    runs, results = dirs
    for name, seed in (("learning_gru", 4), ("learning_gru_retnorm", 4), ("learning_gru", 5), ("learning_lstm", 4)):
        write_sitting(os.path.join(runs, f"multi_car_racing__{name}__{seed}__1700000000"), [(500, 1.0, 0.1, 0)], 1e6)
    learning_report.report(runs, results)
    with open(os.path.join(results, "screening", "ablations.md")) as f:
        runs_there = [row.split(" | ")[0].removeprefix("| ") for row in f.read().splitlines()[2:]]
    assert runs_there[:2] == ["gru_seed4", "gru_retnorm_seed4"]  # not gru seed 5, not lstm seed 4
    assert runs_there[2:] == ["random (baseline)", "pursuit@70 (baseline)"]


def test_ablation_runs_are_named_by_every_changed_flag():
    assert learning.experiment_name("gru") == "learning_gru"
    assert (
        learning.experiment_name("lstm", entropy_coef=0.03, decoder_min_log_sigma=0.0)
        == "learning_lstm_alpha0.03_logsigmamin0"
    )
    assert (
        learning.experiment_name("lstm", entropy_coef=None, decoder_min_log_sigma=-1.5)
        == "learning_lstm_logsigmamin-1.5"
    )
    assert learning.experiment_name("gru", norm="layer") == "learning_gru_normlayer"
    assert learning.experiment_name("gru", return_norm=True) == "learning_gru_retnorm"
    assert learning.experiment_name("lstm", dead_zone_start=-0.5) == "learning_lstm_dzstart-0.5"
    with pytest.raises(ValueError, match="^not an ablation flag: free_bits"):
        learning.experiment_name("lstm", free_bits=2.0)
    for name in learning.ABLATION_TAGS:  # each ablation is a real flag of both scripts
        for variant in ("lstm", "gru"):
            assert name in {f.name for f in dataclasses.fields(importlib.import_module(f"dreamer_{variant}").Args)}


def test_an_ablation_reaches_the_script_and_a_refused_value_names_its_flag(tmp_path, monkeypatch):
    monkeypatch.setattr(learning, "RUNS", str(tmp_path))  # no runs here: every sitting starts a new run
    script, args, overrides = learning.run_args(
        "gru", 2, 1.5, False, decoder_min_log_sigma=-1.0, entropy_coef=None, norm="layer", return_norm=True
    )
    assert script.VARIANT == "gru" and args.exp_name == "learning_gru_logsigmamin-1_normlayer_retnorm"
    assert (args.decoder_min_log_sigma, args.norm, args.entropy_coef, args.return_norm) == (-1.0, "layer", 1.0, True)
    cpu = script.PRESETS["cpu"]  # None: the preset's value; the rest is the CPU preset with LEARNING_CONFIG on top
    assert (args.seed, args.time_limit_hours, args.total_updates) == (2, 1.5, learning.FINAL_UPDATES)
    assert (args.image_size, args.batch_size, args.imagination_horizon) == (64, cpu["batch_size"], 15)
    assert (args.stage, args.eval_checkpoints, args.preset, overrides) == ("single", True, "cpu", set())
    _, args, _ = learning.run_args("lstm", 3, 1.0, False, dead_zone_start=-0.5)  # no schedule: the final value
    script = importlib.import_module("dreamer_lstm")
    assert args.exp_name == "learning_lstm_dzstart-0.5" and args.dead_zone_start == args.dead_zone_end == -0.5
    assert {script.dead_zone_at(e, args) for e in (0, 10, 1000)} == {-0.5}
    script, args, _ = learning.run_args("lstm", 1, 1.0, False, decoder_min_log_sigma=3.0)
    with pytest.raises(ckpt.UsageError, match=r"^--decoder-min-log-sigma must lie in \[-5, 2\], got 3.0$"):
        run_tools.validate_args(args, script.LOG_SIGMA_RANGE)


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
    (logged,) = learning.eval_curve(run_dir)
    result = learning.policy_summary(os.path.join(run_dir, "checkpoints", "best.pt"), 10_000, 2, "deterministic")
    assert result["variant"] == variant and result["tracks"] == "10000..10001"
    assert result["eval_return"] == pytest.approx(logged["eval_return"], abs=0.01)  # the CSV keeps 2 decimals
    assert result["eval_progress"] == pytest.approx(logged["eval_progress"], abs=1e-4)
    assert len(result["returns"]) == len(result["progress"]) == 2
    on_training_tracks = learning.policy_summary(os.path.join(run_dir, "checkpoints", "latest.pt"), train_tracks=1)
    assert on_training_tracks["tracks"] == "training races 1..1" and len(on_training_tracks["returns"]) == 1
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


def test_training_curves_read_the_runs_races_and_keep_them_as_csv(dirs):
    runs, results = dirs
    run_dir = os.path.join(runs, "multi_car_racing__learning_lstm__11__1700000000")
    os.makedirs(run_dir)
    with open(os.path.join(run_dir, "progress.csv"), "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["charts/episode", "car_0/charts/episodic_return", "car_0/perf/updates"])
        writer.writerows([[1, -80.0, ""], [2, -70.0, 100], [3, 150.5, 200]])  # the prefill race has no updates
    curves = learning_report.training_curves(runs, results)
    assert curves == {"learning_lstm_seed11": [{"updates": 100, "return": -70.0}, {"updates": 200, "return": 150.5}]}
    os.remove(os.path.join(run_dir, "progress.csv"))  # the run is gone from this machine: its CSV stands in
    assert learning_report.training_curves(runs, results) == curves
    with open(os.path.join(run_dir, "progress.csv"), "w", newline="") as f:  # a restarted run, behind the CSV
        writer = csv.writer(f)
        writer.writerow(["charts/episode", "car_0/charts/episodic_return", "car_0/perf/updates"])
        writer.writerows([[1, -90.0, 100]])
    assert learning_report.training_curves(runs, results) == curves  # the longer saved curve is kept, not overwritten


def test_final_row_refuses_a_run_short_of_its_updates(tmp_path, monkeypatch):
    """A run still training (or stopped early) has no final policy: --final names the run and its updates."""
    run = tmp_path / "multi_car_racing__learning_lstm__12__1700000000"
    (run / "checkpoints").mkdir(parents=True)
    import race

    monkeypatch.setattr(race, "read_checkpoint", lambda path: (None, {"agents": [{"num_updates": 4300}]}))
    with pytest.raises(ValueError, match="has made 4300 of its 8000 updates"):
        learning.final_row("lstm", 12, runs_dir=str(tmp_path))


def test_final_row_counts_the_steps_and_hours_after_the_last_evaluation(tmp_path, monkeypatch):
    """The row's env steps and hours are the whole run's (latest.pt's counter, the last logged scalar of each
    sitting), not those of its last evaluation, which can lie hundreds of updates before the end."""
    run = tmp_path / "multi_car_racing__learning_lstm__12__1700000000"
    (run / "checkpoints").mkdir(parents=True)
    write_sitting(str(run), [(500, -80.0, 0.02, 100), (1000, 50.0, 0.2, 300)], wall_start=1_000_000.0, pid=101)
    before = set(os.listdir(run))
    writer = SummaryWriter(str(run))  # a later sitting: training only, no evaluation
    writer.add_scalar("car_0/perf/updates", 350, 1100, walltime=2_000_000.0)
    writer.add_scalar("car_0/perf/updates", 400, 1234, walltime=2_000_000.0 + 1800.0)
    writer.close()
    as_process(str(run), before, pid=202)
    import race

    checkpoint = {"agents": [{"num_updates": 400}], "counters": {"global_step": 1234}}
    monkeypatch.setattr(race, "read_checkpoint", lambda path: (None, checkpoint))
    measured = {"eval_return": 1.0, "eval_progress": 0.5, "mean_abs_steer": 0.1, "updates": 400}
    monkeypatch.setattr(learning, "policy_summary", lambda *args: measured)
    row = learning.final_row("lstm", 12, runs_dir=str(tmp_path), updates=400)
    assert row["env_steps"] == 1234  # not the last evaluation's 1000
    assert row["hours"] == pytest.approx((1000 + 1800) / 3600, abs=1e-4)  # 1000 s, then 1800 s; not the gap
    assert row["best_eval_return"] == 50.0 and row["last3_eval_return"] == pytest.approx(-15.0)


def test_references_on_other_tracks_are_measured_once_and_kept_apart(tmp_path):
    base = learning_report.baselines(10_100, 1, results_dir=str(tmp_path), filename="baselines_fresh.json")
    assert base["pursuit@70"]["eval_progress"] > 0.95 and base["pursuit@70"]["eval_return"] > 800
    assert base["random"]["eval_progress"] < 0.2 and base["random"]["eval_return"] < 0
    assert not (tmp_path / "baselines.json").exists()  # the held-out tracks' reference is another file
    with pytest.raises(ValueError, match=r"baselines_fresh.json holds the references on tracks 10100..10100, not "
                                         r"10100..10119: give another filename"):  # fmt: skip
        learning_report.baselines(10_100, 20, results_dir=str(tmp_path), filename="baselines_fresh.json")
    with open(tmp_path / "baselines_fresh.json", "w") as f:  # read back, not recomputed
        json.dump({"random": {"eval_return": -1.0, "eval_progress": 0.01},
                   "pursuit@70": {"eval_return": 2.0, "eval_progress": 1.0}}, f)  # fmt: skip
    line = learning_report.fresh_reference(str(tmp_path))
    assert "20 tracks (10100..10119)" in line and "random actions -1.0 (progress 0.01)" in line
    assert "driver at 70 2.0 (1.00)" in line



# --- The command line ------------------------------------------------------------------------
def test_the_command_line_names_the_run_by_its_ablated_flags():
    args = tyro.cli(learning.Args, args=["--variant", "gru", "--return-norm", "--norm", "layer", "--screen", "3100"])
    assert learning.experiment_name(args.variant, **learning.ablation(args)) == "learning_gru_normlayer_retnorm"
    assert args.screen == 3100 and (args.first_track, args.tracks) == (10_100, 5)  # --calibrate's tracks
    assert learning.ablation(tyro.cli(learning.Args, args=[])) == dict.fromkeys(learning.ABLATION_TAGS)  # the preset


@pytest.mark.parametrize("argv, message", [
    (["--report", "--final"], "--report and --final are separate modes: give one at most"),
    (["--screen", "3100", "--policy-rule", "--calibrate", "x.pt"],
     "--screen and --policy-rule and --calibrate are separate modes"),
    (["--horizon", "5"], "--horizon is the imagination horizon of --calibrate; give --calibrate CHECKPOINT"),
    (["--reference-runs-dir", "runs"], "--reference-runs-dir is the default run's place for --screen"),
    (["--hours", "0"], "--hours must be > 0, got 0.0"),
    (["--updates", "0", "--final"], "--updates must be >= 1, got 0"),
    (["--calibrate", "x.pt", "--tracks", "0"], "--tracks and --horizon must be >= 1, got 0 and None"),
    (["--decoder-min-log-sigma", "3"], "--decoder-min-log-sigma must lie in [-5, 2], got 3.0"),  # the script's rule
])  # fmt: skip
def test_the_command_line_refuses_bad_input_in_one_line_before_any_work(argv, message, tmp_path):
    with pytest.raises(SystemExit) as exit_info:
        learning.cli([*argv, "--runs-dir", str(tmp_path / "runs")])
    text = str(exit_info.value)
    assert text.startswith("learning.py: error: ") and message in text and "\n" not in text
    assert not os.path.exists(tmp_path / "runs")  # nothing was trained or written


def test_a_mode_without_its_run_or_checkpoint_names_it_in_one_line(tmp_path):
    for argv, message in [
        (["--diagnose", "--seed", "3"], f"no run of learning_lstm seed 3 in {tmp_path}"),
        (["--final", "--variant", "gru"], f"no run of learning_gru seed 1 in {tmp_path}"),
        (["--calibrate", str(tmp_path / "none.pt")], "none.pt: no such checkpoint file"),
    ]:
        with pytest.raises(SystemExit, match=r"^learning\.py: error: ") as exit_info:
            learning.cli([*argv, "--runs-dir", str(tmp_path)])
        assert message in str(exit_info.value) and "\n" not in str(exit_info.value)


@pytest.mark.parametrize("argv", [
    ["--evaluate", "x.pt"], ["--export", "x.pt", "out.pt"],  # user operations: python evaluate.py now
    ["--variant", "transformer"], ["--norm", "group"], ["--screen", "many"],
])  # fmt: skip
def test_the_parser_refuses_removed_modes_and_bad_values(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        learning.cli(argv)
    assert exit_info.value.code == 2 and argv[0] in capsys.readouterr().err  # tyro's message names the flag
