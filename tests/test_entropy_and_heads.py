"""Options screened to make the agents race (issue 40): an adaptive entropy weight, fixed-sigma heads, the paper
authors' normalisation mix, and a CPU-time budget. Each is off by default (tests/test_reference_runs.py holds the
default to what it computed before); here each does what it says when on."""

import csv
import math
import os

import pytest
import torch
from conftest import TINY, ColumnHead, ConstantHead, random_batch, tiny_args
from torch import nn


def one_update(agent, seed=0):
    torch.manual_seed(seed)
    return agent.update(random_batch())


@pytest.mark.parametrize("target, direction", [(5.0, +1), (-5.0, -1)])
def test_the_entropy_weight_moves_toward_its_target_by_adams_first_step(script, target, direction):
    """SAC's temperature: below its target entropy alpha rises, above it falls. Adam's first step moves log alpha by
    its learning rate whatever the gradient's size, so one update moves it by exactly +-lr."""
    agent = script.Agent(tiny_args(script, entropy_target=target, entropy_coef=0.5, entropy_lr=0.01))
    metrics = one_update(agent)
    assert metrics["alpha"] == pytest.approx(0.5)  # the update's returns used alpha as it was
    assert agent.log_alpha.item() == pytest.approx(math.log(0.5) + direction * 0.01, abs=1e-6)
    other = script.Agent(tiny_args(script, entropy_target=target, entropy_coef=0.5, entropy_lr=0.01))
    other.load_state_dict(agent.state_dict())  # alpha and its optimiser are saved with the agent
    assert other.log_alpha.item() == agent.log_alpha.item()
    assert other.alpha_optimizer.state_dict()["state"][0]["step"] == 1


def test_the_entropy_weight_scales_the_entropy_part_of_the_returns(script, monkeypatch):
    """lambda_returns gets exp(log alpha) under --entropy-target, --entropy-coef without it."""
    seen = []
    real = script.lambda_returns

    def spy(*args):
        seen.append(float(args[-1]))
        return real(*args)

    monkeypatch.setattr(script, "lambda_returns", spy)
    agent = script.Agent(tiny_args(script, entropy_target=0.0, entropy_coef=0.25))
    with torch.no_grad():
        agent.log_alpha.fill_(math.log(0.125))
    one_update(agent)
    one_update(script.Agent(tiny_args(script, entropy_coef=0.25)))
    assert seen == [pytest.approx(0.125), 0.25]


def test_without_a_target_the_agent_has_no_alpha_state(script):
    agent = script.Agent(tiny_args(script))
    assert agent.log_alpha is None and "log_alpha" not in agent.state_dict()
    assert "alpha" not in one_update(agent)


def test_a_fixed_head_sigma_makes_the_reward_and_critic_losses_squared_errors(script):
    """--head-sigma 1: the reward NLL is (r - mu)^2 / 2 + log(2 pi) / 2 of the head's mean, whatever its second
    output says; the critic's sigma is 1 too."""
    agent = script.Agent(tiny_args(script, head_sigma=1.0))
    batch = random_batch()
    agent._set_training(False)
    with torch.no_grad():
        nn.init.constant_(agent.world_model.reward.net[-1].bias, 3.0)  # a large raw sigma: ignored
        _, metrics, post = agent.world_model_loss(
            torch.as_tensor(batch["obs"]), torch.as_tensor(batch["action"]), torch.as_tensor(batch["reward"]),
            torch.as_tensor(batch["is_first"]), torch.zeros(3, 8),
        )  # fmt: skip
        features = torch.cat([post["z"], post["h"]], -1)
        mean = agent.world_model.reward(features)[..., 0]
        expected = 0.5 * (torch.as_tensor(batch["reward"]) - mean).pow(2) + 0.5 * math.log(2 * math.pi)
        torch.testing.assert_close(metrics["reward"], expected.mean(), rtol=1e-5, atol=1e-6)
        _, std = agent.critic(features)
        assert torch.equal(std, torch.ones_like(std))
        learned = script.Agent(tiny_args(script))
        assert not torch.equal(learned.critic(features)[1], torch.ones_like(std))


