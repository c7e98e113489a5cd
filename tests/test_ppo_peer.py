"""benchmarks/ppo_peer.py: the zoo's wrappers, a resumable training run, the evaluation row."""

import csv
import os
import sys

import gymnasium
import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks"))
import ppo_peer  # noqa: E402


def test_frame_skip_sums_rewards_and_stops_at_the_end():
    class Count(gymnasium.Env):
        observation_space = gymnasium.spaces.Box(0, 1, (1,))
        action_space = gymnasium.spaces.Box(-1, 1, (1,))

        def reset(self, *, seed=None, options=None):
            self.t = 0
            return np.zeros(1, np.float32), {}

        def step(self, action):
            self.t += 1
            return np.zeros(1, np.float32), float(self.t), self.t == 3, False, {"t": self.t}

    env = ppo_peer.FrameSkip(Count(), 2)
    env.reset()
    assert env.step(np.zeros(1))[1] == 1 + 2
    _, reward, terminated, _, info = env.step(np.zeros(1))
    assert (reward, terminated, info["t"]) == (3, True, 3)  # the episode ended inside the skip


def test_the_env_is_the_single_car_race_at_64_px_grayscale():
    env = ppo_peer.make_env()
    obs, _ = env.reset(seed=0)
    assert obs.shape == (64, 64, 1) and obs.dtype == np.uint8 and env.action_space.shape == (2,)
    assert env.unwrapped.race.dead_zone == -0.5  # the Dreamer runs' final dead zone
    env.close()


def test_a_run_resumes_in_a_later_sitting_and_writes_its_row(tmp_path, monkeypatch):
    monkeypatch.setitem(ppo_peer.ZOO, "n_envs", 2)
    monkeypatch.setitem(ppo_peer.ZOO, "n_steps", 32)
    monkeypatch.setitem(ppo_peer.ZOO, "batch_size", 32)
    monkeypatch.setitem(ppo_peer.ZOO, "n_epochs", 1)
    argv = ["--seed", "3", "--cpu-hours", "1", "--budget-steps", "64", "--tracks", "1", "--runs-dir", str(tmp_path),
            "--results", str(tmp_path / "ppo_peer.csv")]  # fmt: skip
    first = ppo_peer.main(argv)
    assert (first["env_steps"], first["updates"]) == (2 * 64, 1)  # one rollout of 2 x 32 steps, frame skip 2
    second = ppo_peer.main([*argv[:4], "--budget-steps", "128", *argv[6:]])  # the budget grows: it continues
    assert (second["env_steps"], second["updates"]) == (2 * 128, 2)
    with open(tmp_path / "ppo_peer.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1 and rows[0]["variant"] == "ppo" and int(rows[0]["env_steps"]) == 256  # replaced, not added
    assert -200 < float(rows[0]["final_return"]) < 1000 and 0 <= float(rows[0]["final_mean_abs_steer"]) <= 1
    with pytest.raises(SystemExit):
        ppo_peer.main(["--cpu-hours", "0"])


def test_the_budget_is_cpu_time_of_the_process(tmp_path, monkeypatch):
    """A clock of CPU time that advances 20 minutes per reading: the run stops at its 1 CPU-hour budget, long before
    its PPO steps, whatever the wall clock says; the record counts the CPU hours."""
    monkeypatch.setitem(ppo_peer.ZOO, "n_envs", 2)
    monkeypatch.setitem(ppo_peer.ZOO, "n_steps", 32)
    monkeypatch.setitem(ppo_peer.ZOO, "batch_size", 32)
    monkeypatch.setitem(ppo_peer.ZOO, "n_epochs", 1)
    readings = iter(range(10**6))
    monkeypatch.setattr(ppo_peer.time, "process_time", lambda: 1200.0 * next(readings))
    record = ppo_peer.train(3, hours=1.0, budget_steps=256, run_dir=str(tmp_path))  # (by the wall clock: 4 rollouts)
    assert record["env_steps"] < 2 * 64 and record["cpu_hours"] >= 1.0
