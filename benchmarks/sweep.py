"""Screens as a Ray Tune sweep: a grid of flag sets x variants x seeds of single-car dreamer runs, then their readings.

    python benchmarks/sweep.py --name heads --grid head_sigma=1.0 "head_sigma=1.0 norm=mixed" \\
        --seeds 11 12 --variants lstm --updates 3100                # train (resumable: the same command continues)
    python benchmarks/sweep.py --name heads --status                  # how far each trial got (nothing runs)
    python benchmarks/sweep.py --name heads --report                  # readings of the finished trials
    python benchmarks/sweep.py --name heads --address auto ...        # on a Ray cluster (shared --storage)
    python benchmarks/sweep.py --name repeat --grid action_repeat=4 default --cpu-hours 1.06
                                                                      # equal CPU time, not equal updates

Each (flag set, variant, seed) is one Ray Tune trial: the single-stage run of ``benchmarks/experiment.py`` (the same
trial code: ``--preset cpu`` with the flag set on top, one car, ``--updates`` updates, resumed from its own
``latest.pt`` in chunks; with ``--cpu-hours`` until its process CPU time reaches the budget, whatever the
updates), in its own run directory ``<storage>/<name>/<tag>/trials/single_<variant>_seed<S>/``.
A flag set is ``name=value`` pairs of the scripts' ``Args`` separated by spaces, or ``default`` (the preset alone);
its tag names its directory (``head-sigma-1.0``). The grid of a sweep is fixed when it starts (``sweep.json``):
the same command continues it; another grid, or other trial settings (``SWEEP_FIELDS``), needs another ``--name``.

``--report`` measures every finished trial's final policy (``latest.pt`` at ``--updates``, or when the CPU budget
ran out) on the screening tracks
(10200..10219 by default, never used to report a result), sampled and with its mean action, and writes
``benchmarks/results/screening/sweep_<name>.csv`` and ``.md`` with the readings that say *why* a policy drives as it
does (``readings.measure``; ``readings.COLUMNS`` lists them: driving, the actor's sigma and entropy, the imagined
against the real return, the reward and continue heads on elimination frames, the pedal's range); each measurement
is kept in ``<storage>/<name>/readings.json`` and made once (a MODEL or PEDAL reading added to readings.py later is
measured and added to the kept ones when the report next runs; a MODEL one on the same seeded drive, checked by
the kept readings coming back: model_again).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402  (the blocks of tracks)
import experiment  # noqa: E402  (the trials are the experiment's single-stage trials)
import readings  # noqa: E402  (what a screened policy does and why)
import runs  # noqa: E402

SCREEN_RESULTS = os.path.join(common.RESULTS, "screening")


@dataclasses.dataclass
class Sweep:
    name: str
    """the sweep's name: its directory under --storage, its Tune experiment and its result files"""
    grid: tuple[str, ...] = ("default",)
    """flag sets, each 'name=value name=value' of the dreamer scripts' Args on top of --preset cpu, or 'default'"""
    variants: tuple[str, ...] = ("lstm",)
    """dreamer variants (lstm, gru)"""
    seeds: tuple[int, ...] = (11, 12)
    """seeds of every flag set"""
    updates: int = 3100
    """updates of every trial (the screened policy is the trial's latest.pt there); with --cpu-hours, ignored (but
    fixed with the sweep, as every SWEEP_FIELDS setting is)"""
    cpu_hours: float = 0.0
    """if > 0: a CPU-time budget per trial (process CPU-hours on --torch-threads threads) that ends it instead of
    --updates, to compare flag sets that change the cost of an update at equal CPU time"""
    storage: str = os.path.join(ROOT, "runs", "sweep")
    """where every sweep's trials and Tune's state go"""
    torch_threads: int = 1
    """torch threads, and CPUs Ray reserves, per trial"""
    num_cpus: int | None = None
    """CPUs a local Ray offers (default: the machine's cores)"""
    address: str | None = None
    """address of a Ray cluster (default: a local Ray); --storage must be a filesystem every node mounts"""
    max_failures: int = 2
    """times Ray retries a trial whose worker died (it resumes from its latest.pt)"""
    report_every: int = 500
    """updates of a trial between its reports to Tune"""
    status: bool = False
    """only print how far each trial got (no Ray, nothing trained)"""
    report: bool = False
    """only measure the finished trials and write the readings (no Ray)"""
    first_track: int = common.TRACKS["screening"][0]
    """--report: first track seed of the screening tracks"""
    tracks: int = common.TRACKS["screening"][1]
    """--report: number of screening tracks"""
    results: str = SCREEN_RESULTS
    """--report: directory of sweep_<name>.csv and .md"""


