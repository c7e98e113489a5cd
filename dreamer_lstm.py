# LSTM-Dreamer for decentralized multi-car racing, in one file (CleanRL style).
# Method: "Deep Latent Competition V1: Decentralized multi-car racing with LSTM-Dreamer-V3" (DLC-v1, "the paper"),
# built on DreamerV3 (Hafner et al., "Mastering Diverse Domains through World Models", arXiv:2301.04104).
# Usage: `python dreamer_lstm.py --seed 1` (or `--preset cpu`), then `tensorboard --logdir runs`; docs/agent.md.
"""LSTM-Dreamer: a world model learned from pixels, an actor and a critic trained in its imagination.

Read top to bottom:

1. Args ............ every hyperparameter (the paper's defaults) and the CPU preset
2. Environment ..... the dead-zone warm-up (the env's options, track seeds: utils/run.py)
3. Networks ........ (paper appendix) the encoder, decoder, recurrent core (LSTM with learned initial h and c) and
                     posterior; the output distributions (Gaussian, DreamerV3's two-hot); the world model
                     (prior, reward and continue heads); the actor (its log pi) and the critic
4. Losses .......... their terms: image likelihood and KL, free bits, lambda-returns, discount weights,
                     the returns' range (paper 3.8-3.9; the Agent of section 6 adds them up)
5. Replay .......... per-agent ring buffer of uint8 frames, uniform sequence sampling
6. Agent ........... world-model update, imagination, actor, critic and entropy-weight updates, acting
7. Training loop ... Algorithm 1 in `main`: decentralized agents act, store, train; stages single / ghost / race
8. Checkpoints ..... this script's readers of the checkpoint format

What is around the method is shared by both scripts: the collector that drives the cars and records their
episodes (utils/collector.py: `Races`, frame preprocessing, what a race reads), and the run plumbing (arguments'
checks, memory, run directory and resume, logging, atomic checkpoints and replay saves, the command line:
utils/run.py, utils/checkpoint.py). They, race.py, evaluate.py and benchmarks/ use this module's names (Args,
Agent, Replay, main, dead_zone_at, the checkpoint readers of section 8...): grep before renaming one.

Everything that depends on the recurrent cell is inside `RecurrentCell` (its state is a tuple of
tensors; the model state fed to every head is z||h). The GRU script (dreamer_gru.py) is this file
with that class and the defaults changed.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import itertools
import math
import os
import sys
import time
from typing import Annotated, Literal

import numpy as np
import torch
import torch.nn.functional as F
import tyro
from torch import nn

from utils import checkpoint as checkpoint_io
from utils.checkpoint import UsageError
from utils.collector import Races, preprocess_frames
from utils.run import (
    after_training,
    bf16_autocast,
    finish_run,
    log_race,
    log_updates,
    progress_callback,
    races_seed,
    set_next_dead_zone,
    setup_run,
)

VARIANT = "lstm"  # written into every checkpoint, so race.py knows which script built the agent


# =====================================================================================
# 1. Arguments (defaults: the paper and its authors' code, LSTM column; "(ours)" marks this project's; docs/agent.md)
# =====================================================================================
@dataclasses.dataclass
class Args:
    # An "episode" in these flags and in the run's counters is a race (every car's episode at once)
    # --- experiment
    preset: Literal["paper", "cpu"] = "paper"
    """paper: the paper's sizes and schedule; cpu: a configuration that learns on a 2-core CPU in hours: smaller
    networks and the method options chosen for it (its values: PRESETS in this file, docs/deviations.md; the
    defaults this help shows are the paper's; explicit flags override the preset's values)"""
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment (part of the run name)"""
    seed: int = 1
    """seed of python, numpy, torch and of the training tracks"""
    torch_deterministic: bool = True
    """`torch.backends.cudnn.deterministic` (deterministic cuDNN kernels on a GPU)"""
    cuda: bool = True
    """use CUDA when it is available (else the CPU)"""
    torch_threads: int = 0
    """number of CPU threads of torch (0: torch's default)"""
    malloc_fix: bool = True
    """keep freed memory in the process (glibc mallopt: utils/run.py keep_freed_memory), so an update's large
    blocks are not unmapped and page-faulted in again by the next"""
    compile: bool = False
    """torch.compile the networks' forward passes (same losses up to float rounding; minutes of compiling at the
    start; the recurrent cell's step stays eager, the per-step input layer, posterior and prior are compiled)"""
    amp: Literal["auto", "on", "off", "cuda"] = "auto"
    """bfloat16 autocast of the update's forward passes (losses stay float32); auto: on where bfloat16 is in
    hardware, a CUDA device of Ampere or newer or a CPU with bfloat16 instructions (AVX512-BF16), off elsewhere;
    cuda: on such a CUDA device only. A run saves the on or off that auto chose"""
    runs_dir: str = "runs"
    """directory holding the run directories `{env_id}__{exp_name}__{seed}__{time}`"""
    resume: str | None = None
    """continue a run: its run directory (or a checkpoint file in its checkpoints/), with its saved args and counters
    (flags given again override them, except that a change to what fixes the networks or what the run is, is
    refused)"""
    checkpoint: str | None = None
    """start the agents' networks and optimisers from this checkpoint (e.g. a single-stage best.pt for ghost), and
    their replays from the replay saved beside it; the checkpoint's network sizes and form (--norm, --heads)
    replace any given, and car i takes its agent i mod its number of agents"""
    fresh_replay: bool = False
    """--checkpoint: start with empty replays instead of the one saved beside the checkpoint"""
    stage: Literal["single", "ghost", "race"] = "race"
    """single: one car; ghost: one car against its best previous run; race: N learning cars (every stage evaluates
    and keeps best.pt)"""

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
    """env: a car that touches no new tile for this many steps is eliminated (ours)"""
    brake_speed_threshold: float = 50.0
    """env: braking has no effect below this speed"""
    collision_penalty: float = 0.05
    """env: subtracted from a car's reward every step its hull touches another car"""
    offroad_penalty: float = 100.0
    """env: subtracted once from a car's reward when it is eliminated (off road, off the playfield, stalled)"""
    speed_reward_coef: float = 0.0
    """env: reward per step per unit of forward speed along the track (ours: none)"""
    dead_zone_start: float = -1.0
    """dead-zone lower edge of the throttle-brake axis at episode 0 (ours; a run from --checkpoint races at the end
    value). The axis u is gas above 0; dead_zone < u <= 0 coasts; u <= dead_zone brakes with strength |u|. At -1
    only a pedal at (or clipped to) -1 brakes"""
    dead_zone_end: float = -0.5
    """dead-zone lower edge after the schedule (the paper's -0.5)"""
    dead_zone_episodes: int = 200
    """episodes over which the dead zone moves linearly from start to end (ours)"""
    action_repeat: int = 1
    """repeat every action this many env steps, summing rewards"""

    # --- training loop (Algorithm 1)
    total_episodes: int = 1000
    """races to run (counting prefill races)"""
    total_updates: int = 0
    """stop after the first race at which every agent has made this many updates (0: no limit)"""
    pause_at_updates: int = 0
    """stop, with checkpoints, after the first race at which every agent has made this many updates, as a pause, not
    the run's end: --total-updates stays the budget, and a --resume lifts the pause unless it is given again (0:
    never)"""
    time_limit_hours: float = 0.0
    """stop, with checkpoints, at the start or at the end of the first race past this many hours of this process (0: no
    limit)"""
    cpu_hours_limit: float = 0.0
    """stop, with checkpoints, once the run has used this many CPU-hours (checked at its start and at the end of every
    race): process CPU time summed over the first invocation and every --resume of the run (0: no limit); unlike
    wall time it does not depend on what else the machine runs"""
    prefill_episodes: int = 5
    """random-action races before the first update (ours; from a --checkpoint the agent's own policy fills
    replay)"""
    train_steps_per_episode: int = 200
    """updates per agent after every finished race"""
    replay_capacity: int = 100_000
    """replay buffer capacity per agent, in decisions (each --action-repeat env steps)"""
    eval_every: int = 20
    """evaluate every this many races (--eval-policy on held-out tracks; 0: never); best.pt keeps the best"""
    eval_episodes: int = 10
    """races per evaluation (ours)"""
    eval_policy: Literal["deterministic", "mean-action", "stochastic"] = "mean-action"
    """evaluation's policy: deterministic = posterior mean z and mean action; mean-action = sampled z, mean action;
    stochastic = sampled z and action (the policy that was optimised). Why the mean action:
    docs/learning.md#the-evaluation-policy"""
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
    """write checkpoints/latest.pt every this many races (0: only when the run stops)"""
    replay_save_every: int = 1
    """save the replay buffers beside the checkpoints every this many races (0: never); a resume restores the
    replay as of its last save, so 1 makes a resume exact with --num-races 1 (only the chunks a race changed are
    written; K > 1 races side by side restart on new tracks: docs/reliability.md)"""
    print_table: bool = False
    """also print the logger's table of every race on stdout (TensorBoard and progress.csv always have it)"""
    max_nonfinite_updates: int = 20
    """stop the run (with a checkpoint) after this many updates in a row with a non-finite loss or gradient"""

    # --- world model, actor, critic (paper Algorithm 1 and appendix; the paper authors' configurations)
    batch_size: int = 15
    """B: sequences per update"""
    seq_len: int = 50
    """L: decisions in every sampled sequence"""
    imagination_horizon: int = 50
    """H: imagined decisions per start"""
    imagination_starts: int = 0
    """imagination starts per update, a random subset of the B*L posterior states (0: all B*L, ours; the paper
    authors' code: 100)"""
    model_lr: float = 6e-4
    """Adam learning rate of the world model"""
    critic_lr: float = 6e-4
    """Adam learning rate of the critic"""
    actor_lr: float = 1e-4
    """Adam learning rate of the actor"""
    entropy_coef: float = 1.0
    """alpha: weight of -log pi in the lambda-return (the paper's entropy regulariser; 1.0 in the paper authors'
    configurations. Algorithm 1's "alpha = 0.0006" is the model's and critic's learning rate, not this)"""
    lambda_: Annotated[float, tyro.conf.arg(name="lambda")] = 0.95
    """lambda of the lambda-return"""
    gamma: float = 0.99
    """discount factor"""
    tau: float = 0.005
    """soft-update rate of the target networks: the world model's (the KL terms' stop-gradient side) after every
    world-model step taken, the slow critic after every critic step taken"""
    free_bits: float = 1.0
    """free nats per step of each KL term: max(free_bits, KL)"""
    kl_dyn_scale: float = 1.0
    """beta_dyn: weight of L_dyn = max(free_bits, KL(sg(posterior) || prior)); sg(.): the target networks' output
    (soft-updated copies, --tau), not the live network's with its gradient stopped"""
    kl_rep_scale: float = 1.0
    """beta_rep: weight of L_rep = max(free_bits, KL(posterior || sg(prior)))"""
    decoder_min_log_sigma: float = -5.0
    """floor of the decoder's learned log sigma (paper: learned; 0 gives Dreamer's unit-variance pixel loss)"""
    grad_clip: float = 100.0
    """global gradient-norm clip of every optimiser"""
    target_critic: bool = True
    """bootstrap the lambda-returns with the slow critic (a copy soft-updated with tau after every critic step)
    instead of the critic itself (--heads twohot regresses the critic on the slow critic whatever this flag)"""

    # --- options beyond the paper: off by default (the paper's form); docs/deviations.md lists each, measured
    entropy_target: float | None = None
    """adapt alpha so that the entropy it weighs (-log pi; with --action-penalty, -log N(a) alone) per action
    dimension tends to this many nats: SAC's automatic temperature (Haarnoja et al., 2018), alpha starting at
    --entropy-coef. None: alpha stays --entropy-coef"""
    entropy_lr: float = 1e-3
    """Adam learning rate of log alpha (--entropy-target)"""
    action_penalty: float | None = None
    """weight of log pi's extreme-action term -log(1 - tanh(a)^2) in the lambda-return, apart from alpha, which then
    weighs the Gaussian part alone (and --entropy-target its entropy). None: alpha weighs both (the paper)"""
    return_norm: bool = False
    """DreamerV3's return normalisation: scale the task part of the lambda-return by 1 / max(1, S), S an EMA of
    its 95th - 5th percentile range, in the actor's objective only (the critic learns the unscaled return); the
    entropy part stays unscaled (DreamerV3 pairs it with --entropy-coef 3e-4)"""
    head_sigma: float = 0.0
    """sigma of the reward and critic Gaussians: 0 learns it (softplus + 0.1, the paper); a positive value fixes it
    (1: the paper authors' code, a squared error, so that a rare -100 moves the mean instead of widening sigma)"""
    heads: Literal["gaussian", "twohot"] = "gaussian"
    """the reward and critic heads' distribution: gaussian (the paper; --head-sigma) or twohot (DreamerV3's two-hot
    over bins evenly spaced in symlog space: TwoHot below; the critic also regresses on the slow critic's value)"""
    straight_through_clip: bool = False
    """imagination clips an action outside [-1, 1] with the identity's gradient (Bengio et al., 2013's
    straight-through estimator: imagine_rollout). False: the clip passes no gradient (the paper authors' form)"""

    # --- network sizes (paper appendix; --preset cpu uses smaller ones)
    image_size: Literal[96, 64] = 96
    """what the encoder sees (64 resizes the 96x96 camera)"""
    cnn_depth: int = 32
    """channels of the first conv layer (doubling per layer: 32-64-128-256)"""
    deter_size: int = 512
    """size of the recurrent state h (an LSTM's cell state c has the same size)"""
    hidden_size: int = 1024
    """width of the encoder embedding, the recurrent input layer and the posterior/prior MLPs"""
    mlp_size: int = 512
    """width of the reward, continue, actor and critic MLPs"""
    latent_size: int = 60
    """size of the stochastic latent z"""
    norm: Literal["batch", "layer", "mixed"] = "batch"
    """normalisation of the networks (the critic always uses LayerNorm, as in the appendix); mixed: BatchNorm in the
    convolutions, LayerNorm in every MLP and the recurrent input (the paper authors' code)"""


