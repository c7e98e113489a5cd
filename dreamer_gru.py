# GRU-Dreamer (the Dreamer-v3 baseline) for decentralized multi-car racing, in one file (CleanRL style).
# Method: "Deep Latent Competition V1: Decentralized multi-car racing with LSTM-Dreamer-V3" (DLC-v1).
# Usage: `python dreamer_gru.py --seed 1` (or `--preset cpu`), then `tensorboard --logdir runs`; docs/agent.md.
"""GRU-Dreamer: a world model learned from pixels, an actor and a critic trained in its imagination.

Read top to bottom:

1. Args ............ every hyperparameter (the paper's defaults) and the CPU preset
2. Environment ..... the vectorized race (one slot per car), frame preprocessing, dead-zone schedule
3. Networks ........ encoder, recurrent core (GRU with a learned initial h), posterior/prior,
                     decoder, reward, continue, actor, critic (paper appendix)
4. Losses .......... Gaussian likelihoods and KL, free bits, lambda-returns (paper 3.8-3.9)
5. Replay .......... per-agent ring buffer of uint8 frames, uniform sequence sampling
6. Agent ........... world-model update, imagination, actor and critic updates, acting
7. Training loop ... Algorithm 1: decentralized agents act, store, train; stages single / ghost / race
8. Infrastructure .. validation, memory, set-up and resume, atomic checkpoints, command line

Everything that depends on the recurrent cell is inside `RecurrentCell` (its state is a tuple of
tensors; the model state fed to every head is z||h). The LSTM script (dreamer_lstm.py) is this file
with that class and the defaults changed.
"""

from __future__ import annotations

import contextlib
import copy
import ctypes
import dataclasses
import glob
import itertools
import json
import math
import os
import platform
import random
import sys
import time
from collections import deque
from typing import Annotated, Literal

import cv2
import numpy as np
import torch
import torch.nn.functional as F
import tyro
from torch import nn

VARIANT = "gru"  # written into every checkpoint, so race.py knows which script built the agent


# =====================================================================================
# 1. Arguments (defaults: the paper and its authors' code, GRU column; docs/agent.md)
# =====================================================================================
@dataclasses.dataclass
class Args:
    # --- experiment
    preset: Literal["paper", "cpu"] = "paper"
    """paper: the paper's sizes and schedule; cpu: a configuration that learns on a 2-core CPU in hours
    (explicit flags override the preset's values; docs/deviations.md lists what it changes)"""
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment (part of the run name)"""
    seed: int = 1
    """seed of python, numpy, torch and of the training tracks"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """use CUDA when it is available (else the CPU)"""
    torch_threads: int = 0
    """number of CPU threads of torch (0: torch's default)"""
    malloc_fix: bool = True
    """keep freed memory in the process (glibc mallopt, docs/agent.md): halves update time on these VMs"""
    compile: bool = False
    """torch.compile the networks (same losses up to float rounding; minutes of compiling at the start)"""
    amp: Literal["auto", "on", "off"] = "auto"
    """bfloat16 autocast of the update's forward passes (losses stay float32); auto: on with CUDA, off on the CPU"""
    runs_dir: str = "runs"
    """directory holding the run directories `{env_id}__{exp_name}__{seed}__{time}`"""
    resume: str | None = None
    """continue a run: its run directory or a checkpoint file (saved args and counters are used)"""
    checkpoint: str | None = None
    """start the agents' networks and optimisers from this checkpoint (e.g. a single-stage best.pt for ghost), and
    their replays from the replay saved beside it"""
    fresh_replay: bool = False
    """--checkpoint: start with empty replays instead of the one saved beside the checkpoint"""
    stage: Literal["single", "ghost", "race"] = "race"
    """single: one car, evaluation and best.pt; ghost: one car against its best previous run; race: N learning cars"""

    # --- environment
    env_id: str = "multi_car_racing"
    """environment id of utils.make_vec_env ("multi_car_racing" or e.g. "highway-intersection")"""
    num_agents: int = 2
    """cars per race, one independent agent each (stages single and ghost use 1)"""
    num_races: int = 1
    """K races stepped side by side (K * num_agents vec-env slots); an agent trains after every race that ends"""
    use_subprocess: bool = False
    """run every race in its own worker process"""
    max_steps: int = 1000
    """env: a race is truncated after this many steps (CarRacing's 1000)"""
    stall_steps: int = 150
    """env: a car that touches no new tile for this many steps is eliminated"""
    brake_speed_threshold: float = 50.0
    """env: braking has no effect below this speed"""
    collision_penalty: float = 0.05
    """env: reward paid per step while a car's hull touches another car"""
    offroad_penalty: float = 100.0
    """env: reward paid once when a car is eliminated (off road, off the playfield, stalled)"""
    speed_reward_coef: float = 0.0
    """env: reward per step per unit of forward speed along the track"""
    dead_zone_start: float = -1.0
    """dead-zone lower edge of the throttle-brake axis at episode 0 (a run from --checkpoint races at the end value)"""
    dead_zone_end: float = -0.5
    """dead-zone lower edge after the schedule (the paper's -0.5)"""
    dead_zone_episodes: int = 200
    """episodes over which the dead zone moves linearly from start to end"""
    action_repeat: int = 1
    """repeat every action this many env steps, summing rewards"""

    # --- training loop (Algorithm 1)
    total_episodes: int = 1000
    """races to run (counting prefill races)"""
    total_updates: int = 0
    """stop after the first race at which every agent has made this many updates (0: no limit)"""
    time_limit_hours: float = 0.0
    """stop after the first race that ends past this many hours of this process, with checkpoints (0: no limit)"""
    cpu_hours_limit: float = 0.0
    """stop, with checkpoints, once the run has used this many CPU-hours (checked at the start and at the end of every
    race): process CPU time summed over every sitting of a resumed run (0: no limit); unlike wall time it does not
    depend on what else the machine runs"""
    prefill_episodes: int = 5
    """random-action races before the first update (from a --checkpoint the agent's own policy fills replay)"""
    train_steps_per_episode: int = 200
    """updates per agent after every finished race"""
    replay_capacity: int = 100_000
    """replay buffer capacity per agent, in steps"""
    eval_every: int = 20
    """evaluate every this many races (--eval-policy on held-out tracks); best.pt keeps the best"""
    eval_episodes: int = 10
    """races per evaluation"""
    eval_policy: Literal["deterministic", "mean-action", "stochastic"] = "mean-action"
    """evaluation's policy: deterministic = posterior mean z and mean action; mean-action = sampled z, mean action;
    stochastic = sampled z and action (the policy that was optimised). The mean action by default: a rule fixed
    before it was measured found it drives better than the sampled action after 8,000 updates (six runs, paired,
    95% interval above 0; early in training the mean-action car can stall where the sampled one drives:
    docs/learning.md)"""
    eval_checkpoints: bool = False
    """also keep checkpoints/eval_<race>.pt at every evaluation (the policy as evaluated, for later analysis)"""
    eval_seed: int = 10_000
    """held-out evaluation tracks use seeds eval_seed + i"""
    ghost_tracks: int = 5
    """ghost stage: number of fixed track seeds, one ghost each"""
    ghost_seed: int = 20_000
    """ghost stage: the tracks use seeds ghost_seed + j"""
    video_every: int = 50
    """log a video (real | reconstruction | open-loop imagination) every this many races (0: never)"""
    video_length: int = 100
    """steps per video"""
    checkpoint_every: int = 1
    """write checkpoints/latest.pt every this many races"""
    replay_save_every: int = 1
    """save the replay buffers beside the checkpoints every this many races (0: never); a resume restores the
    replay as of its last save, so 1 makes a resume exact (only the chunks a race changed are written)"""
    print_table: bool = False
    """also print the logger's table of every race on stdout (TensorBoard and progress.csv always have it)"""
    max_nonfinite_updates: int = 20
    """stop the run (with a checkpoint) after this many updates in a row with a non-finite loss or gradient"""

    # --- world model, actor, critic (paper Algorithm 1 and appendix; the paper authors' configurations)
    batch_size: int = 50
    """B: sequences per update"""
    seq_len: int = 50
    """L: length of every sampled sequence"""
    imagination_horizon: int = 15
    """H: imagined steps per start"""
    imagination_starts: int = 0
    """imagination starts per update, a random subset of the B*L posterior states (0: all B*L)"""
    model_lr: float = 6e-4
    """Adam learning rate of the world model"""
    critic_lr: float = 6e-4
    """Adam learning rate of the critic"""
    actor_lr: float = 1e-4
    """Adam learning rate of the actor"""
    entropy_coef: float = 1.0
    """alpha: weight of -log pi in the lambda-return (the paper's entropy regulariser; 1.0 in the paper authors'
    configurations. Algorithm 1's "alpha = 0.0006" is the model's and critic's learning rate, not this)"""
    entropy_target: float | None = None
    """adapt alpha so that the policy's entropy (-log pi, as in the lambda-return) per action dimension tends to this
    many nats: SAC's automatic temperature (Haarnoja et al., 2018), alpha starting at --entropy-coef. None: alpha
    stays --entropy-coef"""
    entropy_lr: float = 1e-3
    """Adam learning rate of log alpha (--entropy-target)"""
    action_penalty: float | None = None
    """weight of log pi's extreme-action term -log(1 - tanh(a)^2) in the lambda-return, apart from alpha, which then
    weighs the Gaussian part alone (and --entropy-target its entropy). None: alpha weighs both (the paper). The term
    keeps actions off +-1: at a fixed weight it keeps the mean action smooth while a lower alpha narrows sigma"""
    return_norm: bool = False
    """DreamerV3's return normalisation: scale the task part of the lambda-return by 1 / max(1, S), S an EMA of
    its 95th - 5th percentile range; the entropy part stays unscaled (DreamerV3 pairs it with --entropy-coef 3e-4)"""
    reward_nll_beta: float = 0.0
    """beta of the reward head's beta-NLL (Seitzer et al., ICLR 2022): each step's Gaussian NLL weighted by the
    stop-gradient sigma^(2 beta), so that a rare large reward (an elimination's -100) moves the head's mean and not
    only its sigma. 0: the paper's Gaussian NLL; 0.5: the value Seitzer et al. recommend; 1: the mean learns as
    with a squared error"""
    head_sigma: float = 0.0
    """sigma of the reward and critic Gaussians: 0 learns it (softplus + 0.1, the paper); a positive value fixes it
    (1: the paper authors' code, a squared error, so that a rare -100 moves the mean instead of widening sigma)"""
    lambda_: Annotated[float, tyro.conf.arg(name="lambda")] = 0.95
    """lambda of the lambda-return"""
    gamma: float = 0.99
    """discount factor"""
    tau: float = 0.005
    """soft-update rate of the target networks, after every optimiser step"""
    free_bits: float = 1.0
    """free nats per step of each KL term: max(free_bits, KL)"""
    kl_dyn_scale: float = 1.0
    """beta_dyn: weight of L_dyn = max(free_bits, KL(sg(posterior) || prior))"""
    kl_rep_scale: float = 1.0
    """beta_rep: weight of L_rep = max(free_bits, KL(posterior || sg(prior)))"""
    decoder_min_log_sigma: float = -5.0
    """floor of the decoder's learned log sigma (paper: learned; 0 gives Dreamer's unit-variance pixel loss)"""
    grad_clip: float = 100.0
    """global gradient-norm clip of every optimiser"""
    target_critic: bool = True
    """bootstrap the lambda-returns with a slow target critic (soft-updated with tau) instead of the critic itself"""

    # --- network sizes (paper appendix; --preset cpu uses smaller ones)
    image_size: Literal[96, 64] = 96
    """what the encoder sees (64 resizes the 96x96 camera)"""
    cnn_depth: int = 32
    """channels of the first conv layer (doubling per layer: 32-64-128-256)"""
    deter_size: int = 512
    """size of the recurrent state h (and c)"""
    hidden_size: int = 1024
    """width of the encoder embedding, the recurrent input layer and the posterior/prior MLPs"""
    mlp_size: int = 512
    """width of the reward, continue, actor and critic MLPs"""
    latent_size: int = 60
    """size of the stochastic latent z"""
    norm: Literal["batch", "layer", "mixed"] = "batch"
    """normalisation of the networks (the critic always uses LayerNorm, as in the appendix); mixed: BatchNorm in the
    convolutions, LayerNorm in every MLP and the recurrent input (the paper authors' code)"""


# --preset cpu: a configuration that learns on a 2-core CPU in hours (docs/deviations.md); explicit flags override it.
# Smaller networks and 64 px frames; 2 env steps per decision; 20 random prefill races (they end off the road
# after ~50 steps); 100 updates per race; the dead-zone schedule within the first 30 races; evaluation every 5;
# a unit-variance pixel likelihood (log sigma floored at 0: with a learned sigma kl_dyn grew without bound on CPU runs).
# It keeps the paper's LSTM-vs-GRU trade: the same imagined steps per update (B * L * H with all starts), the
# LSTM with a small batch and a long horizon (paper: B=15, H=50), the GRU with a larger batch and a short one
# (paper: B=50, H=15).
PRESETS: dict[str, dict] = {
    "paper": {},
    "cpu": {
        "cnn_depth": 16, "deter_size": 256, "hidden_size": 256, "mlp_size": 256, "image_size": 64, "seq_len": 32,
        "imagination_starts": 0, "action_repeat": 2, "prefill_episodes": 20, "train_steps_per_episode": 100,
        "dead_zone_episodes": 30, "eval_every": 5, "video_every": 25, "decoder_min_log_sigma": 0.0,
        "batch_size": 16, "imagination_horizon": 15,  # 16 * 32 * 15 = 7,680 imagined steps per update
    },
}  # fmt: skip
def preset_args(preset: str = "paper", **overrides) -> Args:
    """Args of a preset with `overrides` on top (the Python form of `--preset NAME --flag value ...`)."""
    if preset not in PRESETS:
        raise UsageError(f"--preset must be one of {sorted(PRESETS)}, got {preset!r}")
    return dataclasses.replace(Args(preset=preset), **{**PRESETS[preset], **overrides})



# =====================================================================================
# 2. Environment
# =====================================================================================
def env_kwargs(args: Args, dead_zone: float) -> dict:
    """Keyword arguments of the env constructor (the racing env's options; other envs get num_agents only)."""
    if args.env_id != "multi_car_racing":
        return {"num_agents": args.num_agents}
    return {
        "num_agents": args.num_agents,
        "max_steps": args.max_steps,
        "stall_steps": args.stall_steps,
        "brake_speed_threshold": args.brake_speed_threshold,
        "collision_penalty": args.collision_penalty,
        "offroad_penalty": args.offroad_penalty,
        "speed_reward_coef": args.speed_reward_coef,
        "dead_zone": dead_zone,
    }


def dead_zone_at(episode: int, args: Args) -> float:
    """Linear dead-zone schedule: dead_zone_start at episode 0 to dead_zone_end at dead_zone_episodes. It is a
    warm-up for learning from scratch: a run whose agents start from a --checkpoint races at dead_zone_end."""
    if args.checkpoint is not None:
        return args.dead_zone_end
    frac = min(1.0, episode / max(1, args.dead_zone_episodes))
    return args.dead_zone_start + frac * (args.dead_zone_end - args.dead_zone_start)


def race_seed(seed: int, episode: int) -> int:
    """Track seed of training race `episode` (one race at a time): fixed by the run's seed and the episode number,
    so a resumed run drives the very tracks the uninterrupted run would have."""
    return int(np.random.SeedSequence([seed, episode]).generate_state(1)[0])


def preprocess_frames(frames: np.ndarray, image_size: int) -> np.ndarray:
    """Camera frames (n, 96, 96, 3) uint8 -> what the encoder sees (n, S, S, 3) uint8 (area resize)."""
    frames = np.asarray(frames, dtype=np.uint8)
    if frames.shape[-3] == image_size and frames.shape[-2] == image_size:
        return frames
    return np.stack([cv2.resize(f, (image_size, image_size), interpolation=cv2.INTER_AREA) for f in frames])


def step_with_repeat(envs, actions: np.ndarray, repeat: int):
    """Step the vec env `repeat` times with the same actions, summing rewards.

    Stops early at the first step in which any slot is done, so that a terminal observation or the
    first observation of a new race is never stepped over. Also returns the number of env steps taken.
    """
    total = np.zeros(envs.num_envs, dtype=np.float32)
    for repeats in range(1, repeat + 1):
        obs, rewards, dones, infos = envs.step(actions)
        total += rewards
        if dones.any():
            break
    return obs, total, dones, infos, repeats


# =====================================================================================
# 3. Networks (paper appendix)
# =====================================================================================
LATENT_MIN_STD = 0.1  # sigma of posterior and prior: softplus(.) + this minimum
LOG_SIGMA_RANGE = (-5.0, 2.0)  # bounds of the decoder's log sigma (--decoder-min-log-sigma raises the floor)
HEAD_MIN_STD = 0.1  # sigma of the reward and critic Gaussians
ACTOR_STD_BOUNDS = (0.1, 1.0)  # the paper authors' soft bounds of the actor's sigma (0.1 .. 1.34: soft_bounded)
RETURN_NORM_RATE = 0.01  # --return-norm: EMA rate of the return scale (DreamerV3)
EVAL_POLICIES = ("deterministic", "mean-action", "stochastic")  # Agent.act's policies (--eval-policy)
ACTING_PARTS = ("encoder.", "recurrent_input.", "cell.", "representation.")  # the world model's share of acting


def norm_1d(kind: str, size: int) -> nn.Module:
    return nn.BatchNorm1d(size) if kind == "batch" else nn.LayerNorm(size)


def norm_2d(kind: str, channels: int) -> nn.Module:
    # GroupNorm with one group normalises over (C, H, W): the layer norm of a feature map
    return nn.BatchNorm2d(channels) if kind in ("batch", "mixed") else nn.GroupNorm(1, channels)


def frames_to_input(frames: torch.Tensor) -> torch.Tensor:
    """uint8 frames (..., H, W, 3) -> float (..., 3, H, W) scaled to [-0.5, 0.5] (paper appendix)."""
    return frames.movedim(-1, -3).float() / 255.0 - 0.5


def input_to_frames(images: torch.Tensor) -> torch.Tensor:
    """Inverse of frames_to_input: float (..., 3, H, W) -> uint8 (..., H, W, 3)."""
    return ((images + 0.5) * 255.0).clamp(0, 255).to(torch.uint8).movedim(-3, -1)


class MLP(nn.Module):
    """[Linear -> norm -> SiLU] per hidden layer, then a Linear output; accepts inputs of shape (..., in)."""

    def __init__(self, in_size: int, hidden_sizes: list[int], out_size: int, norm: str):
        super().__init__()
        layers, size = [], in_size
        for hidden in hidden_sizes:  # no bias before a norm layer: the norm's shift replaces it
            layers += [nn.Linear(size, hidden, bias=False), norm_1d(norm, hidden), nn.SiLU()]
            size = hidden
        layers.append(nn.Linear(size, out_size))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-1]
        return self.net(x.reshape(-1, x.shape[-1])).reshape(*lead, -1)


