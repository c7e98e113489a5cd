"""The paper's experiment end to end, as Ray Tune trials: single -> ghost (and its control) -> head to head.

    python benchmarks/experiment.py                                   # the CPU-preset experiment on this machine
    python benchmarks/experiment.py --seeds 11 12 13 --race-episodes 150 --tournament-every 50
    python benchmarks/experiment.py --address auto --gpus-per-trial 1 --torch-threads 4   # on a Ray cluster
    python benchmarks/experiment.py --aggregate-only                  # only the CSVs and the rliable summary
    python benchmarks/experiment.py --aggregate-only --second-policy stochastic   # and the tournaments sampled
    python benchmarks/experiment.py --status                          # where each trial stands (nothing runs)

Every (variant, seed, stage) is one Ray Tune trial (``ray.init()`` on this machine unless ``--address``; each
trial asks for ``--torch-threads`` CPUs, so two share two cores, and ``--gpus-per-trial`` GPUs). A trial is an
ordinary run directory of the dreamer scripts (TensorBoard, ``latest.pt``, replay) under
``<storage>/trials/<stage>_<variant>_seed<S>/``; it works in chunks of ``--report-every`` updates (or one
tournament interval of races), reports its latest evaluation to Tune after each, and continues from its own
``latest.pt``, so a trial Ray retries after its worker died (``--max-failures``) and a trial left unfinished by an
earlier command both resume where they stopped. Running the same command again skips finished trials (Tune
restores each stage's experiment). The stages follow the paper and run one after the other:

* ``single``: one car from scratch, ``--single-updates`` updates (with ``--single-cpu-hours``: until that CPU
  budget is spent); ``best.pt`` keeps the best evaluation.
* ``ghost``: from the single trial's ``best.pt`` of the same variant and seed, ``--ghost-updates`` more updates
  racing the agent's own best runs; ``control`` continues ``single`` from the same ``best.pt`` for as many
  updates without a ghost, so the ghost's effect is measured rather than assumed.
* ``race``: per seed pair (s, s), the LSTM and the GRU ghost-stage agents race each other and both keep learning
  (``race.py --train``, ``--race-train-steps`` updates per agent per race), with a tournament every
  ``--tournament-every`` races: ``--tournament-races`` evaluation races on held-out tracks, start positions
  swapped fairly, the LSTM's win rate with a Wilson 95% interval.

Then it writes (``benchmarks/experiment_report.py``) ``benchmarks/results/ghost_vs_control.csv``,
``head_to_head.csv`` and ``experiment.md`` (IQM and mean of the single-stage final returns per variant with
stratified-bootstrap intervals, and the probability that the LSTM's head-to-head win rate exceeds the GRU's across
seed pairs, both with rliable: descriptions), and the table of the paper's claims, each judged by an exact test
(sign-flip over seed pairs, stats.paired_claim; permutation between two groups, stats.two_group_claim) and a t
interval (a bootstrap is too narrow over so few runs); with ``--second-policy`` the head-to-head claims again, every
tournament raced with that policy too.
"""

from __future__ import annotations

import csv
import dataclasses
import glob
import importlib
import json
import math
import os
import shutil
import signal
import sys
import types
import typing
from typing import Literal, NamedTuple

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import RESULTS, checkpoint_updates, write_json  # noqa: E402
from runs import cpu_hours_of, experiment_name, numerical_stop, run_of, updates_of  # noqa: E402

TOURNAMENT_SEED = 7_777  # held-out tracks of the tournaments (training races use the pair's seed)
NO_UPDATE_TARGET = 10**12  # the update target of a trial that a CPU budget ends (--single-cpu-hours)
SINGLE_UPDATES = 8000  # a single-stage trial's updates by default (the 8,000-update protocol's runs)
# What a single-stage trial adds to the preset: one car; its evaluations (every --eval-every races) on the 10
# held-out tracks 10000..10009, each evaluated policy kept (checkpoints/eval_<race>.pt)
SINGLE_CONFIG = {"stage": "single", "num_agents": 1, "eval_episodes": 10, "eval_checkpoints": True}