# What fixes a sweep's trials: a rerun under the same --name must ask for the same.
SWEEP_FIELDS = ("grid", "variants", "seeds", "updates", "cpu_hours", "torch_threads", "report_every")
FIELD_DEFAULTS = {"cpu_hours": 0.0}  # of fields a sweep.json written before them lacks


def flag_set(text: str) -> tuple[str, ...]:
    """'a=1 b=2' -> ('a=1', 'b=2'); 'default' -> ()."""
    items = tuple(text.split())
    return () if items == ("default",) else items


TAG_LENGTH = 60  # a longer tag is cut and ends in a hash of the whole flag set (file names have limits)


def tag_of(text: str) -> str:
    """A flag set's directory name: 'entropy_coef=0.3 return_norm=true' -> 'entropy-coef-0.3_return-norm-true'."""
    items = flag_set(text)
    tag = "_".join(re.sub(r"[^A-Za-z0-9.+-]", "-", item.replace("=", "-")) for item in items) or "default"
    if len(tag) > TAG_LENGTH:
        tag = tag[: TAG_LENGTH - 9] + "-" + hashlib.sha1(" ".join(items).encode()).hexdigest()[:8]
    return tag


def trial_spec(sweep: Sweep, flags: str, variant: str, seed: int) -> dict:
    """The experiment spec (as a dict) of one trial: its flag set as overrides, its own storage."""
    spec = experiment.Spec(
        variants=(variant,), seeds=(seed,), stages=("single",), overrides=flag_set(flags),
        single_updates=sweep.updates, single_cpu_hours=sweep.cpu_hours, report_every=sweep.report_every,
        torch_threads=sweep.torch_threads,
        storage=os.path.join(os.path.abspath(sweep.storage), sweep.name, tag_of(flags)),
    )  # fmt: skip
    return dataclasses.asdict(spec)


def trial_configs(sweep: Sweep) -> list[dict]:
    """Seed by seed, then flag set, then variant: a sweep cut short has whole seeds of every flag set."""
    return [
        {"spec": trial_spec(sweep, flags, v, s), "stage": "single", "variant": v, "seed": s, "tag": tag_of(flags)}
        for s in sweep.seeds for flags in sweep.grid for v in sweep.variants
    ]  # fmt: skip


def label_of(config: dict) -> str:
    """A trial's name (its flag set's tag, variant and seed) in Tune, messages and tables."""
    return f"{config['tag']}_{config['variant']}_seed{config['seed']}"


def trial_name(trial) -> str:
    return label_of(trial.config["trial"])


def check(sweep: Sweep) -> None:
    """Refuse, before Ray starts: an unknown flag or bad value, a duplicate tag, or another grid or other
    SWEEP_FIELDS under this name."""
    import importlib

    tags = [tag_of(flags) for flags in sweep.grid]
    if len(set(tags)) != len(tags):
        raise SystemExit(f"sweep.py: --grid has flag sets with the same tag: {tags}")
    for variant in sweep.variants:
        if variant not in runs.VARIANTS:
            raise SystemExit(f"sweep.py: --variants: {variant!r} is not one of {runs.VARIANTS}")
        script = importlib.import_module(f"dreamer_{variant}")
        for flags in sweep.grid:
            try:
                experiment.parse_overrides(script, flag_set(flags))
            except ValueError as error:
                raise SystemExit(f"sweep.py: --grid {flags!r}: {error}") from None
    experiment.refuse_below("sweep.py", updates=(sweep.updates, 1), cpu_hours=(sweep.cpu_hours, 0),
                            report_every=(sweep.report_every, 1), torch_threads=(sweep.torch_threads, 1))
    saved = saved_fields(sweep)
    if saved is not None and saved != fields(sweep):
        differ = [k for k in SWEEP_FIELDS if saved[k] != fields(sweep)[k]]
        raise SystemExit(
            f"sweep.py: sweep {sweep.name!r} in {sweep.storage} was started with other {', '.join(differ)} "
            f"({', '.join(f'{k}={saved[k]}' for k in differ)}); continue it with those, or give another --name"
        )  # fmt: skip


def fields(sweep: Sweep) -> dict:
    plain = dataclasses.asdict(sweep)
    return {k: list(plain[k]) if isinstance(plain[k], tuple) else plain[k] for k in SWEEP_FIELDS}


