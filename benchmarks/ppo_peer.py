"""The peers a user would pick instead: Stable-Baselines3 PPO, or sb3-contrib's RecurrentPPO (an LSTM policy), on
the single-car race, at equal CPU time.

    python benchmarks/ppo_peer.py --seed 11 --cpu-hours 3.1                  # train PPO (resumable), then evaluate
    python benchmarks/ppo_peer.py --seed 11 --cpu-hours 3.1 --evaluate-only  # only the evaluation of the saved model
    python benchmarks/ppo_peer.py --seed 11 --curve                          # evaluate its snapshots
    python benchmarks/ppo_peer.py --algo recurrent-ppo --seed 11 --cpu-hours 3.1   # the same with the LSTM policy
    python benchmarks/ppo_peer.py --seed 11 --evaluate-only --first-track 10100 --tracks 20   # the 8,000-update
                                                                                  # protocol's tracks

PPO (``--algo ppo``) trains on ``dlc/SingleCarRacing-v0`` with rl-baselines3-zoo's CarRacing-v3 hyperparameters
(hyperparams/ppo.yml), untuned: frame skip 2 (rewards summed), 64x64 grayscale, 2 stacked frames, 8 envs, rewards
normalised (VecNormalize), a CNN policy with gSDE, 512 steps per env per rollout, batch 128, 10 epochs, learning
rate 1e-4 decaying linearly over ``--budget-steps``, GELU, log-std init -2. RecurrentPPO (``--algo recurrent-ppo``)
has the zoo's CarRacing-v0 entry of hyperparams/ppo_lstm.yml, untuned: the same wrappers and 8 envs, rewards not
normalised (the entry's ``normalize`` is commented out), ``CnnLstmPolicy`` (an LSTM of 128 for the actor, a linear
layer for the critic), gSDE, 512 steps, batch 128, 20 epochs, gae_lambda 0.9, clip range 0.4, a constant learning
rate 3e-5, GELU (inert: that policy has no hidden layer), log-std init -2. The env has the Dreamer runs' settings
(``dreamer_lstm.Args``' defaults at their final dead zone, -0.5). Each gets the final protocol's budget per Dreamer
run (common.PROTOCOL_CPU_HOURS, 3.1) on one torch thread, counted as this process's CPU time
(``--cpu-hours`` over all sittings), so that other processes on the same cores neither shorten nor lengthen it.
While it trains, the weights in force at env step N = 50k, 100k, 250k, 500k, 1M (the policy that takes the N-th
env step; sample efficiency) and their VecNormalize statistics are kept as ``model_<N>.zip`` and
``vecnormalize_<N>.pkl``; ``--curve`` evaluates every snapshot on the given tracks and writes a row per snapshot (its
N, the env steps its weights were trained on, at most N, its tracks) to ``benchmarks/results/<variant>_peer_curve.csv``.
A later sitting continues a run with new seeds (``sitting_seed``): it races other tracks than the sittings before.

A model is evaluated with its deterministic policy (an LSTM's state carried from step to step and reset at each
race's start) on tracks ``--first-track`` .. + ``--tracks`` - 1: by default the final protocol's 30 report tracks
10300..10329 (final_protocol.py), which choose nothing; the 8,000-update protocol's were 10100..10119. The row goes to
``benchmarks/results/ppo_peer.csv`` (``recurrent_ppo_peer.csv``) with its ``tracks`` (``10300..10329``): one row
per seed and tracks, so a seed's rows on the fresh and the report tracks stand side by side (read_rows, write_rows).
A row of a file written before that column was measured on the old default tracks and is read as 10100..10119
(UNNAMED_TRACKS). The final protocol's report takes the peers' rows of the report tracks with ``learning.py
--protocol-report``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import json
import os
import sys
import time
from typing import Literal

import gymnasium
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402  (the blocks of tracks, the results' CSV rows)
from common import track_block  # noqa: E402

RESULTS = common.RESULTS
RUNS = os.path.join(ROOT, "runs", "ppo_peer")
FRESH_TRACKS = common.TRACKS["fresh"]  # the 8,000-update protocol's tracks
FINAL_TRACKS = common.TRACKS["report"]  # the CPU-budget protocol's tracks (final_protocol.py): the default
SNAPSHOT_STEPS = (50_000, 100_000, 250_000, 500_000, 1_000_000)  # env steps (frame skip included)
COLUMNS = (
    "variant", "seed", "updates", "env_steps", "cpu_hours", "final_return", "final_progress", "final_mean_abs_steer",
    "tracks",
)  # fmt: skip
# a snapshot's row: its N (model_<N>.zip), the env steps its weights were trained on, its deterministic policy on
# `tracks`
CURVE_COLUMNS = ("variant", "seed", "snapshot", "env_steps", "return", "progress", "mean_abs_steer", "tracks")
# rl-baselines3-zoo, hyperparams/ppo.yml, CarRacing-v3
ZOO = dict(
    n_envs=8, frame_skip=2, image_size=64, frame_stack=2, normalize=True, n_timesteps=4_000_000, policy="CnnPolicy",
    batch_size=128, n_steps=512, gamma=0.99, gae_lambda=0.95, n_epochs=10, ent_coef=0.0, sde_sample_freq=4,
    max_grad_norm=0.5, vf_coef=0.5, learning_rate=1e-4, lr_schedule="linear", use_sde=True, clip_range=0.2,
    policy_kwargs=dict(log_std_init=-2, ortho_init=False, activation_fn="GELU", net_arch=dict(pi=[256], vf=[256])),
)  # fmt: skip
# rl-baselines3-zoo, hyperparams/ppo_lstm.yml, CarRacing-v0 (a constant learning rate; "# normalize: True" is
# commented out). Later versions of the file renamed it CarRacing-v2 and gave it PPO's values instead: no frame skip,
# rewards normalised, 4e6 steps, gae_lambda 0.95, 10 epochs, lin_1e-4, clip range 0.2.
ZOO_LSTM = dict(
    n_envs=8, frame_skip=2, image_size=64, frame_stack=2, normalize=False, n_timesteps=2_000_000,
    policy="CnnLstmPolicy", batch_size=128, n_steps=512, gamma=0.99, gae_lambda=0.9, n_epochs=20, ent_coef=0.0,
    sde_sample_freq=4, max_grad_norm=0.5, vf_coef=0.5, learning_rate=3e-5, lr_schedule="constant", use_sde=True,
    clip_range=0.4,
    policy_kwargs=dict(log_std_init=-2, ortho_init=False, enable_critic_lstm=False, activation_fn="GELU",
                       lstm_hidden_size=128),
)  # fmt: skip
ALGOS = {  # --algo (Args.algo): (variant: the rows' name, the run directory's prefix, the csv's; hyperparameters)
    "ppo": ("ppo", ZOO),
    "recurrent-ppo": ("recurrent_ppo", ZOO_LSTM),
}
# the hyperparameters given to the algorithm's constructor as they are
ALGO_KEYS = ("batch_size", "n_steps", "gamma", "gae_lambda", "n_epochs", "ent_coef", "sde_sample_freq",
             "max_grad_norm", "vf_coef", "use_sde", "clip_range")  # fmt: skip


class FrameSkip(gymnasium.Wrapper):
    """Repeat each action `skip` env steps and sum the rewards (rl-zoo's FrameSkip); stops at the episode's end."""

    def __init__(self, env: gymnasium.Env, skip: int):
        super().__init__(env)
        self.skip = skip

    def step(self, action):
        total = 0.0
        for _ in range(self.skip):
            obs, reward, terminated, truncated, info = self.env.step(action)
            total += float(reward)
            if terminated or truncated:
                break
        return obs, total, terminated, truncated, info


def env_kwargs() -> dict:
    """The single-car env with the settings the Dreamer runs are evaluated with (final dead zone)."""
    import dreamer_lstm
    import utils.run

    kwargs = utils.run.env_kwargs(dreamer_lstm.Args(), dreamer_lstm.Args().dead_zone_end)
    kwargs.pop("num_agents")
    return kwargs


def make_env() -> gymnasium.Env:
    """dlc/SingleCarRacing-v0 with the zoo's wrappers: frame skip, resize, grayscale (the same for both algorithms)."""
    import envs

    env = gymnasium.make(envs.SINGLE_CAR_ID, **env_kwargs())
    env = FrameSkip(env, ZOO["frame_skip"])
    env = gymnasium.wrappers.ResizeObservation(env, (ZOO["image_size"], ZOO["image_size"]))
    return gymnasium.wrappers.GrayscaleObservation(env, keep_dim=True)


def make_venv(seed: int, n_envs: int | None = None):
    """The zoo's 8 envs, frame-stacked (before the reward normaliser, which is saved and loaded on its own)."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecFrameStack

    return VecFrameStack(make_vec_env(make_env, n_envs=n_envs or ZOO["n_envs"], seed=seed), ZOO["frame_stack"])


def algo_class(algo: str):
    """SB3's PPO or sb3-contrib's RecurrentPPO."""
    if algo == "recurrent-ppo":
        from sb3_contrib import RecurrentPPO

        return RecurrentPPO
    from stable_baselines3 import PPO

    return PPO


def make_model(seed: int, venv, run_dir: str, algo: str = "ppo"):
    """A new model of `algo` with the zoo's hyperparameters on `venv` (the VecNormalize)."""
    from torch import nn

    config = ALGOS[algo][1]
    start_lr = config["learning_rate"]
    # the zoo's lin_1e-4 (SB3's progress: 1 -> 0 over the budget), or a constant
    learning_rate = (lambda progress: start_lr * progress) if config["lr_schedule"] == "linear" else start_lr
    policy_kwargs = {**config["policy_kwargs"], "activation_fn": getattr(nn, config["policy_kwargs"]["activation_fn"])}
    return algo_class(algo)(
        config["policy"], venv, seed=seed, verbose=0, tensorboard_log=run_dir, device="cpu",
        learning_rate=learning_rate, policy_kwargs=policy_kwargs, **{k: config[k] for k in ALGO_KEYS},
    )  # fmt: skip


def atomic_save(save, path: str) -> None:
    """save(tmp), then rename it to `path` (a reader sees the old file or the new one, whole); tmp keeps the
    extension (SB3 adds .zip to a name without one)."""
    root, ext = os.path.splitext(path)
    save(root + ".tmp" + ext)
    os.replace(root + ".tmp" + ext, path)


def sitting_seed(seed: int, env_steps: int) -> int:
    """The seed of a sitting that continues run `seed` at `env_steps`. Loading a model reseeds it with the run's seed
    (SB3's set_random_seed: python, numpy, torch, the action space and the envs' next reset), so without a seed of its
    own every later sitting would race the first sitting's tracks again, with the same noise."""
    return int(np.random.SeedSequence([seed, env_steps]).generate_state(1)[0] % 2**31)


def snapshot_paths(run_dir: str) -> list[tuple[int, str]]:
    """The run's snapshots (threshold, model_<threshold>.zip), by threshold."""
    found = glob.glob(os.path.join(run_dir, "model_*.zip"))
    snapshots = [(os.path.basename(p)[len("model_") : -len(".zip")], p) for p in found]
    return sorted((int(n), p) for n, p in snapshots if n.isdigit())


def read_record(run_dir: str) -> dict:
    """A peer run's record.json (env_steps, cpu_hours, updates); a record of the first version named the same CPU
    hours "hours"."""
    with open(os.path.join(run_dir, "record.json")) as f:
        record = json.load(f)
    if "hours" in record:
        record["cpu_hours"] = record.pop("hours")
    return record


def train(
    seed: int, hours: float, budget_steps: int, run_dir: str, save_every: int = 4, algo: str = "ppo",
    snapshots: tuple[int, ...] = SNAPSHOT_STEPS,
) -> dict:  # fmt: skip
    """Train `algo` until the run has used `hours` of CPU time in all (time.process_time: every thread of this
    process, the envs included; or until `budget_steps` PPO steps), saving model, normaliser and record every
    `save_every` rollouts and at the end (atomic renames); a later sitting continues from them with its own seeds
    (sitting_seed), PPO's learning rate still decaying over the whole budget. When the env steps (PPO steps x frame
    skip) reach a threshold of `snapshots`, the weights that took that step (they change only between rollouts) and
    the normaliser are kept as model_<threshold>.zip and vecnormalize_<threshold>.pkl (the zip written last). A
    snapshot is written once over every sitting; a resumed run deletes those past its saved steps (a killed sitting's
    lost stretch) and takes them again. A save comes at a rollout's end, before SB3 trains on that rollout, so a
    resumed sitting starts from weights that never train on it (its env steps and CPU time stay counted: one rollout,
    8,192 env steps, per sitting, against the ~4.8M of a PPO protocol run and ~1.3M of a RecurrentPPO one). Returns
    the record: env steps, updates (SB3's ``_n_updates``, epochs over a rollout of n_steps * n_envs / batch_size
    gradient steps each) and CPU hours."""
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import VecNormalize

    variant, config = ALGOS[algo]
    os.makedirs(run_dir, exist_ok=True)
    paths = {name: os.path.join(run_dir, name) for name in ("model.zip", "vecnormalize.pkl", "record.json")}
    record = {"env_steps": 0, "cpu_hours": 0.0, "updates": 0}
    venv = make_venv(seed, config["n_envs"])
    if all(os.path.exists(path) for path in paths.values()):  # (a kill between a save's renames: a newer model)
        record = read_record(run_dir)
        norm = VecNormalize.load(paths["vecnormalize.pkl"], venv)
        model = algo_class(algo).load(paths["model.zip"], env=norm, device="cpu", tensorboard_log=run_dir)
        model.set_random_seed(sitting_seed(seed, record["env_steps"]))  # (load reseeded it with `seed`)
        print(
            f"continuing from {paths['model.zip']} at {record['env_steps']} env steps, {record['cpu_hours']:.2f} CPU-h"
        )
    else:
        norm = VecNormalize(venv, norm_obs=False, norm_reward=config["normalize"], gamma=config["gamma"])
        model = make_model(seed, norm, run_dir, algo)
    hours_before, started = record["cpu_hours"], time.process_time()
    hours = hours - hours_before  # the budget is the whole run's, over every sitting

    def save() -> None:
        record.update(
            env_steps=int(model.num_timesteps) * config["frame_skip"], updates=int(model._n_updates),
            cpu_hours=round(hours_before + (time.process_time() - started) / 3600, 4),
        )  # fmt: skip
        atomic_save(model.save, paths["model.zip"])
        atomic_save(norm.save, paths["vecnormalize.pkl"])
        common.write_json(paths["record.json"], record)
        steps = record["updates"] * config["n_steps"] * config["n_envs"] // config["batch_size"]
        print(f"{record['env_steps']} env steps, {record['updates']} epochs ({steps} gradient steps), "
              f"{record['cpu_hours']:.2f} CPU-h")  # fmt: skip

    taken = int(model.num_timesteps) * config["frame_skip"]  # by the weights this sitting starts from
    for threshold, path in snapshot_paths(run_dir):  # kept after those weights by a sitting that was killed
        if threshold > taken:
            os.remove(path)
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(run_dir, f"vecnormalize_{threshold}.pkl"))
    kept = {threshold for threshold, _ in snapshot_paths(run_dir)}
    pending = sorted(n for n in set(snapshots) if n > taken and n not in kept)

    def snapshot() -> None:
        """Keep the weights that took the env step of every threshold passed since the last call."""
        env_steps = int(model.num_timesteps) * config["frame_skip"]
        while pending and pending[0] <= env_steps:
            path = os.path.join(run_dir, f"model_{pending[0]}.zip")
            atomic_save(norm.save, os.path.join(run_dir, f"vecnormalize_{pending.pop(0)}.pkl"))
            atomic_save(model.save, path)
            print(f"snapshot {path} at {env_steps} env steps")

    class Budget(BaseCallback):
        """Keep snapshots; stop at the sitting's CPU-time budget; save every `save_every` rollouts."""

        def _on_step(self) -> bool:  # (after each step of the n_envs envs)
            snapshot()
            return time.process_time() - started < 3600 * hours

        def _on_rollout_end(self) -> None:
            self.rollouts = getattr(self, "rollouts", 0) + 1
            if self.rollouts % save_every == 0:
                save()

    remaining = budget_steps - int(model.num_timesteps)
    if remaining > 0 and hours > 0:
        # PPO's learning rate 1e-4 * (1 - steps / budget) across sittings (SB3's progress_remaining)
        model.learn(remaining, callback=Budget(), reset_num_timesteps=False, tb_log_name=variant)
    save()
    return record


