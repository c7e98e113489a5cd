"""plot.py on synthetic TensorBoard logs: grouping, smoothing, aggregation and the PNGs."""

import json
import os

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d
from torch.utils.tensorboard import SummaryWriter

import plot

STEPS = np.arange(0, 500, 10)


def curve(variant, stage, seed, agent):
    """A distinct, noisy curve per run and agent."""
    rng = np.random.default_rng(hash((variant, stage, seed, agent)) % 2**32)
    base = {"lstm": 2.0, "gru": 1.0}[variant]
    return base * STEPS / 10 + rng.normal(0, 5, len(STEPS)) + agent


def write_run(root, variant, stage, seed, agents, with_config=True):
    name = f"multi_car_racing__dreamer_{variant}_{stage}__{seed}__1700000000"
    run_dir = os.path.join(root, name)
    writer = SummaryWriter(run_dir)
    for agent in range(agents):
        values = curve(variant, stage, seed, agent)
        for step, value in zip(STEPS, values):
            writer.add_scalar(f"car_{agent}/charts/episodic_return", value, step)
            writer.add_scalar(f"car_{agent}/losses/actor", -value / 100, step)
            if stage == "race":
                writer.add_scalar(f"car_{agent}/charts/win_rate", 0.5 + 0.1 * (agent - 0.5), step)
    writer.close()
    if with_config:
        with open(os.path.join(run_dir, "config.json"), "w") as f:
            json.dump({"variant": variant, "stage": stage, "seed": seed}, f)
    return run_dir


@pytest.fixture(autouse=True)
def close_figures():
    """make_figures returns its figures open (for the tests to read): close them after each test."""
    yield
    plot.plt.close("all")


@pytest.fixture(scope="module")
def logdir(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("runs"))
    for variant in ("lstm", "gru"):
        for seed in (1, 2, 3):
            write_run(root, variant, "single", seed, agents=1, with_config=seed != 3)
            write_run(root, variant, "race", seed, agents=2)
    return root


def test_runs_are_grouped_by_variant_and_stage(logdir):
    groups = plot.group_runs(plot.load_runs(logdir))
    assert set(groups) == {("lstm", "single"), ("gru", "single"), ("lstm", "race"), ("gru", "race")}
    assert all([r.seed for r in runs] == [1, 2, 3] for runs in groups.values())
    race = groups[("lstm", "race")][0]
    assert len(race.scalars["charts/episodic_return"]) == 2  # both agents pooled under one tag


