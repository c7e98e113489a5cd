"""envs.highway: highway-env's intersection-multi-agent-v1 as a PettingZoo ParallelEnv.

References: highway-env itself (the same scenario made with gymnasium and stepped with the same seed
and actions), highway-env's own render() frame, and PettingZoo's API test.
"""

from __future__ import annotations

import os
import warnings

import cv2
import gymnasium as gym
import numpy as np
import pytest
from conftest import TINY_RUN
from pettingzoo.test import parallel_api_test, parallel_seed_test

from envs.highway import GRAYSCALE_WEIGHTS, HIGHWAY_ENV_ID, HighwayIntersection
from utils import make_vec_env

AGENTS = ["car_0", "car_1"]


def constant_actions(action) -> dict[str, np.ndarray]:
    return {agent: np.asarray(action, np.float32) for agent in AGENTS}


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.astype(np.float64).ravel(), b.astype(np.float64).ravel())[0, 1])


def test_parallel_api_and_seeding():
    env = HighwayIntersection()
    parallel_api_test(env, num_cycles=15)
    env.close()
    parallel_seed_test(HighwayIntersection, num_cycles=10)  # same seed, same observations and rewards


def test_spaces_and_observations():
    env = HighwayIntersection()
    assert env.possible_agents == AGENTS
    for agent in AGENTS:
        assert env.observation_space(agent) == gym.spaces.Box(0, 255, (96, 96, 3), np.uint8)
        assert env.action_space(agent) == gym.spaces.Box(-1, 1, (2,), np.float32)
    observations, infos = env.reset(seed=0)
    assert os.environ.get("SDL_VIDEODRIVER") != "dummy"
    for agent in AGENTS:
        obs = observations[agent]
        assert obs.shape == (96, 96, 3) and obs.dtype == np.uint8
        assert obs.std() > 0  # not blank
        np.testing.assert_array_equal(obs[..., 0], obs[..., 1])  # gray copied into 3 channels
        np.testing.assert_array_equal(obs[..., 0], obs[..., 2])
    assert not np.array_equal(observations["car_0"], observations["car_1"])  # each centred on its own car
    env.close()


@pytest.mark.parametrize("seed", [0, 1])
def test_observation_is_oriented_like_highway_envs_render(seed):
    """By default the observation covers the render() frame's area, centred on the same car (car_0):
    it must match the frame scaled down to 96x96, and must not match its transpose."""
    env = HighwayIntersection(render_mode="rgb_array")
    observations, _ = env.reset(seed=seed)
    for _ in range(3):
        observations, *_ = env.step(constant_actions([0.2, 0.0]))
    frame = env.render()
    assert frame.shape == (600, 600, 3) and frame.std() > 0
    gray_frame = frame.astype(np.float32) @ np.array(GRAYSCALE_WEIGHTS, np.float32)
    gray = cv2.resize(gray_frame, (96, 96), interpolation=cv2.INTER_AREA)
    obs = observations["car_0"][..., 0]
    assert correlation(obs, gray) > 0.7
    assert correlation(obs.T, gray) < 0.3
    env.close()


