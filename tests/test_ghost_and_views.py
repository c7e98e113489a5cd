"""Ghost racing and the cameras (docs/environment.md)."""

import dataclasses

import cv2
import numpy as np
import pytest

from envs import GhostTrajectory, MultiCarRacing, ghost_beaten
from envs.pursuit import PursuitDriver, drive_race

SEED = 6
LONG = 3000


def record(speed):
    env = MultiCarRacing(num_agents=1, max_steps=LONG)
    drive_race(env, {"car_0": speed}, seed=SEED)
    return env.trajectory("car_0")


@pytest.fixture(scope="module")
def slow_ghost():
    return record(45.0)


@pytest.fixture(scope="module")
def fast_ghost():
    return record(70.0)


def test_replayed_ghost_reproduces_recorded_poses(slow_ghost):
    env = MultiCarRacing(num_agents=1, max_steps=LONG)
    env.reset(seed=SEED, options={"ghosts": {"car_0": slow_ghost}})
    driver = PursuitDriver(env, "car_0", 45.0)
    np.testing.assert_array_equal(env._ghost_poses()[0], slow_ghost.poses[0])
    step = 0
    while env.agents:
        _, _, _, _, infos = env.step({"car_0": driver.act()})
        step += 1
        # the same driver on the same track drives exactly the recorded run
        if env.cars[0] is not None:
            np.testing.assert_array_equal(env._pose(0), slow_ghost.poses[step])
        else:  # the car leaves the track only as it finishes, on the recorded finish step
            assert step == slow_ghost.finish_step
        if step < len(slow_ghost.poses):
            np.testing.assert_array_equal(env._ghost_poses()[0], slow_ghost.poses[step])
    assert step == slow_ghost.finish_step
    # tying with the ghost on every tile: both are leaders
    assert infos["car_0"]["tile_reward"] == pytest.approx(1000.0, abs=1e-6)
    assert infos["car_0"]["ghost_tiles_ahead"] == 0 and not infos["car_0"]["ghost_beaten"]


def test_ghost_takes_the_leader_share(fast_ghost):
    env = MultiCarRacing(num_agents=1, max_steps=LONG)
    _, infos, _ = drive_race(env, {"car_0": 45.0}, seed=SEED, options={"ghosts": {"car_0": fast_ghost}})
    ghost_step = np.full(env.num_tiles, -1)
    ghost_step[fast_ghost.tile_ids] = fast_ghost.tile_steps
    car_step = env.first_touch_step[0]
    per_tile = 1000.0 / env.num_tiles
    expected = np.where(car_step <= ghost_step, per_tile, per_tile / 2).sum()
    assert np.sum(car_step > ghost_step) > 0.9 * env.num_tiles
    assert infos["car_0"]["tile_reward"] == pytest.approx(expected, abs=1e-6)
    assert not infos["car_0"]["ghost_beaten"] and infos["car_0"]["ghost_tiles_ahead"] <= 0


def test_faster_driver_beats_its_ghost(slow_ghost):
    env = MultiCarRacing(num_agents=1, max_steps=LONG)
    env.reset(seed=SEED, options={"ghosts": {"car_0": slow_ghost}})
    driver = PursuitDriver(env, "car_0", 70.0)
    ahead = []
    while env.agents:
        _, _, _, _, infos = env.step({"car_0": driver.act()})
        ahead.append(infos["car_0"]["ahead_of_ghost"])
    assert infos["car_0"]["ghost_beaten"] and infos["car_0"]["finish_step"] < slow_ghost.finish_step
    assert ahead[-1] and np.mean(ahead) > 0.8


def test_ghost_rule():
    def ghost(finish, tiles):
        return GhostTrajectory(0, 10, np.zeros((1, 3)), np.arange(tiles), np.arange(tiles), finish)

    assert ghost_beaten(500, 10, ghost(-1, 10))  # car finished, ghost did not
    assert ghost_beaten(500, 10, ghost(600, 10))  # finished earlier
    assert not ghost_beaten(600, 10, ghost(600, 10))  # a tie is not a win
    assert not ghost_beaten(-1, 9, ghost(600, 10))
    assert ghost_beaten(-1, 7, ghost(-1, 6))  # neither finished: more tiles
    assert not ghost_beaten(-1, 6, ghost(-1, 6))