def test_mean_curve_is_mean_of_scipy_smoothed_seeds(logdir):
    groups = plot.group_runs(plot.load_runs(logdir))
    curves = [c for run in groups[("gru", "race")] for c in run.scalars["charts/episodic_return"]]
    grid, mean, std, n = plot.aggregate(curves, sigma=3.0)
    assert n == 6
    np.testing.assert_array_equal(grid, np.linspace(0, 490, plot.GRID_POINTS))  # all six share steps 0..490
    expected = np.stack(
        [
            np.interp(
                grid,
                STEPS,
                gaussian_filter1d(
                    curve("gru", "race", seed, agent).astype(np.float32).astype(float), 3.0, mode="nearest"
                ),
            )
            for seed in (1, 2, 3)
            for agent in (0, 1)
        ]
    )
    np.testing.assert_allclose(mean, expected.mean(0), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(std, expected.std(0), rtol=1e-6, atol=1e-6)


def test_the_common_grid_is_the_x_range_all_curves_share():
    """Curves over steps 0..90, 30..120 and 20..60 share 30..60: the grid spans it, each curve read there."""
    curves = [(np.arange(0.0, 100, 10), np.arange(10.0)), (np.arange(30.0, 130, 10), np.full(10, 5.0)),
              (np.arange(20.0, 70, 10), np.zeros(5))]  # fmt: skip
    grid, mean, _, n = plot.aggregate(curves, sigma=0.0)
    np.testing.assert_array_equal(grid, np.linspace(30, 60, plot.GRID_POINTS))
    np.testing.assert_allclose(mean, (grid / 10 + 5.0 + 0.0) / 3)  # the first curve is step / 10, unsmoothed
    assert n == 3


def test_figures_have_the_expected_series(logdir, tmp_path):
    figures = plot.make_figures(logdir, str(tmp_path), sigma=2.0)
    assert set(figures) == {
        "single_agent_return.png", "multi_agent_return.png", "multi_agent_win_rate.png", "losses.png"
    }
    for name in figures:
        assert os.path.getsize(tmp_path / name) > 1000
    labels = [line.get_label() for line in figures["single_agent_return.png"].axes[0].lines]
    assert sorted(labels) == ["_seed"] * 6 + ["gru (3 seeds)", "lstm (3 seeds)"]  # each seed drawn thin too
    lines = {line.get_label(): line.get_ydata() for line in figures["single_agent_return.png"].axes[0].lines}
    assert lines["lstm (3 seeds)"][-1] > lines["gru (3 seeds)"][-1]  # lstm's synthetic curve is steeper
    win = figures["multi_agent_win_rate.png"].axes[0].lines[0].get_ydata()
    np.testing.assert_allclose(win, 0.5, atol=1e-6)  # agents at 0.45 and 0.55 average to 0.5


def labelled(ax) -> list[str]:
    """The labels of an axes' labelled lines (the groups), without the thin unlabelled per-seed curves."""
    return [line.get_label() for line in ax.lines if not line.get_label().startswith("_")]


def test_bad_logdir_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit, match="no TensorBoard event files"):
        plot.main([str(tmp_path), "--out", str(tmp_path / "f")])
    with pytest.raises(SystemExit):
        plot.main([str(tmp_path / "missing")])
    assert "is not a directory" in capsys.readouterr().err


def test_evaluation_figures_appear_when_evaluations_are_logged(tmp_path):
    run_dir = str(tmp_path / "multi_car_racing__learning_lstm__1__1700000000")
    writer = SummaryWriter(run_dir)
    for step, (ret, progress) in enumerate([(-80.0, 0.02), (100.0, 0.2), (400.0, 0.5)]):
        writer.add_scalar("car_0/eval/episodic_return", ret, step * 1000)
        writer.add_scalar("car_0/eval/progress", progress, step * 1000)
    writer.close()
    figures = plot.make_figures(str(tmp_path), str(tmp_path / "figures"), sigma=0.0)
    assert set(figures) == {"single_agent_eval_return.png", "single_agent_eval_progress.png"}
    line = figures["single_agent_eval_progress.png"].axes[0].lines[0]
    assert line.get_label() == "lstm (1 seed)"
    np.testing.assert_allclose(line.get_ydata()[[0, -1]], [0.02, 0.5], atol=1e-6)  # sigma 0: the logged values


def write_race_sitting(root, name, races, values):
    """A race.py --train sitting: racer tags per variant and the race count, logged at env-step x (one per race)."""
    run_dir = os.path.join(root, name)
    writer = SummaryWriter(run_dir)
    for k, race_number in enumerate(races):
        step = 1000 * race_number + 7 * k  # env steps: not the race count
        writer.add_scalar("charts/race", race_number, step)
        writer.add_scalar("racer_0_lstm/charts/win_rate", values[k], step)
        writer.add_scalar("racer_1_gru/charts/win_rate", 1 - values[k], step)
        writer.add_scalar("racer_0_lstm/losses/actor", -values[k], step)
    writer.close()
    with open(os.path.join(run_dir, "config.json"), "w") as f:
        json.dump({"variant": "lstm+gru", "stage": "race", "seed": 5}, f)