class Encoder(nn.Module):
    """Conv(3->d->2d->4d->8d, kernel 4, stride 2) with norm and LeakyReLU, then Linear to the embedding e."""

    def __init__(self, depth: int, image_size: int, embed_size: int, norm: str):
        super().__init__()
        channels, layers, size = [3, depth, 2 * depth, 4 * depth, 8 * depth], [], image_size
        for c_in, c_out in itertools.pairwise(channels):
            layers += [nn.Conv2d(c_in, c_out, 4, 2, bias=False), norm_2d(norm, c_out), nn.LeakyReLU()]
            size = (size - 4) // 2 + 1  # 96 -> 47 -> 22 -> 10 -> 4 (64 -> 31 -> 14 -> 6 -> 2)
        self.convs = nn.Sequential(*layers, nn.Flatten())
        self.fc = nn.Linear(8 * depth * size * size, embed_size)  # 4096 -> 1024 at the paper's size

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """uint8 frames (..., S, S, 3) -> embeddings (..., embed_size); all frames in one batched call."""
        lead = frames.shape[:-3]
        x = frames_to_input(frames.reshape(-1, *frames.shape[-3:]))
        return self.fc(self.convs(x)).reshape(*lead, -1)


def conv_transpose_as_subpixel(x: torch.Tensor, layer: nn.ConvTranspose2d) -> torch.Tensor:
    """layer(x) for a transposed conv with stride s, kernel k = m*s, no padding, as a conv and pixel_shuffle(s).

    Output pixel s*q + r only sees inputs q-m+1 .. q, through kernel taps r, r+s, ..., so each of the s*s
    output phases r is an ordinary m x m conv of the input: one conv with s*s times the output channels,
    then pixel_shuffle interleaves the phases. Same function and parameters (float rounding aside); for the
    decoder's last layer (k12 s4, 750 frames) oneDNN runs this in 0.18 s forward instead of 0.44 s (measured).
    """
    weight, s = layer.weight, layer.stride[0]  # weight (c_in, c_out, k, k)
    c_in, c_out, k, _ = weight.shape
    m = k // s
    weight = weight.reshape(c_in, c_out, m, s, m, s).flip(2, 4)  # tap m*s + r -> (m, r); flip: conv, not correlation
    weight = weight.permute(1, 3, 5, 0, 2, 4).reshape(c_out * s * s, c_in, m, m)  # channel c*s*s + r_y*s + r_x
    bias = None if layer.bias is None else layer.bias.repeat_interleave(s * s)
    return F.pixel_shuffle(F.conv2d(x, weight, bias, padding=m - 1), s)


class Decoder(nn.Module):
    """Linear(z||h -> 2d*s*s), reshape (2d, s, s), ConvT 2d->2d (k3 s1), 2d->d (k4 s2), d->3 (k12 s4).

    At 96 px s = 8 (8 -> 10 -> 22 -> 96, the appendix's 64-channel decoder for d = 32); at 64 px s = 4
    (4 -> 6 -> 14 -> 64). The output is the mean of a Gaussian over pixels with one learned log sigma
    (clamped below at --decoder-min-log-sigma).
    """

    def __init__(self, feature_size: int, depth: int, image_size: int, norm: str, min_log_sigma: float):
        super().__init__()
        self.min_log_sigma = min_log_sigma
        self.start, self.channels = (8 if image_size == 96 else 4), 2 * depth
        c = self.channels
        self.fc = nn.Linear(feature_size, c * self.start * self.start, bias=False)
        self.net = nn.Sequential(
            norm_2d(norm, c), nn.LeakyReLU(),
            nn.ConvTranspose2d(c, c, 3, 1, bias=False), norm_2d(norm, c), nn.LeakyReLU(),
            nn.ConvTranspose2d(c, depth, 4, 2, bias=False), norm_2d(norm, depth), nn.LeakyReLU(),
            nn.ConvTranspose2d(depth, 3, 12, 4),
        )  # fmt: skip
        self.log_sigma = nn.Parameter(torch.zeros(()))  # one learned log sigma for every pixel

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """features (..., F) -> image means (..., 3, S, S) in input scale; all steps in one batched call."""
        lead = features.shape[:-1]
        x = self.fc(features.reshape(-1, features.shape[-1])).reshape(-1, self.channels, self.start, self.start)
        x = conv_transpose_as_subpixel(self.net[:-1](x), self.net[-1])  # = self.net(x), faster on CPU
        return x.float().reshape(*lead, *x.shape[1:])  # float32 for the loss, also under --amp

    def sigma(self) -> torch.Tensor:
        # A floor at 0 with log sigma starting at 0 fixes sigma = 1: the pixel term keeps its weight
        # against the KL instead of growing as the reconstructions sharpen (docs/learning_history.md).
        return self.log_sigma.clamp(self.min_log_sigma, LOG_SIGMA_RANGE[1]).exp()


class RecurrentCell(nn.Module):
    """The recurrent core: nn.GRUCell with a learned initial state (Dreamer-v3's deterministic path).

    This class is the seam between the LSTM and GRU scripts: the rest of the file only calls
    `initial_state(batch)` (a tuple of tensors) and `step(state, x) -> (new_state, h)`, and treats
    the state as an opaque tuple. The GRU state is (h,); h is the deterministic part of the model
    state s = (z, h). The initial h is a parameter, so the optimiser learns it.
    """

    def __init__(self, input_size: int, deter_size: int):
        super().__init__()
        self.cell = nn.GRUCell(input_size, deter_size)
        self.initial_h = nn.Parameter(torch.zeros(deter_size))

    def initial_state(self, batch: int) -> tuple[torch.Tensor, ...]:
        return (self.initial_h.expand(batch, -1),)

    def step(self, state: tuple[torch.Tensor, ...], x: torch.Tensor) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
        h = self.cell(x, state[0])
        return (h,), h


