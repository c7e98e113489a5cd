"""The final protocol of the learning benchmark (CPU budget): how the LSTM- and GRU-Dreamer's final policies are
measured, judged against the bar and compared with each other and with the PPO peers. It replaces the 8,000-update
protocol (``learning.py --final`` until commit 32c3b4c), whose ``learning_final.csv`` and ``.md`` are in
``benchmarks/results/history/8000_updates/``.

* The runs: per variant (lstm, gru) the seeds 21..25 (PROTOCOL_SEEDS), each a single-stage trial of
  ``benchmarks/experiment.py --stages single --single-cpu-hours 3.1``: trained until it has spent 3.1 CPU-hours of
  process CPU time over all its sittings (PROTOCOL_CPU_HOURS, the peers' budget), whatever its updates; found under
  ``<storage>/trials/single_<variant>_seed<S>/`` (``--runs-dir <storage>/trials``).
* A run's row of ``learning_final.csv`` (protocol_measure, PROTOCOL_COLUMNS): its final policy, latest.pt once the
  budget is spent (refused before, unless the non-finite guard stopped the run: numerical_stop), driven sampled
  (``final_*``) and with its mean action (``mean_action_*``, with the share of tracks whose lap it finished and its
  mean speed) on the 30 report tracks 10300..10329 (REPORT_TRACKS), which serve no choice; beside them its updates,
  env steps, CPU-hours and wall hours, and the best and last-three-average returns of its own evaluations (tracks
  10000..10009). ``learning_final.csv`` holds one protocol's rows at a time: a file with the 8,000-update protocol's
  columns is refused.
* The peers (PROTOCOL_PEERS: ``ppo_peer.py --algo ppo`` and ``--algo recurrent-ppo``): their deterministic policy
  after the same CPU time on the same tracks: the rows of ``<peer>_peer.csv`` beside learning_final.csv whose
  ``tracks`` are the report tracks (protocol_peer_path, read_peer_rows); the rows of other tracks (the fresh tracks
  10100..10119 of the 8,000-update protocol, which a row without a ``tracks`` column was measured on) are left out,
  and so is a row of a run not finished yet (peer_finished: neither budget spent; listed in the report).
  Their sample efficiency: the snapshots of ``<peer>_peer_curve.csv`` (``ppo_peer.py --curve``) on the report tracks.
* Why a run drives as it does (protocol_readings; ``learning_final_readings.csv``): benchmarks/readings.py's
  readings of the same final policy on the same tracks, per policy: its driving (speed, gas, brake share, laps,
  eliminations: from the row's own drives), its training logs' last updates (sigma, alpha, imagined return), its
  model on sampled drives (imagined against real H-step return, the reward head on the elimination frames) and its
  view of the pedal.
* The bar, per variant over its seeds (protocol_bar): with its mean action, mean return >= 800 with every seed
  >= 650, mean progress >= 0.85 and mean |steer| <= 0.3; sampled, mean return >= 700. A variant short of seeds is
  provisional.
* ``learning_final.md`` (write_protocol_report): per variant and policy and per peer the mean over seeds with its t
  95% interval and the IQM with rliable's stratified-bootstrap 95% interval (a description), the bar, every run's
  row, the LSTM minus the GRU and each variant minus each peer, judged by the exact permutation test and Welch's t
  interval (benchmarks/stats.py), what random actions and the pure-pursuit driver score on the same tracks
  (protocol_references), the env steps after which each peer's snapshots reach each variant's final mean return
  (sample_efficiency), per variant the readings' means over seeds (protocol_why) and, for a protocol that replaced
  one of the same columns and tracks (REPLACED_PROTOCOL), this one's final returns against that one's, per variant
  and policy, by the same two tests (protocol_against_replaced).

How to run it (``learning.py`` stays the benchmark's one command line; its ``--results-dir`` moves
learning_final.csv, learning_final.md and the peers' files; the runs computed in float32, which on a CPU with
bfloat16 instructions takes ``--overrides amp=off`` in a new storage):

    python benchmarks/experiment.py --stages single --single-cpu-hours 3.1 --seeds 21 22 23 24 25 \\
        --storage runs/final --results runs/final                          # the runs (their tables there)
    python benchmarks/learning.py --runs-dir runs/final/trials --variant lstm --seed 21 --protocol-row   # a row
    python benchmarks/ppo_peer.py --seed 14 --cpu-hours 3.1  # a peer's row (its default tracks: REPORT_TRACKS)
    python benchmarks/ppo_peer.py --seed 14 --curve           # its snapshots there (and --algo recurrent-ppo)
    python benchmarks/learning.py --protocol-report                        # learning_final.md alone, from the CSVs
"""

from __future__ import annotations

import os

import numpy as np

import ppo_peer
import readings
from common import (
    PROTOCOL_CPU_HOURS, RESULTS, TRACKS, checkpoint_updates, read_table, replace_rows, track_block, write_text,
)  # fmt: skip
from references import baselines
from runs import VARIANTS, cpu_hours_of, eval_curve, eval_summary, numerical_stop, run_of, training_hours

