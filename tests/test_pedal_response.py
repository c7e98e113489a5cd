"""benchmarks/pedal_response.py: the real return of a held pedal against the env driven directly, the imagined one
against its sum written out, the speed probe against known linear maps and the env's own speeds, and bad input."""

import dataclasses
import importlib
import os

import numpy as np
import pytest
import torch
from torch import nn

import pedal_response
from conftest import TINY_RUN
import utils.checkpoint as ckpt
from utils import make_vec_env


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny trained single-car GRU agent, its Args (races of 200 env steps) and its checkpoint."""
    script = importlib.import_module("dreamer_gru")
    runs = tmp_path_factory.mktemp("runs")
    run_dir = script.main(script.Args(stage="single", runs_dir=str(runs), action_repeat=2, **TINY_RUN))
    latest = os.path.join(run_dir, "checkpoints", "latest.pt")
    args = dataclasses.replace(script.args_from_checkpoint(torch.load(latest, weights_only=True), latest,
                                                           num_agents=1), max_steps=200)  # fmt: skip
    return script, script.agent_from_checkpoint(latest, 0), args, latest


def test_a_held_pedal_drives_the_env_as_the_same_actions_do_directly(trained):
    """From rest, a pedal at or below 0 leaves the car standing whatever the steering: its per-decision rewards are
    those of the env stepped directly with no action, decision by decision (action_repeat env steps each). Full gas
    moves the car onto new tiles; the first `after` decisions are kept as a replay stores them."""
    script, agent, args, _ = trained
    envs = make_vec_env(args.env_id, 1, None, **script.env_kwargs(args, args.dead_zone_end))
    try:
        _, _, standing, out, speed = pedal_response.drive(agent, args, envs, 10_200, 0, 0.0, 40)
        envs.seed(10_200)
        envs.reset()
        direct = [sum(float(envs.step(np.zeros((1, 2), np.float32))[1][0]) for _ in range(args.action_repeat))
                  for _ in range(40)]  # fmt: skip
        np.testing.assert_allclose(standing, direct, atol=1e-6)
        assert not out and len(standing) == 40 and speed < 0.01  # at rest all along
        _, _, driving, _, speed = pedal_response.drive(agent, args, envs, 10_200, 0, 1.0, 40)
        assert (driving > 0).sum() > (standing > 0).sum() + 2  # new tiles (1000/N each) before it leaves the road
        assert speed > 0.0
        frames, actions, _, _, _ = pedal_response.drive(agent, args, envs, 10_200, 5, None, 40)
        assert frames.shape == (6, args.image_size, args.image_size, 3) and actions.shape == (6, 2)
        assert not actions[0].any() and actions[1:].any()  # the action that led to each frame; none to the first
        seen = []
        act = agent.act
        def recording(obs, state, *rest):
            seen.append(None if state is None else state[2].clone())
            return act(obs, state, *rest)

        agent.act = recording
        try:
            pedal_response.drive(agent, args, envs, 10_200, 2, -0.7, 4)
        finally:
            del agent.act
        assert all(float(prev[0, 1]) == pytest.approx(-0.7) for prev in seen[3:])  # its memory holds the held pedal
        with pytest.raises(pedal_response.CarOut, match=r"track 10200: the car was out after \d+ decisions, before"):
            pedal_response.drive(agent, args, envs, 10_200, 150, None, 4)  # (200 env steps: at most 100 decisions)
    finally:
        envs.close()


class _Constant(nn.Module):
    def __init__(self, values):
        super().__init__()
        self.values = torch.tensor(values)

    def forward(self, x):
        return self.values.expand(len(x), -1)


def test_imagined_return_is_the_discounted_sum_of_the_heads_and_holds_the_pedal(trained, monkeypatch):
    """With a reward head that predicts 2.0 and a continue head at 0.5, the imagined return is
    2 * sum_{k<H} (0.5 gamma)^k (training's discount_weights); every imagined action carries the held pedal and the
    actor's mean steering."""
    script, agent, args, _ = trained
    frames = np.zeros((3, args.image_size, args.image_size, 3), np.uint8)
    actions = np.zeros((3, 2), np.float32)
    wm = agent.world_model
    monkeypatch.setattr(wm, "reward", _Constant([2.0, 0.0]))
    monkeypatch.setattr(wm, "cont", _Constant([0.0]))
    seen, step = [], wm.imagine_step

    def recording(state, z, action, sample=True):
        seen.append(action.clone())
        return step(state, z, action, sample)

    monkeypatch.setattr(wm, "imagine_step", recording)
    gamma, horizon = 0.9, 7
    imagined, features = pedal_response.imagine(script, agent, frames, actions, -0.4, horizon, 4, gamma)
    assert imagined == pytest.approx(2.0 * sum((0.5 * gamma) ** k for k in range(horizon)), rel=1e-5)
    assert len(seen) == horizon and all(torch.all(a[:, 1] == -0.4) for a in seen)
    assert all(a.shape == (4, 2) and torch.all(a[:, 0].abs() < 1) for a in seen)  # the actor's tanh mean
    assert features.shape == (4, args.latent_size + args.deter_size)
    ends = []  # the features are the last imagined state's z||h, one row per path

    def keeping(state, z, action, sample=True):
        ends.append(step(state, z, action, sample))
        return ends[-1]

    monkeypatch.setattr(wm, "imagine_step", keeping)
    _, features = pedal_response.imagine(script, agent, frames, actions, -0.4, horizon, 4, gamma)
    _, h, z = ends[-1]
    np.testing.assert_array_equal(features, torch.cat([z, h], -1).numpy())


def test_bad_input_is_refused_naming_what_was_wrong(trained, tmp_path):
    script, _, _, latest = trained
    with pytest.raises(ValueError, match=r"--pedals must lie in \[-1, 1\], got \[0.0, 1.5\]"):
        pedal_response.pedal_response(latest, pedals=(0.0, 1.5))
    with pytest.raises(ValueError, match=r"--after must be >= 0"):
        pedal_response.pedal_response(latest, after=(-1,))
    with pytest.raises(ValueError, match=r"--horizon must be >= 1, got 0"):
        pedal_response.pedal_response(latest, horizon=0)
    with pytest.raises(ValueError, match=r"--probe-tracks must be 0 \(no probe\) or >= 2 .*, got 1"):
        pedal_response.pedal_response(latest, probe_tracks=1)
    with pytest.raises(ValueError, match=r"the env's info has no 'speed' \(keys: \['crashed'\]\)"):
        pedal_response.car_speed({"crashed": False})
    ckpt.export_policy(script, latest, str(tmp_path / "policy.pt"))
    with pytest.raises(ValueError, match=r"policy\.pt: an acting-only export has no reward or continue head"):
        pedal_response.pedal_response(str(tmp_path / "policy.pt"))


def test_the_table_gives_each_starts_range_over_the_pedals():
    rows = [{"track": t, "after": 0, "pedal": p, "real": r, "imagined": i, "out": False, "decisions": 3}
            for t in (1, 2) for p, r, i in ((-1.0, -1.0, 40.0), (1.0, 30.0 + t, 41.0))]  # fmt: skip
    text = pedal_response.table(rows, "x.pt")
    assert "| 0 | +1.00 | 31.50 | 41.00 | 0 |" in text
    assert "after 0: imagined range 1.00 against real 32.50" in text


def test_r_squared_by_hand():
    assert pedal_response.r_squared(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 4.0])) == pytest.approx(0.5)
    assert pedal_response.r_squared(np.array([1.0, 2.0, 3.0]), np.full(3, 2.0)) == pytest.approx(0.0)


