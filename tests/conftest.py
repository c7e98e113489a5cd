"""Shared by the test files: the two agent scripts, tiny network sizes, and a fixture running a test on each script."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import torch

SCRIPTS = ["dreamer_lstm", "dreamer_gru"]

# Tiny sizes for fast tests (the methods are size-agnostic).
TINY = {
    "cnn_depth": 4, "deter_size": 16, "hidden_size": 16, "mlp_size": 16, "latent_size": 4, "image_size": 64,
    "batch_size": 3, "seq_len": 8, "imagination_horizon": 4,
    "imagination_starts": 0,  # every start (a preset's count may exceed the tiny batch's B * L)
}  # fmt: skip

# A tiny single-stage run: one prefill race, one update per race, evaluation after every race on one track.
TINY_RUN = dict(
    TINY, batch_size=2, imagination_horizon=3, max_steps=30, train_steps_per_episode=1, prefill_episodes=1,
    replay_capacity=500, total_episodes=1, eval_every=1, eval_episodes=1, video_every=0,
)  # fmt: skip


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