# --- The protocol ----------------------------------------------------------------------------
# Each run is a single-stage trial of benchmarks/experiment.py trained until it has spent PROTOCOL_CPU_HOURS of
# process CPU time (``--single-cpu-hours 3.1``, the PPO peers' budget); its final policy is its latest.pt then,
# whatever its updates, measured sampled and with its mean action on REPORT_TRACKS, which serve no choice.
PROTOCOL_SEEDS = (21, 22, 23, 24, 25)  # per variant
REPORT_TRACKS = TRACKS["report"]  # first seed and count of the report tracks
PROTOCOL_POLICIES = readings.POLICIES  # sampled (as trained) and the actor's mean
# The bar, per variant over its seeds. Mean action: mean return, every seed's return, mean progress, mean |steer|;
# sampled: mean return.
PROTOCOL_BAR_RETURN, PROTOCOL_BAR_SEED_RETURN, PROTOCOL_BAR_PROGRESS, PROTOCOL_BAR_STEER = 800.0, 650.0, 0.85, 0.3
PROTOCOL_BAR_SAMPLED_RETURN = 700.0
PROTOCOL_COLUMNS = (
    "variant", "seed", "updates", "env_steps", "cpu_hours", "wall_hours",
    "final_return", "final_progress", "final_mean_abs_steer",
    "mean_action_return", "mean_action_progress", "mean_action_abs_steer", "mean_action_laps_finished",
    "mean_speed", "best_eval_return", "last3_eval_return",
)  # fmt: skip
PROTOCOL_PEERS = ("ppo", "recurrent_ppo")  # benchmarks/ppo_peer.py's variants (--algo ppo, recurrent-ppo)
PROTOCOL_PEER_SEEDS = {"ppo": (11, 12, 13, 14, 15), "recurrent_ppo": (11, 12, 13)}
PEER_COLUMNS = tuple(c for c in ppo_peer.COLUMNS if c != "tracks")  # a peer's row (ppo_peer.py's), its tracks aside
PEER_POLICY_COLUMNS = ("final_return", "final_progress", "final_mean_abs_steer")  # its deterministic policy's driving
# Why a run drives as it does: benchmarks/readings.py's readings of its final policy on the report tracks, per policy,
# kept beside learning_final.csv (the driving from the row's own drives, not driven again; the training logs' last
# readings.SCREEN_WINDOW updates; the model on real episodes; its view of the pedal)
WHY_CSV = "learning_final_readings.csv"
# (without terminal_continue, which readings.py read after this table was made: the report's final policies that
# could give it are no longer all on disk, and a table with a column only some runs fill would mislead)
WHY_COLUMNS = tuple(c for c in readings.COLUMNS if c not in ("tag", "terminal_continue"))
OLD_PROTOCOL_HOME = os.path.join("benchmarks", "results", "history", "8000_updates")  # the replaced protocol's files
PROTOCOL_ADVICE = (
    f"move the old protocol's files (learning_final.csv, learning_final.md) to {OLD_PROTOCOL_HOME}/ first"
)
# The protocol this one replaced when both measure the same columns on the same tracks (the runs of another setting):
# its history folder under the results (<results>/history/<folder>/, where its learning_final.csv is kept) and its
# seeds; learning_final.md then compares the two (protocol_against_replaced). None: this protocol replaced no such one.
REPLACED_PROTOCOL: tuple[str, tuple[int, ...]] | None = None
REFERENCES_JSON = "references_report.json"  # random actions and the pure-pursuit driver on the report tracks
WHY_ADVICE = f"it holds other readings than {WHY_CSV}'s: move it aside first"


# --- A run's row of learning_final.csv --------------------------------------------------------
def protocol_peer_path(peer: str, results_dir: str = RESULTS, curve: bool = False) -> str:
    """The CSV of a peer's rows where ppo_peer.py keeps them (ppo_peer.results_path: its rows of the report tracks
    are read, read_peer_rows), or with `curve` its snapshots'."""
    return ppo_peer.results_path(peer, results_dir, curve)


def protocol_run(variant: str, seed: int, runs_dir: str) -> str:
    """The run directory of the protocol's trial of `variant` and `seed`: the latest run with a latest.pt under
    ``<runs_dir>/single_<variant>_seed<S>/`` (experiment.py's trial_dir, runs.run_of, ``runs_dir`` its
    ``<storage>/trials``)."""
    trial = os.path.join(runs_dir, f"single_{variant}_seed{seed}")
    run = run_of(trial)
    if run is None:
        raise ValueError(f"no run with checkpoints/latest.pt under {trial} (experiment.py --stages single "
                         f"--single-cpu-hours {PROTOCOL_CPU_HOURS} trains it)")  # fmt: skip
    return run


def protocol_cpu_hours(run: str, checkpoint: dict) -> float:
    """The CPU-hours the run of `checkpoint` (its latest.pt) has spent over all its sittings. A run short of
    PROTOCOL_CPU_HOURS is refused (ValueError naming the run, its CPU-hours and updates: no final policy yet),
    unless the scripts' non-finite guard stopped it (numerical_stop): every seed counts, so its last policy is its
    final one, and its row's CPU-hours show it stopped short (protocol_seeds says so)."""
    hours = cpu_hours_of(checkpoint)
    if hours < PROTOCOL_CPU_HOURS and not numerical_stop(checkpoint):
        updates = checkpoint_updates(checkpoint)
        raise ValueError(f"{run} has spent {hours:.2f} of its {PROTOCOL_CPU_HOURS} CPU-hours ({updates} updates): "
                         f"not a final policy yet")  # fmt: skip
    return hours


def protocol_measure(variant: str, seed: int, runs_dir: str) -> tuple[dict, dict]:
    """The final protocol's row of one run (PROTOCOL_COLUMNS), and the drives it was measured on (evaluate_checkpoint's
    per-track readings per policy, which protocol_readings reuses). The row: its latest.pt, refused unless the run has
    spent its CPU budget or the non-finite guard stopped it (protocol_cpu_hours), driven on the REPORT_TRACKS sampled
    (``final_*``) and with its mean action (``mean_action_*``), each a mean over the tracks of evaluate.py's readings;
    ``mean_action_laps_finished`` is the share of tracks whose lap the mean action finished within the time limit and
    ``mean_speed`` the mean action's mean speed. Beside them agent 0's updates, the env steps
    (``counters["global_step"]``), the CPU-hours of latest.pt, the wall hours of the sittings (training_hours), and the
    best and last-three-average returns of the run's own evaluations (eval_summary)."""
    if seed not in PROTOCOL_SEEDS:
        raise ValueError(f"the final protocol's seeds are {', '.join(map(str, PROTOCOL_SEEDS))}, got {seed}")
    run = protocol_run(variant, seed, runs_dir)
    latest = os.path.join(run, "checkpoints", "latest.pt")
    import evaluate
    from utils.checkpoint import read_checkpoint

    checkpoint = read_checkpoint(latest)[1]
    cpu_hours = protocol_cpu_hours(run, checkpoint)
    driven = evaluate.evaluate_checkpoint(latest, *REPORT_TRACKS, PROTOCOL_POLICIES)
    sampled, mean_action = (evaluate.track_means(driven[policy]) for policy in PROTOCOL_POLICIES)
    best_eval, last3_eval = eval_summary(eval_curve(run))
    row = {
        "variant": variant, "seed": seed, "updates": checkpoint_updates(checkpoint),
        "env_steps": int(checkpoint["counters"]["global_step"]), "cpu_hours": round(cpu_hours, 4),
        "wall_hours": training_hours(run),
        "final_return": round(sampled["return"], 2), "final_progress": round(sampled["progress"], 4),
        "final_mean_abs_steer": round(sampled["abs_steer"], 4),
        "mean_action_return": round(mean_action["return"], 2),
        "mean_action_progress": round(mean_action["progress"], 4),
        "mean_action_abs_steer": round(mean_action["abs_steer"], 4),
        "mean_action_laps_finished": round(mean_action["lap_finished"], 4),
        "mean_speed": round(mean_action["speed"], 2),
        "best_eval_return": best_eval, "last3_eval_return": last3_eval,
    }  # fmt: skip
    return row, driven


