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

* ``single``: one car from scratch, ``--single-updates`` updates; ``best.pt`` keeps the best evaluation.
* ``ghost``: from the single trial's ``best.pt`` of the same variant and seed, ``--ghost-updates`` more updates
  racing the agent's own best runs; ``control`` continues ``single`` from the same ``best.pt`` for as many
  updates without a ghost, so the ghost's effect is measured rather than assumed.
* ``race``: per seed pair (s, s), the LSTM and the GRU ghost-stage agents race each other and both keep learning
  (``race.py --train``, ``--race-train-steps`` updates per agent per race), with a tournament every
  ``--tournament-every`` races: ``--tournament-races`` evaluation races on held-out tracks, start positions
  swapped fairly, the LSTM's win rate with a Wilson 95% interval.

Then it writes ``benchmarks/results/ghost_vs_control.csv``, ``head_to_head.csv`` and ``experiment.md`` (IQM and
mean of the single-stage final returns per variant with stratified-bootstrap intervals, and the probability that
the LSTM's head-to-head win rate exceeds the GRU's across seed pairs, both with rliable: descriptions), and the
table of the paper's claims, each judged by an exact permutation test and a t interval (stats.paired_claim,
stats.two_group_claim: a bootstrap is too narrow over so few runs); with ``--second-policy`` the head-to-head claims
again, every tournament raced with that policy too.
"""

from __future__ import annotations

import csv
import dataclasses
import glob
import importlib
import json
import os
import shutil
import signal
import sys
import tempfile
import types
import typing
from typing import Literal

import numpy as np
import tyro

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402  (the blocks of tracks)
import learning  # noqa: E402  (the single stage is the learning benchmark's run)
RESULTS = os.path.join(ROOT, "benchmarks", "results")
TOURNAMENT_SEED = 7_777  # held-out tracks of the tournaments (training races use the pair's seed)
NO_UPDATE_TARGET = 10**12  # the update target of a trial that a CPU budget ends (--single-cpu-hours)


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
    single_updates: int = 8000
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
    return os.path.join(spec["storage"], "trials", f"{stage}_{variant}_seed{seed}")


def run_of(directory: str) -> str | None:
    """The run directory of a trial that has a checkpoint (a run killed before its first checkpoint is ignored)."""
    runs = sorted(glob.glob(os.path.join(directory, "*", "checkpoints", "latest.pt")))
    return os.path.dirname(os.path.dirname(runs[-1])) if runs else None


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
        # the learning benchmark's run (benchmarks/learning.py --runs-dir <storage>/trials reads it) unless the
        # spec changes the preset, a flag, the updates, the threads or the evaluation policy (which picks best.pt):
        # the scripts' default, or the sampled policy the final protocol's runs were made with
        plain = spec["preset"] == "cpu" and not spec["overrides"] and spec["single_updates"] == learning.FINAL_UPDATES
        plain = plain and spec["single_cpu_hours"] == 0
        plain = plain and spec["torch_threads"] == learning.LEARNING_CONFIG["torch_threads"]
        plain = plain and spec["eval_policy"] in (script.Args().eval_policy, "stochastic")
        args = script.preset_args(
            spec["preset"], exp_name=learning.experiment_name(variant) if plain else f"{variant}_single",
            **{**learning.LEARNING_CONFIG, **settings},
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
    from latest.pt, with the latest evaluation reported to Tune after every chunk."""
    from ray import tune

    config = config["trial"]  # (the grid puts each trial's settings under "trial")
    spec = restored_spec(config["spec"])
    stage, variant, seed = config["stage"], config["variant"], config["seed"]
    script, args, first, target = trial_args(spec, stage, variant, seed)
    directory = trial_dir(spec, stage, variant, seed)
    goal = (first or 0) + spec["report_every"]
    while True:
        run = run_of(directory)
        done = updates_of(os.path.join(run, "checkpoints", "latest.pt"), script) if run else 0
        if run is None:
            script.main(dataclasses.replace(args, total_updates=min(goal, target)))
        elif done < min(goal, target):
            script.main(script.Args(resume=run, total_updates=min(goal, target)), {"total_updates"})
        run = run_of(directory)
        tune.report(latest_metrics(run))
        # latest.pt, not progress.csv, says what is done: a kill between its save and the csv row (the end of a
        # race) leaves the csv a race behind, and the trial must still end
        done = updates_of(os.path.join(run, "checkpoints", "latest.pt"), script)
        chaos = spec["chaos_kill_after_updates"]
        marker = os.path.join(directory, "chaos_killed")
        if chaos and stage == "single" and done >= chaos and not os.path.exists(marker):
            open(marker, "w").close()
            os.kill(os.getpid(), signal.SIGKILL)  # a dying worker: Ray retries the trial, which resumes
        if done >= target or spent_budget(os.path.join(run, "checkpoints", "latest.pt"), script, args):
            return
        goal = max(goal, done) + spec["report_every"]


