"""benchmarks/pedal_response.py: the real return of a held pedal against the env driven directly, the imagined one
against its sum written out, the speed probe against known linear maps and the env's own speeds, and bad input."""

import dataclasses
import importlib
import os
import types

import numpy as np
import pytest
import torch
from torch import nn

import pedal_response
from conftest import TINY_RUN
import utils.checkpoint as ckpt
from utils import make_vec_env
from utils.run import env_kwargs


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


def with_memory(agent, drive):
    """drive()'s result and the previous action the agent remembered at each of its decisions (None at the first)."""
    seen, act = [], agent.act

    def recording(obs, state, *rest):
        seen.append(None if state is None else state[2].clone())
        return act(obs, state, *rest)

    agent.act = recording
    try:
        return drive(), seen
    finally:
        del agent.act


def test_a_held_pedal_drives_the_env_as_the_same_actions_do_directly(trained):
    """From rest, a pedal at or below 0 leaves the car standing whatever the steering: its per-decision rewards are
    those of the env stepped directly with no action, decision by decision (action_repeat env steps each). Full gas
    moves the car onto new tiles; the first `after` decisions are kept as a replay stores them."""
    script, agent, args, _ = trained
    envs = make_vec_env(args.env_id, 1, None, **env_kwargs(args, args.dead_zone_end))
    try:
        held_frames, held_actions, standing, out, speed = pedal_response.drive(agent, args, envs, 10_200, 0, 0.0, 40)
        envs.seed(10_200)
        envs.reset()
        direct = [sum(float(envs.step(np.zeros((1, 2), np.float32))[1][0]) for _ in range(args.action_repeat))
                  for _ in range(40)]  # fmt: skip
        np.testing.assert_allclose(standing, direct, atol=1e-6)
        assert not out and len(standing) == 40 and speed < 0.01  # at rest all along
        assert len(held_frames) == len(held_actions) == 41 and np.all(held_actions[1:, 1] == 0.0)  # the held part's too
        _, _, driving, _, speed = pedal_response.drive(agent, args, envs, 10_200, 0, 1.0, 40)
        assert (driving > 0).sum() > (standing > 0).sum() + 2  # new tiles (1000/N each) before it leaves the road
        assert speed > 0.0
        frames, actions, _, _, _ = pedal_response.drive(agent, args, envs, 10_200, 5, None, 40)
        assert frames.shape == (6, args.image_size, args.image_size, 3) and actions.shape == (6, 2)
        assert not actions[0].any() and actions[1:].any()  # the action that led to each frame; none to the first
        _, seen = with_memory(agent, lambda: pedal_response.drive(agent, args, envs, 10_200, 2, -0.7, 4))
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
    last = wm.reward.net[-1]  # the reward head itself, its output layer set to a constant mean 2.0
    monkeypatch.setattr(last, "weight", nn.Parameter(torch.zeros_like(last.weight)))
    monkeypatch.setattr(last, "bias", nn.Parameter(torch.tensor([2.0, 0.0])))
    monkeypatch.setattr(wm, "cont", _Constant([0.0]))
    real_forward = agent.actor.forward
    monkeypatch.setattr(agent.actor, "forward", lambda features: (torch.tensor([0.37, 0.9]).expand(len(features), 2),
                                                                  real_forward(features)[1]))  # mean steering 0.37
    seen, step = [], wm.imagine_step

    def recording(state, z, action, sample=True):
        seen.append(action.clone())
        return step(state, z, action, sample)

    monkeypatch.setattr(wm, "imagine_step", recording)
    gamma, horizon = 0.9, 7
    imagined, features = pedal_response.imagine(script, agent, frames, actions, -0.4, horizon, 4, gamma)
    assert imagined == pytest.approx(2.0 * sum((0.5 * gamma) ** k for k in range(horizon)), rel=1e-5)
    assert len(seen) == horizon and all(torch.all(a[:, 1] == -0.4) for a in seen)
    assert all(a.shape == (4, 2) and torch.all(a[:, 0] == 0.37) for a in seen)  # the actor's mean steering
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
    with pytest.raises(ValueError, match=r"--probe-tracks must be 0 \(no probe\) or >= 3 .*, got 2"):
        pedal_response.pedal_response(latest, probe_tracks=2)
    with pytest.raises(ValueError, match=r"the probe needs at least 2 races to fit and 1 to score, got 1 and 1"):
        pedal_response.fit_speed_probe([(np.ones((3, 2)), np.ones(3))], [(np.ones((3, 2)), np.ones(3))])
    with pytest.raises(ValueError, match=r"the env's info has no 'speed' \(keys: \['crashed'\]\)"):
        pedal_response.car_speed({"crashed": False})
    ckpt.export_policy(script, latest, str(tmp_path / "policy.pt"))
    with pytest.raises(ValueError, match=r"policy\.pt: an acting-only export has no reward or continue head"):
        pedal_response.pedal_response(str(tmp_path / "policy.pt"))
    # the command line says it in one line, no traceback: a bad value, and a car out before --after (the tiny
    # agent's races end within 100 decisions)
    for argv, message in [([latest, "--horizon", "0"], "--horizon must be >= 1, got 0"),
                          ([latest, "--after", "150", "--tracks", "1", "--probe-tracks", "0"],
                           "track 10200: the car was out after")]:  # fmt: skip
        with pytest.raises(SystemExit, match=r"^pedal_response\.py: error: ") as exit_info:
            pedal_response.main(argv)
        assert message in str(exit_info.value) and "\n" not in str(exit_info.value)


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
    """Speeds linear in the features (plus a constant feature and a little noise): the probe predicts held-out
    speeds almost exactly; speeds unrelated to the features score R^2 near 0 or below."""
    rng = np.random.default_rng(0)
    weights = rng.normal(size=8)

    def race(n, related=True):
        features = np.concatenate([rng.normal(3.0, 2.0, size=(n, 8)), np.ones((n, 1))], 1)
        speeds = 40.0 + features[:, :8] @ weights + rng.normal(0, 0.01, n) if related else rng.normal(size=n)
        return features, speeds

    probe = pedal_response.fit_speed_probe([race(300), race(300)], [race(300)])
    assert probe.r2 > 0.999 and probe.rmse < 0.05
    held, speeds = race(50)
    np.testing.assert_allclose(probe(held), speeds, atol=0.2)
    unrelated = pedal_response.fit_speed_probe([race(300, False), race(300, False)], [race(300, False)])
    assert unrelated.r2 < 0.05


