"""utils.vec_env: every agent of K ParallelEnv races as one SB3 VecEnv slot.

References: the scripted env (every value known in closed form), a direct step-by-step replay of
the same env with the same seed and actions, and SB3's own DummyVecEnv for num_agents=1.
"""

from __future__ import annotations

import functools

import cv2
import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces
from scripted_env import ScriptedParallelEnv
from stable_baselines3 import PPO
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecVideoRecorder

from envs.multi_car_racing import MultiCarRacing
from utils import ENV_IDS, MultiAgentVecEnv, make_vec_env
from utils.vec_env import EnvFactory


def scripted(num_races=1, **kwargs):
    """One factory per race; race k gets tag=k (written into its observations)."""
    return [functools.partial(ScriptedParallelEnv, tag=k, **kwargs) for k in range(num_races)]


def slot_actions(num_slots: int) -> np.ndarray:
    """A distinct action per slot: slot i -> [i / 100, -i / 100]."""
    return np.stack([[i / 100, -i / 100] for i in range(num_slots)]).astype(np.float32)


# --------------------------------------------------------------------------------------
# Reference replay: step the same env directly and check every slot output against it.
# --------------------------------------------------------------------------------------
def check_against_direct_replay(env_fn, seed: int, actions_per_step: list[np.ndarray], use_subprocess=False):
    """Run one race inside MultiAgentVecEnv and, side by side, a second instance stepped directly.

    Asserts, every step and slot, the semantics of the module docstring of utils.vec_env.
    :return: counts of the events seen (so a caller can check the replay covered them)
    """
    env = env_fn()
    agents = list(env.possible_agents)
    zero = np.zeros(env.observation_space(agents[0]).shape, env.observation_space(agents[0]).dtype)
    venv = MultiAgentVecEnv([env_fn], use_subprocess=use_subprocess)
    events = {"agent_out_race_on": 0, "race_reset": 0, "dead_steps": 0, "truncated": 0, "terminated": 0}
    try:
        venv.seed(seed)
        vobs = venv.reset()
        obs, infos = env.reset(seed=seed)
        for j, agent in enumerate(agents):
            np.testing.assert_array_equal(vobs[j], obs[agent])
            assert venv.reset_infos[j]["is_first"] and venv.reset_infos[j]["alive"]
        for actions in actions_per_step:
            live = list(env.agents)
            obs, rewards, terms, truncs, infos = env.step({a: actions[j] for j, a in enumerate(agents) if a in live})
            vobs, vrew, vdone, vinfos = venv.step(actions)
            race_over = not env.agents
            if race_over:
                first_obs, first_infos = env.reset()  # unseeded: the env's RNG goes on, as in the auto-reset
                events["race_reset"] += 1
            for j, agent in enumerate(agents):
                info = vinfos[j]
                assert info["is_first"] == race_over
                if agent in live:
                    done = terms[agent] or truncs[agent]
                    assert info["alive"] is True
                    assert vrew[j] == pytest.approx(rewards[agent], rel=1e-6, abs=1e-6)
                    assert vdone[j] == done
                    assert info["TimeLimit.truncated"] == (truncs[agent] and not terms[agent])
                    for key, value in infos.get(agent, {}).items():  # the env's own info passes through
                        assert key in info and np.all(info[key] == value), key
                    if done:
                        np.testing.assert_array_equal(info["terminal_observation"], obs[agent])
                        events["truncated" if info["TimeLimit.truncated"] else "terminated"] += 1
                        if not race_over:
                            events["agent_out_race_on"] += 1
                    else:
                        assert "terminal_observation" not in info
                    expected = first_obs[agent] if race_over else (zero if done else obs[agent])
                else:
                    events["dead_steps"] += 1
                    assert info["alive"] is False
                    assert vrew[j] == 0.0 and not vdone[j] and "terminal_observation" not in info
                    expected = first_obs[agent] if race_over else zero
                np.testing.assert_array_equal(vobs[j], expected)
                if race_over:
                    assert venv.reset_infos[j]["is_first"] is True
    finally:
        venv.close()
        env.close()
    return events


