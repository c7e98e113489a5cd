"""The paper's experiment's tables from its trials: ``ghost_vs_control.csv``, ``head_to_head.csv`` and
``experiment.md`` (``python benchmarks/experiment.py --aggregate-only``, and at the end of every experiment.py run;
``benchmarks/experiment.py`` runs the trials and says what the tables hold)."""

from __future__ import annotations

import csv
import dataclasses
import glob
import importlib
import json
import os

import numpy as np

import common
import learning
from experiment import (
    Spec, progress_text, race_tournament, tournament_checkpoints, tournament_metrics, tournament_racers,
    trial_dir, trial_kinds, trial_label, trial_progress,
)  # fmt: skip
from runs import updates_of

GHOST_COLUMNS = ("variant", "seed", "updates_at_start", "updates", "return_before", "return_after_ghost",
                 "return_after_control")  # fmt: skip
HEAD_COLUMNS = ("seed_pair", "races_trained", "eval_races", "lstm_wins", "gru_wins", "both_out", "no_winner",
                "dead_heats", "lstm_win_rate_ci_low", "lstm_win_rate_ci_high", "lstm_progress", "gru_progress",
                "lstm_eliminations", "gru_eliminations", "collision_steps")  # fmt: skip


def aggregate(spec: Spec) -> str:
    """ghost_vs_control.csv, head_to_head.csv and experiment.md from the trials there are; returns the summary.

    Only finished trials are results: a single, ghost or control trial that is finished (experiment.trial_progress:
    its updates made, its CPU budget spent, or stopped by the non-finite guard; the summary names it), and a seed
    pair whose tournament after the last head-to-head race exists. head_to_head.csv lists every tournament held so
    far; the statistics use the finished pairs, and the summary names what it left out. An experiment without
    controls keeps the ghost_vs_control.csv in spec.results and says how its ghost agents made again compare."""
    kept = None if spec.controls else kept_ghost_rows(spec)
    os.makedirs(spec.results, exist_ok=True)
    plain, first = dataclasses.asdict(spec), common.TRACKS["fresh"][0]
    single_returns: dict[str, list[float]] = {}
    ghost_rows, left_out, stopped = [], [], []
    for variant in spec.variants:
        for seed in spec.seeds:
            progress = trial_progress(plain, "single", variant, seed)
            run = progress.run
            if not progress.finished:
                left_out.append(progress_text(trial_label("single", variant, seed), progress))
                continue
            if progress.stopped:  # finished by the non-finite guard: counted, and named in the summary
                stopped.append(progress_text(trial_label("single", variant, seed), progress))

            def fresh(run: str, name: str) -> float:
                return fresh_return(spec, os.path.join(run, "checkpoints", name), first)

            single_returns.setdefault(variant, []).append(fresh(run, "latest.pt"))
            stage = {k: trial_progress(plain, k, variant, seed) for k in trial_kinds(plain, "ghost")}
            if not all(p.finished for p in stage.values()):
                left_out += [progress_text(trial_label(k, variant, seed), p) for k, p in stage.items()
                             if not p.finished]  # fmt: skip
                continue
            stopped += [progress_text(trial_label(k, variant, seed), p) for k, p in stage.items() if p.stopped]
            best = os.path.join(run, "checkpoints", "best.pt")
            start = updates_of(best, importlib.import_module(f"dreamer_{variant}"))
            ghost_rows.append({
                "variant": variant, "seed": seed, "updates_at_start": start, "updates": stage["ghost"].done - start,
                "return_before": fresh(run, "best.pt"),
                "return_after_ghost": fresh(stage["ghost"].run, "latest.pt"),
                "return_after_control": fresh(stage["control"].run, "latest.pt") if "control" in stage else None,
            })  # fmt: skip
    if kept is None:
        common.write_table(os.path.join(spec.results, "ghost_vs_control.csv"), ghost_rows, GHOST_COLUMNS)
        remade = ""
    else:
        remade, ghost_rows = remade_note(kept, ghost_rows), kept
    head_rows = []
    for seed in spec.seeds:
        tournaments = sorted(glob.glob(os.path.join(trial_dir(plain, "race", "lstm_gru", seed), "tournament_*[0-9]")))
        for tournament in tournaments:
            head_rows.append(head_row(seed, tournament_metrics(tournament, int(tournament.rsplit("_", 1)[1]))))
    common.write_table(os.path.join(spec.results, "head_to_head.csv"), head_rows, HEAD_COLUMNS)
    pairs = finished_pairs(head_rows, spec.race_episodes)
    final_rates = {v: [int(rs[-1][f"{v}_wins"]) / int(rs[-1]["eval_races"]) for rs in pairs.values()]
                   for v in ("lstm", "gru")}  # fmt: skip
    held = group_pairs(head_rows)
    for pair in (f"{seed},{seed}" for seed in spec.seeds if f"{seed},{seed}" not in pairs):
        how_far = (f"tournaments up to {held[pair][-1]['races_trained']} of {spec.race_episodes} races"
                   if pair in held else "not started")  # fmt: skip
        left_out.append(f"race pair {pair} ({how_far})")
    summary = summarize(single_returns, final_rates)
    summary += "\n" + claims_table(single_returns, ghost_rows, head_rows, spec.race_episodes)
    summary += remade
    if pairs:
        summary += training_wins_text(plain, [int(k.split(",")[0]) for k in pairs])
    if spec.second_policy == spec.eval_policy:
        print(f"experiment.py: --second-policy {spec.second_policy} is the experiment's --eval-policy: nothing to add")
    elif spec.second_policy is not None:
        summary += second_policy_claims(spec, head_rows)
    if left_out:
        summary += "\nNot finished, left out of the statistics: " + "; ".join(left_out) + ".\n"
    if stopped:
        summary += "\nCounted with their last policies: " + "; ".join(stopped) + ".\n"
    common.write_text(os.path.join(spec.results, "experiment.md"), summary)
    return summary