def test_the_probe_chooses_its_penalty_by_leave_one_race_out_error():
    """572 features (z||h of the paper's sizes), 3 fitted races of 200 frames, speed = 30 + 10 x_0 + N(0, 2^2) (the
    best R^2 any probe can reach: 100 / 104 = 0.96). Each leave-one-out fit has fewer frames than features, so the
    smallest penalty overfits (R^2 below 0 on the held-out races) and the largest shrinks the slope to nothing;
    the penalty chosen between them reads most of it."""
    rng = np.random.default_rng(1)

    def race(n=200):
        features = rng.normal(size=(n, 572))
        return features, 30.0 + 10.0 * features[:, 0] + rng.normal(0, 2.0, n)

    fitted, held = [race() for _ in range(3)], [race(), race()]
    probe = pedal_response.fit_speed_probe(fitted, held)
    ends = [pedal_response.fit_speed_probe(fitted, held, ridges=(r,)).r2 for r in (1e-4, 100.0)]
    assert probe.r2 > 0.7 and max(ends) < 0.1 and probe.ridge not in (1e-4, 100.0)


def test_a_unit_almost_constant_in_the_fitted_races_cannot_blow_up_a_reading():
    """A feature that barely moves in the fitted races (std 1e-9, like a unit at a fixed point of the policy's
    states) and is 1 in a new state: the reading stays near the one without it (its scale is floored at 1e-3 of the
    median feature's; standardised by its own std the 1 would be a 1e9-sigma input)."""
    rng = np.random.default_rng(4)

    def race(n=300):
        features = np.concatenate([rng.normal(size=(n, 5)), rng.normal(0, 1e-9, size=(n, 1))], 1)
        return features, 30.0 + 5.0 * features[:, 0] + rng.normal(0, 1.0, n)

    probe = pedal_response.fit_speed_probe([race(), race()], [race()])
    state = np.zeros(6)
    moved = state.copy()
    moved[5] = 1.0
    assert abs(float(probe(moved)) - float(probe(state))) < 1.0
    constant = [(np.concatenate([np.zeros((300, 10)), f], 1), v) for f, v in (race(), race(), race())]
    probe = pedal_response.fit_speed_probe(constant[:2], constant[2:])  # most features constant: the median is 0
    state = np.zeros(16)
    moved = state.copy()
    moved[15] = 1.0
    assert abs(float(probe(moved)) - float(probe(state))) < 1.0