# --------------------------------------------------------------------------------------
# Scripted env: values known in closed form.
# --------------------------------------------------------------------------------------
def test_slot_layout_and_actions_reach_their_agent():
    venv = MultiAgentVecEnv(scripted(num_races=2, num_agents=3))
    assert venv.num_envs == 6 and venv.num_races == 2 and venv.num_agents == 3
    assert venv.agents == ["agent_0", "agent_1", "agent_2"]
    assert venv.observation_space == spaces.Box(0, 255, (4, 4, 3), np.uint8)
    obs = venv.reset()
    assert obs.shape == (6, 4, 4, 3) and obs.dtype == np.uint8
    for slot in range(6):
        race, agent = divmod(slot, 3)
        assert venv.race_of(slot) == race and slot in venv.slots_of(race)
        assert tuple(obs[slot, 0, 0]) == (0, agent, race)  # (step, agent index, race tag)
    actions = slot_actions(6)
    obs, rewards, dones, infos = venv.step(actions)
    last_actions = venv.get_attr("last_actions", indices=[0, 3])
    for race in range(2):
        for agent in range(3):
            np.testing.assert_array_equal(last_actions[race][f"agent_{agent}"], actions[race * 3 + agent])
    np.testing.assert_allclose(rewards, [1.0, 1.5, 2.0] * 2)  # t + 0.5 * agent at t = 1
    assert rewards.dtype == np.float32 and dones.dtype == np.bool_ and not dones.any()
    assert [info["t"] for info in infos] == [1] * 6  # env info passed through
    venv.close()


def test_agent_out_while_race_goes_on_then_race_resets():
    """agent_0 terminates at step 2, agent_1 is truncated at max_steps=4: every output by hand."""
    venv = MultiAgentVecEnv(scripted(num_agents=2, drop_steps=[2, None], max_steps=4))
    reference = ScriptedParallelEnv(num_agents=2)
    venv.seed(5)
    obs = venv.reset()
    reference.reset(seed=5)
    np.testing.assert_array_equal(obs[0], reference.expected_obs(0, t=0))
    assert venv.reset_infos == [
        {"agent_index": 0, "episode_index": 0, "alive": True, "is_first": True},
        {"agent_index": 1, "episode_index": 0, "alive": True, "is_first": True},
    ]
    zero = np.zeros((4, 4, 3), np.uint8)
    actions = slot_actions(2)

    obs, rewards, dones, infos = venv.step(actions)  # t = 1
    assert dones.tolist() == [False, False] and [i["alive"] for i in infos] == [True, True]

    obs, rewards, dones, infos = venv.step(actions)  # t = 2: agent_0 terminates
    assert dones.tolist() == [True, False]
    np.testing.assert_array_equal(infos[0]["terminal_observation"], reference.expected_obs(0, t=2))
    assert infos[0]["TimeLimit.truncated"] is False and infos[0]["alive"] is True
    np.testing.assert_array_equal(obs[0], zero)
    np.testing.assert_array_equal(obs[1], reference.expected_obs(1, t=2))
    assert rewards.tolist() == [2.0, 2.5]
    assert "terminal_observation" not in infos[1]
    assert [i["is_first"] for i in infos] == [False, False]

    obs, rewards, dones, infos = venv.step(actions)  # t = 3: slot 0 is out
    np.testing.assert_array_equal(obs[0], zero)
    assert rewards.tolist() == [0.0, 3.5] and dones.tolist() == [False, False]
    assert infos[0] == {"alive": False, "is_first": False, "TimeLimit.truncated": False}
    assert infos[1]["alive"] is True

    obs, rewards, dones, infos = venv.step(actions)  # t = 4: agent_1 truncated, race over, auto-reset
    assert dones.tolist() == [False, True] and rewards.tolist() == [0.0, 4.5]
    np.testing.assert_array_equal(infos[1]["terminal_observation"], reference.expected_obs(1, t=4))
    assert infos[1]["TimeLimit.truncated"] is True
    assert [i["is_first"] for i in infos] == [True, True]
    assert [i["alive"] for i in infos] == [False, True]
    reference.reset()  # the auto-reset is unseeded: the env's RNG continues
    np.testing.assert_array_equal(obs[0], reference.expected_obs(0, t=0))
    np.testing.assert_array_equal(obs[1], reference.expected_obs(1, t=0))
    assert [i["episode_index"] for i in venv.reset_infos] == [1, 1]
    assert all(i["is_first"] and i["alive"] for i in venv.reset_infos)

    obs, rewards, dones, infos = venv.step(actions)  # first step of the new race
    assert [i["is_first"] for i in infos] == [False, False] and [i["alive"] for i in infos] == [True, True]
    assert rewards.tolist() == [1.0, 1.5]
    venv.close()


