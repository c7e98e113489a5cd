"""Does the agent learn to drive, and does it keep driving? CPU-sized single-car runs, evaluated on held-out tracks.

    python benchmarks/learning.py --runs-dir runs/final/trials --variant lstm --seed 21 --protocol-row   # a row
    python benchmarks/learning.py --protocol-report                        # the final protocol's learning_final.md
    python benchmarks/learning.py --runs-dir runs/final/trials --variant lstm --protocol-ship   # pretrained/lstm_cpu.pt
    python benchmarks/learning.py --variant lstm --seed 11                 # a learning run (8,000 updates)
    python benchmarks/learning.py --variant lstm --seed 11 --resume        # continue it in a later sitting
    python benchmarks/learning.py --report                                 # curves + table only
    python benchmarks/learning.py --variant lstm --seed 11 --diagnose      # sigma, entropy, kl_dyn... per 500 updates
    python benchmarks/learning.py --runs-dir runs/final/trials --variant lstm --seed 21 --diagnose   # a protocol run
    python benchmarks/learning.py --calibrate runs/learning/<run>/checkpoints/latest.pt   # optimistic critic/model?

Trains `dreamer_<variant>.py --preset cpu` on the single-car race (stage ``single``, one torch thread, so two runs
share two cores) until ``--updates`` updates or ``--hours`` of wall time (resumable: a run may span sittings),
evaluating every 5 races on the 10 held-out tracks (seeds 10000..10009) and keeping each evaluated policy
(``checkpoints/eval_<race>.pt``). At most one mode flag (``--report``, ``--diagnose``, ``--protocol-row``,
``--protocol-report``, ``--protocol-ship``, ``--calibrate``) replaces the training. It writes, under
``benchmarks/results/``:

* ``learning_<variant>_seed<S>.csv``: evaluation return and progress against env steps, updates and hours;
* ``baselines.json``: random actions and the pure-pursuit driver on the same 10 tracks;
* ``learning.png`` and ``learning.md``: every curve, with the baselines;
* with ``--calibrate``: a row of ``calibration.csv``, the agent's value and imagined return of real states against
  what the real episodes returned from them;
* with ``--protocol-row``: the final protocol's row of ``learning_final.csv``, the run's readings (why it drives as
  it does, benchmarks/readings.py) in ``learning_final_readings.csv``, and ``learning_final.md``;
  ``--protocol-report`` rewrites ``learning_final.md`` alone;
* with ``--protocol-ship``: ``ship_<variant>.csv``, the protocol's final policies and the shipped agent on the
  screening tracks, and ``pretrained/<variant>_cpu.pt`` replaced by the best of them.

The final protocol (CPU budget: per variant the seeds 21..25, each a single-stage trial of ``benchmarks/experiment.py
--single-cpu-hours 3.1``, measured on the report tracks 10300..10329; its bar and its peers' files) is
``final_protocol.py``, which the ``--protocol-*`` modes call. It replaces the 8,000-update protocol (final policies
on the tracks 10100..10119), whose files are in ``benchmarks/results/history/8000_updates/``.

This file holds the learning runs (names, settings, what their event files and progress.csv hold), the
measurement of a saved policy on a block of tracks, the helpers of the final protocol's rows (eval_curve,
training_hours, eval_summary) and the command line. The rest lives beside it: ``learning_report.py`` (curves,
table, figure, diagnostics), ``final_protocol.py`` and ``calibration.py``. A saved agent on other tracks, or its
acting-only export: ``evaluate.py`` at the top level (``python evaluate.py CHECKPOINT --first-track 10100 --tracks
20``, ``python evaluate.py CHECKPOINT --export OUT``).

``benchmarks/experiment.py`` trains these same runs as its single stage (under ``<storage>/trials/``);
``--runs-dir`` points every mode at them.
"""

from __future__ import annotations

import csv
import dataclasses
import glob
import importlib
import json
import os
import re
import sys
from typing import Annotated, Literal

