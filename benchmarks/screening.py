"""Screens and the rule for the evaluation policy (``benchmarks/learning.py --screen``, ``--policy-rule``). Both
measure saved policies, sampled and with their mean action, on the screening tracks SCREEN_TRACKS, apart from the
fresh tracks the final protocol reports on:

* a screen: an ablation and the default run of the same variant and seed, each at the policy it kept at the same
  update count, with their training diagnostics (``screening/screens.csv``);
* the rule: every final policy of the default method in ``learning_final.csv``, and the evaluation policy their
  paired differences choose (``policy_rule.csv``, ``policy_rule.md``).
"""

from __future__ import annotations

import csv
import glob
import os

import numpy as np

from common import TRACKS, replace_rows
from learning import RESULTS, RUNS, VARIANTS, experiment_name, find_run, policy_summary
from learning_report import DIAGNOSTICS, progress_rows


# --- Screens ---------------------------------------------------------------------------------
# A screen: an ablation against the default at the same point of training (same variant, seed and updates), on
# tracks of its own, so that what screening picks is not then reported on the tracks it was picked on.
SCREEN_TRACKS = TRACKS["screening"]
SCREEN_POLICIES = ("stochastic", "mean-action")  # the policy as trained, and the steering it means
SCREEN_WINDOW = 500  # the diagnostics of a screen row: means over the updates (u - SCREEN_WINDOW, u]
SCREEN_DIAGNOSTICS = {  # column of screens.csv: its DIAGNOSTICS name
    "training_return": "training return", "actor_sigma": "actor sigma", "entropy": "entropy", "kl_dyn": "kl_dyn",
    "reward_nll": "reward NLL (real data)", "imagined_return": "imagined return",
}  # fmt: skip
SCREEN_COLUMNS = (
    "exp_name", "variant", "seed", "updates", "policy", "return", "progress", "mean_abs_steer", *SCREEN_DIAGNOSTICS,
    "tracks", "run", "checkpoint",
)  # fmt: skip


def checkpoint_at(run_dir: str, updates: int) -> str:
    """The policy `run_dir` kept at exactly `updates` updates: its latest.pt or one of its eval_<race>.pt."""
    import race

    paths = [os.path.join(run_dir, "checkpoints", "latest.pt")]
    paths += sorted(glob.glob(os.path.join(run_dir, "checkpoints", "eval_*.pt")), reverse=True)
    kept = []
    for path in paths:
        if not os.path.exists(path):
            continue
        done = int(race.read_checkpoint(path)[1]["agents"][0]["num_updates"])
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


def screen_rows(
    variant: str, seed: int, updates: int, exp_name: str, runs_dir: str = RUNS, reference_runs_dir: str = RUNS,
    tracks: tuple[int, int] = SCREEN_TRACKS,
) -> list[dict]:
    """An ablation (`exp_name`) and the default run (``learning_<variant>``) of the same seed, each at the policy it
    kept at `updates` updates: one row per run and SCREEN_POLICIES entry, measured on `tracks` (first seed, count),
    with the run's SCREEN_DIAGNOSTICS averaged over its last SCREEN_WINDOW updates. Those come from the training
    races and updates of that window, i.e. from the policies on the way to the screened one."""
    reference = experiment_name(variant)
    if exp_name == reference:
        raise ValueError("a screen compares an ablation with the default run: give the ablated flag(s)")
    rows = []
    for name, where in ((reference, reference_runs_dir), (exp_name, runs_dir)):
        run = find_run(name, seed, where)
        if run is None:
            raise ValueError(f"no run of {name} seed {seed} in {where}")
        path = checkpoint_at(run, updates)
        window = [row for u, row in progress_rows(run) if updates - SCREEN_WINDOW < u <= updates]
        tags, means = dict(DIAGNOSTICS), {}
        for column, diag in SCREEN_DIAGNOSTICS.items():
            values = [float(row[tags[diag]]) for row in window if row.get(tags[diag])]
            means[column] = round(float(np.mean(values)), 3) if values else float("nan")
        for policy in SCREEN_POLICIES:
            result = policy_summary(path, *tracks, policy)
            rows.append({
                "exp_name": name, "variant": variant, "seed": seed, "updates": updates, "policy": policy,
                "return": round(result["eval_return"], 2), "progress": round(result["eval_progress"], 4),
                "mean_abs_steer": round(result["mean_abs_steer"], 4), **means, "tracks": result["tracks"],
                "run": os.path.basename(run), "checkpoint": os.path.basename(path),
            })  # fmt: skip
    return rows


def write_screen_rows(rows: list[dict], path: str = os.path.join(RESULTS, "screening", "screens.csv")) -> str:
    """Add `rows` to the screens' CSV and return the whole table as markdown, the default run of each (variant,
    seed, updates) first. A row of the same run, updates, policy and tracks is replaced (a run measured again).
    Screens may run side by side: the file is locked for the read and the write, and replaced atomically."""

    def key(r: dict) -> tuple:
        return r["run"], int(r["updates"]), r["policy"], r["tracks"]

    def order(r: dict) -> tuple:
        default_last = r["exp_name"] != experiment_name(r["variant"])
        return r["variant"], int(r["seed"]), int(r["updates"]), default_last, r["exp_name"], *key(r)

    table = replace_rows(path, rows, SCREEN_COLUMNS, key, order)
    shown = [c for c in SCREEN_COLUMNS if c not in ("run", "checkpoint")]
    lines = ["| " + " | ".join(shown) + " |", "|" + "---|" * len(shown)]
    lines += ["| " + " | ".join(str(r[c]) for c in shown) + " |" for r in table]
    return "\n".join(lines) + "\n"


