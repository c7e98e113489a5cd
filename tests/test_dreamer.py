"""The Dreamer scripts: defaults, network sizes, losses, returns, replay, agent updates, training stages.

Every test takes the script module as a fixture, so the same tests run on every variant listed in
SCRIPTS. Variant-specific facts (the recurrent cell's
parameter count and the defaults table) are looked up by the module's VARIANT.
"""

from __future__ import annotations

import dataclasses
import glob
import importlib
import itertools
import math
import os
import shutil
import types

import numpy as np
import pytest
import scipy.stats
import torch
import utils
import utils.checkpoint as ckpt
import utils.collector as collector
import utils.run as run_tools
import tyro
from conftest import SCRIPTS, TINY, ColumnHead, ConstantHead, assert_same, random_batch, tiny_args
from torch import nn

# The defaults: the paper's hyperparameters (Algorithm 1, appendix) and the paper authors' configurations, one column
# per variant (docs/agent.md lists them with their sources).
DEFAULTS = {
    "lstm": {
        "batch_size": 15, "seq_len": 50, "imagination_horizon": 50, "train_steps_per_episode": 200,
        "model_lr": 6e-4, "critic_lr": 6e-4, "actor_lr": 1e-4, "entropy_coef": 1.0, "lambda_": 0.95, "gamma": 0.99,
        "tau": 0.005, "free_bits": 1.0, "kl_dyn_scale": 1.0, "kl_rep_scale": 1.0, "grad_clip": 100.0,
        "imagination_starts": 0, "action_repeat": 1, "image_size": 96,
        "prefill_episodes": 5, "replay_capacity": 100_000,
        "eval_episodes": 10, "dead_zone_start": -1.0, "dead_zone_end": -0.5, "dead_zone_episodes": 200,
        "brake_speed_threshold": 50.0, "max_steps": 1000, "stall_steps": 150,
        "collision_penalty": 0.05, "offroad_penalty": 100.0, "speed_reward_coef": 0.0,
        # the appendix's widths and the scripts' other flags
        "cnn_depth": 32, "deter_size": 512, "hidden_size": 1024, "mlp_size": 512, "latent_size": 60, "norm": "batch",
        "num_agents": 2, "stage": "race", "env_id": "multi_car_racing", "seed": 1, "cuda": True, "preset": "paper",
        "return_norm": False, "eval_policy": "mean-action",
    },
}  # fmt: skip
DEFAULTS["gru"] = {**DEFAULTS["lstm"], "batch_size": 50, "imagination_horizon": 15}

def num_params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


# ------------------------------------------------------------------------------------------
# Defaults and sizes
# ------------------------------------------------------------------------------------------
def test_parsed_defaults_equal_the_documented_defaults_table(script):
    args = tyro.cli(script.Args, args=[])
    expected = DEFAULTS[script.VARIANT]
    assert {key: getattr(args, key) for key in expected} == expected
    assert tyro.cli(script.Args, args=["--lambda", "0.9"]).lambda_ == 0.9  # the flag is --lambda


def test_parameter_counts_at_default_sizes(script):
    """Counts from the paper appendix's layer sizes: conv/linear layers followed by a norm have no bias;
    BatchNorm and LayerNorm have a weight and a bias per channel."""
    agent = script.Agent(script.Args(), device="cpu")
    wm = agent.world_model
    z, a, h, hidden, mlp, e = 60, 2, 512, 1024, 512, 1024
    feat = z + h  # 572

    def mlp_count(sizes):  # hidden layers: Linear without bias + norm; output Linear with bias
        hidden_layers = sum(i * o + 2 * o for i, o in itertools.pairwise(sizes[:-1]))
        return hidden_layers + sizes[-2] * sizes[-1] + sizes[-1]

    encoder = sum(ci * co * 16 + 2 * co for ci, co in [(3, 32), (32, 64), (64, 128), (128, 256)]) + 4096 * e + e
    recurrent_input = (z + a) * hidden + 2 * hidden
    cell = {
        "lstm": 4 * h * (hidden + h) + 2 * 4 * h + 2 * h,  # LSTMCell weights, two biases, learned h0 and c0
        "gru": 3 * h * (hidden + h) + 2 * 3 * h + h,  # GRUCell weights, two biases, learned h0
    }[script.VARIANT]
    representation = mlp_count([e + h, hidden, hidden, 2 * z])
    transition = mlp_count([h, hidden, hidden, 2 * z])
    decoder = feat * 4096 + 2 * 64 + 64 * 64 * 9 + 2 * 64 + 64 * 32 * 16 + 2 * 32 + 32 * 3 * 144 + 3 + 1
    reward = mlp_count([feat, mlp, mlp, 2])
    cont = mlp_count([feat, mlp, mlp, 1])
    actor = mlp_count([feat, mlp, mlp, mlp, mlp, 4])
    critic = mlp_count([feat, mlp, mlp, 2])

    assert num_params(wm.encoder) == encoder == 4_885_952
    assert num_params(wm.recurrent_input) == recurrent_input
    assert num_params(wm.cell) == cell
    assert num_params(wm.representation) == representation
    assert num_params(wm.transition) == transition
    assert num_params(wm.decoder) == decoder
    assert num_params(wm.reward) == reward
    assert num_params(wm.cont) == cont
    assert num_params(agent.actor) == actor
    assert num_params(agent.critic) == critic
    assert num_params(wm) == encoder + recurrent_input + cell + representation + transition + decoder + reward + cont
    assert isinstance(agent.critic.net.net[1], nn.LayerNorm)  # the critic uses LayerNorm (appendix)
    assert isinstance(wm.transition.net[1], nn.BatchNorm1d)  # the rest BatchNorm by default
    # Targets: copies of encoder, representation, transition and critic that take no gradient.
    assert num_params(agent.targets) == encoder + representation + transition + critic
    assert not any(p.requires_grad for p in agent.targets.parameters())


@pytest.mark.parametrize("image_size", [96, 64])
@pytest.mark.parametrize("norm", ["batch", "layer"])
def test_shapes_through_every_network(script, image_size, norm):
    args = tiny_args(script, image_size=image_size, norm=norm)
    agent = script.Agent(args)
    wm, B, L = agent.world_model, 3, 5
    obs = torch.randint(0, 256, (B, L, image_size, image_size, 3), dtype=torch.uint8)
    embed = wm.encoder(obs)
    assert embed.shape == (B, L, args.hidden_size)
    post = wm.observe(embed, torch.zeros(B, L, 2), torch.zeros(B, L, dtype=torch.bool))
    assert post["h"].shape == (B, L, args.deter_size) and post["z"].shape == (B, L, args.latent_size)
    assert post["post_mean"].shape == post["post_std"].shape == (B, L, args.latent_size)
    assert (post["post_std"] >= script.LATENT_MIN_STD).all()
    assert all(s.shape[:2] == (B, L) for s in post["states"])
    features = torch.cat([post["z"], post["h"]], -1)
    assert wm.decoder(features).shape == (B, L, 3, image_size, image_size)
    assert wm.reward(features).shape == (B, L, 2) and wm.cont(features).shape == (B, L, 1)
    assert wm.transition(post["h"]).shape == (B, L, 2 * args.latent_size)
    action, log_pi = agent.actor.sample(features)
    assert action.shape == (B, L, 2) and log_pi.shape == (B, L) and (action.abs() <= 1).all()
    value = agent.critic.dist(features)
    assert value.mean.shape == value.std.shape == (B, L)
    # imagination from every posterior state
    state, h, z, cont = agent.start_states(post, torch.zeros(B, L))
    feats, log_pis, actions, stds = script.imagine_rollout(wm, agent.actor, state, h, z, horizon=4)
    assert feats.shape == (5, B * L, args.latent_size + args.deter_size) and cont.shape == (B * L,)
    assert log_pis.shape == (4, B * L) and actions.shape == stds.shape == (4, B * L, 2)


def test_input_to_frames_undoes_frames_to_input_exactly(script):
    """Every uint8 level, in the layout the env gives (H, W, 3), survives the round trip the videos take: the
    network's input (3, H, W) in [-0.5, 0.5] and back; reconstructions outside that range clip to 0 and 255."""
    frames = torch.arange(256, dtype=torch.uint8).repeat(3).reshape(16, 16, 3)
    images = script.frames_to_input(frames)
    assert images.shape == (3, 16, 16) and images.min() == -0.5 and images.max() == 0.5
    assert torch.equal(script.input_to_frames(images), frames)
    assert script.input_to_frames(torch.tensor([-0.7, 0.6]).reshape(2, 1, 1)).flatten().tolist() == [0, 255]


@pytest.mark.parametrize("c_in, c_out, kernel, stride, size", [(4, 3, 12, 4, 14), (8, 4, 4, 2, 6), (8, 8, 3, 1, 4)])
def test_subpixel_conv_transpose_equals_conv_transpose(script, c_in, c_out, kernel, stride, size):
    torch.manual_seed(0)
    layer = nn.ConvTranspose2d(c_in, c_out, kernel, stride, bias=c_out == 3)
    x = torch.randn(5, c_in, size, size, requires_grad=True)
    expected, got = layer(x), script.conv_transpose_as_subpixel(x, layer)
    torch.testing.assert_close(got, expected)
    upstream = torch.randn_like(expected)
    grads = torch.autograd.grad((got * upstream).sum(), [x, layer.weight])
    expected_grads = torch.autograd.grad((expected * upstream).sum(), [x, layer.weight])
    for grad, expected_grad in zip(grads, expected_grads):
        torch.testing.assert_close(grad, expected_grad, rtol=1e-4, atol=1e-4)


def compile_works() -> bool:
    try:
        return torch.compile(lambda x: x + 1)(torch.zeros(1)).item() == 1
    except Exception:  # no C++ compiler, unsupported platform, ...
        return False


@pytest.mark.skipif(not compile_works(), reason="torch.compile is not supported here")
def test_compile_gives_the_losses_of_eager(script, tmp_path):
    metrics = {}
    for compile_ in (False, True):
        torch.manual_seed(0)
        agent = script.Agent(tiny_args(script, compile=compile_))
        metrics[compile_] = agent.update(random_batch())  # world-model step, then behaviour on the stepped model
        torch.save(agent.state_dict(), str(tmp_path / f"{compile_}.pt"))
    assert metrics[True].keys() == metrics[False].keys()
    for key, value in metrics[False].items():
        assert metrics[True][key] == pytest.approx(value, rel=1e-4, abs=1e-5), key
    eager, compiled = (torch.load(tmp_path / f"{c}.pt", weights_only=True) for c in (False, True))
    assert eager["world_model"].keys() == compiled["world_model"].keys()  # checkpoints unchanged


