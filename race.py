"""Head-to-head races between saved agents of any variant, and the multi-agent training phase.

    python race.py A.pt B.pt [C.pt ...] --races 100 --seed 1
    python race.py runs/<lstm run>/checkpoints/best.pt --opponent pursuit:70
    python race.py A.pt B.pt --train --episodes 200      # both keep learning while they race

Every checkpoint names its variant (``"lstm"`` -> ``dreamer_lstm.py``, ``"gru"`` ->
``dreamer_gru.py``) and the agent is built from that script's own importable pieces. A
checkpoint path may end in ``:k`` to pick agent ``k`` of a multi-agent checkpoint (default 0).

Races run on seeded tracks: track ``j`` is raced once per car with the start grid rotated, so
every car starts from every grid slot equally often. Each Dreamer racer decides at the rate it was
trained at: a new action every ``action_repeat`` env steps of its own, held in between (its
recorded transitions sum the rewards of the held steps). Actions are deterministic (posterior mean
and actor mean) unless ``--stochastic``. The table per racer (also as CSV and JSON in
``--out``): wins, win rate with a Wilson 95% interval, mean finish time of finished races,
mean progress, eliminations, collision steps; plus an mp4 of the first race (``--video``).

``--train``: the multi-agent phase of the paper. Every Dreamer racer keeps training,
decentralized (Algorithm 1): its own replay buffer (the one saved beside its checkpoint, in
``checkpoints/replay_car_k/``, unless ``--fresh-replay``), filled with its own car's transitions, and
``--train-steps`` updates after every race; TensorBoard logging per racer (return, progress,
win rate, losses) and a checkpoint per racer in ``runs/<run>/checkpoints/``.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import importlib
import json
import math
import os
import pickle
import sys
import time
import zipfile

import numpy as np
import torch

from envs import MultiCarRacing, race_winners
from envs.pursuit import PursuitDriver, lane_of

VARIANT_SCRIPTS = {"lstm": "dreamer_lstm", "gru": "dreamer_gru"}
WILSON_Z = 1.959963984540054  # two-sided 95%


def wilson_interval(wins: int, n: int, z: float = WILSON_Z) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (wins out of n)."""
    if n == 0:
        return 0.0, 1.0
    p = wins / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


# --- Racers ---------------------------------------------------------------------------------
class CheckpointError(ValueError):
    """A file that is not a readable checkpoint of ours; the message names the file."""


def read_checkpoint(path: str, device="cpu") -> dict:
    """Load one of our checkpoints with ``weights_only=True``, with one-line errors."""
    if not os.path.isfile(path):
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        checkpoint = torch.load(path, map_location=device, weights_only=True)
    except (RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile, ValueError, OSError) as e:
        first_line = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or not a torch file): {first_line}") from None
    if not isinstance(checkpoint, dict) or "variant" not in checkpoint or "agents" not in checkpoint:
        raise CheckpointError(f"{path}: not a DLC checkpoint (no 'variant' and 'agents' entries)")
    if not isinstance(checkpoint["agents"], list) or not isinstance(checkpoint.get("args"), dict):
        raise CheckpointError(f"{path}: not a DLC checkpoint (its 'agents' or 'args' entry is malformed)")
    if not isinstance(checkpoint["variant"], str) or checkpoint["variant"] not in VARIANT_SCRIPTS:
        raise CheckpointError(f"{path}: unknown variant {checkpoint['variant']!r}; known: {sorted(VARIANT_SCRIPTS)}")
    return checkpoint


