"""The learning benchmark's reports (``benchmarks/learning.py``): what its runs did, and how their final policies
compare.

* curves: each run's evaluations (its event files) and training races (its progress.csv), saved as
  ``learning_<variant>_seed<S>.csv`` and ``..._training.csv`` so that runs on other machines stay in; the figure and
  table of the default runs (``learning.png``, ``learning.md``) and of each ablation beside the default run of its
  variant and seed (``screening/ablations.png``, ``.md``), with the references (random actions and the pure-pursuit
  driver: ``baselines``);
* diagnostics: a run's progress.csv per bucket of updates (``--diagnose``; the screens' training readings).

The final protocol's ``learning_final.md`` (``--protocol-row``, ``--protocol-report``) is written by
``final_protocol.py``.
"""

from __future__ import annotations

import csv
import glob
import json
import os
import re

import numpy as np

from common import RESULTS, track_block, write_json, write_table, write_text
from runs import RUNS, eval_curve, learning_runs, progress_rows

# The lines the figure and table draw: the 8,000-update protocol's bar on a learning run's mean evaluation return
# and progress (docs/learning.md).
BAR_RETURN, BAR_PROGRESS = 600.0, 0.65


# --- Curves, their figure and table ----------------------------------------------------------
def baselines(
    eval_seed: int = 10_000, episodes: int = 10, results_dir: str = RESULTS, filename: str = "baselines.json"
) -> dict:
    """Random actions and the pursuit driver on the tracks ``eval_seed ..`` (by default the 10 held-out tracks of
    the evaluations), with the env settings of training. Computed once, then read from ``results_dir/filename``,
    which names its tracks (a file of other tracks is refused; one written before it named them is read as it
    is)."""
    path, tracks = os.path.join(results_dir, filename), track_block(eval_seed, episodes)
    if os.path.exists(path):
        with open(path) as f:
            saved = json.load(f)
        if saved.setdefault("tracks", tracks) != tracks:
            raise ValueError(f"{path} holds the references on tracks {saved['tracks']}, not {tracks}: give another "
                             "results_dir or filename")  # fmt: skip
        return {name: value for name, value in saved.items() if name != "tracks"}
    from envs import MultiCarRacing
    from envs.pursuit import PursuitDriver

    results = {}
    for reference in ("random", "pursuit@70"):
        returns, progress = [], []
        for e in range(episodes):
            env = MultiCarRacing(num_agents=1, dead_zone=-0.5)
            env.reset(seed=eval_seed + e)
            rng = np.random.default_rng(e)
            driver = PursuitDriver(env, "car_0", 70.0)
            total = 0.0
            while env.agents:
                action = driver.act() if reference.startswith("pursuit") else rng.uniform(-1, 1, 2)
                _, rewards, _, _, infos = env.step({"car_0": action})
                total += rewards["car_0"]
            returns.append(total)
            progress.append(infos["car_0"]["progress"])
        results[reference] = {"eval_return": float(np.mean(returns)), "eval_progress": float(np.mean(progress))}
    os.makedirs(results_dir, exist_ok=True)
    write_json(path, {**results, "tracks": tracks})  # atomic: final_protocol.py reads it as a cache
    return results


def read_curve(csv_path: str) -> list[dict]:
    """Rows of a saved ``learning_*.csv`` with their numeric types back."""
    kinds = {"env_steps": int, "updates": int, "wall_hours": float, "eval_return": float, "eval_progress": float}
    with open(csv_path, newline="") as f:
        return [{key: kinds[key](value) for key, value in row.items()} for row in csv.DictReader(f)]