def protocol_readings(row: dict, driven: dict, runs_dir: str) -> list[dict]:
    """Why the run of `row` drives as it does (WHY_COLUMNS, one row per policy): readings.measure of its final
    policy on the REPORT_TRACKS, its driving from `driven` (protocol_measure's drives, not driven again), its
    training logs' last readings.SCREEN_WINDOW updates before the row's updates, its model on a sampled drive of the
    same tracks (calibration) and its view of the pedal. Costs another sampled drive and the model's imagination
    from every frame of it."""
    run = protocol_run(row["variant"], int(row["seed"]), runs_dir)
    latest = os.path.join(run, "checkpoints", "latest.pt")
    updates = int(row["updates"])
    measured = readings.measure(latest, run, updates, *REPORT_TRACKS, driven=driven)
    rows = [{"variant": row["variant"], "seed": int(row["seed"]), "updates": updates, "policy": policy,
             **measured[policy], "checkpoint": os.path.relpath(latest, runs_dir)}
            for policy in PROTOCOL_POLICIES]  # fmt: skip
    return [{column: r[column] for column in WHY_COLUMNS} for r in rows]


def write_protocol_row(row: dict, path: str = os.path.join(RESULTS, "learning_final.csv")) -> None:
    """Add a row of the final protocol to learning_final.csv, replacing an earlier row of the same variant and seed.
    A file with other columns (the 8,000-update protocol's) is refused (common.replace_rows)."""
    replace_rows(path, [row], PROTOCOL_COLUMNS, lambda r: (r["variant"], int(r["seed"])),
                 other_header=PROTOCOL_ADVICE)  # fmt: skip


def write_why_rows(rows: list[dict], path: str = os.path.join(RESULTS, WHY_CSV)) -> None:
    """Add a run's readings (protocol_readings: one row per policy) to learning_final_readings.csv, replacing its
    earlier ones. A file with other columns is refused (WHY_ADVICE)."""
    replace_rows(path, rows, WHY_COLUMNS, lambda r: (r["variant"], int(r["seed"]), r["policy"]),
                 other_header=WHY_ADVICE)  # fmt: skip


# --- learning_final.md -----------------------------------------------------------------------
# Its CSV's return, progress and |steer| of the final policy, by how it acts; the mean action first (the evaluation
# policy of docs/learning.md's rule), then sampled, as trained
PROTOCOL_POLICY_COLUMNS = {
    "mean-action": ("mean_action_return", "mean_action_progress", "mean_action_abs_steer"),
    "stochastic": ("final_return", "final_progress", "final_mean_abs_steer"),
}
POLICY_NAMES = {"mean-action": "mean action", "stochastic": "sampled"}
PEER_NAMES = {"ppo": "SB3 PPO", "recurrent_ppo": "RecurrentPPO"}
# Each part of the bar (protocol_bar's keys): what it says
PROTOCOL_BAR_PARTS = {
    "return": f"mean action: mean return >= {PROTOCOL_BAR_RETURN:g}",
    "every seed": f"mean action: every seed >= {PROTOCOL_BAR_SEED_RETURN:g}",
    "progress": f"mean action: mean progress >= {PROTOCOL_BAR_PROGRESS:g}",
    "steer": f"mean action: mean \\|steer\\| <= {PROTOCOL_BAR_STEER:g}",
    "sampled return": f"sampled: mean return >= {PROTOCOL_BAR_SAMPLED_RETURN:g}",
}
# The bar's values are means of CSV values of at most 4 decimals over the seeds: rounded to 6 decimals they are
# exact, and a mean exactly at a threshold meets it (np.mean of 702.91, 846.15, 905.62, 753.47, 791.85 is
# 799.9999999999999)
BAR_DECIMALS = 6


def column(rows: list[dict], key: str) -> np.ndarray:
    """Column `key` of CSV rows as floats."""
    return np.array([float(r[key]) for r in rows])


def protocol_bar(rows: list[dict]) -> dict[str, tuple[float, bool]]:
    """Each part of the final protocol's bar for the rows of one variant (its seeds): (its value, met). The mean
    action: mean return >= PROTOCOL_BAR_RETURN, every seed's >= PROTOCOL_BAR_SEED_RETURN (the value: the lowest),
    mean progress >= PROTOCOL_BAR_PROGRESS, mean |steer| <= PROTOCOL_BAR_STEER; sampled: mean return >=
    PROTOCOL_BAR_SAMPLED_RETURN. The bar reads the rows as learning_final.csv holds them (returns to 2 decimals,
    progress and |steer| to 4: protocol_measure), so anyone can judge it again from the file; each value is rounded
    to BAR_DECIMALS (what the CSV's values make exact)."""
    returns, progress, steer = (column(rows, key) for key in PROTOCOL_POLICY_COLUMNS["mean-action"])
    sampled = column(rows, PROTOCOL_POLICY_COLUMNS["stochastic"][0])
    values = {"return": returns.mean(), "every seed": returns.min(), "progress": progress.mean(),
              "steer": steer.mean(), "sampled return": sampled.mean()}  # fmt: skip
    values = {part: round(float(value), BAR_DECIMALS) for part, value in values.items()}
    met = {"return": values["return"] >= PROTOCOL_BAR_RETURN,
           "every seed": values["every seed"] >= PROTOCOL_BAR_SEED_RETURN,
           "progress": values["progress"] >= PROTOCOL_BAR_PROGRESS, "steer": values["steer"] <= PROTOCOL_BAR_STEER,
           "sampled return": values["sampled return"] >= PROTOCOL_BAR_SAMPLED_RETURN}  # fmt: skip
    return {part: (values[part], bool(met[part])) for part in PROTOCOL_BAR_PARTS}


def read_peer_rows(path: str, columns: tuple[str, ...] = PEER_COLUMNS) -> list[dict]:
    """A peer's rows (or with ppo_peer.CURVE_COLUMNS its curve's) measured on the report tracks (protocol_peer_path;
    none while its file does not exist): only runs measured on the same tracks are compared, and a row of other
    tracks is left out (ppo_peer.read_rows: a row without a ``tracks`` column was measured on 10100..10119). A file
    that lacks one of `columns`, or holds another peer's rows (``ppo_peer.py --results`` given the wrong file), is
    refused with a one-line ValueError naming it."""
    rows = ppo_peer.read_rows(path)
    missing = [c for c in columns if rows and c not in rows[0]]
    if missing:
        raise ValueError(f"{path} lacks the column(s) {', '.join(missing)} of a peer's row")
    peer = os.path.basename(path).split("_peer")[0]
    foreign = sorted({r["variant"] for r in rows if r["variant"] != peer})
    if foreign:
        raise ValueError(f"{path} holds rows of {', '.join(foreign)}, not only {peer}'s: move them to their own file")
    return [r for r in rows if r["tracks"] == track_block(*REPORT_TRACKS)]