def test_amp_runs_the_networks_in_bfloat16_and_keeps_the_losses_of_float32(script):
    matmul_dtypes = []
    metrics = {}
    for amp in ("off", "on"):
        torch.manual_seed(0)
        agent = script.Agent(tiny_args(script, amp=amp))
        hook = agent.world_model.encoder.convs[0].register_forward_hook(
            lambda m, i, out: matmul_dtypes.append(out.dtype)
        )
        metrics[amp] = agent.update(random_batch())
        hook.remove()
        assert all(p.dtype == torch.float32 for p in agent.world_model.parameters())  # master weights stay float32
    assert matmul_dtypes == [torch.float32, torch.bfloat16]
    for key, value in metrics["off"].items():  # bfloat16 matmuls: within 3% (losses taken in bfloat16: kl_dyn 9% off)
        assert math.isfinite(metrics["on"][key])
        assert metrics["on"][key] == pytest.approx(value, rel=3e-2, abs=2e-2), key


def test_imagination_starts_subset(script):
    agent = script.Agent(tiny_args(script, imagination_starts=7))
    post = agent.world_model.observe(torch.zeros(3, 5, 16), torch.zeros(3, 5, 2), torch.zeros(3, 5, dtype=torch.bool))
    terminated = torch.zeros(3, 5)
    terminated[1, 2] = 1.0
    state, h, z, cont = agent.start_states(post, terminated)
    assert h.shape[0] == z.shape[0] == cont.shape[0] == 7 and all(s.shape[0] == 7 for s in state)
    _, _, _, all_cont = script.Agent(tiny_args(script)).start_states(post, terminated)
    torch.testing.assert_close(all_cont, 1.0 - terminated.flatten())  # each start's continue flag, in order
    assert not h.requires_grad and not z.requires_grad  # starts are detached
    # every part of a chosen start comes from the same posterior step: each tensor carries its step's flat index
    index = torch.arange(15.0).reshape(3, 5, 1)
    coded = {"h": index.expand(3, 5, 4), "z": index.expand(3, 5, 6) + 0.5, "states": (-index, 2 * index)}
    torch.manual_seed(0)
    state, h, z, cont = agent.start_states(coded, index.squeeze(-1) % 2)
    chosen = h[:, 0]
    assert len(set(chosen.tolist())) == 7  # distinct steps
    torch.testing.assert_close(z[:, 0], chosen + 0.5)
    torch.testing.assert_close(state[0][:, 0], -chosen)
    torch.testing.assert_close(state[1][:, 0], 2 * chosen)
    torch.testing.assert_close(cont, 1.0 - chosen % 2)  # each start's own continue flag


# ------------------------------------------------------------------------------------------
# Recurrent state
# ------------------------------------------------------------------------------------------
def test_learned_initial_state_gets_gradient_and_changes(script):
    agent = script.Agent(tiny_args(script))
    cell = agent.world_model.cell
    initial = [p for name, p in cell.named_parameters() if name.startswith("initial_")]
    assert len(initial) == {"lstm": 2, "gru": 1}[script.VARIANT]  # h and c (LSTM), h (GRU)
    assert all(any(p is q for q in agent.model_optimizer.param_groups[0]["params"]) for p in initial)
    before = [p.detach().clone() for p in initial]
    agent.update(random_batch())
    for p, b in zip(initial, before):
        assert p.grad is not None and p.grad.abs().sum() > 0
        assert not torch.equal(p.detach(), b)


def test_is_first_inside_a_sequence_resets_to_a_fresh_start(script):
    torch.manual_seed(0)
    agent = script.Agent(tiny_args(script))
    wm = agent.world_model.eval()
    B, L, k = 2, 8, 5
    embed, actions = torch.randn(B, L, 16), torch.randn(B, L, 2)
    is_first = torch.zeros(B, L, dtype=torch.bool)
    is_first[:, k] = True
    with torch.no_grad():
        full = wm.observe(embed, actions, is_first, sample=False)
        fresh = wm.observe(embed[:, k:], actions[:, k:], is_first[:, k:], sample=False)
        no_reset = wm.observe(embed, actions, torch.zeros_like(is_first), sample=False)
    torch.testing.assert_close(full["h"][:, k:], fresh["h"])
    torch.testing.assert_close(full["z"][:, k:], fresh["z"])
    for s_full, s_fresh in zip(full["states"], fresh["states"]):
        torch.testing.assert_close(s_full[:, k:], s_fresh)
    assert not torch.allclose(no_reset["h"][:, k], full["h"][:, k])  # without is_first the past matters


def test_act_carries_state_and_resets_on_is_first(script):
    torch.manual_seed(0)
    agent = script.Agent(tiny_args(script))
    obs = np.random.default_rng(0).integers(0, 256, (2, 96, 96, 3), dtype=np.uint8)  # raw camera size
    a1, s1 = agent.act(obs, None, policy="deterministic")
    assert a1.shape == (2, 2) and np.all(np.abs(a1) <= 1)
    a2, _s2 = agent.act(obs, s1, np.array([False, True]), policy="deterministic")
    np.testing.assert_allclose(a2[1], a1[1], atol=1e-6)  # car 1 restarted: same as a fresh start
    assert not np.allclose(a2[0], a1[0])  # car 0 continued with its memory
    torch.manual_seed(1)
    mean, _ = agent.act(obs, s1, policy="mean-action")  # from the same state and latent draw as the sample below
    torch.manual_seed(1)
    a3, _ = agent.act(obs, s1)  # sampled actions differ from the mean
    assert not np.allclose(a3, mean)
    # the mean action of a sampled latent (evaluation's default) is not the deterministic policy's, whose posterior
    # mean repeats whatever the random stream
    torch.manual_seed(2)
    other_mean, _ = agent.act(obs, s1, policy="mean-action")
    determined = []
    for seed in (1, 2):
        torch.manual_seed(seed)
        determined.append(agent.act(obs, s1, policy="deterministic")[0])
    np.testing.assert_array_equal(determined[0], determined[1])
    assert not np.allclose(mean, other_mean) and not np.allclose(mean, determined[0])


def test_sampled_actions_are_the_mean_plus_independent_unit_noise_clipped(script):
    """The sampled policy's action is clip(mean + sigma eps, -1, 1), eps ~ N(0, 1) drawn afresh at every decision:
    with the actor's output fixed at mean 0.5 and sigma 0.4, the actions of many cars match the clipped normal's
    closed-form mean and standard deviation, and one decision's noise is uncorrelated with the next."""
    torch.manual_seed(0)
    agent = script.Agent(tiny_args(script))
    agent.actor.forward = lambda features: (torch.full((len(features), 2), 0.5), torch.full((len(features), 2), 0.4))
    n = 4096
    obs = np.random.default_rng(0).integers(0, 256, (n, 96, 96, 3), dtype=np.uint8)
    first, state = agent.act(obs)
    second, _ = agent.act(obs, state)
    lo, hi = (-1 - 0.5) / 0.4, (1 - 0.5) / 0.4  # the clip's bounds in units of sigma
    # E[clip(X)] and E[clip(X)^2] for X ~ N(0.5, 0.4^2), by the truncated normal's moments plus the clipped mass
    mass_lo, mass_hi = scipy.stats.norm.cdf(lo), scipy.stats.norm.sf(hi)
    inside = scipy.stats.truncnorm(lo, hi, 0.5, 0.4)
    mean = -mass_lo + mass_hi + (1 - mass_lo - mass_hi) * inside.mean()
    second_moment = mass_lo + mass_hi + (1 - mass_lo - mass_hi) * (inside.var() + inside.mean() ** 2)
    for actions in (first, second):
        assert actions.mean() == pytest.approx(mean, abs=0.01)
        assert actions.std() == pytest.approx(math.sqrt(second_moment - mean**2), abs=0.01)
    lag1 = np.corrcoef(first.ravel(), second.ravel())[0, 1]
    assert abs(lag1) < 0.05


# ------------------------------------------------------------------------------------------
# Returns, weights, KL, free bits, targets
# ------------------------------------------------------------------------------------------
def test_lambda_returns_hand_computed(script):
    r = torch.tensor([1.0, 2.0, 3.0])  # r_1..r_3
    c = torch.tensor([1.0, 1.0, 0.0])  # c_1..c_3
    v = torch.tensor([10.0, 20.0, 30.0])  # V(s_1)..V(s_3)
    R = script.lambda_returns(r, c, v, torch.zeros(3), gamma=0.5, lam=0.5, alpha=1.0)
    torch.testing.assert_close(R, torch.tensor([5.4375, 7.75, 3.0]))
    # with the entropy term: log pi = (0.5, -1, 2), alpha = 0.1
    #   R_2 = 3 - 0.2 = 2.8; R_1 = 2 + 0.1 + 0.5 (10 + 1.4) = 7.8; R_0 = 1 - 0.05 + 0.5 (5 + 3.9) = 5.4
    R = script.lambda_returns(r, c, v, torch.tensor([0.5, -1.0, 2.0]), gamma=0.5, lam=0.5, alpha=0.1)
    torch.testing.assert_close(R, torch.tensor([5.4, 7.8, 2.8]))
    # lambda = 1 with no termination: the discounted Monte-Carlo return bootstrapped with V(s_H)
    R = script.lambda_returns(r, torch.ones(3), v, torch.zeros(3), gamma=0.5, lam=1.0, alpha=0.0)
    torch.testing.assert_close(R[0], torch.tensor(1 + 0.5 * 2 + 0.25 * 3 + 0.125 * 30))
    # batched (H, N) inputs
    R = script.lambda_returns(r[:, None].repeat(1, 4), c[:, None].repeat(1, 4), v[:, None].repeat(1, 4),
                              torch.zeros(3, 4), gamma=0.5, lam=0.5, alpha=0.0)  # fmt: skip
    torch.testing.assert_close(R[:, 2], torch.tensor([5.4375, 7.75, 3.0]))


def test_actor_weights(script):
    c = torch.tensor([1.0, 1.0, 0.0], requires_grad=True)
    w = script.discount_weights(c, gamma=0.5)
    torch.testing.assert_close(w, torch.tensor([1.0, 0.5, 0.25]))  # w_0 = 1, w_{t+1} = w_t gamma c_{t+1}
    assert not w.requires_grad
    c2 = torch.tensor([0.5, 0.0, 1.0])
    torch.testing.assert_close(script.discount_weights(c2, gamma=0.9), torch.tensor([1.0, 0.45, 0.0]))
    # batched, with the starts' own continue flags: a terminal start (0) weighs nothing at any step
    c3 = torch.tensor([[1.0, 1.0], [0.5, 1.0]])  # (H=2, N=2)
    w3 = script.discount_weights(c3, gamma=0.5, start=torch.tensor([1.0, 0.0]))
    torch.testing.assert_close(w3, torch.tensor([[1.0, 0.0], [0.5, 0.0]]))