@dataclasses.dataclass
class Spec:
    variants: tuple[Literal["lstm", "gru"], ...] = ("lstm", "gru")
    """variants of the single and ghost stages (the race stage needs both)"""
    seeds: tuple[int, ...] = (11, 12, 13)
    """seeds of every stage; the race stage pairs the LSTM and GRU agents of the same seed"""
    stages: tuple[Literal["single", "ghost", "race"], ...] = ("single", "ghost", "race")
    """stages to run (a later stage needs the earlier ones finished)"""
    preset: Literal["paper", "cpu"] = "cpu"
    """the dreamer scripts' --preset"""
    overrides: tuple[str, ...] = ()
    """more flags of the dreamer scripts as name=value (e.g. entropy_coef=0.5), on top of the preset"""
    single_updates: int = SINGLE_UPDATES
    """updates of a single-stage trial"""
    single_cpu_hours: float = 0.0
    """if > 0, a single-stage trial ends when its run has used this many CPU-hours (process CPU time over all its
    sittings, the dreamer scripts' --cpu-hours-limit; the final protocol's budget, 3.1, is the PPO peer's) instead
    of at --single-updates: its final policy is the one it has when the budget runs out"""
    ghost_updates: int = 2000
    """updates of a ghost-stage trial beyond its starting best.pt (and of its control)"""
    controls: bool = True
    """run each ghost trial's control. Without them (--no-controls) the ghost stage trains only the ghost agents the
    race stage starts from: for an experiment whose ghost-vs-control table is measured and kept in --results but
    whose trial directories were lost. The same seed and code are expected to make the same agents, so the
    aggregation keeps that table and checks it against the ghost agents made again. It may change until the ghost
    stage begins"""
    race_episodes: int = 150
    """head-to-head training races per seed pair"""
    tournament_every: int = 50
    """races between tournaments (checkpoints of both agents)"""
    tournament_races: int = 100
    """evaluation races per tournament (held-out tracks, each raced twice with the start positions swapped: even)"""
    race_train_steps: int = 25
    """updates per agent after every head-to-head race"""
    eval_policy: Literal["deterministic", "mean-action", "stochastic"] = "mean-action"
    """the agents' policy in the tournaments and in the fresh-track measurements (race.py --policy): the mean
    action from a sampled latent (the default, as in race.py and the dreamer scripts), sampled as trained, or the
    mean action from the posterior-mean latent; head-to-head training races are always sampled; also the
    evaluation policy (--eval-policy) of the dreamer trials, which selects their best.pt. It may change until the
    race stage begins (the tables measured before are measured again with the new policy); a stage already
    started keeps the policy it started with (its trials and their best.pt)"""
    second_policy: Literal["deterministic", "mean-action", "stochastic"] | None = None
    """a second policy for the head-to-head tournaments, asked of the aggregation (it changes no trial): every
    tournament's two checkpoints race again on the same held-out tracks with it (kept beside the tournament as
    tournament_<races>_<policy>/, raced once), into head_to_head_<policy>.csv and a second table of the head-to-head
    claims in experiment.md. The verdicts stay those of --eval-policy; this shows whether they depend on it
    (e.g. stochastic: the policy the agents race with in their training races)"""
    report_every: int = 500
    """updates of a dreamer trial between its reports to Tune"""
    fresh_tracks: int = 20
    """tracks (from 10100) on which ghost_vs_control.csv measures the agents"""
    storage: str = os.path.join(ROOT, "runs", "experiment")
    """where the trials' run directories and Tune's experiment state go"""
    name: str = "dlc"
    """experiment name (one Tune experiment per stage: <name>_<stage>)"""
    torch_threads: int = 1
    """torch threads, and CPUs Ray reserves, per trial"""
    gpus_per_trial: float = 0.0
    """GPUs Ray reserves per trial (on a cluster with GPUs)"""
    num_cpus: int | None = None
    """CPUs a local Ray offers the trials (default: the machine's cores); num_cpus // torch_threads trials run at
    once. More than the cores time-shares them, which changes no result (each trial is its own seeded process) and
    keeps every core busy when a stage has fewer trials left than the cores: the race stage's three seed pairs on
    two cores run at once with --num-cpus 3, instead of two and then one alone"""
    address: str | None = None
    """address of a Ray cluster (default: a local Ray on this machine); --storage must then be a filesystem every
    node mounts at the same path (later stages start from earlier trials' checkpoints)"""
    max_failures: int = 2
    """times Ray retries a trial whose worker died (it resumes from its latest.pt)"""
    aggregate_only: bool = False
    """only write the result CSVs and the summary from existing trials"""
    status: bool = False
    """only print where each trial of the experiment in --storage stands, read from its run directories (no Ray,
    nothing trained or measured)"""
    results: str = RESULTS
    """directory of ghost_vs_control.csv, head_to_head.csv and experiment.md"""
    chaos_kill_after_updates: int = 0
    """testing aid: each single-stage trial kills its own worker once (SIGKILL) after this many updates (0: never)"""


# --- Trials ----------------------------------------------------------------------------------
def trial_dir(spec: dict, stage: str, variant: str, seed: int) -> str:
    """Where a trial's run directories go: <storage>/trials/<trial_label>."""
    return os.path.join(spec["storage"], "trials", trial_label(stage, variant, seed))


def start_checkpoint(spec: dict, stage: str, variant: str, seed: int, name: str) -> str:
    """checkpoints/<name> of the finished `stage` trial a later stage starts from, or an error naming what is
    missing (on a cluster: a worker whose node does not see the driver's --storage)."""
    run = run_of(trial_dir(spec, stage, variant, seed))
    path = os.path.join(run, "checkpoints", name) if run else None
    if path is None or not os.path.exists(path):
        raise FileNotFoundError(
            f"the {stage} trial of {variant} seed {seed} has no checkpoints/{name} under "
            f"{trial_dir(spec, stage, variant, seed)}; a later stage starts from it. On a Ray cluster every node must "
            f"see --storage at the same path (a shared filesystem)"
        )  # fmt: skip
    return path


