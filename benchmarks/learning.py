"""Does the agent learn to drive, and does it keep driving? The measurements of single-car runs on held-out tracks.

    python benchmarks/learning.py --runs-dir runs/final/trials --variant lstm --seed 21 --protocol-row   # a row
    python benchmarks/learning.py --protocol-report                        # the final protocol's learning_final.md
    python benchmarks/learning.py --runs-dir runs/final/trials --variant lstm --protocol-ship   # pretrained/lstm_cpu.pt
    python benchmarks/learning.py --runs-dir runs/final/trials --variant lstm --seed 21 --diagnose   # sigma, entropy...
    python benchmarks/learning.py --calibrate runs/final/trials/<trial>/<run>/checkpoints/latest.pt   # optimistic?

The runs are the single-stage trials of ``benchmarks/experiment.py`` (``dreamer_<variant>.py --preset cpu`` on the
single-car race, one torch thread, evaluated every 5 races on the 10 held-out tracks 10000..10009, each evaluated
policy kept as ``checkpoints/eval_<race>.pt``), under ``<storage>/trials/``: ``--runs-dir`` points every mode at
them. Each command runs one mode (``--protocol-row``, ``--protocol-report``, ``--protocol-ship``, ``--diagnose``,
``--calibrate``) and writes, under ``--results-dir`` (default ``benchmarks/results/``, the reported files):

* with ``--protocol-row``: the final protocol's row of ``learning_final.csv``, the run's readings (why it drives as
  it does, benchmarks/readings.py) in ``learning_final_readings.csv``, and ``learning_final.md``;
  ``--protocol-report`` rewrites ``learning_final.md`` alone;
* with ``--protocol-ship``: ``ship_<variant>.csv``, the protocol's final policies and the shipped agent on the
  screening tracks, and ``pretrained/<variant>_cpu.pt`` (or ``--shipped``) replaced by the best of them;
* with ``--diagnose``: ``<experiment>_seed<S>_diagnostics.md``, the run's training logs per 500 updates;
* with ``--calibrate``: a row of ``calibration.csv``, the agent's value and imagined return of real states against
  what the real episodes returned from them.

The final protocol (CPU budget: per variant the seeds 21..25, each a single-stage trial of ``benchmarks/experiment.py
--single-cpu-hours 3.1``, measured on the report tracks 10300..10329; its bar and its peers' files) is
``final_protocol.py``, which the ``--protocol-*`` modes call (``--protocol-ship``: ``ship.py``). It replaces the
8,000-update protocol (final policies on the tracks 10100..10119, its runs the experiment's single stage at 8,000
updates), whose files are in ``benchmarks/results/history/8000_updates/``. (This command line also trained and
plotted such runs one at a time until commit b28dd0c.)

This file holds the measurement of a saved policy on a block of tracks, a run's diagnostics and the command line.
The rest lives beside it: ``runs.py`` (where the runs are; what their event files, progress.csv and checkpoints
hold), ``references.py`` (random actions and the pursuit driver), ``final_protocol.py``, ``ship.py`` and
``calibration.py``. A saved agent on other tracks, or its acting-only export: ``evaluate.py`` at the top level
(``python evaluate.py CHECKPOINT --first-track 10100 --tracks 20``, ``python evaluate.py CHECKPOINT --export OUT``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from typing import Annotated, Literal

import numpy as np
import tyro

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402  (the blocks of tracks, the results' CSV rows)
import final_protocol as protocol  # noqa: E402  (the --protocol-* modes)
import ship  # noqa: E402  (--protocol-ship)
from calibration import calibrate_checkpoint, write_calibration_row  # noqa: E402
from runs import RUNS, experiment_name, find_run, learning_runs, progress_rows  # noqa: E402

RESULTS = common.RESULTS


# --- A saved policy on a block of tracks -----------------------------------------------------
def policy_summary(
    path: str, first_track: int = common.TRACKS["eval"][0], tracks: int = common.TRACKS["eval"][1],
    policy: str = "stochastic",
) -> dict:
    """One policy's summary (evaluate.py's evaluate_checkpoint drives and reads; this keeps one policy's means): a
    saved agent (any variant, any stage; agent 0 of a multi-agent checkpoint) driving alone with `policy` on
    tracks ``first_track .. first_track + tracks - 1``, with the env settings it was trained with (final dead
    zone): mean return, progress and |steer| (near 1: bang-bang steering), and the per-track values. The training
    runs' own evaluation is this on 10000..10009 with their --eval-policy (the same numbers exactly only for
    deterministic: acting samples from torch's stream, seeded here, not as in the run); another block of tracks
    measures a best.pt without the bias of having been picked there."""
    if tracks < 1:
        raise ValueError(f"tracks must be >= 1, got {tracks}")
    from evaluate import evaluate_checkpoint as drive, track_means
    from utils.checkpoint import read_checkpoint  # one-line errors naming the file

    script, checkpoint = read_checkpoint(path)
    variant = checkpoint["variant"]
    if policy not in script.EVAL_POLICIES:
        raise ValueError(f"policy must be one of {', '.join(script.EVAL_POLICIES)}, got {policy!r}")
    args = script.args_from_checkpoint(checkpoint, path, num_agents=1)
    readings = drive(path, first_track, tracks, (policy,))[policy]
    means = track_means(readings)
    result = {
        "checkpoint": path,
        "variant": variant,
        "updates": common.checkpoint_updates(checkpoint),
        "policy": policy,
        "tracks": common.track_block(first_track, tracks),
        "eval_return": means["return"],
        "eval_progress": means["progress"],
        "returns": [round(float(r), 2) for r in readings["return"]],
        "progress": [round(float(p), 4) for p in readings["progress"]],
    }
    if args.env_id == "multi_car_racing":  # action 0 is the steer there (highway-env: the acceleration)
        result["mean_abs_steer"] = means["abs_steer"]
    return result


# --- A run's training logs (--diagnose) ------------------------------------------------------
# What to look at when a run falls short: (column, tag of progress.csv), averaged per bucket of updates.
DIAGNOSTICS = (
    ("training return", "car_0/charts/episodic_return"),
    ("training progress", "car_0/charts/progress"),
    ("actor sigma", "car_0/losses/actor_std"),
    ("entropy", "car_0/losses/entropy"),
    ("kl_dyn", "car_0/losses/kl_dyn"),
    ("reward NLL (real data)", "car_0/losses/reward"),
    ("imagined return", "car_0/losses/imagined_return"),
    ("eval return", "car_0/eval/episodic_return"),
    ("eval progress", "car_0/eval/progress"),
    ("eval mean |steer|", "car_0/eval/mean_abs_steer"),
)


def diagnostics(run_dir: str, bucket: int = 500) -> list[dict]:
    """A run's progress.csv in buckets of `bucket` updates: per bucket its training races and the mean of each
    DIAGNOSTICS column over the rows logged in it. A row belongs to the bucket of the updates made when it was
    logged (rows before the first update: bucket 0); empty cells stay out of the means (NaN if all are empty).
    The imagined return is the lambda-return of imagination with its entropy part; the training races are driven
    by the sampled policy; the evaluation uses the run's --eval-policy."""
    table = {}
    for updates, row in progress_rows(run_dir):
        cell = table.setdefault(updates // bucket, {"races": 0, **{name: [] for name, _ in DIAGNOSTICS}})
        cell["races"] += bool(row.get("car_0/charts/episodic_return"))
        for name, tag in DIAGNOSTICS:
            if row.get(tag):
                cell[name].append(float(row[tag]))
    return [
        {"updates": f"{b * bucket}-{(b + 1) * bucket - 1}", "races": cell.pop("races"),
         **{name: float(np.mean(v)) if v else float("nan") for name, v in cell.items()}}
        for b, cell in sorted(table.items())
    ]  # fmt: skip


def diagnostics_table(rows: list[dict]) -> str:
    """Markdown of diagnostics(): one line per bucket."""
    names = list(rows[0]) if rows else ["updates", "races"]
    lines = ["| " + " | ".join(n.replace("|", "\\|") for n in names) + " |", "|" + "---|" * len(names)]
    for row in rows:
        cells = [v if isinstance(v, (str, int)) else "" if np.isnan(v) else f"{v:.2f}" for v in row.values()]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


# --- Command line ----------------------------------------------------------------------------
@dataclasses.dataclass
class Args:
    variant: Literal["lstm", "gru"] = "lstm"
    """the run's agent: dreamer_<variant>.py"""
    seed: int = 1
    """the run's seed"""
    runs_dir: str = RUNS
    """where the runs are, at any depth (e.g. runs/final/trials: the single-stage trials of experiment.py
    --storage runs/final)"""
    diagnose: bool = False
    """mode: the run's diagnostics per 500 updates (returns, sigma, entropy, kl_dyn, reward NLL, imagined
    return, evaluations): printed and written to <experiment>_seed<S>_diagnostics.md in --results-dir; the run
    is learning_<variant>, else an experiment trial <variant>_single (e.g. --runs-dir runs/final/trials --seed 21)"""
    protocol_row: bool = False
    """mode: measure the final protocol's run of --variant and --seed (21..25: the single-stage trial of
    experiment.py --single-cpu-hours 3.1 under --runs-dir <storage>/trials, refused before its budget is spent
    unless the non-finite guard stopped it),
    its latest.pt sampled and with its mean action on the 30 report tracks 10300..10329: its row of
    learning_final.csv; its readings (benchmarks/readings.py: the same drives, its training logs, its model on
    sampled drives of those tracks, its view of the pedal) in learning_final_readings.csv; then learning_final.md"""
    protocol_readings: bool = True
    """--protocol-row: also measure the run's readings (--no-protocol-readings skips them; they cost another sampled
    drive of the tracks and the model's imagination from every frame of it)"""
    protocol_report: bool = False
    """mode: rewrite learning_final.md from the final protocol's learning_final.csv and its peers' rows of the
    report tracks in <peer>_peer.csv and <peer>_peer_curve.csv (no agent is driven; the random-action and pursuit
    references are, once, if <--results-dir>/references_report.json is missing)"""
    protocol_ship: bool = False
    """mode: choose the shipped agent of --variant: the final policies of the protocol's seeds (under
    --runs-dir: the seeds of --ship-seeds, every one by default; --seed is not read) and pretrained/<variant>_cpu.pt
    with the mean action on the screening tracks 10200..10219; the best seed is exported over the shipped file if it
    drives better there (ship_<variant>.csv in --results-dir)"""
    ship_seeds: tuple[int, ...] = protocol.PROTOCOL_SEEDS
    """--protocol-ship: the seeds whose final policies are the candidates (default every seed; fewer only where a
    run's directory is gone, e.g. a machine lost: the seeds left still drive by the same rule)"""
    shipped: str | None = None
    """--protocol-ship: the agent file the best seed must beat and, if it does, is exported over (default
    pretrained/<variant>_cpu.pt, which git tracks: give another path, with a --results-dir of its own for the
    decision's record, to make the choice without changing either; a missing file: the best seed is exported there)"""
    results_dir: str = RESULTS
    """where every mode's tables are: learning_final.csv and .md (and the readings, the peers' CSVs,
    ship_<variant>.csv), the diagnostics, calibration.csv (default: the reported ones in benchmarks/results)"""
    calibrate: Annotated[str | None, tyro.conf.arg(metavar="CHECKPOINT")] = None
    """mode: measure whether this agent's critic and imagination are optimistic on real episodes (its sampled
    policy on --tracks tracks from --first-track); a row of calibration.csv in --results-dir"""
    horizon: int | None = None
    """--calibrate: imagination horizon (default: the agent's own)"""
    first_track: int = common.TRACKS["fresh"][0]
    """--calibrate: seed of the first track"""
    tracks: int = 5
    """--calibrate: number of tracks"""
    torch_threads: int = 0
    """torch CPU threads (0: torch's default; 1 when other runs share the cores)"""


MODES = ("protocol_row", "protocol_report", "protocol_ship", "diagnose", "calibrate")  # Args' mode fields


def check(args: Args) -> None:
    """Refuse a command line that asks for two modes or none, or gives an impossible value, before any work:
    ValueError naming the flags."""
    flags = [f"--{name.replace('_', '-')}" for name in MODES]
    modes = [flag for name, flag in zip(MODES, flags) if getattr(args, name) not in (None, False)]
    if len(modes) > 1:
        raise ValueError(f"{' and '.join(modes)} are separate modes: give one")
    if args.horizon is not None and args.calibrate is None:
        raise ValueError("--horizon is the imagination horizon of --calibrate; give --calibrate CHECKPOINT")
    if args.ship_seeds != protocol.PROTOCOL_SEEDS and not args.protocol_ship:
        raise ValueError("--ship-seeds are the candidates of --protocol-ship; give --protocol-ship")
    if args.shipped is not None and not args.protocol_ship:
        raise ValueError("--shipped is the agent file of --protocol-ship; give --protocol-ship")
    if args.shipped is not None and os.path.abspath(args.results_dir) == os.path.abspath(RESULTS):
        raise ValueError("--shipped: give a --results-dir of its own too (the decision would go into the reported "
                         "ship_<variant>.csv, which records what pretrained/ holds)")
    wrong = [seed for seed in args.ship_seeds if seed not in protocol.PROTOCOL_SEEDS]
    if wrong or not args.ship_seeds or len(set(args.ship_seeds)) < len(args.ship_seeds):
        raise ValueError(f"--ship-seeds must be distinct seeds of the final protocol "
                         f"({', '.join(map(str, protocol.PROTOCOL_SEEDS))}), got {list(args.ship_seeds)}")  # fmt: skip
    if args.tracks < 1 or (args.horizon is not None and args.horizon < 1):
        raise ValueError(f"--tracks and --horizon must be >= 1, got {args.tracks} and {args.horizon}")
    if not modes:
        raise ValueError(f"give a mode: {', '.join(flags)} (the runs themselves are benchmarks/experiment.py's "
                         "single stage)")  # fmt: skip


def run_mode(args: Args) -> None:
    """Run the mode `args` gives, printing and writing what it makes. Bad input (no such run, checkpoint or kept
    policy) raises ValueError naming it."""
    name = experiment_name(args.variant)
    if args.calibrate is not None:
        row = calibrate_checkpoint(args.calibrate, args.first_track, args.tracks, args.horizon)
        os.makedirs(args.results_dir, exist_ok=True)
        write_calibration_row(row, os.path.join(args.results_dir, "calibration.csv"))
        print(json.dumps(row, indent=1))
    elif args.diagnose:
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
        os.makedirs(args.results_dir, exist_ok=True)
        common.write_text(os.path.join(args.results_dir, f"{name}_seed{args.seed}_diagnostics.md"),
                          f"{os.path.basename(run)}\n\n{table}")
        print(table)
    elif args.protocol_ship:
        shipped = args.shipped or os.path.join(ROOT, "pretrained", f"{args.variant}_cpu.pt")
        print(ship.ship(args.variant, args.runs_dir, shipped, args.results_dir, args.ship_seeds))
    elif args.protocol_row or args.protocol_report:
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


def cli(argv: list[str] | None = None) -> None:
    """The command line: one mode. Bad input ends with one line naming it, no traceback."""
    from utils.run import tyro_cli

    args = tyro_cli(Args, argv, __doc__)
    try:
        check(args)
        common.set_torch_threads(args.torch_threads)
        run_mode(args)
    except ValueError as e:  # (utils.checkpoint.CheckpointError is a ValueError)
        raise SystemExit(f"learning.py: error: {' '.join(str(e).split())}") from None


if __name__ == "__main__":
    cli()