import numpy as np
import tyro

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402  (the blocks of tracks, the results' CSV rows)

# --- The protocol ----------------------------------------------------------------------------
RESULTS = common.RESULTS
RUNS = os.path.join(ROOT, "runs", "learning")
VARIANTS = ("lstm", "gru")
LEARNING_UPDATES = 8000  # a learning run's updates (the 8,000-update protocol's; the final protocol's runs end on CPU
# time)
# What the benchmark adds to the scripts' CPU preset (--preset cpu): one car; decisions evaluated on the 10 held-out
# tracks every 5 races, each evaluated policy kept; the run ends at --updates; one thread, two runs on two cores.
LEARNING_CONFIG = {
    "stage": "single",
    "num_agents": 1,
    "eval_episodes": 10,
    "eval_checkpoints": True,
    "total_episodes": 1_000_000,  # --updates (or the time limit) ends the run
    "torch_threads": 1,
}


def experiment_name(variant: str) -> str:
    """The name of a learning run of `variant` (and of experiment.py's default single-stage trial)."""
    return f"learning_{variant}"


def learning_runs(runs_dir: str = RUNS, exp_name: str = "learning_*", seed: int | str = "*") -> list[str]:
    """Run directories of the learning benchmark under ``runs_dir``, at any depth (benchmarks/experiment.py keeps
    its single-stage runs, which are these runs, one directory per trial), oldest first."""
    pattern = os.path.join(runs_dir, "**", f"*__{exp_name}__{seed}__*")
    runs = [path for path in glob.glob(pattern, recursive=True) if os.path.isdir(path)]
    return sorted(runs, key=lambda run: (os.path.basename(run).split("__")[-1], run))


def find_run(exp_name: str, seed: int, runs_dir: str = RUNS) -> str | None:
    runs = learning_runs(runs_dir, exp_name, seed)
    return runs[-1] if runs else None


def run_args(variant: str, seed: int, hours: float, resume: bool, updates: int = LEARNING_UPDATES,
             runs_dir: str = RUNS):  # fmt: skip
    """The dreamer script of ``variant``, the Args of this sitting and the fields they override: a new run at the
    CPU preset plus LEARNING_CONFIG, or (``resume``) the latest run of the same name and seed, continued with its
    own settings (only the time limit and the update target are this sitting's)."""
    script = importlib.import_module(f"dreamer_{variant}")
    exp_name = experiment_name(variant)
    existing = find_run(exp_name, seed, runs_dir)
    if resume and existing:
        args = script.Args(resume=existing, time_limit_hours=hours, total_updates=updates)
        return script, args, {"time_limit_hours", "total_updates"}
    if existing and not resume:
        print(f"note: {existing} exists; starting a new run (use --resume to continue it)")
    args = script.preset_args(
        "cpu", seed=seed, exp_name=exp_name, runs_dir=runs_dir, time_limit_hours=hours, total_updates=updates,
        **LEARNING_CONFIG,
    )  # fmt: skip
    return script, args, set()


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


def eval_curve(run_dir: str) -> list[dict]:
    """Evaluation points of a run, with the update count and the training hours at each.

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


# --- A saved policy on a block of tracks -----------------------------------------------------
def policy_summary(
    path: str, first_track: int = common.TRACKS["eval"][0], tracks: int = common.TRACKS["eval"][1],
    policy: str = "stochastic",
) -> dict:
    """One policy's summary (evaluate.py's evaluate_checkpoint drives and reads; this keeps one policy's means): a
    saved agent (any variant, any stage; agent 0 of a multi-agent checkpoint) driving alone with `policy` on
    tracks ``first_track .. first_track + tracks - 1``, with the env settings it was trained with (final dead
    zone): mean return, progress and |steer| (near 1: bang-bang steering), and the per-track values. The training
    runs' own evaluation is this on 10000..10009; another block of tracks measures a best.pt without the bias of
    having been picked there."""
    if tracks < 1:
        raise ValueError(f"tracks must be >= 1, got {tracks}")
    from evaluate import evaluate_checkpoint as drive
    from utils.checkpoint import read_checkpoint  # one-line errors naming the file

    script, checkpoint = read_checkpoint(path)
    variant = checkpoint["variant"]
    if policy not in script.EVAL_POLICIES:
        raise ValueError(f"policy must be one of {', '.join(script.EVAL_POLICIES)}, got {policy!r}")
    args = script.args_from_checkpoint(checkpoint, path, num_agents=1)
    readings = drive(path, first_track, tracks, (policy,))[policy]
    returns, progress, abs_steer = (np.asarray(readings[key]) for key in ("return", "progress", "abs_steer"))
    result = {
        "checkpoint": path,
        "variant": variant,
        "updates": common.checkpoint_updates(checkpoint),
        "policy": policy,
        "tracks": common.track_block(first_track, tracks),
        "eval_return": float(returns.mean()),
        "eval_progress": float(progress.mean()),
        "returns": [round(float(r), 2) for r in returns],
        "progress": [round(float(p), 4) for p in progress],
    }
    if args.env_id == "multi_car_racing":  # action 0 is the steer there (highway-env: the acceleration)
        result["mean_abs_steer"] = float(abs_steer.mean())
    return result


def eval_summary(curve: list[dict]) -> tuple[float, float]:
    """A run's best evaluation return and the mean of its last three (eval_curve's points, its own evaluation
    tracks 10000..10009), 2 decimals: how far its last policies fell from its best. NaN, NaN without evaluations."""
    evals = [r["eval_return"] for r in curve]
    if not evals:
        return float("nan"), float("nan")
    return round(max(evals), 2), round(float(np.mean(evals[-3:])), 2)


# --- Command line ----------------------------------------------------------------------------
@dataclasses.dataclass
class Args:
    variant: Literal["lstm", "gru"] = "lstm"
    """the agent: dreamer_<variant>.py"""
    seed: int = 1
    """the run's seed"""
    hours: float = 3.0
    """wall-clock budget of this sitting"""
    updates: int = LEARNING_UPDATES
    """the run ends after this many updates"""
    resume: bool = False
    """continue the latest run of this variant and seed"""
    runs_dir: str = RUNS
    """where the runs are, at any depth (e.g. runs/experiment/trials: the experiment's single stage)"""
    report: bool = False
    """mode: only write the curves and the table"""
    diagnose: bool = False
    """mode: only the run's diagnostics per 500 updates (returns, sigma, entropy, kl_dyn, reward NLL, imagined
    return, evaluations): printed and written to benchmarks/results/<experiment>_seed<S>_diagnostics.md; the run
    is learning_<variant>, else an experiment trial <variant>_single (e.g. --runs-dir runs/final/trials --seed 21)"""
    protocol_row: bool = False
    """mode: only measure the final protocol's run of --variant and --seed (21..25: the single-stage trial of
    experiment.py --single-cpu-hours 3.1 under --runs-dir <storage>/trials, refused before its budget is spent
    unless the non-finite guard stopped it),
    its latest.pt sampled and with its mean action on the 30 report tracks 10300..10329: its row of
    learning_final.csv; its readings (benchmarks/readings.py: the same drives, its training logs, its model on
    sampled drives of those tracks, its view of the pedal) in learning_final_readings.csv; then learning_final.md"""
    protocol_readings: bool = True
    """--protocol-row: also measure the run's readings (--no-protocol-readings skips them; they cost another sampled
    drive of the tracks and the model's imagination from every frame of it)"""
    protocol_report: bool = False
    """mode: only rewrite learning_final.md from the final protocol's learning_final.csv and its peers' rows of the
    report tracks in <peer>_peer.csv and <peer>_peer_curve.csv (no evaluation)"""
    protocol_ship: bool = False
    """mode: only choose the shipped agent of --variant: the final policies of the protocol's seeds (under
    --runs-dir: every seed 21..25, --seed is not read) and pretrained/<variant>_cpu.pt with the mean action on the
    screening tracks 10200..10219; the best seed is exported over the shipped file if it drives better there
    (ship_<variant>.csv in --results-dir)"""
    results_dir: str = RESULTS
    """--protocol-row, --protocol-report, --protocol-ship: where learning_final.csv and .md (and the readings, the
    peers' CSVs, ship_<variant>.csv) are"""
    calibrate: Annotated[str | None, tyro.conf.arg(metavar="CHECKPOINT")] = None
    """mode: only measure whether this agent's critic and imagination are optimistic on real episodes (its sampled
    policy on --tracks tracks from --first-track); a row of benchmarks/results/calibration.csv"""
    horizon: int | None = None
    """--calibrate: imagination horizon (default: the agent's own)"""
    first_track: int = common.TRACKS["fresh"][0]
    """--calibrate: seed of the first track"""
    tracks: int = 5
    """--calibrate: number of tracks"""