# --- The rule for the evaluation policy ------------------------------------------------------
# The rule for the evaluation policy, fixed before seeds 12 and 13 were measured (docs/learning.md): each final policy
# of the default method, sampled and with its mean action, on the screening tracks; the mean action becomes the
# evaluation policy only if its paired advantage has a 95% interval above 0 over RULE_SEEDS seeds of each variant.
RULE_SEEDS = 3
RULE_COLUMNS = (
    "variant", "seed", "updates", "stochastic_return", "mean_action_return", "difference", "tracks", "run",
)  # fmt: skip


def policy_rule_rows(
    runs_dir: str = RUNS, final_csv: str = os.path.join(RESULTS, "learning_final.csv"),
    path: str = os.path.join(RESULTS, "policy_rule.csv"), tracks: tuple[int, int] = SCREEN_TRACKS,
) -> list[dict]:
    """The rule's measurements: for each run of the default method in `final_csv` (a final policy), its latest.pt
    sampled and with its mean action on `tracks`. The same run at the same updates and tracks in `path` is not
    measured again; the rows are saved to `path` (replaced atomically) and returned, sorted by variant and seed."""
    with open(final_csv, newline="") as f:
        finals = [r for r in csv.DictReader(f) if r["exp_name"] == experiment_name(r["variant"])]
    saved = {}
    if os.path.exists(path):
        with open(path, newline="") as f:
            saved = {(r["variant"], int(r["seed"])): r for r in csv.DictReader(f)}
    name = f"{tracks[0]}..{tracks[0] + tracks[1] - 1}"
    rows = []
    for final in finals:
        variant, seed, updates = final["variant"], int(final["seed"]), int(final["updates"])
        run = find_run(final["exp_name"], seed, runs_dir)
        if run is None:
            raise ValueError(f"no run of {final['exp_name']} seed {seed} in {runs_dir} (it has a row in {final_csv})")
        earlier = saved.get((variant, seed))
        if earlier and (int(earlier["updates"]), earlier["tracks"], earlier["run"]) == (
            updates, name, os.path.basename(run)
        ):
            rows.append(earlier)  # this run's final policy, measured before
            continue
        latest = os.path.join(run, "checkpoints", "latest.pt")
        sampled = policy_summary(latest, *tracks, "stochastic")
        mean_action = policy_summary(latest, *tracks, "mean-action")
        if sampled["updates"] != updates:
            raise ValueError(f"{latest} has {sampled['updates']} updates, its row in {final_csv} {updates}")
        rows.append({
            "variant": variant, "seed": seed, "updates": updates,
            "stochastic_return": round(sampled["eval_return"], 2),
            "mean_action_return": round(mean_action["eval_return"], 2),
            "difference": round(mean_action["eval_return"] - sampled["eval_return"], 2),
            "tracks": name, "run": os.path.basename(run),
        })  # fmt: skip
    rows.sort(key=lambda r: (r["variant"], int(r["seed"])))
    with open(path + ".tmp", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=RULE_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    os.replace(path + ".tmp", path)
    return rows


def policy_rule(rows: list[dict], seeds: int = RULE_SEEDS) -> dict:
    """The decision from `rows` (policy_rule_rows): the mean over runs of (mean-action return - sampled return),
    each variant weighted alike, judged as the claim "the mean action returns more" (stats.paired_claim on the
    differences of shape (seeds, variants): the exact sign-flip test over all 2^6 sign assignments and the t 95%
    interval with each variant a stratum, its own variance). ``policy`` is "mean-action" if the claim is supported
    (one-sided p < 0.05 and the interval above 0), "stochastic" if it is not (weak, or not supported), and None
    while a variant has fewer than `seeds` measured runs."""
    from stats import paired_claim

    by_variant = {v: sorted((r for r in rows if r["variant"] == v), key=lambda r: int(r["seed"])) for v in VARIANTS}
    counts = {v: len(mine) for v, mine in by_variant.items()}
    if min(counts.values()) < seeds:
        return {"policy": None, "counts": counts}
    diffs = np.array([[float(r["difference"]) for r in by_variant[v][:seeds]] for v in VARIANTS]).T  # (seeds, 2)
    claim = paired_claim(diffs)
    return {
        "policy": "mean-action" if claim["verdict"] == "supported" else "stochastic", "counts": counts,
        "mean": claim["estimate"], "ci": claim["ci"], "p": claim["p"], "n": claim["n"], "verdict": claim["verdict"],
    }  # fmt: skip


def policy_rule_table(rows: list[dict], decision: dict) -> str:
    """Markdown: the rule's rows and its decision."""
    lines = ["| variant | seed | updates | sampled | mean action | difference |", "|---|---|---|---|---|---|"]
    lines += [
        f"| {r['variant']} | {r['seed']} | {r['updates']} | {float(r['stochastic_return']):.1f} "
        f"| {float(r['mean_action_return']):.1f} | {float(r['difference']):+.1f} |"
        for r in rows
    ]
    tracks = rows[0]["tracks"] if rows else "-"
    if decision["policy"] is None:
        waiting = ", ".join(f"{v} {n} of {RULE_SEEDS}" for v, n in decision["counts"].items())
        verdict = f"No decision yet: the rule waits for {RULE_SEEDS} final policies per variant ({waiting})."
    else:
        low, high = decision["ci"]
        verdict = (
            f"Mean of (mean action - sampled) over {RULE_SEEDS} seeds per variant: {decision['mean']:+.1f} "
            f"[{low:+.1f}, {high:+.1f}] (t 95%, variants as strata; exact sign-flip p = {decision['p']:.3f} "
            f"one-sided, n = {decision['n']}): {decision['verdict']}. Evaluation policy: **{decision['policy']}**."
        )
    head = f"Final policies on the screening tracks {tracks}, both policies."
    return f"{head}\n\n" + "\n".join(lines) + f"\n\n{verdict}\n"