def test_final_info_carries_the_run_as_a_ghost():
    """The ghost in the last info is the race as driven, read by hand: the car's pose after the reset and after each
    step (the last step's is gone with the car), and each tile's first touch at the step the tiles count grew (the
    tiles under the car at the start at step 0)."""
    env = MultiCarRacing(num_agents=1, max_steps=LONG)
    _, infos = env.reset(seed=SEED)
    tiles = infos["car_0"]["tiles"]  # the tiles under the car at the start count as touched at step 0
    driver, steps, poses, touches = PursuitDriver(env, "car_0", 70.0), 0, [], [0] * tiles
    while env.agents:
        hull = env.cars[0].hull
        poses.append((hull.position[0], hull.position[1], hull.angle))
        *_, infos = env.step({"car_0": driver.act()})
        steps += 1
        touches += [steps] * (infos["car_0"]["tiles"] - tiles)
        tiles = infos["car_0"]["tiles"]
    ghost = infos["car_0"]["trajectory"]
    assert ghost.track_seed == SEED and ghost.finish_step == steps and ghost.tiles == env.num_tiles
    assert len(ghost.poses) == steps + 1
    np.testing.assert_array_equal(ghost.poses[:-1], np.array(poses))
    np.testing.assert_array_equal(ghost.tile_steps, touches)
    assert sorted(ghost.tile_ids) == list(range(env.num_tiles))  # every tile, each once


def test_ghost_round_trips_through_plain_types(slow_ghost):
    back = GhostTrajectory.from_dict(slow_ghost.to_dict())
    np.testing.assert_array_equal(back.poses, slow_ghost.poses)
    assert back.finish_step == slow_ghost.finish_step and back.tiles == slow_ghost.tiles
    assert back == slow_ghost and back != dataclasses.replace(slow_ghost, finish_step=slow_ghost.finish_step + 1)


def test_ghost_needs_its_own_track(slow_ghost):
    env = MultiCarRacing(num_agents=1)
    with pytest.raises(ValueError, match=f"recorded on track seed {SEED}"):
        env.reset(seed=SEED + 1, options={"ghosts": {"car_0": slow_ghost}})
    with pytest.raises(ValueError, match="unknown agent 'car_5'"):
        env.reset(seed=SEED, options={"ghosts": {"car_5": slow_ghost}})
    env.reset()
    with pytest.raises(ValueError, match="needs a track seed"):
        env.trajectory("car_0")


# --- Views ----------------------------------------------------------------------------
ROAD = np.array([102, 102, 102])


def test_road_and_grass_colours_at_known_pixels():
    env = MultiCarRacing(num_agents=1)
    obs, _ = env.reset(seed=0)  # the start is on a straight
    view = obs["car_0"].astype(int)
    assert np.all(np.abs(view[50, 48] - ROAD) <= 6)  # straight ahead of the car: road
    grass = view[30, 2]  # far to the side
    assert grass[1] in (204, 230) and grass[0] == 102 and grass[2] == 102
    assert np.all(view[84:] == 0)  # dashboard: black strip, no bars while standing still


def test_dashboard_shows_speed_and_steering():
    env = MultiCarRacing(num_agents=1)
    env.reset(seed=0)
    for _ in range(30):
        obs, *_ = env.step({"car_0": np.array([0.5, 1.0])})
    strip = obs["car_0"][84:].astype(int)
    white = np.argwhere(np.all(strip == 255, axis=-1))
    assert len(white) and set(white[:, 1]) <= {12, 13, 14}  # speed bar, CarRacing's slot 5 of 40
    green = np.argwhere((strip[..., 1] == 255) & (strip[..., 0] == 0))
    assert len(green) and green[:, 1].min() >= 40  # steering bar grows from slot 20 (x = 48)