def training_race_wins(spec: dict, seed: int) -> dict[int, tuple[int, int]]:
    """Who won each head-to-head training race of seed pair (seed, seed): {race: (LSTM won, GRU won)}, (1, 1) a
    dead heat, from the progress.csv of each sitting of race.py --train in the intervals. It logs each racer's win
    rate over the last 20 races of the sitting, w_k after its k-th race, so that race was won iff
    min(k, 20)·w_k - min(k-1, 20)·w_{k-1} (plus the outcome of race k-20 once the window is full) is 1. A race
    whose row is missing (race.py writes it after both checkpoints: a kill between the two) is missing here."""
    wins: dict[int, tuple[int, int]] = {}
    directory = trial_dir(spec, "race", "lstm_gru", seed)
    # the sittings in the order they ran: run directories are named <env>__<exp>__<seed>__<start time>
    for path in sorted(glob.glob(os.path.join(directory, "races_*[0-9]", "*", "progress.csv")),
                       key=lambda p: os.path.basename(os.path.dirname(p))):  # fmt: skip
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get("charts/race")]
        outcomes = []
        for racer in ("racer_0_lstm", "racer_1_gru"):
            rates, won = [float(r[f"{racer}/charts/win_rate"]) for r in rows], []
            for k in range(1, len(rates) + 1):
                x = min(k, 20) * rates[k - 1] - (min(k - 1, 20) * rates[k - 2] if k > 1 else 0.0)
                x += won[k - 21] if k > 20 else 0
                if abs(x - round(x)) > 1e-6 or round(x) not in (0, 1):
                    raise ValueError(f"{path}: {racer}'s win rate after row {k} is not a 20-race window of wins")
                won.append(round(x))
            outcomes.append(won)
        for r, lstm, gru in zip(rows, *outcomes):
            wins[int(float(r["charts/race"]))] = (lstm, gru)
    return wins