class Representation(nn.Module):
    """Posterior q(z_t | h_t, e_t): MLP on e||h (3 layers, hidden 1024, SiLU, norm), Gaussian mu(60), sigma(60).

    The first layer is written as two bias-free Linears, W [e; h] = W_e e + W_h h: the same function and
    parameter count as one Linear on e||h, but `embed_part` (W_e e) runs once for all B*L frames before
    the recurrence, which then only adds W_h h at every step.
    """

    def __init__(self, embed_size: int, deter_size: int, hidden_size: int, latent_size: int, norm: str):
        super().__init__()
        self.embed_in = nn.Linear(embed_size, hidden_size, bias=False)
        self.deter_in = nn.Linear(deter_size, hidden_size, bias=False)
        self.first_norm = nn.Sequential(norm_1d(norm, hidden_size), nn.SiLU())
        self.rest = MLP(hidden_size, [hidden_size], 2 * latent_size, norm)

    def embed_part(self, embed: torch.Tensor) -> torch.Tensor:
        return self.embed_in(embed)

    def forward(self, embed_part: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        x = embed_part + self.deter_in(h)
        lead = x.shape[:-1]
        return self.rest(self.first_norm(x.reshape(-1, x.shape[-1]))).reshape(*lead, -1)


def gaussian_params(out: torch.Tensor, min_std: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Split a head's output into the mean and sigma (softplus plus a minimum) of a diagonal Gaussian, in float32
    (under --amp the head computed in bfloat16; distributions and losses do not)."""
    mean, raw_std = out.float().chunk(2, dim=-1)
    return mean, F.softplus(raw_std) + min_std


def head_gaussian(out: torch.Tensor, sigma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The reward's or the critic's Gaussian: sigma learned (gaussian_params, floored at HEAD_MIN_STD) when `sigma`
    is 0, else fixed at `sigma` (--head-sigma; the head's second output is then unused)."""
    mean, std = gaussian_params(out, HEAD_MIN_STD)
    return (mean, std) if sigma == 0 else (mean, torch.full_like(mean, sigma))


class WorldModel(nn.Module):
    """Encoder, recurrent core, representation (posterior), transition (prior), decoder, reward, continue.

    One step of the model (paper): h_t = f(h_{t-1}, z_{t-1}, a_{t-1}) (recurrent core),
    posterior z_t ~ q(z | h_t, e_t) (representation), prior z_t ~ p(z | h_t) (transition); the heads
    read the model state s_t = z_t || h_t.
    """

    def __init__(self, args: Args, action_dim: int):
        super().__init__()
        self.latent_size, self.action_dim = args.latent_size, action_dim
        feature_size = args.latent_size + args.deter_size
        self.encoder = Encoder(args.cnn_depth, args.image_size, args.hidden_size, args.norm)
        self.encoder.to(memory_format=torch.channels_last)  # oneDNN's conv layout on CPU: ~1.5x faster here
        self.recurrent_input = nn.Sequential(  # Linear(z||a -> 1024), then the cell (1024 -> 512)
            nn.Linear(args.latent_size + action_dim, args.hidden_size, bias=False),
            norm_1d(args.norm, args.hidden_size),
            nn.SiLU(),
        )
        self.cell = RecurrentCell(args.hidden_size, args.deter_size)
        hidden, latent = [args.hidden_size] * 2, args.latent_size
        self.representation = Representation(args.hidden_size, args.deter_size, args.hidden_size, latent, args.norm)
        self.transition = MLP(args.deter_size, hidden, 2 * latent, args.norm)  # on h
        self.decoder = Decoder(feature_size, args.cnn_depth, args.image_size, args.norm, args.decoder_min_log_sigma)
        self.decoder.to(memory_format=torch.channels_last)
        self.reward = MLP(feature_size, [args.mlp_size] * 2, 2, args.norm)
        self.cont = MLP(feature_size, [args.mlp_size] * 2, 1, args.norm)

    def reset_where(self, is_first: torch.Tensor, state: tuple, z: torch.Tensor, prev_action: torch.Tensor):
        """Where is_first, put the learned initial state, z = 0 and previous action = 0 (episode starts)."""
        mask = is_first.unsqueeze(-1)
        initial = self.cell.initial_state(z.shape[0])
        state = tuple(torch.where(mask, s0, s) for s0, s in zip(initial, state))
        return state, torch.where(mask, 0.0, z), torch.where(mask, 0.0, prev_action)

    def core_step(self, state, x):
        """Advance the recurrent core on x = z||a. Its state stays float32: under --amp the cell's matmuls run
        in bfloat16, and a bfloat16 state carried over 50 steps would round away what the cell remembers."""
        state, h = self.cell.step(state, self.recurrent_input(x))
        return tuple(s.float() for s in state), h.float()

    def observe_step(self, state, z, prev_action, embed_part, is_first, sample: bool = True):
        """One posterior step: reset at episode starts, advance the core, sample z_t ~ q(z | h_t, e_t).

        embed_part = representation.embed_part(e_t), the embedding's share of the posterior's first layer.
        """
        state, z, prev_action = self.reset_where(is_first, state, z, prev_action)
        state, h = self.core_step(state, torch.cat([z, prev_action], -1))
        mean, std = gaussian_params(self.representation(embed_part, h), LATENT_MIN_STD)
        z = mean + std * torch.randn_like(std) if sample else mean
        return state, h, z, mean, std

    def imagine_step(self, state, z, action, sample: bool = True):
        """One prior step: advance the core with (z, a), sample z ~ p(z | h) by rsample."""
        state, h = self.core_step(state, torch.cat([z, action], -1))
        mean, std = gaussian_params(self.transition(h), LATENT_MIN_STD)
        z = mean + std * torch.randn_like(std) if sample else mean
        return state, h, z

    def observe(self, embed: torch.Tensor, actions: torch.Tensor, is_first: torch.Tensor, sample: bool = True) -> dict:
        """Posterior over sequences: embed (B, L, E), actions (B, L, A) (action that led to frame t), is_first (B, L).

        The only Python loop of the world model; every sequence starts from the learned initial state.
        Returns stacked (B, L, .) tensors: states (tuple), h, z, post_mean, post_std.
        """
        batch, length = is_first.shape
        embed_part = self.representation.embed_part(embed)  # batched over all B*L frames, outside the loop
        state = self.cell.initial_state(batch)
        z = embed.new_zeros(batch, self.latent_size)
        out = {"states": [], "h": [], "z": [], "post_mean": [], "post_std": []}
        for t in range(length):
            state, h, z, mean, std = self.observe_step(
                state, z, actions[:, t], embed_part[:, t], is_first[:, t], sample
            )
            for key, value in zip(out, (state, h, z, mean, std)):
                out[key].append(value)
        out = {key: torch.stack(values, 1) if key != "states" else values for key, values in out.items()}
        out["states"] = tuple(torch.stack(parts, 1) for parts in zip(*out["states"]))
        return out


def soft_bounded(x: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """low + softplus(high - softplus(high - x) - low): smooth, increasing, ~x in between, above low, and
    saturating at low + softplus(high - low) (the actor's sigma: 0.1 .. 1.34 for the bounds (0.1, 1))."""
    return low + F.softplus(high - F.softplus(high - x) - low)


class Actor(nn.Module):
    """MLP 572->512->512->512->512->4 giving mu(2), sigma(2); the action is a ~ N(tanh(mu), sigma), clipped to
    [-1, 1] (the paper authors' form).

    The noise lives in action space with sigma softly bounded below by 0.1, so the policy keeps exploring
    even where its mean saturates; a tanh-squashed Gaussian has no such floor (the std of tanh(N(2, 0.05))
    is 0.004), and it collapsed to bang-bang steering in our runs (docs/learning_history.md).
    """

    def __init__(self, feature_size: int, mlp_size: int, action_dim: int, norm: str):
        super().__init__()
        self.net = MLP(feature_size, [mlp_size] * 4, 2 * action_dim, norm)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, raw_std = self.net(features).float().chunk(2, dim=-1)
        return torch.tanh(mean), soft_bounded(raw_std, *ACTOR_STD_BOUNDS)

    def sample(self, features: torch.Tensor, deterministic: bool = False):
        """a = tanh(mu) + sigma eps by rsample, and log pi(a) = sum_d [log N(a_d; tanh mu_d, sigma_d)
        - log(1 - tanh(a_d)^2 + 1e-6)] (paper 3.9: the second term penalises extreme actions). Returns the
        action clipped to [-1, 1] (what the env and the world model receive) and log pi (None if deterministic:
        the mean action)."""
        mean, std = self(features)
        if deterministic:
            return mean, None
        action = mean + std * torch.randn_like(std)
        return action.clamp(-1.0, 1.0), policy_log_prob(action, mean, std)


def policy_log_prob(action: torch.Tensor, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """log pi(a) = sum_d [log N(a_d; mean_d, sigma_d) - log(1 - tanh(a_d)^2 + 1e-6)] of the unclipped sample a
    (paper 3.9): the Gaussian's log density plus a penalty that grows with |a| (extreme_action_term)."""
    return (-gaussian_nll(action, mean, std) - torch.log(1 - torch.tanh(action).pow(2) + 1e-6)).sum(-1)


def extreme_action_term(action: torch.Tensor) -> torch.Tensor:
    """sum_d -log(1 - tanh(a_d)^2 + 1e-6): log pi's part that grows with |a| (0 at a = 0; --action-penalty)."""
    return -torch.log(1 - torch.tanh(action).pow(2) + 1e-6).sum(-1)


class Critic(nn.Module):
    """MLP 572->512->512->2 with LayerNorm (appendix): Gaussian over the lambda-return (sigma: head_gaussian)."""

    def __init__(self, feature_size: int, mlp_size: int, sigma: float = 0.0):
        super().__init__()
        self.net, self.sigma = MLP(feature_size, [mlp_size] * 2, 2, "layer"), sigma

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, std = head_gaussian(self.net(features), self.sigma)
        return mean.squeeze(-1), std.squeeze(-1)


# =====================================================================================
# 4. Losses and returns (paper 3.8 world model, 3.9 behaviour)
# =====================================================================================
def gaussian_nll(x: torch.Tensor, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """-log N(x; mean, std), elementwise."""
    return 0.5 * ((x - mean) / std).pow(2) + torch.log(std) + 0.5 * math.log(2 * math.pi)


def beta_nll(x: torch.Tensor, mean: torch.Tensor, std: torch.Tensor, beta: float) -> torch.Tensor:
    """gaussian_nll weighted by the stop-gradient std^(2 beta), elementwise: the beta-NLL of Seitzer et al. (ICLR
    2022). The mean's gradient is (mean - x) / std^(2 - 2 beta): at beta = 0 the Gaussian NLL's, which a large
    std all but silences; at beta = 1 a squared error's."""
    nll = gaussian_nll(x, mean, std)
    return nll if beta == 0 else nll * std.detach().pow(2 * beta)


def image_gaussian_nll(x: torch.Tensor, mean: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """-log N(x; mean, sigma) summed over the pixels (..., 3, S, S) of each image, with one sigma for all:
    sum((x - mean)^2) / (2 sigma^2) + P (log sigma + log(2 pi) / 2), so only two ops touch every pixel."""
    pixels = x.shape[-3] * x.shape[-2] * x.shape[-1]
    squared_error = (x - mean).pow(2).sum((-3, -2, -1))
    return 0.5 * squared_error / sigma.pow(2) + pixels * (torch.log(sigma) + 0.5 * math.log(2 * math.pi))


def gaussian_kl(mean_p, std_p, mean_q, std_q) -> torch.Tensor:
    """KL(N(mean_p, std_p) || N(mean_q, std_q)) of diagonal Gaussians, summed over the last (latent) dim."""
    return (torch.log(std_q / std_p) + (std_p.pow(2) + (mean_p - mean_q).pow(2)) / (2 * std_q.pow(2)) - 0.5).sum(-1)


def kl_free_bits(kl: torch.Tensor, free_bits: float) -> torch.Tensor:
    """max(free_bits, KL) per step: below free_bits nats the KL term has no gradient (paper: free bits 1.0)."""
    return torch.clamp(kl, min=free_bits)


def lambda_returns(rewards, continues, values, log_pi, gamma: float, lam: float, alpha: float) -> torch.Tensor:
    """Entropy-regularised lambda-returns of an imagined rollout, all tensors (H, N):

    rewards[t] = r_{t+1}, continues[t] = c_{t+1}, values[t] = V(s_{t+1}), log_pi[t] = log pi(a_t | s_t).
    R_H = V(s_H);  R_t = r_{t+1} - alpha * log pi_t + gamma * c_{t+1} * [(1 - lambda) V(s_{t+1}) + lambda R_{t+1}].
    (The paper prints lambda and 1 - lambda swapped and leaves gamma implicit; this is the recursion.)
    Returns R_0 .. R_{H-1}, shape (H, N). R is linear in (rewards, values, log_pi) for fixed continues, so
    lambda_returns(r, c, V, log_pi) = lambda_returns(r, c, V, 0) + lambda_returns(0, c, 0, log_pi): the task
    part and the entropy part, which --return-norm scales apart.
    """
    next_return = values[-1]
    returns = []
    for t in reversed(range(rewards.shape[0])):
        bootstrap = (1 - lam) * values[t] + lam * next_return
        next_return = rewards[t] - alpha * log_pi[t] + gamma * continues[t] * bootstrap
        returns.append(next_return)
    return torch.stack(returns[::-1])


def discount_weights(continues: torch.Tensor, gamma: float, start: torch.Tensor | None = None) -> torch.Tensor:
    """w_0 = start (default 1), w_{t+1} = w_t * gamma * c_{t+1} (stop-gradient): how much imagined step t counts.

    `start` is the continue flag of the imagination start (1 - terminated, as DreamerV3): a rollout from a
    terminal state imagines a future that does not exist, and gets weight 0."""
    first = torch.ones_like(continues[:1]) if start is None else start.to(continues.dtype)[None]
    return torch.cumprod(torch.cat([first, gamma * continues[:-1]], 0), 0).detach()


def return_range(returns: torch.Tensor) -> torch.Tensor:
    """95th minus 5th percentile of a batch of returns (DreamerV3's return scale, before its EMA)."""
    flat = returns.detach().float().flatten()
    return torch.quantile(flat, 0.95) - torch.quantile(flat, 0.05)


@torch.no_grad()
def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- target + tau (source - target), for parameters and float buffers (BatchNorm statistics)."""
    for t, s in zip(target.parameters(), source.parameters()):
        t.lerp_(s, tau)
    for t, s in zip(target.buffers(), source.buffers()):
        if t.dtype.is_floating_point:
            t.lerp_(s, tau)
        else:  # BatchNorm's num_batches_tracked
            t.copy_(s)


@contextlib.contextmanager
def frozen(*modules: nn.Module):
    """Parameters of `modules` take no gradient inside the block (gradients still flow through them)."""
    params = [p for m in modules for p in m.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


def imagine_rollout(world_model: WorldModel, actor: Actor, state: tuple, h, z, horizon: int):
    """Roll the prior forward `horizon` steps from detached start states, acting with the actor.

    Returns features s_0..s_H (H+1, N, F), log pi_0..log pi_{H-1} (H, N), the sampled actions before clipping
    (H, N, A; the model is given them clipped to [-1, 1]) and the actor's sigma at every step (H, N, A).
    Everything is reparameterised, so the actor loss backpropagates through the learned dynamics.
    """
    features, log_pis, samples, stds = [torch.cat([z, h], -1)], [], [], []
    for _ in range(horizon):
        mean, std = actor(features[-1])
        action = mean + std * torch.randn_like(std)  # Actor.sample, keeping sigma for the diagnostics
        log_pis.append(policy_log_prob(action, mean, std))
        samples.append(action)
        state, h, z = world_model.imagine_step(state, z, action.clamp(-1.0, 1.0))
        features.append(torch.cat([z, h], -1))
        stds.append(std)
    return torch.stack(features), torch.stack(log_pis), torch.stack(samples), torch.stack(stds)


# =====================================================================================
# 5. Replay (one per agent)
# =====================================================================================
class Replay:
    """Ring buffer of steps: uint8 frame (at --image-size), action that led to it, reward received with it,
    is_first, terminated.

    Frames are stored once (no separate next observation): a sequence of L steps holds L frames.
    Whole car episodes are added at once, so K parallel races never interleave inside the buffer;
    sequences may cross episode boundaries, which is_first marks. Capacity is in steps.
    """

    def __init__(self, capacity: int, image_size: int, action_dim: int = 2, chunk_size: int = 1000):
        self.capacity, self.chunk_size = int(capacity), int(chunk_size)
        self.obs = np.zeros((self.capacity, image_size, image_size, 3), dtype=np.uint8)  # pages are touched lazily
        self.action = np.zeros((self.capacity, action_dim), dtype=np.float32)
        self.reward = np.zeros(self.capacity, dtype=np.float32)
        self.is_first = np.zeros(self.capacity, dtype=bool)
        self.terminated = np.zeros(self.capacity, dtype=bool)
        self.next_index, self.size, self.total_steps, self.episodes = 0, 0, 0, 0
        self._dirty: set[int] = set()
        self._saved_to: str | None = None
        self._files: dict[int, str] = {}  # chunk -> its file in _saved_to

    @staticmethod
    def bytes_per_step(image_size: int, action_dim: int = 2) -> int:
        """Memory of one stored step: frame, action (float32), reward (float32), is_first, terminated."""
        return image_size * image_size * 3 + 4 * action_dim + 4 + 1 + 1

    def __len__(self) -> int:
        return self.size

    def add_episode(self, obs: np.ndarray, action: np.ndarray, reward: np.ndarray, terminated: np.ndarray) -> None:
        """Append one car episode: obs (T, S, S, 3); action[t] led to obs[t] (action[0] = 0); reward[t] came
        with obs[t]; terminated[t]: obs[t] is terminal (not set on truncation)."""
        length = len(obs)
        idx = (self.next_index + np.arange(length)) % self.capacity
        self.obs[idx], self.action[idx], self.reward[idx], self.terminated[idx] = obs, action, reward, terminated
        self.is_first[idx] = False
        self.is_first[idx[0]] = True
        self._dirty.update(np.unique(idx // self.chunk_size).tolist())
        self.next_index = int((self.next_index + length) % self.capacity)
        self.size = min(self.capacity, self.size + length)
        self.total_steps += length
        self.episodes += 1

    def can_sample(self, seq_len: int) -> bool:
        return self.size >= seq_len

    def sample(self, batch_size: int, seq_len: int, rng=np.random) -> dict[str, np.ndarray]:
        """B sequences of L consecutive steps, uniformly over all that do not cross the write position."""
        oldest = self.next_index if self.size == self.capacity else 0
        offsets = rng.randint(0, self.size - seq_len + 1, size=batch_size)
        idx = (oldest + offsets[:, None] + np.arange(seq_len)[None]) % self.capacity
        return {
            "obs": self.obs[idx],
            "action": self.action[idx],
            "reward": self.reward[idx],
            "is_first": self.is_first[idx],
            "terminated": self.terminated[idx],
        }

    def save(self, directory: str) -> dict:
        """Save as chunked compressed .npz files; returns the manifest (counters and chunk files) that `load` takes.

        Only chunks changed since the last save to the same directory are written, each to a new file (named by
        total_steps), then meta.npz with the manifest; every write is atomic. Files of earlier saves stay until
        `prune`, so a checkpoint holding an earlier manifest still loads: a kill at any moment loses nothing saved.
        """
        os.makedirs(directory, exist_ok=True)
        num_chunks = math.ceil(self.size / self.chunk_size)  # filled steps: [0, size) until the buffer wraps
        if self._saved_to != directory:
            self._files, changed = {}, range(num_chunks)
        else:
            changed = sorted(c for c in self._dirty if c < num_chunks)
        for c in changed:
            name = f"chunk_{c:05d}_{self.total_steps:012d}.npz"
            part = slice(c * self.chunk_size, min(self.size, (c + 1) * self.chunk_size))
            _atomic_npz(
                os.path.join(directory, name),
                obs=self.obs[part], action=self.action[part], reward=self.reward[part],
                is_first=self.is_first[part], terminated=self.terminated[part],
            )  # fmt: skip
            self._files[c] = name
        manifest = self.manifest()
        meta = {k: np.asarray(v, dtype=str) if k == "files" else np.asarray(v) for k, v in manifest.items()}
        _atomic_npz(os.path.join(directory, "meta.npz"), **meta)
        self._dirty.clear()
        self._saved_to = directory
        return manifest

    def load(self, directory: str, manifest: dict | None = None) -> None:
        """Restore a save: `manifest` (as a checkpoint holds it) or else the directory's meta.npz (the newest save)."""
        if manifest is None:
            with np.load(os.path.join(directory, "meta.npz")) as meta:
                manifest = {k: meta[k].tolist() for k in meta.files}
        if int(manifest["capacity"]) != self.capacity:
            raise ValueError(f"replay in {directory} has capacity {manifest['capacity']}, this buffer {self.capacity}")
        chunk_size = int(manifest["chunk_size"])
        if "files" in manifest:
            files = list(manifest["files"])
        else:  # the layout before chunk files were versioned
            files = [f"chunk_{c:05d}.npz" for c in range(manifest["num_chunks"])]
        for c, name in enumerate(files):
            with np.load(os.path.join(directory, name)) as chunk:
                start = c * chunk_size
                for key in ("obs", "action", "reward", "is_first", "terminated"):
                    getattr(self, key)[start : start + len(chunk[key])] = chunk[key]
        self.next_index, self.size = int(manifest["next_index"]), int(manifest["size"])
        self.total_steps, self.episodes = int(manifest["total_steps"]), int(manifest["episodes"])
        self.chunk_size = chunk_size
        self._files = dict(enumerate(files))
        self._dirty.clear()
        self._saved_to = directory

    def manifest(self) -> dict:
        """What the last save holds, in plain types (a checkpoint names it): counters and chunk files."""
        return {
            "capacity": self.capacity, "chunk_size": self.chunk_size, "next_index": self.next_index,
            "size": self.size, "total_steps": self.total_steps, "episodes": self.episodes,
            "files": [self._files[c] for c in range(len(self._files))],
        }  # fmt: skip

    @staticmethod
    def prune(directory: str, keep: dict) -> None:
        """Delete the chunk files (and leftover temporary files) of `directory` that manifest `keep` does not name."""
        keep_files = set(keep["files"])
        for path in glob.glob(os.path.join(directory, "chunk_*.npz*")):
            if os.path.basename(path) not in keep_files:
                with contextlib.suppress(OSError):
                    os.remove(path)


# =====================================================================================
# 6. Agent: world-model learning, behaviour learning in imagination, acting
# =====================================================================================
class Agent:
    """One car's learner: world model, actor, critic, their target networks and three Adam optimisers."""

    def __init__(self, args: Args, action_dim: int = 2, device: torch.device | str = "cpu"):
        self.args, self.action_dim, self.device = args, action_dim, torch.device(device)
        feature_size = args.latent_size + args.deter_size
        self.world_model = WorldModel(args, action_dim).to(self.device)
        self.actor = Actor(feature_size, args.mlp_size, action_dim, args.norm).to(self.device)
        self.critic = Critic(feature_size, args.mlp_size, args.head_sigma).to(self.device)
        # Target networks (hard copy now, soft updates later): the stop-gradient sides of the KL terms
        # and the slow critic for bootstrap values. They never receive gradient.
        self.targets = nn.ModuleDict(
            {
                "encoder": copy.deepcopy(self.world_model.encoder),
                "representation": copy.deepcopy(self.world_model.representation),
                "transition": copy.deepcopy(self.world_model.transition),
                "critic": copy.deepcopy(self.critic),
            }
        ).requires_grad_(False)
        self.targets.eval()  # targets always use their (soft-updated) running statistics
        self.model_optimizer = torch.optim.Adam(self.world_model.parameters(), lr=args.model_lr)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=args.actor_lr)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=args.critic_lr)
        self.log_alpha = None  # --entropy-target: alpha = exp(log_alpha), learned (SAC); else alpha = --entropy-coef
        if args.entropy_target is not None:
            self.log_alpha = nn.Parameter(torch.tensor(math.log(args.entropy_coef), device=self.device))
            self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=args.entropy_lr)
        if args.compile:  # in place (nn.Module.compile): parameter names, and so checkpoints, stay the same
            for module in (*self.world_model.children(), self.actor, self.critic, *self.targets.values()):
                module.compile()
        # --amp: bfloat16 autocast of the update (not of acting); needs no loss scaling, unlike float16
        self.amp = args.amp == "on" or (args.amp == "auto" and self.device.type == "cuda")
        self.acting_only = False  # True once an acting-only export is loaded
        self.return_scale = torch.zeros((), device=self.device)  # --return-norm: EMA of the returns' 5-95% range
        self.num_updates = 0
        self.nonfinite_updates = 0  # updates in which an optimiser step was skipped (non-finite loss or gradient)
        self.nonfinite_in_a_row = 0  # ... of the latest updates, in a row

    # --- modes -------------------------------------------------------------------------
    def autocast(self) -> torch.autocast:
        """The forward passes of an update: bfloat16 matmuls and convolutions under --amp, else float32."""
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.amp)

    def _set_training(self, training: bool) -> None:
        """Train mode (batch statistics) for updates, eval mode (running statistics) for acting."""
        if self.world_model.training != training or self.actor.training != training:
            for module in (self.world_model, self.actor, self.critic):
                module.train(training)

    def _update_targets(self) -> None:
        wm, tau = self.world_model, self.args.tau
        soft_update(self.targets["encoder"], wm.encoder, tau)
        soft_update(self.targets["representation"], wm.representation, tau)
        soft_update(self.targets["transition"], wm.transition, tau)

    # --- world model (paper 3.8) ------------------------------------------------------------
    def world_model_loss(self, obs, actions, rewards, is_first, terminated):
        """L = mean over batch and time of L_pred + beta_dyn L_dyn + beta_rep L_rep; also returns the posterior.

        (The paper sums over time; the mean differs by the constant factor L, as in Dreamer's own code,
        and keeps the gradient-clip threshold of 100 meaningful for any sequence length.)
        """
        args, wm = self.args, self.world_model
        embed = wm.encoder(obs)  # all B*L frames in one call
        post = wm.observe(embed, actions, is_first)  # the recurrence: the only Python loop
        h, z = post["h"], post["z"]
        features = torch.cat([z, h], -1)
        prior_mean, prior_std = gaussian_params(wm.transition(h), LATENT_MIN_STD)  # batched over B*L
        # L_pred: -log p(x|s) - log p(r|s) - log p(cont|s); cont = 1 - terminated (truncation is not termination)
        image_nll = image_gaussian_nll(frames_to_input(obs), wm.decoder(features), wm.decoder.sigma())
        reward_mean, reward_std = head_gaussian(wm.reward(features), args.head_sigma)
        reward_nll = gaussian_nll(rewards, reward_mean.squeeze(-1), reward_std.squeeze(-1))  # (logged as is)
        reward_loss = beta_nll(rewards, reward_mean.squeeze(-1), reward_std.squeeze(-1), args.reward_nll_beta)
        cont_logits = wm.cont(features).float().squeeze(-1)
        cont_nll = F.binary_cross_entropy_with_logits(cont_logits, 1.0 - terminated, reduction="none")
        # Stop-gradient sides of the KL terms come from the target networks, computed once per update.
        with torch.no_grad():
            target_embed = self.targets["encoder"](obs)
            target_representation = self.targets["representation"]
            target_post = target_representation(target_representation.embed_part(target_embed), h.detach())
            sg_post_mean, sg_post_std = gaussian_params(target_post, LATENT_MIN_STD)
            sg_prior_mean, sg_prior_std = gaussian_params(self.targets["transition"](h.detach()), LATENT_MIN_STD)
        kl_dyn = gaussian_kl(sg_post_mean, sg_post_std, prior_mean, prior_std)  # paper eq. L_dyn: trains the prior
        kl_rep = gaussian_kl(post["post_mean"], post["post_std"], sg_prior_mean, sg_prior_std)  # paper eq. L_rep
        loss = (
            image_nll + reward_loss + cont_nll
            + args.kl_dyn_scale * kl_free_bits(kl_dyn, args.free_bits)
            + args.kl_rep_scale * kl_free_bits(kl_rep, args.free_bits)
        ).mean()  # fmt: skip
        metrics = {
            "model_loss": loss, "reconstruction": image_nll.mean(), "reward": reward_nll.mean(),
            "continue": cont_nll.mean(), "kl_dyn": kl_dyn.mean(), "kl_rep": kl_rep.mean(),
        }  # fmt: skip
        return loss, metrics, post

    # --- behaviour (paper 3.9) ---------------------------------------------------------------
    def alpha(self) -> float | torch.Tensor:
        """The entropy weight of the lambda-return: --entropy-coef, or exp(log alpha) under --entropy-target."""
        return self.args.entropy_coef if self.log_alpha is None else self.log_alpha.detach().exp()

    def imagination_starts(self, post: dict, terminated: torch.Tensor):
        """Detached posterior states (state tuple, h, z) of all B*L steps, or a random subset of them, and each
        start's continue flag 1 - terminated."""
        state = tuple(s.flatten(0, 1).detach() for s in post["states"])
        h, z = post["h"].flatten(0, 1).detach(), post["z"].flatten(0, 1).detach()
        cont = 1.0 - terminated.flatten(0, 1)
        num = self.args.imagination_starts
        if 0 < num < h.shape[0]:
            idx = torch.randperm(h.shape[0], device=h.device)[:num]
            state, h, z, cont = tuple(s[idx] for s in state), h[idx], z[idx], cont[idx]
        return state, h, z, cont

    def behaviour_losses(self, post: dict, terminated: torch.Tensor):
        """Actor loss (backprop through the frozen dynamics) and critic loss on imagined rollouts.

        BatchNorm sees imagined states only through its running statistics: the world model's come from the
        real posterior states of its own loss, the actor's from a no-grad train-mode pass over the same real
        states here. Imagined states are never what the car sees (a 50-step imagination drifts away from the
        real state distribution), and acting uses the same running statistics as the policy optimised here.
        """
        args, wm = self.args, self.world_model
        with torch.no_grad():  # the actor's BatchNorm statistics: real posterior states of the batch
            self.actor.train()
            self.actor(torch.cat([post["z"], post["h"]], -1).detach())
        state, h, z, start_cont = self.imagination_starts(post, terminated)
        bootstrap = self.targets["critic"] if args.target_critic else self.critic
        wm.eval()
        self.actor.eval()
        with frozen(wm, self.critic):  # only the actor's parameters take gradient from the actor loss
            features, log_pi, samples, stds = imagine_rollout(wm, self.actor, state, h, z, args.imagination_horizon)
            rewards = head_gaussian(wm.reward(features[1:]), args.head_sigma)[0].squeeze(-1)  # r_1..r_H
            continues = torch.sigmoid(wm.cont(features[1:]).float().squeeze(-1))  # c_1..c_H
            values = bootstrap(features[1:])[0]  # V(s_1..s_H)
            weights = discount_weights(continues, args.gamma, start_cont)
            gamma, lam, zero, alpha = args.gamma, args.lambda_, torch.zeros_like(rewards), self.alpha()
            # the bonus -alpha log pi_t comes with r_{t+1}; --action-penalty beta reweighs its extreme-action part:
            # -alpha log pi + (alpha - beta) term = -alpha log N(a) - beta term (added where lambda_returns is linear)
            extra = None if args.action_penalty is None else (alpha - args.action_penalty) * extreme_action_term(samples)
            if args.return_norm:  # scale the task part only (lambda_returns is linear in r, V and log pi)
                task = lambda_returns(rewards, continues, values, torch.zeros_like(log_pi), gamma, lam, 0.0)
                entropy = lambda_returns(zero if extra is None else extra, continues, zero, log_pi, gamma, lam, alpha)
                with torch.no_grad():  # (a non-finite batch leaves the scale alone)
                    spread = return_range(task)
                    moved = self.return_scale.lerp(spread, RETURN_NORM_RATE)
                    self.return_scale.copy_(torch.where(spread.isfinite(), moved, self.return_scale))
                returns = task + entropy  # what the critic learns
                objective = task / self.return_scale.clamp(min=1.0) + entropy
            else:
                bonus_rewards = rewards if extra is None else rewards + extra
                returns = lambda_returns(bonus_rewards, continues, values, log_pi, gamma, lam, alpha)
                objective = returns
            actor_loss = -(weights * objective).mean()
        wm.train()
        self.actor.train()
        value_mean, value_std = self.critic(features[:-1].detach())  # V(s_0..s_{H-1}) on detached states
        critic_loss = (weights * gaussian_nll(returns.detach(), value_mean, value_std)).mean()
        metrics = {
            "actor": actor_loss, "critic": critic_loss, "entropy": -log_pi.mean(), "actor_std": stds.mean(),
            "imagined_return": returns.mean(),
        }  # fmt: skip
        if args.return_norm:
            metrics["return_scale"] = self.return_scale.clone()
        if self.log_alpha is not None:  # and the entropy alpha weighs (without the extreme-action term if apart)
            metrics["alpha"] = self.log_alpha.detach().exp()
            apart = 0 if args.action_penalty is None else extreme_action_term(samples.detach()).mean()
            metrics["alpha_entropy"] = -log_pi.detach().mean() + apart
        return actor_loss, critic_loss, metrics

    def _step(self, optimizer: torch.optim.Optimizer, loss: torch.Tensor, params) -> bool:
        """Backward, clip, step. A non-finite loss or gradient norm skips the step (the parameters and the
        optimiser's state stay as they were); returns whether the step was taken."""
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        norm = nn.utils.clip_grad_norm_(params, self.args.grad_clip)
        if not bool(torch.isfinite(loss.detach()) & torch.isfinite(norm)):
            optimizer.zero_grad(set_to_none=True)
            return False
        optimizer.step()
        return True

    def update(self, batch: dict) -> dict[str, float]:
        """One training update on a batch of B sequences of length L (numpy arrays from Replay.sample).

        Each optimiser step whose loss or gradient is not finite is skipped: its network, its BatchNorm
        statistics and its targets stay unchanged, and the update counts in nonfinite_updates."""
        if self.acting_only:
            raise RuntimeError("an acting-only export has no decoder, critic or optimiser state: it cannot learn")
        dev = self.device
        obs = torch.as_tensor(batch["obs"], device=dev)
        actions = torch.as_tensor(batch["action"], device=dev, dtype=torch.float32)
        rewards = torch.as_tensor(batch["reward"], device=dev, dtype=torch.float32)
        is_first = torch.as_tensor(batch["is_first"], device=dev, dtype=torch.bool)
        terminated = torch.as_tensor(batch["terminated"], device=dev, dtype=torch.float32)
        self._set_training(True)
        statistics = {m: [b.clone() for b in m.buffers()] for m in (self.world_model, self.actor)}  # BatchNorm

        with self.autocast():
            model_loss, metrics, post = self.world_model_loss(obs, actions, rewards, is_first, terminated)
        model_ok = self._step(self.model_optimizer, model_loss, self.world_model.parameters())
        if model_ok:
            self._update_targets()

        with self.autocast():
            actor_loss, critic_loss, behaviour_metrics = self.behaviour_losses(post, terminated)
        actor_ok = self._step(self.actor_optimizer, actor_loss, self.actor.parameters())
        critic_ok = self._step(self.critic_optimizer, critic_loss, self.critic.parameters())
        alpha_ok = True
        if self.log_alpha is not None:  # SAC: alpha rises while the entropy is below its target, falls above it
            shortfall = self.args.entropy_target * self.action_dim - behaviour_metrics["alpha_entropy"]
            alpha_ok = self._step(self.alpha_optimizer, -self.log_alpha * shortfall, [self.log_alpha])
        if self.args.target_critic and critic_ok:
            soft_update(self.targets["critic"], self.critic, self.args.tau)
        for module, ok in ((self.world_model, model_ok), (self.actor, actor_ok)):
            if not ok:  # the batch's forward pass moved the running statistics: put them back
                with torch.no_grad():
                    for buffer, saved in zip(module.buffers(), statistics[module]):
                        buffer.copy_(saved)
        self.num_updates += 1
        faulty = not (model_ok and actor_ok and critic_ok and alpha_ok)
        self.nonfinite_updates += int(faulty)
        self.nonfinite_in_a_row = self.nonfinite_in_a_row + 1 if faulty else 0

        metrics.update(behaviour_metrics)
        values = torch.stack([v.detach().float() for v in metrics.values()]).tolist()  # one host sync per update
        return dict(zip(metrics, values))

    # --- acting --------------------------------------------------------------------------
    def initial_state(self, n: int):
        """Recurrent state of n cars before their first frame: (cell state, z, previous action)."""
        with torch.no_grad():
            cell = tuple(s.clone() for s in self.world_model.cell.initial_state(n))
        z = torch.zeros(n, self.args.latent_size, device=self.device)
        return cell, z, torch.zeros(n, self.action_dim, device=self.device)

    @torch.no_grad()
    def act(self, obs: np.ndarray, state=None, is_first=None, policy: str = "stochastic"):
        """Actions for the n cars this agent drives: obs (n, H, W, 3) uint8, is_first (n,) bool.

        Returns actions (n, A) numpy in [-1, 1] and the new recurrent state. state=None starts every car
        fresh; is_first restarts the marked cars (a new race) and defaults to none. `policy` (EVAL_POLICIES):
        "stochastic" samples z from the posterior and the action from the actor (training); "mean-action"
        samples z and takes the actor's mean; "deterministic" takes the posterior mean and the actor's mean.
        """
        if policy not in EVAL_POLICIES:
            raise ValueError(f"policy must be one of {EVAL_POLICIES}, got {policy!r}")
        n = len(obs)
        if state is None:  # a fresh start for every car
            state, is_first = self.initial_state(n), np.ones(n, dtype=bool)
        is_first = np.zeros(n, dtype=bool) if is_first is None else np.asarray(is_first, dtype=bool)
        frames = torch.as_tensor(preprocess_frames(obs, self.args.image_size), device=self.device)
        self._set_training(False)  # BatchNorm uses its running statistics while acting
        cell, z, prev_action = state
        embed_part = self.world_model.representation.embed_part(self.world_model.encoder(frames))
        first = torch.as_tensor(is_first, device=self.device)
        sample_z = policy != "deterministic"
        cell, h, z, _, _ = self.world_model.observe_step(cell, z, prev_action, embed_part, first, sample_z)
        action, _ = self.actor.sample(torch.cat([z, h], -1), deterministic=policy != "stochastic")
        return action.cpu().numpy(), (cell, z, action)

    @torch.no_grad()
    def video(self, obs: np.ndarray, actions: np.ndarray, is_first: np.ndarray, context: int = 5) -> np.ndarray:
        """Video frames (T, S, 3S, 3) uint8: real | posterior reconstruction | open-loop imagination.

        The imagination sees the first `context` frames, then only the actions (prior steps)."""
        self._set_training(False)
        wm = self.world_model
        obs_t = torch.as_tensor(obs[None], device=self.device)
        actions_t = torch.as_tensor(actions[None], device=self.device, dtype=torch.float32)
        first = torch.as_tensor(is_first[None], device=self.device)
        post = wm.observe(wm.encoder(obs_t), actions_t, first, sample=False)
        recon = wm.decoder(torch.cat([post["z"], post["h"]], -1))[0]
        context = max(1, min(context, len(obs)))
        state = tuple(s[:, context - 1] for s in post["states"])
        z, imagined = post["z"][:, context - 1], [recon[:context]]
        for t in range(context, len(obs)):
            state, h, z = wm.imagine_step(state, z, actions_t[:, t], sample=False)
            imagined.append(wm.decoder(torch.cat([z, h], -1)))
        real = torch.as_tensor(obs, device=self.device)
        return torch.cat([real, input_to_frames(recon), input_to_frames(torch.cat(imagined))], dim=2).cpu().numpy()

    # --- persistence -------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "world_model": self.world_model.state_dict(),
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "targets": self.targets.state_dict(),
            "model_optimizer": self.model_optimizer.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "return_scale": self.return_scale.clone(),
            "num_updates": self.num_updates,
            "nonfinite_updates": self.nonfinite_updates,
            "nonfinite_in_a_row": self.nonfinite_in_a_row,
        } | ({} if self.log_alpha is None else {
            "log_alpha": self.log_alpha.detach().clone(), "alpha_optimizer": self.alpha_optimizer.state_dict(),
        })  # fmt: skip

    def acting_state_dict(self) -> dict:
        """What acting needs and nothing else: encoder, posterior, recurrent core (with its input layer), actor.
        No decoder, reward, continue, prior or critic, no targets, optimisers or replay (an exported policy)."""
        world_model = {k: v for k, v in self.world_model.state_dict().items() if k.startswith(ACTING_PARTS)}
        return {"world_model": world_model, "actor": self.actor.state_dict(), "num_updates": self.num_updates}

    def load_state_dict(self, state: dict) -> None:
        if "critic" not in state:  # an acting-only export: it drives, it cannot learn
            missing, unexpected = self.world_model.load_state_dict(state["world_model"], strict=False)
            missing = [k for k in missing if k.startswith(ACTING_PARTS)]
            if missing or unexpected:
                raise KeyError(f"acting-only state: missing {missing[:3]}, unexpected {unexpected[:3]}")
            self.actor.load_state_dict(state["actor"])
            self.num_updates, self.acting_only = int(state["num_updates"]), True
            return
        self.world_model.load_state_dict(state["world_model"])
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.targets.load_state_dict(state["targets"])
        self.model_optimizer.load_state_dict(state["model_optimizer"])
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        if "return_scale" in state:
            self.return_scale.copy_(state["return_scale"])
        if self.log_alpha is not None and "log_alpha" in state:  # (else alpha starts at --entropy-coef)
            with torch.no_grad():
                self.log_alpha.copy_(state["log_alpha"])
            self.alpha_optimizer.load_state_dict(state["alpha_optimizer"])
        self.num_updates = int(state["num_updates"])
        self.nonfinite_updates = int(state.get("nonfinite_updates", 0))
        self.nonfinite_in_a_row = int(state.get("nonfinite_in_a_row", 0))

    def save(self, path: str) -> None:
        _atomic_torch_save(self.state_dict(), path)

    def load(self, path: str) -> None:
        self.load_state_dict(torch.load(path, map_location=self.device, weights_only=True))


# =====================================================================================
# 7. Training loop (Algorithm 1)
# =====================================================================================
class CarEpisode:
    """One car's episode as it is being driven: frames at the encoder's size, the action that led to
    each frame (zero for the first), the reward that came with it, and whether it is a terminal state."""

    def __init__(self, first_frame: np.ndarray, action_dim: int = 2):
        self.obs, self.action = [first_frame], [np.zeros(action_dim, dtype=np.float32)]
        self.reward, self.terminated = [0.0], [False]
        self.ret, self.final_info = 0.0, None

    def add(self, frame, action, reward, terminated) -> None:
        self.obs.append(frame)
        self.action.append(np.asarray(action, dtype=np.float32))
        self.reward.append(float(reward))
        self.terminated.append(bool(terminated))
        self.ret += float(reward)

    def arrays(self) -> tuple[np.ndarray, ...]:
        reward, terminated = np.asarray(self.reward, np.float32), np.asarray(self.terminated)
        return np.stack(self.obs), np.stack(self.action), reward, terminated


def evaluate(agents: list[Agent], args: Args, eval_envs, policy: str | None = None, seeds=None) -> tuple:
    """Races with `policy` (default --eval-policy) on the tracks `seeds` (default: the held-out eval_seed + i, i <
    eval_episodes); per race and car the return, the final progress (fraction of tiles) and the mean |action[0]|
    of the car's decisions while racing, each (E, N). On the racing env action 0 is the steer: near 1 is bang-bang
    steering (the pursuit driver: ~0.06). `drive_races` has more readings of the same races."""
    readings = drive_races(agents, args, eval_envs, policy, seeds)
    return readings["return"], readings["progress"], readings["abs_steer"]


def drive_races(agents: list[Agent], args: Args, eval_envs, policy: str | None = None, seeds=None) -> dict:
    """`evaluate`'s races, with every reading per race and car, each an (E, N) array: return, progress, abs_steer;
    gas (mean of max(action[1], 0) over decisions), brake_share (share of decisions with action[1] at or below the
    dead zone's edge: braking), speed (mean over env steps while racing), lap_finished (within the time limit) and
    eliminated (off the road or stalled)."""
    n, policy = args.num_agents, policy or args.eval_policy
    seeds = [args.eval_seed + e for e in range(args.eval_episodes)] if seeds is None else list(seeds)
    keys = ("return", "progress", "abs_steer", "gas", "brake_share", "speed", "lap_finished", "eliminated")
    out = {key: np.zeros((len(seeds), n)) for key in keys}
    decisions, steps = np.zeros((len(seeds), n)), np.zeros((len(seeds), n))
    for e, seed in enumerate(seeds):
        eval_envs.seed(seed)
        obs, states, is_first = eval_envs.reset(), [None] * n, np.ones(n, dtype=bool)
        racing = np.ones(n, dtype=bool)
        while True:
            frames = preprocess_frames(obs, args.image_size)
            actions = np.zeros((n, 2), dtype=np.float32)
            for i, agent in enumerate(agents):
                car = slice(i, i + 1)
                actions[car], states[i] = agent.act(frames[car], states[i], is_first[car], policy)
            out["abs_steer"][e] += np.abs(actions[:, 0]) * racing
            out["gas"][e] += np.maximum(actions[:, 1], 0.0) * racing
            out["brake_share"][e] += (actions[:, 1] <= args.dead_zone_end) * racing
            decisions[e] += racing
            obs, rewards, dones, infos, _ = step_with_repeat(eval_envs, actions, args.action_repeat)
            out["return"][e] += rewards  # cars that are out get reward 0
            for i, info in enumerate(infos):
                if racing[i] and "speed" in info:  # (the speed after the decision's last env step)
                    out["speed"][e, i] += info["speed"]
                    steps[e, i] += 1
                racing[i] = info["alive"] and not dones[i]  # a car that went out this step decides no more
                if info["alive"]:
                    out["progress"][e, i] = info.get("progress", 0.0)
                    out["lap_finished"][e, i] = float(bool(info.get("lap_finished", False)))
                    out["eliminated"][e, i] = float(bool(info.get("eliminated")))
            if infos[0]["is_first"]:
                break
            is_first[:] = False
    for key in ("abs_steer", "gas", "brake_share"):
        out[key] /= np.maximum(decisions, 1)
    out["speed"] /= np.maximum(steps, 1)
    return out


def train_agent(agent: Agent, replay: Replay, args: Args, logger, prefix: str, on_update=None) -> float:
    """--train-steps-per-episode updates on uniformly sampled sequences; returns updates per second.

    Each update's losses go to the logger as running means (SB3's record_mean; non-finite values are left out).
    `on_update(done, seconds)` is called after every update (progress display). Stops early once the agent has
    had --max-nonfinite-updates updates in a row with a non-finite loss or gradient (main then ends the run)."""
    started, done = time.time(), 0
    for done in range(1, args.train_steps_per_episode + 1):
        t_update = time.time()
        for key, value in agent.update(replay.sample(args.batch_size, args.seq_len)).items():
            if math.isfinite(value):
                logger.record_mean(f"{prefix}losses/{key}", value)
        if on_update is not None:
            on_update(done, time.time() - t_update)
        if agent.nonfinite_in_a_row >= args.max_nonfinite_updates:
            break
    return done / max(time.time() - started, 1e-9)


@dataclasses.dataclass
class Run:
    """What a training run carries from race to race; `setup_run` builds it, `save_latest` writes it."""

    args: Args
    run_dir: str
    device: torch.device
    agents: list[Agent]
    replays: list[Replay]
    counters: dict  # episode (races finished), global_step (env steps), best_eval_return
    logger: object
    envs: object
    eval_envs: object = None  # made at the first evaluation
    ghosts: dict = dataclasses.field(default_factory=dict)  # ghost stage: track seed -> the best run on it so far
    wins: list = dataclasses.field(default_factory=list)  # per agent, its last 100 race results
    manifests: list = dataclasses.field(default_factory=list)  # per agent, the replay save that latest.pt names
    from_checkpoint: bool = False  # the agents started from --checkpoint: no random prefill
    started: float = dataclasses.field(default_factory=time.time)
    cpu_started: float = dataclasses.field(default_factory=time.process_time)
    cpu_before: float = 0.0  # CPU seconds of the run's earlier sittings (a resumed run)
    fault: str | None = None  # set when an agent had --max-nonfinite-updates faulty updates in a row
    update_seconds: list = dataclasses.field(default_factory=list)  # the first two updates' times (CPU report)
    pbar: object = None

    def cpu_seconds(self) -> float:
        """Process CPU time of the run so far, over all its sittings (--cpu-hours-limit)."""
        return self.cpu_before + time.process_time() - self.cpu_started

    @property
    def checkpoint_dir(self) -> str:
        return os.path.join(self.run_dir, "checkpoints")

    def replay_dir(self, j: int) -> str:
        return os.path.join(self.checkpoint_dir, f"replay_car_{j}")

    def finished(self) -> bool:
        """The run's end: --total-episodes races, --total-updates updates, the time limit, or a numerical fault."""
        args = self.args
        return (
            self.counters["episode"] >= args.total_episodes
            or (args.total_updates > 0 and min(agent.num_updates for agent in self.agents) >= args.total_updates)
            or (args.time_limit_hours > 0 and time.time() - self.started > 3600 * args.time_limit_hours)
            or (args.cpu_hours_limit > 0 and self.cpu_seconds() > 3600 * args.cpu_hours_limit)
            or self.fault is not None
        )

    def acts_randomly(self) -> bool:
        """Random actions in the prefill races of a new single or race stage (also when resumed during them)."""
        args = self.args
        return self.counters["episode"] < args.prefill_episodes and not self.from_checkpoint and args.stage != "ghost"

    def learning_starts(self) -> int:
        """Updates start after the prefill races; a ghost-stage run first races every ghost track once with the
        starting policy (those runs are the first ghosts)."""
        return self.args.ghost_tracks if self.args.stage == "ghost" else self.args.prefill_episodes


def start_race(run: Run) -> tuple[np.ndarray, int]:
    """One race at a time (K = 1): reset on the next race's track, a ghost track with its ghost (if it has one yet)
    in the ghost stage, else the track race_seed(seed, episode), so a resumed run drives the same tracks."""
    args, episode = run.args, run.counters["episode"]
    if args.stage == "ghost":
        seed = args.ghost_seed + episode % args.ghost_tracks
        run.envs.set_options({"ghosts": {"car_0": run.ghosts[seed]}} if seed in run.ghosts else {})
    else:
        seed = race_seed(args.seed, episode)
    run.envs.seed(seed)
    return run.envs.reset(), seed


def log_race(run: Run, cars: list[CarEpisode], track_seed: int | None) -> None:
    """Per car: return, progress, lap time and win rate (race stages; the ghost stage: beating the ghost, whose
    record is replaced when beaten)."""
    from envs import race_winners

    args, logger = run.args, run.logger
    final_infos = [car.final_info or {} for car in cars]
    racing = args.env_id == "multi_car_racing"
    won = race_winners(final_infos) if len(cars) > 1 and racing else None  # (highway-env has no ranks)
    if args.stage == "ghost":  # a win is beating the ghost (races without a ghost yet do not count)
        won = [bool(final_infos[0]["ghost_beaten"])] if "ghost_beaten" in final_infos[0] else None
        if track_seed not in run.ghosts or (won and won[0]):  # the first run on the track, or the ghost beaten
            run.ghosts[track_seed] = final_infos[0]["trajectory"].to_dict()
        logger.record("ghost/track_seed", track_seed)
        logger.record("ghost/ghosts_recorded", len(run.ghosts))
    for j, car in enumerate(cars):
        logger.record(f"car_{j}/charts/episodic_return", car.ret)
        logger.record(f"car_{j}/charts/progress", float(final_infos[j].get("progress", 0.0)))
        if final_infos[j].get("lap_finished"):
            logger.record(f"car_{j}/charts/lap_time", int(final_infos[j]["finish_step"]))
        if won is not None:
            run.wins[j].append(float(won[j]))
            logger.record(f"car_{j}/charts/win_rate", float(np.mean(run.wins[j])))
    logger.record("charts/episode", run.counters["episode"])
    if racing:
        logger.record("charts/dead_zone", dead_zone_at(run.counters["episode"], args))


def train_all(run: Run) -> None:
    """Every agent trains on its own replay (Algorithm 1, after each race); the burst shows in the progress bar,
    and on a CPU the time of one update is reported after the first few."""
    args = run.args
    for j, (agent, replay) in enumerate(zip(run.agents, run.replays)):

        burst_start = time.time()

        def on_update(done: int, seconds: float, j=j) -> None:
            if len(run.update_seconds) < 2:
                run.update_seconds.append(seconds)
                if len(run.update_seconds) == 2 and run.device.type == "cpu":
                    report_update_time(run)
            if run.pbar is not None:
                rate = done / max(time.time() - burst_start, 1e-9)
                run.pbar.set_postfix_str(f"training car_{j}: {done}/{args.train_steps_per_episode} updates, "
                                         f"{rate:.2f} updates/s", refresh=True)  # fmt: skip

        updates_per_s = train_agent(agent, replay, args, run.logger, f"car_{j}/", on_update)
        run.logger.record(f"car_{j}/perf/updates_per_s", updates_per_s)
        run.logger.record(f"car_{j}/perf/updates", agent.num_updates)
        run.logger.record(f"car_{j}/faults/nonfinite_updates", agent.nonfinite_updates)
        if agent.nonfinite_in_a_row >= args.max_nonfinite_updates:
            run.fault = (f"car_{j}: {agent.nonfinite_in_a_row} updates in a row had a non-finite loss or gradient"
                         f" (--max-nonfinite-updates {args.max_nonfinite_updates})")  # fmt: skip
            return


def report_update_time(run: Run) -> None:
    """Say how long one update takes on this CPU (the second update: the first warms up) and what that means per
    race, as soon as it is known (at the paper's size within a minute or two of the start)."""
    args, n = run.args, len(run.agents)
    per_update = run.update_seconds[1]
    minutes = per_update * args.train_steps_per_episode * n / 60
    message = (f"On this CPU one update takes {per_update:.2f} s: {args.train_steps_per_episode} updates x {n}"
               f" agent(s) = {minutes:.1f} min of training per race.")  # fmt: skip
    if args.preset == "paper":
        message += f" For a CPU-sized run: python {os.path.basename(__file__)} --preset cpu --seed 1 (README.md)"
    _print(run, message)


def log_videos(run: Run, cars: list[CarEpisode]) -> None:
    """Each car's race so far beside the model's reconstruction and an open-loop imagination."""
    from utils.logger import log_video

    for j, (agent, car) in enumerate(zip(run.agents, cars)):
        obs, actions, _, _ = car.arrays()
        length = min(len(obs), run.args.video_length)
        first = np.zeros(length, dtype=bool)
        first[0] = True
        video = agent.video(obs[:length], actions[:length], first)
        log_video(run.logger, f"car_{j}/videos/real_reconstruction_imagination", video, run.counters["global_step"], 25)


def evaluate_and_keep_best(run: Run) -> None:
    """Evaluate on the held-out tracks, log it, print one line, keep best.pt (and eval_<race>.pt if asked)."""
    from utils import make_vec_env

    args, counters = run.args, run.counters
    if run.eval_envs is None:
        run.eval_envs = make_vec_env(args.env_id, 1, None, **env_kwargs(args, args.dead_zone_end))
    returns, progress, abs_steer = evaluate(run.agents, args, run.eval_envs)
    for j in range(len(run.agents)):
        run.logger.record(f"car_{j}/eval/episodic_return", float(returns[:, j].mean()))
        run.logger.record(f"car_{j}/eval/progress", float(progress[:, j].mean()))
        if args.env_id == "multi_car_racing":  # highway-env's action 0 is the acceleration
            run.logger.record(f"car_{j}/eval/mean_abs_steer", float(abs_steer[:, j].mean()))
    updates = run.agents[0].num_updates
    _print(run, f"evaluation after race {counters['episode']} ({updates} updates, {counters['global_step']} env steps):"
                f" return {returns.mean():.1f}, progress {progress.mean():.2f}, |steer| {abs_steer.mean():.2f}"
                f" ({args.eval_policy}, {len(returns)} held-out tracks)")  # fmt: skip
    extra = _extra(run)
    if args.eval_checkpoints:
        path = os.path.join(run.checkpoint_dir, f"eval_{counters['episode']:06d}.pt")
        save_checkpoint(path, args, run.agents, counters, extra)
    if returns.mean() > counters["best_eval_return"]:
        counters["best_eval_return"] = float(returns.mean())
        save_checkpoint(os.path.join(run.checkpoint_dir, "best.pt"), args, run.agents, counters, extra)


def save_latest(run: Run) -> str:
    """checkpoints/latest.pt, naming each agent's replay save; then the replay files it does not name go."""
    path = os.path.join(run.checkpoint_dir, "latest.pt")
    save_checkpoint(path, run.args, run.agents, run.counters, _extra(run))
    for j, manifest in enumerate(run.manifests):
        if manifest is not None:
            Replay.prune(run.replay_dir(j), manifest)
    return path


def end_race(run: Run, cars: list[CarEpisode], track_seed: int | None, env_sps: float) -> None:
    """After race `episode` ended: log it, train every agent, then video, evaluation, replay save, checkpoint."""
    args, counters = run.args, run.counters
    counters["episode"] += 1
    episode = counters["episode"]
    log_race(run, cars, track_seed)
    for j in range(len(cars)):
        run.logger.record(f"car_{j}/perf/env_sps", env_sps)
    if args.env_id == "multi_car_racing":  # the dead-zone schedule, applied at the env's next reset: one race at
        # a time resets after this (start_race); K races have already auto-reset this slot, so K > 1 sets the value
        # one race ahead, for the race that starts when the next one ends (main sets it for the first)
        run.envs.env_method("set_dead_zone", dead_zone_at(episode + (args.num_races > 1), args))
    if episode >= run.learning_starts() and all(r.can_sample(args.seq_len) for r in run.replays):
        train_all(run)
    if run.fault is None:
        if args.video_every and episode % args.video_every == 0:
            log_videos(run, cars)
        if args.eval_every and episode % args.eval_every == 0:
            evaluate_and_keep_best(run)
        # The replay first, then latest.pt naming it: a kill between the two leaves the previous pair intact.
        if args.replay_save_every and episode % args.replay_save_every == 0:
            run.manifests = [replay.save(run.replay_dir(j)) for j, replay in enumerate(run.replays)]
        if args.checkpoint_every and episode % args.checkpoint_every == 0:
            save_latest(run)
    run.logger.record("charts/cpu_hours", run.cpu_seconds() / 3600)  # after the race's training and evaluation
    run.logger.dump(counters["global_step"])
    if run.pbar is not None:
        run.pbar.update(1)
        run.pbar.set_postfix_str(f"race {episode}: return {np.mean([c.ret for c in cars]):.1f}, "
                                 f"{env_sps:.0f} env steps/s, {run.agents[0].num_updates} updates")  # fmt: skip


def main(args: Args, overrides=()) -> str:
    """Train with `args` (Algorithm 1); returns the run directory. With args.resume the run continues with the
    settings it was started with, except the fields named in `overrides`, which come from `args`.

    Bad input (an impossible argument, an unreadable checkpoint, a replay that cannot fit in memory) raises
    UsageError before anything is written. --max-nonfinite-updates faulty updates in a row end the run with a
    checkpoint and raise NumericalFault."""
    from tqdm import tqdm

    run = setup_run(args, overrides)
    args, n, k_races = run.args, run.args.num_agents, run.args.num_races
    slots = k_races * n  # agent i drives car i of every race: slots i, i + n, ...
    # One race at a time starts on its own track (start_race); K races side by side auto-reset on the tracks of
    # each race's seeded stream, with the dead zone set ahead for the race that starts next (end_race).
    obs, track_seed = start_race(run) if k_races == 1 else (run.envs.reset(), None)
    if args.env_id == "multi_car_racing" and k_races > 1:
        run.envs.env_method("set_dead_zone", dead_zone_at(run.counters["episode"] + 1, args))
    frames, is_first = preprocess_frames(obs, args.image_size), np.ones(slots, dtype=bool)
    states, episodes = [None] * n, [None] * slots
    env_time, env_steps, env_sps = 0.0, 0, 0.0
    run.pbar = tqdm(total=args.total_episodes, initial=run.counters["episode"], desc=f"{VARIANT} {args.stage}")
    while not run.finished():
        t0 = time.time()
        # --- act: every agent drives its own car in every race (random actions during the prefill) -------
        for slot in np.flatnonzero(is_first):
            episodes[slot] = CarEpisode(frames[slot], run.agents[0].action_dim)
        actions = np.zeros((slots, run.agents[0].action_dim), dtype=np.float32)
        for i, agent in enumerate(run.agents):
            mine = np.arange(i, slots, n)
            if run.acts_randomly():
                actions[mine] = np.random.uniform(-1, 1, size=(len(mine), agent.action_dim))
            else:
                actions[mine], states[i] = agent.act(frames[mine], states[i], is_first[mine])
        obs, rewards, dones, infos, repeats = step_with_repeat(run.envs, actions, args.action_repeat)
        frames = preprocess_frames(obs, args.image_size)
        run.counters["global_step"] += k_races * repeats
        env_steps += k_races * repeats
        # --- store: each live car's transition goes to its own agent's episode, a finished one to its replay
        for slot, info in enumerate(infos):
            if not info["alive"]:
                continue
            if dones[slot]:
                frame = preprocess_frames(info["terminal_observation"][None], args.image_size)[0]
                episodes[slot].add(frame, actions[slot], rewards[slot], terminated=not info["TimeLimit.truncated"])
                episodes[slot].final_info = info
                run.replays[slot % n].add_episode(*episodes[slot].arrays())
            else:
                episodes[slot].add(frames[slot], actions[slot], rewards[slot], terminated=False)
        is_first = np.array([info["is_first"] for info in infos], dtype=bool)
        env_time += time.time() - t0
        # --- train: after every race that ended, each agent updates on its own replay --------------------
        if is_first.any():  # env steps per second while the agents acted, since the last race ended
            env_sps, env_time, env_steps = env_steps / max(env_time, 1e-9), 0.0, 0
        for race in np.flatnonzero(is_first[::n]):
            end_race(run, episodes[race * n : (race + 1) * n], track_seed, env_sps)
            if run.finished():
                break
        if k_races == 1 and is_first.any() and not run.finished():
            obs, track_seed = start_race(run)  # the next race's own track (the ghost stage: with its ghost)
            frames, is_first[:] = preprocess_frames(obs, args.image_size), True
    return finish_run(run)


# =====================================================================================
# 8. Run infrastructure: arguments, memory, set-up and resume, checkpoints, command line
# =====================================================================================
# Arguments that fix the networks' shapes (a --checkpoint brings its own; a resumed run cannot change them),
# and what a run is (a resumed run cannot change those either).
ARCHITECTURE = ("image_size", "cnn_depth", "deter_size", "hidden_size", "mlp_size", "latent_size", "norm")
IDENTITY = ("env_id", "num_agents", "num_races", "stage", "seed", "exp_name", "runs_dir", "checkpoint", "preset")


def explicit_fields(argv: list[str]) -> set[str]:
    """Names of the Args fields that a command line sets explicitly (`--flag v`, `--flag=v`, `--[no-]flag`)."""
    fields = {field.name: field for field in dataclasses.fields(Args)}
    names = {_flag(name)[2:]: name for name in fields}
    found = set()
    for token in argv:
        if not token.startswith("--"):
            continue
        flag = token[2:].split("=", 1)[0].replace("_", "-")
        if flag in names:
            found.add(names[flag])
        elif flag.startswith("no-") and flag[3:] in names and fields[names[flag[3:]]].type in (bool, "bool"):
            found.add(names[flag[3:]])
    return found


class UsageError(ValueError):
    """Bad input (an argument, a checkpoint file, a memory budget), found before any work starts; one-line message."""


class CheckpointError(UsageError):
    """A missing, truncated or foreign checkpoint (or replay) file; the message names the file."""


class WrongVariant(CheckpointError):
    """A checkpoint of the other variant's script (race.py then asks that script)."""


class NumericalFault(RuntimeError):
    """--max-nonfinite-updates updates in a row had a non-finite loss or gradient; the run stopped with a checkpoint."""


def _flag(name: str) -> str:
    return "--lambda" if name == "lambda_" else "--" + name.replace("_", "-")


def validate_args(args: Args) -> None:
    """Refuse impossible arguments before any work starts: raises UsageError (a ValueError) naming the flag."""

    def require(ok: bool, name: str, requirement: str) -> None:
        if not ok:
            raise UsageError(f"{_flag(name)} {requirement}, got {getattr(args, name)!r}")

    for field in dataclasses.fields(args):
        value = getattr(args, field.name)
        if isinstance(value, float):
            require(math.isfinite(value), field.name, "must be a finite number")
    for minimum, names in {
        1: ("num_agents", "num_races", "max_steps", "action_repeat", "total_episodes", "replay_capacity", "batch_size",
            "imagination_horizon", "eval_episodes", "ghost_tracks", "video_length", "max_nonfinite_updates",
            "cnn_depth", "deter_size", "hidden_size", "mlp_size", "latent_size"),
        2: ("seq_len",),  # a sequence model learns from transitions: at least two steps
        0: ("torch_threads", "stall_steps", "dead_zone_episodes", "prefill_episodes", "train_steps_per_episode",
            "eval_every", "video_every", "checkpoint_every", "replay_save_every", "imagination_starts",
            "time_limit_hours", "cpu_hours_limit", "entropy_coef", "free_bits", "kl_dyn_scale", "kl_rep_scale", "brake_speed_threshold",
            "collision_penalty", "offroad_penalty", "eval_seed", "ghost_seed"),
    }.items():  # fmt: skip
        for name in names:
            require(getattr(args, name) >= minimum, name, f"must be >= {minimum}")
    for name in ("model_lr", "critic_lr", "actor_lr", "grad_clip"):
        require(getattr(args, name) > 0, name, "must be > 0")
    require(0 < args.gamma <= 1, "gamma", "must lie in (0, 1]")
    require(0 <= args.lambda_ <= 1, "lambda_", "must lie in [0, 1]")
    require(0 <= args.reward_nll_beta <= 1, "reward_nll_beta", "must lie in [0, 1]")
    require(args.head_sigma >= 0, "head_sigma", "must be >= 0 (0: learned)")
    require(args.entropy_lr > 0, "entropy_lr", "must be > 0")
    if args.action_penalty is not None:
        require(math.isfinite(args.action_penalty) and args.action_penalty >= 0, "action_penalty", "must be >= 0")
    if args.entropy_target is not None:
        require(math.isfinite(args.entropy_target), "entropy_target", "must be a finite number")
        require(args.entropy_coef > 0, "entropy_coef", "must be > 0 with --entropy-target (alpha starts there)")
    require(0 < args.tau <= 1, "tau", "must lie in (0, 1]")
    low, high = LOG_SIGMA_RANGE
    require(low <= args.decoder_min_log_sigma <= high, "decoder_min_log_sigma", f"must lie in [{low:g}, {high:g}]")
    for name in ("dead_zone_start", "dead_zone_end"):
        require(-1 <= getattr(args, name) <= 0, name, "must lie in [-1, 0]")
    require(0 <= args.seed < 2**32, "seed", "must lie in [0, 2**32)")
    starts = args.batch_size * args.seq_len
    require(args.imagination_starts <= starts, "imagination_starts", f"must be <= batch-size * seq-len = {starts}")
    require(args.replay_capacity >= args.seq_len, "replay_capacity", f"must be >= --seq-len ({args.seq_len})")
    from utils.vec_env import ENV_IDS

    require(args.env_id in ENV_IDS, "env_id", f"must be one of {sorted(ENV_IDS)}")
    if args.stage == "ghost":
        require(args.env_id == "multi_car_racing", "env_id", "must be multi_car_racing for --stage ghost")
        if not args.checkpoint and not args.resume:
            raise UsageError("--stage ghost needs --checkpoint (e.g. runs/<run>/checkpoints/best.pt)")
    if args.resume is not None:
        require(os.path.isfile(resolve_checkpoint(args.resume)), "resume", "must be a run directory with "
                "checkpoints/latest.pt or a checkpoint file")  # fmt: skip
    elif args.checkpoint is not None:  # (a resumed run has its networks already)
        require(os.path.isfile(args.checkpoint), "checkpoint", "must be a checkpoint file")
    elif args.fresh_replay:
        raise UsageError("--fresh-replay applies to a run started from --checkpoint (give one, or drop the flag)")


def available_memory() -> tuple[int | None, str]:
    """Bytes of memory a new allocation can use, and where the number comes from: MemAvailable of /proc/meminfo
    (capped by a cgroup memory limit), else free physical pages (sysconf), else (None, "unknown")."""
    available, source = None, "unknown"
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    available, source = int(line.split()[1]) * 1024, "MemAvailable in /proc/meminfo"
    if available is None:
        with contextlib.suppress(OSError, ValueError, AttributeError):
            available, source = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "free pages (sysconf)"
    cgroup_files = [("memory.max", "memory.current"), ("memory/memory.limit_in_bytes", "memory/memory.usage_in_bytes")]
    for limit_file, usage_file in cgroup_files:
        with contextlib.suppress(OSError, ValueError):  # a container's limit ("max": none)
            with open(f"/sys/fs/cgroup/{limit_file}") as f, open(f"/sys/fs/cgroup/{usage_file}") as g:
                room = int(f.read()) - int(g.read())
            if available is None or room < available:
                available, source = room, f"cgroup limit /sys/fs/cgroup/{limit_file}"
    return available, source


def _size(num_bytes: float) -> str:
    return f"{num_bytes / 1e9:,.2f} GB" if num_bytes >= 1e9 else f"{num_bytes / 1e6:,.1f} MB"


def check_replay_memory(args: Args) -> int:
    """Print the replay buffers' size (all agents) and refuse a capacity that cannot fit in available memory.

    The buffers are allocated lazily (pages are touched as they fill), so a run that does not fit would only
    fail hours later; returns their size in bytes."""
    step_bytes = Replay.bytes_per_step(args.image_size)
    per_agent = args.replay_capacity * step_bytes
    total = args.num_agents * per_agent
    available, source = available_memory()
    room = "unknown" if available is None else _size(available)
    print(f"replay buffers: {args.num_agents} x {args.replay_capacity:,} steps x {step_bytes:,} B = {_size(total)}"
          f" (memory available: {room}, {source})")  # fmt: skip
    if available is not None and total > available:
        raise UsageError(
            f"--replay-capacity {args.replay_capacity}: the replay buffers need {args.num_agents} x {_size(per_agent)}"
            f" = {_size(total)} but only {_size(available)} of memory is available ({source}); lower --replay-capacity"
        )
    return total


def keep_freed_memory() -> bool:
    """Stop glibc from returning freed memory to the OS (docs/agent.md, update time).

    Every update allocates and frees the same large blocks; by default glibc unmaps them and the
    kernel page-faults them in again on the next update (~45% of wall time measured here).
    mallopt(M_TRIM_THRESHOLD, 2**31-1) and mallopt(M_MMAP_MAX, 0) keep them in the process.
    Linux/glibc only; returns whether both settings took effect.
    """
    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # from glibc's malloc.h
    return libc.mallopt(M_TRIM_THRESHOLD, 2**31 - 1) == 1 and libc.mallopt(M_MMAP_MAX, 0) == 1


def setup_run(args: Args, overrides=()) -> Run:
    """Check everything, then build the run: a new one, or (args.resume) the saved one exactly as it stopped.
    Nothing is written before every check has passed."""
    from utils import make_vec_env
    from utils.logger import configure_logger, make_run_name

    validate_args(args)
    resumed = start = None
    if args.resume:
        checkpoint_path = resolve_checkpoint(args.resume)
        resumed = load_checkpoint(checkpoint_path, training=True)
        args = resumed_args(resumed, checkpoint_path, args, overrides)
        validate_args(args)
        run_dir = os.path.dirname(os.path.dirname(os.path.abspath(checkpoint_path)))
    else:
        args, start = new_run_args(args)
        run_dir = os.path.join(args.runs_dir, make_run_name(args.env_id, args.exp_name, args.seed))
    check_replay_memory(args)
    if args.malloc_fix:
        keep_freed_memory()
    if args.torch_threads > 0:
        torch.set_num_threads(args.torch_threads)
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")

    n, episode = args.num_agents, int(resumed["counters"]["episode"]) if resumed else 0
    kwargs = env_kwargs(args, dead_zone_at(episode, args))
    envs = make_vec_env(args.env_id, args.num_races, args.seed + episode, args.use_subprocess, **kwargs)
    action_dim = int(envs.action_space.shape[0])
    run = Run(
        args, run_dir, device,
        agents=[Agent(args, action_dim, device) for _ in range(n)],
        replays=[Replay(args.replay_capacity, args.image_size, action_dim) for _ in range(n)],
        counters={"episode": 0, "global_step": 0, "best_eval_return": -math.inf},
        logger=None, envs=envs, wins=[deque(maxlen=100) for _ in range(n)], manifests=[None] * n,
        from_checkpoint=args.checkpoint is not None,
    )  # fmt: skip
    if resumed is not None:
        restore_run(run, resumed, checkpoint_path)
    elif start is not None:
        for i, agent in enumerate(run.agents):
            source = i % len(start["agents"])
            load_agent_state(agent, start["agents"][source], args.checkpoint, source)
            directory = replay_dir_of(args.checkpoint, source)
            if not args.fresh_replay and os.path.isfile(os.path.join(directory, "meta.npz")):
                # The agent keeps learning from all it has seen: the newest save beside the checkpoint (for a
                # best.pt, its run's replay at the end, which holds all best.pt had seen and what came after).
                with np.load(os.path.join(directory, "meta.npz")) as meta:
                    capacity = int(meta["capacity"])
                if capacity != args.replay_capacity:
                    raise UsageError(f"--replay-capacity {args.replay_capacity}: the replay beside --checkpoint "
                                     f"({directory}) holds {capacity}; give --replay-capacity {capacity}, or "
                                     "--fresh-replay to start with an empty one")  # fmt: skip
                restore_replay(run.replays[i], directory, None, races=0)
                print(f"car {i}: continues with the replay in {directory} ({len(run.replays[i]):,} steps)")
                # (run.manifests stay None: the run's own replay directory holds no save until its first one)
    formats = ("stdout", "csv", "tensorboard") if args.print_table else ("csv", "tensorboard")
    run.logger = configure_logger(run_dir, dataclasses.asdict(args), formats)
    with open(os.path.join(run_dir, "config.json"), "w") as f:  # plot.py groups runs by variant and stage
        json.dump({"variant": VARIANT, **dataclasses.asdict(args)}, f, indent=1)
    print(f"run directory: {run_dir} (device {device}); tensorboard --logdir {args.runs_dir}")
    if resumed is not None:
        print(f"resumed from {checkpoint_path} at race {run.counters['episode']}, step {run.counters['global_step']}")
        set_rng_state(resumed["rng"])  # last of the set-up: the random streams continue where they stopped
    elif args.checkpoint:
        print(f"agents start from {args.checkpoint}")
    return run


def new_run_args(args: Args) -> tuple[Args, dict | None]:
    """A new run's Args with what its stage implies (one car for single and ghost, one race at a time for ghost)
    and the network sizes of --checkpoint, and that checkpoint (or None)."""
    if args.stage in ("single", "ghost") and args.num_agents != 1:
        print(f"stage {args.stage!r} races one car: --num-agents {args.num_agents} -> 1")
        args = dataclasses.replace(args, num_agents=1)
    if args.stage == "ghost" and args.num_races != 1:
        print(f"stage 'ghost' races one track at a time: --num-races {args.num_races} -> 1")
        args = dataclasses.replace(args, num_races=1)
    if not args.checkpoint:
        return args, None
    start = load_checkpoint(args.checkpoint, training=True)
    sizes = args_from_checkpoint(start, args.checkpoint)
    changed = {key: getattr(sizes, key) for key in ARCHITECTURE if getattr(sizes, key) != getattr(args, key)}
    if changed:  # the networks must have the sizes they were trained with
        print(f"network sizes from {args.checkpoint}: {changed}")
        args = dataclasses.replace(args, **changed)
    return args, start


def restore_run(run: Run, resumed: dict, path: str) -> None:
    """Put a checkpoint's agents, counters, ghosts, recent wins and replays into `run`."""
    n = run.args.num_agents
    if len(resumed["agents"]) != n:
        raise CheckpointError(f"{path}: holds {len(resumed['agents'])} agent(s), its arguments {n}")
    for i, (agent, state) in enumerate(zip(run.agents, resumed["agents"])):
        load_agent_state(agent, state, path, i)
    run.counters.update(resumed["counters"])
    extra = resumed.get("extra") or {}
    run.ghosts = {int(s): ghost_from_tensors(g) for s, g in extra.get("ghosts", {}).items()}
    for j, history in enumerate(extra.get("wins", [])[:n]):
        run.wins[j].extend(history)
    run.cpu_before = float(extra.get("cpu_seconds", 0.0))  # (0 for a checkpoint written before it was kept)
    saved = list(extra.get("replays") or []) + [None] * n
    for j, replay in enumerate(run.replays):
        run.manifests[j] = restore_replay(replay, run.replay_dir(j), saved[j], run.counters["episode"])


def finish_run(run: Run) -> str:
    """Save the replays and latest.pt, close everything; raise NumericalFault if that is why the run ended."""
    run.manifests = [replay.save(run.replay_dir(j)) for j, replay in enumerate(run.replays)]
    latest = save_latest(run)
    if run.pbar is not None:
        run.pbar.close()
    run.envs.close()
    if run.eval_envs is not None:
        run.eval_envs.close()
    run.logger.close()
    if run.fault is not None:
        raise NumericalFault(f"{run.fault}; stopped after race {run.counters['episode']} with the checkpoint {latest}")
    return run.run_dir


def _print(run: Run, message: str) -> None:
    """A line on stdout that does not break the progress bar."""
    if run.pbar is not None:
        run.pbar.write(message)
    else:
        print(message)


def resolve_checkpoint(path: str) -> str:
    """A run directory means its checkpoints/latest.pt."""
    return os.path.join(path, "checkpoints", "latest.pt") if os.path.isdir(path) else path


def replay_dir_of(path: str, index: int) -> str:
    """The replay of agent `index` saved beside a checkpoint: ``<stem>_replay_car_<index>`` (race.py --train) or
    ``replay_car_<index>`` (a training run's ``checkpoints/``)."""
    own = f"{os.path.splitext(path)[0]}_replay_car_{index}"
    return own if os.path.isdir(own) else os.path.join(os.path.dirname(os.path.abspath(path)), f"replay_car_{index}")


def restore_replay(replay: Replay, directory: str, manifest: dict | None, races: int) -> dict | None:
    """Resume: load an agent's replay as the checkpoint names it (else the newest save in `directory`), say what
    it lacks, and return the manifest loaded (None: nothing saved, the replay starts empty)."""
    if manifest is not None and not all(os.path.isfile(os.path.join(directory, f)) for f in manifest["files"]):
        print(f"note: {directory} no longer holds the replay save the checkpoint names; loading its newest save")
        manifest = None
    if manifest is None and not os.path.isfile(os.path.join(directory, "meta.npz")):
        print(f"note: no replay saved in {directory}: it starts empty")
        return None
    try:
        replay.load(directory, manifest)
    except Exception as e:  # a chunk file damaged outside this program (the writes themselves are atomic)
        raise CheckpointError(f"{directory}: replay not readable: {_first_line(e)}") from None
    if replay.episodes < races:
        print(f"note: {directory} was saved {races - replay.episodes} race(s) before the checkpoint"
              " (--replay-save-every): the transitions of those races are not restored")  # fmt: skip
    return replay.manifest()


def resumed_args(checkpoint: dict, path: str, args: Args, overrides) -> Args:
    """The Args of a resumed run: every setting it was started with, except the fields named in `overrides` (those
    the resuming command line set explicitly), which come from `args`; prints each change (old -> new)."""
    saved = args_from_checkpoint(checkpoint, path)
    changes = {name: getattr(args, name) for name in overrides if name != "resume"}
    fixed = sorted(n for n in changes if n in ARCHITECTURE + IDENTITY and changes[n] != getattr(saved, n))
    if fixed:
        raise UsageError(f"--resume: {', '.join(_flag(n) for n in fixed)} cannot change in a resumed run")
    for name, value in changes.items():
        if value != getattr(saved, name):
            print(f"resume: {_flag(name)} {getattr(saved, name)!r} -> {value!r}")
    return dataclasses.replace(saved, resume=args.resume, **changes)


def _atomic_write(path: str, write) -> None:
    """Write a file so that a kill at any moment leaves the old file or the new one, never a part: write(f) into a
    temporary file beside it, flush and fsync it, rename it over `path` (os.replace), fsync the directory."""
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    tmp = path + ".tmp"
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    with contextlib.suppress(OSError):  # the rename itself reaches the disk (not possible on every platform)
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _atomic_npz(path: str, **arrays) -> None:
    _atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


def _atomic_torch_save(obj, path: str) -> None:
    _atomic_write(path, lambda f: torch.save(obj, f))


def rng_state() -> dict:
    """python, numpy and torch RNG states as tensors (restorable with set_rng_state)."""
    np_state = np.random.get_state()
    py_state = random.getstate()
    state = {
        "torch": torch.get_rng_state(),
        "numpy_key": torch.from_numpy(np_state[1].astype(np.int64)),
        "numpy_meta": torch.tensor([np_state[2], np_state[3]], dtype=torch.int64),
        "numpy_gauss": torch.tensor(np_state[4], dtype=torch.float64),
        "python": torch.tensor(py_state[1], dtype=torch.int64),
        "python_gauss": torch.tensor(float("nan") if py_state[2] is None else py_state[2], dtype=torch.float64),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.stack(torch.cuda.get_rng_state_all())
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    meta = state["numpy_meta"].tolist()
    key = state["numpy_key"].numpy().astype(np.uint32)
    np.random.set_state(("MT19937", key, meta[0], meta[1], float(state["numpy_gauss"])))
    gauss = float(state["python_gauss"])
    random.setstate((3, tuple(state["python"].tolist()), None if math.isnan(gauss) else gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(list(state["cuda"]))


def save_checkpoint(path: str, args: Args, agents: list[Agent], counters: dict, extra: dict | None = None) -> None:
    """The one checkpoint format: variant, args (dict), counters, every agent's networks and optimisers, RNG states."""
    checkpoint = {
        "variant": VARIANT,
        "args": dataclasses.asdict(args),
        "counters": dict(counters),
        "agents": [agent.state_dict() for agent in agents],
        "rng": rng_state(),
        "extra": extra or {},
    }
    _atomic_torch_save(checkpoint, path)


def export_policy(checkpoint_path: str, out: str, index: int = 0) -> int:
    """Write agent `index` of a checkpoint as an acting-only export (Agent.acting_state_dict, with its args and
    counters): what race.py and `learning.py --evaluate` need to drive, small enough for git. Returns its size."""
    checkpoint = load_checkpoint(checkpoint_path)
    agent = agent_from_checkpoint(checkpoint_path, index)
    export = {
        "variant": VARIANT, "kind": "policy", "args": checkpoint["args"], "counters": checkpoint["counters"],
        "agents": [agent.acting_state_dict()],
    }  # fmt: skip
    _atomic_torch_save(export, out)
    return os.path.getsize(out)


CHECKPOINT_KEYS = ("variant", "args", "counters", "agents")  # and "rng", except in an acting-only export


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def load_checkpoint(path: str, map_location="cpu", training: bool = False) -> dict:
    """Load a checkpoint (or an acting-only export) of this script with weights_only=True; a missing, truncated or
    foreign file (or one of the other variant, or an export when `training`) raises CheckpointError, whose
    one-line message names the file."""
    if not os.path.isfile(path):
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # truncated zip, not a torch file, a pickle weights_only refuses, ...
        reason = _first_line(e)
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or not a torch file): {reason}") from None
    export = isinstance(checkpoint, dict) and checkpoint.get("kind") == "policy"
    keys = CHECKPOINT_KEYS if export else (*CHECKPOINT_KEYS, "rng")
    if not isinstance(checkpoint, dict) or not all(key in checkpoint for key in keys):
        raise CheckpointError(f"{path}: not a checkpoint of these scripts (needs entries {', '.join(keys)})")
    if checkpoint["variant"] != VARIANT:
        raise WrongVariant(f"{path}: holds a {checkpoint['variant']!r} agent, this script builds {VARIANT!r}")
    if not isinstance(checkpoint["agents"], list) or not checkpoint["agents"]:
        raise CheckpointError(f"{path}: holds no agents")
    if training and checkpoint.get("kind") == "policy":
        raise CheckpointError(f"{path}: is an acting-only export (no critic, optimisers or replay): it cannot train")
    return checkpoint


def args_from_checkpoint(checkpoint: dict, path: str, **overrides) -> Args:
    """The Args a checkpoint was trained with (new flags keep their defaults, flags removed since are dropped)."""
    names = {field.name for field in dataclasses.fields(Args)}
    saved = checkpoint["args"] if isinstance(checkpoint["args"], dict) else {}
    dropped = sorted(set(saved) - names)
    if dropped:
        print(f"note: {path} has arguments this script does not know (ignored): {', '.join(dropped)}")
    try:
        return Args(**{**{k: v for k, v in saved.items() if k in names}, **overrides})
    except TypeError as e:
        raise CheckpointError(f"{path}: its arguments do not fit this script: {_first_line(e)}") from None


def load_agent_state(agent: Agent, state, path: str, index: int) -> None:
    """agent.load_state_dict, with a one-line CheckpointError naming the file when the state does not fit."""
    try:
        agent.load_state_dict(state)
    except (RuntimeError, KeyError, TypeError, ValueError, AttributeError) as e:
        raise CheckpointError(f"{path}: agent {index} does not fit the networks it names: {_first_line(e)}") from None


def agent_from_checkpoint(path: str, index: int = 0, device="cpu") -> Agent:
    """Build agent `index` of a checkpoint with the sizes it was trained with (used by race.py)."""
    checkpoint = load_checkpoint(path, map_location=device)
    if not 0 <= index < len(checkpoint["agents"]):
        raise CheckpointError(f"{path}: has {len(checkpoint['agents'])} agent(s), asked for agent {index}")
    state = checkpoint["agents"][index]
    agent = Agent(args_from_checkpoint(checkpoint, path), action_dim_of(state), device=device)
    load_agent_state(agent, state, path, index)
    return agent


def action_dim_of(agent_state: dict) -> int:
    """The action size a saved agent was built for: its actor's output layer gives a mean and a sigma per action."""
    try:
        last = max((k for k in agent_state["actor"] if k.endswith(".bias")), key=lambda k: int(k.split(".")[2]))
        return int(agent_state["actor"][last].shape[0]) // 2
    except (KeyError, TypeError, ValueError, IndexError, AttributeError):
        return 2  # not an agent's state: load_agent_state names the file and what does not fit


def ghost_to_tensors(trajectory: dict) -> dict:
    return {k: torch.as_tensor(np.asarray(v)) if isinstance(v, np.ndarray) else v for k, v in trajectory.items()}


def ghost_from_tensors(trajectory: dict) -> dict:
    return {k: v.numpy() if isinstance(v, torch.Tensor) else v for k, v in trajectory.items()}


def _extra(run: Run) -> dict:
    """The checkpoint's extra state: ghosts (ghost stage), the replay save of every agent, recent wins, CPU time."""
    return {
        "ghosts": {str(seed): ghost_to_tensors(g) for seed, g in run.ghosts.items()},
        "replays": list(run.manifests),
        "wins": [list(w) for w in run.wins],
        "cpu_seconds": run.cpu_seconds(),
    }


def parse_args(argv: list[str] | None = None) -> tuple[Args, set[str]]:
    """Args of a command line, with its --preset applied under the flags it sets, and the fields it sets."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = tyro.cli(Args, args=argv)
    explicit = explicit_fields(argv)
    if not args.resume:
        args = dataclasses.replace(args, **{k: v for k, v in PRESETS[args.preset].items() if k not in explicit})
    return args, explicit


def cli(argv: list[str] | None = None) -> str:
    """The command line: bad input and a run stopped by numerical faults end with a one-line error, no traceback."""
    args, explicit = parse_args(argv)
    try:
        return main(args, explicit)
    except (UsageError, NumericalFault) as e:
        message = " ".join(str(e).split())
        raise SystemExit(f"{os.path.basename(__file__)}: error: {message}") from None


if __name__ == "__main__":
    cli()
