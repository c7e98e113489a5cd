"""Does the world model see what the pedal does? Real against imagined returns and speeds with the pedal held.

    python benchmarks/pedal_response.py runs/<run>/checkpoints/latest.pt      # tracks 10200..10202, probe 10203..10208
    python benchmarks/pedal_response.py <checkpoint> --pedals -1 0 0.3 1 --after 0 40 --tracks 5
    python benchmarks/pedal_response.py <checkpoint> --probe-tracks 0         # the returns only

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
car cruises. The table gives each start's range over the pedals, imagined against real.

Where is the pedal lost? A linear probe reads the car's speed off the model's state (``fit_speed_probe``: ridge
regression, its penalty chosen by leave-one-race-out error), fitted on the first two thirds of ``--probe-tracks``
races and scored on the rest (the tracks after the pedal's). Those races drive as the pedal's do, the actor's mean
steering with a held pedal, but the pedal is drawn afresh (uniform in [-1, 1]) for every stretch of 8..48
decisions, so that speed varies apart from the time since the start (a policy that drives alike in every race has
a speed that the clock alone predicts). The table gives R^2 and RMSE of the probes on z||h, on h alone (what the
dynamics carry forward) and on z alone, beside that clock's (speed as a cubic in the decision index). Per start
and pedal, with the car still in after the H decisions, it then gives the real speed there, the probe's reading of
the posterior of that real drive (the same instrument as the imagined side; a ridge probe shrinks some directions
more than others, so the two sides agree only as far as their states differ alike) and its reading of the imagined
state after the H decisions; and the probe's reading of the posterior where the pedal is first held, against the
real speed there. The probe is fitted on posterior states and read on imagined (prior) ones as well. For the LSTM,
h is the cell's output; its cell state c is carried forward too and is not probed.
"""

from __future__ import annotations

import dataclasses
import os
import sys

import numpy as np
import tyro

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from calibration import posterior  # noqa: E402  (one race through the world model)
from common import TRACKS, set_torch_threads, write_json  # noqa: E402

SCREENING = TRACKS["screening"][0]
PROBE_RIDGES = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0)  # the probe's ridge penalty per sample (lambda / N)
PROBE_TIME_DEGREE = 3  # the time baseline: speed as a polynomial of this degree in the decision index
PROBE_STRETCH = (8, 48)  # a probe race holds each random pedal for this many decisions (uniform, both included)


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
    """races (on the tracks after the pedal's, random pedals held) for the speed probe: fitted on the first 2n // 3,
    scored on the rest (0: no probe, the returns only; else at least 3)"""
    json: str | None = None
    """also write every track's values to this file"""
    torch_threads: int = 0
    """torch CPU threads (0: torch's default; 1 when other runs share the cores)"""


def hold_pedal(action: np.ndarray, state: tuple, pedal: float) -> tuple[np.ndarray, tuple]:
    """The agent's action with its pedal replaced by `pedal`, and its acting state (Agent.act's cell, z, previous
    action) remembering that action as its previous one, as the world model must see what was driven."""
    import torch

    action = action.copy()
    action[:, 1] = pedal
    cell, z, previous = state
    return action, (cell, z, torch.as_tensor(action, device=previous.device))


def drive(agent, args, envs, track: int, after: int, pedal: float | None, horizon: int) -> tuple:
    """One race on `track`: `after` decisions with the mean action, then (if `pedal` is given) `horizon` decisions
    steering with the mean action and the pedal held. Returns the first frame and those of every decision after
    which the car was still in, with their actions (as a replay stores them: the action that led to each frame,
    zero for the first), the per-decision rewards of the held part, whether the car went out there (they stop at
    that decision) and the car's speed at the end (the env's `speed` after the last env step driven; NaN in an env
    without it)."""
    import torch

    from utils.collector import preprocess_frames

    torch.manual_seed(track)  # the same latent samples, so every pedal starts from the same state and place
    envs.seed(track)
    obs, state, first = envs.reset(), None, np.ones(1, dtype=bool)
    frames, actions = [preprocess_frames(obs, args.image_size)[0]], [np.zeros(agent.action_dim, np.float32)]
    rewards, out, speed = [], False, float(envs.reset_infos[0].get("speed", np.nan))
    for t in range(after + (0 if pedal is None else horizon)):
        action, state = agent.act(obs, state, first, "mean-action")
        first[:] = False
        if t >= after:
            action, state = hold_pedal(action, state, pedal)
        reward = 0.0
        for _ in range(args.action_repeat):
            obs, step_rewards, dones, infos = envs.step(action)
            reward += float(step_rewards[0])
            speed = float(infos[0].get("speed", np.nan))
            if dones[0]:
                break
        if t < after and dones[0]:
            raise CarOut(f"track {track}: the car was out after {t + 1} decisions, before --after {after}")
        if t >= after:
            rewards.append(reward)
        if dones[0]:  # (the env has reset: obs is the next race's)
            out = True
            break
        frames.append(preprocess_frames(obs, args.image_size)[0])
        actions.append(action[0].astype(np.float32))
    return np.stack(frames), np.stack(actions), np.array(rewards), out, speed