def test_race_sittings_join_per_variant_against_races(tmp_path):
    write_race_sitting(str(tmp_path), "races_00002/run", [1, 2], [0.2, 0.4])
    write_race_sitting(str(tmp_path), "races_00004/run", [3, 4], [0.6, 0.8])  # the next sitting of the same seed
    groups = plot.group_runs(plot.load_runs(str(tmp_path)))
    assert set(groups) == {("lstm", "race"), ("gru", "race")}
    ((races, lstm),) = groups[("lstm", "race")][0].scalars["charts/win_rate"]
    ((_, gru),) = groups[("gru", "race")][0].scalars["charts/win_rate"]
    assert races.tolist() == [1, 2, 3, 4] and lstm.tolist() == pytest.approx([0.2, 0.4, 0.6, 0.8])
    assert gru.tolist() == pytest.approx([0.8, 0.6, 0.4, 0.2])
    figures = plot.make_figures(str(tmp_path), str(tmp_path / "figures"), sigma=0.0)
    ax = figures["multi_agent_win_rate.png"].axes[0]
    assert ax.get_xlabel() == "races"
    line = next(line for line in ax.lines if line.get_label() == "lstm (1 seed)")
    np.testing.assert_allclose(line.get_xdata()[[0, -1]], [1, 4])
    np.testing.assert_allclose(line.get_ydata()[[0, -1]], [0.2, 0.8], atol=1e-6)
    write_race_sitting(str(tmp_path), "again/run", [1, 2], [0.5, 0.5])  # another run of seed 5: not a sitting
    runs = plot.group_runs(plot.load_runs(str(tmp_path)))[("lstm", "race")]
    assert sorted(run.scalars["charts/win_rate"][0][0].tolist() for run in runs) == [[1, 2], [1, 2, 3, 4]]


def test_losses_are_drawn_per_x_unit_and_controls_beside_the_ghost(logdir, tmp_path):
    """Steps and races never share an axis; a single-stage run continued from a checkpoint (the experiment's
    control) is not a seed of the single stage but the ghost stage's comparison."""
    import shutil

    root = tmp_path / "runs"
    shutil.copytree(logdir, root)
    write_race_sitting(str(root), "races/run", [1, 2, 3], [0.2, 0.4, 0.6])
    control = write_run(str(root), "lstm", "single", 9, agents=1)
    with open(os.path.join(control, "config.json"), "w") as f:
        json.dump({"variant": "lstm", "stage": "single", "seed": 9, "checkpoint": "runs/x/checkpoints/best.pt"}, f)
    ghost_run = write_run(str(root), "lstm", "ghost", 9, agents=1)
    for run_dir, values in ((ghost_run, [100.0, 300.0]), (control, [200.0, 250.0])):  # evaluations, car alone
        writer = SummaryWriter(run_dir, filename_suffix=".eval")
        for step, value in zip((10, 20), values):
            writer.add_scalar("car_0/eval/episodic_return", value, step)
        writer.close()
    figures = plot.make_figures(str(root), str(tmp_path / "f"), sigma=0.0)
    steps = figures["losses.png"].axes[0]
    races = figures["losses_race.png"].axes[0]
    assert steps.get_xlabel() == "step" and races.get_xlabel() == "races"
    assert "lstm/race (3 seeds)" in labelled(steps)  # the step-counted race runs only
    assert labelled(races) == ["lstm/race (1 seed)"]
    assert max(line.get_xdata().max() for line in races.lines) == 3
    steps, races = (figures[f"multi_agent_win_rate{s}.png"].axes[0] for s in ("", "_races"))  # never on one axis
    assert steps.get_xlabel() == "step" and "lstm (3 seeds)" in labelled(steps)
    assert races.get_xlabel() == "races" and sorted(labelled(races)) == ["gru (1 seed)", "lstm (1 seed)"]
    single = labelled(figures["single_agent_return.png"].axes[0])
    assert sorted(single) == ["gru (3 seeds)", "lstm (3 seeds)"]  # the continued run is no fourth seed
    ghost = sorted(labelled(figures["ghost_return.png"].axes[0]))
    assert ghost == ["lstm/ghost (1 seed)", "lstm/single-continued (1 seed)"]
    evaluations = figures["ghost_eval_return.png"].axes[0]  # the comparable one: each car alone, held-out tracks
    for label, values in (("lstm/ghost (1 seed)", [100.0, 300.0]), ("lstm/single-continued (1 seed)", [200.0, 250.0])):
        line = next(line for line in evaluations.lines if line.get_label() == label)
        np.testing.assert_allclose(line.get_ydata()[[0, -1]], values, atol=1e-6)
    assert "single_agent_eval_return.png" not in figures  # the continued run's evaluations are no single seed's


