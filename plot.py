"""Paper-style figures from the TensorBoard logs of several runs and seeds.

    python plot.py runs/ --out figures/ --sigma 2
    python plot.py runs/experiment/trials --out figures/ --head-to-head benchmarks/results/head_to_head*.csv
    python plot.py --help    # every option and its default

Options: LOGDIR (positional), ``--out`` (default ``figures``), ``--sigma`` (default 2.0), ``--head-to-head CSV
[CSV ...]`` (several CSVs after one flag, so a shell glob works). Bad input (no such LOGDIR, no event files under
it, a missing or malformed CSV, a negative or non-finite ``--sigma``, an ``--out`` that is a file) ends with one
line naming it (status 2 for an option, 1 for logs or a CSV that cannot be read); a value that does not parse at
all (``--sigma abc``) gets tyro's own message, naming the option.

Every run directory under ``runs/`` holding a TensorBoard event file is one seed of one
group. A run's group is ``(variant, stage)``, read from the ``config.json`` the dreamer
scripts write beside their logs (``variant``, ``stage``, ``seed``), or else parsed from the
CleanRL run name ``{env_id}__{exp_name}__{seed}__{time}``. Per-agent tags
(``car_0/charts/episodic_return``) are pooled over the agents of a run.

Each curve is smoothed with a Gaussian filter (``--sigma`` in logged points, scipy's
``gaussian_filter1d``), resampled onto a common x grid, and drawn as the mean across seeds
(and agents) with a band of one standard deviation, each seed's own curve drawn thin beside it (also where
it runs longer than the others). Figures (one PNG each):

* ``single_agent_return.png``  - stage ``single``: episodic return
* ``multi_agent_return.png``   - stage ``race``: episodic return
* ``multi_agent_win_rate.png`` - stage ``race``: win rate
* ``ghost_return.png``         - stage ``ghost`` and its control (a ``single`` run continued from a checkpoint,
  ``single-continued``): the training races' return (when present). Not comparable between the two: racing its
  ghost, a car that follows it is paid the follower's half of each tile the ghost reached first
* ``ghost_eval_return.png``    - the same two: the evaluation on the held-out tracks, each car alone, comparable
* ``single_agent_eval_{return,progress}.png`` - stage ``single``: the evaluation on the held-out tracks
  (the dreamer scripts' ``--eval-policy``: the mean action by default, sampled in runs begun before; when
  logged)
* a figure above whose runs are counted in env steps (the dreamer scripts) and in races (``race.py --train``)
  is drawn once for each: the races one is ``<name>_races.png``
* ``losses.png``               - actor, critic, reconstruction, KL (dyn) for every group against steps
* ``losses_race.png``          - the same for ``race.py --train`` runs, against races
* ``head_to_head.png``         - with ``--head-to-head CSV [CSV ...]``: the tournaments of
  ``benchmarks/experiment.py``, one figure per CSV named after it (``head_to_head_stochastic.csv``: the same
  tournaments raced with the sampled policy, ``head_to_head_stochastic.png``)

A ``race.py --train`` run (tags ``racer_<i>_<variant>/...``) counts as one run per variant of its racers, drawn
against the race count it logs (``charts/race``); its later sittings (the experiment's intervals of races) join
it end to end. (Its ``charts/win_rate`` is over the last 20 races of the sitting, so it restarts with each one;
the tournaments' figure is the measured win rate.)
"""

from __future__ import annotations

import dataclasses
import glob
import json
import math
import os
import re
import sys
from typing import Annotated

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import tyro  # noqa: E402
from scipy.ndimage import gaussian_filter1d  # noqa: E402
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: E402

import utils.run as run_tools  # noqa: E402

VARIANTS = ("lstm", "gru")
STAGES = ("single", "ghost", "race")
AGENT_PREFIX = re.compile(r"^car_\d+/")
GRID_POINTS = 200
FIGURES = {
    "single_agent_return.png": ("single", "charts/episodic_return", "episodic return"),
    "multi_agent_return.png": ("race", "charts/episodic_return", "episodic return"),
    "multi_agent_win_rate.png": ("race", "charts/win_rate", "win rate"),
    "ghost_return.png": (
        ("ghost", "single-continued"), "charts/episodic_return", "training return (tiles the ghost took pay half)"
    ),
    "ghost_eval_return.png": (
        ("ghost", "single-continued"), "eval/episodic_return", "evaluation return (held-out tracks, alone)"
    ),
    "single_agent_eval_return.png": ("single", "eval/episodic_return", "evaluation return (held-out tracks)"),
    "single_agent_eval_progress.png": ("single", "eval/progress", "evaluation progress (held-out tracks)"),
}
LOSSES = ("losses/actor", "losses/critic", "losses/reconstruction", "losses/kl_dyn")