def test_lambda_returns_split_into_task_and_entropy_parts(script):
    """--return-norm scales the task part alone: the two parts must add up to the whole lambda-return."""
    g = torch.Generator().manual_seed(0)
    r, v, log_pi = torch.randn(6, 5, generator=g), torch.randn(6, 5, generator=g), torch.randn(6, 5, generator=g)
    c = torch.rand(6, 5, generator=g)
    whole = script.lambda_returns(r, c, v, log_pi, 0.9, 0.8, 0.3)
    task = script.lambda_returns(r, c, v, torch.zeros_like(log_pi), 0.9, 0.8, 0.0)
    entropy = script.lambda_returns(torch.zeros_like(r), c, torch.zeros_like(v), log_pi, 0.9, 0.8, 0.3)
    torch.testing.assert_close(task + entropy, whole)
    x = torch.arange(101.0)
    torch.testing.assert_close(script.return_range(x), torch.tensor(90.0))  # 95th - 5th percentile of 0..100


@pytest.mark.parametrize(
    "rewards, scale_before, scale_after, loss",
    [
        # task returns r + gamma V = r + 0.5; their 5-95% range (torch's linear quantiles of 5 values) is
        # (30.5 + 0.8 * 10) - (0.5 + 0.2 * 10) = 36 (of task + entropy it would be 36.72), so S = 5 + 0.01 (36 - 5)
        # = 5.31; the entropy part is -0.2 log pi = 0.2, 0.4, .., 1.0; the terminal fifth start weighs 0:
        # loss = -(1/5) sum_{i<4} (task_i / 5.31 + entropy_i) = -(62 / 5.31 + 2) / 5
        ([0.0, 10.0, 20.0, 30.0, 40.0], 5.0, 5.31, -(62 / 5.31 + 2.0) / 5),
        # a fresh scale and a narrow range (0.36): S = 0.0036 < 1, so the task part is not scaled up
        ([0.0, 0.1, 0.2, 0.3, 0.4], 0.0, 0.0036, -(2.6 + 2.0) / 5),
    ],
)
def test_return_norm_scales_the_task_part_of_the_actor_objective(script, monkeypatch, rewards, scale_before,
                                                                 scale_after, loss):  # fmt: skip
    """The actor loss is -mean(w (task / max(1, S) + entropy)) with S the EMA (rate 0.01) of the task returns'
    5-95% range; the critic learns task + entropy. A one-step imagination with rewards, values and log pi fixed by
    hand (continue 1, gamma 0.5, entropy weight 0.2, log pi -1 .. -5, the last start terminal), so every number
    above is computed on paper."""
    torch.manual_seed(0)
    args = tiny_args(script, return_norm=True, entropy_coef=0.2, gamma=0.5, imagination_horizon=1)
    agent = script.Agent(args)
    batch = random_batch()
    terminated = torch.zeros(3, 8)
    with torch.no_grad():
        _, _, post = agent.world_model_loss(
            torch.as_tensor(batch["obs"]), torch.as_tensor(batch["action"]), torch.as_tensor(batch["reward"]),
            torch.as_tensor(batch["is_first"]), terminated,
        )  # fmt: skip
    size = torch.cat([post["z"], post["h"]], -1).shape[-1]
    features = torch.zeros(2, 5, size)  # s_0 and s_1 of 5 starts: column 0 is r_1, column 1 is V(s_1)
    features[1, :, 0], features[1, :, 1] = torch.tensor(rewards), 1.0
    log_pi = -torch.arange(1.0, 6.0)[None].requires_grad_()
    monkeypatch.setattr(script, "imagine_rollout", lambda *a: (features, log_pi, None, torch.ones(1, 5, 2)))
    start_cont = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0])  # the fifth start is a terminal state
    monkeypatch.setattr(agent, "start_states", lambda post, terminated: (None, None, None, start_cont))
    agent.world_model.reward = ColumnHead(0)
    agent.world_model.cont = ConstantHead(100.0)  # sigmoid(100) = 1 in float32
    agent.targets["critic"] = ColumnHead(1)
    agent.return_scale.fill_(scale_before)
    actor_loss, critic_loss, _, metrics = agent.behaviour_losses(post, terminated)
    # the critic learns the unscaled return R_i = r_i + gamma V(s_1) + alpha (-log pi_i), its Gaussian NLL at s_0
    # weighted by the start's continue flag (the terminal fifth start counts 0)
    returns = torch.tensor(rewards) + 0.5 * 1.0 + 0.2 * torch.arange(1.0, 6.0)
    value = agent.critic.dist(features[:1])
    nll = -torch.distributions.Normal(value.mean, value.std).log_prob(returns[None])
    torch.testing.assert_close(critic_loss, (start_cont * nll).mean())
    torch.testing.assert_close(agent.return_scale, torch.tensor(scale_after), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(metrics["return_scale"], torch.tensor(scale_after), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(actor_loss, torch.tensor(loss), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(metrics["imagined_return"], torch.tensor(sum(rewards) / 5 + 0.5 + 0.6))  # unweighted
    saved = script.Agent(args)  # the scale is part of the agent's saved state
    saved.return_scale.copy_(agent.return_scale)
    other = script.Agent(args)
    other.load_state_dict(saved.state_dict())
    torch.testing.assert_close(other.return_scale, torch.tensor(scale_after), rtol=1e-5, atol=1e-6)


def test_gaussian_kl_matches_torch(script):
    g = torch.Generator().manual_seed(0)
    m1, m2 = torch.randn(4, 6, generator=g), torch.randn(4, 6, generator=g)
    s1, s2 = torch.rand(4, 6, generator=g) + 0.1, torch.rand(4, 6, generator=g) + 0.1
    D = torch.distributions
    expected = D.kl_divergence(D.Independent(D.Normal(m1, s1), 1), D.Independent(D.Normal(m2, s2), 1))
    torch.testing.assert_close(script.gaussian_kl(m1, s1, m2, s2), expected)
    x = torch.randn(4, 6, generator=g)
    torch.testing.assert_close(script.gaussian_nll(x, m1, s1), -D.Normal(m1, s1).log_prob(x))
    images, means, sigma = (
        torch.rand(2, 3, 3, 4, 4, generator=g),
        torch.rand(2, 3, 3, 4, 4, generator=g),
        torch.tensor(0.3),
    )
    expected = -D.Normal(means, sigma).log_prob(images).sum((-3, -2, -1))
    torch.testing.assert_close(script.image_gaussian_nll(images, means, sigma), expected)


def test_kl_free_bits(script):
    kl = torch.tensor([0.3, 0.99, 1.5, 4.0], requires_grad=True)
    loss = script.kl_free_bits(kl, 1.0)
    torch.testing.assert_close(loss.detach(), torch.tensor([1.0, 1.0, 1.5, 4.0]))
    loss.sum().backward()
    torch.testing.assert_close(kl.grad, torch.tensor([0.0, 0.0, 1.0, 1.0]))


def test_actor_samples_around_tanh_mean_with_bounded_sigma_and_the_paper_log_prob(script):
    """a = tanh(mu) + sigma eps, clipped to [-1, 1]; sigma soft-bounded to (0.1, 0.1 + log(1 + e^0.9) = 1.341); log pi
    of the unclipped sample is torch's Normal log-density minus log(1 - tanh(a)^2) (paper 3.9); the deterministic
    action is tanh(mu)."""
    # hand-computed: sigma's floor, its ceiling 0.1 + log(1 + e^0.9), and sigma(0) = 0.1 + softplus(0.9 - log(1 + e))
    sigma = script.soft_bounded(torch.tensor([-1e4, 1e4, 0.0]), 0.1, 1.0)
    torch.testing.assert_close(sigma, torch.tensor([0.1, 1.341154, 0.607714]), atol=1e-5, rtol=0)
    # log pi at a = 0.5 per dimension, mean 0, sigma 1: -log(2 pi)/2 - 1/8 - log(1 - tanh(0.5)^2) = -0.803711
    log_pi = script.policy_log_prob(torch.tensor([[0.5, 0.5]]), torch.zeros(1, 2), torch.ones(1, 2))
    torch.testing.assert_close(log_pi, torch.tensor([2 * -0.803711]), atol=1e-5, rtol=0)
    torch.manual_seed(0)
    actor = script.Actor(8, 16, 2, "layer")
    with torch.no_grad():  # spread the raw outputs so both soft bounds are reached
        actor.net.net[-1].weight.mul_(30.0)
    features = torch.randn(2000, 8)
    torch.manual_seed(1)
    action, log_pi = actor.sample(features)
    raw_mean, raw_std = actor.net(features).chunk(2, -1)
    mean = torch.tanh(raw_mean)
    std = 0.1 + torch.nn.functional.softplus(1.0 - torch.nn.functional.softplus(1.0 - raw_std) - 0.1)
    torch.manual_seed(1)
    sample = mean + std * torch.randn_like(std)
    torch.testing.assert_close(actor(features)[1], std)
    assert std.min() > 0.1 - 1e-6 and std.min() < 0.11  # the floor is reached, never crossed
    assert std.max() < 1.342 and std.max() > 1.33  # the soft upper bound is reached, never crossed
    torch.testing.assert_close(action, sample.clamp(-1, 1))
    assert (sample.abs() > 1).any()  # clipping happened: the env and the world model get [-1, 1]
    D = torch.distributions
    expected = (D.Normal(mean, std).log_prob(sample) - torch.log(1 - torch.tanh(sample) ** 2 + 1e-6)).sum(-1)
    torch.testing.assert_close(log_pi, expected, atol=1e-4, rtol=1e-4)
    deterministic, none = actor.sample(features, deterministic=True)
    torch.testing.assert_close(deterministic, mean)
    assert none is None


def test_batchnorm_statistics_never_move_on_imagined_states(script):
    """Every BatchNorm of the agent: a forward pass in train mode moves its running statistics, so none may run in
    train mode on imagined states. The imagination-start count (5) differs from B (3) and B*L (24), and every
    imagined batch is a multiple of it (one step: 5; H or H + 1 steps together: 10 or 15), while no real batch is
    (3 or 24 rows), so the hook can tell imagined inputs apart."""
    torch.manual_seed(0)
    args = tiny_args(script, imagination_starts=5, imagination_horizon=2)
    agent = script.Agent(args)
    moved_on_imagined, seen = [], []

    def imagined(rows):
        return rows % 5 == 0

    def hook(module, inputs, output):
        rows = inputs[0].shape[0]
        seen.append((type(module).__name__, rows, module.training))
        if imagined(rows) and module.training:
            moved_on_imagined.append((type(module).__name__, rows))

    bns = [m for net in (agent.world_model, agent.actor, agent.critic) for m in net.modules()
           if isinstance(m, nn.modules.batchnorm._BatchNorm)]  # fmt: skip
    assert bns, "the default --norm batch has BatchNorm layers"
    for bn in bns:
        bn.register_forward_hook(hook)
    actor_bns = [m for m in agent.actor.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    before = [m.running_mean.clone() for m in actor_bns]
    agent.update(random_batch())
    assert not moved_on_imagined, f"BatchNorm ran in train mode on imagined states: {moved_on_imagined}"
    assert any(rows == 24 and training for _, rows, training in seen)  # real posterior states of the batch do
    assert {rows for _, rows, _ in seen if not imagined(rows)} == {3, 24}  # the real batches are told apart
    assert any(imagined(rows) and not training for _, rows, training in seen)  # imagined: running stats
    assert all(not torch.equal(b, m.running_mean) for b, m in zip(before, actor_bns))  # ... from the real states


def test_soft_update_moves_targets_by_tau(script):
    torch.manual_seed(0)
    source = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))
    target = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))
    source(torch.randn(8, 3))  # moves source's running statistics
    before = {k: v.clone() for k, v in target.state_dict().items()}
    script.soft_update(target, source, 0.1)
    for key, value in target.state_dict().items():
        if value.dtype.is_floating_point:
            torch.testing.assert_close(value, before[key] + 0.1 * (source.state_dict()[key] - before[key]))
        else:
            assert torch.equal(value, source.state_dict()[key])


