"""Head-to-head races between saved agents of any variant, and the multi-agent training phase.

    python race.py A.pt B.pt [C.pt ...] --races 100 --seed 1
    python race.py pretrained/lstm_cpu.pt --opponent pursuit:70
    python race.py A.pt B.pt --train --episodes 200      # both keep learning while they race

Every checkpoint names its variant (``"lstm"`` -> ``dreamer_lstm.py``, ``"gru"`` -> ``dreamer_gru.py``) and the
agent is built and loaded by that script's own functions; an acting-only export (``pretrained/*.pt``) races like a
checkpoint. A path may end in ``:k`` to pick agent ``k`` of a multi-agent checkpoint (default 0).

Races run on seeded tracks: track ``j`` is raced once per car with the start grid rotated, so every car starts from
every grid slot equally often, driven by the collector of training and evaluation (``Races``, utils/collector.py).
Each Dreamer racer decides at the rate it was trained at: a new action every
``action_repeat`` env steps of its own, held in between (its recorded transitions sum the rewards of the held
steps), with ``--policy`` (default: the mean action from a sampled latent; ``--train`` always samples; torch is
seeded with ``--seed``). The table per racer
(also as CSV and JSON in ``--out``): wins, win rate with a Wilson 95% interval, mean finish time of finished races,
mean progress, eliminations, collision steps; plus an mp4 of the first race (``--no-video``: none).

``--train``: the multi-agent phase of the paper. Every Dreamer racer keeps training, decentralized (Algorithm 1):
its own replay buffer (the one saved beside its checkpoint unless ``--fresh-replay``), filled with its own car's
transitions, and ``--train-steps`` updates after every race (the scripts' ``train_agent``); TensorBoard logging per
racer (return, progress, win rate, losses) and, after every race, a checkpoint per racer with its replay beside it
(``runs/<run>/checkpoints/racer_<i>.pt`` and ``racer_<i>_replay_car_0/``), so a later ``--train`` command continues
from both.
"""

from __future__ import annotations

import csv
import dataclasses
import importlib
import json
import math
import os
import random
import sys
import time
from typing import Annotated, Literal

import numpy as np
import scipy.stats
import torch
import tyro

from envs import MultiCarRacing, race_winners
from envs.pursuit import PursuitDriver, lane_of
import utils.run as run_tools
from utils import checkpoint as saved
from utils.collector import Races


@dataclasses.dataclass
class Args:
    checkpoints: tyro.conf.Positional[tuple[str, ...]] = ()
    """checkpoint files or acting-only exports (path, or path:agent_index)"""
    races: int = 100
    """races to run (evaluation)"""
    seed: int = 1
    """track seeds are derived from it"""
    opponent: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """a scripted pure-pursuit driver to add: pursuit or pursuit:SPEED (default speed 70); repeatable"""
    policy: Literal["deterministic", "mean-action", "stochastic"] = "mean-action"
    """how Dreamer racers act: deterministic = posterior-mean latent and mean action; mean-action = sampled latent,
    mean action (the default, as the scripts' evaluation: docs/learning.md); stochastic = sampled
    latent and action, as trained (--train always samples)"""
    out: str | None = None
    """directory of results.csv/json and race.mp4 (default races/<time>)"""
    video: bool = True
    """save an mp4 of the first race"""
    max_steps: int | None = None
    """env max_steps (default: the first checkpoint's)"""
    cuda: bool = True
    """use CUDA when available"""
    torch_threads: int = 0
    """torch CPU threads (0: torch's default)"""
    train: bool = False
    """the multi-agent phase: keep training every agent while racing"""
    episodes: int = 200
    """--train: races to train for"""
    train_steps: int | None = None
    """--train: updates per agent per race (default: each agent's own --train-steps-per-episode)"""
    fresh_replay: bool = False
    """--train: start from empty replays (default: each checkpoint's saved replay)"""
    runs_dir: str = "runs"
    """--train: where the run directory goes"""
    exp_name: str = "race"
    """--train: experiment name of the run"""