def car_speed(info: dict) -> float:
    """The car's speed in an env step's info (the env's `speed`: the norm of its hull's velocity), or a clear error."""
    if "speed" not in info:
        raise ValueError(f"the env's info has no 'speed' (keys: {sorted(info)}); the speed probe needs a car's speed")
    return float(info["speed"])


def drive_race(agent, args, envs, track: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One race on `track` for the speed probe, until the car is out or the time limit: the actor's mean steering
    and a pedal drawn uniformly from [-1, 1] for each stretch of PROBE_STRETCH decisions (numpy seeded by the track),
    held in the action and in the agent's memory as `drive` holds it. Returns every frame, the action that led to it
    (zero for the first: a replay's layout) and the car's speed at each (the env's `speed`: in the reset's info at
    the first frame, where every car stands; then at the end of the decision that led to the frame)."""
    import torch

    from utils.collector import preprocess_frames

    torch.manual_seed(track)
    envs.seed(track)
    rng = np.random.default_rng(track)
    obs, state, first = envs.reset(), None, np.ones(1, dtype=bool)
    frames, actions = [preprocess_frames(obs, args.image_size)[0]], [np.zeros(agent.action_dim, np.float32)]
    speeds = [car_speed(envs.reset_infos[0])]
    pedal, left = 0.0, 0
    for _ in range(-(-args.max_steps // args.action_repeat)):
        if left == 0:
            pedal, left = float(rng.uniform(-1.0, 1.0)), int(rng.integers(PROBE_STRETCH[0], PROBE_STRETCH[1] + 1))
        left -= 1
        action, state = agent.act(obs, state, first, "mean-action")
        first[:] = False
        action, state = hold_pedal(action, state, pedal)
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


def posterior_features(agent, frames: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """z||h of the posterior at every frame, float64 on the CPU: what the speed probe reads."""
    import torch

    post = posterior(agent, frames, actions)
    return torch.cat([post["z"], post["h"]], -1)[0].double().cpu().numpy()


@dataclasses.dataclass
class SpeedProbe:
    """speed ~ ((x - mean) / scale) . weights + bias on features x; scored on held-out races: `r2`, `rmse`."""

    mean: np.ndarray
    scale: np.ndarray
    weights: np.ndarray
    bias: float
    ridge: float
    r2: float = float("nan")
    rmse: float = float("nan")

    def __call__(self, features: np.ndarray) -> np.ndarray:
        return ((np.asarray(features, np.float64) - self.mean) / self.scale) @ self.weights + self.bias


def r_squared(truth: np.ndarray, predicted: np.ndarray) -> float:
    """1 - SS_res / SS_tot: the share of the truth's variance the prediction explains (0: its mean's; < 0: worse)."""
    return float(1.0 - np.sum((truth - predicted) ** 2) / np.sum((truth - truth.mean()) ** 2))


def ridge(features: np.ndarray, speeds: np.ndarray, penalty: float) -> SpeedProbe:
    """Ridge regression of speeds on standardised features with lambda = penalty * N, the intercept (the mean speed)
    unpenalised; float64. A feature's scale is floored at 1e-3 of the median of the scales that are not 0 (at 1 if
    all are 0), so that a unit almost constant in the fitted races cannot turn a small change elsewhere into a huge
    reading."""
    x, y = np.asarray(features, np.float64), np.asarray(speeds, np.float64)
    mean, scale = x.mean(0), x.std(0)
    moving = scale[scale > 0]
    scale = np.maximum(scale, 1e-3 * np.median(moving) if len(moving) else 1.0)
    x, bias = (x - mean) / scale, float(y.mean())
    weights = np.linalg.solve(x.T @ x + penalty * len(x) * np.eye(x.shape[1]), x.T @ (y - bias))
    return SpeedProbe(mean, scale, weights, bias, penalty)


def fit_speed_probe(fitted: list[tuple], held: list[tuple], ridges=PROBE_RIDGES) -> SpeedProbe:
    """The probe of speed on features from the `fitted` races [(features (n, F), speeds (n,)), ...] (at least 2):
    its penalty the one of `ridges` with the least leave-one-race-out squared error, then fitted on them all, and
    scored by R^2 and RMSE on the `held` races."""
    if len(fitted) < 2 or not held:
        raise ValueError(f"the probe needs at least 2 races to fit and 1 to score, got {len(fitted)} and {len(held)}")

    def error(penalty: float) -> float:
        errors = []
        for k, (features, speeds) in enumerate(fitted):
            rest = [race for j, race in enumerate(fitted) if j != k]
            probe = ridge(np.concatenate([f for f, _ in rest]), np.concatenate([s for _, s in rest]), penalty)
            errors.append((probe(features) - speeds) ** 2)
        return float(np.mean(np.concatenate(errors)))

    penalty = min(ridges, key=error)
    probe = ridge(np.concatenate([f for f, _ in fitted]), np.concatenate([s for _, s in fitted]), penalty)
    features, speeds = np.concatenate([f for f, _ in held]), np.concatenate([s for _, s in held])
    read = probe(features)
    probe.r2, probe.rmse = r_squared(speeds, read), float(np.sqrt(np.mean((read - speeds) ** 2)))
    return probe


def time_baseline_r2(fitted: list[np.ndarray], held: list[np.ndarray], degree: int = PROBE_TIME_DEGREE) -> float:
    """R^2 on the `held` races' speeds (one per frame: 0, 1, ... decisions in) of a polynomial in the decision index
    fitted on the `fitted` races' speeds: how much of speed the time alone predicts (NaN with too few frames)."""

    def clock(races: list[np.ndarray]) -> np.ndarray:
        return np.concatenate([np.arange(len(speeds)) / 100.0 for speeds in races])

    if sum(len(speeds) for speeds in fitted) <= degree or sum(len(speeds) for speeds in held) < 2:
        return float("nan")
    coefficients = np.polyfit(clock(fitted), np.concatenate(fitted), degree)
    return r_squared(np.concatenate(held), np.polyval(coefficients, clock(held)))


