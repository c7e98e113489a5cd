"""The peer a user would pick instead: Stable-Baselines3 PPO on the single-car race, at equal CPU time.

    python benchmarks/ppo_peer.py --seed 11 --cpu-hours 3.1                  # train (resumable), then evaluate
    python benchmarks/ppo_peer.py --seed 11 --cpu-hours 3.1 --evaluate-only  # only the evaluation of the saved model

PPO trains on ``dlc/SingleCarRacing-v0`` with rl-baselines3-zoo's CarRacing-v3 hyperparameters, untuned: frame
skip 2 (rewards summed), 64x64 grayscale, 2 stacked frames, 8 envs, rewards normalised (VecNormalize), a CNN policy
with gSDE, 512 steps per env per rollout, batch 128, 10 epochs, learning rate 1e-4 decaying linearly over
``--budget-steps``, GELU, log-std init -2. The env has the Dreamer runs' settings (``dreamer_lstm.Args``'
defaults at their final dead zone, -0.5). It gets the budget of one Dreamer run of the learning benchmark on one
torch thread, counted as this process's CPU time (``--cpu-hours`` over all sittings), so that other processes on
the same cores neither shorten nor lengthen it; and it is evaluated on the Dreamer runs' 20 fresh tracks
10100..10119 with its deterministic policy. Its row goes to ``benchmarks/results/ppo_peer.csv``, and
``learning_final.md`` beside it is rewritten with PPO over its seeds and each Dreamer variant minus PPO.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time

import gymnasium
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
RESULTS = os.path.join(ROOT, "benchmarks", "results")
RUNS = os.path.join(ROOT, "runs", "ppo_peer")
FRESH_TRACKS = (10_100, 20)
COLUMNS = (
    "variant", "seed", "updates", "env_steps", "cpu_hours", "final_return", "final_progress", "final_mean_abs_steer"
)
# rl-baselines3-zoo, hyperparams/ppo.yml, CarRacing-v3
ZOO = dict(
    n_envs=8, frame_skip=2, image_size=64, frame_stack=2, batch_size=128, n_steps=512, gamma=0.99, gae_lambda=0.95,
    n_epochs=10, ent_coef=0.0, sde_sample_freq=4, max_grad_norm=0.5, vf_coef=0.5, learning_rate=1e-4, use_sde=True,
    clip_range=0.2,
)  # fmt: skip

# SB3's PPO counts an epoch over a rollout as one update; each is this many minibatch gradient steps
PPO_MINIBATCHES = ZOO["n_steps"] * ZOO["n_envs"] // ZOO["batch_size"]


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

    kwargs = dreamer_lstm.env_kwargs(dreamer_lstm.Args(), dreamer_lstm.Args().dead_zone_end)
    kwargs.pop("num_agents")
    return kwargs


def make_env(seed: int | None = None) -> gymnasium.Env:
    """dlc/SingleCarRacing-v0 with the zoo's wrappers: frame skip, resize, grayscale."""
    import envs

    env = gymnasium.make(envs.SINGLE_CAR_ID, **env_kwargs())
    env = FrameSkip(env, ZOO["frame_skip"])
    env = gymnasium.wrappers.ResizeObservation(env, (ZOO["image_size"], ZOO["image_size"]))
    return gymnasium.wrappers.GrayscaleObservation(env, keep_dim=True)