def evaluate(model, first_track: int, tracks: int) -> dict:
    """The deterministic policy (PPO's own choice for evaluation; gSDE's noise is exploration) alone on tracks
    first_track .. first_track + tracks - 1, the frame stack starting from zeros as VecFrameStack's does and a
    recurrent policy's state carried from step to step, from zeros with episode_start True at each race's first
    step (PPO ignores both): mean return (the raw env reward), progress and |steer| of its decisions."""
    from collections import deque

    returns, progress, steer = [], [], []
    for seed in range(first_track, first_track + tracks):
        env = make_env()
        obs, _ = env.reset(seed=seed)
        frames = deque([np.zeros_like(obs)] * (ZOO["frame_stack"] - 1) + [obs], maxlen=ZOO["frame_stack"])
        total, done, info, steers, state, start = 0.0, False, {}, [], None, True
        while not done:
            action, state = model.predict(
                np.concatenate(frames, axis=-1)[None], state=state, episode_start=np.array([start]), deterministic=True
            )
            start = False
            obs, reward, terminated, truncated, info = env.step(action[0])
            frames.append(obs)
            total += reward
            steers.append(abs(float(np.clip(action[0][0], -1, 1))))
            done = terminated or truncated
        env.close()
        returns.append(total)
        progress.append(float(info.get("progress", 0.0)))
        steer.append(float(np.mean(steers)))
    return {"return": float(np.mean(returns)), "progress": float(np.mean(progress)), "abs_steer": float(np.mean(steer))}


