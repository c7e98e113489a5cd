"""The learning benchmark's reports (``benchmarks/learning.py``): what its runs did, and how their final policies
compare.

* curves: each run's evaluations (its event files) and training races (its progress.csv), saved as
  ``learning_<variant>_seed<S>.csv`` and ``..._training.csv`` so that runs on other machines stay in; the figure and
  table of the default runs (``learning.png``, ``learning.md``) and of each ablation beside the default run of its
  variant and seed (``screening/ablations.png``, ``.md``), with the references (random actions and the pure-pursuit
  driver: ``baselines``);
* diagnostics: a run's progress.csv per bucket of updates (``--diagnose``; the screens' training readings);
* ``learning_final.md`` from ``learning_final.csv``: the bar per variant with rliable intervals, the LSTM against the
  GRU, the references on the fresh tracks and the SB3 PPO peer (``--final``, ``--final-report``: the 8,000-update
  protocol). The final protocol's (CPU budget: ``--protocol-row``, ``--protocol-report``) is written by
  ``final_protocol.py``.
"""

from __future__ import annotations

import csv
import glob
import json
import os
import re

import numpy as np

from learning import (
    BAR_HOLD, BAR_PROGRESS, BAR_RETURN, BAR_SEED_RETURN, BAR_STEER, FINAL_ADVICE, FINAL_COLUMNS, FRESH_TRACKS, RESULTS,
    RUNS, eval_curve, experiment_name, learning_runs, read_rows,
)  # fmt: skip