def test_all_agents_truncated_together_at_max_steps():
    venv = MultiAgentVecEnv(scripted(num_agents=3, max_steps=3))
    venv.reset()
    for _ in range(2):
        _, _, dones, _ = venv.step(slot_actions(3))
        assert not dones.any()
    obs, _, dones, infos = venv.step(slot_actions(3))
    assert dones.all()
    assert all(i["TimeLimit.truncated"] and i["is_first"] and i["alive"] for i in infos)
    assert [int(i["terminal_observation"][0, 0, 0]) for i in infos] == [3, 3, 3]  # last real step
    assert obs[:, 0, 0, 0].tolist() == [0, 0, 0]  # first observation of the new race
    venv.close()


@pytest.mark.parametrize("use_subprocess", [False, True])
def test_scripted_env_matches_direct_replay(use_subprocess):
    fn = functools.partial(ScriptedParallelEnv, num_agents=3, drop_steps=[2, 5, None], max_steps=6)
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, (3, 2)) for _ in range(15)]
    events = check_against_direct_replay(fn, seed=11, actions_per_step=actions, use_subprocess=use_subprocess)
    assert events["agent_out_race_on"] >= 4 and events["race_reset"] == 2 and events["dead_steps"] > 0
    assert events["truncated"] >= 2 and events["terminated"] >= 4


def test_seed_reproduces_observations_and_race_k_gets_seed_plus_k():
    venv = MultiAgentVecEnv(scripted(num_races=3, num_agents=2))
    assert venv.seed(100) == [100, 100, 101, 101, 102, 102]
    first = venv.reset()
    for k in range(3):
        reference_obs, _ = ScriptedParallelEnv(num_agents=2, tag=k).reset(seed=100 + k)
        np.testing.assert_array_equal(first[2 * k + 1], reference_obs["agent_1"])
    unseeded = venv.reset()  # seeds are used once: the RNG goes on
    assert not np.array_equal(unseeded, first)
    venv.seed(100)
    np.testing.assert_array_equal(venv.reset(), first)
    venv.close()


def test_set_options_one_dict_per_race_used_by_the_next_reset_only():
    """Race k resets with its own options (here the start grid: race 0 swaps the cars, race 1 keeps them), as the env
    reset directly with them; the reset after it uses none."""
    venv = make_vec_env("multi_car_racing", 2, 5, num_agents=2)
    grids = [{"grid": [1, 0]}, {"grid": [0, 1]}]
    venv.set_options(grids)
    with_options = venv.reset()
    venv.seed(5)
    without = venv.reset()
    venv.close()
    for k, options in enumerate(grids):
        env = MultiCarRacing(num_agents=2)
        swapped, _ = env.reset(seed=5 + k, options=options)
        plain, _ = env.reset(seed=5 + k)
        env.close()
        for j, agent in enumerate(("car_0", "car_1")):
            np.testing.assert_array_equal(with_options[2 * k + j], swapped[agent])
            np.testing.assert_array_equal(without[2 * k + j], plain[agent])
    assert not np.array_equal(with_options[0], without[0])  # the swapped grid shows car_0 another view
    venv = MultiAgentVecEnv(scripted(num_races=2, num_agents=2))
    with pytest.raises(ValueError, match="one options dict per race"):
        venv.set_options([{}, {}, {}])
    venv.close()


