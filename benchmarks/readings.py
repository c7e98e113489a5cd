"""What a screened or final policy does and why: the readings of ``benchmarks/sweep.py --report`` and of the final
protocol's runs (``final_protocol.protocol_readings``, ``learning.py --protocol-row``).

For one saved single-car agent, on a block of tracks (a sweep's: the screening tracks 10200..10219 by default; the
final protocol's: its report tracks 10300..10329):

* driving, for each policy (sampled as trained, and the mean action): return, progress, |steer| (near 1: bang-bang),
  gas (mean of max(action[1], 0)), brake share (decisions at or below the dead zone's edge: brake commands, which
  brake above speed 50), speed (at the end of each decision), the share of laps finished within the time limit and
  of races ended by an elimination (``drive_races``, utils/collector.py);
* the model on those real episodes (sampled policy; ``calibration.calibrate_checkpoint``): the imagined H-step task
  return against the real one from the same states, and on the frames where a car was eliminated the reward head's
  mean (the real reward there is about -100: the penalty plus that decision's other terms) and the continue head's
  probability (the real value there is 0);
* the model's view of the pedal (``pedal_response.py``): after 40 decisions of the mean action on the block's first
  3 tracks, the pedal held at -1, 0, 0.3 and 1 for H decisions; the range over the pedals of the mean imagined
  return and of the mean real one (a model that sees the pedal imagines a range near the real one);
* training, as logged over the run's last ``SCREEN_WINDOW`` updates: the actor's sigma, the entropy
  (-log pi), the entropy weight alpha (--entropy-target) and the imagined lambda-return; and the run's CPU-hours.
"""

from __future__ import annotations

import glob
import os

import numpy as np
from calibration import calibrate_checkpoint
from common import checkpoint_updates
from runs import progress_rows
from utils.collector import READINGS

POLICIES = ("stochastic", "mean-action")
DRIVING = READINGS  # what the collector reads of each car's race (utils/collector.py), over the tracks
TRAINING = {  # column: the progress.csv tag averaged over the last SCREEN_WINDOW updates
    "actor_sigma": "car_0/losses/actor_std", "entropy": "car_0/losses/entropy", "alpha": "car_0/losses/alpha",
    "imagined_return": "car_0/losses/imagined_return",
}  # fmt: skip
MODEL = ("imagined_task_return", "real_task_return", "eliminations", "terminal_reward_predicted", "terminal_continue")
PEDAL = ("pedal_range_imagined", "pedal_range_real")
SCREEN_WINDOW = 500  # the TRAINING readings: means over the updates (u - SCREEN_WINDOW, u]
PEDAL_AFTER, PEDAL_TRACKS = 40, 3  # pedal_response.py's start (decisions) and tracks (the block's first)
COLUMNS = ("tag", "variant", "seed", "updates", "policy", *DRIVING, *TRAINING, *MODEL, *PEDAL, "cpu_hours",
           "checkpoint")  # fmt: skip


def checkpoint_at(run_dir: str, updates: int) -> str:
    """The policy `run_dir` kept at exactly `updates` updates: its latest.pt or one of its eval_<race>.pt."""
    from utils.checkpoint import read_checkpoint

    paths = [os.path.join(run_dir, "checkpoints", "latest.pt")]
    paths += sorted(glob.glob(os.path.join(run_dir, "checkpoints", "eval_*.pt")), reverse=True)
    kept = []
    for path in paths:
        if not os.path.exists(path):
            continue
        done = checkpoint_updates(read_checkpoint(path)[1])
        if done == updates:
            return path
        kept.append(done)
    kept = sorted(set(kept))
    hint = (
        f"it passed {updates} without keeping a policy there: screen at one of the counts it kept"
        if kept and kept[-1] > updates
        else "resume it with --updates to reach them"
    )
    raise ValueError(
        f"{run_dir} kept no policy at {updates} updates (it kept: {', '.join(map(str, kept)) or 'none'}); {hint}"
    )


def driving(path: str, first_track: int, tracks: int, driven: dict | None = None) -> dict[str, dict[str, float]]:
    """Per policy, the mean of every DRIVING reading over the tracks: of evaluate.py's evaluate_checkpoint, or of
    `driven`, its answer for this policy and these tracks when it is already in hand."""
    import evaluate  # (the repository's evaluate.py: loaded when a policy is driven or averaged)

    if driven is None:
        driven = evaluate.evaluate_checkpoint(path, first_track, tracks, POLICIES)
    means = {policy: evaluate.track_means({key: r[key] for key in DRIVING}) for policy, r in driven.items()}
    return {policy: {key: round(value, 4) for key, value in m.items()} for policy, m in means.items()}


def training(run_dir: str, updates: int) -> dict[str, float]:
    """Means of the TRAINING columns over the updates (updates - SCREEN_WINDOW, updates], and the run's CPU-hours
    when it had made `updates` updates (NaN where the run did not log them)."""
    window = [row for u, row in progress_rows(run_dir) if updates - SCREEN_WINDOW < u <= updates]
    out = {}
    for column, tag in TRAINING.items():
        values = [float(row[tag]) for row in window if row.get(tag)]
        out[column] = round(float(np.mean(values)), 4) if values else float("nan")
    hours = [float(row["charts/cpu_hours"]) for row in window if row.get("charts/cpu_hours")]
    out["cpu_hours"] = round(hours[-1], 3) if hours else float("nan")
    return out


def pedal(path: str, first_track: int) -> dict[str, float]:
    """The PEDAL readings (pedal_response.py); NaN when the car was out before PEDAL_AFTER decisions on a track."""
    from pedal_response import CarOut, pedal_response, ranges

    try:
        rows = pedal_response(path, first_track, PEDAL_TRACKS, after=(PEDAL_AFTER,))
    except CarOut:
        return dict.fromkeys(PEDAL, float("nan"))
    imagined, real = ranges(rows)[PEDAL_AFTER]
    return {"pedal_range_imagined": round(imagined, 2), "pedal_range_real": round(real, 2)}


def model(path: str, first_track: int, tracks: int) -> dict[str, float]:
    """The MODEL readings (calibration.calibrate_checkpoint: a sampled drive of the tracks, seeded by the first)."""
    calibrated = calibrate_checkpoint(path, first_track, tracks)
    return {key: calibrated[key] for key in MODEL}


def measure(path: str, run_dir: str, updates: int, first_track: int, tracks: int, driven: dict | None = None) -> dict:
    """Every reading of the policy at `path` (kept by `run_dir` at `updates` updates): {policy: row fields}; the
    driving from `driven` if given (driving)."""
    model_readings = {**model(path, first_track, tracks), **pedal(path, first_track)}
    trained = training(run_dir, updates)
    driven = driving(path, first_track, tracks, driven)
    return {policy: {**values, **trained, **model_readings} for policy, values in driven.items()}