def updates_of(path: str, script) -> int:
    return int(script.load_checkpoint(path)["agents"][0]["num_updates"])


def cpu_hours_of(checkpoint: dict) -> float:
    """The process CPU-hours a run had spent over all its sittings when it saved `checkpoint` (its "extra")."""
    return float((checkpoint.get("extra") or {}).get("cpu_seconds", 0.0)) / 3600


def spent_budget(path: str, script, args) -> bool:
    """Whether the run of checkpoint `path` has used its --cpu-hours-limit (no limit: never)."""
    if args.cpu_hours_limit <= 0:
        return False
    return cpu_hours_of(script.load_checkpoint(path)) >= args.cpu_hours_limit


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
    import race

    runs = sorted(path for path in glob.glob(os.path.join(interval, "*")) if os.path.isdir(path))
    for k in range(len(runs) - 1, -1, -1):
        paths = [os.path.join(runs[k], "checkpoints", f"racer_{i}.pt") for i in (0, 1)]
        if not all(os.path.exists(p) for p in paths):
            continue
        races = {int(race.read_checkpoint(p)[1]["counters"]["race_episodes"]) for p in paths}
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
    return f"{config['stage']}_{config['variant']}_seed{config['seed']}"


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


def runtime_env(spec: Spec) -> dict:
    """Where Ray's workers find this code: on this machine the repository itself; on a cluster a copy of it
    (Ray's working_dir upload, without runs/ and .git/), with the same import paths."""
    here = os.path.join(ROOT, "benchmarks")
    if spec.address is None:
        return {"env_vars": {"PYTHONPATH": os.pathsep.join([ROOT, here, os.environ.get("PYTHONPATH", "")])}}
    return {"working_dir": ROOT, "excludes": ["runs/", ".git/", "races/"], "env_vars": {"PYTHONPATH": ".:benchmarks"}}


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


def check_spec(spec: Spec) -> None:
    """Refuse, before Ray starts, what cannot work: a bad override, a stage whose earlier stage has not run, or a
    rerun that asks for other trials than the experiment in --storage holds (its spec is saved there)."""
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
    if spec.tournament_every < 1 or spec.race_episodes % spec.tournament_every:
        raise SystemExit(f"experiment.py: --race-episodes ({spec.race_episodes}) must be a multiple of "
                         f"--tournament-every ({spec.tournament_every})")  # fmt: skip
    if spec.tournament_races < 2 or spec.tournament_races % 2:
        raise SystemExit(f"experiment.py: --tournament-races ({spec.tournament_races}) must be a positive even number: "
                         f"each track is raced twice, the start positions swapped")  # fmt: skip
    if not spec.controls:
        kept_ghost_rows(spec)  # the table the aggregation will keep: refused now, not after the trials
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
            with open(path + ".tmp", "w") as f:
                json.dump(wanted, f, indent=1)
            os.replace(path + ".tmp", path)
        elif changed:
            raise SystemExit(f"experiment.py: {spec.storage} holds an experiment with other {', '.join(changed)}; "
                             "use another --storage (or the same settings)")  # fmt: skip
    else:
        os.makedirs(spec.storage, exist_ok=True)
        with open(path, "w") as f:
            json.dump(wanted, f, indent=1)


def trial_progress(spec: dict, kind: str, variant: str, seed: int) -> tuple[str | None, int, int | None]:
    """A dreamer trial's run directory, the updates its latest.pt has made and its target; (None, 0, None) for a
    trial not started (a ghost or control trial's target depends on the best.pt it will start from)."""
    run = run_of(trial_dir(spec, kind, variant, seed))
    if run is None:
        return None, 0, None
    script, args, _, target = trial_args(spec, kind, variant, seed)
    latest = os.path.join(run, "checkpoints", "latest.pt")
    done = updates_of(latest, script)
    return run, done, done if spent_budget(latest, script, args) else target  # a spent CPU budget ends a trial