PROBE_PARTS = ("zh", "h", "z")  # the probe's features: z||h, h alone, z alone


def speed_probe(agent, args, envs, first_track: int, tracks: int) -> tuple[SpeedProbe, dict[str, float]]:
    """The probe of speed on z||h, fitted on the races (drive_race) of the first 2 * tracks // 3 of tracks
    first_track.. and scored on the rest; each race's features are its posterior's z||h at every frame. Returns it
    with its summary: R^2 of the probes on z||h, h and z, the time baseline's, the z||h probe's
    RMSE, its ridge penalty and the numbers of fitted and held-out frames."""
    import torch

    races = []
    for track in range(first_track, first_track + tracks):
        frames, actions, speeds = drive_race(agent, args, envs, track)
        torch.manual_seed(track)
        races.append((posterior_features(agent, frames, actions), speeds))
    cut, latent = 2 * tracks // 3, args.latent_size
    columns = {"zh": slice(None), "h": slice(latent, None), "z": slice(0, latent)}
    probes = {part: fit_speed_probe([(f[:, c], s) for f, s in races[:cut]], [(f[:, c], s) for f, s in races[cut:]])
              for part, c in columns.items()}  # fmt: skip
    summary = {f"probe_r2_{part}": round(probes[part].r2, 4) for part in PROBE_PARTS}
    summary["probe_r2_time"] = round(time_baseline_r2([s for _, s in races[:cut]], [s for _, s in races[cut:]]), 4)
    summary.update(probe_rmse=round(probes["zh"].rmse, 2), probe_ridge=probes["zh"].ridge,
                   probe_fitted=sum(len(s) for _, s in races[:cut]), probe_held=sum(len(s) for _, s in races[cut:]))
    return probes["zh"], summary


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
            rewards.append(wm.reward.dist(features).mean)
            continues.append(torch.sigmoid(wm.cont(features).float().squeeze(-1)))
        weights = script.discount_weights(torch.stack(continues), gamma)
        return float((weights * torch.stack(rewards)).sum(0).mean()), features.double().cpu().numpy()