def parse_overrides(script, overrides) -> dict:
    """name=value pairs, each converted to the type its field of the script's Args is annotated with (bool: 1, true,
    yes or 0, false, no; an optional field: none; a Literal: one of its values); a bad name or value fails loudly."""
    fields, values = {f.name: f for f in dataclasses.fields(script.Args)}, {}
    hints = typing.get_type_hints(script.Args, include_extras=False)
    for item in overrides:
        name, _, text = item.partition("=")
        if name not in fields or not _:
            raise ValueError(f"--overrides: {item!r} is not name=value with a field of {script.__name__}.Args")
        try:
            values[name] = convert(text, hints[name])
        except ValueError as e:
            raise ValueError(f"--overrides: {item!r}: {e}") from None
    return values


def convert(text: str, kind) -> object:
    """`text` as a value of the annotation `kind` (bool, int, float, str, a Literal, or one of them | None)."""
    if typing.get_origin(kind) in (typing.Union, types.UnionType) and type(None) in typing.get_args(kind):
        if text.lower() == "none":
            return None
        kind = next(k for k in typing.get_args(kind) if k is not type(None))
    if typing.get_origin(kind) is Literal:
        choices = typing.get_args(kind)
        match = [c for c in choices if str(c) == text]
        if not match:
            raise ValueError(f"must be one of {', '.join(map(str, choices))}")
        return match[0]
    if kind is bool:
        if text.lower() not in ("1", "true", "yes", "0", "false", "no"):
            raise ValueError("must be true or false")
        return text.lower() in ("1", "true", "yes")
    return kind(text)


def trial_args(spec: dict, stage: str, variant: str, seed: int):
    """The dreamer script of a single, ghost or control trial, the Args of its run, the updates it starts from
    (None: from scratch) and the updates it ends at."""
    script = importlib.import_module(f"dreamer_{variant}")
    settings = {**parse_overrides(script, spec["overrides"]), "torch_threads": spec["torch_threads"], "seed": seed,
                "eval_policy": spec["eval_policy"]}  # fmt: skip
    if stage == "single":
        first, target = None, spec["single_updates"]
        if spec["single_cpu_hours"] > 0:  # the budget ends the trial (dreamer_trial), whatever the updates
            settings["cpu_hours_limit"], target = spec["single_cpu_hours"], NO_UPDATE_TARGET
        # named learning_<variant> (the 8,000-update protocol's runs, so its storage resumes) unless the spec changes
        # the preset, a flag, the updates, the threads or the evaluation policy (which picks best.pt): the scripts'
        # default, or the sampled policy the 8,000-update protocol's runs were made with
        plain = spec["preset"] == "cpu" and not spec["overrides"]
        plain = plain and spec["single_updates"] == SINGLE_UPDATES
        plain = plain and spec["single_cpu_hours"] == 0
        plain = plain and spec["torch_threads"] == 1
        plain = plain and spec["eval_policy"] in (script.Args().eval_policy, "stochastic")
        args = script.preset_args(
            spec["preset"], exp_name=experiment_name(variant) if plain else f"{variant}_single",
            **{**SINGLE_CONFIG, **settings},
        )  # fmt: skip
    else:  # ghost, or its control: from the single trial's best.pt, for as many updates
        best = start_checkpoint(spec, "single", variant, seed, "best.pt")
        first = updates_of(best, script)
        target = first + spec["ghost_updates"]
        ghost = stage == "ghost"
        # the control starts updating after as many races as the ghost stage (one per ghost track)
        prefill = {} if ghost else {"prefill_episodes": settings.get("ghost_tracks", script.Args().ghost_tracks)}
        args = script.preset_args(
            spec["preset"], stage="ghost" if ghost else "single", exp_name=f"{variant}_{stage}", checkpoint=best,
            **{**settings, **prefill},
        )  # fmt: skip
    args = dataclasses.replace(args, runs_dir=trial_dir(spec, stage, variant, seed), total_episodes=10**9)
    return script, args, first, target


def dreamer_trial(config: dict) -> None:
    """A single, ghost or control trial: the dreamer script's run, in chunks of report_every updates, each resumed
    from latest.pt, with the latest evaluation reported to Tune after every chunk. It ends when trial_progress says
    it is finished: its updates made, its CPU budget spent, or the scripts' non-finite guard stopped the run (that
    stop is kept: the run is not resumed, by this loop or by Tune's retries)."""
    from ray import tune

    from utils.run import NumericalFault

    config = config["trial"]  # (the grid puts each trial's settings under "trial")
    spec = restored_spec(config["spec"])
    stage, variant, seed = config["stage"], config["variant"], config["seed"]
    script, args, first, target = trial_args(spec, stage, variant, seed)
    directory = trial_dir(spec, stage, variant, seed)
    goal = (first or 0) + spec["report_every"]
    while True:
        # latest.pt, not progress.csv, says what is done: a kill between its save and the csv row (the end of a
        # race) leaves the csv a race behind, and the trial must still end
        progress = trial_progress(spec, stage, variant, seed)
        if not progress.finished:  # (a trial restored after its end trains no more)
            try:
                # the run pauses every report_every updates (to report to Tune); its budget stays the trial's
                budget = 0 if target == NO_UPDATE_TARGET else target  # (a CPU budget: --cpu-hours-limit)
                chunk = {"total_updates": budget, "pause_at_updates": min(goal, target)}
                if progress.run is None:
                    script.main(dataclasses.replace(args, **chunk))
                elif progress.done < min(goal, target):
                    script.main(script.Args(resume=progress.run, **chunk), set(chunk))
            except NumericalFault as fault:  # the guard stopped the run and saved latest.pt: the trial ends with it
                print(f"experiment.py: {trial_label(stage, variant, seed)}: {fault}", flush=True)
                if not trial_progress(spec, stage, variant, seed).stopped:  # (a stop its latest.pt does not show)
                    raise
            progress = trial_progress(spec, stage, variant, seed)
        run, done, end = progress.run, progress.done, progress.target
        tune.report({**latest_metrics(run), "numerical_stop": int(progress.stopped)})
        chaos = spec["chaos_kill_after_updates"]
        marker = os.path.join(directory, "chaos_killed")
        if chaos and stage == "single" and done >= chaos and not os.path.exists(marker):
            open(marker, "w").close()
            os.kill(os.getpid(), signal.SIGKILL)  # a dying worker: Ray retries the trial, which resumes
        if done >= end:
            return
        goal = max(goal, done) + spec["report_every"]


