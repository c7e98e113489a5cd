"""Options screened to make the agents race (docs/sweeps.md): an adaptive entropy weight, fixed-sigma and two-hot
heads, the paper authors' normalisation mix, and a CPU-time budget. Each is off by default (tests/test_reference_runs.py
holds the default to what it computed before); here each does what it says when on."""

import csv
import math
import os

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import utils.run as run_tools
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


def test_the_entropy_alpha_weighs_is_minus_log_pi_plus_the_extreme_action_term_it_leaves_to_the_penalty(
    script, monkeypatch
):
    """--entropy-target with --action-penalty (the CPU preset): alpha weighs the Gaussian part of -log pi only, so
    its step reads -log pi plus the extreme-action term: log pi -1 and both sampled dimensions 0.5 (a one-step
    imagination fixed by hand) give 1 + 2 * -log(1 - tanh(0.5)^2) = 1.48046; without --action-penalty, 1."""
    agent = script.Agent(tiny_args(script, entropy_target=0.0, action_penalty=1.0, imagination_horizon=1))
    features = torch.zeros(2, 1, TINY["latent_size"] + TINY["deter_size"])
    *_, metrics = one_step_behaviour(script, agent, monkeypatch, features, samples=torch.full((1, 1, 2), 0.5))
    term = 2 * -math.log(1 - math.tanh(0.5) ** 2)
    assert metrics["alpha_entropy"].item() == pytest.approx(1 + term, rel=1e-5)
    # without --action-penalty (SAC alone) alpha weighs all of -log pi: its step reads -log pi, no term added
    agent = script.Agent(tiny_args(script, entropy_target=0.0, imagination_horizon=1))
    *_, metrics = one_step_behaviour(script, agent, monkeypatch, features, samples=torch.full((1, 1, 2), 0.5))
    assert metrics["alpha_entropy"].item() == pytest.approx(1.0, rel=1e-6)


@pytest.mark.parametrize("per_dimension, direction", [(0.6, -1), (0.8, +1)])
def test_the_entropy_target_is_per_action_dimension(script, monkeypatch, per_dimension, direction):
    """--entropy-target is in nats per action dimension: with 2 dimensions and an entropy of 1.5 nats, a target of
    0.6 (1.2 in all) is below it and alpha falls, 0.8 (1.6 in all) above it and alpha rises, by Adam's first step."""
    agent = script.Agent(tiny_args(script, entropy_target=per_dimension, entropy_coef=0.5, entropy_lr=0.01))
    real = agent.alpha_loss

    def entropy_of_one_and_a_half_nats(log_pi, raw_actions):
        return real(torch.full_like(log_pi, -1.5), raw_actions)

    monkeypatch.setattr(agent, "alpha_loss", entropy_of_one_and_a_half_nats)
    assert one_update(agent)["alpha_entropy"] == pytest.approx(1.5)
    assert agent.log_alpha.item() == pytest.approx(math.log(0.5) + direction * 0.01, abs=1e-6)


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


def test_a_fixed_head_sigma_makes_the_reward_and_critic_losses_squared_errors(script, monkeypatch):
    """--head-sigma 1: the reward NLL is (r - mu)^2 / 2 + log(2 pi) / 2 of the head's mean, whatever its second
    output says; the critic's sigma is 1 too, and its loss the squared error against a lambda-return worked by hand."""
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
        std = agent.critic.dist(features).std
        assert torch.equal(std, torch.ones_like(std))
        learned = script.Agent(tiny_args(script))
        assert not torch.equal(learned.critic.dist(features).std, torch.ones_like(std))
    # the critic's loss: the squared error of its mean against the lambda-return, here r_1 + gamma V(s_1) + alpha
    # (-log pi) = 3 + 0.5 * 4 + 0.25 * 1 = 5.25 on a one-step imagination fixed by hand (one start, weight 1)
    agent = script.Agent(tiny_args(script, head_sigma=1.0, entropy_coef=0.25, gamma=0.5, imagination_horizon=1))
    features = torch.zeros(2, 1, TINY["latent_size"] + TINY["deter_size"])
    features[0, :, 1] = 7.0
    features[1, :, 0], features[1, :, 1] = 3.0, 4.0
    _, critic_loss, _, metrics = one_step_behaviour(script, agent, monkeypatch, features)
    assert metrics["imagined_return"].item() == pytest.approx(5.25)
    value = agent.critic(features[0]).detach()[0, 0]  # the mean output; the second (a sigma) unused
    expected = 0.5 * (5.25 - value) ** 2 + 0.5 * math.log(2 * math.pi)
    torch.testing.assert_close(critic_loss.detach(), expected, rtol=1e-5, atol=1e-6)


