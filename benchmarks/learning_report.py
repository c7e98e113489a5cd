"""What the learning benchmark (``benchmarks/learning.py``) reads beside its runs' final policies:

* ``baselines``: the references, random actions and the pure-pursuit driver on a block of tracks (the final
  protocol's report puts them beside its rows);
* ``diagnostics``: a run's progress.csv per bucket of updates (``--diagnose``; the screens' training readings).

The final protocol's ``learning_final.md`` (``--protocol-row``, ``--protocol-report``) is written by
``final_protocol.py``. (The curves, figure and table of the 8,000-update protocol's runs were written here until
commit b28dd0c; they are in ``benchmarks/results/history/8000_updates/``, with the ablations' beside them.)
"""

from __future__ import annotations

import json
import os

import numpy as np

from common import RESULTS, track_block, write_json
from runs import progress_rows


# --- The references --------------------------------------------------------------------------
def baselines(eval_seed: int, episodes: int, results_dir: str = RESULTS, filename: str = "references.json") -> dict:
    """Random actions and the pursuit driver on the tracks ``eval_seed .. eval_seed + episodes - 1``, with the env
    settings of training. Computed once, then read from ``results_dir/filename``, which names its tracks (a file of
    other tracks is refused; one written before it named them is read as it is)."""
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