def latest_metrics(run: str) -> dict:
    """The run's counters and its latest evaluation (from its progress.csv)."""
    with open(os.path.join(run, "progress.csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    evaluated = [r for r in rows if r.get("car_0/eval/episodic_return")]
    last = evaluated[-1] if evaluated else (rows[-1] if rows else {})
    updates = [r for r in rows if r.get("car_0/perf/updates")]

    def number(row: dict, key: str) -> float:
        return float(row[key]) if row.get(key) else float("nan")

    return {
        "races": int(float(rows[-1]["charts/episode"])) if rows else 0,
        "updates": int(float(updates[-1]["car_0/perf/updates"])) if updates else 0,
        "eval_return": number(last, "car_0/eval/episodic_return"),
        "eval_progress": number(last, "car_0/eval/progress"),
        "eval_mean_abs_steer": number(last, "car_0/eval/mean_abs_steer"),
    }


def race_trial(config: dict) -> None:
    """Seed pair (s, s): the LSTM and GRU ghost-stage agents race and learn (race.py --train) in intervals of
    tournament_every races; before the first and after each, a tournament on held-out tracks, reported to Tune.
    A finished tournament is kept (its results.json). An interval cut short continues from the newest pair of racer
    checkpoints it saved after the same race (race.py saves both after every race), so a sitting's end costs at
    most the race in progress; a trained interval whose tournament was cut short only races the tournament."""
    from ray import tune

    import race

    config = config["trial"]
    spec, seed = restored_spec(config["spec"]), config["seed"]
    directory = trial_dir(spec, "race", "lstm_gru", seed)
    checkpoints = tournament_checkpoints(spec, seed, 0)
    threads = ["--torch-threads", str(spec["torch_threads"])]
    for trained in range(0, spec["race_episodes"] + 1, spec["tournament_every"]):
        tournament = os.path.join(directory, f"tournament_{trained:05d}")
        done = os.path.join(tournament, "results.json")
        if trained > 0:  # (the tournament at 0: the ghost-stage agents before any head-to-head race)
            interval = os.path.join(directory, f"races_{trained:05d}")
            found = interval_racers(interval)
            if found is None or found[1] < trained:
                start, before = found or (checkpoints, trained - spec["tournament_every"])
                if found is None:
                    shutil.rmtree(interval, ignore_errors=True)  # nothing to continue from: race it again
                race.main([*start, "--train", "--episodes", str(trained - before), "--seed", str(seed),
                           "--train-steps", str(spec["race_train_steps"]), "--runs-dir", interval,
                           *threads])  # fmt: skip
                found = interval_racers(interval)
            checkpoints = found[0]
        if not os.path.exists(done):
            race_tournament(spec, checkpoints, spec["eval_policy"], tournament)
        tune.report(tournament_metrics(tournament, trained))


def race_tournament(spec: dict, checkpoints: list[str], policy: str, out: str) -> None:
    """One tournament: spec["tournament_races"] races of the two checkpoints on the held-out tracks (seed
    TOURNAMENT_SEED, each track from both starts) with `policy`, written to `out` whole or not at all."""
    import race

    race.main([*checkpoints, "--races", str(spec["tournament_races"]), "--seed", str(TOURNAMENT_SEED),
               "--policy", policy, "--out", out + ".tmp", "--no-video",
               "--torch-threads", str(spec["torch_threads"])])  # fmt: skip
    shutil.rmtree(out, ignore_errors=True)
    os.replace(out + ".tmp", out)


def tournament_checkpoints(spec: dict, seed: int, trained: int) -> list[str]:
    """The LSTM's and the GRU's checkpoints that raced the tournament after `trained` head-to-head races of seed
    pair (seed, seed): the ghost-stage agents at 0, else the pair both racers saved after race `trained`."""
    if trained == 0:
        return [start_checkpoint(spec, "ghost", variant, seed, "latest.pt") for variant in ("lstm", "gru")]
    interval = os.path.join(trial_dir(spec, "race", "lstm_gru", seed), f"races_{trained:05d}")
    found = interval_racers(interval, prune=False)
    if found is None or found[1] != trained:
        raise FileNotFoundError(f"{interval} holds no pair of racer checkpoints saved after race {trained}")
    return found[0]


def interval_racers(interval: str, prune: bool = True) -> tuple[list[str], int] | None:
    """The newest pair of racer checkpoints (LSTM, GRU) in the run directories of `interval` that were saved after
    the same race, and the head-to-head races they have done in all; None if there is none. Runs newer than that
    pair (a kill in the microseconds between the two renames that end the saves of one race leaves racer 0 a
    race ahead) are removed unless `prune` is False: the interval continues from the pair, and their logs would
    count races twice."""
    from utils.checkpoint import read_checkpoint

    runs = sorted(path for path in glob.glob(os.path.join(interval, "*")) if os.path.isdir(path))
    for k in range(len(runs) - 1, -1, -1):
        paths = [os.path.join(runs[k], "checkpoints", f"racer_{i}.pt") for i in (0, 1)]
        if not all(os.path.exists(p) for p in paths):
            continue
        races = {int(read_checkpoint(p)[1]["counters"]["race_episodes"]) for p in paths}
        if len(races) == 1:
            for newer in runs[k + 1 :] if prune else ():
                shutil.rmtree(newer)
            return paths, races.pop()
    return None


def tournament_racers(tournament: str) -> list[str]:
    """The two racers (LSTM, GRU) of a tournament as its results.json names them: variant, run and checkpoint."""
    with open(os.path.join(tournament, "results.json")) as f:
        return [r["racer"] for r in json.load(f)[:2]]


def tournament_metrics(tournament: str, trained: int) -> dict:
    """The LSTM's (racer 0) and GRU's (racer 1) results of one tournament, with the LSTM's Wilson interval."""
    with open(os.path.join(tournament, "results.json")) as f:
        lstm, gru = json.load(f)[:2]
    if not (lstm["racer"].startswith("lstm:") and gru["racer"].startswith("gru:")):
        raise ValueError(f"{tournament}: racer 0 must be the LSTM and racer 1 the GRU, got {lstm['racer']}, "
                         f"{gru['racer']}")  # fmt: skip
    return {
        "races_trained": trained, "eval_races": lstm["races"], "lstm_wins": lstm["wins"], "gru_wins": gru["wins"],
        "both_out": lstm["all_eliminated"], "no_winner": lstm["no_winner"], "dead_heats": lstm["dead_heats"],
        "lstm_win_rate": lstm["win_rate"],
        "lstm_win_rate_ci_low": lstm["win_rate_ci_low"], "lstm_win_rate_ci_high": lstm["win_rate_ci_high"],
        "lstm_progress": lstm["mean_progress"], "gru_progress": gru["mean_progress"],
        "lstm_eliminations": lstm["eliminations"], "gru_eliminations": gru["eliminations"],
        "collision_steps": lstm["collision_steps"],
    }  # fmt: skip


# --- Running the stages ----------------------------------------------------------------------
def stage_configs(spec: Spec, stage: str) -> list[dict]:
    plain = dataclasses.asdict(spec)
    if stage == "race":
        return [{"spec": plain, "stage": "race", "variant": "lstm_gru", "seed": s} for s in spec.seeds]
    # seed by seed, so that an experiment cut short has whole seeds of every variant
    return [{"spec": plain, "stage": k, "variant": v, "seed": s}
            for s in spec.seeds for k in trial_kinds(plain, stage) for v in spec.variants]


def trial_kinds(spec: dict, stage: str) -> list[str]:
    """The dreamer trials of a single or ghost stage, per variant and seed: the ghost stage's with its control
    unless the experiment runs without controls."""
    if stage == "single":
        return ["single"]
    return ["ghost", "control"] if spec["controls"] else ["ghost"]


def trial_name(trial) -> str:
    config = trial.config["trial"]
    return trial_label(config["stage"], config["variant"], config["seed"])


def run_stage(spec: Spec, stage: str):
    """One Tune experiment per stage; an existing one is restored (finished trials are skipped)."""
    trainable = race_trial if stage == "race" else dreamer_trial
    resources = {"cpu": spec.torch_threads, **({"gpu": spec.gpus_per_trial} if spec.gpus_per_trial else {})}
    path = os.path.join(os.path.abspath(spec.storage), "tune", f"{spec.name}_{stage}")
    return fit_trials(trainable, resources, path, stage_configs(spec, stage), trial_name, spec.max_failures)


def fit_trials(trainable, resources: dict, path: str, configs: list[dict], name, max_failures: int):
    """Run `trainable` once per config (each under config "trial") as the Tune experiment at `path`, named per trial
    by `name`; an experiment already at `path` is restored, its finished trials skipped and the others resumed.
    Raises RuntimeError naming the first trial that failed after `max_failures` retries."""
    from ray import tune

    trainable = tune.with_resources(trainable, resources)
    if tune.Tuner.can_restore(path):
        tuner = tune.Tuner.restore(path, trainable, resume_unfinished=True, resume_errored=True)
    else:
        tuner = tune.Tuner(
            trainable,
            param_space={"trial": tune.grid_search(configs)},
            tune_config=tune.TuneConfig(trial_name_creator=name, trial_dirname_creator=name),
            run_config=tune.RunConfig(
                name=os.path.basename(path), storage_path=os.path.dirname(path), verbose=1,
                failure_config=tune.FailureConfig(max_failures=max_failures),
            ),
        )  # fmt: skip
    results = tuner.fit()
    errors = [r.error for r in results if r.error]
    if errors:
        raise RuntimeError(f"{os.path.basename(path)}: {len(errors)} trial(s) failed: {errors[0]}")
    return results


def runtime_env(address: str | None) -> dict:
    """Where Ray's workers find this code: on this machine (`address` None) the repository itself; on a cluster a
    copy of it (Ray's working_dir upload, without runs/ and .git/), with the same import paths."""
    here = os.path.join(ROOT, "benchmarks")
    if address is None:
        return {"env_vars": {"PYTHONPATH": os.pathsep.join([ROOT, here, os.environ.get("PYTHONPATH", "")])}}
    return {"working_dir": ROOT, "excludes": ["runs/", ".git/", "races/"], "env_vars": {"PYTHONPATH": ".:benchmarks"}}


def start_ray(address: str | None, num_cpus: int | None) -> None:
    """Ray on this machine (`address` None, `num_cpus` cores) or the cluster at `address`, its workers at nice 0:
    at Ray's nice 15 they yield the cores to anything else running here (measured: ~6.5 s instead of ~1.2 s per
    update beside one ordinary process), and the trials are the experiment."""
    import ray

    os.environ.setdefault("RAY_worker_niceness", "0")
    ray.init(address=address, num_cpus=num_cpus, runtime_env=runtime_env(address), include_dashboard=False,
             log_to_driver=False)  # fmt: skip


# What fixes the trials of an experiment: a rerun must ask for the same (Tune restores the trials it saved).
TRIAL_FIELDS = (
    "variants", "seeds", "preset", "overrides", "single_updates", "single_cpu_hours", "ghost_updates", "race_episodes",
    "tournament_every", "tournament_races", "race_train_steps", "report_every", "torch_threads", "eval_policy",
    "controls",
)  # fmt: skip
# The trial fields that may change until the stage that first uses them has begun: the evaluation policy until the
# race stage (the tables measured before are measured again with the new one), the controls until the ghost stage.
CHANGEABLE_UNTIL = {"eval_policy": "race", "controls": "ghost"}


def trial_fields(spec: Spec) -> dict:
    """The TRIAL_FIELDS of `spec` as saved in spec.json (lists for tuples)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(spec).items() if k in TRIAL_FIELDS}


def refuse_below(prog: str, **flags: tuple[float, float]) -> None:
    """Exit naming the first flag whose value is below its minimum (flags as name=(value, minimum)): a count of
    updates or races below 1 would read as "no limit" to the scripts, and a trial would never end."""
    for name, (value, minimum) in flags.items():
        if not value >= minimum:
            raise SystemExit(f"{prog}: --{name.replace('_', '-')} must be >= {minimum:g}, got {value}")


def check_spec(spec: Spec) -> None:
    """Refuse, before Ray starts, what cannot work: a bad count, a bad override, a stage whose earlier stage has not
    run, or a rerun that asks for other trials than the experiment in --storage holds. Then record the experiment in
    <storage>/spec.json: a new one's fields, or the fields that may still change (CHANGEABLE_UNTIL)."""
    refuse_below("experiment.py", **{name: (getattr(spec, name), minimum) for name, minimum in (
        ("single_updates", 1), ("single_cpu_hours", 0), ("ghost_updates", 1), ("race_episodes", 0),
        ("tournament_every", 1), ("race_train_steps", 0), ("report_every", 1), ("fresh_tracks", 1),
        ("torch_threads", 1), ("gpus_per_trial", 0), ("max_failures", -1), ("chaos_kill_after_updates", 0))})
    for variant in ("lstm", "gru"):
        parse_overrides(importlib.import_module(f"dreamer_{variant}"), spec.overrides)
    if spec.num_cpus is not None and spec.address is not None:
        raise SystemExit("experiment.py: --num-cpus is for a local Ray; a cluster (--address) offers its own CPUs")
    if spec.num_cpus is not None and spec.num_cpus < spec.torch_threads:
        raise SystemExit(f"experiment.py: --num-cpus ({spec.num_cpus}) must be at least --torch-threads "
                         f"({spec.torch_threads}), the CPUs each trial reserves: no trial would start")  # fmt: skip
    plain = dataclasses.asdict(spec)
    needs = {"ghost": "single", "race": "ghost"}
    for stage in spec.stages:
        earlier = needs.get(stage)
        if earlier and earlier not in spec.stages:
            variants = ("lstm", "gru") if stage == "race" else spec.variants
            missing = unfinished(plain, earlier, variants, spec.seeds)
            if missing:
                raise SystemExit(f"experiment.py: stage {stage} needs the {earlier} trials finished: "
                                 f"{', '.join(missing)}")  # fmt: skip
    if spec.race_episodes % spec.tournament_every:
        raise SystemExit(f"experiment.py: --race-episodes ({spec.race_episodes}) must be a multiple of "
                         f"--tournament-every ({spec.tournament_every})")  # fmt: skip
    if spec.tournament_races < 2 or spec.tournament_races % 2:
        raise SystemExit(f"experiment.py: --tournament-races ({spec.tournament_races}) must be a positive even number: "
                         f"each track is raced twice, the start positions swapped")  # fmt: skip
    if not spec.controls:
        import experiment_report

        experiment_report.kept_ghost_rows(spec)  # the table the aggregation keeps: refused now, not after the trials
    if "race" in spec.stages and set(spec.variants) != {"lstm", "gru"}:
        raise SystemExit("experiment.py: the race stage pairs an LSTM and a GRU agent: --variants lstm gru")
    path = os.path.join(spec.storage, "spec.json")
    wanted, saved = trial_fields(spec), saved_spec(spec.storage)
    if saved is not None:
        changed = sorted(k for k in TRIAL_FIELDS if saved[k] != wanted[k])
        if changed and all(k in CHANGEABLE_UNTIL and not stage_started(plain, CHANGEABLE_UNTIL[k]) for k in changed):
            # no trial has used them yet: they may change (and are written down)
            for k in changed:
                print(f"experiment.py: --{k.replace('_', '-')} {wanted[k]} (was {saved[k]}) for {spec.storage}")
            write_json(path, wanted)
        elif changed:
            raise SystemExit(f"experiment.py: {spec.storage} holds an experiment with other {', '.join(changed)}; "
                             "use another --storage (or the same settings)")  # fmt: skip
    else:
        os.makedirs(spec.storage, exist_ok=True)
        write_json(path, wanted)


class Progress(NamedTuple):
    """How far a dreamer trial got (trial_progress). It is finished when `done` reaches `target`."""

    run: str | None
    """its run directory; None for a trial not started"""
    done: int
    """the updates its latest.pt has made"""
    target: int | None
    """the updates it ends at (None before it starts: a ghost or control trial's depends on the best.pt it will start
    from); a trial that a CPU budget ends has NO_UPDATE_TARGET; a trial whose budget is spent, or whose run the
    non-finite guard stopped (numerical_stop), has its own updates"""
    budget: tuple[float, float] | None = None
    """(CPU-hours its latest.pt has spent, the budget) of a trial that a CPU budget ends (--single-cpu-hours)"""
    stopped: bool = False
    """whether the non-finite guard stopped its run (numerical_stop): finished, with its last policy"""
    hours: float = 0.0
    """the CPU-hours its latest.pt has spent (cpu_hours_of)"""

    @property
    def finished(self) -> bool:
        """Started, and its latest.pt has reached its target (its updates, or the end a budget or a stop set)."""
        return self.run is not None and self.target is not None and self.done >= self.target


def trial_progress(spec: dict, kind: str, variant: str, seed: int) -> Progress:
    """How far a dreamer trial got, from its latest.pt (read once)."""
    run = run_of(trial_dir(spec, kind, variant, seed))
    if run is None:
        return Progress(None, 0, None)
    script, args, _, target = trial_args(spec, kind, variant, seed)
    checkpoint = script.load_checkpoint(os.path.join(run, "checkpoints", "latest.pt"))
    done, hours = checkpoint_updates(checkpoint), cpu_hours_of(checkpoint)
    budget = (hours, args.cpu_hours_limit) if args.cpu_hours_limit > 0 else None
    stopped = numerical_stop(checkpoint)
    finished = stopped or (budget is not None and budget[0] >= budget[1])  # either ends it, whatever its updates
    return Progress(run, done, done if finished else target, budget, stopped, hours)


def trial_label(stage: str, variant: str, seed: int) -> str:
    """A trial's name in messages and tables, and its directory's under <storage>/trials (trial_dir)."""
    return f"{stage}_{variant}_seed{seed}"


def progress_text(name: str, progress: Progress) -> str:
    """How far a trial got (trial_progress): its updates against its target or its CPU budget (and that it is
    finished when the budget is spent), and whether the non-finite guard stopped it."""
    if progress.run is None:
        return f"{name} (not started)"
    guard = ", stopped by the non-finite guard" if progress.stopped else ""
    if progress.budget is not None:
        spent = math.floor(progress.budget[0] * 100) / 100  # rounded down: short of its budget never reads as at it
        end = guard or (", finished" if progress.finished else "")
        return f"{name} ({progress.done} updates, {spent:.2f} of {progress.budget[1]:g} CPU-hours{end})"
    return f"{name} ({progress.done} of {progress.target} updates{guard})"


def unfinished(spec: dict, stage: str, variants, seeds) -> list[str]:
    """The trials of a single or ghost stage that the next stage starts from (the ghost stage's ghosts, not their
    controls) that are not finished (trial_progress: all their updates made, their CPU budget spent, or stopped by
    the non-finite guard), each named with how far it got."""
    names = []
    for variant in variants:
        for seed in seeds:
            progress = trial_progress(spec, stage, variant, seed)
            if not progress.finished:
                names.append(progress_text(trial_label(stage, variant, seed), progress))
    return names


def race_progress(spec: dict, seed: int) -> str:
    """How far the race trial of seed pair (seed, seed) has got: head-to-head races trained (by the newest pair of
    racer checkpoints both saved after the same race) and the tournaments held. Read only."""
    directory = trial_dir(spec, "race", "lstm_gru", seed)
    name = trial_label("race", "lstm_gru", seed)
    if not os.path.isdir(directory):
        return f"{name} (not started)"
    held = sorted(int(path.rsplit("_", 1)[1]) for path in glob.glob(os.path.join(directory, "tournament_*[0-9]"))
                  if os.path.exists(os.path.join(path, "results.json")))  # fmt: skip
    trained = max(held, default=0)
    for interval in glob.glob(os.path.join(directory, "races_*[0-9]")):
        found = interval_racers(interval, prune=False)
        trained = max(trained, found[1] if found else 0)
    tournaments = ", ".join(map(str, held)) or "none yet"
    return f"{name} ({trained} of {spec['race_episodes']} races; tournaments after {tournaments} races)"


def status(spec: Spec) -> str:
    """Every trial of the experiment, stage by stage, with how far it has got: a dreamer trial's updates against
    its target, or against its CPU budget (read from its latest.pt), a race trial's races and tournaments.
    Nothing is started or measured."""
    plain, lines = dataclasses.asdict(spec), []
    for stage in ("single", "ghost", "race"):
        if stage == "race":
            trials = [race_progress(plain, seed) for seed in spec.seeds]
        else:
            trials = [progress_text(trial_label(kind, variant, seed), trial_progress(plain, kind, variant, seed))
                      for seed in spec.seeds for kind in trial_kinds(plain, stage) for variant in spec.variants]
        lines += [f"{stage}:"] + [f"  {trial}" for trial in trials]
    return "\n".join(lines)


def stage_started(spec: dict, stage: str) -> bool:
    """Whether a stage of the experiment in spec["storage"] has begun (its Tune experiment or a trial)."""
    tune_dir = os.path.join(spec["storage"], "tune", f"{spec['name']}_{stage}")
    # (a ghost stage begun with or without controls has begun either way)
    kinds = {"single": ["single"], "ghost": ["ghost", "control"], "race": ["race"]}[stage]
    return os.path.exists(tune_dir) or any(glob.glob(trial_dir(spec, k, "*", "*")) for k in kinds)


# The value of a trial field whose default changed after it was added: what an experiment whose spec.json predates
# the field ran with (the evaluation policy was sampled until the rule of docs/learning.md chose the mean action).
FIELD_ORIGINS = {"eval_policy": "stochastic"}


def restored_spec(saved: dict) -> dict:
    """The spec of a trial as Tune restores it: a field its saved config lacks was added to Spec after the trial's
    experiment began, so it takes the value that field had then (FIELD_ORIGINS), else its default."""
    return {**dataclasses.asdict(Spec()), **FIELD_ORIGINS, **saved}


def saved_spec(storage: str, write: bool = True) -> dict | None:
    """The TRIAL_FIELDS of the experiment in `storage` (None: there is none yet). A field its spec.json lacks was
    added to Spec after it started, so it ran with the value that field had then (FIELD_ORIGINS, else its
    default); that value is written into its spec.json (unless `write` is False: --status only reads), so that a
    later change of the default cannot change what the experiment was."""
    path = os.path.join(storage, "spec.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        saved = json.load(f)
    missing = {k: FIELD_ORIGINS.get(k, v) for k, v in trial_fields(Spec()).items() if k not in saved}
    saved |= missing
    if missing and write:
        write_json(path, saved)
    return saved


def as_run(spec: Spec, saved: dict) -> Spec:
    """`spec` with the seeds, variants, budgets and settings of the experiment as it was run (its spec.json)."""
    return dataclasses.replace(spec, **{k: tuple(v) if isinstance(v, list) else v for k, v in saved.items()})


def main(spec: Spec) -> None:
    spec = dataclasses.replace(spec, storage=os.path.abspath(spec.storage))
    if spec.status:
        if (saved := saved_spec(spec.storage, write=False)) is None:
            raise SystemExit(f"experiment.py: --status: no experiment in {spec.storage} (it has no spec.json)")
        print(status(as_run(spec, saved)))
        return
    if not spec.aggregate_only:
        check_spec(spec)
    elif (saved := saved_spec(spec.storage)) is not None:
        if saved["eval_policy"] != spec.eval_policy:
            policy = saved["eval_policy"]
            raise SystemExit(f"experiment.py: the experiment in {spec.storage} measures its agents with "
                             f"--eval-policy {policy}; its tables take the same: give --eval-policy {policy}")
        spec = as_run(spec, saved)  # the tables are of the experiment as it was run, whatever the flags say
    if not spec.aggregate_only:
        start_ray(spec.address, spec.num_cpus)
        for stage in ("single", "ghost", "race"):
            if stage in spec.stages:
                run_stage(spec, stage)
    import experiment_report  # the tables (not imported above: it imports this module)

    print(experiment_report.aggregate(spec))


if __name__ == "__main__":
    from utils.run import tyro_cli

    main(tyro_cli(Spec))