def test_head_to_head_figure_from_the_tournaments_csv(logdir, tmp_path, capsys):
    path = tmp_path / "head_to_head.csv"
    path.write_text(
        "seed_pair,races_trained,eval_races,lstm_wins,gru_wins,both_out,lstm_win_rate_ci_low,lstm_win_rate_ci_high\n"
        "\"11,11\",100,100,60,30,10,0.5,0.69\n\"11,11\",50,100,40,50,10,0.31,0.5\n\"12,12\",50,100,20,70,10,0.13,0.29\n"
    )
    figures = plot.make_figures(logdir, str(tmp_path / "f"), head_to_head=str(path))
    ax = figures["head_to_head.png"].axes[0]
    lstm = next(line for line in ax.lines if line.get_label() == "LSTM, seeds 11,11")
    assert lstm.get_xdata().tolist() == [50, 100] and lstm.get_ydata().tolist() == pytest.approx([0.4, 0.6])
    gru = next(line for line in ax.lines if line.get_label() == "GRU, seeds 12,12")
    assert gru.get_ydata().tolist() == pytest.approx([0.7])
    bars = next(c for c in ax.containers if c.get_label() == "_interval 12,12")  # the lone tournament's interval
    (segment,) = bars.lines[2][0].get_segments()
    np.testing.assert_allclose(segment, [[50, 0.13], [50, 0.29]])
    assert os.path.getsize(tmp_path / "f" / "head_to_head.png") > 1000
    assert ax.get_title() == "tournaments: LSTM vs GRU (Wilson 95%)"
    sampled = tmp_path / "head_to_head_stochastic.csv"  # the same tournaments raced with another policy
    sampled.write_text(path.read_text().replace(",60,30,10,0.5,0.69", ",25,70,10,0.18,0.34"))
    plot.main([logdir, "--out", str(tmp_path / "h"), "--head-to-head", str(path), str(sampled)])
    assert {"head_to_head.png", "head_to_head_stochastic.png"} <= set(os.listdir(tmp_path / "h"))
    figures = plot.make_figures(logdir, str(tmp_path / "h"), head_to_head=[str(path), str(sampled)])
    ax = figures["head_to_head_stochastic.png"].axes[0]
    assert ax.get_title() == "tournaments (stochastic policy): LSTM vs GRU (Wilson 95%)"
    lstm = next(line for line in ax.lines if line.get_label() == "LSTM, seeds 11,11")
    assert lstm.get_ydata().tolist() == pytest.approx([0.4, 0.25])  # each figure draws its own CSV
    with pytest.raises(ValueError, match="same name"):
        plot.make_figures(logdir, str(tmp_path / "h"), head_to_head=[str(path), str(tmp_path / "f" / "..")
                                                                     + "/head_to_head.csv"])  # fmt: skip
    bad = tmp_path / "bad.csv"
    bad.write_text("seed_pair,races_trained\n\"1,1\",50\n")
    with pytest.raises(SystemExit, match="not a head_to_head.csv"):
        plot.main([logdir, "--out", str(tmp_path / "g"), "--head-to-head", str(bad)])
    with pytest.raises(SystemExit):
        plot.main([logdir, "--out", str(tmp_path / "g"), "--head-to-head", str(tmp_path / "missing.csv")])
    assert "is not a file" in capsys.readouterr().err