PEER_CPU_OVERSHOOT = 0.1  # CPU-hours a peer's run may pass its budget by (it stops at the first check past it)


def peer_finished(row: dict) -> bool:
    """Whether a peer's row is the protocol's final policy, as ppo_peer.py ends a run: its CPU budget
    (PROTOCOL_CPU_HOURS, passed by at most PEER_CPU_OVERSHOOT) spent, or the zoo's step budget (n_timesteps,
    frame_skip env steps each) taken first. A row measured with --evaluate-only before either, or of a run given
    another --cpu-hours or --budget-steps, is not."""
    config = {variant: config for variant, config in ppo_peer.ALGOS.values()}[row["variant"]]
    steps, hours = config["n_timesteps"] * config["frame_skip"], float(row["cpu_hours"])
    if hours > PROTOCOL_CPU_HOURS + PEER_CPU_OVERSHOOT:
        return False
    return hours >= PROTOCOL_CPU_HOURS or int(row["env_steps"]) >= steps


def check_finite(rows: list[dict], keys: tuple[str, ...], what: str) -> None:
    """Refuse (a one-line ValueError naming the run) a row whose return, progress or |steer| is not a finite number:
    a measurement that failed, which no mean, test or bar may take in."""
    def finite(value) -> bool:
        try:
            return bool(np.isfinite(float(value)))
        except (TypeError, ValueError):  # an empty cell
            return False

    for r in rows:
        bad = [k for k in keys if not finite(r[k])]
        if bad:
            run = r["candidate"] if "candidate" in r else f"seed {r['seed']}"  # (ship.py's rows name theirs)
            run += f", snapshot {r['snapshot']}" if "snapshot" in r else ""  # (a curve's row)
            raise ValueError(f"{what}: {r['variant']} {run} has {', '.join(bad)} = "
                             f"{', '.join(repr(r[k]) for k in bad)}: measure it again")


def check_seeds(rows: list[dict], seeds: tuple[int, ...], what: str, per: tuple[str, ...] = ("seed",)) -> None:
    """Refuse (a one-line ValueError naming it) a row of a seed outside `seeds`, the protocol's (a run of another
    seed measured on the report tracks, as ``ppo_peer.py --seed 16`` writes by default), or a second row of one run
    (`per`: its seed, and its snapshot for a curve's rows): either would enter the statistics as a run of the
    protocol."""
    foreign = sorted({int(r["seed"]) for r in rows} - set(seeds))
    if foreign:
        raise ValueError(f"{what}: seed(s) {', '.join(map(str, foreign))} are not the protocol's "
                         f"({', '.join(map(str, seeds))}): move their rows to a file of their own")
    keys = [tuple(int(r[k]) for k in per) for r in rows]
    twice = sorted({key for key in keys if keys.count(key) > 1})
    if twice:
        names = "; ".join(", ".join(f"{k} {v}" for k, v in zip(per, key)) for key in twice)
        raise ValueError(f"{what}: more than one row for {names}: keep one per run")


def groups(rows: list[dict], peers: dict[str, list[dict]]) -> list[tuple[str, str, list[dict], tuple]]:
    """What the report describes over seeds: (name, policy, rows, their return, progress and |steer| columns) for
    each variant with rows, with each policy, then each peer with rows, with its deterministic policy."""
    out = [
        (variant, POLICY_NAMES[policy], mine, PROTOCOL_POLICY_COLUMNS[policy])
        for variant in VARIANTS if (mine := [r for r in rows if r["variant"] == variant])
        for policy in PROTOCOL_POLICY_COLUMNS
    ]  # fmt: skip
    return out + [(PEER_NAMES[peer], "deterministic", mine, PEER_POLICY_COLUMNS)
                  for peer, mine in peers.items() if mine]  # fmt: skip


