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
    expected = np.stack(
        [
            np.interp(grid, STEPS, gaussian_filter1d(curve("gru", "race", seed, agent).astype(np.float32).astype(float), 3.0, mode="nearest"))
            for seed in (1, 2, 3)
            for agent in (0, 1)
        ]
    )
    np.testing.assert_allclose(mean, expected.mean(0), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(std, expected.std(0), rtol=1e-6, atol=1e-6)


def test_figures_have_the_expected_series(logdir, tmp_path):
    figures = plot.make_figures(logdir, str(tmp_path), sigma=2.0)
    assert set(figures) == {"single_agent_return.png", "multi_agent_return.png", "multi_agent_win_rate.png", "losses.png"}
    for name in figures:
        assert os.path.getsize(tmp_path / name) > 1000
    labels = [line.get_label() for line in figures["single_agent_return.png"].axes[0].lines]
    assert sorted(labels) == ["gru (3 seeds)", "lstm (3 seeds)"]
    lines = {line.get_label(): line.get_ydata() for line in figures["single_agent_return.png"].axes[0].lines}
    assert lines["lstm (3 seeds)"][-1] > lines["gru (3 seeds)"][-1]  # lstm's synthetic curve is steeper
    win = figures["multi_agent_win_rate.png"].axes[0].lines[0].get_ydata()
    np.testing.assert_allclose(win, 0.5, atol=1e-6)  # agents at 0.45 and 0.55 average to 0.5


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