MODES = ("report", "diagnose", "protocol_row", "protocol_report", "protocol_ship", "calibrate")  # Args' mode fields
PROTOCOL_MODES = ("protocol_row", "protocol_report", "protocol_ship")  # the modes of --results-dir


def check(args: Args) -> None:
    """Refuse a command line that asks for two modes or gives an impossible value, before any work: ValueError
    naming the flags."""
    modes = [f"--{name.replace('_', '-')}" for name in MODES if getattr(args, name) not in (None, False)]
    if len(modes) > 1:
        raise ValueError(f"{' and '.join(modes)} are separate modes: give one at most")
    if args.horizon is not None and args.calibrate is None:
        raise ValueError("--horizon is the imagination horizon of --calibrate; give --calibrate CHECKPOINT")
    if args.results_dir != RESULTS and not any(getattr(args, name) for name in PROTOCOL_MODES):
        raise ValueError("--results-dir is the place of learning_final.csv for --protocol-row, --protocol-report "
                         "and --protocol-ship; give one of them")  # fmt: skip
    if args.hours <= 0:
        raise ValueError(f"--hours must be > 0, got {args.hours}")
    if args.updates < 1:
        raise ValueError(f"--updates must be >= 1, got {args.updates}")
    if args.tracks < 1 or (args.horizon is not None and args.horizon < 1):
        raise ValueError(f"--tracks and --horizon must be >= 1, got {args.tracks} and {args.horizon}")


