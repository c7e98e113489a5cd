"""benchmarks/calibration.py: the realised returns the critic and the imagination are set against, and a
calibration of a tiny trained agent on the episode it drives."""

import importlib
import math
import os
import types

import numpy as np
import pytest
import torch

import calibration
import learning
from conftest import TINY_RUN
import utils.checkpoint as ckpt


def test_realised_and_horizon_returns_match_their_sums_written_out():
    """G_t and J_t of --calibrate against the sums they stand for, term by term."""
    rng = np.random.default_rng(0)
    rewards, bonus, gamma, last = rng.normal(size=7), rng.normal(size=6), 0.9, 5.0
    for ended in (False, True):  # truncated (bootstrapped with the last value) or terminated (nothing after)
        terminated = np.array([False] * 6 + [ended])
        expected = [
            sum(gamma**k * (rewards[t + k + 1] + bonus[t + k]) for k in range(6 - t))
            + (not ended) * gamma ** (6 - t) * last
            for t in range(6)
        ]  # fmt: skip
        np.testing.assert_allclose(calibration.realised_returns(rewards, terminated, bonus, last, gamma), expected)
        horizon = calibration.horizon_task_returns(rewards, terminated, gamma, 4)
        for t in range(6):
            if t + 4 <= 6 or ended:
                assert horizon[t] == pytest.approx(sum(gamma**k * rewards[t + 1 + k] for k in range(min(4, 6 - t))))
            else:  # truncated before t + H: the rewards there are unknown
                assert np.isnan(horizon[t])


class ZeroLogit(torch.nn.Module):
    """A continue head whose logit is 0 everywhere (probability 0.5)."""

    def forward(self, x):
        return torch.zeros(*x.shape[:-1], 1)


def test_calibrate_measures_the_real_episode_the_agent_drives(tmp_path, monkeypatch):
    """With gamma 1 and a horizon as long as the episode, the real task return from the first frame is the race's
    return, which the evaluation of the same agent with the same sampled actions measures independently; the
    critic's value is the mean of V(s_0..s_{T-1}) and the realised return the mean of the sums written out (log pi
    fixed at -1, so each decision's bonus is alpha); the imagination's return is the heads' discounted sum; an
    acting-only export, which has no critic, is refused naming the file."""
    script = importlib.import_module("dreamer_gru")
    run_dir = script.main(script.Args(stage="single", runs_dir=str(tmp_path), gamma=1.0, action_repeat=2, **TINY_RUN))
    latest = os.path.join(run_dir, "checkpoints", "latest.pt")
    row = calibration.calibrate_checkpoint(latest, 10_100, 1)
    assert row["horizon"] == TINY_RUN["imagination_horizon"] and row["starts"] == 15  # 30 env steps, repeat 2
    assert row["horizon_starts"] == row["starts"] - row["horizon"] + 1  # truncated: the last starts lack H rewards
    assert row["bootstrap_weight"] == 1.0  # truncated at gamma 1: every G_t carries all of V(s_T)
    assert row["eliminations"] == 0 and row["elimination_reasons"] == "" and np.isnan(row["terminal_reward"])
    assert all(np.isfinite(row[k]) for k in ("value", "realised_return", "imagined_task_return", "real_task_return"))
    monkeypatch.setattr(script, "policy_log_prob", lambda action, mean, std: -torch.ones(action.shape[:-1]))
    # a critic whose value moves from frame to frame (the tiny agent's barely does), so each frame's value counts
    monkeypatch.setattr(script.Critic, "dist", lambda self, features: types.SimpleNamespace(mean=features.sum(-1)))
    whole = calibration.calibrate_checkpoint(latest, 10_100, 1, horizon=row["starts"])
    reference = learning.policy_summary(latest, 10_100, 1, "stochastic")
    assert whole["horizon_starts"] == 1
    assert whole["real_task_return"] == pytest.approx(reference["eval_return"], abs=0.01)
    import evaluate  # the same drive and posterior draws, summed here by hand

    _, _, _, agent, envs = evaluate.single_car(latest)
    frames, actions, rewards, terminated = evaluate.sampled_episodes(agent, agent.args, envs, 10_100, 1)[0][0].arrays()
    post = calibration.posterior(agent, frames, actions)  # (the stream where calibrate_checkpoint's finds it)
    with torch.no_grad():
        values = agent.critic.dist(torch.cat([post["z"], post["h"]], -1)[0]).mean.numpy()
    last, alpha = len(rewards) - 1, float(agent.alpha())
    assert not terminated[-1]  # truncated: every G_t ends with V(s_T)
    realised = [rewards[t + 1:].sum() + (last - t) * alpha + values[-1] for t in range(last)]
    assert np.ptp(values) > 1 and whole["value"] == pytest.approx(values[:-1].mean(), abs=0.006)
    assert whole["realised_return"] == pytest.approx(np.mean(realised), abs=0.006)
    # the imagination's return and the reward head's sigma, with the heads pinned: reward mean 2 and raw sigma 0
    # (sigma softplus(0) + 0.1 = 0.793), continue logit 0 (probability 0.5): over H = 3 steps at gamma 1 the
    # imagined return is 2 (1 + 0.5 + 0.25) = 3.5 from every start
    single_car = evaluate.single_car

    def pinned_heads(path):
        loaded = single_car(path)
        last = loaded[3].world_model.reward.net[-1]
        with torch.no_grad():
            last.weight.zero_()
            last.bias.copy_(torch.tensor([2.0, 0.0]))
        loaded[3].world_model.cont = ZeroLogit()
        return loaded

    monkeypatch.setattr(evaluate, "single_car", pinned_heads)
    pinned = calibration.calibrate_checkpoint(latest, 10_100, 1)
    assert pinned["imagined_task_return"] == pytest.approx(3.5, abs=0.005)
    assert pinned["reward_sigma"] == pytest.approx(math.log(2) + 0.1, abs=0.0005)
    ckpt.export_policy(script, latest, str(tmp_path / "policy.pt"))
    with pytest.raises(ValueError, match=r"policy\.pt: an acting-only export has no critic"):
        calibration.calibrate_checkpoint(str(tmp_path / "policy.pt"))

