"""Does the world model see what the pedal does? Real against imagined returns with the pedal held.

    python benchmarks/pedal_response.py runs/<run>/checkpoints/latest.pt                  # tracks 10200..10202
    python benchmarks/pedal_response.py <checkpoint> --pedals -1 0 0.3 1 --after 0 40 --tracks 5
    python benchmarks/pedal_response.py <checkpoint> --probe-tracks 0                     # returns only

For one saved agent (a training checkpoint: it needs its reward and continue heads), on each track: the car drives
``--after`` decisions with the agent's mean action; from there, for every pedal value ``p`` of ``--pedals``, it
drives H more decisions (H: the agent's imagination horizon, or ``--horizon``) steering with the actor's mean and
the pedal held at ``p``, and the world model imagines those H decisions from the agent's state at the same point
(the actor's mean steering on the imagined states, the pedal ``p``; ``--samples`` imagined latent paths). Per start
and pedal:

* ``real``: the H-decision task return sum_{k<H} gamma^k r_{k+1} (a decision's reward sums its held env steps;
  nothing after the car is out, as calibration.horizon_task_returns counts it);
* ``imagined``: sum_k w_k r_k with the reward head's mean r_k and the weights w_k of training's discount_weights
  (gamma and the continue head), averaged over the samples.

A world model that has learned the pedal imagines braking from rest as standing still (a real return of about
-0.1 per env step) and full gas as faster than coasting. One that imagines about the same return whatever the pedal
gives the actor no gradient to use it: its pedal drifts to wherever the entropy and action terms put it, and the
car cruises. The table ends with each start's range over the pedals, imagined against real.

Where is the pedal lost? A linear probe reads the car's speed off the model's state z||h (ridge regression,
``fit_speed_probe``), fitted on ``--probe-tracks`` other races driven with the sampled policy (its noise varies the
speed; the tracks after the pedal's) and scored by its R^2 on the last third of them, which it was not fitted on.
Per start and pedal the table then also gives the car's real speed after the H decisions and the probe's reading of
the imagined state after them. With a probe that reads speed well (R^2 near 1), imagined speeds that barely move
with the pedal while the real ones do say the model's dynamics ignore the pedal; a probe that cannot read speed
says the model's state does not hold it.
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
from common import TRACKS  # noqa: E402

SCREENING = TRACKS["screening"][0]
PROBE_RIDGE = 1e-3  # the speed probe's ridge penalty per standardised feature and sample: lambda = 1e-3 N F


class CarOut(ValueError):
    """The car was out before the pedal could be held (before --after decisions)."""


@dataclasses.dataclass
class Args:
    checkpoint: tyro.conf.Positional[str]
    """a training checkpoint (latest.pt or best.pt of a single-car run)"""
    first_track: int = SCREENING
    """seed of the first track (10200..: the screening tracks)"""
    tracks: int = 3
    """number of tracks"""
    pedals: tuple[float, ...] = (-1.0, 0.0, 0.3, 1.0)
    """pedal values to hold, in [-1, 1] (u > 0 gas; u at or below the env's dead zone brakes; in between coasts)"""
    after: tuple[int, ...] = (0, 40)
    """decisions driven with the mean action before the pedal is held (0: from the race's first frame)"""
    samples: int = 16
    """imagined latent paths per start"""
    horizon: int | None = None
    """decisions the pedal is held (default: the agent's imagination horizon H)"""
    probe_tracks: int = 6
    """races (on the tracks after the pedal's) for the speed probe: fitted on the first two thirds, scored on the
    rest (0: no probe, returns only; else at least 2)"""
    json: str | None = None
    """also write every track's values to this file"""


def drive(agent, args, envs, track: int, after: int, pedal: float | None, horizon: int) -> tuple:
    """One race on `track`: `after` decisions with the mean action, then (if `pedal` is given) `horizon` decisions
    steering with the mean action and the pedal held. Returns the first frame and those of the first `after`
    decisions with their actions (as a replay stores them: the action that led to each frame, zero for the first)
    and the per-decision rewards of the held part, with whether the car went out there (they stop at that decision)
    and the car's speed at its end (the env's `speed` after the last env step driven; NaN in an env without it)."""
    import torch

    from utils.collector import preprocess_frames

    torch.manual_seed(track)  # the same latent samples, so every pedal starts from the same state and place
    envs.seed(track)
    obs, state, first = envs.reset(), None, np.ones(1, dtype=bool)
    frames, actions = [preprocess_frames(obs, args.image_size)[0]], [np.zeros(agent.action_dim, np.float32)]
    rewards, out, speed = [], False, 0.0
    for t in range(after + (0 if pedal is None else horizon)):
        action, state = agent.act(obs, state, first, "mean-action")
        first[:] = False
        if t >= after:  # the held pedal, in the action and in the agent's memory of it (its previous action)
            action = action.copy()
            action[:, 1] = pedal
            state = (state[0], state[1], torch.as_tensor(action, device=state[2].device), state[3])
        reward = 0.0
        for _ in range(args.action_repeat):
            obs, step_rewards, dones, infos = envs.step(action)
            reward += float(step_rewards[0])
            speed = float(infos[0].get("speed", np.nan))
            if dones[0]:
                break
        if t < after:
            if dones[0]:
                raise CarOut(f"track {track}: the car was out after {t + 1} decisions, before --after {after}")
            frames.append(preprocess_frames(obs, args.image_size)[0])
            actions.append(action[0].astype(np.float32))
        else:
            rewards.append(reward)
            if dones[0]:
                out = True
                break
    return np.stack(frames), np.stack(actions), np.array(rewards), out, speed


def car_speed(info: dict) -> float:
    """The car's speed in an env step's info (the env's `speed`: the norm of its hull's velocity), or a clear error."""
    if "speed" not in info:
        raise ValueError(f"the env's info has no 'speed' (keys: {sorted(info)}); the speed probe needs a car's speed")
    return float(info["speed"])


def drive_race(agent, args, envs, track: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One race on `track` with the sampled policy, until the car is out or the time limit: every frame, the action
    that led to it (zero for the first: a replay's layout) and the car's speed at each frame after the first (at the
    end of the decision that led to it)."""
    import torch

    from utils.collector import preprocess_frames

    torch.manual_seed(track)
    envs.seed(track)
    obs, state, first = envs.reset(), None, np.ones(1, dtype=bool)
    frames, actions, speeds = [preprocess_frames(obs, args.image_size)[0]], [np.zeros(agent.action_dim, np.float32)], []
    for _ in range(-(-args.max_steps // args.action_repeat)):
        action, state = agent.act(obs, state, first, "stochastic")
        first[:] = False
        for _ in range(args.action_repeat):
            obs, _, dones, infos = envs.step(action)
            if dones[0]:
                break
        if dones[0]:
            break
        frames.append(preprocess_frames(obs, args.image_size)[0])
        actions.append(action[0].astype(np.float32))
        speeds.append(car_speed(infos[0]))
    return np.stack(frames), np.stack(actions), np.array(speeds)


def posterior(agent, frames: np.ndarray, actions: np.ndarray) -> dict:
    """The world model's posterior over one race's `frames` observed with `actions` (world_model.observe from the
    learned initial state; BatchNorm with its running statistics, as when acting)."""
    import torch

    wm = agent.world_model
    agent._set_training(False)
    with torch.no_grad():
        is_first = torch.zeros(1, len(frames), dtype=torch.bool, device=agent.device)
        is_first[0, 0] = True
        embed = wm.encoder(torch.as_tensor(frames[None], device=agent.device))
        return wm.observe(embed, torch.as_tensor(actions[None], device=agent.device), is_first)


@dataclasses.dataclass
class SpeedProbe:
    """speed ~ ((x - mean) / scale) . weights + bias on the model's features x = z||h; `r2` on held-out races."""

    mean: np.ndarray
    scale: np.ndarray
    weights: np.ndarray
    bias: float
    r2: float
    samples: int

    def __call__(self, features: np.ndarray) -> np.ndarray:
        return ((features - self.mean) / self.scale) @ self.weights + self.bias


def r_squared(truth: np.ndarray, predicted: np.ndarray) -> float:
    """1 - SS_res / SS_tot: the share of the truth's variance the prediction explains (0: its mean's; < 0: worse)."""
    return float(1.0 - np.sum((truth - predicted) ** 2) / np.sum((truth - truth.mean()) ** 2))


def fit_speed_probe(features: np.ndarray, speeds: np.ndarray, held_features: np.ndarray,
                    held_speeds: np.ndarray) -> SpeedProbe:  # fmt: skip
    """Ridge regression of speed on standardised features (N, F) (lambda = PROBE_RIDGE N F, a constant feature
    left at scale 1), scored by its R^2 on held-out (features, speeds) from other races."""
    mean, scale = features.mean(0), features.std(0)
    scale = np.where(scale > 1e-6, scale, 1.0)
    x, bias = (features - mean) / scale, float(speeds.mean())
    gram = x.T @ x + PROBE_RIDGE * x.size * np.eye(x.shape[1])
    probe = SpeedProbe(mean, scale, np.linalg.solve(gram, x.T @ (speeds - bias)), bias, float("nan"), len(speeds))
    probe.r2 = r_squared(held_speeds, probe(held_features))
    return probe


def speed_probe(agent, args, envs, first_track: int, tracks: int) -> SpeedProbe:
    """The probe fitted on the races of the first two thirds of tracks first_track.. (drive_race) and scored on the
    rest; each race's features are its posterior's z||h at every frame after the first."""
    import torch

    fitted = -(-2 * tracks // 3)
    data = []
    for track in range(first_track, first_track + tracks):
        frames, actions, speeds = drive_race(agent, args, envs, track)
        torch.manual_seed(track)
        post = posterior(agent, frames, actions)
        features = torch.cat([post["z"], post["h"]], -1)[0, 1:].float().cpu().numpy()
        data.append((features, speeds))
    fit, held = ([np.concatenate(part) for part in zip(*races)] for races in (data[:fitted], data[fitted:]))
    return fit_speed_probe(*fit, *held)


def imagine(script, agent, frames: np.ndarray, actions: np.ndarray, pedal: float, horizon: int, samples: int,
            gamma: float) -> tuple[float, np.ndarray]:  # fmt: skip
    """The world model's H-decision task return from the posterior state of the last of `frames` (observed with
    `actions`), steering with the actor's mean on imagined states and the pedal held: mean over `samples` paths.
    Also returns the imagined features z||h after the H decisions, one row per path (for the speed probe)."""
    import torch

    wm, actor = agent.world_model, agent.actor
    post = posterior(agent, frames, actions)
    with torch.no_grad():
        state = tuple(s[0, -1:].repeat(samples, 1) for s in post["states"])
        h, z = post["h"][0, -1:].repeat(samples, 1), post["z"][0, -1:].repeat(samples, 1)
        rewards, continues = [], []
        for _ in range(horizon):
            action, _ = actor(torch.cat([z, h], -1))
            action = action.clone()
            action[:, 1] = pedal
            state, h, z = wm.imagine_step(state, z, action.clamp(-1.0, 1.0))
            features = torch.cat([z, h], -1)
            rewards.append(script.gaussian_params(wm.reward(features), script.HEAD_MIN_STD)[0].squeeze(-1))
            continues.append(torch.sigmoid(wm.cont(features).float().squeeze(-1)))
        weights = script.discount_weights(torch.stack(continues), gamma)
        return float((weights * torch.stack(rewards)).sum(0).mean()), features.float().cpu().numpy()


def pedal_response(path: str, first_track: int = SCREENING, tracks: int = 3, pedals=(-1.0, 0.0, 0.3, 1.0),
                   after=(0, 40), samples: int = 16, horizon: int | None = None,
                   probe_tracks: int = 0) -> list[dict]:  # fmt: skip
    """Per track, start (`after`) and pedal: the real and the imagined H-decision task return (module docstring;
    `horizon` decisions instead of the agent's H if given). With `probe_tracks` races for the speed probe, also the
    real speed after the H decisions, the probe's reading of the imagined one and the probe's held-out R^2."""
    import torch

    from utils.checkpoint import read_checkpoint
    from utils import make_vec_env

    script, checkpoint = read_checkpoint(path)
    agent = script.agent_from_checkpoint(path, 0)
    if agent.acting_only:
        raise ValueError(f"{path}: an acting-only export has no reward or continue head; give a training checkpoint")
    if any(not -1.0 <= p <= 1.0 for p in pedals):
        raise ValueError(f"--pedals must lie in [-1, 1], got {list(pedals)}")
    if any(a < 0 for a in after):
        raise ValueError(f"--after must be >= 0, got {list(after)}")
    if horizon is not None and horizon < 1:
        raise ValueError(f"--horizon must be >= 1, got {horizon}")
    if probe_tracks < 0 or probe_tracks == 1:
        raise ValueError(f"--probe-tracks must be 0 (no probe) or >= 2 (fitted and scored on other races), got "
                         f"{probe_tracks}")
    args = script.args_from_checkpoint(checkpoint, path, num_agents=1)
    horizon, gamma = horizon or args.imagination_horizon, args.gamma
    envs = make_vec_env(args.env_id, 1, None, **script.env_kwargs(args, args.dead_zone_end))
    rows = []
    try:
        probe = speed_probe(agent, args, envs, first_track + tracks, probe_tracks) if probe_tracks else None
        for track in range(first_track, first_track + tracks):
            for start in after:
                frames, actions, _, _, _ = drive(agent, args, envs, track, start, None, horizon)
                for pedal in pedals:
                    _, _, rewards, out, speed = drive(agent, args, envs, track, start, pedal, horizon)
                    real = float(np.sum(rewards * gamma ** np.arange(len(rewards))))
                    torch.manual_seed(track)
                    imagined, features = imagine(script, agent, frames, actions, pedal, horizon, samples, gamma)
                    rows.append({"track": track, "after": start, "pedal": pedal, "real": round(real, 2),
                                 "imagined": round(imagined, 2), "out": out, "decisions": len(rewards)})  # fmt: skip
                    if probe is not None:
                        read = float(probe(features).mean())
                        rows[-1].update(real_speed=round(speed, 2), imagined_speed=round(read, 2),
                                        probe_r2=round(probe.r2, 4))  # fmt: skip
    finally:
        envs.close()
    return rows


def means(rows: list[dict], keys=("real", "imagined")) -> dict[int, dict[float, tuple[float, ...]]]:
    """Per start (`after`) and pedal, the mean over the tracks of each of `keys` (default: the real and the imagined
    return)."""
    out = {}
    for start in sorted({r["after"] for r in rows}):
        out[start] = {}
        for pedal in sorted({r["pedal"] for r in rows}):
            mine = [r for r in rows if r["after"] == start and r["pedal"] == pedal]
            out[start][pedal] = tuple(float(np.mean([r[key] for r in mine])) for key in keys)
    return out


def ranges(rows: list[dict], keys=("real", "imagined")) -> dict[int, tuple[float, float]]:
    """Per start, the range over the pedals (max - min) of the mean imagined and of the mean real value of `keys`
    (real, imagined; default: the returns): (imagined range, real range)."""
    return {start: (float(np.ptp([m[1] for m in by_pedal.values()])), float(np.ptp([m[0] for m in by_pedal.values()])))
            for start, by_pedal in means(rows, keys).items()}  # fmt: skip


SPEEDS = ("real_speed", "imagined_speed")


def table(rows: list[dict], path: str) -> str:
    """Markdown: mean real and imagined return per start and pedal over the tracks (and speeds, with the probe),
    then each start's range over the pedals (max - min of the means), imagined against real."""
    probed = all(SPEEDS[0] in r for r in rows)
    lines = [f"Pedal held for H decisions, {path} ({len({r['track'] for r in rows})} tracks):", "",
             "| after | pedal | real | imagined | out |" + (" real speed | imagined speed (probe) |" if probed else ""),
             "|---|---|---|---|---|" + ("---|---|" if probed else "")]  # fmt: skip
    speeds = means(rows, SPEEDS) if probed else {}
    for start, by_pedal in means(rows).items():
        for pedal, (real, imagined) in by_pedal.items():
            out = sum(r["out"] for r in rows if r["after"] == start and r["pedal"] == pedal)
            line = f"| {start} | {pedal:+.2f} | {real:.2f} | {imagined:.2f} | {out} |"
            if probed:
                line += " {:.1f} | {:.1f} |".format(*speeds[start][pedal])
            lines.append(line)
    spans = [f"after {start}: imagined range {imagined:.2f} against real {real:.2f}"
             for start, (imagined, real) in ranges(rows).items()]  # fmt: skip
    if probed:
        spans += [f"after {start}: speed range imagined {imagined:.1f} against real {real:.1f}"
                  for start, (imagined, real) in ranges(rows, SPEEDS).items()]  # fmt: skip
        spans.append(f"speed probe: held-out R^2 {rows[0]['probe_r2']:.3f} (ridge on z||h; other races, sampled)")
    return "\n".join(lines + [""] + spans) + "\n"


def main(argv=None) -> list[dict]:
    args = tyro.cli(Args, args=argv)
    rows = pedal_response(args.checkpoint, args.first_track, args.tracks, args.pedals, args.after, args.samples,
                          args.horizon, args.probe_tracks)  # fmt: skip
    print(table(rows, args.checkpoint), end="")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return rows


if __name__ == "__main__":
    main()