UNNAMED_TRACKS = track_block(*FRESH_TRACKS)  # the tracks of a row without a ``tracks`` (the default before it)


def read_rows(path: str) -> list[dict]:
    """The rows of a peer's CSV (rows or curve; none while it does not exist), each with its ``tracks``: a row
    without one (a file written before the column, or an empty cell) was measured on the default tracks of the
    time, 10100..10119, and is read as such (UNNAMED_TRACKS)."""
    return common.read_table(path, defaults={"tracks": UNNAMED_TRACKS})


def write_rows(rows: list[dict], path: str, columns: tuple[str, ...]) -> None:
    """Add `rows`, replacing the earlier rows of the same seed and tracks only (rows of the seed on other tracks
    stay; an old row's tracks are named as read_rows names them); sorted by seed, tracks (and env steps). Locked
    and replaced atomically (common.replace_rows): two seeds' measurements may finish side by side."""
    common.replace_rows(
        path, rows, columns, key=lambda r: (int(r["seed"]), r["tracks"]),
        order=lambda r: (int(r["seed"]), r["tracks"], int(r.get("env_steps") or 0)),
        defaults={"tracks": UNNAMED_TRACKS},
    )  # fmt: skip


def results_path(variant: str, results_dir: str = RESULTS, curve: bool = False) -> str:
    """Where a peer's rows are kept: ``<results_dir>/<variant>_peer.csv`` (one row per seed and tracks), or with
    `curve` its snapshots' ``<variant>_peer_curve.csv``."""
    return os.path.join(results_dir, f"{variant}_peer{'_curve' * curve}.csv")


