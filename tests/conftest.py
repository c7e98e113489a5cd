"""Shared by the test files: the two agent scripts, tiny network sizes, a fixture running a test on each script, random
batches, stand-in heads and TensorBoard event files written as a run's sittings would."""

from __future__ import annotations

import importlib
import math
import os
import types

import numpy as np
import pytest
import torch
from torch import nn

SCRIPTS = ["dreamer_lstm", "dreamer_gru"]

# Tiny sizes for fast tests (the methods are size-agnostic).
TINY = {
    "cnn_depth": 4, "deter_size": 16, "hidden_size": 16, "mlp_size": 16, "latent_size": 4, "image_size": 64,
    "batch_size": 3, "seq_len": 8, "imagination_horizon": 4,
    "imagination_starts": 0,  # every start (a preset's count may exceed the tiny batch's B * L)
    "amp": "off",  # float32 on every machine (--amp auto is bfloat16 on a CPU with bfloat16 instructions)
}  # fmt: skip

# A tiny single-stage run: one prefill race, one update per race, evaluation after every race on one track.
TINY_RUN = dict(
    TINY, batch_size=2, imagination_horizon=3, max_steps=30, train_steps_per_episode=1, prefill_episodes=1,
    replay_capacity=500, total_episodes=1, eval_every=1, eval_episodes=1, video_every=0,
)  # fmt: skip
TINY_TRIAL = {k: v for k, v in TINY_RUN.items() if k != "total_episodes"}  # the same, for trials that set the length


@pytest.fixture(params=SCRIPTS)
def script(request):
    """The module of each agent script in turn (the same test runs on both variants)."""
    return importlib.import_module(request.param)


def assert_same(a, b, where="") -> None:
    """Bit-exact equality of nested dicts, lists and tuples (of the same type) of tensors, arrays, numbers and
    strings; NaN equals NaN. `where` names the first difference."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{where}: keys {sorted(a)} != {sorted(b)}"
        for key in a:
            assert_same(a[key], b[key], f"{where}/{key}")
    elif isinstance(a, (tuple, list)):
        assert type(a) is type(b) and len(a) == len(b), f"{where}: {a!r} != {b!r}"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True, msg=where)
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, float) and math.isnan(a):
        assert isinstance(b, float) and math.isnan(b), where
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def tiny_args(script, **overrides):
    """The script's Args at the TINY sizes, with `overrides`."""
    return script.Args(**{**TINY, **overrides})


def random_batch(batch=3, length=8, size=64, seed=0, episode_starts=(0,)):
    """A batch as Replay.sample returns it: random frames, actions (zero at an episode's first step), rewards."""
    rng = np.random.default_rng(seed)
    is_first = np.zeros((batch, length), dtype=bool)
    is_first[:, list(episode_starts)] = True
    return {
        "obs": rng.integers(0, 256, (batch, length, size, size, 3), dtype=np.uint8),
        "action": rng.uniform(-1, 1, (batch, length, 2)).astype(np.float32) * ~is_first[..., None],
        "reward": rng.normal(size=(batch, length)).astype(np.float32),
        "is_first": is_first,
        "terminated": np.zeros((batch, length), dtype=bool),
    }


class ColumnHead(nn.Module):
    """A stand-in reward head or critic whose distribution (`dist`) has mean column `index` of its input, sigma 1."""

    def __init__(self, index: int):
        super().__init__()
        self.index = index

    def dist(self, features):
        mean = features[..., self.index]
        return types.SimpleNamespace(mean=mean, std=torch.ones_like(mean))


class ConstantHead(nn.Module):
    """A stand-in head with one output, `value` everywhere (a continue logit)."""

    def __init__(self, value: float):
        super().__init__()
        self.value = value

    def forward(self, features):
        return torch.full((*features.shape[:-1], 1), self.value)


def write_sitting(run_dir, points, wall_start, pid=None):
    """One event file: eval points (env_steps, return, progress, updates) at 1000 s apart from wall_start, named
    as SB3's logger names a file of process `pid` (this test's own when None)."""
    from torch.utils.tensorboard import SummaryWriter

    before = set(os.listdir(run_dir)) if os.path.isdir(run_dir) else set()
    writer = SummaryWriter(run_dir)
    for i, (steps, ret, progress, updates) in enumerate(points):
        wall = wall_start + 1000.0 * i
        writer.add_scalar("car_0/perf/updates", updates, steps, walltime=wall)
        writer.add_scalar("car_0/eval/episodic_return", ret, steps, walltime=wall)
        writer.add_scalar("car_0/eval/progress", progress, steps, walltime=wall)
    writer.close()
    if pid is not None:
        as_process(run_dir, before, pid)


def as_process(run_dir, before, pid):
    """Rename the one event file written to run_dir since `before` (its file names) as process `pid`'s:
    events.out.tfevents.<time>.<host>.<pid>.<n>."""
    (name,) = set(os.listdir(run_dir)) - before
    head, rest = name.split(f".{os.getpid()}.", 1)
    os.rename(os.path.join(run_dir, name), os.path.join(run_dir, f"{head}.{pid}.{rest}"))