def one_step_behaviour(script, agent, monkeypatch, features, samples=None):
    """agent.behaviour_losses on a one-step imagination fixed by hand: features (2, 1, F) are s_0 and s_1, the
    reward r_1 is column 0 of s_1 and the slow critic's value column 1 (of s_0 and s_1), continue 1, log pi -1, the
    sampled actions `samples`, one start that is not terminal."""
    monkeypatch.setattr(
        script, "imagine_rollout", lambda *a: (features, torch.full((1, 1), -1.0), samples, torch.ones(1, 1, 2))
    )
    monkeypatch.setattr(agent, "start_states", lambda post, terminated: (None, None, None, torch.ones(1)))
    agent.world_model.reward = ColumnHead(0)
    agent.world_model.cont = ConstantHead(100.0)
    agent.targets["critic"] = ColumnHead(1)
    post = {"z": torch.randn(1, 2, TINY["latent_size"]), "h": torch.randn(1, 2, TINY["deter_size"])}  # 2: BatchNorm
    return agent.behaviour_losses(post, torch.zeros(1, 1))


def hand_twohot(x: float, bins: np.ndarray) -> np.ndarray:
    """The two-hot encoding by hand, in float64: the two bins around x, weights by linear interpolation."""
    x = min(max(x, bins[0]), bins[-1])
    k = min(max(int(np.searchsorted(bins, x, side="left")), 1), len(bins) - 1)
    weights = np.zeros(len(bins))
    weights[k - 1], weights[k] = (bins[k] - x) / (bins[k] - bins[k - 1]), (x - bins[k - 1]) / (bins[k] - bins[k - 1])
    return weights


def symlog(x):
    """DreamerV3's symlog, by its definition: sign(x) ln(1 + |x|)."""
    return torch.sign(x) * torch.log(1 + x.abs())


def test_symexp_inverts_symlog_and_the_twohot_bins_are_evenly_spaced_in_symlog(script):
    x = torch.tensor([-1e6, -100.0, -1.0, 0.0, 0.5, 3.5, 1e6], dtype=torch.float64)
    torch.testing.assert_close(script.symexp(symlog(x)), x)
    assert script.symexp(torch.tensor([1.0, -2.0])).tolist() == pytest.approx([math.e - 1, -(math.e**2 - 1)])
    bins = script.twohot_bins()
    assert bins.shape == (255,) and bins[127].item() == 0.0 and torch.equal(bins, -bins.flip(0))
    spacing = symlog(bins.double()).diff()
    torch.testing.assert_close(spacing, torch.full((254,), 40 / 254, dtype=torch.float64), rtol=1e-4, atol=1e-5)
    assert bins[-1].item() == pytest.approx(math.exp(20) - 1, rel=1e-5)


@pytest.mark.parametrize("x", [-1e10, -100.0, -3.3, -1e-3, 0.0, 0.05, 3.5, 100.0, 1e10])
def test_the_twohot_encoding_is_the_two_neighbouring_bins_and_its_mean_is_the_value(script, x):
    bins = script.twohot_bins()
    encoding = script.twohot(torch.tensor([x]), bins)[0]
    expected = hand_twohot(x, bins.double().numpy())
    np.testing.assert_allclose(encoding.double().numpy(), expected, atol=1e-6)
    assert (encoding > 0).sum() <= 2 and encoding.sum().item() == pytest.approx(1.0)
    clipped = min(max(x, bins[0].item()), bins[-1].item())
    assert (encoding.double() @ bins.double()).item() == pytest.approx(clipped, rel=1e-6, abs=1e-6)


def test_the_twohot_nll_is_the_cross_entropy_with_the_encoding_and_uniform_logits_predict_zero(script):
    torch.manual_seed(0)
    bins = script.twohot_bins()
    logits = torch.randn(4, 255)
    targets = torch.tensor([-100.0, 0.0, 2.7, 40.0])
    dist = script.TwoHot(logits, bins)
    soft = torch.tensor(np.stack([hand_twohot(float(t), bins.double().numpy()) for t in targets]), dtype=torch.float32)
    torch.testing.assert_close(dist.nll(targets), F.cross_entropy(logits, soft, reduction="none"))
    torch.testing.assert_close(dist.mean, logits.softmax(-1).double() @ bins.double(), check_dtype=False)
    assert torch.equal(script.TwoHot(torch.zeros(3, 255), bins).mean, torch.zeros(3))  # exactly, not ~1e-2