@dataclasses.dataclass
class Args:
    logdir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="LOGDIR")]
    """directory holding run directories, searched recursively for TensorBoard event files (e.g. runs/)"""
    out: str = "figures"
    """directory the PNGs go to (made if missing)"""
    sigma: float = 2.0
    """Gaussian smoothing of each curve, in logged points (0: none)"""
    head_to_head: Annotated[tuple[str, ...] | None, tyro.conf.arg(metavar="CSV [CSV ...]")] = None
    """also the tournaments' figure from each of benchmarks/experiment.py's head_to_head CSVs (one or more, after
    one flag), named after its CSV"""


RACER_PREFIX = re.compile(r"^racer_\d+_([A-Za-z0-9]+)/")  # race.py --train: racer_<i>_<variant>/...
RACE_COUNT = "charts/race"  # race.py --train: the races each learning racer has run, over every sitting


@dataclasses.dataclass
class Run:
    path: str
    variant: str
    stage: str
    seed: int
    scalars: dict[str, list[tuple[np.ndarray, np.ndarray]]]  # tag -> one (x, values) per agent
    x_label: str = "step"

    @property
    def group(self) -> tuple[str, str]:
        return self.variant, self.stage


def run_identity(run_dir: str) -> tuple[str, str, int]:
    """(variant, stage, seed) of a run: its config.json, else its CleanRL run name."""
    config_path = os.path.join(run_dir, "config.json")
    if os.path.exists(config_path):
        try:
            with open(config_path) as f:
                config = json.load(f)
            stage = str(config["stage"])
            if stage == "single" and config.get("checkpoint"):  # continued from a saved agent (e.g. a control)
                stage = "single-continued"
            return str(config["variant"]), stage, int(config["seed"])
        except KeyError as e:
            raise ValueError(f"{config_path} lacks {e.args[0]!r} (needs variant, stage, seed)") from None
        except (ValueError, TypeError, OSError) as e:  # not JSON, not an object, a seed that is no integer
            reason = (str(e).strip().splitlines() or [type(e).__name__])[0]
            raise ValueError(f"{config_path}: not a readable run config: {reason}") from None
    parts = os.path.basename(os.path.normpath(run_dir)).split("__")
    if len(parts) < 3 or not parts[2].lstrip("-").isdigit():
        raise ValueError(f"{run_dir}: no config.json and not a run name env__exp__seed__time")
    exp_name, seed = parts[1], parts[2]
    variant = next((v for v in VARIANTS if v in exp_name), exp_name)
    stage = next((s for s in STAGES if s in exp_name), "single")
    return variant, stage, int(seed)


def read_scalars(run_dir: str) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """All scalars of the event files of one run, per-agent prefixes pooled by tag."""
    acc = EventAccumulator(run_dir, size_guidance={"scalars": 0})
    acc.Reload()
    scalars: dict[str, list] = {}
    for tag in acc.Tags()["scalars"]:
        events = acc.Scalars(tag)
        steps = np.array([e.step for e in events], dtype=np.float64)
        values = np.array([e.value for e in events], dtype=np.float64)
        order = np.argsort(steps, kind="stable")
        scalars.setdefault(AGENT_PREFIX.sub("", tag), []).append((steps[order], values[order]))
    return scalars