def write_row(row: dict, path: str = results_path("ppo")) -> None:
    """Add `row`, replacing an earlier row of the same seed and tracks."""
    write_rows([row], path, COLUMNS)


def curve(algo: str, seed: int, run_dir: str, first_track: int, tracks: int, path: str) -> list[dict]:
    """Evaluate every snapshot of the run (model_<threshold>.zip) on the same tracks and write one row per snapshot
    to `path` (replacing the seed's earlier rows on those tracks): snapshot is its threshold, env_steps the steps
    its weights were trained on (whole rollouts: a sitting's unfinished one is never trained on; each train() makes
    n_epochs updates, as no target_kl stops one early)."""
    variant, config = ALGOS[algo]
    rollout_env_steps = config["n_steps"] * config["n_envs"] * config["frame_skip"]
    rows = []
    for threshold, snapshot in snapshot_paths(run_dir):
        model = algo_class(algo).load(snapshot, device="cpu")
        result = evaluate(model, first_track, tracks)
        rows.append({
            "variant": variant, "seed": seed, "snapshot": threshold,
            "env_steps": model._n_updates // config["n_epochs"] * rollout_env_steps,
            "return": round(result["return"], 2),
            "progress": round(result["progress"], 4), "mean_abs_steer": round(result["abs_steer"], 4),
            "tracks": track_block(first_track, tracks),
        })  # fmt: skip
        print(rows[-1])
    if not rows:
        raise SystemExit(f"no snapshots (model_<steps>.zip) in {run_dir}")
    write_rows(rows, path, CURVE_COLUMNS)
    return rows


