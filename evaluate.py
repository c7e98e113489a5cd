"""Evaluate a saved agent on a block of tracks, or export it acting-only (in the manner of rl-zoo's enjoy.py).

    python evaluate.py runs/<run>/checkpoints/latest.pt                          # tracks 10000..10009, both policies
    python evaluate.py pretrained/lstm_cpu.pt --first-track 10100 --tracks 20 --policies mean-action
    python evaluate.py runs/<run>/checkpoints/best.pt --export pretrained/lstm_cpu.pt   # acting-only, for git

The agent (any variant: the checkpoint names its script; agent ``--agent`` of a multi-agent checkpoint) drives alone,
with the env settings it was trained with at the end of its dead-zone schedule, one race per track. Per policy it
prints the mean over the tracks of what ``drive_races`` (utils/collector.py) reads: return, progress (fraction of
tiles), |steer| (near 1: bang-bang steering), gas, brake share, speed, laps finished within the time limit,
eliminations.
``--json`` also writes every track's values. A sampled policy's random stream starts from the first track's seed,
so the same command gives the same numbers.
"""

from __future__ import annotations

import dataclasses
import json
import os
from typing import Any, Literal, NamedTuple

import numpy as np
import tyro


@dataclasses.dataclass
class Args:
    checkpoint: tyro.conf.Positional[str]
    """a training checkpoint (latest.pt, best.pt, race.py's racer_<i>.pt) or an acting-only export"""
    first_track: int = 10_000
    """seed of the first track (10000..10009: the runs' own evaluation tracks; 10100..10119: the 8,000-update
    protocol's report; 10200..: screening; 10300..10329: the final protocol's report)"""
    tracks: int = 10
    """number of tracks, one race each"""
    policies: tuple[Literal["stochastic", "mean-action", "deterministic"], ...] = ("stochastic", "mean-action")
    """stochastic = sampled latent and action (as trained); mean-action = sampled latent, the actor's mean;
    deterministic = the posterior's mean latent and the actor's mean"""
    agent: int = 0
    """which agent of a multi-agent checkpoint"""
    json: str | None = None
    """also write every track's readings to this file"""
    export: str | None = None
    """instead of evaluating, write the agent as an acting-only export here (no critic, optimisers or replay)"""
    torch_threads: int = 0
    """torch CPU threads (0: torch's default; 1 when other runs share the cores)"""


class SingleCar(NamedTuple):
    """A saved agent set up to drive alone (single_car)."""

    script: Any  # the module of the dreamer script that wrote the checkpoint
    checkpoint: dict  # the loaded checkpoint (or export)
    args: Any  # its Args, with one car
    agent: Any  # its agent `index`
    envs: Any  # a one-car vec env with the env settings it was trained with, at the end of its dead-zone schedule


def single_car(path: str, index: int = 0) -> SingleCar:
    """Agent `index` of the checkpoint (or export) at `path`, set up to drive alone. The caller closes its env."""
    from utils import make_vec_env
    from utils.checkpoint import read_checkpoint  # one-line errors naming the file
    from utils.run import env_kwargs

    script, checkpoint = read_checkpoint(path)
    args = script.args_from_checkpoint(checkpoint, path, num_agents=1)
    agent = script.agent_from_checkpoint(path, index, checkpoint=checkpoint)
    envs = make_vec_env(args.env_id, 1, None, **env_kwargs(args, args.dead_zone_end))
    return SingleCar(script, checkpoint, args, agent, envs)


def sampled_episodes(agent, args, envs, first_track: int, tracks: int) -> list:
    """The agent's sampled policy (as it fills its replay) on tracks first_track .. first_track + tracks - 1, its
    random stream from the first track's seed: drive_races' records, one list of cars per race. Closes `envs`."""
    import torch

    from utils.collector import drive_races

    torch.manual_seed(first_track)
    records = []
    try:
        drive_races([agent], args, envs, "stochastic", range(first_track, first_track + tracks), records)
    finally:
        envs.close()
    return records


def evaluate_checkpoint(path: str, first_track: int = 10_000, tracks: int = 10, policies=("stochastic",),
                        index: int = 0) -> dict[str, dict[str, list[float]]]:  # fmt: skip
    """Per policy, every reading of `drive_races` per track: {policy: {reading: [value per track]}}. The tracks are
    first_track .. first_track + tracks - 1."""
    import torch

    from utils.collector import drive_races

    if tracks < 1 or first_track < 0:
        raise ValueError(f"--tracks must be >= 1 and --first-track >= 0 (a track's seed), got {tracks} and "
                         f"{first_track}")  # fmt: skip
    _, _, args, agent, envs = single_car(path, index)
    out, tracks_of = {}, list(range(first_track, first_track + tracks))
    try:
        for policy in policies:
            torch.manual_seed(first_track)  # a sampled policy: the same command gives the same numbers
            readings = drive_races([agent], args, envs, policy, tracks_of)
            out[policy] = {key: [float(v) for v in value[:, 0]] for key, value in readings.items()}
    finally:
        envs.close()
    return out


def track_means(per_track: dict[str, list[float]]) -> dict[str, float]:
    """The mean over the tracks of each reading of one policy (evaluate_checkpoint's answer for that policy)."""
    return {key: float(np.mean(values)) for key, values in per_track.items()}


def table(results: dict[str, dict[str, list[float]]]) -> str:
    """Markdown: one row per policy, the mean over tracks of every reading."""
    keys = list(next(iter(results.values())))
    lines = ["| policy | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    for policy, readings in results.items():
        means = track_means(readings)
        lines.append(f"| {policy} | " + " | ".join(f"{means[k]:.2f}" for k in keys) + " |")
    return "\n".join(lines)


def main(args: Args) -> None:
    from utils.checkpoint import read_checkpoint
    from utils.checkpoint import export_policy

    if args.torch_threads < 0:
        raise ValueError(f"--torch-threads must be >= 0 (0: torch's default), got {args.torch_threads}")
    if args.torch_threads > 0:
        import torch

        torch.set_num_threads(args.torch_threads)
    if args.export:
        script, _ = read_checkpoint(args.checkpoint)
        size = export_policy(script, args.checkpoint, args.export, args.agent)
        print(f"wrote {args.export} ({size / 1e6:.1f} MB)")
        return
    results = evaluate_checkpoint(args.checkpoint, args.first_track, args.tracks, args.policies, args.agent)
    last = args.first_track + args.tracks - 1
    print(f"{args.checkpoint}, agent {args.agent}, tracks {args.first_track}..{last} (means over tracks):")
    print(table(results))
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump({"checkpoint": args.checkpoint, "tracks": [args.first_track, args.tracks], **results}, f,
                      indent=1)  # fmt: skip


def cli(argv: list[str] | None = None) -> None:
    """The command line: a bad file or value ends with one line naming it, no traceback."""
    from utils.checkpoint import CheckpointError
    from utils.run import tyro_cli

    args = tyro_cli(Args, argv, __doc__)
    try:
        main(args)
    except (CheckpointError, ValueError) as e:
        raise SystemExit(f"evaluate.py: error: {' '.join(str(e).split())}") from None


if __name__ == "__main__":
    cli()