def test_the_speed_probe_recovers_a_linear_map_and_scores_on_held_out_data():
    """Speeds that are a linear function of the features (plus a constant feature and a little noise): the probe
    predicts held-out speeds almost exactly; speeds unrelated to the features score R^2 near 0 or below."""
    rng = np.random.default_rng(0)
    weights = rng.normal(size=8)

    def data(n):
        features = np.concatenate([rng.normal(3.0, 2.0, size=(n, 8)), np.ones((n, 1))], 1)
        return features, 40.0 + features[:, :8] @ weights + rng.normal(0, 0.01, n)

    probe = pedal_response.fit_speed_probe(*data(600), *data(300))
    assert probe.r2 > 0.999 and probe.samples == 600
    held, speeds = data(50)
    np.testing.assert_allclose(probe(held), speeds, atol=0.2)
    features, _ = data(600)
    unrelated = pedal_response.fit_speed_probe(features, rng.normal(size=600), data(300)[0], rng.normal(size=300))
    assert unrelated.r2 < 0.05


def test_a_race_for_the_probe_records_the_envs_own_speeds(trained):
    """drive_race's speeds are the env's `speed` after each decision when the same actions step it directly; the
    frames are one more than the speeds (the first, at rest, has none) and the first action is zero."""
    script, agent, args, _ = trained
    envs = make_vec_env(args.env_id, 1, None, **script.env_kwargs(args, args.dead_zone_end))
    try:
        frames, actions, speeds = pedal_response.drive_race(agent, args, envs, 10_201)
        assert len(frames) == len(actions) == len(speeds) + 1 and not actions[0].any()
        envs.seed(10_201)
        envs.reset()
        direct = []
        for action in actions[1:]:
            for _ in range(args.action_repeat):
                infos = envs.step(action[None])[3]
            direct.append(infos[0]["speed"])
        np.testing.assert_allclose(speeds, direct, rtol=1e-6)
        assert np.ptp(speeds) > 0
    finally:
        envs.close()


def test_the_probe_adds_speeds_and_leaves_the_returns_as_they_were(trained):
    """With probe races the rows carry the real and the probed imagined speed and the probe's R^2; the returns,
    the decisions and the outs are those of a run without the probe (it draws on the same seeds)."""
    _, _, _, latest = trained
    plain = pedal_response.pedal_response(latest, tracks=1, pedals=(0.0, 1.0), after=(0,), samples=2, horizon=3)
    probed = pedal_response.pedal_response(latest, tracks=1, pedals=(0.0, 1.0), after=(0,), samples=2, horizon=3,
                                           probe_tracks=3)  # fmt: skip
    for row, with_probe in zip(plain, probed, strict=True):
        assert {k: with_probe[k] for k in row} == row
        assert set(with_probe) - set(row) == {"real_speed", "imagined_speed", "probe_r2"}
    assert probed[0]["real_speed"] < 0.01 < probed[1]["real_speed"]  # pedal 0 from rest; full gas
    assert len({r["probe_r2"] for r in probed}) == 1 and np.isfinite(probed[0]["imagined_speed"])


def test_the_table_gives_the_speeds_and_the_probe_with_it():
    rows = [{"track": t, "after": 0, "pedal": p, "real": 1.0, "imagined": 2.0, "out": False, "decisions": 3,
             "real_speed": rs, "imagined_speed": 30.0 + t, "probe_r2": 0.91}
            for t in (1, 2) for p, rs in ((0.0, 0.0), (1.0, 40.0))]  # fmt: skip
    text = pedal_response.table(rows, "x.pt")
    assert "| 0 | +1.00 | 1.00 | 2.00 | 0 | 40.0 | 31.5 |" in text
    assert "after 0: speed range imagined 0.0 against real 40.0" in text
    assert "speed probe: held-out R^2 0.910" in text