def test_a_twohot_head_learns_the_mean_of_a_target_with_a_rare_minus_100(script):
    """Targets +3 with probability 0.95 and -100 with 0.05 at one input: the head's mean goes to their mean,
    0.95 * 3 - 0.05 * 100 = -2.15, with 5% of its mass below -50 (the -100 is a mode of its own; a Gaussian head
    fits that mean by widening its sigma, to sqrt(0.95 * 0.05) * 103 = 22.4 at its optimum)."""
    torch.manual_seed(0)
    head = script.ScalarHead(4, [32], "layer", "twohot")
    features = torch.randn(1, 4).expand(100, 4)
    targets = torch.where(torch.arange(100) % 20 == 0, -100.0, 3.0)
    optimiser = torch.optim.Adam(head.parameters(), lr=1e-2)
    for _ in range(300):
        optimiser.zero_grad()
        head.dist(features).nll(targets).mean().backward()
        optimiser.step()
    with torch.no_grad():
        dist = head.dist(features[:1])
        assert dist.mean.item() == pytest.approx(-2.15, abs=0.1)
        assert dist.logits.softmax(-1)[0, head.bins < -50].sum().item() == pytest.approx(0.05, abs=0.005)


def test_twohot_agents_start_at_zero_learn_and_regress_the_critic_on_its_slow_copy(script, monkeypatch):
    """A fresh two-hot agent predicts reward and value exactly 0; its update is finite; its critic loss is, on a
    one-step imagination fixed by hand (reward 3, V(s_1) 4, gamma 0.5, alpha 0.25, log pi -1: R = 5.25; the slow
    critic's value at s_0 is 7), CE(p(s_0), twohot(5.25)) + CE(p(s_0), twohot(7)), the encodings by hand."""
    torch.manual_seed(0)
    agent = script.Agent(tiny_args(script, heads="twohot"))
    features = torch.randn(6, TINY["latent_size"] + TINY["deter_size"])
    with torch.no_grad():
        assert torch.equal(agent.world_model.reward.dist(features).mean, torch.zeros(6))
        assert torch.equal(agent.critic.dist(features).mean, torch.zeros(6))
    assert agent.world_model.reward(features).shape == agent.critic(features).shape == (6, 255)
    heads = (agent.world_model.reward, agent.critic)
    before = [[p.detach().clone() for p in head.parameters()] for head in heads]
    metrics = one_update(agent)
    assert all(math.isfinite(v) for v in metrics.values()) and agent.nonfinite_updates == 0
    for head, old in zip(heads, before):  # both heads learn from their first update
        assert any(not torch.equal(p, q) for p, q in zip(head.parameters(), old))

    agent = script.Agent(tiny_args(script, heads="twohot", entropy_coef=0.25, gamma=0.5, imagination_horizon=1))
    nn.init.normal_(agent.critic.net.net[-1].weight)  # a critic that does not predict uniformly: the targets matter
    size = TINY["latent_size"] + TINY["deter_size"]
    features = torch.zeros(2, 1, size)
    features[0, :, 1] = 7.0
    features[1, :, 0], features[1, :, 1] = 3.0, 4.0
    _, critic_loss, _, metrics = one_step_behaviour(script, agent, monkeypatch, features)
    assert metrics["imagined_return"].item() == pytest.approx(5.25)
    bins = agent.critic.net.bins.double().numpy()
    soft = torch.tensor(np.stack([hand_twohot(5.25, bins), hand_twohot(7.0, bins)]), dtype=torch.float32)
    logits = agent.critic(features[0]).detach().expand(2, -1)
    torch.testing.assert_close(critic_loss, F.cross_entropy(logits, soft, reduction="sum"))


def test_twohot_heads_refuse_the_gaussian_heads_sigma(script):
    run_tools.validate_args(script.Args(heads="twohot"), script.LOG_SIGMA_RANGE)
    with pytest.raises(ValueError, match="^--head-sigma .*--heads twohot"):
        run_tools.validate_args(script.Args(heads="twohot", head_sigma=1.0), script.LOG_SIGMA_RANGE)


@pytest.mark.parametrize("target_critic", [True, False])
def test_the_slow_critic_follows_the_critic_whatever_bootstraps(script, target_critic):
    """After every critic step the slow critic moves tau of the way to the critic (target <- target + tau (critic -
    target)), also with --no-target-critic, where two-hot heads still regress on it: it never stays at its copy of
    the initial critic."""
    agent = script.Agent(tiny_args(script, heads="twohot", target_critic=target_critic))
    before = [p.detach().clone() for p in agent.targets["critic"].parameters()]
    agent.update(random_batch())
    tau = agent.args.tau
    for slow, old, live in zip(agent.targets["critic"].parameters(), before, agent.critic.parameters()):
        torch.testing.assert_close(slow, old + tau * (live.detach() - old))
    assert any(not torch.equal(slow, old) for slow, old in zip(agent.targets["critic"].parameters(), before))