@pytest.mark.parametrize("use_subprocess", [False, True])
def test_get_attr_set_attr_env_method_map_slots_to_races(use_subprocess):
    venv = MultiAgentVecEnv(scripted(num_races=2, num_agents=2), use_subprocess=use_subprocess)
    venv.reset()
    # slots 2 and 3 are race 1: its env is called once, the value is reported per slot
    assert venv.env_method("set_dead_zone", -0.8, indices=[2, 3]) == [-0.8, -0.8]
    assert venv.get_attr("dead_zone_calls") == [0, 0, 1, 1]
    assert venv.get_attr("dead_zone") == [-0.5, -0.5, -0.8, -0.8]
    assert venv.get_attr("tag", indices=3) == [1]
    venv.set_attr("dead_zone", -0.6)
    assert venv.get_attr("dead_zone") == [-0.6] * 4
    assert venv.env_method("set_dead_zone", value=-0.7) == [-0.7] * 4
    assert venv.get_attr("dead_zone_calls", indices=[0, 2]) == [1, 2]
    assert venv.has_attr("dead_zone") and not venv.has_attr("no_such_attribute")
    with pytest.raises(AttributeError):
        venv.get_attr("no_such_attribute")
    assert venv.env_is_wrapped(Monitor) == [False] * 4
    with pytest.raises(IndexError):
        venv.get_attr("tag", indices=[4])
    venv.close()


@pytest.mark.parametrize("start_method", ["forkserver", "spawn"])
def test_subprocess_gives_the_same_outputs_as_in_process(start_method):
    fns = scripted(num_races=2, num_agents=2, drop_steps=[3, None], max_steps=5)
    results = []
    for use_subprocess in (False, True):
        venv = MultiAgentVecEnv(fns, use_subprocess=use_subprocess, start_method=start_method)
        venv.seed(3)
        trace = [venv.reset()]
        for _ in range(7):
            obs, rewards, dones, infos = venv.step(slot_actions(4))
            trace += [obs, rewards, dones]
            trace += [i.get("terminal_observation", np.zeros(0)) for i in infos]
            trace += [np.array([i["alive"], i["is_first"], i["TimeLimit.truncated"]]) for i in infos]
        venv.close()
        results.append(trace)
    assert len(results[0]) == len(results[1])
    for a, b in zip(*results, strict=True):
        np.testing.assert_array_equal(a, b)


def test_subprocess_worker_errors_are_raised_in_the_parent():
    venv = MultiAgentVecEnv(scripted(num_races=2, num_agents=1), use_subprocess=True)
    with pytest.raises(RuntimeError, match="step\\(\\) called on a finished episode"):
        venv.step(slot_actions(2))  # never reset: the env refuses to step
    assert venv.env_method("set_dead_zone", -0.9) == [-0.9, -0.9]  # the pipes are still in sync
    venv.close()
    with pytest.raises(TypeError, match="no_such_argument"):
        MultiAgentVecEnv([functools.partial(ScriptedParallelEnv, no_such_argument=1)], use_subprocess=True)
    with pytest.raises(ValueError, match="start_method"):
        MultiAgentVecEnv(scripted(), use_subprocess=True, start_method="fork")


def test_get_images_one_frame_per_race():
    venv = MultiAgentVecEnv(scripted(num_races=2, num_agents=3, render_mode="rgb_array"))
    assert venv.render_mode == "rgb_array" and venv.metadata["render_fps"] == 10
    venv.reset()
    venv.step(slot_actions(6))
    images = venv.get_images()
    assert len(images) == 2 and all(img.shape == (16, 16, 3) and (img == 1).all() for img in images)
    assert venv.render().shape == (32, 16, 3)  # SB3's tiling of the two races
    venv.close()


def test_unequal_spaces_are_rejected():
    class Mixed(ScriptedParallelEnv):
        def observation_space(self, agent):
            return spaces.Box(0, 255, (4, 4, 3) if agent == "agent_0" else (5, 4, 3), np.uint8)

    with pytest.raises(ValueError, match="share one observation space"):
        MultiAgentVecEnv([Mixed])


