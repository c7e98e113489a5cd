"""benchmarks/norm_gap.py: the windows against hand-cut ones, the readings against hand-computed norms, each pass
against the model observed directly in its mode (LayerNorm's all equal, BatchNorm's apart), the agent left as it
was, a saved run end to end, bad input."""

import importlib
import json
import os
import types

import numpy as np
import pytest
import torch

import norm_gap
from conftest import TINY_RUN, random_batch, tiny_args


def episode(length: int, start: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Frames numbered start, start + 1, ... (one pixel each) and actions numbered alike."""
    frames = np.arange(start, start + length, dtype=np.uint8).reshape(length, 1, 1, 1)
    return frames, np.arange(start, start + length, dtype=np.float32).reshape(length, 1)


def test_windows_are_cut_from_each_episodes_start_in_order_and_batched_whole():
    batches = norm_gap.windows([episode(7), episode(5, start=100)], length=3, batch=2)
    # episode 1 gives windows 0..2 and 3..5 (6 dropped), episode 2 gives 100..102 (103, 104 dropped): one batch of 2
    assert len(batches) == 1
    frames, actions, first = batches[0]
    assert frames[..., 0, 0, 0].tolist() == [[0, 1, 2], [3, 4, 5]] and actions[..., 0].tolist() == [[0, 1, 2],
                                                                                                     [3, 4, 5]]
    assert first.tolist() == [[True, False, False], [False, False, False]]
    frames = norm_gap.windows([episode(7), episode(5, start=100)], length=3, batch=1)[2][0]
    assert frames[..., 0, 0, 0].tolist() == [[100, 101, 102]]
    shuffled = norm_gap.windows([episode(7), episode(5, start=100)], 3, 1, np.random.default_rng(0))
    order = np.random.default_rng(0).permutation(3)  # the three windows, in the generator's order
    assert [int(b[0][0, 0, 0, 0, 0]) for b in shuffled] == [[0, 3, 100][i] for i in order]
    assert [bool(b[2][0, 0]) for b in shuffled] == [[True, False, True][i] for i in order]
    with pytest.raises(ValueError, match="gave 1 windows of 4 decisions, fewer than one batch of 2: drive more"):
        norm_gap.windows([episode(7)], length=4, batch=2)


def test_the_readings_are_the_relative_norm_the_sigma_units_and_the_actors_mean_action_apart():
    h_eval = torch.tensor([[[3.0, 4.0], [0.0, 2.0]]])  # one window of two steps: ||h|| 5 and 2
    h_train = h_eval + torch.tensor([[[0.0, 1.0], [1.0, 0.0]]])  # apart by 1 and 1: 0.2 and 0.5, mean 0.35
    evaluated = {"h": h_eval, "z": torch.zeros(1, 2, 1), "post_mean": torch.zeros(1, 2, 2),
                 "post_std": torch.tensor([[[2.0, 4.0], [1.0, 1.0]]])}  # fmt: skip
    train = {"h": h_train, "z": torch.zeros(1, 2, 1), "post_mean": torch.tensor([[[1.0, 1.0], [0.5, -0.5]]]),
             "post_std": torch.ones(1, 2, 2)}  # (the train sigma is not read)

    class Actor(torch.nn.Module):  # mean action (h_0 / 10, -h_1 / 10): read on [z, h]
        def forward(self, features):
            return torch.stack([features[..., 1] / 10, -features[..., 2] / 10], -1), None

    agent = types.SimpleNamespace(actor=Actor().train())
    out = norm_gap.gaps(agent, train, evaluated)
    np.testing.assert_allclose(out["h_gap"], [0.35], rtol=1e-6)
    np.testing.assert_allclose(out["z_gap"], [((0.5 + 0.25) / 2 + 0.5) / 2], rtol=1e-6)  # mean over latents, steps
    np.testing.assert_allclose(out["steer_gap"], [0.05], rtol=1e-6)  # h_0 apart by 0 and 1
    np.testing.assert_allclose(out["pedal_gap"], [0.05], rtol=1e-6)  # h_1 apart by 1 and 0
    np.testing.assert_allclose(out["steer"], [0.15], rtol=1e-6)
    np.testing.assert_allclose(out["pedal"], [0.3], rtol=1e-6)
    assert agent.actor.training  # put back as it was


@pytest.mark.parametrize("name", ["dreamer_lstm", "dreamer_gru"])
def test_each_pass_is_the_model_observed_in_its_mode_from_the_agents_own_statistics_and_the_agent_is_left_as_was(
        name):  # fmt: skip
    """eval is a plain eval-mode observe; train and recurrence are train-mode observes from the same running
    statistics (the encoder in eval mode for recurrence); LayerNorm gives the same states in every pass, BatchNorm
    does not; the buffers and every module's mode are as before, whichever mode the agent was in."""
    script = importlib.import_module(name)
    batch = random_batch(batch=3, length=8)
    inputs = [torch.as_tensor(batch[key]) for key in ("obs", "action", "is_first")]
    for norm in ("layer", "batch"):
        torch.manual_seed(0)
        agent = script.Agent(tiny_args(script, norm=norm))
        wm = agent.world_model
        with torch.no_grad():  # running statistics away from a fresh layer's 0 and 1, as after training
            for module in wm.modules():
                if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                    module.running_mean.uniform_(-1, 1), module.running_var.uniform_(0.5, 2)
        before = [b.clone() for b in wm.buffers()]
        expected = {}
        with torch.no_grad():
            for name_, (model_mode, encoder_mode) in {"eval": (False, False), "train": (True, True),
                                                       "recurrence": (True, False)}.items():  # fmt: skip
                wm.train(model_mode)
                wm.encoder.train(encoder_mode)
                expected[name_] = wm.observe(wm.encoder(inputs[0]), inputs[1], inputs[2], sample=False)
                for b, saved in zip(wm.buffers(), before):
                    b.copy_(saved)
        for training in (True, False):
            for part in (wm, agent.actor, agent.critic):
                part.train(training)
            passes = norm_gap.observe_modes(agent, batch["obs"], batch["action"], batch["is_first"])
            for key in ("eval", "train", "recurrence"):
                for part in ("h", "post_mean"):
                    torch.testing.assert_close(passes[key][part], expected[key][part], rtol=0, atol=0)
            for b, saved in zip(wm.buffers(), before):
                torch.testing.assert_close(b, saved, rtol=0, atol=0)
            assert all(m.training == training for part in (wm, agent.actor, agent.critic) for m in part.modules())
        out = norm_gap.gaps(agent, passes["train"], passes["eval"])
        inside = norm_gap.gaps(agent, passes["recurrence"], passes["eval"])
        if norm == "layer":
            assert all(float(np.max(out[key])) == 0.0 for key in ("h_gap", "z_gap", "steer_gap", "pedal_gap"))
            assert float(np.max(inside["h_gap"])) == 0.0
        else:
            assert float(np.min(out["h_gap"])) > 0.01 and float(np.min(out["z_gap"])) > 0.01
            assert float(np.min(inside["h_gap"])) > 0.01


def test_the_readings_use_the_actors_running_statistics_and_leave_its_mode():
    script = importlib.import_module("dreamer_lstm")
    agent = script.Agent(tiny_args(script, norm="batch"))
    agent._set_training(True)
    buffers = [b.clone() for b in agent.actor.buffers()]
    states = {"h": torch.randn(3, 8, 16), "z": torch.randn(3, 8, 4), "post_mean": torch.zeros(3, 8, 4),
              "post_std": torch.ones(3, 8, 4)}  # fmt: skip
    norm_gap.gaps(agent, states, states)
    for b, saved in zip(agent.actor.buffers(), buffers):  # a train-mode actor would have moved them
        torch.testing.assert_close(b, saved, rtol=0, atol=0)
    assert agent.actor.training


def test_a_saved_run_is_read_end_to_end_and_bad_input_is_named(tmp_path):
    script = importlib.import_module("dreamer_lstm")
    run_dir = script.main(script.Args(stage="single", runs_dir=str(tmp_path / "runs"), **TINY_RUN))
    latest = os.path.join(run_dir, "checkpoints", "latest.pt")
    out = str(tmp_path / "gap.json")
    row = norm_gap.main([latest, "--tracks", "1", "--json", out])
    assert json.load(open(out)) == row
    assert (row["variant"], row["norm"], row["batch_size"], row["seq_len"], row["tracks"]) == (
        "lstm", "batch", 2, 8, "10200..10200")  # fmt: skip
    assert row["windows"] == 30 // 8 // 2 * 2 and row["h_gap"] > 0  # 30 decisions: 3 windows, one batch of 2
    assert row["h_gap_recurrence"] > 0
    with pytest.raises(SystemExit, match="^norm_gap.py: error: --tracks must be >= 1, got 0$"):
        norm_gap.main([latest, "--tracks", "0"])
    with pytest.raises(SystemExit, match="^norm_gap.py: error: .*no such file|^norm_gap.py: error: .*missing.pt"):
        norm_gap.main([str(tmp_path / "missing.pt")])