def training_wins_text(spec: dict, pairs: list[int]) -> str:
    """Markdown: the training races' outcomes of each finished seed pair per interval of tournament_every races,
    descriptive only (the agents change from race to race, and the tracks are the pair's training tracks), with
    the races whose outcome the logs lack named."""
    every, parts, missing = spec["tournament_every"], [], []
    for seed in pairs:
        wins, counts = training_race_wins(spec, seed), []
        for start in range(0, spec["race_episodes"], every):
            block = [wins[k] for k in range(start + 1, start + every + 1) if k in wins]
            heats = block.count((1, 1))
            counts.append(f"{sum(w == (1, 0) for w in block)}-{sum(w == (0, 1) for w in block)} "
                          f"({block.count((0, 0))}{f', {heats} dead heats' if heats else ''})")  # fmt: skip
            if len(block) < every:
                missing.append(f"{seed},{seed}: {every - len(block)} of races {start + 1}..{start + every}")
        parts.append(f"{seed},{seed}: " + ", ".join(counts))
    lacking = f" The logs lack the outcome of {'; '.join(missing)}." if missing else ""
    return (f"\nThe training races (both agents learning and sampling their actions, on the pair's training tracks; "
            f"read from the logs, descriptive): LSTM wins - GRU wins (neither) in each interval of {every} races, per "
            f"seed pair: {'; '.join(parts)}.{lacking}\n")


def head_row(seed: int, metrics: dict) -> dict:
    """A row of head_to_head.csv: seed pair (seed, seed) and one tournament's metrics (tournament_metrics)."""
    return {"seed_pair": f"{seed},{seed}",
            **{k: round(metrics[k], 4) if isinstance(metrics[k], float) else metrics[k] for k in HEAD_COLUMNS[1:]}}


def second_policy_claims(spec: Spec, head_rows: list[dict]) -> str:
    """The tournaments of `head_rows` raced again with spec.second_policy (the same checkpoints, held-out tracks and
    starts; each raced once, kept as tournament_<races>_<policy>/ beside the tournament), written to
    head_to_head_<policy>.csv; returns markdown: the head-to-head claims measured with that policy."""
    plain, policy, rows = dataclasses.asdict(spec), spec.second_policy, []
    for r in head_rows:
        seed, trained = int(r["seed_pair"].split(",")[0]), int(r["races_trained"])
        out = os.path.join(trial_dir(plain, "race", "lstm_gru", seed), f"tournament_{trained:05d}_{policy}")
        if not os.path.exists(os.path.join(out, "results.json")):
            race_tournament(plain, tournament_checkpoints(plain, seed, trained), policy, out)
        held = os.path.join(os.path.dirname(out), f"tournament_{trained:05d}")
        if tournament_racers(held) != tournament_racers(out):
            raise ValueError(f"{out} raced {tournament_racers(out)}, not the agents of {held} "
                             f"({tournament_racers(held)}): remove it to race it again with the tournament's own "
                             f"checkpoints")  # fmt: skip
        rows.append(head_row(seed, tournament_metrics(out, trained)))
    common.write_table(os.path.join(spec.results, f"head_to_head_{policy}.csv"), rows, HEAD_COLUMNS)
    table = claims_table({}, [], rows, spec.race_episodes)
    again = finished_pairs(rows, spec.race_episodes)
    ends = [(rs[-1], again[pair][-1]) for pair, rs in finished_pairs(head_rows, spec.race_episodes).items()]
    shift = ""
    if ends:
        rate = lambda r: int(r["lstm_wins"]) / int(r["eval_races"])  # noqa: E731
        shift = policy_shift([rate(a) - rate(b) for a, b in ends], spec.eval_policy, policy)
    return (f"\nThe same tournaments raced again with the {policy} policy (the same checkpoints, held-out tracks and "
            f"starts; head_to_head_{policy}.csv).{shift}\n\n{table}")


