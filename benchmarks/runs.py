"""What a training run leaves on disk, read back: where the runs of a name and seed are, the run of an experiment
trial, a run's evaluation curve and training hours (from its TensorBoard event files), its progress.csv rows, and
what a checkpoint says about its run (updates, CPU-hours, a stop by the non-finite guard).

A run directory is the dreamer scripts' ``<runs_dir>/<env>__<exp_name>__<seed>__<time>/`` (TensorBoard event files,
``progress.csv``, ``checkpoints/``). ``benchmarks/experiment.py`` and ``sweep.py`` train their trials (one run
directory per trial under ``<storage>/trials/``), and they, ``learning.py``, ``final_protocol.py``,
``readings.py``, ``experiment_report.py`` and ``highway_random.py`` read them through this module.
"""

from __future__ import annotations

import csv
import glob
import os
import re

import numpy as np

from common import checkpoint_updates

# --- Where the runs are ----------------------------------------------------------------------
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RUNS = os.path.join(ROOT, "runs", "experiment", "trials")  # experiment.py's trials at its default --storage
VARIANTS = ("lstm", "gru")  # dreamer_<variant>.py


def experiment_name(variant: str) -> str:
    """The name of experiment.py's default single-stage trial of `variant` (the 8,000-update protocol's runs)."""
    return f"learning_{variant}"


def learning_runs(runs_dir: str = RUNS, exp_name: str = "learning_*", seed: int | str = "*") -> list[str]:
    """Run directories of the learning benchmark under ``runs_dir``, at any depth (benchmarks/experiment.py keeps
    its single-stage runs, which are these runs, one directory per trial), oldest first."""
    pattern = os.path.join(runs_dir, "**", f"*__{exp_name}__{seed}__*")
    runs = [path for path in glob.glob(pattern, recursive=True) if os.path.isdir(path)]
    return sorted(runs, key=lambda run: (os.path.basename(run).split("__")[-1], run))


def find_run(exp_name: str, seed: int, runs_dir: str = RUNS) -> str | None:
    """The newest run of `exp_name` and `seed` under `runs_dir` (learning_runs), or None."""
    runs = learning_runs(runs_dir, exp_name, seed)
    return runs[-1] if runs else None


def run_of(directory: str) -> str | None:
    """The run directory of a trial that has a checkpoint (a run killed before its first checkpoint is ignored)."""
    runs = sorted(glob.glob(os.path.join(directory, "*", "checkpoints", "latest.pt")))
    return os.path.dirname(os.path.dirname(runs[-1])) if runs else None


# --- A run's curve, from its event files and its progress.csv --------------------------------
EVENT_FILE_PROCESS = re.compile(r"events\.out\.tfevents\.\d+\.(?P<process>.+\.\d+)\.\d+")
"""The name SB3's TensorBoard logger gives an event file, ``events.out.tfevents.<time>.<host>.<pid>.<n>`` (no
suffix): host (which may hold dots) and pid name the process that wrote it."""


def sittings(run_dir: str) -> list[tuple[list, float, float]]:
    """Each sitting of a run with anything logged, in the order they ran: its event files as (event accumulator,
    scalar tags), and its first and last logged wall time.

    A sitting is one process. Each call of a script's ``main`` opens a new event file, and an experiment trial
    calls it again every few hundred updates in the same process, so consecutive files of one host and pid are
    one sitting and the time between them counts; the time between processes does not."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, last_process = [], None
    for events_file in sorted(glob.glob(os.path.join(run_dir, "events.out.tfevents.*"))):
        acc = EventAccumulator(events_file, size_guidance={"scalars": 0})
        acc.Reload()
        tags = acc.Tags()["scalars"]
        if not tags:
            continue
        wall_times = [e.wall_time for tag in tags for e in acc.Scalars(tag)]
        match = EVENT_FILE_PROCESS.fullmatch(os.path.basename(events_file))
        process = match["process"] if match else events_file
        if out and process == last_process:
            files, start, end = out[-1]
            out[-1] = (files + [(acc, tags)], min(start, min(wall_times)), max(end, max(wall_times)))
        else:
            out.append(([(acc, tags)], min(wall_times), max(wall_times)))
        last_process = process
    return out


def training_hours(run_dir: str) -> float:
    """A run's training time in hours up to its last logged scalar: each sitting from its first logged scalar to its
    last, added up (the time between sittings does not count), as ``eval_curve``'s hours."""
    return round(sum(end - start for _, start, end in sittings(run_dir)) / 3600, 4)