@dataclasses.dataclass
class Args:
    algo: Literal["ppo", "recurrent-ppo"] = "ppo"
    """SB3's PPO or sb3-contrib's RecurrentPPO, each with rl-baselines3-zoo's CarRacing hyperparameters"""
    seed: int = 11
    """the run's seed (its directory: <runs-dir>/<variant>__<seed>)"""
    cpu_hours: float = common.PROTOCOL_CPU_HOURS
    """CPU-time budget of the whole run (all sittings): the final protocol's per Dreamer run"""
    budget_steps: int | None = None
    """PPO steps the run takes at most and PPO's learning rate decays over (default: the zoo's n_timesteps)"""
    torch_threads: int = 1
    """torch threads of the run (and of its evaluation)"""
    first_track: int = FINAL_TRACKS[0]
    """first evaluation track"""
    tracks: int = FINAL_TRACKS[1]
    """evaluation tracks from --first-track"""
    snapshot_steps: tuple[int, ...] = SNAPSHOT_STEPS
    """env steps at which the model is kept as model_<steps>.zip"""
    evaluate_only: bool = False
    """only evaluate the saved model"""
    curve: bool = False
    """only evaluate every snapshot: <variant>_peer_curve.csv"""
    runs_dir: str = RUNS
    """where the runs' directories are"""
    results: str | None = None
    """the row's csv (default benchmarks/results/<variant>_peer.csv); the curve's csv is <variant>_peer_curve.csv
    beside it"""