def racer_runs(path: str, stage: str, seed: int, scalars: dict) -> list[Run]:
    """A race.py --train run as one Run per variant of its racers (``racer_<i>_<variant>/`` tags, the prefix
    removed), each against the race count: the x of a point is the race after which it was logged."""
    count = scalars.get(RACE_COUNT)
    races = dict(zip(*count[0])) if count else {}
    by_variant: dict[str, dict] = {}
    for tag, curves in scalars.items():
        match = RACER_PREFIX.match(tag)
        if match is None:
            continue
        for steps, values in curves:
            keep = np.array([s in races for s in steps], dtype=bool) if races else np.ones(len(steps), dtype=bool)
            x = np.array([races[s] for s in steps[keep]]) if races else steps
            by_variant.setdefault(match.group(1), {}).setdefault(RACER_PREFIX.sub("", tag), []).append(
                (x, values[keep])
            )
    label = "races" if races else "step"
    return [Run(path, variant, stage, seed, tags, label) for variant, tags in sorted(by_variant.items())]


def join_sittings(runs: list[Run]) -> list[Run]:
    """Runs counted in races with the same (variant, stage, seed) where one starts at the race after the other's
    last are sittings of one run (race.py --train continued from the checkpoints of the last): one Run whose curves
    are theirs end to end (the i-th curve of a tag, one per racer of the variant, joined with the i-th curve of the
    next sitting). Runs whose races do not follow on stay apart (e.g. two runs of the same seed)."""

    def races(run: Run) -> tuple[float, float]:
        xs = [x for curves in run.scalars.values() for x, _ in curves if len(x)]
        return (min(x[0] for x in xs), max(x[-1] for x in xs)) if xs else (0.0, 0.0)

    out, chains = [], []  # chains: (key, [sittings]), in the order they start
    for run in sorted(runs, key=lambda r: races(r)[0]):
        if run.x_label != "races":
            out.append(run)
            continue
        key = (run.variant, run.stage, run.seed)
        chain = next((c for k, c in chains if k == key and races(c[-1])[1] + 1 == races(run)[0]), None)
        if chain is None:
            chains.append((key, [run]))
        else:
            chain.append(run)
    for key, parts in chains:
        scalars = {}
        for tag in {tag for part in parts for tag in part.scalars}:
            pieces = [part.scalars.get(tag, []) for part in parts]
            scalars[tag] = [
                (
                    np.concatenate([p[i][0] for p in pieces if i < len(p)]),
                    np.concatenate([p[i][1] for p in pieces if i < len(p)]),
                )
                for i in range(max(len(p) for p in pieces))
            ]  # fmt: skip
        out.append(Run(parts[0].path, *key, scalars, "races"))
    return out


def load_runs(logdir: str) -> list[Run]:
    event_files = glob.glob(os.path.join(logdir, "**", "events.out.tfevents.*"), recursive=True)
    run_dirs = sorted({os.path.dirname(f) for f in event_files})
    if not run_dirs:
        raise ValueError(f"no TensorBoard event files under {logdir!r}")
    runs = []
    for d in run_dirs:
        variant, stage, seed = run_identity(d)
        scalars = read_scalars(d)
        if any(RACER_PREFIX.match(tag) for tag in scalars):
            runs.extend(racer_runs(d, stage, seed, scalars))
        else:
            runs.append(Run(d, variant, stage, seed, scalars))
    return join_sittings(runs)


def group_runs(runs: list[Run]) -> dict[tuple[str, str], list[Run]]:
    groups: dict[tuple[str, str], list[Run]] = {}
    for run in sorted(runs, key=lambda r: (r.group, r.seed)):
        groups.setdefault(run.group, []).append(run)
    return groups


X_LABELS = ("step", "races")  # a run's x unit: env steps (the dreamer scripts), races (race.py --train)


def same_x(groups: dict[tuple[str, str], list[Run]], x_label: str) -> dict[tuple[str, str], list[Run]]:
    """The groups' runs counted in `x_label` (one axis never mixes env steps and races)."""
    kept = {k: [r for r in runs if r.x_label == x_label] for k, runs in groups.items()}
    return {k: runs for k, runs in kept.items() if runs}