# --- Curves, their figure and table ----------------------------------------------------------
def baselines(
    eval_seed: int = 10_000, episodes: int = 10, results_dir: str = RESULTS, filename: str = "baselines.json"
) -> dict:
    """Random actions and the pursuit driver on the tracks ``eval_seed ..`` (by default the 10 held-out tracks of
    the evaluations; ``FRESH_TRACKS`` for the final policies' reference), with the env settings of training.
    Computed once, then read from ``results_dir/filename``, which names its tracks (a file of other tracks is
    refused; one written before it named them is read as it is)."""
    from common import track_block

    path, tracks = os.path.join(results_dir, filename), track_block(eval_seed, episodes)
    if os.path.exists(path):
        with open(path) as f:
            saved = json.load(f)
        if saved.setdefault("tracks", tracks) != tracks:
            raise ValueError(f"{path} holds the references on tracks {saved['tracks']}, not {tracks}: give another "
                             "filename")  # fmt: skip
        return {name: value for name, value in saved.items() if name != "tracks"}
    from envs import MultiCarRacing
    from envs.pursuit import PursuitDriver

    results = {}
    for name in ("random", "pursuit@70"):
        returns, progress = [], []
        for e in range(episodes):
            env = MultiCarRacing(num_agents=1, dead_zone=-0.5)
            env.reset(seed=eval_seed + e)
            rng = np.random.default_rng(e)
            driver = PursuitDriver(env, "car_0", 70.0)
            total = 0.0
            while env.agents:
                action = driver.act() if name.startswith("pursuit") else rng.uniform(-1, 1, 2)
                _, rewards, _, _, infos = env.step({"car_0": action})
                total += rewards["car_0"]
            returns.append(total)
            progress.append(infos["car_0"]["progress"])
        results[name] = {"eval_return": float(np.mean(returns)), "eval_progress": float(np.mean(progress))}
    os.makedirs(results_dir, exist_ok=True)
    with open(path, "w") as f:
        json.dump({**results, "tracks": tracks}, f, indent=2)
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
        with open(csv_path, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
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
            with open(saved_path, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=["updates", "return"])
                writer.writeheader()
                writer.writerows(rows)
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
        with open(stem + ".md", "w") as f:
            f.write(table)
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
        ax.axhline(bar, color="red", linestyle="-.", alpha=0.6, label="bar (final policy, mean over seeds)")
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


# --- The 8,000-update protocol's summary: learning_final.md ---------------------------------
# learning_final.csv's columns of the final policy, by how it acts: sampled (as trained) or its mean action
FINAL_POLICY_COLUMNS = {
    "stochastic": ("final_return", "final_progress"), "mean-action": ("mean_action_return", "mean_action_progress"),
}  # fmt: skip


def bar_verdict(rows: list[dict], policy: str = "stochastic") -> dict[str, bool]:
    """Each part of the bar for the rows of one variant (its seeds), the final policy acting with `policy`
    (FINAL_POLICY_COLUMNS): mean final return >= BAR_RETURN, every seed
    >= BAR_SEED_RETURN, mean progress >= BAR_PROGRESS, mean |steer| of the final policy's mean action <= BAR_STEER,
    and every run holds (its last three evaluations average within BAR_HOLD of its best: the run's own evaluations,
    with its --eval-policy, whatever `policy` is; sampled for the runs begun before the mean action's rule).

    Smoothness is judged on the mean action, the steering the policy means: the sampled policy's |steer| carries
    its exploration noise (sigma ~0.8 puts it near 0.6 even for a mean of 0), and the bang-bang agents this gauge
    was made for (0.78-0.85) were measured on their mean action too. The sampled |steer| is reported beside it."""

    def values(key: str) -> np.ndarray:
        return np.array([float(r[key]) for r in rows])

    returns, progress = FINAL_POLICY_COLUMNS[policy]
    return {
        "return": values(returns).mean() >= BAR_RETURN,
        "every seed": values(returns).min() >= BAR_SEED_RETURN,
        "progress": values(progress).mean() >= BAR_PROGRESS,
        "steer": values("mean_action_abs_steer").mean() <= BAR_STEER,
        "holds": bool(np.all(values("best_eval_return") - values("last3_eval_return") <= BAR_HOLD)),
    }


def final_summary(
    path: str = os.path.join(RESULTS, "learning_final.csv"), reps: int = 2000, policy: str = "stochastic"
) -> str:
    """Markdown: per variant the IQM and mean of the final return, the final policy acting with `policy`, with
    stratified-bootstrap 95% intervals (rliable), the bar's numbers, and which parts of the bar (bar_verdict)
    fail."""
    from stats import interval_estimates

    rows = read_rows(path, FINAL_COLUMNS, FINAL_ADVICE)
    return_key, progress_key = FINAL_POLICY_COLUMNS[policy]
    lines = [
        f"The final policy {'sampled, as trained' if policy == 'stochastic' else 'driving its mean action'}:",
        "",
        "| experiment | seeds | IQM final return [95% CI] | mean final return [95% CI] | min seed | mean progress "
        "| mean \\|steer\\|: mean action (sampled) | runs that hold | bar |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for variant in sorted({r["exp_name"] for r in rows}):  # each experiment (a variant, or an ablation of it)
        mine = [r for r in rows if r["exp_name"] == variant]
        returns = np.array([float(r[return_key]) for r in mine])
        est = interval_estimates({variant: returns[:, None]}, reps=reps)[variant]
        verdict = bar_verdict(mine, policy)
        holds = sum(float(r["best_eval_return"]) - float(r["last3_eval_return"]) <= BAR_HOLD for r in mine)
        failed = [part for part, ok in verdict.items() if not ok]
        lines.append(
            f"| {variant} | {len(mine)} | {est['iqm']:.1f} [{est['iqm_ci'][0]:.1f}, {est['iqm_ci'][1]:.1f}] "
            f"| {est['mean']:.1f} [{est['mean_ci'][0]:.1f}, {est['mean_ci'][1]:.1f}] | {returns.min():.1f} "
            f"| {np.mean([float(r[progress_key]) for r in mine]):.2f} "
            f"| {np.mean([float(r['mean_action_abs_steer']) for r in mine]):.2f} "
            f"({np.mean([float(r['final_mean_abs_steer']) for r in mine]):.2f}) | {holds} of {len(mine)} "
            f"| {'met' if not failed else 'not met: ' + ', '.join(failed)} |"
        )
    return "\n".join(lines) + "\n"


def fresh_reference(results_dir: str = RESULTS) -> str:
    """One line for learning_final.md: random actions and the pursuit driver on the same fresh tracks."""
    base = baselines(*FRESH_TRACKS, results_dir=results_dir, filename="baselines_fresh.json")
    first, count = FRESH_TRACKS
    rand, pursuit = base["random"], base["pursuit@70"]
    return (
        f"\nOn the same {count} tracks ({first}..{first + count - 1}): random actions "
        f"{rand['eval_return']:.1f} (progress {rand['eval_progress']:.2f}), the pure-pursuit driver at 70 "
        f"{pursuit['eval_return']:.1f} ({pursuit['eval_progress']:.2f}).\n"
    )


def variant_difference(path: str = os.path.join(RESULTS, "learning_final.csv")) -> str:
    """Markdown for learning_final.md: the paper's solo claim, the LSTM's mean final return minus the GRU's over
    their seeds (the variants' defaults only), with the final policy driving its mean action and sampled: the
    difference of the means of independent runs, its test (the exact permutation test's one-sided p over every
    split of the runs, Welch's t 95% interval: stats.two_group_claim) and the verdict (stats.judge). "" until both
    variants have a row."""
    from stats import describe, two_group_claim

    rows = [r for r in read_rows(path, FINAL_COLUMNS, FINAL_ADVICE) if r["exp_name"] == experiment_name(r["variant"])]
    if not {"lstm", "gru"} <= {r["variant"] for r in rows}:
        return ""
    lines = ["", "| final policy: LSTM - GRU | difference of means | test (one-sided p of the claim) "
                 "| the LSTM beats the GRU |"]  # fmt: skip
    lines.append("|---|---|---|---|")
    for policy, label in (("mean-action", "mean action"), ("stochastic", "sampled")):
        key = FINAL_POLICY_COLUMNS[policy][0]
        lstm, gru = (np.array([float(r[key]) for r in rows if r["variant"] == v]) for v in ("lstm", "gru"))
        claim = two_group_claim(lstm, gru)
        lines.append(f"| {label} | {claim['estimate']:+.1f} | {describe(claim)} | {claim['verdict']} |")
    return "\n".join(lines) + "\n"


def peer_summary(
    final_path: str = os.path.join(RESULTS, "learning_final.csv"),
    peer_path: str = os.path.join(RESULTS, "ppo_peer.csv"), reps: int = 2000,
) -> str:
    """Markdown for learning_final.md: SB3 PPO (benchmarks/ppo_peer.py, its deterministic policy) over its seeds,
    each with the CPU time it had, and each variant's final policy driving its mean action minus PPO on the same
    fresh tracks: the difference of the means of independent runs, its test (the exact permutation test's one-sided
    p, Welch's t 95% interval: stats.two_group_claim) and the verdict (stats.judge: none while a side has fewer than
    stats.MIN_RUNS runs). PPO's own mean has a stratified-bootstrap interval (rliable): a description. Only PPO's
    rows of the fresh tracks count (ppo_peer.read_rows: a row without a ``tracks`` column was measured there); the
    variants' defaults only (an ablation is not the method); "" while ppo_peer.csv has no such row."""
    from ppo_peer import read_rows as read_peer_rows
    from common import track_block
    from stats import MIN_RUNS, describe, interval_estimates, two_group_claim

    peer = [r for r in read_peer_rows(peer_path) if r["tracks"] == track_block(*FRESH_TRACKS)]
    if not peer:
        return ""
    ppo = np.array([float(r["final_return"]) for r in peer])
    rows = read_rows(final_path, FINAL_COLUMNS, FINAL_ADVICE)
    rows = [r for r in rows if r["exp_name"] == experiment_name(r["variant"])]
    budget = {r["seed"]: f" at {float(r['cpu_hours']):.2f} CPU-h" if r.get("cpu_hours") else "" for r in peer}
    seeds = ", ".join(f"{r['seed']}: {float(r['final_return']):.1f}{budget[r['seed']]}" for r in peer)
    if ppo.size >= MIN_RUNS:
        est = interval_estimates({"ppo": ppo[:, None]}, reps=reps)["ppo"]
        mean = f"mean {est['mean']:.1f} [{est['mean_ci'][0]:.1f}, {est['mean_ci'][1]:.1f}]"
    else:
        mean = f"{ppo.mean():.1f} (one seed: no interval)"
    lines = [
        "",
        f"SB3 PPO at the same CPU time (benchmarks/ppo_peer.py), {ppo.size} seed{'s' * (ppo.size > 1)}, its "
        f"deterministic policy: {mean} (seed {seeds}).",
        "",
        "| variant (mean action) - PPO | difference of means | test (one-sided p of the claim) "
        "| the variant beats PPO |",
        "|---|---|---|---|",
    ]
    for variant in sorted({r["variant"] for r in rows}):
        mine = np.array([float(r[FINAL_POLICY_COLUMNS["mean-action"][0]]) for r in rows if r["variant"] == variant])
        claim = two_group_claim(mine, ppo)
        lines.append(f"| {variant} - ppo | {claim['estimate']:+.1f} | {describe(claim)} | {claim['verdict']} |")
    return "\n".join(lines) + "\n"


def write_final_report(results_dir: str = RESULTS, reps: int = 2000, peer_path: str | None = None) -> str:
    """(Re)write learning_final.md from learning_final.csv (and the PPO peer's csv, by default ppo_peer.csv beside
    it, when present): the evaluation policy of the rule in docs/learning.md first (the mean action), then the
    policy as trained, the LSTM against the GRU, the references on the same tracks, and the PPO peer. Returns the
    text."""
    final_path = os.path.join(results_dir, "learning_final.csv")
    peer_path = peer_path or os.path.join(results_dir, "ppo_peer.csv")
    text = (
        final_summary(final_path, reps, policy="mean-action") + "\n" + final_summary(final_path, reps)
        + variant_difference(final_path) + fresh_reference(results_dir)
        + peer_summary(final_path, peer_path, reps)
    )  # fmt: skip
    with open(os.path.join(results_dir, "learning_final.md"), "w") as f:
        f.write(text)
    return text