def test_the_time_baseline_reads_a_speed_that_only_follows_the_clock():
    clock = [30.0 * (1 - np.exp(-np.arange(n) / 40.0)) for n in (200, 160, 180)]
    assert pedal_response.time_baseline_r2(clock[:2], clock[2:]) > 0.99
    rng = np.random.default_rng(2)
    noise = [rng.normal(size=n) for n in (200, 160, 180)]
    assert pedal_response.time_baseline_r2(noise[:2], noise[2:]) < 0.05
    assert np.isnan(pedal_response.time_baseline_r2([np.zeros(1), np.zeros(1)], noise[2:]))  # 2 frames for a cubic


def test_speed_probe_pairs_each_frame_with_its_speed_and_splits_by_race(monkeypatch):
    """Stand-in races whose speeds are random and whose first h unit holds the speed of its frame (z: noise): a probe
    that pairs a frame with its own speed reads it (R^2 1 from h, about 0 from z); a frame paired with a neighbour's
    speed would read noise. The first 2 * 4 // 3 = 2 races are fitted, the other 2 scored (their frames)."""
    rng = np.random.default_rng(3)
    latent, lengths = 4, {20: 50, 21: 70, 22: 60, 23: 40}
    races = {}
    for track, n in lengths.items():
        speeds = np.concatenate([[0.0], rng.uniform(0, 80, n - 1)])
        features = rng.normal(size=(n, latent + 6))
        features[:, latent] = speeds
        races[track] = (np.zeros((n, 1)), np.zeros((n, 2)), speeds, features)

    monkeypatch.setattr(pedal_response, "drive_race", lambda agent, args, envs, track: races[track][:3])
    monkeypatch.setattr(pedal_response, "posterior_features",
                        lambda agent, frames, actions: next(r[3] for r in races.values() if r[0] is frames))
    probe, summary = pedal_response.speed_probe(None, types.SimpleNamespace(latent_size=latent), None, 20, 4)
    assert summary["probe_r2_zh"] > 0.999 and summary["probe_r2_h"] > 0.999 and summary["probe_r2_z"] < 0.1
    assert summary["probe_fitted"] == 50 + 70 and summary["probe_held"] == 60 + 40
    np.testing.assert_allclose(probe(races[23][3]), races[23][2], atol=0.5)


def test_a_race_for_the_probe_holds_random_pedals_and_records_the_envs_own_speeds(trained):
    """drive_race's speeds are the env's `speed` (0 at the reset, then after each decision) when the same actions
    step it directly; its pedal is held for stretches of 8..48 decisions (the last one may end with the race) at
    values in [-1, 1], the same for the same track; the first action is zero."""
    script, agent, args, _ = trained
    args = dataclasses.replace(args, max_steps=400)
    envs = make_vec_env(args.env_id, 1, None, **env_kwargs(args, args.dead_zone_end))
    try:
        frames, actions, speeds = pedal_response.drive_race(agent, args, envs, 10_201)
        assert len(frames) == len(actions) == len(speeds) and not actions[0].any() and speeds[0] == 0.0
        envs.seed(10_201)
        envs.reset()
        direct = [0.0]
        for action in actions[1:]:
            for _ in range(args.action_repeat):
                infos = envs.step(action[None])[3]
            direct.append(infos[0]["speed"])
        np.testing.assert_allclose(speeds, direct, rtol=1e-6)
        pedals = actions[1:, 1]
        changes = np.flatnonzero(np.diff(pedals)) + 1
        stretches = np.diff(np.concatenate([[0], changes, [len(pedals)]]))
        assert len(stretches) >= 2 and np.all((stretches[:-1] >= 8) & (stretches[:-1] <= 48)) and stretches[-1] <= 48
        assert np.all(np.abs(pedals) <= 1) and np.ptp(speeds) > 0
        (_, again, _), seen = with_memory(agent, lambda: pedal_response.drive_race(agent, args, envs, 10_201))
        np.testing.assert_array_equal(again[:, 1], actions[:, 1])
        held = [float(prev[0, 1]) for prev in seen[1:]]  # its memory holds the pedal it held, not its own
        np.testing.assert_allclose(held, actions[1 : len(held) + 1, 1], rtol=1e-6)
    finally:
        envs.close()