# --preset cpu (docs/deviations.md says why each value): smaller networks, 64 px frames, 2 env steps per decision, a
# unit-variance pixel likelihood, and the paper's trade at a smaller size: the same imagined steps per update for
# both variants, the LSTM with a small batch and a long horizon, the GRU the other way. Explicit flags override it.
PRESETS: dict[str, dict] = {
    "paper": {},
    "cpu": {
        "cnn_depth": 16, "deter_size": 256, "hidden_size": 256, "mlp_size": 256, "image_size": 64, "seq_len": 32,
        "action_repeat": 2, "prefill_episodes": 20, "train_steps_per_episode": 100,
        "dead_zone_episodes": 30, "eval_every": 5, "video_every": 25, "decoder_min_log_sigma": 0.0,
        # this variant's own: the paper's trade (B * L * H = 5 * 32 * 48 = 7,680 imagined steps per update), and the
        # defaults chosen for it (docs/deviations.md): SAC's alpha toward 0 nats per action dimension with the
        # extreme-action term at its own weight 1, and imagination from half the starts (80 * 48 = 3,840 steps)
        "batch_size": 5, "imagination_horizon": 48,
        "imagination_starts": 80, "entropy_target": 0.0, "action_penalty": 1.0,
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
def dead_zone_at(episode: int, args: Args) -> float:
    """Linear dead-zone schedule: dead_zone_start at episode 0 to dead_zone_end at dead_zone_episodes. It is a
    warm-up for learning from scratch: a run whose agents start from a --checkpoint races at dead_zone_end."""
    if args.checkpoint is not None:
        return args.dead_zone_end
    frac = min(1.0, episode / max(1, args.dead_zone_episodes))
    return args.dead_zone_start + frac * (args.dead_zone_end - args.dead_zone_start)


# =====================================================================================
# 3. Networks (paper appendix)
# =====================================================================================
LATENT_MIN_STD = 0.1  # sigma of posterior and prior: softplus(.) + this minimum
LOG_SIGMA_RANGE = (-5.0, 2.0)  # the decoder's log sigma: the smallest --decoder-min-log-sigma allowed, its cap
HEAD_MIN_STD = 0.1  # a learned sigma of the reward and critic Gaussians: softplus(.) + this minimum
TWOHOT_BINS, TWOHOT_SPAN = 255, 20.0  # --heads twohot: DreamerV3's bins, symexp(-20 .. 20) (+-4.9e8, 0 in the middle)
ACTOR_STD_BOUNDS = (0.1, 1.0)  # the paper authors' (low, high) of soft_bounded for the actor's sigma: 0.1 .. 1.34


# --- MLP, encoder, decoder, recurrent core, posterior ---------------------------------------------
def norm_1d(kind: str, size: int) -> nn.Module:
    return nn.BatchNorm1d(size) if kind == "batch" else nn.LayerNorm(size)


def norm_2d(kind: str, channels: int) -> nn.Module:
    # GroupNorm with one group normalises over (C, H, W): the layer norm of a feature map
    return nn.BatchNorm2d(channels) if kind in ("batch", "mixed") else nn.GroupNorm(1, channels)


def frames_to_input(frames: torch.Tensor) -> torch.Tensor:
    """uint8 frames (..., H, W, 3) -> float (..., 3, H, W) scaled to [-0.5, 0.5] (paper appendix)."""
    return frames.movedim(-1, -3).float() / 255.0 - 0.5


def input_to_frames(images: torch.Tensor) -> torch.Tensor:
    """Inverse of frames_to_input: float (..., 3, H, W) -> uint8 (..., H, W, 3), rounded to the nearest level."""
    return ((images + 0.5) * 255.0).round().clamp(0, 255).to(torch.uint8).movedim(-3, -1)


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
    decoder's last layer (k12 s4, B * L frames) oneDNN runs this about 2x faster on a CPU than the transposed conv.
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
    (clamped to [--decoder-min-log-sigma, 2]: LOG_SIGMA_RANGE).
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
        # A floor at 0 with log sigma starting at 0 fixes sigma = 1: at sigma = 1 the likelihood pulls log sigma down
        # while the mean squared error per pixel is below 1 (pixels lie in [-0.5, 0.5]). The pixel term keeps its
        # weight against the KL instead of growing as the reconstructions sharpen (docs/deviations.md, --preset cpu).
        return self.log_sigma.clamp(self.min_log_sigma, LOG_SIGMA_RANGE[1]).exp()


class RecurrentCell(nn.Module):
    """The recurrent core: nn.LSTMCell with a learned initial state (DLC-v1's change to Dreamer-v3).

    This class is the seam between the LSTM and GRU scripts: the rest of the file only calls
    `initial_state(batch)` (a tuple of tensors) and `step(state, x) -> (new_state, h)`, and treats
    the state as an opaque tuple. The LSTM state is (h, c); h is the deterministic part of the model
    state s = (z, h). The initial h and c are parameters, so the optimiser learns them.
    """

    def __init__(self, input_size: int, deter_size: int):
        super().__init__()
        self.cell = nn.LSTMCell(input_size, deter_size)
        self.initial_h = nn.Parameter(torch.zeros(deter_size))
        self.initial_c = nn.Parameter(torch.zeros(deter_size))

    def initial_state(self, batch: int) -> tuple[torch.Tensor, ...]:
        return (self.initial_h.expand(batch, -1), self.initial_c.expand(batch, -1))

    def step(self, state: tuple[torch.Tensor, ...], x: torch.Tensor) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
        h, c = self.cell(x, state)
        return (h, c), h


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


# --- output distributions: Gaussian (latents, heads), DreamerV3's two-hot (--heads) ---------------
def gaussian_params(out: torch.Tensor, min_std: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Split a head's output into the mean and sigma (softplus plus a minimum) of a diagonal Gaussian, in float32
    (under --amp the head computed in bfloat16; distributions and losses do not)."""
    mean, raw_std = out.float().chunk(2, dim=-1)
    return mean, F.softplus(raw_std) + min_std


def gaussian_nll(x: torch.Tensor, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """-log N(x; mean, std), elementwise."""
    return 0.5 * ((x - mean) / std).pow(2) + torch.log(std) + 0.5 * math.log(2 * math.pi)


def symexp(x: torch.Tensor) -> torch.Tensor:
    """sign(x) (exp(|x|) - 1): the inverse of DreamerV3's symlog(x) = sign(x) log(1 + |x|)."""
    return torch.sign(x) * torch.expm1(x.abs())


def twohot_bins(count: int = TWOHOT_BINS, span: float = TWOHOT_SPAN) -> torch.Tensor:
    """`count` (odd) bins evenly spaced in symlog space over [-span, span]: symexp of a linspace, built from its
    lower half so that the middle bin is exactly 0 and the bins are exactly symmetric."""
    half = symexp(torch.linspace(-span, 0.0, count // 2 + 1))
    return torch.cat([half, -half[:-1].flip(0)])


def twohot(x: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
    """Two-hot encoding (..., K) of x (...): x clipped to the bins' range, its mass split between the two bins
    around it in proportion to nearness, so that the encoding's mean sum_k w_k b_k is x."""
    x = x.detach().float().clamp(bins[0], bins[-1])
    upper = torch.bucketize(x, bins).clamp(1, len(bins) - 1)  # bins[upper - 1] <= x <= bins[upper]
    low, high = bins[upper - 1], bins[upper]
    weight_high = (x - low) / (high - low)
    encoding = torch.zeros(*x.shape, len(bins), device=x.device)
    encoding.scatter_(-1, (upper - 1).unsqueeze(-1), (1 - weight_high).unsqueeze(-1))
    return encoding.scatter_(-1, upper.unsqueeze(-1), weight_high.unsqueeze(-1))


class Gaussian:
    """A scalar's Gaussian from a head's two outputs: mean, and sigma learned (softplus, floored at HEAD_MIN_STD)
    when `sigma` is 0, else fixed at `sigma` (--head-sigma; the second output is then unused)."""

    def __init__(self, out: torch.Tensor, sigma: float):
        mean, std = gaussian_params(out, HEAD_MIN_STD)
        self.mean, self.std = mean.squeeze(-1), (std if sigma == 0 else torch.full_like(mean, sigma)).squeeze(-1)

    def nll(self, x: torch.Tensor) -> torch.Tensor:
        """-log N(x; mean, sigma)."""
        return gaussian_nll(x, self.mean, self.std)


class TwoHot:
    """A scalar's distribution as a softmax over fixed bins (DreamerV3): mean sum_k p_k b_k; a target x is learned
    by cross-entropy against its two-hot encoding, whose mean is x."""

    def __init__(self, logits: torch.Tensor, bins: torch.Tensor):
        self.logits, self.bins = logits.float(), bins

    @property
    def mean(self) -> torch.Tensor:
        """sum_k p_k b_k, summed in pairs from the middle out (b_{m-i} with b_{m+i}), as DreamerV3 does: uniform
        probabilities over symmetric bins then give exactly 0, as a left-to-right sum over +-4.9e8 would not."""
        products, middle = self.logits.softmax(-1) * self.bins, len(self.bins) // 2
        pairs = products[..., :middle].flip(-1) + products[..., middle + 1 :]
        return products[..., middle] + pairs.sum(-1)

    @property
    def std(self) -> torch.Tensor:
        return (self.logits.softmax(-1) * (self.bins - self.mean.unsqueeze(-1)).pow(2)).sum(-1).sqrt()

    def nll(self, x: torch.Tensor) -> torch.Tensor:
        """Cross-entropy -sum_k twohot(x)_k log p_k."""
        return -(twohot(x, self.bins) * self.logits.log_softmax(-1)).sum(-1)


class ScalarHead(MLP):
    """The reward head and the critic's network: an MLP whose output is a scalar's distribution (--heads):
    a Gaussian (2 outputs: mean, sigma) or DreamerV3's two-hot (TWOHOT_BINS logits, output layer zeroed, so that
    every prediction starts at exactly 0)."""

    def __init__(self, in_size: int, hidden_sizes: list[int], norm: str, kind: str = "gaussian", sigma: float = 0.0):
        super().__init__(in_size, hidden_sizes, 2 if kind == "gaussian" else TWOHOT_BINS, norm)
        self.kind, self.sigma = kind, sigma
        if kind == "twohot":
            self.register_buffer("bins", twohot_bins(), persistent=False)  # (not in checkpoints: a constant)
            nn.init.zeros_(self.net[-1].weight)
            nn.init.zeros_(self.net[-1].bias)

    def distribution(self, out: torch.Tensor) -> Gaussian | TwoHot:
        """The scalar's distribution given this head's output: .mean, .std and .nll(x), of shape out.shape[:-1]."""
        return Gaussian(out, self.sigma) if self.kind == "gaussian" else TwoHot(out, self.bins)

    def dist(self, features: torch.Tensor) -> Gaussian | TwoHot:
        """The scalar's distribution at `features` (..., F)."""
        return self.distribution(self(features))


# --- the world model: one step observed or imagined -----------------------------------------------
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
        self.reward = ScalarHead(feature_size, [args.mlp_size] * 2, args.norm, args.heads, args.head_sigma)
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

        The only Python loop of the world model; every sequence starts from the learned initial state and z = 0,
        with its first step's real previous action (zeroed only where is_first marks an episode's start).
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


# --- the actor (its log pi and sigma bound first) and the critic ----------------------------------
def policy_log_prob(action: torch.Tensor, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """log pi(a) = sum_d [log N(a_d; mean_d, sigma_d) - log(1 - tanh(a_d)^2 + 1e-6)] of the unclipped sample a
    (paper 3.9): the Gaussian's log density plus a penalty that grows with |a| (extreme_action_term)."""
    return (-gaussian_nll(action, mean, std) - torch.log(1 - torch.tanh(action).pow(2) + 1e-6)).sum(-1)


def extreme_action_term(action: torch.Tensor) -> torch.Tensor:
    """sum_d -log(1 - tanh(a_d)^2 + 1e-6): log pi's part that grows with |a| (0 at a = 0; --action-penalty)."""
    return -torch.log(1 - torch.tanh(action).pow(2) + 1e-6).sum(-1)


def soft_bounded(x: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """low + softplus(high - softplus(high - x) - low): smooth and increasing, above low, saturating at
    low + softplus(high - low) (the actor's sigma for the bounds (0.1, 1): 0.1 .. 1.34, 0.61 at x = 0)."""
    return low + F.softplus(high - F.softplus(high - x) - low)


class Actor(nn.Module):
    """MLP 572->512->512->512->512->4 giving mu(2), sigma(2); the action is a ~ N(tanh(mu), sigma), clipped to
    [-1, 1] (the paper authors' form).

    The noise lives in action space with sigma softly bounded below by 0.1, so the policy keeps exploring
    even where its mean saturates; a tanh-squashed Gaussian has no such floor (the std of tanh(N(2, 0.05))
    is 0.004), and its steering goes bang-bang (docs/deviations.md).
    """

    def __init__(self, feature_size: int, mlp_size: int, action_dim: int, norm: str):
        super().__init__()
        self.net = MLP(feature_size, [mlp_size] * 4, 2 * action_dim, norm)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, raw_std = self.net(features).float().chunk(2, dim=-1)
        return torch.tanh(mean), soft_bounded(raw_std, *ACTOR_STD_BOUNDS)

    def sample(self, features: torch.Tensor, deterministic: bool = False):
        """a = tanh(mu) + sigma eps by rsample (eps ~ N(0, I)), and log pi(a) = sum_d
        [log N(a_d; tanh mu_d, sigma_d) - log(1 - tanh(a_d)^2 + 1e-6)] (paper 3.9: the second term penalises
        extreme actions). Returns the action clipped to [-1, 1] (what the env and the world model receive) and
        log pi (None if deterministic: the mean action)."""
        mean, std = self(features)
        if deterministic:
            return mean, None
        action = mean + std * torch.randn_like(std)
        return action.clamp(-1.0, 1.0), policy_log_prob(action, mean, std)


class Critic(nn.Module):
    """MLP 572->512->512->2 with LayerNorm (appendix): the lambda-return's distribution (ScalarHead: a Gaussian, or
    255 two-hot logits with --heads twohot)."""

    def __init__(self, feature_size: int, mlp_size: int, kind: str = "gaussian", sigma: float = 0.0):
        super().__init__()
        self.net = ScalarHead(feature_size, [mlp_size] * 2, "layer", kind, sigma)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.net(features)

    def dist(self, features: torch.Tensor) -> Gaussian | TwoHot:
        """The lambda-return's distribution at `features` (..., F): .mean is the value V(s). Through self(...), not
        self.net.dist, so that --compile's compiled forward is the one used."""
        return self.net.distribution(self(features))


# =====================================================================================
# 4. Losses and returns (paper 3.8 world model, 3.9 behaviour)
# =====================================================================================
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
    assert rewards.shape == continues.shape == values.shape == log_pi.shape, (rewards.shape, values.shape, log_pi.shape)
    ret = values[-1]  # R_H
    returns = []
    for t in reversed(range(rewards.shape[0])):  # ret is R_{t+1} here, R_t after the step
        bootstrap = (1 - lam) * values[t] + lam * ret
        ret = rewards[t] - alpha * log_pi[t] + gamma * continues[t] * bootstrap
        returns.append(ret)
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


# =====================================================================================
# 5. Replay (one per agent)
# =====================================================================================
class Replay:
    """Ring buffer of steps: uint8 frame (at --image-size), action that led to it, reward received with it,
    is_first, terminated.

    Frames are stored once (no separate next observation): a sequence of L steps holds L frames.
    Whole car episodes are added at once, so K parallel races never interleave inside the buffer;
    sequences may cross episode boundaries, which is_first marks. A step is one decision (--action-repeat env
    steps); capacity is in steps. chunk_size and saver serve only the replay's saves (utils/checkpoint.py).
    """

    def __init__(self, capacity: int, image_size: int, action_dim: int = 2, chunk_size: int = 1000):
        self.capacity, self.chunk_size = int(capacity), int(chunk_size)
        self.obs = np.zeros((self.capacity, image_size, image_size, 3), dtype=np.uint8)  # pages are touched lazily
        self.action = np.zeros((self.capacity, action_dim), dtype=np.float32)
        self.reward = np.zeros(self.capacity, dtype=np.float32)
        self.is_first = np.zeros(self.capacity, dtype=bool)
        self.terminated = np.zeros(self.capacity, dtype=bool)
        self.next_index, self.size, self.total_steps, self.episodes = 0, 0, 0, 0
        self.saver = None  # utils.checkpoint.ReplaySaver: what was saved of this buffer, and where

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


# =====================================================================================
# 6. Agent: world-model learning, behaviour learning in imagination, acting
# =====================================================================================
RETURN_NORM_RATE = 0.01  # --return-norm: EMA rate of the return scale (DreamerV3)
EVAL_POLICIES = ("deterministic", "mean-action", "stochastic")  # Agent.act's policies (--eval-policy)


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


@torch.no_grad()
def restore_buffers(module: nn.Module, saved: list[torch.Tensor]) -> None:
    """Put back `module`'s buffers (BatchNorm statistics) as `saved` (their clones, in module.buffers() order)."""
    for buffer, value in zip(module.buffers(), saved):
        buffer.copy_(value)


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


def imagine_rollout(world_model: WorldModel, actor: Actor, state: tuple, h, z, horizon: int,
                    straight_through: bool = False):  # fmt: skip
    """Roll the prior forward `horizon` steps from detached start states, acting with the actor.

    Returns features s_0..s_H (H+1, N, F), log pi_0..log pi_{H-1} (H, N), the sampled actions before clipping
    (H, N, A; the model is given them clipped to [-1, 1]) and the actor's sigma at every step (H, N, A).
    Everything is reparameterised, so the actor loss backpropagates through the learned dynamics, except where a
    sample falls outside [-1, 1]: the clip passes no gradient, so that step's action dimension gets no gradient of
    reward or value, only the entropy bonus's (a share of samples that grows with sigma and as the mean nears +-1).
    `straight_through` (--straight-through-clip) gives the model the same clipped action with the identity's
    gradient instead.
    """
    features, log_pis, raw_actions, stds = [torch.cat([z, h], -1)], [], [], []
    for _ in range(horizon):
        mean, std = actor(features[-1])
        action = mean + std * torch.randn_like(std)  # Actor.sample, keeping sigma for the diagnostics
        log_pis.append(policy_log_prob(action, mean, std))
        raw_actions.append(action)
        clipped = action.clamp(-1.0, 1.0)
        if straight_through:
            clipped = action + (clipped - action).detach()
        state, h, z = world_model.imagine_step(state, z, clipped)
        features.append(torch.cat([z, h], -1))
        stds.append(std)
    return torch.stack(features), torch.stack(log_pis), torch.stack(raw_actions), torch.stack(stds)


class Agent:
    """One car's learner: world model, actor, critic, the target networks (the KL terms' stop-gradient side, the
    slow critic) and Adam optimisers for the model, actor, critic (and alpha, with --entropy-target)."""

    def __init__(self, args: Args, action_dim: int = 2, device: torch.device | str = "cpu"):
        self.args, self.action_dim, self.device = args, action_dim, torch.device(device)
        feature_size = args.latent_size + args.deter_size
        self.world_model = WorldModel(args, action_dim).to(self.device)
        self.actor = Actor(feature_size, args.mlp_size, action_dim, args.norm).to(self.device)
        self.critic = Critic(feature_size, args.mlp_size, args.heads, args.head_sigma).to(self.device)
        # Target networks (hard copy now, soft updates later): the stop-gradient sides of the KL terms
        # and the slow critic for bootstrap values. They never receive gradient.
        self.targets = nn.ModuleDict(
            {
                "encoder": copy.deepcopy(self.world_model.encoder),
                "representation": copy.deepcopy(self.world_model.representation),
                "transition": copy.deepcopy(self.world_model.transition),
                "critic": copy.deepcopy(self.critic),  # (always kept: checkpoints hold it whatever the flags)
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
        self.amp = bf16_autocast(args.amp, self.device)
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

    # --- world model (paper 3.8) ------------------------------------------------------------
    def world_model_loss(self, obs, actions, rewards, is_first, terminated):
        """L = mean over batch and time of L_pred + beta_dyn L_dyn + beta_rep L_rep; also returns the posterior.
        Each KL term is at least --free-bits (kl_free_bits).

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
        reward = wm.reward.dist(features)
        reward_nll = reward.nll(rewards)
        cont_logits = wm.cont(features).float().squeeze(-1)
        cont_nll = F.binary_cross_entropy_with_logits(cont_logits, 1.0 - terminated, reduction="none")
        # The KL terms' stop-gradient sides, sg(.), come from slowly updated copies of the encoder, posterior and
        # prior (the paper's target networks; DreamerV3 uses the live networks under a stop-gradient). L_dyn pulls the
        # prior toward the target posterior, L_rep the posterior toward the target prior, both at the live h.
        with torch.no_grad():
            target_embed = self.targets["encoder"](obs)
            target_representation = self.targets["representation"]
            target_post = target_representation(target_representation.embed_part(target_embed), h.detach())
            sg_post_mean, sg_post_std = gaussian_params(target_post, LATENT_MIN_STD)
            sg_prior_mean, sg_prior_std = gaussian_params(self.targets["transition"](h.detach()), LATENT_MIN_STD)
        # paper eq. L_dyn: trains the prior and, through the live h, the recurrent core and the earlier posteriors
        kl_dyn = gaussian_kl(sg_post_mean, sg_post_std, prior_mean, prior_std)
        kl_rep = gaussian_kl(post["post_mean"], post["post_std"], sg_prior_mean, sg_prior_std)  # paper eq. L_rep
        loss = (
            image_nll + reward_nll + cont_nll
            + args.kl_dyn_scale * kl_free_bits(kl_dyn, args.free_bits)
            + args.kl_rep_scale * kl_free_bits(kl_rep, args.free_bits)
        ).mean()  # fmt: skip
        metrics = {
            # "reconstruction": the frames' negative log-likelihood (below 0 once a learned sigma is small)
            "model_loss": loss, "reconstruction": image_nll.mean(), "reward": reward_nll.mean(),
            "continue": cont_nll.mean(), "kl_dyn": kl_dyn.mean(), "kl_rep": kl_rep.mean(),
        }  # fmt: skip
        return loss, metrics, post

    def _update_model_targets(self) -> None:
        """After a world-model step: the KL terms' target encoder, posterior and prior move tau toward the live ones."""
        wm, tau = self.world_model, self.args.tau
        soft_update(self.targets["encoder"], wm.encoder, tau)
        soft_update(self.targets["representation"], wm.representation, tau)
        soft_update(self.targets["transition"], wm.transition, tau)

    # --- behaviour (paper 3.9) ---------------------------------------------------------------
    def alpha(self) -> float | torch.Tensor:
        """The entropy weight of the lambda-return: --entropy-coef, or exp(log alpha) under --entropy-target."""
        return self.args.entropy_coef if self.log_alpha is None else self.log_alpha.detach().exp()

    def start_states(self, post: dict, terminated: torch.Tensor):
        """Detached posterior states (state tuple, h, z) of all B*L steps, or a random subset of them, and each
        start's continue flag 1 - terminated."""
        state = tuple(s.flatten(0, 1).detach() for s in post["states"])
        h, z = post["h"].flatten(0, 1).detach(), post["z"].flatten(0, 1).detach()
        cont = 1.0 - terminated.flatten(0, 1)
        num = self.args.imagination_starts
        if 0 < num < h.shape[0]:
            idx = torch.randperm(h.shape[0], device=h.device)[:num]
            state, h, z, cont = tuple(s[idx] for s in state), h[idx], z[idx], cont[idx]
        assert all(s.shape[0] == h.shape[0] for s in state) and z.shape[0] == cont.shape[0] == h.shape[0]
        return state, h, z, cont

    def behaviour_losses(self, post: dict, terminated: torch.Tensor):
        """The behaviour's losses on imagined rollouts: the actor's (backprop through the frozen dynamics), the
        critic's, and alpha's under --entropy-target (else None); and their metrics.

        BatchNorm sees imagined states only through its running statistics: the world model's come from the
        real posterior states of its own loss, the actor's from a no-grad train-mode pass over the same real
        states here. Imagined states are never what the car sees (a long imagination drifts away from the
        real state distribution), and acting uses the same running statistics as the policy optimised here.
        """
        args, wm = self.args, self.world_model
        if args.norm == "batch":  # the actor's BatchNorm statistics: real posterior states of the batch
            with torch.no_grad():  # (--norm layer or mixed: the actor's LayerNorms keep none)
                self.actor.train()
                self.actor(torch.cat([post["z"], post["h"]], -1).detach())
        state, h, z, start_cont = self.start_states(post, terminated)
        value_net = self.targets["critic"] if args.target_critic else self.critic  # what the returns bootstrap on
        wm.eval()
        self.actor.eval()
        with frozen(wm, self.critic):  # only the actor's parameters take gradient from the actor loss
            features, log_pi, raw_actions, stds = imagine_rollout(wm, self.actor, state, h, z,
                                                                 args.imagination_horizon, args.straight_through_clip)
            rewards = wm.reward.dist(features[1:]).mean  # r_1..r_H
            continues = torch.sigmoid(wm.cont(features[1:]).float().squeeze(-1))  # c_1..c_H
            values = value_net.dist(features[1:]).mean  # V(s_1..s_H)
            weights = discount_weights(continues, args.gamma, start_cont)
            returns, objective = self.returns_and_objective(rewards, continues, values, log_pi, raw_actions)
            actor_loss = -(weights * objective).mean()  # its gradient flows back through the imagined dynamics
        wm.train()
        self.actor.train()
        critic_loss = self.critic_loss(features[:-1].detach(), returns.detach(), weights)
        metrics = {
            "actor": actor_loss, "critic": critic_loss, "actor_std": stds.mean(),
            "entropy": -log_pi.mean(),  # -log pi with the extreme-action term: an entropy estimate minus that penalty
            "imagined_return": returns.mean(),  # the lambda-return with the entropy bonus (and --action-penalty's term)
        }  # fmt: skip
        if args.return_norm:
            metrics["return_scale"] = self.return_scale.clone()
        alpha_loss = None
        if self.log_alpha is not None:
            metrics["alpha"] = self.log_alpha.detach().exp()
            alpha_loss, metrics["alpha_entropy"] = self.alpha_loss(log_pi.detach(), raw_actions.detach())
        return actor_loss, critic_loss, alpha_loss, metrics

    def returns_and_objective(self, rewards, continues, values, log_pi, raw_actions):
        """The lambda-returns the critic learns, and the actor's objective (paper 3.9): the lambda-return of the
        imagined rewards with the entropy bonus -alpha log pi_t, which comes with r_{t+1}. The two are the same
        tensor unless --return-norm scales the objective's task part; it also moves that scale (an EMA of the task
        returns' 5-95% range over every imagined step, those after a predicted termination too)."""
        args, alpha = self.args, self.alpha()
        gamma, lam = args.gamma, args.lambda_
        # --action-penalty beta reweighs log pi's extreme-action part: -alpha log pi + (alpha - beta) term
        # = -alpha log N(a) - beta term, added to the rewards (lambda_returns is linear in r, V and log pi)
        action_term = None
        if args.action_penalty is not None:
            action_term = (alpha - args.action_penalty) * extreme_action_term(raw_actions)
        if not args.return_norm:  # the paper's
            shaped = rewards if action_term is None else rewards + action_term
            returns = lambda_returns(shaped, continues, values, log_pi, gamma, lam, alpha)
            return returns, returns
        # --return-norm (DreamerV3): the task part over max(1, S), S an EMA of its 95th - 5th percentile range; the
        # entropy part unscaled
        zero = torch.zeros_like(rewards)
        task = lambda_returns(rewards, continues, values, torch.zeros_like(log_pi), gamma, lam, 0.0)
        entropy_rewards = zero if action_term is None else action_term
        entropy = lambda_returns(entropy_rewards, continues, zero, log_pi, gamma, lam, alpha)
        with torch.no_grad():  # (a non-finite batch leaves the scale alone)
            spread = return_range(task)
            moved = self.return_scale.lerp(spread, RETURN_NORM_RATE)
            self.return_scale.copy_(torch.where(spread.isfinite(), moved, self.return_scale))
        return task + entropy, task / self.return_scale.clamp(min=1.0) + entropy

    def critic_loss(self, features: torch.Tensor, returns: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """The critic's loss on the imagined states s_0..s_{H-1} (the caller detaches them and the returns): the
        negative log-likelihood of their lambda-returns under V, weighted by the discount weights. Two-hot heads
        (DreamerV3) also regress on the slow critic's value, with weight 1."""
        value = self.critic.dist(features)
        nll = value.nll(returns)
        if self.args.heads == "twohot":
            with torch.no_grad():
                slow_value = self.targets["critic"].dist(features).mean
            nll = nll + value.nll(slow_value)
        return (weights * nll).mean()

    def alpha_loss(self, log_pi: torch.Tensor, raw_actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """--entropy-target (SAC's automatic tuning): the loss -log(alpha) (target - entropy), whose step raises alpha
        while the policy's entropy is below the target (nats per action dimension, times the action size) and lowers
        it above. The entropy is the one alpha weighs, -log pi (-log N(a) when --action-penalty takes the
        extreme-action term apart), a plain mean over every imagined step (not discount-weighted). Returns the loss
        and that entropy."""
        penalty_part = 0 if self.args.action_penalty is None else extreme_action_term(raw_actions).mean()
        entropy = -log_pi.mean() + penalty_part
        shortfall = self.args.entropy_target * self.action_dim - entropy
        return -self.log_alpha * shortfall, entropy

    def _batch_tensors(self, batch: dict) -> tuple[torch.Tensor, ...]:
        """Replay.sample's arrays as tensors on the device, shapes checked: obs (B, L, S, S, 3) uint8, actions
        (B, L, A), rewards (B, L), is_first (B, L) bool, terminated (B, L)."""
        dev = self.device
        obs = torch.as_tensor(batch["obs"], device=dev)
        actions = torch.as_tensor(batch["action"], device=dev, dtype=torch.float32)
        rewards = torch.as_tensor(batch["reward"], device=dev, dtype=torch.float32)
        is_first = torch.as_tensor(batch["is_first"], device=dev, dtype=torch.bool)
        terminated = torch.as_tensor(batch["terminated"], device=dev, dtype=torch.float32)
        b, l, size = *is_first.shape, self.args.image_size  # B sequences of L steps
        assert obs.shape == (b, l, size, size, 3), obs.shape
        assert actions.shape == (b, l, self.action_dim), actions.shape
        assert rewards.shape == terminated.shape == (b, l), (rewards.shape, terminated.shape)
        return obs, actions, rewards, is_first, terminated

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

        In order: the world model's loss and step, then its targets; imagination from the posterior states of that
        loss (computed before the step) rolled out by the stepped model; the actor's and critic's losses and steps;
        alpha's step (--entropy-target) on that imagination's entropy; the slow critic.

        Each optimiser step whose loss or gradient is not finite is skipped: its network, its BatchNorm statistics
        and its targets stay unchanged, and the update counts in nonfinite_updates. (The --return-norm scale is
        moved by the actor's returns before its step: a finite batch moves it even if that step is skipped.)"""
        if self.acting_only:
            raise RuntimeError("an acting-only export has no decoder, critic or optimiser state: it cannot learn")
        obs, actions, rewards, is_first, terminated = self._batch_tensors(batch)
        self._set_training(True)
        statistics = {m: [buf.clone() for buf in m.buffers()] for m in (self.world_model, self.actor)}  # BatchNorm

        with self.autocast():
            model_loss, metrics, post = self.world_model_loss(obs, actions, rewards, is_first, terminated)
        model_ok = self._step(self.model_optimizer, model_loss, self.world_model.parameters())
        if model_ok:
            self._update_model_targets()

        with self.autocast():
            actor_loss, critic_loss, alpha_loss, behaviour_metrics = self.behaviour_losses(post, terminated)
        actor_ok = self._step(self.actor_optimizer, actor_loss, self.actor.parameters())
        critic_ok = self._step(self.critic_optimizer, critic_loss, self.critic.parameters())
        alpha_ok = alpha_loss is None or self._step(self.alpha_optimizer, alpha_loss, [self.log_alpha])
        if critic_ok:  # the slow critic: the bootstrap (--target-critic) and two-hot's regression target
            soft_update(self.targets["critic"], self.critic, self.args.tau)
        for module, ok in ((self.world_model, model_ok), (self.actor, actor_ok)):
            if not ok:  # the batch's forward pass moved the running statistics: put them back
                restore_buffers(module, statistics[module])
        self.num_updates += 1
        faulty = not (model_ok and actor_ok and critic_ok and alpha_ok)
        self.nonfinite_updates += int(faulty)
        self.nonfinite_in_a_row = self.nonfinite_in_a_row + 1 if faulty else 0

        metrics.update(behaviour_metrics)
        values = torch.stack([v.detach().float() for v in metrics.values()]).tolist()  # one host sync per update
        return dict(zip(metrics, values))

    # --- acting --------------------------------------------------------------------------
    def initial_state(self, n: int):
        """Recurrent state of n cars before their first frame: (the recurrent core's state tuple, z, previous
        action)."""
        with torch.no_grad():
            core_state = tuple(s.clone() for s in self.world_model.cell.initial_state(n))
        z = torch.zeros(n, self.args.latent_size, device=self.device)
        return core_state, z, torch.zeros(n, self.action_dim, device=self.device)

    @torch.no_grad()
    def act(self, obs: np.ndarray, state=None, is_first=None, policy: str = "stochastic"):
        """Actions for the n cars this agent drives: obs (n, H, W, 3) uint8, is_first (n,) bool.

        Returns actions (n, A) numpy in [-1, 1] and the new state (core state, z, action). state=None starts every car
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
        core_state, z, prev_action = state
        embed_part = self.world_model.representation.embed_part(self.world_model.encoder(frames))
        first = torch.as_tensor(is_first, device=self.device)
        sample_z = policy != "deterministic"
        core_state, h, z, _, _ = self.world_model.observe_step(core_state, z, prev_action, embed_part, first,
                                                              sample_z)  # fmt: skip
        action, _ = self.actor.sample(torch.cat([z, h], -1), deterministic=policy != "stochastic")
        return action.cpu().numpy(), (core_state, z, action)

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

    # --- persistence (what is saved: utils/checkpoint.py) -------------------------------------------
    def state_dict(self) -> dict:
        """Everything the agent learns and counts: networks, targets, optimisers, alpha, return scale, counters."""
        return checkpoint_io.agent_state_dict(self)

    def load_state_dict(self, state: dict) -> None:
        """A full state, or an acting-only export (the agent then drives, it cannot learn)."""
        checkpoint_io.load_agent(self, state)


# =====================================================================================
# 7. Training loop (Algorithm 1)
# =====================================================================================
def train_agent(agent: Agent, replay: Replay, args: Args, logger, prefix: str, on_update=None) -> float:
    """Algorithm 1's training step of one agent: --train-steps-per-episode updates, each on B sequences of length L
    sampled uniformly from its own replay; returns updates per second.

    Each update's losses go to the logger as running means (SB3's record_mean; non-finite values are left out).
    `on_update(done, seconds)` is called after every update (progress display). Stops early once the agent has
    had --max-nonfinite-updates updates in a row with a non-finite loss or gradient (the run then ends)."""
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


def start_race(run) -> tuple[np.ndarray, int]:
    """One race at a time (K = 1): reset on the next race's track, a ghost track with its ghost (if it has one yet)
    in the ghost stage, else the track races_seed(seed, episode), so a resumed run drives the same tracks."""
    args, episode = run.args, run.counters["episode"]
    if args.stage == "ghost":
        seed = args.ghost_seed + episode % args.ghost_tracks
        run.envs.set_options({"ghosts": {"car_0": run.ghosts[seed]}} if seed in run.ghosts else {})
    else:
        seed = races_seed(args.seed, episode)
    run.envs.seed(seed)
    return run.envs.reset(), seed


def record_ghost(run, final_info: dict, track_seed: int) -> None:
    """The ghost stage (paper): each ghost track's ghost is the agent's first run on it, replaced by every run that
    beats it (finishes earlier or, if neither finishes, has touched more tiles: envs.ghost_beaten), so the agent
    always races its own best run on that track."""
    if track_seed not in run.ghosts or final_info.get("ghost_beaten"):
        run.ghosts[track_seed] = final_info["trajectory"].to_dict()


def main(args: Args, overrides=()) -> str:
    """Train with `args` (Algorithm 1); returns the run directory. With args.resume the run continues with the
    settings it was started with, except the fields named in `overrides`, which come from `args`.

    Bad input (an impossible argument, an unreadable checkpoint, a replay that cannot fit in memory) raises
    UsageError before anything is written. --max-nonfinite-updates faulty updates in a row end the run with a
    checkpoint and raise NumericalFault. The run's set-up, logging and checkpoints: utils/run.py."""
    from tqdm import tqdm

    run = setup_run(sys.modules[__name__], args, overrides)  # a new run, or a saved one exactly as it stopped
    args, n, k_races = run.args, run.args.num_agents, run.args.num_races
    # One race at a time starts on its own track (start_race); K races side by side auto-reset on the tracks of
    # each race's seeded stream, with the dead zone set ahead for the race that starts next (below).
    if k_races == 1:
        obs, track_seed = start_race(run)
    else:
        obs, track_seed = run.envs.reset(), None
        set_next_dead_zone(run)
    races = Races(run.agents, args, run.envs, obs)  # agent i drives car i of every race
    run.pbar = tqdm(total=args.total_episodes, initial=run.counters["episode"], desc=f"{VARIANT} {args.stage}")
    while not run.finished():
        # --- act: every agent drives its own car in every race until a race ends (random actions in the prefill).
        # Races.drive (utils/collector.py) holds each decision --action-repeat env steps and sums their rewards; a
        # prefill action is uniform in [-1, 1]; a car's episode starts with its first frame (action and reward 0), and
        # a frame is terminal on an elimination or a finished lap, never at the time limit (truncation).
        started = time.time()
        ended, steps = races.drive(["random" if run.acts_randomly() else "stochastic"] * n)
        run.counters["global_step"] += k_races * steps
        env_sps = k_races * steps / max(time.time() - started, 1e-9)
        for race in ended:
            # --- store: each car's episode goes to its own agent's replay
            for j, car in enumerate(race.cars):
                run.replays[j].add_episode(*car.arrays())
            run.counters["episode"] += 1
            if args.stage == "ghost":
                record_ghost(run, race.cars[0].final_info or {}, track_seed)
            log_race(run, race.cars, track_seed, env_sps)
            set_next_dead_zone(run)
            # --- train: after every race that ended, each agent updates on its own replay (once the prefill races
            # are done; a ghost stage first races each of its ghost tracks once: Run.learning_starts)
            if run.learns_now():
                for j, (agent, replay) in enumerate(zip(run.agents, run.replays)):
                    updates_per_s = train_agent(agent, replay, args, run.logger, f"car_{j}/", progress_callback(run, j))
                    log_updates(run, j, updates_per_s)
                    if run.fault is not None:
                        break
            # video every --video-every races, evaluation every --eval-every (best.pt), replay save, latest.pt, logs
            after_training(run, race.cars, env_sps)
            if run.finished():
                break
        if k_races == 1 and not run.finished():
            # the next race's own track (the ghost stage: with its ghost); the race the vec env's auto-reset began
            # is replaced
            obs, track_seed = start_race(run)
            races.start(obs)
    return finish_run(run)


# =====================================================================================
# 8. This script's checkpoints (the formats and the run plumbing: utils/checkpoint.py, utils/run.py)
# =====================================================================================
def load_checkpoint(path: str, map_location="cpu", training: bool = False) -> dict:
    """A checkpoint or acting-only export of this script, loaded with weights_only=True (utils.checkpoint)."""
    return checkpoint_io.load_checkpoint(path, VARIANT, map_location, training)


def args_from_checkpoint(checkpoint: dict, path: str, **overrides) -> Args:
    """The Args a checkpoint was trained with (new flags keep their defaults, flags removed since are dropped)."""
    return checkpoint_io.args_from_checkpoint(Args, checkpoint, path, **overrides)


def agent_from_checkpoint(path: str, index: int = 0, device="cpu", checkpoint: dict | None = None) -> Agent:
    """Agent `index` of a checkpoint of this script, built with the sizes it was trained with (race.py, evaluate.py);
    `checkpoint`: the file already loaded (load_checkpoint), not read again."""
    return checkpoint_io.agent_from_checkpoint(sys.modules[__name__], path, index, device, checkpoint)


if __name__ == "__main__":
    from utils.run import cli

    cli(sys.modules[__name__])