def test_update_soft_updates_targets_and_targets_get_no_gradient(script):
    torch.manual_seed(0)
    agent = script.Agent(tiny_args(script, tau=0.25))
    sources = {"encoder": agent.world_model.encoder, "representation": agent.world_model.representation,
               "transition": agent.world_model.transition, "critic": agent.critic}  # fmt: skip
    for name, source in sources.items():  # a hard copy at the start
        for key, value in agent.targets[name].state_dict().items():
            assert torch.equal(value, source.state_dict()[key]), (name, key)
    old = {name: {k: v.clone() for k, v in agent.targets[name].state_dict().items()} for name in sources}
    agent.update(random_batch())
    for name, source in sources.items():  # every target, the critic's too: old + tau (new - old)
        new_source = source.state_dict()
        for key, value in agent.targets[name].state_dict().items():
            if value.dtype.is_floating_point:  # parameters and BatchNorm statistics alike
                torch.testing.assert_close(value, old[name][key] + 0.25 * (new_source[key] - old[name][key]))
        assert any(not torch.equal(v, old[name][k]) for k, v in agent.targets[name].state_dict().items()), name
    assert all(p.grad is None and not p.requires_grad for p in agent.targets.parameters())


def test_the_critic_target_bootstraps_the_returns_unless_target_critic_is_off(script):
    """The lambda-returns bootstrap from the slow critic (target_critic, the default): changing the online critic's
    weights leaves them alone; with --no-target-critic they move with it."""
    batch = random_batch()
    obs = torch.as_tensor(batch["obs"])
    args = [torch.as_tensor(batch[k]) for k in ("action", "reward")]
    is_first, terminated = torch.as_tensor(batch["is_first"]), torch.as_tensor(batch["terminated"]).float()
    returns = {}
    for target_critic in (True, False):
        returns[target_critic] = []
        for shift in (0.0, 5.0):  # the same agent made twice, its online critic shifted the second time
            torch.manual_seed(0)
            agent = script.Agent(tiny_args(script, target_critic=target_critic))
            _, _, post = agent.world_model_loss(obs, *args, is_first, terminated)
            with torch.no_grad():
                for p in agent.critic.parameters():
                    p.add_(shift)
            torch.manual_seed(1)
            returns[target_critic].append(agent.behaviour_losses(post, terminated)[3]["imagined_return"].item())
    assert returns[True][0] == returns[True][1]  # the target critic bootstraps: unmoved
    assert returns[False][0] != pytest.approx(returns[False][1], abs=1e-3)


def test_actor_loss_leaves_world_model_and_critic_alone(script):
    """The actor's gradient comes through the imagined states (dynamics backpropagation): without the entropy term
    (alpha 0) it is the only path, and it reaches the actor; the world model and the critic get none."""
    torch.manual_seed(0)
    agent = script.Agent(tiny_args(script, entropy_coef=0.0))
    batch = random_batch()
    obs = torch.as_tensor(batch["obs"])
    args = [torch.as_tensor(batch[k]) for k in ("action", "reward")]
    is_first, terminated = torch.as_tensor(batch["is_first"]), torch.as_tensor(batch["terminated"]).float()
    _, _, post = agent.world_model_loss(obs, *args, is_first, terminated)
    actor_loss, *_ = agent.behaviour_losses(post, terminated)
    actor_params = list(agent.actor.parameters())
    for p in list(agent.world_model.parameters()) + list(agent.critic.parameters()):
        p.grad = None
    actor_loss.backward()
    assert all(p.grad is None for p in agent.world_model.parameters())  # no world-model gradient
    assert all(p.grad is None for p in agent.critic.parameters())
    assert sum(p.grad.abs().sum() for p in actor_params) > 0
    assert all(p.requires_grad for p in agent.world_model.parameters())  # unfrozen again


def test_the_kl_terms_train_the_prior_and_the_posterior_apart_and_add_up_to_the_model_loss(script):
    """L_dyn = KL(sg(posterior) || prior) trains the transition (prior) only, L_rep = KL(posterior || sg(prior)) the
    encoder and representation only (the stop-gradient sides are the target networks); on a one-step batch the
    recurrence adds no other path. Without free bits the model loss is reconstruction + reward + continue +
    kl_dyn_scale L_dyn + kl_rep_scale L_rep."""
    torch.manual_seed(0)
    agent = script.Agent(tiny_args(script, free_bits=0.0, kl_dyn_scale=0.5, kl_rep_scale=0.1))
    batch = random_batch(length=1)
    obs = torch.as_tensor(batch["obs"])
    args = [torch.as_tensor(batch[k]) for k in ("action", "reward")]
    is_first, terminated = torch.as_tensor(batch["is_first"]), torch.as_tensor(batch["terminated"]).float()
    wm = agent.world_model

    def grads(term: str) -> dict[str, float]:
        wm.zero_grad(set_to_none=True)
        _, metrics, _ = agent.world_model_loss(obs, *args, is_first, terminated)
        metrics[term].backward()
        return {name: sum(float(p.grad.abs().sum()) for p in getattr(wm, name).parameters() if p.grad is not None)
                for name in ("encoder", "representation", "transition")}  # fmt: skip

    dyn, rep = grads("kl_dyn"), grads("kl_rep")
    assert dyn["transition"] > 0 and dyn["encoder"] == 0 and dyn["representation"] == 0
    assert rep["transition"] == 0 and rep["encoder"] > 0 and rep["representation"] > 0
    loss, metrics, _ = agent.world_model_loss(obs, *args, is_first, terminated)
    parts = metrics["reconstruction"] + metrics["reward"] + metrics["continue"]  # ~1.2e4, the KL part ~0.15
    torch.testing.assert_close(loss - parts, 0.5 * metrics["kl_dyn"] + 0.1 * metrics["kl_rep"], rtol=0, atol=5e-3)


def test_update_returns_the_logged_losses(script):
    """update() returns, as floats under their names, the losses its steps computed: the same agent's world-model
    loss on the batch and, after the model's step, its behaviour losses, computed here step by step from the same
    random draws."""
    import copy

    batch, agent = random_batch(), script.Agent(tiny_args(script))
    twin = copy.deepcopy(agent)
    torch.manual_seed(5)
    metrics = agent.update(batch)
    torch.manual_seed(5)
    obs, actions, rewards, is_first, terminated = twin._batch_tensors(batch)
    twin._set_training(True)
    model_loss, expected, post = twin.world_model_loss(obs, actions, rewards, is_first, terminated)
    assert twin._step(twin.model_optimizer, model_loss, twin.world_model.parameters())
    twin._update_model_targets()
    expected.update(twin.behaviour_losses(post, terminated)[3])
    for key in ("reconstruction", "reward", "continue", "kl_dyn", "kl_rep", "actor", "critic", "entropy"):
        assert isinstance(metrics[key], float) and math.isfinite(metrics[key])
        assert metrics[key] == pytest.approx(expected[key].item(), rel=1e-6), key


def moving_square_batch(B=4, L=8, S=64):
    """Structured frames: a bright square moving across a dark background; rewards follow its position."""
    obs = np.full((B, L, S, S, 3), 30, dtype=np.uint8)
    for b in range(B):
        for t in range(L):
            x = 4 + 6 * t + 3 * b
            obs[b, t, 20:36, x : x + 12] = (230, 200, 40)
    reward = np.linspace(0, 1, L, dtype=np.float32)[None].repeat(B, 0)
    tensors = [
        torch.as_tensor(obs),
        torch.zeros(B, L, 2),
        torch.as_tensor(reward),
        torch.as_tensor(np.eye(1, L, dtype=bool).repeat(B, 0)),
    ]
    return tensors, torch.zeros(B, L)  # (obs, action, reward, is_first), terminated


def small_model_args(script, **overrides):
    return tiny_args(
        script, cnn_depth=8, deter_size=32, hidden_size=32, mlp_size=32, latent_size=8, model_lr=3e-3, **overrides
    )


def test_world_model_loss_falls_on_a_fixed_batch(script):
    torch.manual_seed(0)
    agent = script.Agent(small_model_args(script))
    tensors, terminated = moving_square_batch()
    target = script.frames_to_input(tensors[0])
    losses, squared_errors = [], []
    for _ in range(40):
        loss, _, post = agent.world_model_loss(*tensors, terminated)
        with torch.no_grad():
            recon = agent.world_model.decoder(torch.cat([post["z"], post["h"]], -1))
            squared_errors.append((recon - target).pow(2).sum((-3, -2, -1)).mean().item())
        agent._step(agent.model_optimizer, loss, agent.world_model.parameters())
        losses.append(loss.item())
    # The loss holds a constant 0.5 log(2 pi) per pixel (~11,300 nats at 64 px); the fitted part falls clearly.
    assert np.mean(squared_errors[-5:]) < 0.3 * np.mean(squared_errors[:5])
    assert np.mean(losses[-5:]) < np.mean(losses[:5]) - 1000


def test_decoder_min_log_sigma_zero_keeps_the_unit_variance_pixel_loss(script):
    tensors, terminated = moving_square_batch()
    pixels = tensors[0][0, 0].numel()
    sigmas = {}
    for floor in (-5.0, 0.0):
        torch.manual_seed(0)
        agent = script.Agent(small_model_args(script, decoder_min_log_sigma=floor))
        for _ in range(15):
            loss, metrics, post = agent.world_model_loss(*tensors, terminated)
            agent._step(agent.model_optimizer, loss, agent.world_model.parameters())
        sigmas[floor] = agent.world_model.decoder.sigma().item()
    assert sigmas[-5.0] < 0.97  # the learned sigma falls as the reconstructions sharpen (the paper's choice)
    assert sigmas[0.0] == 1.0  # the floor holds it at Dreamer's unit variance
    # ... so the image term is 0.5 * squared error + a constant, as in Dreamer's MSE loss.
    with torch.no_grad():
        _, metrics, post = agent.world_model_loss(*tensors, terminated)
        recon = agent.world_model.decoder(torch.cat([post["z"], post["h"]], -1))
        squared_error = (recon - script.frames_to_input(tensors[0])).pow(2).sum((-3, -2, -1)).mean()
    expected = 0.5 * squared_error + 0.5 * pixels * math.log(2 * math.pi)
    assert float(metrics["reconstruction"]) == pytest.approx(expected.item(), rel=1e-5)