def test_the_probe_adds_speeds_and_leaves_the_returns_as_they_were(trained):
    """With probe races the rows carry the speeds and the probe's summary; the returns, the decisions and the outs
    are those of a run without the probe (it draws on the same seeds). From rest, pedal 0 leaves the car standing
    and full gas moves it; where the pedal is first held (the race's first frame) the car stands."""
    _, _, _, latest = trained
    plain = pedal_response.pedal_response(latest, tracks=1, pedals=(0.0, 1.0), after=(0,), samples=2, horizon=3)
    probed = pedal_response.pedal_response(latest, tracks=1, pedals=(0.0, 1.0), after=(0,), samples=2, horizon=3,
                                           probe_tracks=3)  # fmt: skip
    summary = {"probe_r2_zh", "probe_r2_h", "probe_r2_z", "probe_r2_time", "probe_rmse", "probe_ridge",
               "probe_fitted", "probe_held"}  # fmt: skip
    for row, with_probe in zip(plain, probed, strict=True):
        assert {k: with_probe[k] for k in row} == row
        assert set(with_probe) - set(row) == set(pedal_response.SPEEDS) | summary
        assert with_probe["start_speed"] == 0.0 and not with_probe["out"]
    assert probed[0]["real_speed"] < 0.01 < probed[1]["real_speed"]
    assert len({tuple(r[k] for k in sorted(summary)) for r in probed}) == 1
    assert all(np.isfinite(r[k]) for r in probed for k in pedal_response.SPEEDS)


def test_the_table_gives_the_speeds_and_the_probe_with_it():
    summary = dict(probe_r2_zh=0.91, probe_r2_h=0.85, probe_r2_z=0.4, probe_r2_time=0.3, probe_rmse=6.25,
                   probe_ridge=0.001, probe_fitted=900, probe_held=450)  # fmt: skip
    rows = [{"track": t, "after": 0, "pedal": p, "real": 1.0, "imagined": 2.0, "out": out, "decisions": 3,
             "start_speed": 0.0, "start_speed_probed": 1.0 + t, "real_speed": None if out else rs,
             "real_speed_probed": None if out else rs - 2.0, "imagined_speed": None if out else 30.0 + t, **summary}
            for t, out in ((1, False), (2, False), (3, True)) for p, rs in ((0.0, 0.0), (1.0, 40.0))]  # fmt: skip
    rows += [{**rows[0], "track": t, "pedal": 0.5, "out": True, "real_speed": None, "real_speed_probed": None,
              "imagined_speed": None} for t in (1, 2, 3)]  # a pedal out on every track: no speed, left out of the range
    text = pedal_response.table(rows, "x.pt")
    assert "| 0 | +0.50 | 1.00 | 2.00 | 3 | nan | nan | nan |" in text
    assert "| 0 | +1.00 | 1.00 | 2.00 | 1 | 40.0 | 38.0 | 31.5 |" in text  # track 3 (out) left out of the speeds
    assert ("after 0: speed range over the 2 pedals with a car still in, imagined 0.0 against real 40.0 (both read by "
            "the probe; the env's: 40.0)") in text
    assert "after 0: speed where the pedal is first held 0.0, the probe reads 3.0" in text
    assert ("speed probe (ridge 0.001 per sample; fitted on 900 frames, scored on 450 frames): held-out R^2 z||h "
            "0.910, h 0.850, z 0.400; time alone 0.300; RMSE 6.2") in text
    edge = pedal_response.table([{**r, "probe_ridge": pedal_response.PROBE_RIDGES[-1]} for r in rows], "x.pt")
    assert "speed probe (ridge 100 per sample at the grid's edge; fitted on 900 frames" in edge