def wilson_interval(wins: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (wins out of n), by scipy; (0, 1) before any race."""
    if n == 0:
        return 0.0, 1.0
    interval = scipy.stats.binomtest(wins, n).proportion_ci(confidence_level=confidence, method="wilson")
    return float(interval.low), float(interval.high)


# --- Racers ---------------------------------------------------------------------------------
class DreamerRacer:
    """A saved Dreamer agent driving one car; built and loaded by its own script."""

    def __init__(self, spec: str, device="cpu", policy: str = "stochastic", training: bool = False):
        path, _, index = spec.rpartition(":") if spec.rpartition(":")[2].isdigit() else (spec, "", "0")
        self.module, checkpoint = saved.read_checkpoint(path, device, training)
        self.path, self.index, self.variant = path, int(index), checkpoint["variant"]
        try:  # the script's own reading of its arguments and networks, with one-line errors naming the file
            self.args = self.module.args_from_checkpoint(checkpoint, path)
            self.agent = self.module.agent_from_checkpoint(path, self.index, device, checkpoint)
        except (ValueError, RuntimeError, TypeError) as e:  # the script's CheckpointError, or impossible sizes
            text = (str(e).strip().splitlines() or [type(e).__name__])[0]
            message = text if text.startswith(path) else f"{path}: does not build an agent: {text}"
            raise saved.CheckpointError(message) from None
        self.policy, self.counters = policy, dict(checkpoint.get("counters") or {})
        manifests = list((checkpoint.get("extra") or {}).get("replays") or [])
        self.replay_manifest = manifests[self.index] if self.index < len(manifests) else None  # the save it names
        folder = os.path.dirname(os.path.abspath(path))  # a run's checkpoints/ is named by its run directory
        owner = os.path.dirname(folder) if os.path.basename(folder) == "checkpoints" else folder
        self.name = f"{self.variant}:{os.path.basename(owner)}/{os.path.basename(path)}:{self.index}"
        self.learns = True
        self.action_repeat = int(self.args.action_repeat)  # as in training: one decision per this many env steps


class PursuitRacer:
    """The scripted pure-pursuit driver of ``envs/pursuit.py`` as a racer, keeping to the lane of its start-grid
    column; it decides every env step and drives like an agent of the scripts' collector (``act``)."""

    learns, action_repeat, action_dim, policy = False, 1, 2, "scripted"

    def __init__(self, speed: float):
        self.speed = speed
        self.name = f"pursuit@{speed:g}"
        self.env = self.agent = self.driver = None

    def bind(self, env: MultiCarRacing, agent: str) -> None:
        """The race env it reads the track and its car from, and the car it drives."""
        self.env, self.agent = env, agent

    def act(self, obs, state, is_first, policy):
        if is_first[0]:  # a new race: the lane of its grid column
            self.driver = PursuitDriver(self.env, self.agent, self.speed, lane=lane_of(self.env, self.agent))
        return self.driver.act()[None], state


# --- One race -------------------------------------------------------------------------------
@dataclasses.dataclass
class RaceResult:
    final_infos: list[dict]
    returns: list[float]
    winners: list[bool]
    frames: list[np.ndarray]
    episodes: list  # per racer: its car's episode (a CarEpisode, frames at the image size of the collector's Args)


def collector_args(racers: list):
    """The Args the collector (utils/collector.py) drives the races with, for the env settings and recorded frames:
    the first Dreamer racer's (scripted drivers alone: the LSTM script's defaults)."""
    dreamers = [r for r in racers if isinstance(r, DreamerRacer)]
    return dreamers[0].args if dreamers else importlib.import_module(saved.VARIANT_SCRIPTS["lstm"]).Args()


def run_race(envs, racers: list, seed: int, grid: list[int], record_video=False) -> RaceResult:
    """One race on track `seed` with start grid `grid`, driven by the shared collector (`Races`): each Dreamer
    racer decides every action_repeat env steps of its own car with its policy, the pursuit driver every step."""
    args = collector_args(racers)
    env = envs.get_attr("unwrapped")[0]  # (the env itself: the race runs in this process)
    for racer, agent in zip(racers, env.possible_agents):
        if isinstance(racer, PursuitRacer):
            racer.bind(env, agent)
    envs.set_options({"grid": grid})
    envs.seed(seed)
    obs = envs.reset()
    frames = [envs.get_images()[0]] if record_video else None
    drivers = [r.agent if isinstance(r, DreamerRacer) else r for r in racers]
    races = Races(drivers, args, envs, obs, [r.action_repeat for r in racers])
    [race], _ = races.drive([r.policy for r in racers], frames)
    final_infos = [car.final_info for car in race.cars]
    returns = [float(r) for r in race.readings["return"]]
    return RaceResult(final_infos, returns, race_winners(final_infos), frames or [], race.cars)


# --- Statistics -----------------------------------------------------------------------------
class Tally:
    def __init__(self, name: str):
        self.name = name
        self.races = self.wins = self.eliminations = self.collision_steps = 0
        self.finish_steps: list[int] = []
        self.progress: list[float] = []
        self.returns: list[float] = []

    def add(self, info: dict, won: bool, ret: float):
        self.races += 1
        self.wins += int(won)
        self.eliminations += int(info.get("eliminated") is not None)
        self.collision_steps += int(info["collision_steps"])
        self.progress.append(float(info["progress"]))
        self.returns.append(float(ret))
        if info["lap_finished"]:
            self.finish_steps.append(int(info["finish_step"]))

    def row(self) -> dict:
        lo, hi = wilson_interval(self.wins, self.races)
        return {
            "racer": self.name,
            "races": self.races,
            "wins": self.wins,
            "win_rate": self.wins / max(1, self.races),
            "win_rate_ci_low": lo,
            "win_rate_ci_high": hi,
            "finished": len(self.finish_steps),
            "mean_finish_step": float(np.mean(self.finish_steps)) if self.finish_steps else None,
            "mean_progress": float(np.mean(self.progress)) if self.progress else 0.0,
            "mean_return": float(np.mean(self.returns)) if self.returns else 0.0,
            "eliminations": self.eliminations,
            "collision_steps": self.collision_steps,
        }


def format_table(rows: list[dict]) -> str:
    header = (f"{'racer':<44} {'wins':>5} {'win rate [95% CI]':>22} {'finish':>8} {'progress':>9} {'elim':>5}"
              f" {'coll':>6}")  # fmt: skip
    lines = [header, "-" * len(header)]
    for r in rows:
        finish = "-" if r["mean_finish_step"] is None else f"{r['mean_finish_step']:.0f}"
        ci = f"{r['win_rate']:.2f} [{r['win_rate_ci_low']:.2f}, {r['win_rate_ci_high']:.2f}]"
        lines.append(
            f"{r['racer'][-44:]:<44} {r['wins']:>5} {ci:>22} {finish:>8} {r['mean_progress']:>9.2f}"
            f" {r['eliminations']:>5} {r['collision_steps']:>6}"
        )
    return "\n".join(lines)


def write_outputs(out: str, rows: list[dict], frames: list[np.ndarray]) -> list[str]:
    os.makedirs(out, exist_ok=True)
    written = []
    with open(os.path.join(out, "results.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    with open(os.path.join(out, "results.json"), "w") as f:
        json.dump(rows, f, indent=2)
    written += [os.path.join(out, "results.csv"), os.path.join(out, "results.json")]
    if frames:
        import imageio.v2 as imageio

        path = os.path.join(out, "race.mp4")
        imageio.mimwrite(path, frames, fps=MultiCarRacing.metadata["render_fps"], macro_block_size=8)
        written.append(path)
    return written


# --- Main -------------------------------------------------------------------------------------
def usage_error(message: str) -> None:
    """Exit as argparse does on bad input: status 2, one line on stderr (utils.run.usage_error)."""
    run_tools.usage_error("race.py", message)


def parse_args(argv=None) -> Args:
    """Args of a command line, checked: any impossible value exits with status 2 and one line naming it."""
    args = run_tools.tyro_cli(Args, argv, __doc__)
    racers = len(args.checkpoints) + len(args.opponent)
    if racers < 1 or (racers < 2 and not args.train):
        fewest = "one racer with --train" if args.train else "two racers"
        usage_error(f"need at least {fewest} (checkpoints plus --opponent), got {racers}")
    for name, minimum in (("torch_threads", 0), ("races", 1), ("seed", 0), ("episodes", 1), ("train_steps", 0),
                          ("max_steps", 1)):  # fmt: skip
        value = getattr(args, name)
        if value is not None and value < minimum:
            usage_error(f"--{name.replace('_', '-')} must be >= {minimum}, got {value}")
    if args.train and args.out is not None:
        usage_error("--out is where a race's results go; --train writes its run directory under --runs-dir")
    for flag, path in (("--out", args.out), ("--runs-dir", args.runs_dir)):
        if path is not None and os.path.exists(path) and not os.path.isdir(path):
            usage_error(f"{flag} {path!r} exists and is not a directory")
    opponent_speeds(args)  # (checks them)
    return args


def opponent_speeds(args: Args) -> list[float]:
    """The speed of every --opponent (pursuit or pursuit:SPEED, default 70)."""
    speeds = []
    for spec in args.opponent:
        kind, _, speed = spec.partition(":")
        try:
            value = float(speed) if speed else 70.0
        except ValueError:
            value = -1.0
        if kind != "pursuit" or not math.isfinite(value) or value <= 0:
            usage_error(f"--opponent must be pursuit or pursuit:SPEED with a finite SPEED > 0, got {spec!r}")
        speeds.append(value)
    return speeds


def build_racers(args: Args, device) -> list:
    policy = "stochastic" if args.train else args.policy
    racers = [DreamerRacer(spec, device, policy, training=args.train) for spec in args.checkpoints]
    return racers + [PursuitRacer(speed) for speed in opponent_speeds(args)]


def make_env(args, racers, render=False):
    """The race as a one-race vec env of the scripts (utils.make_vec_env), with the env settings the first Dreamer
    racer trained with (utils.run.env_kwargs at its final dead zone; all cars share one env)."""
    from utils import make_vec_env

    kwargs = {}
    dreamers = [r for r in racers if isinstance(r, DreamerRacer)]
    if dreamers:
        kwargs = run_tools.env_kwargs(dreamers[0].args, dreamers[0].args.dead_zone_end)
    kwargs["num_agents"] = len(racers)
    if args.max_steps is not None:
        kwargs["max_steps"] = args.max_steps
    return make_vec_env("multi_car_racing", 1, None, render_mode="rgb_array" if render else None, **kwargs)


def schedule(seed: int, race: int, num_cars: int) -> tuple[int, list[int]]:
    """Track seed and grid of race ``race``: each track is raced ``num_cars`` times, the grid
    rotated by one slot each time."""
    rotation = race % num_cars
    return seed * 100_003 + race // num_cars, [(i + rotation) % num_cars for i in range(num_cars)]


def evaluate(args, racers) -> list[dict]:
    env = make_env(args, racers)
    video_env = make_env(args, racers, render=True) if args.video else None
    tallies = [Tally(r.name) for r in racers]
    frames = []
    if args.races % len(racers):
        print(f"note: {args.races} races is not a multiple of {len(racers)} racers: start slots are not balanced")
    all_out = no_winner = dead_heats = 0  # races in which every car was eliminated / nobody won / several won
    for race in range(args.races):
        seed, grid = schedule(args.seed, race, len(racers))
        filmed = race == 0 and video_env is not None
        result = run_race(video_env if filmed else env, racers, seed, grid, record_video=filmed)
        frames = frames or result.frames
        for tally, info, won, ret in zip(tallies, result.final_infos, result.winners, result.returns):
            tally.add(info, won, ret)
        all_out += all(info.get("eliminated") is not None for info in result.final_infos)
        no_winner += not any(result.winners)
        dead_heats += sum(result.winners) > 1
    # (race-wide counts, the same on every row; for two cars: both rows' wins + no_winner - dead_heats = races)
    rows = [{**t.row(), "all_eliminated": all_out, "no_winner": no_winner, "dead_heats": dead_heats} for t in tallies]
    print(format_table(rows))
    out = args.out or os.path.join("races", time.strftime("%Y%m%d-%H%M%S"))
    for path in write_outputs(out, rows, frames):
        print("wrote", path)
    return rows


def train(args: Args, racers: list) -> str:
    """The multi-agent phase: race, store each car's own transitions, update each agent (Algorithm 1); after every
    race each learning racer's checkpoint and replay are saved side by side. Returns the run directory."""
    from utils.logger import configure_logger, make_run_name

    learners = [i for i, r in enumerate(racers) if r.learns]
    if not learners:
        raise SystemExit("race.py: --train needs at least one checkpoint (scripted drivers do not learn)")
    sizes = {racers[i].args.image_size for i in learners}
    if len(sizes) > 1:  # (the race records every car's frames at one size)
        raise SystemExit(f"race.py: --train needs learning racers of one image size, got {sorted(sizes)}")
    env = make_env(args, racers)
    run_dir = os.path.join(args.runs_dir, make_run_name("multi_car_racing", args.exp_name, args.seed))
    print("run directory:", run_dir)  # (for tensorboard --logdir while it trains)
    checkpoint_dir = os.path.join(run_dir, "checkpoints")
    config = {"variant": "+".join(racers[i].variant for i in learners), "stage": "race", "seed": args.seed}
    hyperparameters = {**dataclasses.asdict(args), "racers": [r.name for r in racers]}
    logger = configure_logger(run_dir, hyperparameters, ("csv", "tensorboard"))
    saved.atomic_write(os.path.join(run_dir, "config.json"), lambda f: f.write(json.dumps(config).encode()))
    replays, train_args = {}, {}
    for i in learners:
        r = racers[i]
        replays[i] = r.module.Replay(r.args.replay_capacity, r.args.image_size, r.agent.action_dim)
        kept = saved.replay_dir_of(r.path, r.index)
        if not args.fresh_replay and os.path.isdir(kept):  # the agent keeps learning from all it has seen
            saved.restore_replay(replays[i], kept, r.replay_manifest, races=0)
            print(f"{r.name}: continues with the replay in {kept} ({len(replays[i]):,} steps)")
        steps = r.args.train_steps_per_episode if args.train_steps is None else args.train_steps
        train_args[i] = dataclasses.replace(r.args, train_steps_per_episode=steps)
    wins = {i: [] for i in range(len(racers))}
    # A later sitting continues the schedule of tracks (and the random stream) where the racers' last one stopped,
    # and counts env steps on from theirs (the x of its TensorBoard scalars)
    done_before = max(int(racers[i].counters.get("race_episodes", 0)) for i in learners)
    env_steps = max(int(racers[i].counters.get("race_env_steps", 0)) for i in learners)
    stream = args.seed * 100_003 + done_before  # seeds every random stream of training: actions, replay batches
    torch.manual_seed(stream)
    np.random.seed(stream % 2**32)
    random.seed(stream)
    for episode in range(args.episodes):
        seed, grid = schedule(args.seed, done_before + episode, len(racers))
        result = run_race(env, racers, seed, grid)
        env_steps += max(int(info["step"]) for info in result.final_infos)
        logger.record("charts/race", done_before + episode + 1)  # over every sitting: the x of plot.py's race figures
        for i, (info, won, ret) in enumerate(zip(result.final_infos, result.winners, result.returns)):
            wins[i].append(won)
            prefix = f"racer_{i}_{racers[i].variant if i in learners else 'pursuit'}"
            logger.record(f"{prefix}/charts/episodic_return", ret)
            logger.record(f"{prefix}/charts/progress", info["progress"])
            logger.record(f"{prefix}/charts/win_rate", float(np.mean(wins[i][-20:])))
            if info["lap_finished"]:
                logger.record(f"{prefix}/charts/lap_time", info["finish_step"])
        for i in learners:
            racer, replay, prefix = racers[i], replays[i], f"racer_{i}_{racers[i].variant}/"
            replay.add_episode(*result.episodes[i].arrays())
            if replay.can_sample(racer.args.seq_len):
                updates_per_s = racer.module.train_agent(racer.agent, replay, train_args[i], logger, prefix)
                logger.record(f"{prefix}perf/updates_per_s", updates_per_s)
            logger.record(f"{prefix}perf/updates", racer.agent.num_updates)
        save_racers({i: (racers[i], replays[i]) for i in learners}, checkpoint_dir, episode + 1, env_steps)
        for i in learners:
            racer = racers[i]
            if racer.agent.nonfinite_in_a_row >= racer.args.max_nonfinite_updates:
                logger.dump(env_steps)
                raise SystemExit(f"race.py: {racer.name}: {racer.agent.nonfinite_in_a_row} updates in a row had a "
                                 f"non-finite loss or gradient; stopped after race {episode + 1} with its checkpoint")
        logger.dump(env_steps)
        print(f"race {episode + 1}/{args.episodes}: "
              + ", ".join(f"{racers[i].name} win rate {np.mean(wins[i]):.2f}" for i in wins))  # fmt: skip
    logger.close()
    print("run directory:", run_dir)
    return run_dir


def save_racers(learning: dict, checkpoint_dir: str, races: int, env_steps: int) -> None:
    """Every learning racer's checkpoint (``racer_<i>.pt``) with its replay beside it (``racer_<i>_replay_car_0``),
    as one pair: each replay is saved first, then a pending checkpoint naming that save, and only when all are
    written do the pending checkpoints replace the previous ones, back to back. A kill while saving leaves the
    previous pair (a later sitting continues from racers saved after the same race) except in the microseconds
    between those renames; the replay chunks that no checkpoint names any more are deleted last.

    Its counters: those the racer started with (``episode``, ``global_step``: its training before the head-to-head
    races) and, over every sitting so far, the head-to-head races (``race_episodes``: this sitting's `races` added)
    and env steps (``race_env_steps``: `env_steps`, counted on from the last sitting's)."""
    pending = {}
    for i, (racer, replay) in learning.items():
        path = os.path.join(checkpoint_dir, f"racer_{i}.pt")
        manifest = saved.save_replay(replay, f"{os.path.splitext(path)[0]}_replay_car_0")
        before = int(racer.counters.get("race_episodes", 0))  # races of earlier head-to-head sittings
        counters = {**racer.counters, "race_episodes": before + races, "race_env_steps": env_steps}
        saved.save_checkpoint(path + ".pending", racer.variant, racer.args, [racer.agent], counters,
                              {"replays": [manifest]})  # fmt: skip
        pending[i] = (path, manifest)
    for path, _ in pending.values():
        os.replace(path + ".pending", path)
    for i, (path, manifest) in pending.items():
        saved.prune_replay(f"{os.path.splitext(path)[0]}_replay_car_0", manifest)


def main(argv=None):
    args = parse_args(argv)
    device = torch.device("cuda" if args.cuda and torch.cuda.is_available() else "cpu")
    torch.manual_seed(args.seed)  # sampled actions: the same command races the same races
    if args.torch_threads > 0:
        torch.set_num_threads(args.torch_threads)
    try:
        racers = build_racers(args, device)
    except saved.CheckpointError as e:
        sys.exit(f"race.py: {e}")
    if args.train:
        return train(args, racers)
    return evaluate(args, racers)


if __name__ == "__main__":
    main()