def policy_shift(diffs: list[float], policy: str, second: str) -> str:
    """A sentence: the LSTM's win rate in the last tournaments with `policy` minus with `second`, per seed pair, its
    mean with the t 95% interval and the exact sign-flip test, two-sided (no side is claimed beforehand): whether the
    policy changes the win rate ("weak" while the test does not reach stats.ALPHA or the interval includes 0)."""
    from stats import ALPHA, MIN_RUNS, sign_flip_test, t_interval

    mean, (low, high) = t_interval(diffs)
    p, n = sign_flip_test(diffs, "two-sided"), len(diffs)
    interval = "no interval" if n < MIN_RUNS else f"t 95% [{low:+.2f}, {high:+.2f}]"
    if n < MIN_RUNS:
        judged = f"too few pairs to judge (n = {n})"
    elif p < ALPHA and (low > 0 or high < 0):
        judged = "the policy changes the win rate"
    elif mean != 0:
        why = f"p = {p:.3f} is not below {ALPHA}" if p >= ALPHA else "the t interval includes 0"
        judged = f"weak evidence that the policy changes the win rate ({why})"
    else:
        judged = "no sign that the policy changes the win rate"
    return (f" In the last tournaments the LSTM's win rate with the {policy} policy - with the {second} policy is "
            f"{mean:+.2f} (sign-flip p={p:.3f} two-sided, {interval}, n={n}) over {n} seed pairs "
            f"({', '.join(f'{d:+.2f}' for d in diffs)}): {judged}.")  # fmt: skip


def kept_ghost_rows(spec: Spec) -> list[dict]:
    """The ghost_vs_control.csv in spec.results, which an experiment without controls keeps (it cannot measure it):
    refused unless it has a row for every variant and seed of the experiment."""
    path = os.path.join(spec.results, "ghost_vs_control.csv")
    if not os.path.exists(path):
        problem = "does not exist"
    else:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        have = {(r["variant"], int(r["seed"])) for r in rows}
        missing = [f"{v} seed {s}" for v in spec.variants for s in spec.seeds if (v, s) not in have]
        if not missing:
            return rows
        problem = f"has no row for {', '.join(missing)}"
    raise SystemExit(f"experiment.py: without controls the ghost-vs-control table measured before is kept, and {path} "
                     f"{problem}: run the controls, or give --results the directory of the measured table (restore "
                     f"it with git if an aggregation with controls emptied it)")  # fmt: skip


def remade_note(kept: list[dict], remade: list[dict]) -> str:
    """Markdown: the ghost agents made again without controls, their return before and after the ghost stage
    against the kept table's for the same variant and seed, and the largest difference."""
    table = {(r["variant"], int(r["seed"])): r for r in kept}  # (it has every variant and seed: kept_ghost_rows)
    parts, worst = [], 0.0
    for r in remade:
        old = table[(r["variant"], int(r["seed"]))]
        pairs = [(float(r[c]), float(old[c])) for c in ("return_before", "return_after_ghost")]
        worst = max([worst] + [abs(new - was) for new, was in pairs])
        parts.append(f"{r['variant']} seed {r['seed']} " + " -> ".join(f"{new:.2f} ({was:.2f})" for new, was in pairs))
    return (f"\nThe ghost row is the ghost_vs_control.csv measured before: this experiment's ghost stage ran without "
            f"controls. Its ghost agents made again, return on the fresh tracks before -> after the ghost stage (the "
            f"table's in brackets): {'; '.join(parts) or 'none finished yet'}. Largest difference: {worst:.2f}.\n")


def group_pairs(head_rows: list[dict]) -> dict[str, list[dict]]:
    """The tournaments of each seed pair, in the order of the races trained before them."""
    pairs: dict[str, list[dict]] = {}
    for r in head_rows:
        pairs.setdefault(r["seed_pair"], []).append(r)
    return {k: sorted(rs, key=lambda r: int(r["races_trained"])) for k, rs in pairs.items()}


def finished_pairs(head_rows: list[dict], race_episodes: int) -> dict[str, list[dict]]:
    """The seed pairs whose head-to-head training is done (a tournament after `race_episodes` races), each with its
    tournaments in order: pairs at different lengths would not measure the same thing."""
    return {k: rs for k, rs in group_pairs(head_rows).items() if int(rs[-1]["races_trained"]) == race_episodes}