def make_venv(seed: int):
    """The zoo's 8 envs, frame-stacked (before the reward normaliser, which is saved and loaded on its own)."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecFrameStack

    return VecFrameStack(make_vec_env(make_env, n_envs=ZOO["n_envs"], seed=seed), ZOO["frame_stack"])


def make_model(seed: int, venv, run_dir: str):
    """A new PPO model with the zoo's hyperparameters on `venv` (reward-normalised)."""
    from stable_baselines3 import PPO
    from torch import nn

    start_lr = ZOO["learning_rate"]
    return PPO(
        "CnnPolicy", venv, seed=seed, verbose=0, tensorboard_log=run_dir, device="cpu",
        learning_rate=lambda progress: start_lr * progress,  # the zoo's lin_1e-4 (progress: 1 -> 0 over the budget)
        **{k: ZOO[k] for k in ("batch_size", "n_steps", "gamma", "gae_lambda", "n_epochs", "ent_coef",
                               "sde_sample_freq", "max_grad_norm", "vf_coef", "use_sde", "clip_range")},
        policy_kwargs=dict(log_std_init=-2, ortho_init=False, activation_fn=nn.GELU, net_arch=dict(pi=[256], vf=[256])),
    )  # fmt: skip


def train(seed: int, hours: float, budget_steps: int, run_dir: str, save_every: int = 4) -> dict:
    """Train until the run has used `hours` of CPU time in all (time.process_time: every thread of this process, the
    envs included; or until `budget_steps` PPO steps), saving model, normaliser and
    record every `save_every` rollouts and at the end (atomic renames); a later sitting continues from them, with
    the learning rate still decaying over the whole budget. Returns the record: env steps, updates (SB3's
    ``_n_updates``, epochs over a rollout of PPO_MINIBATCHES gradient steps each) and CPU hours."""
    import json

    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import VecNormalize

    os.makedirs(run_dir, exist_ok=True)
    paths = {name: os.path.join(run_dir, name) for name in ("model.zip", "vecnormalize.pkl", "record.json")}
    record = {"env_steps": 0, "cpu_hours": 0.0, "updates": 0}
    if all(os.path.exists(path) for path in paths.values()):  # (the record is written last: a save is whole)
        with open(paths["record.json"]) as f:
            record = json.load(f)
        if "hours" in record:  # a record of the first version, which named the same CPU hours "hours"
            record["cpu_hours"] = record.pop("hours")
        norm = VecNormalize.load(paths["vecnormalize.pkl"], make_venv(seed))
        model = PPO.load(paths["model.zip"], env=norm, device="cpu", tensorboard_log=run_dir)
        print(
            f"continuing from {paths['model.zip']} at {record['env_steps']} env steps, {record['cpu_hours']:.2f} CPU-h"
        )
    else:
        norm = VecNormalize(make_venv(seed), norm_obs=False, norm_reward=True, gamma=ZOO["gamma"])
        model = make_model(seed, norm, run_dir)
    hours_before, started = record["cpu_hours"], time.process_time()
    hours = hours - hours_before  # the budget is the whole run's, over every sitting

    def save() -> None:
        record.update(
            env_steps=int(model.num_timesteps) * ZOO["frame_skip"], updates=int(model._n_updates),
            cpu_hours=round(hours_before + (time.process_time() - started) / 3600, 4),
        )  # fmt: skip
        model.save(paths["model.zip"] + ".tmp.zip")
        os.replace(paths["model.zip"] + ".tmp.zip", paths["model.zip"])
        norm.save(paths["vecnormalize.pkl"] + ".tmp")
        os.replace(paths["vecnormalize.pkl"] + ".tmp", paths["vecnormalize.pkl"])
        with open(paths["record.json"] + ".tmp", "w") as f:
            json.dump(record, f)
        os.replace(paths["record.json"] + ".tmp", paths["record.json"])
        steps = record["updates"] * PPO_MINIBATCHES
        print(f"{record['env_steps']} env steps, {record['updates']} epochs ({steps} gradient steps), "
              f"{record['cpu_hours']:.2f} CPU-h")  # fmt: skip

    class Budget(BaseCallback):
        """Stop at the sitting's CPU-time budget; save every `save_every` rollouts."""

        def _on_step(self) -> bool:
            return time.process_time() - started < 3600 * hours

        def _on_rollout_end(self) -> None:
            self.rollouts = getattr(self, "rollouts", 0) + 1
            if self.rollouts % save_every == 0:
                save()

    remaining = budget_steps - int(model.num_timesteps)
    if remaining > 0 and hours > 0:
        # learning rate 1e-4 * (1 - steps / budget) across sittings (SB3's progress_remaining)
        model.learn(remaining, callback=Budget(), reset_num_timesteps=False, tb_log_name="ppo")
    save()
    return record