def main(argv=None) -> dict | list[dict]:
    from utils.run import tyro_cli, usage_error

    args = tyro_cli(Args, argv, __doc__)

    def error(message: str) -> None:
        usage_error("ppo_peer.py", message)

    if args.evaluate_only and args.curve:
        error("--evaluate-only and --curve are two modes: give one")
    variant, config = ALGOS[args.algo]
    budget_steps = config["n_timesteps"] if args.budget_steps is None else args.budget_steps
    if not args.cpu_hours > 0:
        error(f"--cpu-hours must be > 0, got {args.cpu_hours}")
    for flag, value in (("--budget-steps", budget_steps), ("--tracks", args.tracks), ("--torch-threads",
                        args.torch_threads), ("--snapshot-steps", min(args.snapshot_steps, default=1))):  # fmt: skip
        if value < 1:
            error(f"{flag} must be >= 1, got {value}")
    import torch

    torch.set_num_threads(args.torch_threads)
    results = args.results or results_path(variant)
    run_dir = os.path.join(args.runs_dir, f"{variant}__{args.seed}")
    if args.curve:
        curve_path = results_path(variant, os.path.dirname(os.path.abspath(results)), curve=True)
        return curve(args.algo, args.seed, run_dir, args.first_track, args.tracks, curve_path)
    if args.evaluate_only:
        record = read_record(run_dir)
    else:
        snapshots = tuple(args.snapshot_steps)
        record = train(args.seed, args.cpu_hours, budget_steps, run_dir, algo=args.algo, snapshots=snapshots)
    model = algo_class(args.algo).load(os.path.join(run_dir, "model.zip"), device="cpu")
    result = evaluate(model, args.first_track, args.tracks)
    row = {
        "variant": variant, "seed": args.seed, "updates": record["updates"], "env_steps": record["env_steps"],
        "cpu_hours": record["cpu_hours"], "final_return": round(result["return"], 2),
        "final_progress": round(result["progress"], 4), "final_mean_abs_steer": round(result["abs_steer"], 4),
        "tracks": track_block(args.first_track, args.tracks),
    }  # fmt: skip
    write_row(row, results)
    print(row)
    results_dir = os.path.dirname(os.path.abspath(results))
    if (args.first_track, args.tracks) == FINAL_TRACKS:
        print(f"python benchmarks/learning.py --protocol-report --results-dir {results_dir}  # the report with it")
    return row


if __name__ == "__main__":
    main()