def fresh_return(spec: Spec, path: str, first: int) -> float:
    """The return of the checkpoint at `path` on the fresh tracks (spec.fresh_tracks from `first`, with
    spec.eval_policy), measured once: kept in <storage>/evaluations.json under the file's path, size and
    modification time, so a rerun of the aggregation measures only checkpoints that are new or have changed."""
    cache_path = os.path.join(spec.storage, "evaluations.json")
    try:
        with open(cache_path) as f:
            cache = json.load(f)
    except (OSError, ValueError):  # none yet (or unreadable): measured again, nothing is lost
        cache = {}
    stat = os.stat(path)
    key = f"{os.path.abspath(path)}|{stat.st_size}|{stat.st_mtime_ns}|{spec.eval_policy}|{first}|{spec.fresh_tracks}"
    if key not in cache:
        cache[key] = learning.policy_summary(path, first, spec.fresh_tracks, spec.eval_policy)["eval_return"]
        os.makedirs(spec.storage, exist_ok=True)
        common.write_json(cache_path, cache)
    return cache[key]


def summarize(single_returns: dict[str, list[float]], final_rates: dict[str, list[float]], reps: int = 2000) -> str:
    """Markdown: IQM and mean of the single-stage final returns per variant (stratified bootstrap, 95%), and the
    probability that the LSTM's final head-to-head win rate exceeds the GRU's across seed pairs: the share of
    pairs in which it does, each pair's two rates measured in the same tournament races (paired; a bootstrap over
    pairs). `final_rates` holds each variant's rates in the same order of pairs."""
    from stats import interval_estimates, paired_probability_of_improvement

    lines = ["| variant | seeds | IQM final return [95% CI] | mean final return [95% CI] |", "|---|---|---|---|"]
    if single_returns:
        estimates = interval_estimates({k: np.asarray(v)[:, None] for k, v in single_returns.items()}, reps=reps)
        for variant, e in estimates.items():
            iqm = f"{e['iqm']:.1f} [{e['iqm_ci'][0]:.1f}, {e['iqm_ci'][1]:.1f}]"
            mean = f"{e['mean']:.1f} [{e['mean_ci'][0]:.1f}, {e['mean_ci'][1]:.1f}]"
            lines.append(f"| {variant} | {len(single_returns[variant])} | {iqm} | {mean} |")
    if final_rates["lstm"]:
        p = paired_probability_of_improvement(final_rates["lstm"], final_rates["gru"], reps)
        lines += ["", f"P(LSTM win rate > GRU win rate), paired: the share of {len(final_rates['lstm'])} seed "
                      f"pair(s) whose final tournament the LSTM won more often (bootstrap over pairs): "
                      f"{p['p']:.2f} [{p['ci'][0]:.2f}, {p['ci'][1]:.2f}]"]  # fmt: skip
    return "\n".join(lines) + "\n"