def load_curves(runs_dir: str = RUNS, results_dir: str = RESULTS) -> dict[str, list[dict]]:
    """Every learning curve by name (``learning_<variant>_seed<S>``): read from the run's event files when
    the run is on this machine (and written to its CSV), else from the CSV committed by an earlier sitting,
    so runs on other machines stay in the table and the figure. A saved CSV that reaches further than the
    run here (a run restarted from scratch) is kept, never overwritten by the shorter curve."""
    curves = {}
    for run_dir in learning_runs(runs_dir):
        _, exp_name, seed = os.path.basename(run_dir).split("__")[:3]
        rows = eval_curve(run_dir)
        if not rows:
            continue
        name = f"{exp_name}_seed{seed}"
        csv_path = os.path.join(results_dir, name + ".csv")
        saved = read_curve(csv_path) if os.path.exists(csv_path) else []
        if saved and saved[-1]["env_steps"] > rows[-1]["env_steps"]:
            # a restarted run has not caught up with the curve an earlier sitting saved: keep that one
            print(f"note: {run_dir} ({rows[-1]['env_steps']} env steps) is behind {csv_path}; keeping the CSV")
            continue
        write_table(csv_path, rows, list(rows[0]))
        curves[name] = rows
    for csv_path in sorted(glob.glob(os.path.join(results_dir, "learning_*_seed*.csv"))):
        if csv_path.endswith("_training.csv"):
            continue
        name = os.path.basename(csv_path).removesuffix(".csv")
        if name not in curves:
            rows = read_curve(csv_path)
            if rows:
                curves[name] = rows
    return dict(sorted(curves.items()))


def training_curves(runs_dir: str = RUNS, results_dir: str = RESULTS) -> dict[str, list[dict]]:
    """Per run, the return of every training race after the first update (the sampled policy, on tracks it has not
    seen before) against the updates made: read from the run's progress.csv when the run is here (and saved as
    ``<name>_training.csv``), else from that CSV. As with load_curves, a saved CSV that reaches further than the
    run here is kept, never overwritten by the shorter curve."""

    def read(path: str) -> list[dict]:
        with open(path, newline="") as f:
            return [{"updates": int(r["updates"]), "return": float(r["return"])} for r in csv.DictReader(f)]

    curves = {}
    for run_dir in learning_runs(runs_dir):
        _, exp_name, seed = os.path.basename(run_dir).split("__")[:3]
        path = os.path.join(run_dir, "progress.csv")
        if not os.path.exists(path):
            continue
        with open(path, newline="") as f:
            rows = [
                {
                    "updates": int(float(r["car_0/perf/updates"])),
                    "return": round(float(r["car_0/charts/episodic_return"]), 2),
                }
                for r in csv.DictReader(f) if r.get("car_0/perf/updates") and r.get("car_0/charts/episodic_return")
            ]  # fmt: skip
        saved_path = os.path.join(results_dir, f"{exp_name}_seed{seed}_training.csv")
        saved = read(saved_path) if os.path.exists(saved_path) else []
        if saved and (not rows or saved[-1]["updates"] > rows[-1]["updates"]):
            print(f"note: {run_dir} is behind {saved_path}; keeping the CSV")
            continue
        if rows:
            curves[f"{exp_name}_seed{seed}"] = rows
            write_table(saved_path, rows, ["updates", "return"])
    for path in sorted(glob.glob(os.path.join(results_dir, "learning_*_training.csv"))):
        name = os.path.basename(path).removesuffix("_training.csv")
        if name not in curves:
            curves[name] = read(path)
    return curves


def first_at_bar(rows: list[dict]) -> dict | None:
    """The first evaluation at which both halves of the bar hold (return and progress of the same eval)."""
    return next((r for r in rows if r["eval_return"] >= BAR_RETURN and r["eval_progress"] >= BAR_PROGRESS), None)


