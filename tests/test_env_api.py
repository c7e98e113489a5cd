"""The racing env against the standards it claims: PettingZoo's parallel API and seed tests,
gymnasium's and Stable-Baselines3's env checkers, and the bad-input rules (docs/environment.md)."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from pettingzoo.test import parallel_api_test, parallel_seed_test
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from envs import SINGLE_CAR_ID, MultiCarRacing


@pytest.mark.parametrize("num_agents", [2, 3])
def test_pettingzoo_parallel_api(num_agents):
    parallel_api_test(MultiCarRacing(num_agents=num_agents, max_steps=200), num_cycles=200)


@pytest.mark.parametrize("num_agents", [2, 3])
def test_pettingzoo_parallel_seed(num_agents):
    parallel_seed_test(lambda: MultiCarRacing(num_agents=num_agents, max_steps=100), num_cycles=100)


def test_classic_action_mode_passes_the_api_test():
    parallel_api_test(MultiCarRacing(num_agents=2, action_mode="classic", max_steps=100), num_cycles=100)


def test_single_car_id_passes_gymnasium_and_sb3_checkers():
    env = gymnasium.make(SINGLE_CAR_ID, max_steps=100)
    gym_check_env(env.unwrapped, skip_render_check=True)
    sb3_check_env(gymnasium.make(SINGLE_CAR_ID, max_steps=100).unwrapped)
    assert env.observation_space.shape == (96, 96, 3) and env.observation_space.dtype == np.uint8
    assert env.action_space.shape == (2,)


def test_single_car_env_is_the_one_car_race():
    single = gymnasium.make(SINGLE_CAR_ID).unwrapped
    race = MultiCarRacing(num_agents=1)
    o1, _ = single.reset(seed=4)
    o2, _ = race.reset(seed=4)
    np.testing.assert_array_equal(o1, o2["car_0"])
    for _ in range(20):
        a = np.array([0.2, 0.6], dtype=np.float32)
        o1, r1, *_ = single.step(a)
        o2, r2, *_ = race.step({"car_0": a})
        np.testing.assert_array_equal(o1, o2["car_0"])
        assert r1 == r2["car_0"]
    assert single.np_random is single.race.np_random  # env.np_random is the generator the track came from
    unseeded = gymnasium.make(SINGLE_CAR_ID).unwrapped
    unseeded.reset()
    assert unseeded.np_random_seed == -1 and unseeded.np_random is unseeded.race.np_random  # (gymnasium: unknown)


def test_human_mode_shows_the_race_frame_in_real_time(monkeypatch):
    """As CarRacing's human mode: reset and every step show the frame in a window (so does render()), and the clock
    holds the loop at render_fps."""
    import pygame

    monkeypatch.setenv("SDL_VIDEODRIVER", "offscreen")
    ticks = []

    class Clock:
        def tick(self, fps):
            ticks.append(fps)

    monkeypatch.setattr(pygame.time, "Clock", Clock)
    env = MultiCarRacing(num_agents=1, render_mode="human")
    env.reset(seed=0)
    for _ in range(2):
        env.step({"car_0": np.zeros(2)})
        assert env.render() is None
    shown = pygame.surfarray.array3d(pygame.display.get_surface()).swapaxes(0, 1)
    env.close()
    assert ticks == [env.metadata["render_fps"]] * 5 == [50] * 5  # reset, 2 steps, 2 calls of render()
    assert shown.shape[:2] == env._race_frame().shape[:2] and shown.std() > 0  # a picture, not a blank window


@pytest.fixture
def race():
    env = MultiCarRacing(num_agents=2)
    env.reset(seed=0)
    return env


@pytest.mark.parametrize(
    "actions, message",
    [
        ({"car_0": [np.nan, 0.0], "car_1": [0.0, 0.0]}, "action for car_0 is not finite"),
        ({"car_0": [0.0, 0.0], "car_1": [np.inf, 0.0]}, "action for car_1 is not finite"),
        ({"car_0": [0.0, 0.0, 0.0], "car_1": [0.0, 0.0]}, r"action for car_0 has shape \(3,\), expected \(2,\)"),
        ({"car_0": [0.0, 0.0], "car_1": [0.0, 0.0], "car_7": [0.0, 0.0]}, "unknown agent 'car_7'"),
        ({"car_0": [0.0, 0.0]}, "no action for car_1"),
        ({"car_0": "fast", "car_1": [0.0, 0.0]}, "action for car_0 is not numeric"),
    ],
)
def test_bad_actions_raise_value_error_naming_the_agent(race, actions, message):
    with pytest.raises(ValueError, match=message):
        race.step(actions)


def test_rejected_step_leaves_the_race_untouched():
    a, b = MultiCarRacing(num_agents=2), MultiCarRacing(num_agents=2)
    a.reset(seed=1)
    b.reset(seed=1)
    good = {"car_0": np.array([0.1, 0.5]), "car_1": np.array([-0.1, 0.5])}
    for t in range(30):
        if t % 7 == 3:
            with pytest.raises(ValueError):
                a.step({"car_0": np.array([np.nan, 0.0]), "car_1": good["car_1"]})
        oa, ra, *_ = a.step(good)
        ob, rb, *_ = b.step(good)
        assert ra == rb
        np.testing.assert_array_equal(oa["car_0"], ob["car_0"])


def test_out_of_range_actions_are_clipped():
    a, b = MultiCarRacing(num_agents=1), MultiCarRacing(num_agents=1)
    a.reset(seed=2)
    b.reset(seed=2)
    for _ in range(10):
        oa, ra, *_ = a.step({"car_0": np.array([5.0, 3.0])})
        ob, rb, *_ = b.step({"car_0": np.array([1.0, 1.0])})
        assert ra == rb
        np.testing.assert_array_equal(oa["car_0"], ob["car_0"])


def test_stepping_a_finished_race_is_an_error():
    env = MultiCarRacing(num_agents=1, max_steps=3)
    env.reset(seed=0)
    for _ in range(3):
        env.step({"car_0": np.zeros(2)})
    assert env.agents == []
    with pytest.raises(RuntimeError, match="race is over"):
        env.step({})


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"num_agents": 0}, "num_agents must be a positive integer"),
        ({"action_mode": "joystick"}, "action_mode must be one of"),
        ({"rules": "f1"}, "rules must be one of"),
        ({"rules": "carracing", "num_agents": 2}, "one-car game: num_agents must be 1, got 2"),
        ({"dead_zone": 0.5}, r"dead_zone must lie in \[-1, 0\]"),
        ({"max_steps": 0}, "max_steps must be a positive integer"),
        ({"render_mode": "video"}, "render_mode must be None or one of"),
    ],
)
def test_bad_constructor_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        MultiCarRacing(**kwargs)