# ------------------------------------------------------------------------------------------
# Replay
# ------------------------------------------------------------------------------------------
def make_episode(length, episode_id, size=8):
    obs = np.random.default_rng(episode_id).integers(0, 256, (length, size, size, 3), dtype=np.uint8)
    obs[:, 0, 0, 0] = episode_id  # which episode a frame came from
    obs[:, 0, 0, 1] = np.arange(length)  # its step in that episode
    action = np.random.default_rng(episode_id).uniform(-1, 1, (length, 2)).astype(np.float32)
    action[0] = 0
    terminated = np.zeros(length, bool)
    terminated[-1] = episode_id % 2 == 0
    return obs, action, np.arange(length, dtype=np.float32) + episode_id, terminated


def test_replay_frames_bit_exact_and_is_first_marks_episode_starts(script):
    replay = script.Replay(capacity=100, image_size=8)
    episodes = {e: make_episode(7 + e, e) for e in range(1, 16)}
    for ep in episodes.values():
        replay.add_episode(*ep)
    assert len(replay) == 100 and replay.total_steps == sum(7 + e for e in episodes)  # wrapped around
    batch = replay.sample(64, 12, rng=np.random.RandomState(0))
    assert batch["obs"].shape == (64, 12, 8, 8, 3) and batch["obs"].dtype == np.uint8
    for b in range(64):
        ids, steps = batch["obs"][b, :, 0, 0, 0], batch["obs"][b, :, 0, 0, 1]
        for t in range(12):
            obs, action, reward, terminated = episodes[ids[t]]
            np.testing.assert_array_equal(batch["obs"][b, t], obs[steps[t]])  # bit-exact
            np.testing.assert_array_equal(batch["action"][b, t], action[steps[t]])
            assert batch["reward"][b, t] == reward[steps[t]] and batch["terminated"][b, t] == terminated[steps[t]]
            assert batch["is_first"][b, t] == (steps[t] == 0)  # every episode start, and only those
        # consecutive steps within an episode, a new episode only where is_first
        for t in range(1, 12):
            assert (ids[t] == ids[t - 1] and steps[t] == steps[t - 1] + 1) or (
                batch["is_first"][b, t] and ids[t] == ids[t - 1] + 1
            )


def test_replay_save_load_round_trip(script, tmp_path):
    replay = script.Replay(capacity=50, image_size=8, chunk_size=16)
    for e in range(1, 6):
        replay.add_episode(*make_episode(13, e))
    ckpt.save_replay(replay, str(tmp_path / "replay"))
    assert len(glob.glob(str(tmp_path / "replay" / "chunk_*.npz"))) == 4
    loaded = script.Replay(capacity=50, image_size=8)
    ckpt.load_replay(loaded, str(tmp_path / "replay"))
    for key in ("obs", "action", "reward", "is_first", "terminated"):
        np.testing.assert_array_equal(getattr(loaded, key), getattr(replay, key))
    assert (loaded.next_index, loaded.size, loaded.total_steps) == (replay.next_index, replay.size, replay.total_steps)
    a, b = replay.sample(5, 6, np.random.RandomState(1)), loaded.sample(5, 6, np.random.RandomState(1))
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    # later saves to the same directory write only the changed chunks: 65 steps into 50 left next_index at 15, so 3
    # new steps land at 15..17, in chunks 0 (0..15) and 1 (16..31); chunks 2 and 3 keep their files of step 65 (the
    # earlier files of chunks 0 and 1 stay, for a checkpoint that names them, until prune_replay)
    assert replay.next_index == 15
    replay.add_episode(*make_episode(3, 9))
    manifest = ckpt.save_replay(replay, str(tmp_path / "replay"))
    assert manifest["files"] == ["chunk_00000_000000000068.npz", "chunk_00001_000000000068.npz",
                                 "chunk_00002_000000000065.npz", "chunk_00003_000000000065.npz"]  # fmt: skip
    assert len(glob.glob(str(tmp_path / "replay" / "chunk_*.npz"))) == 6
    ckpt.load_replay(loaded, str(tmp_path / "replay"))
    np.testing.assert_array_equal(loaded.obs, replay.obs)


# ------------------------------------------------------------------------------------------
# Checkpoints, memory setting
# ------------------------------------------------------------------------------------------
def test_acting_only_export_acts_exactly_like_its_checkpoint(script, tmp_path):
    """An export keeps encoder, posterior, recurrent core and actor (nothing to learn with), loads with
    weights_only=True, and drives exactly like the full checkpoint under every policy (same random streams)."""
    torch.manual_seed(0)
    args = tiny_args(script)
    agent = script.Agent(args)
    agent.update(random_batch())  # weights and BatchNorm statistics away from their initial values
    full_path, export_path = str(tmp_path / "latest.pt"), str(tmp_path / "policy.pt")
    ckpt.save_checkpoint(full_path, script.VARIANT, args, [agent], {"episode": 1, "global_step": 10})
    size = ckpt.export_policy(script, full_path, export_path)
    assert size == os.path.getsize(export_path) < os.path.getsize(full_path) / 3
    export = torch.load(export_path, weights_only=True)
    assert set(export["agents"][0]) == {"world_model", "actor", "num_updates"}
    prefixes = {key.split(".")[0] for key in export["agents"][0]["world_model"]}
    assert prefixes == {"encoder", "recurrent_input", "cell", "representation"}
    full, policy = script.agent_from_checkpoint(full_path), script.agent_from_checkpoint(export_path)
    frames = np.random.default_rng(0).integers(0, 256, (6, 2, 64, 64, 3), dtype=np.uint8)
    for mode in script.EVAL_POLICIES:
        actions = []
        for driver in (full, policy):
            torch.manual_seed(3)
            state, taken = None, []
            for t, obs in enumerate(frames):
                action, state = driver.act(obs, state, np.array([t == 0, False]), mode)
                taken.append(action)
            actions.append(np.stack(taken))
        np.testing.assert_array_equal(actions[0], actions[1])
    with pytest.raises(RuntimeError, match="cannot learn"):
        policy.update(random_batch())
    with pytest.raises(ckpt.CheckpointError, match="acting-only export"):
        script.load_checkpoint(export_path, training=True)


def test_checkpoint_round_trip_with_weights_only(script, tmp_path):
    args = tiny_args(script)
    agents = [script.Agent(args) for _ in range(2)]
    agents[0].update(random_batch())
    path = str(tmp_path / "ckpt" / "latest.pt")
    np.random.seed(3)
    counters = {"episode": 7, "global_step": 123, "best_eval_return": -math.inf}
    ckpt.save_checkpoint(path, script.VARIANT, args, agents, counters)
    expected_draw = np.random.rand()
    checkpoint = torch.load(path, weights_only=True)  # tensors and plain Python types only
    assert checkpoint["variant"] == script.VARIANT and checkpoint["counters"]["episode"] == 7
    assert checkpoint["args"] == dataclasses.asdict(args)
    assert not glob.glob(str(tmp_path / "ckpt" / "*.tmp"))  # written atomically
    restored = script.agent_from_checkpoint(path, index=0)
    # everything: networks, targets, the three optimisers, counters, return scale, non-finite-step counts
    assert_same(agents[0].state_dict(), restored.state_dict(), "agent 0")
    assert restored.num_updates == 1
    assert restored.model_optimizer.state_dict()["state"][0]["step"] == 1
    np.random.seed(99)
    ckpt.set_rng_state(checkpoint["rng"])
    assert np.random.rand() == expected_draw


LARGE_MALLOC_AND_FREE = """
import ctypes, sys
import utils.run as run_tools
libc = ctypes.CDLL("libc.so.6")
if not hasattr(libc, "mallinfo2"):  # glibc < 2.33
    print("no mallinfo2")
    sys.exit()
class Mallinfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]
libc.mallinfo2.restype = Mallinfo2
libc.malloc.restype, libc.malloc.argtypes, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_size_t], [ctypes.c_void_p]
if sys.argv[1] == "fix":
    assert run_tools.keep_freed_memory()
before = libc.mallinfo2()
block = libc.malloc(64 << 20)
mmapped = libc.mallinfo2().hblks - before.hblks
libc.free(block)
print(mmapped, (libc.mallinfo2().arena - before.arena) >> 20)  # mmapped blocks, heap kept after the free (MiB)
"""


def test_keep_freed_memory_keeps_large_blocks_in_the_heap(script):
    """glibc serves a 64 MiB malloc from an mmap of its own (one more mmapped block in mallinfo2) and, freed, gives
    it back, unless keep_freed_memory has set M_MMAP_MAX to 0 (the block comes from the heap) and M_TRIM_THRESHOLD
    high (the heap keeps the freed block); in a fresh process each, as the settings are process-wide."""
    import platform
    import subprocess
    import sys

    assert script.Args().malloc_fix is True  # the scripts set it by default
    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        assert run_tools.keep_freed_memory() is False
        return

    def mmapped_and_heap_mib(mode: str) -> tuple[int, ...]:
        out = subprocess.run([sys.executable, "-c", LARGE_MALLOC_AND_FREE, mode], capture_output=True, text=True,
                             check=True, cwd=os.path.dirname(os.path.dirname(__file__))).stdout  # fmt: skip
        if out.strip() == "no mallinfo2":
            pytest.skip("glibc older than 2.33 has no mallinfo2")
        return tuple(int(x) for x in out.split())

    default, fixed = mmapped_and_heap_mib("default"), mmapped_and_heap_mib("fix")
    assert default[0] == 1 and default[1] < 8
    assert fixed[0] == 0 and fixed[1] >= 56  # (less what the heap had free before the malloc)


def test_dead_zone_schedule(script):
    args = script.Args(dead_zone_start=-1.0, dead_zone_end=-0.5, dead_zone_episodes=200)
    assert script.dead_zone_at(0, args) == -1.0
    assert script.dead_zone_at(100, args) == pytest.approx(-0.75)
    assert script.dead_zone_at(200, args) == script.dead_zone_at(500, args) == -0.5


# ------------------------------------------------------------------------------------------
# End to end: the training stages on the real racing env (tiny networks, 40-step races)
# ------------------------------------------------------------------------------------------
E2E = dict(
    **TINY, max_steps=40, train_steps_per_episode=2, prefill_episodes=1, replay_capacity=2000, total_episodes=2,
    eval_every=2, eval_episodes=1, video_every=2, video_length=12, replay_save_every=1,
)  # fmt: skip


def read_events(run_dir):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    scalars, images = {}, set()
    for path in sorted(glob.glob(os.path.join(run_dir, "events.out.tfevents.*"))):
        acc = EventAccumulator(path, size_guidance={"scalars": 0, "images": 0})
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            scalars.setdefault(tag, []).extend((e.step, e.value) for e in acc.Scalars(tag))
        images.update(acc.Tags()["images"])
    return scalars, images