def test_the_mixed_norm_is_batchnorm_in_the_convolutions_and_layernorm_elsewhere(script):
    agent = script.Agent(tiny_args(script, norm="mixed"))
    wm = agent.world_model
    norms = (nn.BatchNorm1d, nn.BatchNorm2d, nn.LayerNorm, nn.GroupNorm)
    kinds = lambda module: {type(m) for m in module.modules() if isinstance(m, norms)}  # noqa: E731
    assert kinds(wm.encoder) == kinds(wm.decoder) == {nn.BatchNorm2d}
    for module in (wm.recurrent_input, wm.representation, wm.transition, wm.reward, wm.cont, agent.actor):
        assert kinds(module) == {nn.LayerNorm}


def test_a_cpu_hour_budget_counts_every_sitting_and_ends_the_run(script, tmp_path):
    """progress.csv logs the run's CPU time after every race and the checkpoint keeps it; a resumed run adds its own
    to it, so a budget the earlier sittings used up ends the run before another race."""
    run = dict(TINY, stage="single", max_steps=30, train_steps_per_episode=1, prefill_episodes=1,
               replay_capacity=500, eval_every=0, video_every=0, torch_threads=1)  # fmt: skip
    run_dir = script.main(script.Args(**run, total_episodes=2, runs_dir=str(tmp_path)))
    first = script.load_checkpoint(f"{run_dir}/checkpoints/latest.pt")["extra"]["cpu_seconds"]
    with open(os.path.join(run_dir, "progress.csv")) as f:
        hours = [float(row["charts/cpu_hours"]) for row in csv.DictReader(f)]
    assert len(hours) == 2 and 0 < hours[0] < hours[1] <= first / 3600
    script.main(script.Args(resume=run_dir, total_episodes=5, cpu_hours_limit=first / 3600),
                {"total_episodes", "cpu_hours_limit"})  # fmt: skip
    after = script.load_checkpoint(f"{run_dir}/checkpoints/latest.pt")
    assert after["counters"]["episode"] == 2 and after["extra"]["cpu_seconds"] > first
    script.main(script.Args(resume=run_dir, total_episodes=3, cpu_hours_limit=0.0),
                {"total_episodes", "cpu_hours_limit"})  # fmt: skip
    assert script.load_checkpoint(f"{run_dir}/checkpoints/latest.pt")["counters"]["episode"] == 3


@pytest.mark.parametrize("penalty", [None, 0.0, 2.0])
def test_the_action_penalty_reweighs_the_extreme_action_term_of_the_bonus(script, monkeypatch, penalty):
    """A one-step imagination fixed by hand: reward 3, value 4, gamma 0.5, continue 1, log pi -1, both sampled action
    dimensions 0.5. The bonus is -alpha log pi = 0.25; --action-penalty beta replaces alpha on the extreme-action
    term, 2 * -log(1 - tanh(0.5)^2) = 0.48046, so R = 3 + 0.25 + (0.25 - beta) 0.48046 + 0.5 * 4."""

    agent = script.Agent(tiny_args(script, entropy_coef=0.25, action_penalty=penalty, gamma=0.5, imagination_horizon=1))
    size = TINY["latent_size"] + TINY["deter_size"]
    features = torch.zeros(2, 1, size)
    features[1, :, 0], features[1, :, 1] = 3.0, 4.0
    log_pi = torch.full((1, 1), -1.0)
    samples = torch.full((1, 1, 2), 0.5)
    monkeypatch.setattr(script, "imagine_rollout", lambda *a: (features, log_pi, samples, torch.ones(1, 1, 2)))
    monkeypatch.setattr(agent, "start_states", lambda post, terminated: (None, None, None, torch.ones(1)))
    agent.world_model.reward = ColumnHead(0, pair=False)
    agent.world_model.cont = ConstantHead(100.0)
    agent.targets["critic"] = ColumnHead(1, pair=True)
    post = {"z": torch.randn(1, 2, TINY["latent_size"]), "h": torch.randn(1, 2, TINY["deter_size"])}  # 2: BatchNorm
    _, _, metrics = agent.behaviour_losses(post, torch.zeros(1, 1))
    term = 2 * -math.log(1 - math.tanh(0.5) ** 2 + 1e-6)
    beta = 0.25 if penalty is None else penalty
    expected = 3.0 + 0.25 + (0.25 - beta) * term + 0.5 * 4.0
    assert metrics["imagined_return"].item() == pytest.approx(expected, rel=1e-6)