def test_matches_highway_env_stepped_directly():
    """Same seed and actions as highway-env's own multi-agent env: same images, per-agent rewards and flags."""
    env = HighwayIntersection()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        raw = gym.make(HIGHWAY_ENV_ID, config=env.highway_config)
    observations, infos = env.reset(seed=3)
    raw_obs, raw_info = raw.reset(seed=3)
    rng = np.random.default_rng(0)
    for step in range(40):  # (a crash ends this episode at its 20th step)
        for i, agent in enumerate(AGENTS):
            np.testing.assert_array_equal(observations[agent][..., 0], raw_obs[i][0].T)  # (W, H) -> (H, W)
        actions = {agent: rng.uniform(-1, 1, 2).astype(np.float32) for agent in AGENTS}
        observations, rewards, terminations, truncations, infos = env.step(actions)
        raw_obs, raw_rewards, raw_terminated, raw_truncated, raw_info = raw.step(tuple(actions[a] for a in AGENTS))
        for i, agent in enumerate(AGENTS):
            assert rewards[agent] == infos[agent]["agents_rewards"][i] == raw_rewards[i]
            assert raw_rewards[i] == raw_info["agents_rewards"][i]
            assert terminations[agent] == bool(raw.unwrapped._is_terminated())  # highway-env's episode rule
            assert truncations[agent] == (raw_truncated and not terminations[agent])
            assert infos[agent]["crashed"] == raw.unwrapped.controlled_vehicles[i].crashed
        if not env.agents:
            break
    for i, agent in enumerate(AGENTS):  # the last step's images too
        np.testing.assert_array_equal(observations[agent][..., 0], raw_obs[i][0].T)
    assert all(terminations.values())  # the episode ended by highway-env's rule, for every agent:
    assert step == 19 and any(v.crashed for v in raw.unwrapped.controlled_vehicles)  # a crash at the 20th step
    env.close()
    raw.close()


def test_a_crash_ends_the_episode_for_every_agent():
    env = HighwayIntersection()
    env.reset(seed=0)
    for _ in range(40):  # full throttle straight on: seed 0 crashes within a few seconds
        _, rewards, terminations, truncations, infos = env.step(constant_actions([1.0, 0.0]))
        if not env.agents:
            break
    assert env.agents == []
    assert any(infos[a]["crashed"] for a in AGENTS)
    assert terminations == {"car_0": True, "car_1": True} and truncations == {"car_0": False, "car_1": False}
    for i, agent in enumerate(AGENTS):
        assert rewards[agent] == infos[agent]["agents_rewards"][i]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(constant_actions([0.0, 0.0]))
    env.close()


def test_truncation_at_duration():
    env = HighwayIntersection(duration=1.0)  # 5 steps at 5 Hz
    env.reset(seed=0)
    for step in range(1, 6):
        _, _, terminations, truncations, infos = env.step(constant_actions([0.0, 0.0]))
        assert not any(terminations.values())
        assert all(truncations.values()) == (step == 5)
    assert env.agents == []
    env.close()


def test_bad_actions_raise_value_errors():
    env = HighwayIntersection()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="car_1.*not finite"):
        env.step({"car_0": np.zeros(2), "car_1": np.array([np.nan, 0.0])})
    with pytest.raises(ValueError, match=r"car_0.*shape \(3,\)"):
        env.step({"car_0": np.zeros(3), "car_1": np.zeros(2)})
    with pytest.raises(ValueError, match="car_7"):
        env.step({"car_0": np.zeros(2), "car_1": np.zeros(2), "car_7": np.zeros(2)})
    with pytest.raises(ValueError, match="no action for car_1"):
        env.step({"car_0": np.zeros(2)})
    env.close()


def test_runs_through_make_vec_env_in_worker_processes():
    venv = make_vec_env("highway-intersection", 2, seed=5, use_subprocess=True)
    assert venv.num_envs == 4 and venv.agents == AGENTS
    obs = venv.reset()
    assert obs.shape == (4, 96, 96, 3) and obs.dtype == np.uint8
    _, rewards, dones, infos = venv.step(np.tile([0.1, 0.0], (4, 1)).astype(np.float32))
    assert not dones.any() and all(info["alive"] and not info["is_first"] for info in infos)
    for k in range(2):  # race k is seeded with 5 + k
        reference = HighwayIntersection()
        reference_obs, _ = reference.reset(seed=5 + k)
        _, reference_rewards, *_ = reference.step(constant_actions([0.1, 0.0]))
        reference.close()
        for j, agent in enumerate(AGENTS):
            np.testing.assert_array_equal(obs[2 * k + j], reference_obs[agent])
            assert rewards[2 * k + j] == pytest.approx(reference_rewards[agent])
    venv.close()