LOSS_TAGS = [
    f"losses/{k}" for k in ("reconstruction", "reward", "continue", "kl_dyn", "kl_rep", "actor", "critic", "entropy")
]
CHART_TAGS = ["charts/episodic_return", "charts/progress", "perf/env_sps", "perf/updates_per_s"]


@pytest.fixture(scope="module", params=SCRIPTS)
def single_run(request, tmp_path_factory):
    script = importlib.import_module(request.param)
    runs = tmp_path_factory.mktemp("runs")
    run_dir = script.main(script.Args(stage="single", runs_dir=str(runs), **E2E))
    return script, run_dir


def test_an_evaluation_logs_each_cars_means_over_the_tracks(monkeypatch):
    """evaluate_and_keep_best logs per car the mean over the held-out tracks of what drive_races measured (made-up
    readings of 3 tracks x 2 cars, means by hand), and leaves best.pt alone when the return is not the best."""
    from types import SimpleNamespace

    from utils import run as run_module
    from utils.collector import READINGS

    readings = {key: np.zeros((3, 2)) for key in READINGS}
    readings["return"] = np.array([[100.0, -50.0], [200.0, 30.0], [600.0, 80.0]])
    readings["progress"] = np.array([[0.2, 0.1], [0.4, 0.3], [1.0, 0.5]])
    readings["abs_steer"] = np.array([[0.1, 0.9], [0.2, 0.6], [0.3, 0.3]])
    readings["speed"] = np.array([[40.0, 10.0], [50.0, 20.0], [90.0, 60.0]])
    readings["lap_finished"] = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]])
    readings["eliminated"] = np.array([[1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    monkeypatch.setattr(run_module, "drive_races", lambda agents, args, envs: readings)
    logged = {}
    run = SimpleNamespace(
        args=SimpleNamespace(env_id="multi_car_racing", eval_policy="mean-action", eval_checkpoints=False),
        counters={"episode": 5, "global_step": 900, "best_eval_return": 1e9}, method=None, eval_envs=object(),
        agents=[SimpleNamespace(num_updates=7)] * 2, logger=SimpleNamespace(record=logged.__setitem__),
        print=lambda message: None, ghosts={}, manifests=[], wins=[[], []], cpu_seconds=lambda: 1.0,
        checkpoint_dir="/nonexistent",  # best.pt would be written here: the return is not the best
    )  # fmt: skip
    run_module.evaluate_and_keep_best(run)
    expected = {
        "episodic_return": (300.0, 20.0), "progress": (1.6 / 3, 0.3), "mean_abs_steer": (0.2, 0.6),
        "speed": (60.0, 30.0), "laps_finished": (1 / 3, 0.0), "eliminated": (2 / 3, 1 / 3),
    }  # fmt: skip
    assert set(logged) == {f"car_{j}/eval/{tag}" for tag in expected for j in (0, 1)}
    for tag, values in expected.items():
        for j, value in enumerate(values):
            assert logged[f"car_{j}/eval/{tag}"] == pytest.approx(value), (tag, j)


def test_single_stage_writes_scalars_video_and_checkpoints(single_run):
    script, run_dir = single_run
    scalars, images = read_events(run_dir)
    for tag in CHART_TAGS + LOSS_TAGS:
        assert "car_0/" + tag in scalars, tag
    assert "car_1/charts/episodic_return" not in scalars  # one car in the single stage
    assert len(scalars["car_0/charts/episodic_return"]) == 2  # one value per race
    assert len(scalars["car_0/losses/reconstruction"]) == 2  # training after every race, from the prefill race on
    assert "car_0/videos/real_reconstruction_imagination" in images  # the video really is in the event file
    import plot

    assert plot.run_identity(run_dir)[:2] == (script.VARIANT, "single")  # config.json groups the run
    assert {"car_0/eval/episodic_return", "car_0/eval/progress", "car_0/eval/mean_abs_steer"} <= set(scalars)
    assert all(0.0 <= value <= 1.0 for _, value in scalars["car_0/eval/progress"])
    assert all(0.0 <= value <= 1.0 for _, value in scalars["car_0/eval/mean_abs_steer"])
    for tag in ("speed", "laps_finished", "eliminated"):  # what they hold: test_an_evaluation_logs_...
        assert len(scalars[f"car_0/eval/{tag}"]) == len(scalars["car_0/eval/progress"]), tag
    for name in ("latest.pt", "best.pt"):
        checkpoint = torch.load(os.path.join(run_dir, "checkpoints", name), weights_only=True)
        assert checkpoint["variant"] == script.VARIANT and len(checkpoint["agents"]) == 1
    latest = torch.load(os.path.join(run_dir, "checkpoints", "latest.pt"), weights_only=True)
    assert latest["counters"]["episode"] == 2 and latest["agents"][0]["num_updates"] == 2 * 2
    assert math.isfinite(latest["counters"]["best_eval_return"])
    assert os.path.exists(os.path.join(run_dir, "checkpoints", "replay_car_0", "meta.npz"))


def test_resume_continues_from_saved_counters(single_run, tmp_path):
    script, run_dir = single_run
    run_dir = str(shutil.copytree(run_dir, tmp_path / os.path.basename(run_dir)))  # the module's run stays as it was
    before = torch.load(os.path.join(run_dir, "checkpoints", "latest.pt"), weights_only=True)
    replay = script.Replay(E2E["replay_capacity"], TINY["image_size"])
    ckpt.load_replay(replay, os.path.join(run_dir, "checkpoints", "replay_car_0"))
    script.main(script.Args(resume=run_dir, total_episodes=3), {"total_episodes"})  # extends the run (saved: 2)
    after = torch.load(os.path.join(run_dir, "checkpoints", "latest.pt"), weights_only=True)
    assert after["counters"]["episode"] == 3
    assert after["counters"]["global_step"] > before["counters"]["global_step"]
    assert after["agents"][0]["num_updates"] == before["agents"][0]["num_updates"] + 2  # no new prefill
    assert after["args"]["cnn_depth"] == TINY["cnn_depth"]  # the saved configuration, not the defaults
    resumed_replay = script.Replay(E2E["replay_capacity"], TINY["image_size"])
    ckpt.load_replay(resumed_replay, os.path.join(run_dir, "checkpoints", "replay_car_0"))
    assert resumed_replay.episodes == replay.episodes + 1  # the loaded replay grew by the new race
    scalars, _ = read_events(run_dir)
    assert [step for step, _ in scalars["charts/episode"]][-1] == after["counters"]["global_step"]


def test_ghost_stage_records_and_races_a_ghost(single_run, tmp_path):
    script, run_dir = single_run
    args = script.Args(
        stage="ghost", checkpoint=os.path.join(run_dir, "checkpoints", "best.pt"), ghost_tracks=1,
        runs_dir=str(tmp_path), **{**E2E, "cnn_depth": 8},  # sizes come from the checkpoint
    )  # fmt: skip
    ghost_dir = script.main(args)
    checkpoint = torch.load(os.path.join(ghost_dir, "checkpoints", "latest.pt"), weights_only=True)
    ghosts = checkpoint["extra"]["ghosts"]
    assert list(ghosts) == [str(args.ghost_seed)]  # one ghost for the one track, recorded in race 1
    ghost = ghosts[str(args.ghost_seed)]
    assert ghost["track_seed"] == args.ghost_seed and len(ghost["poses"]) > 1
    scalars, _ = read_events(ghost_dir)
    # race 1 has no ghost yet (no win or loss), race 2 raced against it
    assert len(scalars["car_0/charts/win_rate"]) == 1
    assert checkpoint["args"]["cnn_depth"] == TINY["cnn_depth"]
    # the agent keeps its memory: the replay saved beside best.pt, then its own races, all in its own directory
    single = script.Replay(E2E["replay_capacity"], TINY["image_size"])
    ckpt.load_replay(single, os.path.join(run_dir, "checkpoints", "replay_car_0"))
    own = script.Replay(E2E["replay_capacity"], TINY["image_size"])
    ckpt.load_replay(own, os.path.join(ghost_dir, "checkpoints", "replay_car_0"), checkpoint["extra"]["replays"][0])
    races = checkpoint["counters"]["episode"]
    assert single.episodes >= 1 and own.episodes == single.episodes + races
    assert np.array_equal(own.obs[: single.size], single.obs[: single.size])  # its first steps are the single run's
    with pytest.raises(ckpt.UsageError, match=r"^--replay-capacity 3000: the replay beside --checkpoint .* "
                       r"holds 2000; give --replay-capacity 2000, or --fresh-replay"):  # fmt: skip
        script.main(dataclasses.replace(args, replay_capacity=3000, runs_dir=str(tmp_path / "other")))
    assert not (tmp_path / "other").exists()  # refused before anything was written
    fresh_dir = script.main(dataclasses.replace(args, fresh_replay=True, runs_dir=str(tmp_path / "fresh")))
    fresh = torch.load(os.path.join(fresh_dir, "checkpoints", "latest.pt"), weights_only=True)
    assert fresh["extra"]["replays"][0]["episodes"] == fresh["counters"]["episode"]  # --fresh-replay: its own only


def test_race_stage_two_learning_agents(tmp_path, script):
    run_dir = script.main(script.Args(stage="race", runs_dir=str(tmp_path), **E2E))
    scalars, images = read_events(run_dir)
    for car in ("car_0/", "car_1/"):
        for tag in CHART_TAGS + LOSS_TAGS + ["charts/win_rate"]:
            assert car + tag in scalars, car + tag
        assert car + "videos/real_reconstruction_imagination" in images
    for name in ("latest.pt", "best.pt"):
        checkpoint = torch.load(os.path.join(run_dir, "checkpoints", name), weights_only=True)
        assert len(checkpoint["agents"]) == 2
    latest = torch.load(os.path.join(run_dir, "checkpoints", "latest.pt"), weights_only=True)
    # independent agents: own networks (different initialisations and updates)
    w0, w1 = (a["world_model"]["encoder.fc.weight"] for a in latest["agents"])
    assert not torch.equal(w0, w1)


def test_time_limit_stops_with_a_checkpoint(tmp_path, script, monkeypatch):
    """--time-limit-hours 1 with the clock jumping two hours after the run started (Run.started was read from the
    real clock): it stops before its first race, with a checkpoint."""
    real = run_tools.time.time
    monkeypatch.setattr(run_tools.time, "time", lambda: real() + 7200.0)
    run_dir = script.main(script.Args(stage="single", runs_dir=str(tmp_path), time_limit_hours=1.0, **E2E))
    latest = torch.load(os.path.join(run_dir, "checkpoints", "latest.pt"), weights_only=True)
    assert latest["counters"]["episode"] == 0 < E2E["total_episodes"]


class _ScriptedSteer:
    """Stands in for an Agent in drive_races(): steers `steer` with full gas while it sees a camera
    image, and steers 0 on the blank observation of a car that is already out."""

    action_dim = 2

    def __init__(self, steer: float):
        self.steer, self.calls, self.blank_calls = steer, 0, 0

    def act(self, frames, state, is_first, policy):
        self.calls += 1
        sees_track = float(frames.std()) > 0
        self.blank_calls += not sees_track
        return np.array([[self.steer if sees_track else 0.0, 1.0]], dtype=np.float32), state


def test_the_collector_refuses_agents_that_do_not_match_the_cars():
    """Agent i drives car i of every race: another count of agents or action repeats would map cars to the wrong
    agents without a word; drive_races drives one race at a time (with K > 1 it would keep whichever ended first)."""
    one_race_of_two = types.SimpleNamespace(num_envs=2, num_agents=2)
    two_races_of_two = types.SimpleNamespace(num_envs=4, num_agents=2)
    agents, args = [_ConstantDriver(np.zeros(2, np.float32))], types.SimpleNamespace(action_repeat=1)
    with pytest.raises(ValueError, match=r"^1 agents for races of 2 cars \(2 vec-env slots\)"):
        collector.Races(agents, args, one_race_of_two, None)
    with pytest.raises(ValueError, match="^3 action repeats for 2 agents"):
        collector.Races(agents * 2, args, one_race_of_two, None, repeats=[1, 2, 3])
    narrow = _ConstantDriver(np.zeros(2, np.float32))
    narrow.action_dim = 1  # (its actions would fill both columns of the race's actions without a word)
    with pytest.raises(ValueError, match=r"^agents of action sizes \[1, 2\] in one race"):
        collector.Races([agents[0], narrow], args, one_race_of_two, None)
    with pytest.raises(ValueError, match="^drive_races drives one race at a time: eval_envs holds 4 slots for 2"):
        collector.drive_races(agents * 2, args, two_races_of_two)


def test_evaluation_averages_steer_over_the_decisions_of_cars_still_racing(script):
    """car_0 steers hard at full gas and leaves the road early; car_1 races on. car_0's mean |steer| is
    exactly 1: after it went out it is not asked to decide (it would see a blank observation and steer 0)."""
    from utils import make_vec_env

    args = tiny_args(script, num_agents=2, eval_episodes=1, eval_seed=3, max_steps=400, action_repeat=2)
    envs = make_vec_env(args.env_id, 1, None, **run_tools.env_kwargs(args, args.dead_zone_end))
    drivers = [_ScriptedSteer(1.0), _ScriptedSteer(-0.25)]
    readings = collector.drive_races(drivers, args, envs)
    envs.close()
    returns, progress, abs_steer = readings["return"], readings["progress"], readings["abs_steer"]
    assert returns.shape == progress.shape == abs_steer.shape == (1, 2)
    assert readings["eliminated"][0, 0] == 1.0  # car_0 went out ...
    assert drivers[1].calls > drivers[0].calls  # ... while car_1 raced on ...
    assert drivers[0].blank_calls == 0  # ... and was not asked to act after it
    assert abs_steer[0].tolist() == pytest.approx([1.0, 0.25])


class _ScriptedPedal(_ScriptedSteer):
    """Steers `steer` with the throttle-brake axis at `pedal` (1: full gas, -1: full brake)."""

    def __init__(self, steer: float, pedal: float):
        super().__init__(steer)
        self.pedal = pedal

    def act(self, frames, state, is_first, policy):
        action, state = super().act(frames, state, is_first, policy)
        action[0, 1] = self.pedal
        return action, state


def test_drive_races_reads_gas_brakes_speed_and_how_each_race_ended(script):
    """car_0 steers hard at full gas and leaves the road; car_1 stands on the brake from the start, never moves and
    is eliminated for stalling. Their readings follow from what they did, not from the agents."""
    from utils import make_vec_env

    args = tiny_args(script, num_agents=2, eval_episodes=1, eval_seed=3, max_steps=400, action_repeat=2)
    envs = make_vec_env(args.env_id, 1, None, **run_tools.env_kwargs(args, args.dead_zone_end))
    readings = collector.drive_races([_ScriptedPedal(1.0, 1.0), _ScriptedPedal(0.0, -1.0)], args, envs)
    envs.close()
    assert all(value.shape == (1, 2) for value in readings.values())
    assert readings["gas"][0].tolist() == [1.0, 0.0] and readings["brake_share"][0].tolist() == [0.0, 1.0]
    assert readings["speed"][0, 0] > 10 and readings["speed"][0, 1] < 1e-3  # (physics leaves ~1e-7)
    assert readings["eliminated"][0].tolist() == [1.0, 1.0] and readings["lap_finished"][0].tolist() == [0.0, 0.0]
    assert readings["abs_steer"][0].tolist() == [1.0, 0.0] and readings["progress"][0, 0] > readings["progress"][0, 1]
    # return and progress, against the env stepped directly on the same track with the same actions (no collector)
    from envs import MultiCarRacing

    env = MultiCarRacing(**run_tools.env_kwargs(args, args.dead_zone_end))
    env.reset(seed=args.eval_seed)
    actions = {"car_0": np.array([1.0, 1.0], np.float32), "car_1": np.array([0.0, -1.0], np.float32)}
    returns, progress = {agent: 0.0 for agent in actions}, {}
    while env.agents:
        _, rewards, _, _, infos = env.step({agent: actions[agent] for agent in env.agents})
        for agent, reward in rewards.items():
            returns[agent] += reward
            progress[agent] = infos[agent]["progress"]
    env.close()
    np.testing.assert_allclose(readings["return"][0], [returns["car_0"], returns["car_1"]], rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(readings["progress"][0], [progress["car_0"], progress["car_1"]], rtol=1e-6)


class _ConstantDriver:
    """An agent of the collector that always takes `action`; its state counts its car's decisions since its race
    started (a batch-first tensor, as an Agent's), so a state mixed up between cars shows."""

    action_dim = 2

    def __init__(self, action):
        self.action, self.calls = np.asarray(action, dtype=np.float32), []

    def initial_state(self, n):
        return (torch.zeros(n),)

    def act(self, obs, state, is_first, policy):
        state = self.initial_state(len(obs)) if state is None else state
        self.calls.append(len(obs))
        count = torch.where(torch.as_tensor(is_first), torch.zeros(len(obs)), state[0]) + 1
        return np.tile(self.action, (len(obs), 1)), (count,)


def _env_rewards(args, seed, actions):
    """Per car, the rewards of every env step of a race driven with constant `actions`, straight from the env (no
    vec env, no collector): the independent reference of the collector's transitions."""
    from envs import MultiCarRacing

    env = MultiCarRacing(**script_env(args))
    env.reset(seed=seed)
    rewards = {agent: [] for agent in env.possible_agents}
    while env.agents:
        _, step_rewards, _, _, _ = env.step({agent: actions[int(agent[-1])] for agent in env.agents})
        for agent, reward in step_rewards.items():
            rewards[agent].append(reward)
    return [np.asarray(rewards[agent]) for agent in env.possible_agents]


def script_env(args) -> dict:
    return {"num_agents": args.num_agents, "max_steps": args.max_steps, "dead_zone": args.dead_zone_end}


def test_each_car_decides_every_repeat_steps_of_its_own_and_its_transitions_sum_the_held_rewards(script):
    """Two cars with action repeats 3 and 2: car_0 steers hard and leaves the road, car_1 drives on. Each decides
    at the start and then every 3 (2) of its env steps, also after the other car went out; each transition's reward
    is the sum of the env's rewards over the steps it held (read straight from the env); a car that is out decides
    no more."""
    from utils import make_vec_env

    args = tiny_args(script, num_agents=2, max_steps=120)
    actions = [np.array([1.0, 1.0], np.float32), np.array([0.0, 0.3], np.float32)]
    agents = [_ConstantDriver(actions[0]), _ConstantDriver(actions[1])]
    envs = make_vec_env(args.env_id, 1, 3, **script_env(args))
    [race], steps = collector.Races(agents, args, envs, envs.reset(), repeats=[3, 2]).drive(["stochastic"] * 2)
    envs.close()
    reference = _env_rewards(args, 3, actions)
    assert len(reference[0]) < len(reference[1]) == steps  # car_0 went out first, car_1 raced to the end
    for car, agent, repeat, env_rewards in zip(race.cars, agents, (3, 2), reference):
        decisions = math.ceil(len(env_rewards) / repeat)
        assert len(agent.calls) == decisions and len(car.obs) == 1 + decisions
        expected = [env_rewards[k : k + repeat].sum() for k in range(0, len(env_rewards), repeat)]
        np.testing.assert_allclose(car.arrays()[2][1:], expected, rtol=1e-5, atol=1e-5)
        assert car.arrays()[3][1:].tolist() == [False] * (decisions - 1) + [car.final_info["eliminated"] is not None]


def test_races_side_by_side_keep_each_cars_state_when_they_fall_out_of_step(script):
    """K = 2 one-car races on different tracks end at different steps. After the first ends, its new race's car
    decides while the other car holds: the agent acts on that car's row of its state alone, and every row still
    counts its own car's decisions since its race started."""
    from utils import make_vec_env

    args = tiny_args(script, num_agents=1, max_steps=200)
    agent = _ConstantDriver([0.6, 0.4])
    envs = make_vec_env(args.env_id, 2, 11, **script_env(args))
    races = collector.Races([agent], args, envs, envs.reset(), repeats=[3])
    first, _ = races.drive(["stochastic"])
    second, _ = races.drive(["stochastic"])
    envs.close()
    (ended,), (later,) = first, second
    assert 1 in agent.calls  # one car decided alone
    for race in (ended, later):
        steps = race.cars[0].final_info["step"]
        assert len(race.cars[0].obs) == 1 + math.ceil(steps / 3)
    s1, s2 = ended.cars[0].final_info["step"], later.cars[0].final_info["step"]
    assert s1 < s2  # (both races started together: the later one ended s2 env steps in, the new race s2 - s1 ago)
    counts = sorted(races.states[0][0].tolist())
    assert counts == sorted([math.ceil(s2 / 3), math.ceil((s2 - s1) / 3)])


def test_k_races_of_different_seeds_or_a_resume_start_on_tracks_of_their_own(script, tmp_path, monkeypatch):
    """K races side by side start on the tracks of their vec env's seed + k (SB3's VecEnv.seed). With the run's
    seed + races done as that seed, seed 11's second race would be seed 12's first, and a run resumed after 2 races
    would race a new seed-13 run's tracks: no run, resumed or not, shares a starting track with another here."""
    k_races = 4
    starts = {(seed, done): {run_tools.races_seed(seed, done) + k for k in range(k_races)}
              for seed in (11, 12, 13) for done in range(6)}  # fmt: skip
    for a, b in itertools.combinations(starts, 2):
        assert not starts[a] & starts[b], (a, b)
    # pinned (numpy's SeedSequence of (11, 3)): another formula would move a run begun before it onto other tracks
    assert run_tools.races_seed(11, 3) == 520846937

    class Built(Exception):
        pass

    def make_vec_env(env_id, num_races, seed, *args, **kwargs):
        raise Built(num_races, seed)

    monkeypatch.setattr(utils, "make_vec_env", make_vec_env)
    with pytest.raises(Built) as built:
        script.main(tiny_args(script, num_races=k_races, seed=12, stage="single", num_agents=1,
                              runs_dir=str(tmp_path)))  # fmt: skip
    assert built.value.args == (k_races, run_tools.races_seed(12, 0))


def test_amp_auto_only_with_bfloat16_in_hardware(script, monkeypatch):
    """--amp auto: bfloat16 autocast on a CUDA device only if it has bfloat16 in hardware (a GPU before Ampere
    emulates it, slower than float32) and on a CPU only with bfloat16 instructions; cuda (auto's rule of old): on
    such a CUDA device only; on and off as they say."""
    import contextlib

    asked, current = [], [None]

    @contextlib.contextmanager
    def select(device):
        current[0] = device
        yield
        current[0] = None

    def emulating_gpu(including_emulation=True):
        asked.append((current[0], including_emulation))
        return including_emulation  # supported only by emulation

    cuda, cpu = torch.device("cuda", 1), torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "device", select)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", emulating_gpu)
    assert script.bf16_autocast("auto", cuda) is False and asked == [(cuda, False)]  # asked of the run's device
    assert script.bf16_autocast("cuda", cuda) is False
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True: True)  # Ampere or newer
    assert script.bf16_autocast("auto", cuda) is True and script.bf16_autocast("cuda", cuda) is True
    for instructions in (False, True):
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: instructions)
        assert script.bf16_autocast("auto", cpu) is instructions and script.bf16_autocast("cuda", cpu) is False
        assert script.Agent(tiny_args(script, amp="auto")).amp is instructions  # the agent applies the rule
    assert script.bf16_autocast("on", cpu) is True and script.bf16_autocast("off", cuda) is False


def test_a_run_resolves_amp_once_says_so_and_warns_of_emulated_bfloat16(script, monkeypatch, capsys):
    """setup_run's --amp: auto and cuda become on or off (what the run saves), each said; on without bfloat16 in
    hardware (a run moved to another machine) is kept, with a warning that it is slower than float32."""
    cpu = torch.device("cpu")
    for instructions, amp, resolved, said in (
        (True, "auto", "on", "--amp auto -> on: the updates in bfloat16\n"),
        (False, "auto", "off", "--amp auto -> off: the updates in float32\n"),
        (True, "cuda", "off", "--amp cuda (auto's rule until it took in bfloat16 CPUs: a run saved with auto then) "
                              "-> off: the updates in float32\n"),
        (True, "on", "on", ""),
        (False, "off", "off", ""),
        (False, "on", "on", "warning: --amp on, and cpu has no bfloat16 in hardware: emulated, slower than float32 "
                            "(docs/performance.md); --amp off computes otherwise, but faster\n"),
    ):
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: instructions)
        assert run_tools.resolved_amp_args(tiny_args(script, amp=amp), cpu).amp == resolved
        assert capsys.readouterr().out == said