def protocol_summary(rows: list[dict], peers: dict[str, list[dict]], reps: int = 2000) -> str:
    """Markdown: per variant and policy, and per peer, over its seeds: the mean of the final return with its Student
    t 95% interval and the IQM with rliable's stratified-bootstrap 95% interval (a description: a percentile
    bootstrap over so few seeds is too narrow; over 5 seeds the IQM is the mean of the middle 3, the mean counts
    every seed), the lowest seed, the mean progress and |steer|, and the mean action's share of tracks with a
    finished lap. A group of one run has no interval ("1 run")."""
    from stats import interval_estimates, t_interval

    described = groups(rows, peers)
    scores = {f"{name} {policy}": column(mine, keys[0])[:, None] for name, policy, mine, keys in described}
    estimates = interval_estimates(scores, reps=reps)

    def cell(point: float, interval: tuple[float, float], runs: int) -> str:
        return f"{point:.1f} (1 run)" if runs == 1 else f"{point:.1f} [{interval[0]:.1f}, {interval[1]:.1f}]"

    lines = [
        "| runs | policy | seeds | mean return [t 95%] | IQM return [95% bootstrap] | min seed | mean progress "
        "| mean \\|steer\\| | laps finished |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, policy, mine, (ret, progress, steer) in described:
        est, runs = estimates[f"{name} {policy}"], len(mine)
        mean, mean_ci = t_interval(column(mine, ret))
        laps = f"{column(mine, 'mean_action_laps_finished').mean():.2f}" if policy == "mean action" else ""
        lines.append(
            f"| {name} | {policy} | {runs} | {cell(mean, mean_ci, runs)} | {cell(est['iqm'], est['iqm_ci'], runs)} "
            f"| {column(mine, ret).min():.1f} | {column(mine, progress).mean():.2f} | {column(mine, steer).mean():.2f} "
            f"| {laps} |"
        )
    return "\n".join(lines) + "\n"


def protocol_references(results_dir: str) -> str:
    """Markdown: what random actions and the pure-pursuit driver at 70 score on the report tracks (references.py's
    baselines, driven once and then read from REFERENCES_JSON beside learning_final.csv)."""
    refs = baselines(*REPORT_TRACKS, results_dir=results_dir, filename=REFERENCES_JSON)
    random, pursuit = refs["random"], refs["pursuit@70"]
    return (f"On the same tracks random actions score {random['eval_return']:.1f} (progress "
            f"{random['eval_progress']:.2f}) and the pure-pursuit driver at speed 70 {pursuit['eval_return']:.1f} "
            f"(progress {pursuit['eval_progress']:.2f}; {REFERENCES_JSON}).\n")  # fmt: skip


def protocol_seeds(rows: list[dict], peers: dict[str, list[dict]]) -> str:
    """Markdown: every run's row, both policies side by side (the variants), then the peers' runs. A run short of
    PROTOCOL_CPU_HOURS says why: a Dreamer run was stopped by the non-finite guard (protocol_cpu_hours admits no
    other); a peer's is marked short of the budget (the zoo's step budget may have ended it first: it counts; or it
    was measured with --evaluate-only before its budget was spent: peer_finished leaves it out of the statistics)."""

    def policy(row: dict, keys: tuple) -> str:
        ret, progress, steer = (float(row[key]) for key in keys)
        return f"{ret:.1f} / {progress:.2f} / {steer:.2f}"

    def hours(row: dict, short: str) -> str:
        spent = float(row["cpu_hours"])
        return f"{spent:.2f}" + (f" ({short})" if spent < PROTOCOL_CPU_HOURS else "")

    lines = [
        "| variant | seed | updates | env steps | CPU-h | wall h | mean action: return / progress / \\|steer\\| "
        "| laps finished | mean speed | sampled: return / progress / \\|steer\\| | best / last-3 evaluations |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['variant']} | {r['seed']} | {r['updates']} | {r['env_steps']} | {hours(r, 'non-finite stop')} "
        f"| {float(r['wall_hours']):.2f} | {policy(r, PROTOCOL_POLICY_COLUMNS['mean-action'])} "
        f"| {float(r['mean_action_laps_finished']):.2f} | {float(r['mean_speed']):.1f} "
        f"| {policy(r, PROTOCOL_POLICY_COLUMNS['stochastic'])} "
        f"| {float(r['best_eval_return']):.1f} / {float(r['last3_eval_return']):.1f} |"
        for r in rows
    ]  # fmt: skip
    lines += [
        f"| {PEER_NAMES[peer]} | {r['seed']} | {r['updates']} | {r['env_steps']} | {hours(r, 'short of the budget')} | "
        f"| deterministic: {policy(r, PEER_POLICY_COLUMNS)} | | | | |"
        for peer, mine in peers.items() for r in mine
    ]  # fmt: skip
    return "\n".join(lines) + "\n"


def missing_seeds(rows: list[dict], seeds: tuple[int, ...]) -> list[int]:
    """The `seeds` that no row of `rows` (one variant's or one peer's) has, in order."""
    return sorted(set(seeds) - {int(r["seed"]) for r in rows})


def protocol_bar_table(rows: list[dict]) -> str:
    """Markdown: per variant each part of the bar (protocol_bar), its value and whether it is met, and the verdict;
    a variant without all of PROTOCOL_SEEDS is provisional."""
    lines = [
        "| variant | seeds | " + " | ".join(PROTOCOL_BAR_PARTS.values()) + " | bar |",
        "|---|---|" + "---|" * len(PROTOCOL_BAR_PARTS) + "---|",
    ]
    for variant in VARIANTS:
        mine = [r for r in rows if r["variant"] == variant]
        if not mine:
            continue
        parts = protocol_bar(mine)
        # (shown whole, so that a value never reads as its threshold when it misses it: 799.996, not 800.00)
        cells = [f"{value:.10g} {'met' if met else 'not met'}" for value, met in parts.values()]
        failed = [part for part, (_, met) in parts.items() if not met]
        verdict = "met" if not failed else "not met: " + ", ".join(failed)
        missing = missing_seeds(mine, PROTOCOL_SEEDS)
        if missing:
            verdict += f" (provisional: seeds {', '.join(map(str, missing))} missing)"
        lines.append(f"| {variant} | {len(mine)} | " + " | ".join(cells) + f" | {verdict} |")
    return "\n".join(lines) + "\n"


# learning_final.md's readings: (label, column of learning_final_readings.csv, the policy row it is read from: a
# run's training and model readings stand in both of its rows)
WHY_TABLE = (
    (f"actor sigma (last {readings.SCREEN_WINDOW} updates)", "actor_sigma", "stochastic"),
    ("entropy weight alpha", "alpha", "stochastic"),
    ("imagined lambda-return (with the entropy bonus)", "imagined_return", "stochastic"),
    *((f"{POLICY_NAMES[policy]}: {label}", key, policy) for policy in PROTOCOL_POLICIES[::-1] for label, key in (
        ("speed", "speed"), ("gas", "gas"), ("brake-command share", "brake_share"), ("laps finished", "lap_finished"),
        ("eliminated", "eliminated"))),
    ("model on sampled drives: imagined H-step return", "imagined_task_return", "stochastic"),
    ("... the real H-step return from the same states", "real_task_return", "stochastic"),
    ("... eliminations in those drives", "eliminations", "stochastic"),
    ("... reward head's mean on their last frame (real: -100)", "terminal_reward_predicted", "stochastic"),
    ("pedal: range of the imagined return over held pedals", "pedal_range_imagined", "mean-action"),
    ("... of the real return", "pedal_range_real", "mean-action"),
)  # fmt: skip


def protocol_why(why_rows: list[dict]) -> str:
    """Markdown: per reading of WHY_TABLE, per variant with readings, its mean over the seeds and in brackets the
    lowest and highest seed's (NaNs, readings a run could not take, left out and the seeds that have it counted;
    "-" if none); under it, each variant's H (the H-step returns and the pedal ranges are over H decisions of its
    own: the two variants' are not comparable with each other)."""
    import importlib

    variants = [v for v in VARIANTS if any(r["variant"] == v for r in why_rows)]
    seeds = {v: len({r["seed"] for r in why_rows if r["variant"] == v}) for v in variants}
    lines = ["| reading | " + " | ".join(f"{v} ({n} seed{'s' * (n > 1)})" for v, n in seeds.items()) + " |",
             "|---|" + "---|" * len(variants)]  # fmt: skip
    for label, key, policy in WHY_TABLE:
        cells = []
        for variant in variants:
            values = column([r for r in why_rows if r["variant"] == variant and r["policy"] == policy], key)
            values = values[~np.isnan(values)]
            cell = f"{values.mean():.2f} [{values.min():.2f}, {values.max():.2f}]" if values.size else "-"
            if 0 < values.size < seeds[variant]:
                cell += f" ({values.size} of {seeds[variant]} seeds)"
            cells.append(cell)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    scripts = {v: importlib.import_module(f"dreamer_{v}") for v in variants}
    cpu = {v: script.preset_args("cpu") for v, script in scripts.items()}
    horizons = ", ".join(f"{v} {a.imagination_horizon} decisions of {a.action_repeat} env steps"
                         for v, a in cpu.items())  # fmt: skip
    brake = {f"{a.brake_speed_threshold:g}" for a in cpu.values()}
    lines += ["", f"H is each variant's imagination horizon ({horizons}): the H-step returns and pedal ranges are not "
                  f"comparable across the variants. Speed is read at the end of each decision; a brake command (a "
                  f"pedal at or below the dead zone's edge) brakes only above speed {'/'.join(sorted(brake))}."]
    return "\n".join(lines) + "\n"


COMPARISONS_TEXT = (
    "\nThe comparisons (independent runs): the first beats the second when the exact permutation test's one-sided p "
    "that it is higher is below 0.05 and Welch's t 95% interval of the difference lies above 0; it is behind when "
    "the same holds the other way; otherwise no detectable difference. Each comparison is judged at 0.05 on its own "
    "(the protocol names no correction for their number).\n\n"
)


def provisional_note(rows: list[dict], peers: dict[str, list[dict]]) -> str:
    """Markdown: which comparisons are provisional, a side lacking some of its seeds (a variant's PROTOCOL_SEEDS, a
    peer's PROTOCOL_PEER_SEEDS among its finished rows); "" when none is."""
    missing = {v: missing_seeds([r for r in rows if r["variant"] == v], PROTOCOL_SEEDS) for v in VARIANTS}
    missing |= {PEER_NAMES[p]: missing_seeds(peers.get(p, []), seeds) for p, seeds in PROTOCOL_PEER_SEEDS.items()}
    short = [f"{name} lacks seeds {', '.join(map(str, seeds))}" for name, seeds in missing.items() if seeds]
    return f"\nProvisional: {'; '.join(short)}.\n" if short else ""


def comparison_verdict(claim: dict, words: tuple[str, str] = ("beats", "behind")) -> str:
    """The final protocol's word for a comparison (stats.two_group_claim's outcome): `words`' first ("beats") when
    the first is higher by both the exact test (p < 0.05) and Welch's interval (above 0), its second ("behind") when
    it is lower by both, else "no detectable difference" (or too few runs to judge)."""
    said = {"supported": words[0], "contradicted": words[1], "too few runs": claim["verdict"]}
    return said.get(claim["outcome"], "no detectable difference")


def comparison_table(sides: list[tuple[str, np.ndarray, np.ndarray, bool]],
                     words: tuple[str, str] = ("beats", "behind")) -> str:
    """Markdown: one row per comparison (name, the first side's returns, the second's, provisional) over
    independent runs: the difference of the means, Welch's t 95% interval, the exact permutation test's one-sided p
    that the first is higher and that it is lower, and the verdict (comparison_verdict with `words`: the exact test
    and the t interval, never a bootstrap, judge so few runs), marked provisional when a side lacks some of its
    seeds. A comparison a side of which has no run is left out."""
    from stats import two_group_claim

    lines = ["| comparison | runs | difference of means | Welch t 95% | permutation p: higher / lower | verdict |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for name, x, y, provisional in sides:
        if x.size and y.size:
            claim = two_group_claim(x, y)
            low, high = claim["ci"]
            interval = "none (a side has one run)" if np.isnan(low) else f"[{low:+.1f}, {high:+.1f}]"
            verdict = comparison_verdict(claim, words) + (" (provisional: seeds missing)" if provisional else "")
            lines.append(f"| {name} | {claim['sizes']} | {claim['estimate']:+.1f} | {interval} "
                         f"| {claim['p']:.3f} / {claim['p_opposite']:.3f} | {verdict} |")
    return "\n".join(lines) + "\n"


def protocol_comparisons(rows: list[dict], peers: dict[str, list[dict]]) -> str:
    """Markdown (comparison_table): the LSTM minus the GRU with each policy, and each variant with each policy minus
    each peer (its deterministic policy), over independent runs, judged "beats" / "behind" / "no detectable
    difference", provisional while a side lacks some of its seeds (provisional_note)."""
    mine = {variant: [r for r in rows if r["variant"] == variant] for variant in VARIANTS}
    short = {variant: bool(missing_seeds(mine[variant], PROTOCOL_SEEDS)) for variant in VARIANTS}
    short |= {peer: bool(missing_seeds(theirs, PROTOCOL_PEER_SEEDS[peer])) for peer, theirs in peers.items()}
    returns = {(variant, p): column(mine[variant], keys[0])
               for variant in VARIANTS for p, keys in PROTOCOL_POLICY_COLUMNS.items()}  # fmt: skip
    sides = [(f"{POLICY_NAMES[p]}: LSTM - GRU", returns["lstm", p], returns["gru", p], short["lstm"] or short["gru"])
             for p in PROTOCOL_POLICY_COLUMNS]  # fmt: skip
    sides += [
        (f"{POLICY_NAMES[p]}: {variant} - {PEER_NAMES[peer]}", returns[variant, p], column(theirs, "final_return"),
         short[variant] or short[peer])
        for variant in VARIANTS for p in PROTOCOL_POLICY_COLUMNS for peer, theirs in peers.items()
    ]  # fmt: skip
    return comparison_table(sides)


def replaced_path(results_dir: str) -> str:
    """Where the replaced protocol's learning_final.csv is kept (REPLACED_PROTOCOL's history folder)."""
    return os.path.join(results_dir, "history", REPLACED_PROTOCOL[0], "learning_final.csv")


def protocol_against_replaced(rows: list[dict], results_dir: str) -> str:
    """Markdown: per variant and policy, this protocol's final return minus the replaced protocol's (REPLACED_PROTOCOL,
    its rows read from replaced_path: refused, naming the file, if a value is not finite or a seed is not its own or
    counted twice), over independent runs (comparison_table), judged "higher" / "lower" / "no detectable
    difference"; provisional while either protocol lacks seeds. Without the file, a line saying so."""
    seeds, path = REPLACED_PROTOCOL[1], replaced_path(results_dir)
    name = os.path.relpath(path, results_dir)
    if not os.path.exists(path):
        return f"\nThe protocol this one replaced: no {name} here, no comparison.\n"
    before = read_table(path, PROTOCOL_COLUMNS, "not a final protocol's learning_final.csv")
    check_finite(before, PROTOCOL_POLICY_COLUMNS["mean-action"] + PROTOCOL_POLICY_COLUMNS["stochastic"], name)
    sides = []
    for variant in VARIANTS:
        now, then = ([r for r in table if r["variant"] == variant] for table in (rows, before))
        check_seeds(then, seeds, f"{name} ({variant})")
        short = bool(missing_seeds(now, PROTOCOL_SEEDS) or missing_seeds(then, seeds))
        sides += [(f"{POLICY_NAMES[p]}: {variant}", column(now, keys[0]), column(then, keys[0]), short)
                  for p, keys in PROTOCOL_POLICY_COLUMNS.items()]  # fmt: skip
    return (
        f"\nAgainst the protocol this one replaced ({name}: seeds {', '.join(map(str, seeds))}), per variant and "
        f"policy: this protocol's final return minus that one's, higher or lower by the same two tests:\n\n"
        + comparison_table(sides, ("higher", "lower"))
    )  # fmt: skip


def steps_label(steps: int) -> str:
    """Env steps as the snapshots are named: 50k, 1M (else the number)."""
    if steps % 1_000_000 == 0:
        return f"{steps // 1_000_000}M"
    return f"{steps // 1000}k" if steps % 1000 == 0 else f"{steps:,}"


def curve_means(curve: list[dict]) -> dict[int, tuple[float, int]]:
    """A peer's curve (its rows of ``<peer>_peer_curve.csv`` on the report tracks) per snapshot (the N of
    model_<N>.zip), in order: the mean return of its deterministic policy over the seeds that have that snapshot,
    and their number."""
    snapshots = sorted({int(r["snapshot"]) for r in curve})
    returns = {n: column([r for r in curve if int(r["snapshot"]) == n], "return") for n in snapshots}
    return {n: (float(x.mean()), x.size) for n, x in returns.items()}


def reached_at(
    means: dict[int, tuple[float, int]], target: float, seeds: int, final: tuple[float, float, int] | None = None
) -> str:
    """The first snapshot whose mean return (curve_means) reaches `target`, with how many of the peer's `seeds` that
    mean is over, or "not within" the last one, with how many seeds that one's mean is over; then, if `final` (the
    mean return, mean env steps and number of the peer's final policies) reaches it, that they do."""
    def reaches(mean: float) -> bool:
        return round(mean, BAR_DECIMALS) >= round(target, BAR_DECIMALS)

    reached = [n for n, (mean, _) in means.items() if reaches(mean)]
    if reached:
        return f"{steps_label(reached[0])} ({means[reached[0]][1]} of {seeds} seeds)"
    text = f"not within {steps_label(max(means))} ({means[max(means)][1]} of {seeds} seeds)"
    if final is not None and reaches(final[0]):
        text += f"; its final policies do ({final[1] / 1e6:.1f}M env steps, {final[2]} seed{'s' * (final[2] > 1)})"
    return text


def sample_efficiency(rows: list[dict], curves: dict[str, list[dict]], peers: dict[str, list[dict]]) -> str:
    """Markdown: for each variant and policy, its final mean return and mean env steps over its seeds, and the
    snapshot after which each peer's mean return (curve_means: over the seeds that have it) first reaches that
    return (reached_at, out of the peer's seeds: those with a final row or a curve), else, when its final policies
    (`peers`: the finished rows) reach it, that they do; then, per peer with a curve, its snapshots' means and its
    final policies' mean return and env steps. "" while no peer has a curve."""
    means = {peer: curve_means(curve) for peer, curve in curves.items() if curve}
    seeds = {peer: len({int(r["seed"]) for r in curve + peers.get(peer, [])})
             for peer, curve in curves.items() if curve}  # fmt: skip
    finals = {peer: (column(theirs, "final_return").mean(), column(theirs, "env_steps").mean(), len(theirs))
              for peer, theirs in peers.items() if theirs}  # fmt: skip
    if not means:
        return ""
    lines = [
        "\nSample efficiency: the peers' snapshots (model_<N>.zip, the weights that took their N-th env step; of a run "
        "of the same seed and code where the reported run's were lost, as docs/learning.md says), their "
        "deterministic policy on the same report tracks, against the Dreamer's final mean return over its seeds. A "
        "peer reaches it at the first N whose mean return over the seeds that have that snapshot is at least as "
        "high; where none does, \"its final policies do\" follows if the peer's final policies (the last column) "
        "reach it.\n",
        "| Dreamer | its policy | its final mean return | its mean env steps | "
        + " | ".join(f"{PEER_NAMES[peer]} snapshots reach it at" for peer in means) + " |",
        "|---|---|---|---|" + "---|" * len(means),
    ]
    for variant in VARIANTS:
        mine = [r for r in rows if r["variant"] == variant]
        if not mine:
            continue
        steps = column(mine, "env_steps").mean()
        for policy, keys in PROTOCOL_POLICY_COLUMNS.items():
            target = column(mine, keys[0]).mean()
            lines.append(f"| {variant} | {POLICY_NAMES[policy]} | {target:.1f} | {steps:,.0f} | "
                         + " | ".join(reached_at(curve, target, seeds[peer], finals.get(peer))
                                      for peer, curve in means.items())
                         + " |")  # fmt: skip
    snapshots = sorted({n for curve in means.values() for n in curve})
    lines += ["", "| peer snapshot: mean return (seeds) | " + " | ".join(map(steps_label, snapshots))
              + f" | final policies ({PROTOCOL_CPU_HOURS:g} CPU-hours): mean return (seeds), mean env steps |",
              "|---|" + "---|" * (len(snapshots) + 1)]  # fmt: skip
    lines += [
        f"| {PEER_NAMES[peer]} | "
        + " | ".join(f"{curve[n][0]:.1f} ({curve[n][1]})" if n in curve else "" for n in snapshots)
        + (f" | {finals[peer][0]:.1f} ({finals[peer][2]}), {finals[peer][1]:,.0f} |" if peer in finals else " |  |")
        for peer, curve in means.items()
    ]  # fmt: skip
    return "\n".join(lines) + "\n"


def figure_data(rows: list[dict], peers: dict[str, list[dict]], curves: dict[str, list[dict]]) -> dict:
    """What learning_final.png draws. ``finals``: per group (groups: each variant with each policy, then each peer)
    its final returns over seeds, and their mean with Student's t 95% interval (stats.t_interval: with 5 seeds a
    side no bootstrap). ``steps``: per group its mean env steps and mean return; per peer with a curve its
    snapshots' (N, mean return) (curve_means)."""
    from stats import t_interval

    finals, steps = {}, {}
    for name, policy, mine, keys in groups(rows, peers):
        returns = column(mine, keys[0])
        mean, ci = t_interval(returns)  # (one seed: no interval)
        label = f"{name.upper() if name in VARIANTS else name}, {policy}"
        finals[label] = {"returns": returns.tolist(), "mean": float(mean), "ci": tuple(map(float, ci))}
        steps[label] = (float(column(mine, "env_steps").mean()), float(returns.mean()))
    snapshots = {PEER_NAMES[peer]: [(n, m) for n, (m, _) in curve_means(curve).items()]
                 for peer, curve in curves.items() if curve}  # fmt: skip
    return {"finals": finals, "steps": steps, "snapshots": snapshots}


def plot_protocol(data: dict, path: str) -> None:
    """learning_final.png: left, every group's final returns (a dot per seed) with their mean and t interval and the
    bar's lines; right, return against env steps (log): each group's mean at its mean env steps, the peers'
    snapshots as curves."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(14, 4.5))
    labels = list(data["finals"])
    for y, label in enumerate(labels):
        final = data["finals"][label]
        left.scatter(final["returns"], [y] * len(final["returns"]), color="gray", alpha=0.6, s=18)
        if np.all(np.isfinite(final["ci"])):
            left.plot(final["ci"], [y, y], color="black", linewidth=2)
        left.scatter([final["mean"]], [y], color="black", marker="|", s=300)
    left.axvline(PROTOCOL_BAR_RETURN, color="red", linestyle="-.", alpha=0.6, label="bar: mean action mean")
    left.axvline(PROTOCOL_BAR_SAMPLED_RETURN, color="orange", linestyle=":", label="bar: sampled mean")
    left.set_yticks(range(len(labels)), labels)
    left.invert_yaxis()
    left.set_xlabel(f"final return, tracks {track_block(*REPORT_TRACKS)} (dots: seeds; mean, t 95% CI)")
    left.grid(alpha=0.3, axis="x")
    left.legend(fontsize="small", loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2, frameon=False)  # above
    for k, (peer, points) in enumerate(data["snapshots"].items()):
        right.plot(*zip(*points), marker="o", color=f"C{k}", label=f"{peer} snapshots (deterministic)")
    for k, (label, (env_steps, mean)) in enumerate(data["steps"].items(), start=len(PROTOCOL_PEERS)):
        right.scatter([env_steps], [mean], marker="*", s=120, color=f"C{k}", label=f"{label} (final)")
    right.set_xscale("log")
    right.set_xlabel(f"env steps (log; finals at {PROTOCOL_CPU_HOURS:g} CPU-hours, snapshots along the peers' runs)")
    right.set_ylabel("mean return over seeds")
    right.grid(alpha=0.3)
    right.legend(fontsize="x-small", loc="best")  # (where it hides the fewest points)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_protocol_report(results_dir: str = RESULTS, reps: int = 2000) -> str:
    """(Re)write learning_final.md from the final protocol's learning_final.csv (refused if it holds the old
    protocol's columns) and its peers' rows and snapshots on the report tracks (``<peer>_peer.csv`` and
    ``<peer>_peer_curve.csv``, when present): the mean and IQM per variant and policy and per peer, the references
    on the same tracks (protocol_references: driven the first time), the bar, every
    run's row, the comparisons, the peers' sample efficiency, the comparison with the protocol this one replaced
    (protocol_against_replaced, when REPLACED_PROTOCOL names one) and, when learning_final_readings.csv is there, the
    readings per variant (protocol_why); and its figure, learning_final.png (plot_protocol).
    Returns the text."""
    rows = read_table(os.path.join(results_dir, "learning_final.csv"), PROTOCOL_COLUMNS, PROTOCOL_ADVICE)
    measured = {peer: read_peer_rows(protocol_peer_path(peer, results_dir)) for peer in PROTOCOL_PEERS}
    measured = {peer: theirs for peer, theirs in measured.items() if theirs}
    check_finite(rows, PROTOCOL_POLICY_COLUMNS["mean-action"] + PROTOCOL_POLICY_COLUMNS["stochastic"],
                 "learning_final.csv")
    for variant in VARIANTS:
        check_seeds([r for r in rows if r["variant"] == variant], PROTOCOL_SEEDS, f"learning_final.csv ({variant})")
    for peer, theirs in measured.items():
        check_finite(theirs, PEER_POLICY_COLUMNS, f"{peer}_peer.csv")
        check_seeds(theirs, PROTOCOL_PEER_SEEDS[peer], f"{peer}_peer.csv")
    # a peer's row that is not the protocol's final policy (peer_finished) is listed, not compared
    peers = {peer: [r for r in theirs if peer_finished(r)] for peer, theirs in measured.items()}
    unfinished = [f"{PEER_NAMES[peer]} seed {r['seed']} ({float(r['cpu_hours']):.2f} CPU-h, {r['env_steps']} env "
                  f"steps)" for peer, theirs in measured.items() for r in theirs if not peer_finished(r)]
    curves = {peer: read_peer_rows(protocol_peer_path(peer, results_dir, curve=True), ppo_peer.CURVE_COLUMNS)
              for peer in PROTOCOL_PEERS}  # fmt: skip
    for peer, curve in curves.items():
        check_finite(curve, ("return",), f"{peer}_peer_curve.csv")
        check_seeds(curve, PROTOCOL_PEER_SEEDS[peer], f"{peer}_peer_curve.csv", per=("seed", "snapshot"))
    header = (
        f"# The final protocol (CPU budget)\n\nEach run trained until it had spent {PROTOCOL_CPU_HOURS:g} CPU-hours "
        f"of process CPU time; its final policy (latest.pt then) drove the {REPORT_TRACKS[1]} report tracks "
        f"{track_block(*REPORT_TRACKS)} sampled and with its mean action. The peers (benchmarks/ppo_peer.py, their "
        f"deterministic policy) had the same CPU time and tracks. Means over seeds carry their Student t 95% "
        f"intervals; IQMs rliable's stratified-bootstrap 95% intervals, which describe: over 5 seeds a percentile "
        f"bootstrap is too narrow to judge. The comparisons are judged by the exact permutation test and Welch's t "
        f"interval (benchmarks/stats.py).\n\n"
    )
    if not rows:
        text = header + "No run measured yet.\n"
    else:
        plot_protocol(figure_data(rows, peers, curves), os.path.join(results_dir, "learning_final.png"))
        text = (
            header + protocol_summary(rows, peers, reps) + "\n" + protocol_references(results_dir)
            + "\nThe bar, per variant over its seeds:\n\n"
            + protocol_bar_table(rows) + "\nEvery run:\n\n" + protocol_seeds(rows, measured)
            + (f"\nNot the protocol's final policy (peer_finished), left out of the statistics: "
               f"{'; '.join(unfinished)}.\n" if unfinished else "")
            + COMPARISONS_TEXT + protocol_comparisons(rows, peers) + provisional_note(rows, peers)
            + sample_efficiency(rows, curves, peers)
            + (protocol_against_replaced(rows, results_dir) if REPLACED_PROTOCOL else "")
        )  # fmt: skip
        why_rows = read_table(os.path.join(results_dir, WHY_CSV), WHY_COLUMNS, WHY_ADVICE)
        if why_rows:
            text += (
                f"\nWhy they drive as they do: benchmarks/readings.py's readings of the same final policies on the "
                f"same tracks ({WHY_CSV}), the mean over seeds [lowest, highest]:\n\n" + protocol_why(why_rows)
            )  # fmt: skip
    write_text(os.path.join(results_dir, "learning_final.md"), text)
    return text