def test_highway_random_reads_a_runs_evaluations_per_car_over_sittings(tmp_path, monkeypatch, capsys):
    from highway_random import agent_evaluations
    from torch.utils.tensorboard import SummaryWriter

    run_dir = str(tmp_path / "highway-intersection__dreamer_lstm__1__1700000000")
    # (env step, updates, car_0 return, car_1 return); the second sitting (--resume) is a second file
    for suffix, points in ((".a", [(594, 50, 3.0, 2.0)]), (".b", [(848, 550, 13.6, 5.6), (1200, 1050, 21.8, 18.2)])):
        writer = SummaryWriter(run_dir, filename_suffix=suffix)
        for step, updates, *returns in points:
            writer.add_scalar("car_0/perf/updates", updates, step)
            writer.add_scalar("car_0/charts/episodic_return", -1.0, step)  # training races are not evaluations
            for i, value in enumerate(returns[::-1]):  # car_1 first: the rows still list car_0, car_1
                writer.add_scalar(f"car_{1 - i}/eval/episodic_return", value, step)
        writer.close()
    assert agent_evaluations(run_dir) == [
        {"env_steps": 594, "updates": 50, "car_0": 3.0, "car_1": 2.0},
        {"env_steps": 848, "updates": 550, "car_0": 13.6, "car_1": 5.6},
        {"env_steps": 1200, "updates": 1050, "car_0": 21.8, "car_1": 18.2},
    ]

    with pytest.raises(FileNotFoundError, match="no TensorBoard event file in .*empty"):
        agent_evaluations(str(tmp_path / "empty"))
    no_eval = str(tmp_path / "no_eval")
    writer = SummaryWriter(no_eval)
    writer.add_scalar("car_0/charts/episodic_return", 1.0, 10)
    writer.close()
    with pytest.raises(ValueError, match="logged no evaluation .*--eval-every"):
        agent_evaluations(no_eval)

    # the random reference drives as many cars as the run has (a 2-car reference for it: a mismatch is refused)
    import highway_random

    drawn = []
    monkeypatch.setattr(highway_random, "random_returns", lambda e, r, s, n: drawn.append(n) or np.zeros((r, e, n)))
    highway_random.main(["--run", run_dir, "--episodes", "1", "--repeats", "1", "--csv", str(tmp_path / "h.csv")])
    highway_random.main(["--episodes", "1", "--repeats", "1", "--num-agents", "3"])
    three = str(tmp_path / "three_cars")
    writer = SummaryWriter(three)
    for i in range(3):
        writer.add_scalar(f"car_{i}/eval/episodic_return", 1.0, 10)
    writer.close()
    highway_random.main(["--run", three, "--episodes", "1", "--repeats", "1"])
    assert drawn == [2, 3, 3]
    assert open(tmp_path / "h.csv").readline().strip() == "env_steps,updates,car_0,car_1"
    with pytest.raises(SystemExit):
        highway_random.main(["--run", run_dir, "--num-agents", "3"])
    assert "--num-agents 3: the run " in capsys.readouterr().err


def test_dreamer_on_highway_logs_evaluations_but_no_steer_statistic(tmp_path):
    """The racing env's action 0 is the steer, highway-env's the acceleration: a highway run logs its
    evaluation returns and no car_i/eval/mean_abs_steer."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    import dreamer_lstm

    tiny = {k: v for k, v in TINY_RUN.items() if k != "max_steps"}
    run_dir = dreamer_lstm.main(
        dreamer_lstm.Args(env_id="highway-intersection", num_agents=2, runs_dir=str(tmp_path), **tiny)
    )
    tags = set()
    for path in os.listdir(run_dir):
        if path.startswith("events.out.tfevents."):
            acc = EventAccumulator(os.path.join(run_dir, path))
            acc.Reload()
            tags |= set(acc.Tags()["scalars"])
    assert {"car_0/eval/episodic_return", "car_1/eval/episodic_return"} <= tags
    assert not any(tag.endswith("mean_abs_steer") for tag in tags)