def evaluate(model, first_track: int, tracks: int) -> dict:
    """The deterministic policy (PPO's own choice for evaluation; gSDE's noise is exploration) alone on tracks
    first_track .. first_track + tracks - 1, the frame stack starting from zeros as VecFrameStack's does: mean return
    (the raw env reward), progress and |steer| of its decisions."""
    from collections import deque

    returns, progress, steer = [], [], []
    for seed in range(first_track, first_track + tracks):
        env = make_env()
        obs, _ = env.reset(seed=seed)
        frames = deque([np.zeros_like(obs)] * (ZOO["frame_stack"] - 1) + [obs], maxlen=ZOO["frame_stack"])
        total, done, info, steers = 0.0, False, {}, []
        while not done:
            action, _ = model.predict(np.concatenate(frames, axis=-1)[None], deterministic=True)
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


def write_row(row: dict, path: str = os.path.join(RESULTS, "ppo_peer.csv")) -> None:
    """Add `row`, replacing an earlier row of the same seed."""
    rows = []
    if os.path.exists(path):
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if int(r["seed"]) != row["seed"]]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(sorted([*rows, row], key=lambda r: int(r["seed"])))


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument(
        "--cpu-hours", type=float, default=3.1,
        help="CPU-time budget of the whole run (all sittings): one Dreamer run of the learning benchmark",
    )  # fmt: skip
    parser.add_argument("--budget-steps", type=int, default=4_000_000, help="PPO steps the learning rate decays over")
    parser.add_argument("--torch-threads", type=int, default=1)
    parser.add_argument("--tracks", type=int, default=FRESH_TRACKS[1], help="evaluation tracks from 10100")
    parser.add_argument("--evaluate-only", action="store_true", help="only evaluate the saved model")
    parser.add_argument("--runs-dir", default=RUNS)
    parser.add_argument("--results", default=os.path.join(RESULTS, "ppo_peer.csv"))
    args = parser.parse_args(argv)
    if args.cpu_hours <= 0 or args.budget_steps < 1 or args.tracks < 1 or args.torch_threads < 1:
        parser.error("--cpu-hours must be > 0 and --budget-steps, --tracks, --torch-threads >= 1")
    import torch
    from stable_baselines3 import PPO

    torch.set_num_threads(args.torch_threads)
    run_dir = os.path.join(args.runs_dir, f"ppo__{args.seed}")
    if args.evaluate_only:
        import json

        with open(os.path.join(run_dir, "record.json")) as f:
            record = json.load(f)
    else:
        record = train(args.seed, args.cpu_hours, args.budget_steps, run_dir)
    model = PPO.load(os.path.join(run_dir, "model.zip"), device="cpu")
    result = evaluate(model, FRESH_TRACKS[0], args.tracks)
    row = {
        "variant": "ppo", "seed": args.seed, "updates": record["updates"], "env_steps": record["env_steps"],
        "cpu_hours": record["cpu_hours"], "final_return": round(result["return"], 2),
        "final_progress": round(result["progress"], 4), "final_mean_abs_steer": round(result["abs_steer"], 4),
    }  # fmt: skip
    write_row(row, args.results)
    print(row)
    results_dir = os.path.dirname(os.path.abspath(args.results))
    if os.path.exists(os.path.join(results_dir, "learning_final.csv")):  # the Dreamer runs' final protocol is in
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        import learning

        print(learning.write_final_report(results_dir, peer_path=args.results))  # with PPO and the differences
    return row


if __name__ == "__main__":
    main()