# --------------------------------------------------------------------------------------
# num_agents = 1: exactly SB3's semantics (reference: DummyVecEnv over a gymnasium view).
# --------------------------------------------------------------------------------------
class SingleAgentView(gym.Env):
    """The scripted env with one agent as a plain gymnasium env (the reference for DummyVecEnv)."""

    metadata = {"render_modes": []}

    def __init__(self, **kwargs):
        self.env = ScriptedParallelEnv(num_agents=1, **kwargs)
        self.observation_space = self.env.observation_space("agent_0")
        self.action_space = self.env.action_space("agent_0")

    def reset(self, *, seed=None, options=None):
        obs, infos = self.env.reset(seed=seed, options=options)
        return obs["agent_0"], infos["agent_0"]

    def step(self, action):
        obs, rewards, terms, truncs, infos = self.env.step({"agent_0": action})
        return obs["agent_0"], rewards["agent_0"], terms["agent_0"], truncs["agent_0"], infos["agent_0"]


def test_one_agent_matches_sb3_dummy_vec_env_exactly():
    kwargs = [dict(drop_steps=[3], max_steps=10), dict(drop_steps=[None], max_steps=4)]  # terminate / truncate
    ours = MultiAgentVecEnv([functools.partial(ScriptedParallelEnv, num_agents=1, **kw) for kw in kwargs])
    theirs = DummyVecEnv([functools.partial(SingleAgentView, **kw) for kw in kwargs])
    ours.seed(9)
    theirs.seed(9)
    np.testing.assert_array_equal(ours.reset(), theirs.reset())
    for _ in range(10):
        actions = slot_actions(2)
        (o1, r1, d1, i1), (o2, r2, d2, i2) = ours.step(actions), theirs.step(actions)
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(d1, d2)
        for a, b in zip(i1, i2, strict=True):
            assert a["TimeLimit.truncated"] == b["TimeLimit.truncated"]
            assert ("terminal_observation" in a) == ("terminal_observation" in b)
            if "terminal_observation" in a:
                np.testing.assert_array_equal(a["terminal_observation"], b["terminal_observation"])
            assert a["is_first"] == bool(b.get("terminal_observation") is not None)
            assert {k: v for k, v in a.items() if k in b and k != "terminal_observation"} == {
                k: v for k, v in b.items() if k != "terminal_observation"
            }
    ours.close()


def test_sb3_ppo_trains_on_one_agent_scripted_env():
    venv = VecMonitor(MultiAgentVecEnv(scripted(num_races=2, num_agents=1, max_steps=8)))
    model = PPO(
        "MlpPolicy", venv, n_steps=32, batch_size=32, n_epochs=1, policy_kwargs={"net_arch": [16]}, seed=0, device="cpu"
    )
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(total_timesteps=128)
    assert model.num_timesteps == 128
    assert model._n_updates == 2  # two rollouts of 32 steps in 2 races, one epoch each
    assert any(not torch.equal(p, q) for p, q in zip(model.policy.parameters(), before))  # the updates moved it
    lengths = [ep["l"] for ep in model.ep_info_buffer]
    assert len(lengths) == 128 // 8 and set(lengths) == {8}  # every episode is truncated at max_steps
    returns = [ep["r"] for ep in model.ep_info_buffer]
    assert returns == pytest.approx([sum(range(1, 9))] * len(returns))  # reward t at step t
    venv.close()


# --------------------------------------------------------------------------------------
# make_vec_env
# --------------------------------------------------------------------------------------
def test_make_vec_env_rejects_unknown_ids():
    assert set(ENV_IDS) == {"multi_car_racing", "highway-intersection"}
    with pytest.raises(ValueError, match="'no-such-env'.*highway-intersection.*multi_car_racing"):
        make_vec_env("no-such-env", 1, seed=0)
    with pytest.raises(ValueError, match="num_races"):
        make_vec_env("multi_car_racing", 0, seed=0)
    with pytest.raises(ValueError, match="module:attribute"):
        EnvFactory("no_colon")


# --------------------------------------------------------------------------------------
# The racing env
# --------------------------------------------------------------------------------------
def racing_actions(num_steps: int) -> list[np.ndarray]:
    """car_0 full throttle, steering hard left (leaves the road early); car_1 straight, light throttle."""
    return [np.array([[-1.0, 1.0], [0.0, 0.3]], np.float32)] * num_steps