def run_mode(args: Args) -> bool:
    """Run the measuring mode `args` gives (any but --report), printing and writing what it makes; False if it gives
    none. Bad input (no such run, checkpoint or kept policy) raises ValueError naming it."""
    name = experiment_name(args.variant)
    if args.calibrate is not None:
        from calibration import calibrate_checkpoint, write_calibration_row

        row = calibrate_checkpoint(args.calibrate, args.first_track, args.tracks, args.horizon)
        write_calibration_row(row)
        print(json.dumps(row, indent=1))
    elif args.diagnose:
        from learning_report import diagnostics, diagnostics_table

        run = find_run(name, args.seed, args.runs_dir)
        if run is None:  # an experiment.py single-stage trial of its own settings (the final protocol's runs)
            name = f"{args.variant}_single"
            trials = sorted({os.path.dirname(r) for r in learning_runs(args.runs_dir, name, args.seed)})
            if len(trials) > 1:  # e.g. a sweep's flag sets: which one is meant is not for this mode to guess
                raise ValueError(f"{len(trials)} trials of {name} seed {args.seed} under {args.runs_dir}: give "
                                 f"--runs-dir one of them ({', '.join(trials)})")  # fmt: skip
            run = find_run(name, args.seed, args.runs_dir)
        if run is None:
            raise ValueError(f"no run of learning_{args.variant} or {name} seed {args.seed} in {args.runs_dir}")
        table = diagnostics_table(diagnostics(run))
        with open(os.path.join(RESULTS, f"{name}_seed{args.seed}_diagnostics.md"), "w") as f:
            f.write(f"{os.path.basename(run)}\n\n{table}")
        print(table)
    elif args.protocol_ship:
        import final_protocol as protocol

        shipped = os.path.join(ROOT, "pretrained", f"{args.variant}_cpu.pt")
        print(protocol.ship(args.variant, args.runs_dir, shipped, args.results_dir))
    elif args.protocol_row or args.protocol_report:
        import final_protocol as protocol  # (it imports this file: not at the top)

        if args.protocol_row:
            path = os.path.join(args.results_dir, "learning_final.csv")
            why_path = os.path.join(args.results_dir, protocol.WHY_CSV)
            common.read_table(path, protocol.PROTOCOL_COLUMNS, protocol.PROTOCOL_ADVICE)  # another's: refused first
            common.read_table(why_path, protocol.WHY_COLUMNS, protocol.WHY_ADVICE)
            row, driven = protocol.protocol_measure(args.variant, args.seed, args.runs_dir)
            protocol.write_protocol_row(row, path)  # kept before the readings are measured
            print(json.dumps(row, indent=1))
            if args.protocol_readings:
                protocol.write_why_rows(protocol.protocol_readings(row, driven, args.runs_dir), why_path)
        print(protocol.write_protocol_report(args.results_dir))
    else:
        return False
    return True


def training_sitting(args: Args) -> tuple:
    """This sitting's (script, its Args, the fields they override) of run_args, checked by the script's own rules
    (a value it refuses raises UsageError, a ValueError naming the flag) before any work."""
    from utils.run import validate_args

    script, script_args, overrides = run_args(args.variant, args.seed, args.hours, args.resume, args.updates,
                                              args.runs_dir)  # fmt: skip
    validate_args(script_args, script.LOG_SIGMA_RANGE)
    return script, script_args, overrides


def cli(argv: list[str] | None = None) -> None:
    """The command line: one mode, or this sitting's training and then the report. Bad input ends with one line
    naming it, no traceback."""
    args = tyro.cli(Args, args=argv, description=__doc__)
    try:
        check(args)
        if run_mode(args):
            return
        sitting = None if args.report else training_sitting(args)
    except ValueError as e:  # (utils.checkpoint.CheckpointError and UsageError are ValueErrors)
        raise SystemExit(f"learning.py: error: {' '.join(str(e).split())}") from None
    if sitting is not None:
        script, script_args, overrides = sitting
        script.main(script_args, overrides)
    from learning_report import report

    report(args.runs_dir)


if __name__ == "__main__":
    cli()
