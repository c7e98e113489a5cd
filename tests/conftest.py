"""Shared by the test files: the two agent scripts, tiny network sizes, and a fixture running a test on each script."""

from __future__ import annotations

import importlib

import pytest

SCRIPTS = ["dreamer_lstm", "dreamer_gru"]

# Tiny sizes for fast tests (the methods are size-agnostic).
TINY = {
    "cnn_depth": 4, "deter_size": 16, "hidden_size": 16, "mlp_size": 16, "latent_size": 4, "image_size": 64,
    "batch_size": 3, "seq_len": 8, "imagination_horizon": 4,
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