def test_racing_slots_match_a_direct_replay_of_the_race():
    fn = functools.partial(MultiCarRacing, num_agents=2, max_steps=100)
    events = check_against_direct_replay(fn, seed=4, actions_per_step=racing_actions(230))
    assert events["agent_out_race_on"] >= 1 and events["dead_steps"] >= 1 and events["race_reset"] >= 2


def test_racing_slot_layout_and_seeding():
    venv = make_vec_env("multi_car_racing", 2, seed=7, num_agents=2, max_steps=50)
    assert venv.num_envs == 4 and venv.agents == ["car_0", "car_1"]
    assert venv.observation_space == spaces.Box(0, 255, (96, 96, 3), np.uint8)
    assert venv.action_space == spaces.Box(-1, 1, (2,), np.float32)
    obs = venv.reset()
    for k in range(2):
        reference, _ = MultiCarRacing(num_agents=2, max_steps=50).reset(seed=7 + k)
        for j in range(2):
            np.testing.assert_array_equal(obs[2 * k + j], reference[f"car_{j}"])
    assert not np.array_equal(obs[0], obs[2])  # different seeds, different tracks
    venv.close()


def test_racing_dead_zone_reaches_every_race_in_subprocesses():
    venv = make_vec_env("multi_car_racing", 2, seed=0, use_subprocess=True, num_agents=2, max_steps=50)
    venv.reset()
    venv.env_method("set_dead_zone", -0.8)  # takes effect at the next reset (racing env rule)
    venv.set_attr("brake_speed_threshold", 20.0, indices=[2])
    venv.reset()
    assert venv.get_attr("dead_zone") == [-0.8] * 4
    assert venv.get_attr("brake_speed_threshold") == [50.0, 50.0, 20.0, 20.0]
    venv.set_attr("dead_zone", -0.6)
    venv.reset()
    assert venv.get_attr("dead_zone") == [-0.6] * 4
    venv.close()


def test_racing_subprocess_matches_in_process():
    traces = []
    for use_subprocess in (False, True):
        venv = make_vec_env("multi_car_racing", 2, seed=3, use_subprocess=use_subprocess, num_agents=2, max_steps=40)
        trace = [venv.reset()]
        for actions in racing_actions(45):
            obs, rewards, dones, _ = venv.step(np.concatenate([actions, actions[::-1]]))
            trace += [obs, rewards, dones]
        venv.close()
        traces.append(trace)
    for a, b in zip(*traces, strict=True):
        np.testing.assert_array_equal(a, b)


def test_vec_video_recorder_writes_a_race_video(tmp_path):
    venv = make_vec_env("multi_car_racing", 1, seed=0, num_agents=2, max_steps=100, render_mode="rgb_array")
    recorder = VecVideoRecorder(
        venv, str(tmp_path), record_video_trigger=lambda step: step == 0, video_length=12, name_prefix="race"
    )
    recorder.reset()
    frame_shape = venv.get_images()[0].shape
    for actions in racing_actions(14):
        recorder.step(actions)
    recorder.close()
    videos = list(tmp_path.glob("race-*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 0
    capture = cv2.VideoCapture(str(videos[0]))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    assert len(frames) == 13  # the reset frame and 12 steps
    assert frames[0].shape == frame_shape  # one race: its own render() frame, untiled
    assert frames[-1].std() > 0


def test_sb3_ppo_runs_on_the_one_car_race():
    venv = VecMonitor(make_vec_env("multi_car_racing", 1, seed=0, num_agents=1, max_steps=60))
    model = PPO(
        "CnnPolicy",
        venv,
        n_steps=128,
        batch_size=64,
        n_epochs=1,
        policy_kwargs={"features_extractor_kwargs": {"features_dim": 32}, "net_arch": [32]},
        seed=0,
        device="cpu",
    )
    model.learn(total_timesteps=256)
    assert model.num_timesteps == 256
    lengths = [ep["l"] for ep in model.ep_info_buffer]
    assert len(lengths) >= 4 and max(lengths) <= 60  # every race ends by max_steps
    action, _ = model.predict(venv.reset(), deterministic=True)
    assert action.shape == (1, 2)
    venv.close()
