"""Does the agent act on the states it learned from? The world model's train/act gap of its normalisation.

    python benchmarks/norm_gap.py pretrained/lstm_cpu.pt                  # screening tracks 10200..10203
    python benchmarks/norm_gap.py runs/<run>/checkpoints/latest.pt --tracks 8 --json gap.json

With ``--norm batch`` the world model holds BatchNorm in the encoder's convolutions and, inside the recurrence, in
the recurrent input and the posterior's MLP. An update observes B replayed sequences of L decisions, the encoder
over all B * L frames at once and the recurrence one step at a time, so at every step each BatchNorm in it
normalises over the B rows of that step (train mode); acting, and the imagined dynamics, use the running
statistics instead (eval mode). This measures how far apart the two make the model's states on the agent's own
driving. The saved agent (a training checkpoint or its acting-only export) drives its sampled policy, as trained,
on ``--tracks`` tracks; the races are cut into windows of L decisions (the agent's --seq-len) from each race's
start, shuffled (seeded by the first track) so that a batch mixes races as a replay sample does (replay draws its
B sequences at random offsets, which may cross races), and taken B at a time (its --batch-size). Each batch is
observed from the learned initial state with the posterior means (no sampling, so that the normalisation is the
only difference), each pass from the agent's own running statistics (put back after every train-mode pass):

* ``eval``: every BatchNorm with its running statistics, as the agent acts;
* ``train``: every BatchNorm with the batch's statistics, as ``world_model_loss`` observes a batch;
* ``recurrence``: the same but the encoder with its running statistics: the part of the gap that comes from
  inside the recurrence, the part ``--norm mixed`` (LayerNorm in every MLP and the recurrent input, BatchNorm only
  in the convolutions) and ``--norm layer`` remove.

Readings, means over every window (L decisions each), train against eval: ``h_gap``, ||h_train - h_eval|| /
||h_eval|| per step (``h_gap_recurrence``: the same for the recurrence pass); ``z_gap``, |mean_train - mean_eval|
of the posterior in units of the eval posterior's sigma; ``steer_gap`` and ``pedal_gap``, |a_train - a_eval| of
the actor's mean action (its running statistics on both) against ``steer`` and ``pedal``, its mean |a| on the
eval states.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys

import numpy as np
import tyro

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from common import TRACKS, set_torch_threads, track_block  # noqa: E402

READINGS = ("h_gap", "h_gap_recurrence", "z_gap", "steer_gap", "pedal_gap", "steer", "pedal")


@dataclasses.dataclass
class Args:
    checkpoint: tyro.conf.Positional[str]
    """a saved agent: a training checkpoint or an acting-only export (pretrained/<variant>_cpu.pt)"""
    first_track: int = TRACKS["screening"][0]
    """seed of the first track (10200..: the screening tracks)"""
    tracks: int = 4
    """number of tracks driven (enough for at least one batch of B windows of L decisions)"""
    json: str | None = None
    """also write the readings to this file"""
    torch_threads: int = 0
    """torch CPU threads (0: torch's default; 1 when other runs share the cores)"""


def windows(episodes: list[tuple[np.ndarray, np.ndarray]], length: int, batch: int,
            rng: np.random.Generator | None = None) -> list[tuple[np.ndarray, ...]]:  # fmt: skip
    """Batches of `batch` windows of `length` consecutive decisions (frames, the actions that led to them, is_first:
    True at an episode's first frame), cut from each episode from its start (a shorter rest is dropped); the windows
    in the order `rng` permutes them (none: as cut), and a last batch short of `batch` dropped. ValueError when not
    one batch."""
    cut = []
    for frames, actions in episodes:
        for start in range(0, len(frames) - length + 1, length):
            first = np.zeros(length, dtype=bool)
            first[0] = start == 0
            cut.append((frames[start:start + length], actions[start:start + length], first))
    if len(cut) < batch:
        raise ValueError(f"the races gave {len(cut)} windows of {length} decisions, fewer than one batch of "
                         f"{batch}: drive more --tracks")  # fmt: skip
    order = rng.permutation(len(cut)) if rng is not None else np.arange(len(cut))
    cut = [cut[i] for i in order]
    return [tuple(np.stack(parts) for parts in zip(*cut[i:i + batch])) for i in range(0, len(cut) // batch * batch,
                                                                                        batch)]  # fmt: skip


def observe_modes(agent, frames: np.ndarray, actions: np.ndarray, is_first: np.ndarray) -> dict[str, dict]:
    """The world model's posterior (means, not samples) over one batch: ``eval``, with the running statistics, as
    the agent acts; ``train``, every BatchNorm with the batch's statistics, as an update observes the batch;
    ``recurrence``, the same with the encoder's running statistics (the batch's only inside the recurrence: what
    ``--norm mixed`` replaces). The running statistics are put back after each train-mode pass, so each pass starts
    from the agent's own, and the agent's modes are as before afterwards."""
    import torch

    wm, device = agent.world_model, agent.device
    modes = [(module, module.training) for part in (wm, agent.actor, agent.critic) for module in part.modules()]
    saved = [b.detach().clone() for b in wm.buffers()]
    frames, actions, is_first = (torch.as_tensor(x, device=device) for x in (frames, actions, is_first))
    out = {}
    try:
        with torch.no_grad():
            for name in ("eval", "train", "recurrence"):
                wm.train(name != "eval")
                wm.encoder.train(name == "train")
                out[name] = wm.observe(wm.encoder(frames), actions, is_first, sample=False)
                for buffer, value in zip(wm.buffers(), saved):
                    buffer.copy_(value)
    finally:
        with torch.no_grad():
            for buffer, value in zip(wm.buffers(), saved):
                buffer.copy_(value)
        for module, training in modes:
            module.training = training
    return out


def gaps(agent, train: dict, evaluated: dict) -> dict[str, np.ndarray]:
    """Per window, each reading of READINGS averaged over its steps (the actor in eval mode on both states)."""
    import torch

    h_gap = (train["h"] - evaluated["h"]).norm(dim=-1) / evaluated["h"].norm(dim=-1).clamp_min(1e-8)
    z_gap = ((train["post_mean"] - evaluated["post_mean"]).abs() / evaluated["post_std"]).mean(-1)
    was_training = agent.actor.training
    agent.actor.eval()
    with torch.no_grad():
        mean_train, _ = agent.actor(torch.cat([train["z"], train["h"]], -1))
        mean_eval, _ = agent.actor(torch.cat([evaluated["z"], evaluated["h"]], -1))
    agent.actor.train(was_training)
    action_gap, action = (mean_train - mean_eval).abs(), mean_eval.abs()
    readings = {"h_gap": h_gap, "z_gap": z_gap, "steer_gap": action_gap[..., 0], "pedal_gap": action_gap[..., 1],
                "steer": action[..., 0], "pedal": action[..., 1]}  # fmt: skip
    return {key: value.mean(-1).float().cpu().numpy() for key, value in readings.items()}


def norm_gap(path: str, first_track: int = TRACKS["screening"][0], tracks: int = 4) -> dict:
    """The readings of the agent saved at `path` (module docstring), with the settings they were read under."""
    import evaluate  # (the repository's evaluate.py)

    script, _, args, agent, envs = evaluate.single_car(path)
    records = evaluate.sampled_episodes(agent, args, envs, first_track, tracks)
    episodes = [cars[0].arrays()[:2] for cars in records]
    per_window = {key: [] for key in READINGS}
    for batch in windows(episodes, args.seq_len, args.batch_size, np.random.default_rng(first_track)):
        passes = observe_modes(agent, *batch)
        for key, values in gaps(agent, passes["train"], passes["eval"]).items():
            per_window[key].append(values)
        per_window["h_gap_recurrence"].append(gaps(agent, passes["recurrence"], passes["eval"])["h_gap"])
    means = {key: round(float(np.mean(np.concatenate(v))), 4) for key, v in per_window.items()}
    return {"checkpoint": path, "variant": script.VARIANT, "norm": args.norm, "batch_size": args.batch_size,
            "seq_len": args.seq_len, "tracks": track_block(first_track, tracks),
            "windows": len(np.concatenate(per_window["h_gap"])), **means}  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    from utils.run import tyro_cli

    args = tyro_cli(Args, argv, __doc__)
    try:
        if args.tracks < 1:
            raise ValueError(f"--tracks must be >= 1, got {args.tracks}")
        set_torch_threads(args.torch_threads)
        row = norm_gap(args.checkpoint, args.first_track, args.tracks)
    except ValueError as e:  # (utils.checkpoint.CheckpointError is a ValueError)
        raise SystemExit(f"norm_gap.py: error: {' '.join(str(e).split())}") from None
    print(json.dumps(row, indent=1))
    if args.json:
        import common

        common.write_json(args.json, row)
    return row


if __name__ == "__main__":
    main()
