"""``MultiCarRacing(num_agents=1, action_mode="classic", rules="carracing")`` against
gymnasium's own CarRacing-v3 (docs/environment.md): same tiles, same pose every step, same rewards,
same termination, and views that look like CarRacing's."""

import gymnasium
import numpy as np
import pytest

from envs import MultiCarRacing
from envs.pursuit import PursuitDriver

STEPS = 500


def make_pair(seed):
    reference = gymnasium.make("CarRacing-v3").unwrapped
    env = MultiCarRacing(num_agents=1, action_mode="classic", rules="carracing")
    ref_obs, _ = reference.reset(seed=seed)
    obs, _ = env.reset(seed=seed)
    return reference, env, ref_obs, obs["car_0"]


def pose(car):
    return np.array([car.hull.position[0], car.hull.position[1], car.hull.angle])


@pytest.mark.parametrize("seed", [0, 1, 7, 123])
def test_random_actions_reproduce_carracing(seed):
    reference, env, _, _ = make_pair(seed)
    assert env.num_tiles == len(reference.track)
    np.testing.assert_array_equal(env.track, np.array(reference.track))
    for ours, theirs in zip(env.road, reference.road):
        assert ours.fixtures[0].shape.vertices == theirs.fixtures[0].shape.vertices
    np.testing.assert_allclose(pose(env.cars[0]), pose(reference.car), atol=1e-6)

    rng = np.random.default_rng(seed)
    space = reference.action_space
    for t in range(STEPS):
        action = rng.uniform(space.low, space.high).astype(np.float32)
        _, ref_reward, ref_term, ref_trunc, ref_info = reference.step(action)
        _, rewards, terms, truncs, infos = env.step({"car_0": action})
        np.testing.assert_allclose(pose(env.cars[0]), pose(reference.car), atol=1e-6, err_msg=f"step {t}")
        assert rewards["car_0"] == pytest.approx(ref_reward, abs=1e-9), f"step {t}"
        assert terms["car_0"] == ref_term and truncs["car_0"] == ref_trunc, f"step {t}"
        assert infos["car_0"]["tiles"] == reference.tile_visited_count
        if ref_term:  # (random pedals rarely end a race in 500 steps: the tests below end one each way)
            break


@pytest.mark.parametrize("seed", [0, 1])
def test_leaving_the_playfield_terminates_like_carracing(seed):
    """Straight ahead at gas 0.3, the car crosses the grass out of the playfield: both envs end the race at the
    same step with CarRacing's -100 and no lap; ours names the reason."""
    reference, env, _, _ = make_pair(seed)
    action = np.array([0.0, 0.3, 0.0], np.float32)
    for t in range(1000):
        _, ref_reward, ref_term, _, ref_info = reference.step(action)
        _, rewards, terms, _, infos = env.step({"car_0": action})
        np.testing.assert_allclose(pose(env.cars[0]), pose(reference.car), atol=1e-6, err_msg=f"step {t}")
        assert terms["car_0"] == ref_term, f"step {t}"
        if ref_term:
            break
    assert ref_term and ref_reward == rewards["car_0"] == -100.0 and t > 100
    assert not ref_info["lap_finished"] and not infos["car_0"]["lap_finished"]
    assert infos["car_0"]["eliminated"] == "off_playfield"


@pytest.mark.parametrize("seed", [8])
def test_finished_lap_terminates_like_carracing(seed):
    """A pursuit driver completes a lap in both envs: same step, same reward, lap_finished."""
    reference, env, _, _ = make_pair(seed)
    driver = PursuitDriver(env, "car_0", target_speed=90)
    ref_total = total = 0.0
    for t in range(1000):
        action = driver.act()
        _, ref_reward, ref_term, _, ref_info = reference.step(action)
        _, rewards, terms, _, infos = env.step({"car_0": action})
        ref_total += ref_reward
        total += rewards["car_0"]
        assert terms["car_0"] == ref_term, f"step {t}"
        if ref_term:
            break
    assert ref_term and ref_info["lap_finished"] and infos["car_0"]["lap_finished"]
    assert total == pytest.approx(ref_total, abs=1e-6)
    assert infos["car_0"]["finish_step"] == t + 1


def road_or_grass(img):
    """0 road (grey), 1 grass (green), 2 anything else."""
    img = img.astype(int)
    green = img[..., 1] - img[..., 0]
    return np.where(green > 50, 1, np.where(np.abs(green) < 8, 0, 2))


@pytest.mark.parametrize("seed", [0, 5])
def test_views_match_carracing_pixels(seed):
    """After CarRacing's one-second zoom-in, our directly drawn view shows the same scene."""
    reference, env, _, _ = make_pair(seed)
    rng = np.random.default_rng(seed)
    for _ in range(80):
        action = np.array([rng.uniform(-0.3, 0.3), 0.5, 0.0], dtype=np.float32)
        ref_obs, *_ = reference.step(action)
        obs, *_ = env.step({"car_0": action})
    scene = slice(0, 84)  # above the dashboard strip
    agreement = np.mean(road_or_grass(ref_obs[scene]) == road_or_grass(obs["car_0"][scene]))
    assert agreement > 0.95
    assert np.mean(np.abs(ref_obs[scene].astype(int) - obs["car_0"][scene].astype(int))) < 8