def test_the_mixed_norm_is_batchnorm_in_the_convolutions_and_layernorm_elsewhere(script):
    agent = script.Agent(tiny_args(script, norm="mixed"))
    wm = agent.world_model
    norms = (nn.BatchNorm1d, nn.BatchNorm2d, nn.LayerNorm, nn.GroupNorm)
    kinds = lambda module: {type(m) for m in module.modules() if isinstance(m, norms)}  # noqa: E731
    assert kinds(wm.encoder) == kinds(wm.decoder) == {nn.BatchNorm2d}
    for module in (wm.recurrent_input, wm.representation, wm.transition, wm.reward, wm.cont, agent.actor):
        assert kinds(module) == {nn.LayerNorm}


def test_a_cpu_hour_budget_counts_every_sitting_and_ends_the_run(script, tmp_path, capsys):
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
    assert f"{run_dir}: stopped after race 2: --cpu-hours-limit {first / 3600:g} spent" in capsys.readouterr().out
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
    *_, metrics = one_step_behaviour(script, agent, monkeypatch, features, samples=torch.full((1, 1, 2), 0.5))
    term = 2 * -math.log(1 - math.tanh(0.5) ** 2 + 1e-6)
    beta = 0.25 if penalty is None else penalty
    expected = 3.0 + 0.25 + (0.25 - beta) * term + 0.5 * 4.0
    assert metrics["imagined_return"].item() == pytest.approx(expected, rel=1e-6)


class FixedMeanActor(nn.Module):
    """An actor whose mean is one learnable vector for every state and whose sigma is fixed: imagine_rollout's
    sample is then mean + sigma * eps, so d(action)/d(mean) is the identity."""

    def __init__(self, mean, sigma):
        super().__init__()
        self.mean, self.sigma = nn.Parameter(torch.tensor(mean)), sigma

    def forward(self, features):
        mean = self.mean.expand(features.shape[0], -1)
        return mean, torch.full_like(mean, self.sigma)


@pytest.mark.parametrize("straight_through", [False, True])
def test_a_clipped_imagined_action_passes_gradient_only_straight_through(script, straight_through):
    """--straight-through-clip: the model is given clip(a) either way (the same imagined state); the gradient of
    what it imagines with respect to the actor's mean equals the model's own gradient at the clipped action, masked
    to the samples inside [-1, 1] by the hard clip and not masked straight through. The reference calls the
    model's imagine_step directly on the clipped action, with the same random numbers."""
    agent = script.Agent(tiny_args(script, norm="layer"))
    wm = agent.world_model.eval()
    B, L = 2, 3
    embed = wm.encoder(torch.randint(0, 256, (B, L, 64, 64, 3), dtype=torch.uint8))
    post = wm.observe(embed, torch.zeros(B, L, 2), torch.zeros(B, L, dtype=torch.bool))
    state, h, z, _ = agent.start_states(post, torch.zeros(B, L))
    actor = FixedMeanActor([0.9, -0.2], 0.5)
    torch.manual_seed(3)
    features, _, samples, _ = script.imagine_rollout(wm, actor, state, h, z, 1, straight_through)
    (grad,) = torch.autograd.grad(features[1].sum(), actor.mean)
    torch.manual_seed(3)
    torch.randn(B * L, 2)  # the rollout's action noise
    clipped = samples[0].detach().clamp(-1.0, 1.0).requires_grad_()
    _, h_ref, z_ref = wm.imagine_step(state, z, clipped)
    torch.testing.assert_close(torch.cat([z_ref, h_ref], -1), features[1])  # the model saw the clipped action
    (model_grad,) = torch.autograd.grad(torch.cat([z_ref, h_ref], -1).sum(), clipped)
    inside = (samples[0].abs() <= 1).float()
    assert 0 < inside[:, 0].sum() < B * L  # some samples of the first dimension were clipped, some were not
    expected = model_grad.sum(0) if straight_through else (model_grad * inside).sum(0)
    torch.testing.assert_close(grad, expected)
    assert not torch.allclose(model_grad.sum(0), (model_grad * inside).sum(0))  # the two estimators differ here


@pytest.mark.parametrize("straight_through", [False, True])
def test_the_actor_update_imagines_with_the_runs_clip(script, monkeypatch, straight_through):
    """--straight-through-clip reaches the imagination of an update (the test above checks what it does there)."""
    seen, real = [], script.imagine_rollout
    monkeypatch.setattr(script, "imagine_rollout", lambda *a: seen.append(a[6:]) or real(*a))
    one_update(script.Agent(tiny_args(script, straight_through_clip=straight_through)))
    assert seen == [(straight_through,)]