class DreamerRacer:
    """A saved Dreamer agent driving one car; built by its own script's ``Agent`` and ``Args``."""

    def __init__(self, spec: str, device="cpu", policy: str = "deterministic"):
        path, _, index = spec.rpartition(":") if spec.rpartition(":")[2].isdigit() else (spec, "", "0")
        checkpoint = read_checkpoint(path, device)
        self.path, self.index = path, int(index)
        if not 0 <= self.index < len(checkpoint["agents"]):
            raise CheckpointError(f"{path}: has {len(checkpoint['agents'])} agent(s), asked for agent {self.index}")
        self.variant = checkpoint["variant"]
        self.module = importlib.import_module(VARIANT_SCRIPTS[self.variant])
        try:  # the script's own reading of its arguments and networks, with one-line errors naming the file
            self.args = self.module.args_from_checkpoint(checkpoint, path)
            self.agent = self.module.Agent(self.args, device=device)
            self.module.load_agent_state(self.agent, checkpoint["agents"][self.index], path, self.index)
        except (ValueError, RuntimeError, TypeError) as e:  # the script's CheckpointError, or impossible sizes
            text = (str(e).strip().splitlines() or [type(e).__name__])[0]
            raise CheckpointError(text if text.startswith(path) else f"{path}: does not build an agent: {text}") from None
        self.policy = policy
        self.name = f"{self.variant}:{os.path.basename(os.path.dirname(os.path.dirname(os.path.abspath(path))))}/{os.path.basename(path)}:{self.index}"
        self.state, self.learns = None, True
        self.action_repeat = int(self.args.action_repeat)  # as in training: one decision per this many env steps
        self.held, self.held_steps = None, 0

    def reset(self, env, agent):
        self.state, self.held, self.held_steps = None, None, 0

    def act(self, obs: np.ndarray, is_first: bool) -> np.ndarray:
        """A new action every --action-repeat env steps of this racer (the rate it was trained at), else the held one."""
        if self.held is None or self.held_steps == self.action_repeat:
            action, self.state = self.agent.act(obs[None], self.state, np.array([is_first]), self.policy)
            self.held, self.held_steps = action[0], 0
        self.held_steps += 1
        return self.held


class PursuitRacer:
    """The scripted pure-pursuit driver of ``envs/pursuit.py`` as a racer, keeping to the lane
    of its start-grid column."""

    learns = False

    def __init__(self, speed: float):
        self.speed = speed
        self.name = f"pursuit@{speed:g}"

    def reset(self, env, agent):
        self.driver = PursuitDriver(env, agent, self.speed, lane=lane_of(env, agent))

    def act(self, obs, is_first):
        return self.driver.act()


class EpisodeRecorder:
    """A learning racer's own car episode, frames at its encoder's size (its script's CarEpisode), one transition
    per decision as in training: rewards summed over the racer's action repeat, the frame after the last of them."""

    def __init__(self, racer: DreamerRacer, first_obs: np.ndarray):
        self.racer = racer
        self.episode = racer.module.CarEpisode(self._frame(first_obs))
        self.reward, self.steps = 0.0, 0

    def _frame(self, obs):
        return self.racer.module.preprocess_frames(obs[None], self.racer.args.image_size)[0]

    def add(self, obs, action, reward, terminated, done):
        """One env step of the car; `done`: its episode ended with this step (terminated or truncated)."""
        self.reward, self.steps = self.reward + reward, self.steps + 1
        if self.steps == self.racer.action_repeat or done:
            self.episode.add(self._frame(obs), action, self.reward, terminated)
            self.reward, self.steps = 0.0, 0


# --- One race -------------------------------------------------------------------------------
@dataclasses.dataclass
class RaceResult:
    final_infos: list[dict]
    returns: list[float]
    winners: list[bool]
    frames: list[np.ndarray]
    episodes: list  # per racer: its EpisodeRecorder when training, else None