def test_the_amp_ratio_benchmark_starts_both_settings_alike(script, monkeypatch):
    """train_throughput --amp-ratio compares --amp on and off from the same weights, batches and random draws, so
    that their losses differ by bfloat16's rounding alone: with autocast off for both, they are equal."""
    import train_throughput

    monkeypatch.setattr(script, "bf16_autocast", lambda amp, device: False)  # both settings in float32
    seconds, losses = train_throughput.paired_cpu_seconds(script, {**TINY, "seq_len": 4}, "amp", ("on", "off"),
                                                          updates=2, warmup=1)  # fmt: skip
    assert set(seconds) == {"on", "off"} and losses["on"] == losses["off"]
    assert losses["on"]["actor"] != 0.0 and math.isfinite(losses["on"]["model_loss"])


def test_the_compile_ratio_benchmark_times_both_settings_from_the_same_start(script, monkeypatch):
    """train_throughput --compile-ratio builds one agent with --compile and one without, from the same weights,
    batches and random draws: with compiling made a no-op, their losses are equal, and only one was compiled."""
    import train_throughput

    compiled = []
    monkeypatch.setattr(nn.Module, "compile", lambda module, *a, **k: compiled.append(type(module).__name__))
    seconds, losses = train_throughput.paired_cpu_seconds(script, {**TINY, "seq_len": 4}, "compile", (True, False),
                                                          updates=1, warmup=1)  # fmt: skip
    assert set(seconds) == {True, False} and losses[True] == losses[False]
    assert "Actor" in compiled and compiled.count("Actor") == 1  # the compiled agent's networks only