def summary_table(curves: dict[str, list[dict]], base: dict) -> str:
    """Markdown: per run its last point, its best evaluation, and where it first met the bar."""
    lines = [
        (
            "| run | env steps | updates | hours | last eval return | last progress | best eval return (progress) "
            "| bar first met at |"
        ),
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, rows in curves.items():
        last, best, hit = rows[-1], max(rows, key=lambda r: r["eval_return"]), first_at_bar(rows)
        met = f"{hit['env_steps']} steps, {hit['wall_hours']:.2f} h" if hit else "not met"
        lines.append(
            f"| {name.removeprefix('learning_')} | {last['env_steps']} | {last['updates']} | {last['wall_hours']:.2f} "
            f"| {last['eval_return']:.1f} | {last['eval_progress']:.2f} "
            f"| {best['eval_return']:.1f} ({best['eval_progress']:.2f}) | {met} |"
        )
    for bname, b in base.items():
        lines.append(f"| {bname} (baseline) | | | | {b['eval_return']:.1f} | {b['eval_progress']:.2f} | | |")
    return "\n".join(lines) + "\n"


def is_default(name: str) -> bool:
    """Whether a curve's name (``<experiment>_seed<S>``) is a run of the default method, not an ablation."""
    return re.fullmatch(r"learning_(lstm|gru)_seed\d+", name) is not None


def report(runs_dir: str = RUNS, results_dir: str = RESULTS) -> None:
    """CSV per run; a PNG of the default runs' curves with the baselines and the bar, and a markdown table of them
    (learning.png, learning.md); the same of the ablations beside the default runs of their variant and seed in
    screening/ablations.png and .md."""
    os.makedirs(results_dir, exist_ok=True)
    base = baselines(results_dir=results_dir)
    curves, training = load_curves(runs_dir, results_dir), training_curves(runs_dir, results_dir)
    default = [name for name in curves | training if is_default(name)]
    ablations = [name for name in curves | training if not is_default(name)]
    pages = [(os.path.join(results_dir, "learning"), default)]
    if ablations:  # each beside the default run of its variant and seed
        paired = {re.sub(r"^learning_(lstm|gru)_.*_seed", r"learning_\1_seed", name) for name in ablations}
        pages.append((os.path.join(results_dir, "screening", "ablations"), sorted(paired & set(default)) + ablations))
    for stem, names in pages:
        os.makedirs(os.path.dirname(stem), exist_ok=True)
        plot_curves({n: curves[n] for n in names if n in curves}, {n: training[n] for n in names if n in training},
                    base, stem + ".png")  # fmt: skip
        table = summary_table({n: curves[n] for n in names if n in curves}, base)
        write_text(stem + ".md", table)
        print(table)


def plot_curves(curves: dict[str, list[dict]], training: dict[str, list[dict]], base: dict, path: str) -> None:
    """One PNG: the training races' returns against updates, and the evaluations' return and progress against env
    steps with the baselines and the bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(18, 4))
    panels = (
        (axes[1], "eval_return", "evaluation return (--eval-policy)", BAR_RETURN),
        (axes[2], "eval_progress", "evaluation progress", BAR_PROGRESS),
    )
    for name, rows in training.items():  # the races it trained on: sampled policy
        returns = np.array([r["return"] for r in rows])
        smooth = np.convolve(returns, np.ones(5) / 5, mode="valid") if len(returns) >= 5 else returns
        axes[0].plot(
            [r["updates"] for r in rows][len(rows) - len(smooth):], smooth, label=name.removeprefix("learning_")
        )
    axes[0].set_xlabel("updates")
    axes[0].set_ylabel("training race return (mean of 5)")
    axes[0].grid(alpha=0.3)
    axes[0].legend(fontsize="small")
    for ax, key, label, bar in panels:
        for name, rows in curves.items():
            ax.plot(
                [r["env_steps"] for r in rows], [r[key] for r in rows], marker="o", label=name.removeprefix("learning_")
            )
        for (bname, b), style in zip(base.items(), (":", "--")):
            ax.axhline(b[key], color="gray", linestyle=style, label=bname)
        ax.axhline(bar, color="red", linestyle="-.", alpha=0.6,
                   label="8,000-update bar (final policy, mean over seeds)")
        ax.set_xlabel("env steps")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --- Diagnostics -----------------------------------------------------------------------------
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