CAR_EVAL = re.compile(r"^car_(\d+)/eval/episodic_return$")  # every car's evaluation return


def eval_curve(run_dir: str, cars: bool = False) -> list[dict]:
    """Evaluation points of a run, with the update count and the training hours at each; with `cars`, also every
    car's return at each (``car_<i>``, in car order; ``eval_return`` is car 0's).

    Hours add up the sittings (each from its first logged scalar to its last; see ``sittings``), so the time
    between sittings does not count."""
    rows, hours_before = [], 0.0
    for files, start, end in sittings(run_dir):
        for acc, tags in files:
            if "car_0/eval/episodic_return" not in tags:
                continue
            progress = (
                {e.step: e.value for e in acc.Scalars("car_0/eval/progress")} if "car_0/eval/progress" in tags else {}
            )
            returns: dict[int, dict] = {}  # env step: {car_<i>: return}
            car_tags = {int(m[1]): m[0] for m in map(CAR_EVAL.match, tags) if m} if cars else {}
            for car in sorted(car_tags):
                for e in acc.Scalars(car_tags[car]):
                    returns.setdefault(e.step, {})[f"car_{car}"] = round(float(e.value), 2)
            updates = acc.Scalars("car_0/perf/updates") if "car_0/perf/updates" in tags else []
            update_steps = np.array([e.step for e in updates])
            update_values = np.array([e.value for e in updates])
            for e in acc.Scalars("car_0/eval/episodic_return"):
                before = update_steps <= e.step
                rows.append(
                    {
                        "env_steps": int(e.step),
                        "updates": int(update_values[before][-1]) if before.any() else 0,
                        "wall_hours": round(hours_before + (e.wall_time - start) / 3600, 4),
                        "eval_return": round(float(e.value), 2),
                        "eval_progress": round(float(progress.get(e.step, float("nan"))), 4),
                        **returns.get(e.step, {}),
                    }
                )
        hours_before += (end - start) / 3600
    rows.sort(key=lambda row: row["env_steps"])
    return [row for i, row in enumerate(rows) if i == 0 or row["env_steps"] != rows[i - 1]["env_steps"]]


def progress_rows(run_dir: str) -> list[tuple[int, dict]]:
    """A run's progress.csv rows, each with the updates made when it was logged (0 before the first update)."""
    with open(os.path.join(run_dir, "progress.csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    updates, out = 0, []
    for row in rows:
        if row.get("car_0/perf/updates"):
            updates = int(float(row["car_0/perf/updates"]))
        out.append((updates, row))
    return out


def eval_summary(curve: list[dict]) -> tuple[float, float]:
    """A run's best evaluation return and the mean of its last three (eval_curve's points, its own evaluation
    tracks 10000..10009), 2 decimals: how far its last policies fell from its best. NaN, NaN without evaluations."""
    evals = [r["eval_return"] for r in curve]
    if not evals:
        return float("nan"), float("nan")
    return round(max(evals), 2), round(float(np.mean(evals[-3:])), 2)


# --- What a checkpoint says about its run ----------------------------------------------------
def updates_of(path: str, script) -> int:
    """The updates the checkpoint at `path` has made (checkpoint_updates)."""
    return checkpoint_updates(script.load_checkpoint(path))


def cpu_hours_of(checkpoint: dict) -> float:
    """The process CPU-hours a run had spent over all its sittings when it saved `checkpoint` (its "extra")."""
    return float((checkpoint.get("extra") or {}).get("cpu_seconds", 0.0)) / 3600


def numerical_stop(checkpoint: dict) -> bool:
    """Whether the run of `checkpoint` was stopped by the dreamer scripts' guard: an agent had
    --max-nonfinite-updates updates in a row with a non-finite loss or gradient (utils.run.NumericalFault)."""
    limit = (checkpoint.get("args") or {}).get("max_nonfinite_updates")
    return limit is not None and any(agent.get("nonfinite_in_a_row", 0) >= limit for agent in checkpoint["agents"])