def claims_table(single_returns: dict[str, list[float]], ghost_rows: list[dict], head_rows: list[dict],
                 race_episodes: int) -> str:  # fmt: skip
    """Markdown: each claim of the paper, what measures it here, the estimate, its test (the exact one-sided p of the
    claim, the t 95% interval, the units) and the verdict (stats.judge: "supported" needs p < 0.05 and the interval
    above 0, "weak" a positive estimate short of that; "too few runs" below stats.MIN_RUNS). Solo: LSTM mean - GRU
    mean of the single-stage final returns (independent runs: the exact permutation test over every split of the
    runs, Welch's t interval). Head to head, over the seed pairs that finished `race_episodes` races: per pair the
    LSTM's minus the GRU's win rate in the last tournament (the same races: paired); each agent's progress in the
    tournament before head-to-head training minus in the first after it (both must drop: one row per agent); the
    LSTM's win rate at the last tournament minus at the first after training began; the mean over pairs with the
    exact sign-flip test and the t interval of the differences (each pair's Wilson interval is in
    head_to_head.csv). Ghost: return after the ghost stage minus after its control, per variant and seed (paired
    likewise). A note under the table says when a row is over so few units that its exact test cannot reach 0.05
    (stats.SMALL_SAMPLE_NOTE)."""
    from stats import ALPHA, MIN_RUNS, SMALL_SAMPLE_NOTE, describe, paired_claim, two_group_claim

    floors = []

    def row(claim: str, measured: str, judged: dict, digits: int = 1) -> str:
        floors.append(judged["min_p"] if judged["n"] >= MIN_RUNS else 0.0)
        return (f"| {claim} | {measured} | {judged['estimate']:.{digits}f} | {describe(judged, digits)} "
                f"| {judged['verdict']} |")  # fmt: skip

    lines = ["| claim of the paper | what we measured | estimate | test (one-sided p of the claim) | verdict |",
             "|---|---|---|---|---|"]  # fmt: skip
    lstm, gru = single_returns.get("lstm", []), single_returns.get("gru", [])
    if lstm and gru:
        lines.append(row(
            "the LSTM-Dreamer beats the GRU-Dreamer as a solo agent",
            f"final single-stage return on the fresh tracks, LSTM mean - GRU mean ({len(lstm)} and {len(gru)} seeds)",
            two_group_claim(lstm, gru),
        ))  # fmt: skip
    ends = list(finished_pairs(head_rows, race_episodes).values())
    ends = [rs for rs in ends if any(int(r["races_trained"]) > 0 for r in rs)]  # (race_episodes 0: no training)
    if ends:
        rate = {"lstm": lambda r: int(r["lstm_wins"]) / int(r["eval_races"]),
                "gru": lambda r: int(r["gru_wins"]) / int(r["eval_races"])}  # fmt: skip
        above = sum(float(rs[-1]["lstm_win_rate_ci_low"]) > 0.5 for rs in ends)
        lines.append(row(
            "the LSTM-Dreamer beats the GRU-Dreamer head to head",
            f"last tournament (after {race_episodes} races): LSTM win rate - GRU win rate, mean over {len(ends)} seed "
            f"pairs; the LSTM's Wilson interval above 0.5 in {above} of {len(ends)}",
            paired_claim([rate["lstm"](rs[-1]) - rate["gru"](rs[-1]) for rs in ends]), digits=2,
        ))  # fmt: skip
        # the first tournament after head-to-head training began (the one at 0 is before it)
        firsts = [next(r for r in rs if int(r["races_trained"]) > 0) for rs in ends]
        before = [(rs[0], first) for rs, first in zip(ends, firsts) if int(rs[0]["races_trained"]) == 0]
        for v, name in (("lstm", "LSTM"), ("gru", "GRU")) if before else ():
            lines.append(row(
                f"head-to-head training first perturbs both agents: the {name}",
                f"the {name}'s mean progress in the tournament before head-to-head training - in the first after it "
                f"(races 0 to {firsts[0]['races_trained']}), mean over {len(before)} seed pairs",
                paired_claim([float(r0[f"{v}_progress"]) - float(r1[f"{v}_progress"]) for r0, r1 in before]),
                digits=2,
            ))  # fmt: skip
        lines.append(row(
            "trained against each other, the LSTM recovers (about race 120) and outperforms",
            f"LSTM win rate at the last tournament - at the first after training began (races "
            f"{firsts[0]['races_trained']} to {race_episodes}), mean over {len(ends)} seed pairs",
            paired_claim([rate["lstm"](rs[-1]) - rate["lstm"](first) for rs, first in zip(ends, firsts)]), digits=2,
        ))  # fmt: skip
    if ghost_rows:
        diffs = [float(r["return_after_ghost"]) - float(r["return_after_control"]) for r in ghost_rows]
        lines.append(row(
            "racing a ghost of its best run improves an agent (the curriculum's second stage)",
            f"return on the fresh tracks after the ghost stage - after its control (same start, same updates), "
            f"{len(diffs)} (variant, seed) pairs",
            paired_claim(diffs),
        ))  # fmt: skip
    if any(floor >= ALPHA for floor in floors):
        lines += ["", SMALL_SAMPLE_NOTE]
    return "\n".join(lines) + "\n"