def smooth(values: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing over logged points; edges repeat the end values."""
    if sigma <= 0 or len(values) < 2:
        return np.asarray(values, dtype=np.float64)
    return gaussian_filter1d(np.asarray(values, dtype=np.float64), sigma, mode="nearest")


def aggregate(curves: list[tuple[np.ndarray, np.ndarray]], sigma: float):
    """Mean and standard deviation across curves on a common grid (the x range all share)."""
    curves = [(s, v) for s, v in curves if len(s)]
    if not curves:
        return None
    lo = max(s[0] for s, _ in curves)
    hi = min(s[-1] for s, _ in curves)
    grid = np.linspace(lo, hi, GRID_POINTS) if hi > lo else np.array([lo])
    stacked = np.stack([np.interp(grid, s, smooth(v, sigma)) for s, v in curves])
    return grid, stacked.mean(axis=0), stacked.std(axis=0), len(curves)


def plot_metric(ax, groups, tag: str, sigma: float, stage: str | tuple[str, ...] | None = None) -> list[str]:
    """Mean and one standard deviation across the seeds of each group (of `stage`, or of any of several stages,
    or of every stage) that logged `tag`, over the x range they all share, with each seed's own curve drawn thin
    (unlabelled) beside it; returns the labels drawn."""
    stages = (stage,) if isinstance(stage, str) else stage
    labels, x_labels = [], set()
    for (variant, group_stage), runs in groups.items():
        if stages is not None and group_stage not in stages:
            continue
        curves = [c for run in runs for c in run.scalars.get(tag, [])]
        result = aggregate(curves, sigma)
        if result is None:
            continue
        x_labels.update(run.x_label for run in runs if tag in run.scalars)
        grid, mean, std, n = result
        seeds = f"{len(runs)} seed{'s' * (len(runs) > 1)}"
        label = f"{variant} ({seeds})" if stages and len(stages) == 1 else f"{variant}/{group_stage} ({seeds})"
        (line,) = ax.plot(grid, mean, label=label)
        ax.fill_between(grid, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        for x, values in curves:  # every seed (and agent) thin and whole, also beyond the range all share
            ax.plot(x, smooth(values, sigma), color=line.get_color(), lw=0.7, alpha=0.35, label="_seed")
        labels.append(label)
    ax.set_xlabel(x_labels.pop() if len(x_labels) == 1 else "step")
    ax.grid(alpha=0.3)
    if labels:
        ax.legend()
    return labels


def head_to_head_figure(csv_path: str) -> plt.Figure:
    """The tournaments of benchmarks/experiment.py (its head_to_head.csv, or head_to_head_<policy>.csv: titled
    with the policy): per seed pair the LSTM's win rate in the evaluation races with its Wilson 95% interval, the
    GRU's, and the races both cars were eliminated in, against the head-to-head races trained."""
    import csv

    columns = {"seed_pair", "races_trained", "eval_races", "lstm_wins", "gru_wins", "both_out",
               "lstm_win_rate_ci_low", "lstm_win_rate_ci_high"}  # fmt: skip
    with open(csv_path, newline="") as f:
        reader = csv.DictReader(f)
        missing = sorted(columns - set(reader.fieldnames or ()))
        rows = list(reader)
    if missing:
        raise ValueError(f"{csv_path}: not a head_to_head.csv (no column {', '.join(missing)})")
    if not rows:
        raise ValueError(f"{csv_path}: no tournaments")
    fig, ax = plt.subplots(figsize=(6, 4))
    for pair in sorted({r["seed_pair"] for r in rows}):
        mine = sorted((r for r in rows if r["seed_pair"] == pair), key=lambda r: int(r["races_trained"]))
        x = np.array([int(r["races_trained"]) for r in mine])
        n = np.array([int(r["eval_races"]) for r in mine])
        lstm = np.array([int(r["lstm_wins"]) for r in mine]) / n
        low, high = (np.array([float(r[k]) for r in mine]) for k in ("lstm_win_rate_ci_low", "lstm_win_rate_ci_high"))
        (line,) = ax.plot(x, lstm, marker="o", label=f"LSTM, seeds {pair}")
        ax.fill_between(x, low, high, color=line.get_color(), alpha=0.15)  # the band between tournaments
        ax.errorbar(x, lstm, yerr=[lstm - low, high - lstm], fmt="none", ecolor=line.get_color(), capsize=3,
                    label=f"_interval {pair}")  # each tournament's own interval, visible for a single one too
        ax.plot(x, np.array([int(r["gru_wins"]) for r in mine]) / n, marker="s", linestyle="--",
                color=line.get_color(), alpha=0.6, label=f"GRU, seeds {pair}")  # fmt: skip
        ax.plot(x, np.array([int(r["both_out"]) for r in mine]) / n, linestyle=":", color=line.get_color(), alpha=0.6)
    ax.axhline(0.5, color="gray", linewidth=0.8)
    ax.set_xlabel("head-to-head races trained")
    ax.set_ylabel("win rate in evaluation races (dotted: both out)")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    stem = os.path.splitext(os.path.basename(csv_path))[0]  # head_to_head_<policy>: the tournaments with <policy>
    policy = f" ({stem.removeprefix('head_to_head_')} policy)" if stem.startswith("head_to_head_") else ""
    ax.set_title(f"tournaments{policy}: LSTM vs GRU (Wilson 95%)")
    return fig


def figure_name(csv_path: str) -> str:
    """The tournaments' figure of a CSV: its name with .png (head_to_head.csv: head_to_head.png)."""
    return os.path.splitext(os.path.basename(csv_path))[0] + ".png"


def make_figures(logdir: str, out: str, sigma: float = 2.0, head_to_head: str | list[str] | None = None
                 ) -> dict[str, plt.Figure]:  # fmt: skip
    """Build every figure that has data (and a tournaments' figure from each head_to_head CSV); save each as a PNG
    in ``out``; return them."""
    csvs = [head_to_head] if isinstance(head_to_head, str) else list(head_to_head or [])
    names = [figure_name(path) for path in csvs]
    if len(set(names)) < len(names):
        raise ValueError(f"--head-to-head: two CSVs of the same name would draw the same figure: {csvs}")
    groups = group_runs(load_runs(logdir))
    os.makedirs(out, exist_ok=True)
    figures = {name: head_to_head_figure(path) for name, path in zip(names, csvs)}
    for name, (stage, tag, ylabel) in FIGURES.items():
        for x_label in X_LABELS:  # one x unit per figure: the races one is <name>_races.png beside a steps one
            fig, ax = plt.subplots(figsize=(6, 4))
            if plot_metric(ax, same_x(groups, x_label), tag, sigma, stage=stage):
                ax.set_ylabel(ylabel)
                ax.set_title(f"{stage if isinstance(stage, str) else ' vs '.join(stage)}: {ylabel}")
                figures[name if name not in figures else name.replace(".png", f"_{x_label}.png")] = fig
            else:
                plt.close(fig)
    for x_label, name in zip(X_LABELS, ("losses.png", "losses_race.png")):
        fig, axes = plt.subplots(1, len(LOSSES), figsize=(5 * len(LOSSES), 4))
        if any([plot_metric(ax, same_x(groups, x_label), tag, sigma) for ax, tag in zip(axes, LOSSES)]):
            for ax, tag in zip(axes, LOSSES):
                ax.set_title(tag)
            figures[name] = fig
        else:
            plt.close(fig)
    for name, fig in figures.items():
        fig.tight_layout()
        fig.savefig(os.path.join(out, name), dpi=100)
    return figures


def usage_error(message: str) -> None:
    """Exit as argparse does on bad input: status 2, one line on stderr (utils.run.usage_error)."""
    run_tools.usage_error("plot.py", message)


def parse_args(argv=None) -> Args:
    """Args of a command line, checked: any impossible value exits with status 2 and one line naming it."""
    args = run_tools.tyro_cli(Args, argv, __doc__)
    if not os.path.isdir(args.logdir):
        usage_error(f"logdir {args.logdir!r} is not a directory")
    if not math.isfinite(args.sigma) or args.sigma < 0:
        usage_error(f"--sigma must be a finite number >= 0, got {args.sigma}")
    if args.head_to_head == ():
        usage_error("--head-to-head needs at least one CSV")
    for path in args.head_to_head or ():
        if not os.path.isfile(path):
            usage_error(f"--head-to-head {path!r} is not a file")
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        usage_error(f"--out {args.out!r} exists and is not a directory")
    return args


def main(argv=None):
    args = parse_args(argv)
    try:
        figures = make_figures(args.logdir, args.out, args.sigma, list(args.head_to_head or ()))
    except ValueError as e:
        sys.exit(f"plot.py: {e}")
    for name in figures:
        print(os.path.join(args.out, name))


if __name__ == "__main__":
    main()