def progress_text(name: str, run: str | None, done: int, target: int | None) -> str:
    if run is None:
        return f"{name} (not started)"
    if target == NO_UPDATE_TARGET:
        return f"{name} ({done} updates, CPU budget not spent)"
    return f"{name} ({done} of {target} updates)"


def unfinished(spec: dict, stage: str, variants, seeds) -> list[str]:
    """The trials of a single or ghost stage that the next stage starts from (the ghost stage's ghosts, not their
    controls) and that have not made all their updates, each named with how far it got."""
    names = []
    for variant in variants:
        for seed in seeds:
            for kind in [stage]:
                run, done, target = trial_progress(spec, kind, variant, seed)
                if run is None or done < target:
                    names.append(progress_text(f"{kind}_{variant}_seed{seed}", run, done, target))
    return names


def race_progress(spec: dict, seed: int) -> str:
    """How far the race trial of seed pair (seed, seed) has got: head-to-head races trained (by the newest pair of
    racer checkpoints both saved after the same race) and the tournaments held. Read only."""
    directory = trial_dir(spec, "race", "lstm_gru", seed)
    name = f"race_lstm_gru_seed{seed}"
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
    its target (read from its latest.pt), a race trial's races and tournaments. Nothing is started or measured."""
    plain, lines = dataclasses.asdict(spec), []
    for stage in ("single", "ghost", "race"):
        if stage == "race":
            trials = [race_progress(plain, seed) for seed in spec.seeds]
        else:
            trials = [progress_text(f"{kind}_{variant}_seed{seed}", *trial_progress(plain, kind, variant, seed))
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
        with open(path + ".tmp", "w") as f:
            json.dump(saved, f, indent=1)
        os.replace(path + ".tmp", path)
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
        import ray

        # Ray starts its workers at nice 15, where they yield the cores to anything else running here (measured:
        # ~6.5 s instead of ~1.2 s per update beside one ordinary process); the trials are the experiment.
        os.environ.setdefault("RAY_worker_niceness", "0")
        ray.init(address=spec.address, num_cpus=spec.num_cpus, runtime_env=runtime_env(spec), include_dashboard=False,
                 log_to_driver=False)  # fmt: skip
        for stage in ("single", "ghost", "race"):
            if stage in spec.stages:
                run_stage(spec, stage)
    print(aggregate(spec))


# --- Aggregation -----------------------------------------------------------------------------
GHOST_COLUMNS = ("variant", "seed", "updates_at_start", "updates", "return_before", "return_after_ghost",
                 "return_after_control")  # fmt: skip
HEAD_COLUMNS = ("seed_pair", "races_trained", "eval_races", "lstm_wins", "gru_wins", "both_out", "no_winner",
                "dead_heats", "lstm_win_rate_ci_low", "lstm_win_rate_ci_high", "lstm_progress", "gru_progress",
                "lstm_eliminations", "gru_eliminations", "collision_steps")  # fmt: skip


def aggregate(spec: Spec) -> str:
    """ghost_vs_control.csv, head_to_head.csv and experiment.md from the trials there are; returns the summary.

    Only finished trials are results: a single, ghost or control trial that has made all its updates, and a seed
    pair whose tournament after the last head-to-head race exists. head_to_head.csv lists every tournament held so
    far; the statistics use the finished pairs, and the summary names what it left out. An experiment without
    controls keeps the ghost_vs_control.csv in spec.results and says how its ghost agents made again compare."""
    kept = None if spec.controls else kept_ghost_rows(spec)
    os.makedirs(spec.results, exist_ok=True)
    plain, first = dataclasses.asdict(spec), common.TRACKS["fresh"][0]
    single_returns: dict[str, list[float]] = {}
    ghost_rows, left_out = [], []
    for variant in spec.variants:
        for seed in spec.seeds:
            run, done, target = trial_progress(plain, "single", variant, seed)
            if run is None or done < target:
                left_out.append(progress_text(f"single_{variant}_seed{seed}", run, done, target))
                continue

            def fresh(run: str, name: str) -> float:
                return fresh_return(spec, os.path.join(run, "checkpoints", name), first)

            single_returns.setdefault(variant, []).append(fresh(run, "latest.pt"))
            stage = {k: trial_progress(plain, k, variant, seed) for k in trial_kinds(plain, "ghost")}
            if any(r is None or d < t for r, d, t in stage.values()):
                left_out += [progress_text(f"{k}_{variant}_seed{seed}", r, d, t) for k, (r, d, t) in stage.items()
                             if r is None or d < t]  # fmt: skip
                continue
            best = os.path.join(run, "checkpoints", "best.pt")
            start = updates_of(best, importlib.import_module(f"dreamer_{variant}"))
            ghost_rows.append({
                "variant": variant, "seed": seed, "updates_at_start": start, "updates": stage["ghost"][1] - start,
                "return_before": fresh(run, "best.pt"),
                "return_after_ghost": fresh(stage["ghost"][0], "latest.pt"),
                "return_after_control": fresh(stage["control"][0], "latest.pt") if "control" in stage else None,
            })  # fmt: skip
    if kept is None:
        write_csv(os.path.join(spec.results, "ghost_vs_control.csv"), GHOST_COLUMNS, ghost_rows)
        remade = ""
    else:
        remade, ghost_rows = remade_note(kept, ghost_rows), kept
    head_rows = []
    for seed in spec.seeds:
        tournaments = sorted(glob.glob(os.path.join(trial_dir(plain, "race", "lstm_gru", seed), "tournament_*[0-9]")))
        for tournament in tournaments:
            head_rows.append(head_row(seed, tournament_metrics(tournament, int(tournament.rsplit("_", 1)[1]))))
    write_csv(os.path.join(spec.results, "head_to_head.csv"), HEAD_COLUMNS, head_rows)
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
    with open(os.path.join(spec.results, "experiment.md"), "w") as f:
        f.write(summary)
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
    write_csv(os.path.join(spec.results, f"head_to_head_{policy}.csv"), HEAD_COLUMNS, rows)
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
        fd, tmp = tempfile.mkstemp(dir=spec.storage, suffix=".tmp")  # two writers never share a temporary file
        with os.fdopen(fd, "w") as f:
            json.dump(cache, f, indent=1)
        os.replace(tmp, cache_path)
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


def paired_mean(diffs: list[float]) -> dict:
    """The claim "the mean of paired differences (one per run) is positive", judged by the exact sign-flip test over
    all 2^n sign assignments and the t 95% interval of the differences (stats.paired_claim): ``estimate``, ``ci``,
    ``p`` (one-sided), ``n`` and ``verdict``."""
    from stats import paired_claim

    return paired_claim(diffs)


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
    from stats import ALPHA, MIN_RUNS, SMALL_SAMPLE_NOTE, describe, two_group_claim

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
            paired_mean([rate["lstm"](rs[-1]) - rate["gru"](rs[-1]) for rs in ends]), digits=2,
        ))  # fmt: skip
        # the first tournament after head-to-head training began (the one at 0 is before it)
        firsts = [next(r for r in rs if int(r["races_trained"]) > 0) for rs in ends]
        before = [(rs[0], first) for rs, first in zip(ends, firsts) if int(rs[0]["races_trained"]) == 0]
        for v, name in (("lstm", "LSTM"), ("gru", "GRU")) if before else ():
            lines.append(row(
                f"head-to-head training first perturbs both agents: the {name}",
                f"the {name}'s mean progress in the tournament before head-to-head training - in the first after it "
                f"(races 0 to {firsts[0]['races_trained']}), mean over {len(before)} seed pairs",
                paired_mean([float(r0[f"{v}_progress"]) - float(r1[f"{v}_progress"]) for r0, r1 in before]),
                digits=2,
            ))  # fmt: skip
        lines.append(row(
            "trained against each other, the LSTM recovers (about race 120) and outperforms",
            f"LSTM win rate at the last tournament - at the first after training began (races "
            f"{firsts[0]['races_trained']} to {race_episodes}), mean over {len(ends)} seed pairs",
            paired_mean([rate["lstm"](rs[-1]) - rate["lstm"](first) for rs, first in zip(ends, firsts)]), digits=2,
        ))  # fmt: skip
    if ghost_rows:
        diffs = [float(r["return_after_ghost"]) - float(r["return_after_control"]) for r in ghost_rows]
        lines.append(row(
            "racing a ghost of its best run improves an agent (the curriculum's second stage)",
            f"return on the fresh tracks after the ghost stage - after its control (same start, same updates), "
            f"{len(diffs)} (variant, seed) pairs",
            paired_mean(diffs),
        ))  # fmt: skip
    if any(floor >= ALPHA for floor in floors):
        lines += ["", SMALL_SAMPLE_NOTE]
    return "\n".join(lines) + "\n"


def write_csv(path: str, columns: tuple[str, ...], rows: list[dict]) -> None:
    """The rows under a fixed header (no rows: the header alone, so no table of an earlier experiment survives)."""
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(columns))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main(tyro.cli(Spec))