def test_dead_zone_of_the_next_race_is_set_before_its_reset(script):
    """The env applies a dead zone at its next reset; a race races at the schedule's value for the races ended when
    it starts. One race at a time resets after the race's turn: the races ended so far. K > 1 races have already
    auto-reset the ended race's slot inside the step: one more, for the race that starts when the next one ends."""
    for races, ahead in ((1, 0), (3, 1)):
        args = tiny_args(script, num_races=races, dead_zone_start=-1.0, dead_zone_end=-0.5, dead_zone_episodes=4)
        next_zone = run_tools.next_dead_zone(script, args, 2)
        assert next_zone == script.dead_zone_at(2 + ahead, args) == -1.0 + 0.5 * (2 + ahead) / 4
    # the schedule is a warm-up for learning from scratch: agents that start trained race at its end from race 0
    assert script.dead_zone_at(0, tiny_args(script, checkpoint="best.pt", dead_zone_start=-1.0)) == -0.5
    # what main gives the env after each race (set_next_dead_zone): the racing env only, at the races ended so far
    calls = []
    envs = types.SimpleNamespace(env_method=lambda *a: calls.append(a))
    for env_id in ("multi_car_racing", "highway-intersection"):
        args = tiny_args(script, env_id=env_id, dead_zone_start=-1.0, dead_zone_end=-0.5, dead_zone_episodes=4)
        script.set_next_dead_zone(types.SimpleNamespace(method=script, args=args, envs=envs, counters={"episode": 2}))
    assert calls == [("set_dead_zone", -0.75)]


def test_a_ghost_is_the_agents_first_run_on_its_track_until_a_run_beats_it(script):
    """The ghost stage's rule (record_ghost): the first run on a ghost track becomes its ghost; a run that does not
    beat it leaves it; a run that beats it (envs.ghost_beaten) replaces it; each track keeps its own."""
    run = types.SimpleNamespace(ghosts={})

    def final_info(name, **beaten):
        return {"trajectory": types.SimpleNamespace(to_dict=lambda: {"run": name}), **beaten}

    script.record_ghost(run, final_info("first"), 20_000)  # no ghost yet: the env reports no ghost_beaten
    script.record_ghost(run, final_info("slower", ghost_beaten=False), 20_000)
    script.record_ghost(run, final_info("other track"), 20_001)
    assert run.ghosts == {20_000: {"run": "first"}, 20_001: {"run": "other track"}}
    script.record_ghost(run, final_info("faster", ghost_beaten=True), 20_000)
    assert run.ghosts == {20_000: {"run": "faster"}, 20_001: {"run": "other track"}}


def test_a_checkpoint_that_brings_two_hot_heads_is_checked_again(script, tmp_path):
    """--checkpoint brings its networks' form: a two-hot checkpoint makes a two-hot run, so the two-hot checks apply
    to it even when the command line asked for Gaussian heads (its --head-sigma would fail at the first update,
    after the prefill races)."""
    args = script.Args(heads="twohot", runs_dir=str(tmp_path), **E2E)
    agent = script.Agent(args)
    path = str(tmp_path / "twohot.pt")
    ckpt.save_checkpoint(path, script.VARIANT, args, [agent], {"episode": 0, "global_step": 0})
    with pytest.raises(ckpt.UsageError, match="^--head-sigma .*--heads twohot"):
        script.main(script.Args(checkpoint=path, head_sigma=1.0, runs_dir=str(tmp_path / "run"), **E2E))
    assert not (tmp_path / "run").exists()


def test_a_run_from_a_checkpoint_takes_its_preset_unless_the_command_line_chooses(script, tmp_path, monkeypatch):
    """`--stage ghost --checkpoint <a --preset cpu run's best.pt>` goes on at the CPU preset (two env steps per
    decision, its batch and horizon), not at the paper's settings the default --preset would give; --preset, or a
    preset flag given again, still chooses. The look at its preset maps the file: its weights are read once, by the
    run's set-up."""
    args = script.preset_args("cpu", **TINY)
    path = str(tmp_path / "cpu.pt")
    ckpt.save_checkpoint(path, script.VARIANT, args, [script.Agent(args)], {"episode": 0, "global_step": 0})
    cpu, paper = script.PRESETS["cpu"], script.Args()
    assert cpu["action_repeat"] != paper.action_repeat and cpu["batch_size"] != paper.batch_size  # a test that can fail
    loads, torch_load = [], torch.load
    monkeypatch.setattr(torch, "load", lambda *a, **k: loads.append(k.get("mmap", False)) or torch_load(*a, **k))
    taken, explicit = run_tools.parse_args(script, ["--stage", "ghost", "--checkpoint", path])
    assert taken.preset == "cpu" and "preset" not in explicit and loads == [True]
    assert (taken.action_repeat, taken.batch_size) == (cpu["action_repeat"], cpu["batch_size"])
    chosen, _ = run_tools.parse_args(script, ["--checkpoint", path, "--preset", "paper"])
    assert (chosen.preset, chosen.action_repeat, chosen.batch_size) == ("paper", paper.action_repeat, paper.batch_size)
    flag, _ = run_tools.parse_args(script, ["--checkpoint", path, "--action-repeat", "3"])
    assert (flag.preset, flag.action_repeat, flag.batch_size) == ("cpu", 3, cpu["batch_size"])
    fresh, _ = run_tools.parse_args(script, ["--stage", "single"])  # without a checkpoint, the default preset
    assert fresh.preset == "paper" and fresh.action_repeat == paper.action_repeat


def test_a_run_says_why_it_stopped_also_when_resumed_at_its_end(tmp_path, capsys):
    """A run that has reached --total-episodes, resumed without more races, says so instead of exiting silently
    with a full progress bar; so does every run at its end."""
    import dreamer_lstm

    args = dreamer_lstm.Args(stage="single", runs_dir=str(tmp_path), **{**E2E, "total_episodes": 1, "eval_every": 1})
    run_dir = dreamer_lstm.main(args)
    assert f"{run_dir}: stopped after race 1: --total-episodes 1 races run" in capsys.readouterr().out
    assert dreamer_lstm.main(dataclasses.replace(args, resume=run_dir)) == run_dir
    assert f"{run_dir}: stopped after race 1: --total-episodes 1 races run (a --resume with more races continues it)" \
        in capsys.readouterr().out