def pedal_response(path: str, first_track: int = SCREENING, tracks: int = 3, pedals=(-1.0, 0.0, 0.3, 1.0),
                   after=(0, 40), samples: int = 16, horizon: int | None = None,
                   probe_tracks: int = 0) -> list[dict]:  # fmt: skip
    """Per track, start (`after`) and pedal: the real and the imagined H-decision task return (module docstring;
    `horizon` decisions instead of the agent's H if given). With `probe_tracks` (>= 3) races for the speed probe,
    also (SPEEDS) the real speed where the pedal is first held and the probe's reading of the posterior there, and,
    if the car is still in after the H decisions (else None), the real speed then, the probe's reading of the real
    drive's posterior then and of the imagined state after the H decisions (mean over the samples); every row also
    carries the probe's summary (speed_probe)."""
    import torch

    import evaluate  # (the repository's evaluate.py)

    if any(not -1.0 <= p <= 1.0 for p in pedals):
        raise ValueError(f"--pedals must lie in [-1, 1], got {list(pedals)}")
    if any(a < 0 for a in after):
        raise ValueError(f"--after must be >= 0, got {list(after)}")
    if horizon is not None and horizon < 1:
        raise ValueError(f"--horizon must be >= 1, got {horizon}")
    if probe_tracks < 0 or probe_tracks in (1, 2):
        raise ValueError(f"--probe-tracks must be 0 (no probe) or >= 3 (2 races to fit, 1 to score), got "
                         f"{probe_tracks}")
    script, _, args, agent, envs = evaluate.single_car(path)
    if agent.acting_only:
        envs.close()
        raise ValueError(f"{path}: an acting-only export has no reward or continue head; give a training checkpoint")
    horizon, gamma = horizon or args.imagination_horizon, args.gamma
    rows = []
    try:
        probe, summary = (None, {})
        if probe_tracks:
            probe, summary = speed_probe(agent, args, envs, first_track + tracks, probe_tracks)
        for track in range(first_track, first_track + tracks):
            for start in after:
                frames, actions, _, _, start_speed = drive(agent, args, envs, track, start, None, horizon)
                if probe is not None:  # (a posterior draws on torch's generator: every drive and imagine seeds it)
                    torch.manual_seed(track)
                    start_read = float(probe(posterior_features(agent, frames, actions)[-1]))
                for pedal in pedals:
                    held_frames, held_actions, rewards, out, speed = drive(agent, args, envs, track, start, pedal,
                                                                           horizon)  # fmt: skip
                    real = float(np.sum(rewards * gamma ** np.arange(len(rewards))))
                    torch.manual_seed(track)
                    imagined, features = imagine(script, agent, frames, actions, pedal, horizon, samples, gamma)
                    rows.append({"track": track, "after": start, "pedal": pedal, "real": round(real, 2),
                                 "imagined": round(imagined, 2), "out": out, "decisions": len(rewards)})  # fmt: skip
                    if probe is None:
                        continue
                    end = {"real_speed": None, "real_speed_probed": None, "imagined_speed": None}
                    if not out:
                        torch.manual_seed(track)
                        real_read = float(probe(posterior_features(agent, held_frames, held_actions)[-1]))
                        end = {"real_speed": round(speed, 2), "real_speed_probed": round(real_read, 2),
                               "imagined_speed": round(float(probe(features).mean()), 2)}  # fmt: skip
                    rows[-1].update(start_speed=round(start_speed, 2), start_speed_probed=round(start_read, 2), **end,
                                    **summary)  # fmt: skip
    finally:
        envs.close()
    return rows


def means(rows: list[dict], keys=("real", "imagined")) -> dict[int, dict[float, tuple[float, ...]]]:
    """Per start (`after`) and pedal, the mean over the tracks of each of `keys` (default: the real and the imagined
    return), leaving out None (a speed after the car went out); NaN where every track's is None."""
    out = {}
    for start in sorted({r["after"] for r in rows}):
        out[start] = {}
        for pedal in sorted({r["pedal"] for r in rows}):
            mine = [r for r in rows if r["after"] == start and r["pedal"] == pedal]
            values = [[r[key] for r in mine if r[key] is not None] for key in keys]
            out[start][pedal] = tuple(float(np.mean(v)) if v else float("nan") for v in values)
    return out


def ranges(rows: list[dict]) -> dict[int, tuple[float, float]]:
    """Per start, the range over the pedals (max - min) of the mean imagined and of the mean real return."""
    return {start: (float(np.ptp([m[1] for m in by_pedal.values()])), float(np.ptp([m[0] for m in by_pedal.values()])))
            for start, by_pedal in means(rows).items()}  # fmt: skip