def test_every_car_is_visible_in_every_view():
    """In each grid order the car behind sees the car ahead drawn in front of itself; between the two orders each
    car is once the one behind (so neither car's view is left unchecked)."""
    behind_cars = set()
    for grid in ([0, 1], [1, 0]):
        env = MultiCarRacing(num_agents=2)
        obs, _ = env.reset(seed=1, options={"grid": grid})
        for _ in range(20):
            obs, *_ = env.step({a: np.array([0.0, 0.0]) for a in env.agents})
        ahead = max(env.agents, key=lambda a: env.car_state(a)["tile"])
        behind = min(env.agents, key=lambda a: env.car_state(a)["tile"])
        view = obs[behind][:84].astype(int)
        blue = (view[..., 2] > 150) & (view[..., 0] < 60) & (view[..., 1] < 60)
        red = (view[..., 0] > 150) & (view[..., 1] < 60) & (view[..., 2] < 60)
        assert blue.sum() > 15  # the other car, drawn in front of this one
        assert red.sum() > 15  # this car, in the ego colour
        assert np.argwhere(blue)[:, 0].mean() < np.argwhere(red)[:, 0].mean()  # higher in the frame
        assert ahead != behind
        behind_cars.add(behind)
        env.close()
    assert behind_cars == {"car_0", "car_1"}


def test_views_are_deterministic_and_per_car():
    def run():
        env = MultiCarRacing(num_agents=2)
        obs, _ = env.reset(seed=9)
        rng = np.random.default_rng(0)
        frames = []
        for _ in range(30):
            obs, *_ = env.step({a: rng.uniform(-1, 1, 2) for a in env.agents})
            frames.append(obs)
        return frames

    a, b = run(), run()
    for fa, fb in zip(a, b):
        for agent in fa:
            np.testing.assert_array_equal(fa[agent], fb[agent])
    assert not np.array_equal(a[-1]["car_0"], a[-1]["car_1"])


def test_ghost_is_drawn(fast_ghost):
    env = MultiCarRacing(num_agents=1)
    obs, _ = env.reset(seed=SEED, options={"ghosts": {"car_0": fast_ghost}})
    for _ in range(60):  # the ghost pulls away in front of the standing car
        obs, *_ = env.step({"car_0": np.array([0.0, 0.0])})
    view = obs["car_0"][:84].astype(int)
    ghostly = np.all(np.abs(view - np.array([190, 190, 255])) < 20, axis=-1)
    assert ghostly.sum() > 10


def test_rgb_array_frame_shows_track_and_views():
    """The frame: the track on the left, and each car's own view (its observation, scaled) in its panel on the right,
    car_0's on top."""
    env = MultiCarRacing(num_agents=2, render_mode="rgb_array")
    obs, _ = env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape == (400, 600, 3)
    assert frame.std() > 10
    for i, agent in enumerate(("car_0", "car_1")):
        panel = frame[200 * i : 200 * i + 200, 400:600][20:].astype(float)  # (its top rows: the panel's label)
        own = cv2.resize(obs[agent], (200, 200))[20:].astype(float)
        other = cv2.resize(obs[f"car_{1 - i}"], (200, 200))[20:].astype(float)
        assert np.abs(panel - own).mean() < 2 and np.abs(panel - other).mean() > 5


def test_rgb_array_frame_keeps_its_size_when_a_car_leaves_the_race():
    """Videos need one frame size: with three cars (two panel columns) an eliminated car keeps
    its last view in its panel instead of the layout shrinking to one column."""
    env = MultiCarRacing(num_agents=3, render_mode="rgb_array")
    env.reset(seed=3)
    shapes = {env.render().shape}
    car_2_panel = np.s_[:200, 600:800]  # third view: first row, second column of panels
    for _ in range(300):
        _, _, terms, _, infos = env.step({a: np.array([1.0, 1.0]) if a == "car_2" else np.zeros(2) for a in env.agents})
        frame = env.render()
        shapes.add(frame.shape)
        if terms.get("car_2"):
            break
    assert infos["car_2"]["eliminated"] == "off_road" and env.agents == ["car_0", "car_1"]
    env.step({a: np.zeros(2) for a in env.agents})
    after = env.render()
    assert shapes | {after.shape} == {(400, 800, 3)}
    assert np.array_equal(after[car_2_panel][20:], frame[car_2_panel][20:])  # frozen view (label row aside)
    assert after[car_2_panel].std() > 10