def run_race(env: MultiCarRacing, racers: list, seed: int, grid: list[int], record_video=False, episodes=None) -> RaceResult:
    """One race; ``episodes[i]`` (optional, a callable obs -> episode recorder) collects racer i's transitions."""
    obs, infos = env.reset(seed=seed, options={"grid": grid})
    agents = env.possible_agents
    for racer, agent in zip(racers, agents):
        racer.reset(env, agent)
    recorders = [make(obs[a]) if make else None for make, a in zip(episodes or [None] * len(racers), agents)]
    final = dict(infos)
    returns = [0.0] * len(racers)
    frames = [env.render()] if record_video else []
    first = True
    while env.agents:
        actions = {a: racers[i].act(obs[a], first) for i, a in enumerate(agents) if a in env.agents}
        obs, rewards, terms, truncs, infos = env.step(actions)
        first = False
        for i, a in enumerate(agents):
            if a in rewards:
                returns[i] += rewards[a]
                if recorders[i] is not None:
                    recorders[i].add(obs[a], actions[a], rewards[a], terms[a], terms[a] or truncs[a])
        final.update(infos)
        if record_video:
            frames.append(env.render())
    final_infos = [final[a] for a in agents]
    return RaceResult(final_infos, returns, race_winners(final_infos), frames, recorders)


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
    header = f"{'racer':<44} {'wins':>5} {'win rate [95% CI]':>22} {'finish':>8} {'progress':>9} {'elim':>5} {'coll':>6}"
    lines = [header, "-" * len(header)]
    for r in rows:
        finish = "-" if r["mean_finish_step"] is None else f"{r['mean_finish_step']:.0f}"
        ci = f"{r['win_rate']:.2f} [{r['win_rate_ci_low']:.2f}, {r['win_rate_ci_high']:.2f}]"
        lines.append(
            f"{r['racer'][-44:]:<44} {r['wins']:>5} {ci:>22} {finish:>8} {r['mean_progress']:>9.2f} {r['eliminations']:>5} {r['collision_steps']:>6}"
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
def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoints", nargs="*", help="checkpoint files (path or path:agent_index)")
    parser.add_argument("--races", type=int, default=100, help="races to run (evaluation)")
    parser.add_argument("--seed", type=int, default=1, help="track seeds are derived from it")
    parser.add_argument(
        "--opponent", action="append", default=[], metavar="pursuit[:SPEED]", help="add a scripted pure-pursuit driver (repeatable; default speed 70)"
    )
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of taking the means")
    parser.add_argument("--out", default=None, help="directory of results.csv/json and race.mp4 (default races/<time>)")
    parser.add_argument("--video", action=argparse.BooleanOptionalAction, default=True, help="save an mp4 of the first race")
    parser.add_argument("--max-steps", type=int, default=None, help="env max_steps (default: the first checkpoint's)")
    parser.add_argument("--cuda", action=argparse.BooleanOptionalAction, default=True, help="use CUDA when available")
    parser.add_argument("--torch-threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--train", action="store_true", help="the multi-agent phase: keep training every agent while racing")
    parser.add_argument("--episodes", type=int, default=200, help="--train: races to train for")
    parser.add_argument("--train-steps", type=int, default=None, help="--train: updates per agent per race (default: each agent's own)")
    parser.add_argument(
        "--fresh-replay", action="store_true", help="--train: start from empty replays (default: each checkpoint's saved replay)"
    )
    parser.add_argument("--runs-dir", default="runs", help="--train: where the run directory goes")
    parser.add_argument("--exp-name", default="race", help="--train: experiment name of the run")
    args = parser.parse_args(argv)
    racers = len(args.checkpoints) + len(args.opponent)
    if racers < 1 or (racers < 2 and not args.train):
        parser.error(f"need at least two racers (checkpoints plus --opponent), got {racers}")
    if args.torch_threads < 0:
        parser.error(f"--torch-threads must be >= 0, got {args.torch_threads}")
    if args.races < 1:
        parser.error(f"--races must be >= 1, got {args.races}")
    if args.seed < 0:
        parser.error(f"--seed must be >= 0 (track seeds derive from it), got {args.seed}")
    if args.max_steps is not None and args.max_steps < 1:
        parser.error(f"--max-steps must be >= 1, got {args.max_steps}")
    for flag, path in (("--out", args.out), ("--runs-dir", args.runs_dir)):
        if path is not None and os.path.exists(path) and not os.path.isdir(path):
            parser.error(f"{flag} {path!r} exists and is not a directory")
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    args.opponent_speeds = []
    for spec in args.opponent:
        kind, _, speed = spec.partition(":")
        try:
            value = float(speed) if speed else 70.0
        except ValueError:
            value = -1.0
        if kind != "pursuit" or not math.isfinite(value) or value <= 0:
            parser.error(f"--opponent must be pursuit or pursuit:SPEED with a finite SPEED > 0, got {spec!r}")
        args.opponent_speeds.append(value)
    if args.train_steps is not None and args.train_steps < 0:
        parser.error(f"--train-steps must be >= 0, got {args.train_steps}")
    return args


def build_racers(args, device) -> list:
    policy = "stochastic" if args.stochastic or args.train else "deterministic"
    racers = [DreamerRacer(spec, device, policy) for spec in args.checkpoints]
    racers += [PursuitRacer(speed) for speed in args.opponent_speeds]
    return racers


def make_env(args, racers, render=False) -> MultiCarRacing:
    """The race env with the first Dreamer racer's env settings (all cars share one env)."""
    kwargs = {}
    dreamers = [r for r in racers if isinstance(r, DreamerRacer)]
    if dreamers:
        a = dreamers[0].args
        kwargs = dict(
            max_steps=a.max_steps,
            stall_steps=a.stall_steps,
            brake_speed_threshold=a.brake_speed_threshold,
            collision_penalty=a.collision_penalty,
            offroad_penalty=a.offroad_penalty,
            speed_reward_coef=a.speed_reward_coef,
            dead_zone=a.dead_zone_end,
        )
    if args.max_steps is not None:
        kwargs["max_steps"] = args.max_steps
    return MultiCarRacing(num_agents=len(racers), render_mode="rgb_array" if render else None, **kwargs)


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
        print(f"note: {args.races} races is not a multiple of {len(racers)} racers: start slots are not perfectly balanced")
    for race in range(args.races):
        seed, grid = schedule(args.seed, race, len(racers))
        result = run_race(video_env if race == 0 and video_env else env, racers, seed, grid, record_video=race == 0 and args.video)
        frames = frames or result.frames
        for tally, info, won, ret in zip(tallies, result.final_infos, result.winners, result.returns):
            tally.add(info, won, ret)
    rows = [t.row() for t in tallies]
    print(format_table(rows))
    out = args.out or os.path.join("races", time.strftime("%Y%m%d-%H%M%S"))
    for path in write_outputs(out, rows, frames):
        print("wrote", path)
    return rows


def train(args, racers, device) -> None:
    """The multi-agent phase: race, store each car's own transitions, update each agent (Algorithm 1)."""
    from utils.logger import configure_logger, make_run_name

    learners = [i for i, r in enumerate(racers) if r.learns]
    if not learners:
        raise SystemExit("race.py: --train needs at least one checkpoint (scripted drivers do not learn)")
    env = make_env(args, racers)
    run_name = make_run_name("multi_car_racing", args.exp_name, args.seed)
    run_dir = os.path.join(args.runs_dir, run_name)
    config = {"variant": "+".join(racers[i].variant for i in learners), "stage": "race", "seed": args.seed}
    logger = configure_logger(run_dir, {**vars(args), "racers": [r.name for r in racers]})
    with open(os.path.join(run_dir, "config.json"), "w") as f:
        json.dump(config, f)
    replays = {}
    for i in learners:
        r = racers[i]
        replays[i] = r.module.Replay(r.args.replay_capacity, r.args.image_size)
        saved = os.path.join(os.path.dirname(os.path.abspath(r.path)), f"replay_car_{r.index}")
        if not args.fresh_replay and os.path.isdir(saved):  # the agent keeps learning from all it has seen
            r.module.restore_replay(replays[i], saved, None, races=0)
            print(f"{r.name}: continues with the replay in {saved} ({len(replays[i]):,} steps)")
    rng = np.random.RandomState(args.seed)
    wins = {i: [] for i in range(len(racers))}
    env_steps = 0
    for episode in range(args.episodes):
        seed, grid = schedule(args.seed, episode, len(racers))
        recorders = [(lambda obs, r=racers[i]: EpisodeRecorder(r, obs)) if i in learners else None for i in range(len(racers))]
        result = run_race(env, racers, seed, grid, episodes=recorders)
        env_steps += max(int(info["step"]) for info in result.final_infos)
        for i, (info, won, ret) in enumerate(zip(result.final_infos, result.winners, result.returns)):
            wins[i].append(won)
            prefix = f"racer_{i}_{racers[i].variant if i in learners else 'pursuit'}"
            logger.record(f"{prefix}/charts/episodic_return", ret)
            logger.record(f"{prefix}/charts/progress", info["progress"])
            logger.record(f"{prefix}/charts/win_rate", float(np.mean(wins[i][-20:])))
            if info["lap_finished"]:
                logger.record(f"{prefix}/charts/lap_time", info["finish_step"])
        for i in learners:
            racer, replay = racers[i], replays[i]
            replay.add_episode(*result.episodes[i].episode.arrays())
            steps = racer.args.train_steps_per_episode if args.train_steps is None else args.train_steps
            losses = {}
            if replay.can_sample(racer.args.seq_len):
                for _ in range(steps):
                    losses = racer.agent.update(replay.sample(racer.args.batch_size, racer.args.seq_len, rng))
            for key, value in losses.items():
                logger.record(f"racer_{i}_{racer.variant}/losses/{key}", value)
            racer.module.save_checkpoint(
                os.path.join(run_dir, "checkpoints", f"racer_{i}.pt"),
                racer.args,
                [racer.agent],
                {"episode": episode + 1, "env_steps": env_steps, "updates": racer.agent.num_updates},
            )
        logger.dump(env_steps)
        print(f"episode {episode + 1}/{args.episodes}: " + ", ".join(f"{racers[i].name} win rate {np.mean(wins[i]):.2f}" for i in wins))
    logger.close()
    print("run directory:", run_dir)


def main(argv=None):
    args = parse_args(argv)
    device = torch.device("cuda" if args.cuda and torch.cuda.is_available() else "cpu")
    if args.torch_threads > 0:
        torch.set_num_threads(args.torch_threads)
    try:
        racers = build_racers(args, device)
    except CheckpointError as e:
        sys.exit(f"race.py: {e}")
    if args.train:
        train(args, racers, device)
    else:
        return evaluate(args, racers)


if __name__ == "__main__":
    main()