def speed_ranges(rows: list[dict]) -> dict[int, dict[str, float]]:
    """Per start, the range over the pedals of the mean speeds after the H decisions: real (the env's), read by the
    probe on the real drive's posterior, and on the imagined states; over the pedals after which a car was still
    in on some track (NaN with fewer than two such pedals), with their count under "pedals". Each pedal's mean is
    over its own tracks with a car still in, so with cars out a range can compare different tracks."""
    keys = ("real_speed", "real_speed_probed", "imagined_speed")
    out = {}
    for start, by_pedal in means(rows, keys).items():
        kept = [values for values in by_pedal.values() if not np.isnan(values[0])]
        spans = [float(np.ptp(column)) if len(kept) > 1 else float("nan") for column in zip(*kept)] or [np.nan] * 3
        out[start] = {**dict(zip(keys, spans)), "pedals": len(kept)}
    return out


SPEEDS = ("start_speed", "start_speed_probed", "real_speed", "real_speed_probed", "imagined_speed")


def table(rows: list[dict], path: str) -> str:
    """Markdown: mean real and imagined return per start and pedal over the tracks (with the probe: the speeds
    after the H decisions, over the tracks where the car was still in), then each start's range over the pedals
    (max - min of the means), imagined against real, and the probe's check at the start and its summary."""
    probed = bool(rows) and all(SPEEDS[0] in r for r in rows)
    speed_columns = (" real speed | probed | imagined (probe) |", "---|---|---|") if probed else ("", "")
    lines = [f"Pedal held for H decisions, {path} ({len({r['track'] for r in rows})} tracks):", "",
             "| after | pedal | real | imagined | out |" + speed_columns[0], "|---|---|---|---|---|" + speed_columns[1]]
    speeds = means(rows, SPEEDS) if probed else {}
    for start, by_pedal in means(rows).items():
        for pedal, (real, imagined) in by_pedal.items():
            out = sum(r["out"] for r in rows if r["after"] == start and r["pedal"] == pedal)
            line = f"| {start} | {pedal:+.2f} | {real:.2f} | {imagined:.2f} | {out} |"
            if probed:
                line += " {:.1f} | {:.1f} | {:.1f} |".format(*speeds[start][pedal][2:])
            lines.append(line)
    spans = [f"after {start}: imagined range {imagined:.2f} against real {real:.2f}"
             for start, (imagined, real) in ranges(rows).items()]  # fmt: skip
    if probed:
        for start, span in speed_ranges(rows).items():
            spans.append(f"after {start}: speed range over the {span['pedals']} pedals with a car still in, imagined "
                         f"{span['imagined_speed']:.1f} against real {span['real_speed_probed']:.1f} (both read by the "
                         f"probe; the env's: {span['real_speed']:.1f})")
        for start, by_pedal in speeds.items():
            real, read = next(iter(by_pedal.values()))[:2]
            spans.append(f"after {start}: speed where the pedal is first held {real:.1f}, the probe reads {read:.1f}")
        r = rows[0]
        edge = " at the grid's edge" if r["probe_ridge"] in (PROBE_RIDGES[0], PROBE_RIDGES[-1]) else ""
        spans.append(f"speed probe (ridge {r['probe_ridge']:g} per sample{edge}; fitted on {r['probe_fitted']} frames, "
                     f"scored on {r['probe_held']} frames): held-out R^2 z||h {r['probe_r2_zh']:.3f}, "
                     f"h {r['probe_r2_h']:.3f}, z {r['probe_r2_z']:.3f}; time alone {r['probe_r2_time']:.3f}; "
                     f"RMSE {r['probe_rmse']:.1f}")
    return "\n".join(lines + [""] + spans) + "\n"


def main(argv=None) -> list[dict]:
    """The command line. A bad file or value ends with one line naming it, no traceback; so does a car out before
    --after on some track (an early policy often is: --after 0 starts at the grid)."""
    from utils.run import tyro_cli

    args = tyro_cli(Args, argv)
    try:
        set_torch_threads(args.torch_threads)
        rows = pedal_response(args.checkpoint, args.first_track, args.tracks, args.pedals, args.after, args.samples,
                              args.horizon, args.probe_tracks)  # fmt: skip
    except CarOut as e:
        raise SystemExit(f"pedal_response.py: error: {e} (a smaller --after, e.g. 0, starts before it)") from None
    except ValueError as e:  # (a CheckpointError too)
        raise SystemExit(f"pedal_response.py: error: {' '.join(str(e).split())}") from None
    print(table(rows, args.checkpoint), end="")
    if args.json:
        write_json(args.json, rows)
    return rows


if __name__ == "__main__":
    main()