def saved_fields(sweep: Sweep) -> dict | None:
    path = os.path.join(sweep.storage, sweep.name, "sweep.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return {**FIELD_DEFAULTS, **json.load(f)}


def save_fields(sweep: Sweep) -> None:
    path = os.path.join(sweep.storage, sweep.name, "sweep.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    common.write_json(path, fields(sweep))


def trial_status(sweep: Sweep) -> list[tuple[dict, str | None, int, float, bool, bool]]:
    """(config, run directory or None, updates and CPU-hours its latest.pt holds, whether it is finished, whether the
    non-finite guard stopped it) of every trial. A trial is finished at --updates updates, or with --cpu-hours once
    its budget is spent, or when the guard stopped its run (experiment.trial_progress, as the experiment's trials)."""
    rows = []
    for config in trial_configs(sweep):
        progress = experiment.trial_progress(config["spec"], "single", config["variant"], config["seed"])
        rows.append((config, progress.run, progress.done, progress.hours, progress.finished, progress.stopped))
    return rows


def budget_text(sweep: Sweep) -> str:
    return f"{sweep.cpu_hours:g} CPU-hours" if sweep.cpu_hours > 0 else f"{sweep.updates} updates"


def progress_text(sweep: Sweep, run: str | None, done: int, hours: float) -> str:
    """How far a trial got, against its budget: 'not started', '1500 of 3100 updates, 0.512 CPU-hours' or
    '0.512 of 1.1 CPU-hours, 1500 updates'."""
    if run is None:
        return "not started"
    if sweep.cpu_hours > 0:
        return f"{hours:.3f} of {sweep.cpu_hours:g} CPU-hours, {done} updates"
    return f"{done} of {sweep.updates} updates, {hours:.3f} CPU-hours"


def status_text(sweep: Sweep) -> str:
    """One line per trial: 'done (...)' once finished (a shell may count the ': done' lines), else progress_text."""
    lines = [f"sweep {sweep.name} ({os.path.join(sweep.storage, sweep.name)}), {budget_text(sweep)} per trial:"]
    for config, run, done, hours, finished, stopped in trial_status(sweep):
        name = label_of(config)
        state = progress_text(sweep, run, done, hours) + (", stopped by the non-finite guard" if stopped else "")
        lines.append(f"  {name}: {'done (' + state + ')' if finished else state}")
    return "\n".join(lines)


def run_sweep(sweep: Sweep):
    """One Tune experiment per sweep; an existing one is restored (finished trials are skipped)."""
    save_fields(sweep)
    experiment.start_ray(sweep.address, sweep.num_cpus)
    path = os.path.join(os.path.abspath(sweep.storage), sweep.name, "tune", f"sweep_{sweep.name}")
    resources = {"cpu": sweep.torch_threads}
    return experiment.fit_trials(experiment.dreamer_trial, resources, path, trial_configs(sweep), trial_name,
                                 sweep.max_failures)  # fmt: skip


# --- The report ------------------------------------------------------------------------------
def report(sweep: Sweep) -> str:
    """Measure every finished trial of `sweep` once (kept in <storage>/<name>/readings.json), write
    sweep_<name>.csv and .md in --results, and return the markdown table."""
    cache_path = os.path.join(sweep.storage, sweep.name, "readings.json")
    cache = {}
    if os.path.exists(cache_path):
        with open(cache_path) as f:
            cache = json.load(f)
    rows, waiting = [], []
    for config, run, done, hours, finished, stopped in trial_status(sweep):
        name = label_of(config)
        if not finished:
            waiting.append(f"{name} ({progress_text(sweep, run, done, hours)})")
            continue
        # a budget, or the non-finite guard's stop: latest.pt, where the run ended
        updates = done if sweep.cpu_hours > 0 or stopped else sweep.updates
        try:
            path = readings.checkpoint_at(run, updates)
        except ValueError as e:  # e.g. updates per race that do not divide --updates: said, not measured
            waiting.append(f"{name} (no policy kept at {updates} updates: {e})")
            continue
        key = f"{os.path.relpath(path, sweep.storage)}@{sweep.first_track}+{sweep.tracks}"
        if key not in cache:
            cache[key] = readings.measure(path, run, updates, sweep.first_track, sweep.tracks)
            common.write_json(cache_path, cache)
        kept = cache[key][readings.POLICIES[0]]
        extra = {}  # readings kept before a column was read (the PEDAL ones, terminal_continue): measured now
        if any(column not in kept for column in readings.PEDAL):
            extra.update(readings.pedal(path, sweep.first_track))
        if any(column not in kept for column in readings.MODEL):
            extra.update(model_again(name, kept, readings.model(path, sweep.first_track, sweep.tracks)))
        if extra:
            cache[key] = {policy: {**values, **extra} for policy, values in cache[key].items()}
            common.write_json(cache_path, cache)
        for policy in readings.POLICIES:
            rows.append({"tag": config["tag"], "variant": config["variant"], "seed": config["seed"],
                         "updates": updates, "policy": policy, **cache[key][policy],
                         "checkpoint": os.path.relpath(path, sweep.storage)})  # fmt: skip
    os.makedirs(sweep.results, exist_ok=True)
    base = os.path.join(sweep.results, f"sweep_{sweep.name}")
    common.write_table(base + ".csv", rows, readings.COLUMNS)
    text = report_table(sweep, rows, waiting)
    common.write_text(base + ".md", text)
    return text


def model_again(name: str, kept: dict, measured: dict) -> dict:
    """`measured`, the MODEL readings of a trial measured again to add a column read since, if the readings `kept`
    for it come back (its seeded sampled drive is the same: the same eliminations, the others within 1%); else a
    ValueError naming what differs, as a column from another drive than its row's would mislead."""
    differ = []
    for column in (c for c in readings.MODEL if c in kept):
        old, new = float(kept[column]), float(measured[column])
        same = (math.isnan(old) and math.isnan(new)) or abs(new - old) <= 0.01 * abs(old) + 1e-9
        if not same or (column == "eliminations" and new != old):
            differ.append(f"{column} kept {old:g}, now {new:g}")
    if differ:
        raise ValueError(f"{name}: its kept readings do not come back on the same tracks ({'; '.join(differ)}): "
                         "the drive differs (another torch, thread count or collector?); remove its entry from "
                         "readings.json to measure it anew")  # fmt: skip
    return measured


def report_table(sweep: Sweep, rows: list[dict], waiting: list[str]) -> str:
    """Markdown: the sweep's command, then one line per trial and policy."""
    grid = " ".join(f'"{flags}"' for flags in sweep.grid)
    budget, when = f"--updates {sweep.updates}", f"at {sweep.updates} updates"
    if sweep.cpu_hours > 0:
        budget, when = f"--cpu-hours {sweep.cpu_hours:g}", f"when its {sweep.cpu_hours:g} CPU-hours ran out"
    lines = [
        f"# Sweep {sweep.name}",
        "",
        f"`python benchmarks/sweep.py --name {sweep.name} --grid {grid} --variants {' '.join(sweep.variants)} "
        f"--seeds {' '.join(map(str, sweep.seeds))} {budget}`, then `--report`: each trial's policy {when} on "
        f"tracks {common.track_block(sweep.first_track, sweep.tracks)} (benchmarks/readings.py says what each "
        "column is).",
        "",
    ]  # fmt: skip
    hidden = ("checkpoint",) if sweep.cpu_hours > 0 else ("updates", "checkpoint")  # (a budget: updates differ)
    shown = [c for c in readings.COLUMNS if c not in hidden]
    lines += ["| " + " | ".join(shown) + " |", "|" + "---|" * len(shown)]
    for row in rows:
        cells = [f"{row[c]:.2f}" if isinstance(row[c], float) else str(row[c]) for c in shown]
        lines.append("| " + " | ".join(cells) + " |")
    if waiting:
        lines += ["", "Not finished yet: " + ", ".join(waiting) + "."]
    return "\n".join(lines) + "\n"


def main(sweep: Sweep) -> None:
    sweep = dataclasses.replace(sweep, storage=os.path.abspath(sweep.storage))
    saved = saved_fields(sweep)
    if (sweep.status or sweep.report) and saved is not None:  # the sweep as it was started, whatever the flags say
        sweep = dataclasses.replace(sweep, **{k: tuple(v) if isinstance(v, list) else v for k, v in saved.items()})
    if sweep.status:
        try:
            print(status_text(sweep))
        except ValueError as error:  # a flag of its grid this code no longer has (trial_progress parses them)
            raise SystemExit(f"sweep.py: --status of sweep {sweep.name!r}: {error}") from None
        return
    check(sweep)
    if sweep.report:
        try:
            print(report(sweep))
        except ValueError as error:  # kept readings that do not come back (model_again)
            raise SystemExit(f"sweep.py: --report of sweep {sweep.name!r}: {error}") from None
        return
    run_sweep(sweep)
    print(status_text(sweep))


if __name__ == "__main__":
    from utils.run import tyro_cli

    main(tyro_cli(Sweep))
