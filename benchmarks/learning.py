"""Does the agent learn to drive, and does it keep driving? CPU-sized single-car runs, evaluated on held-out tracks.

    python benchmarks/learning.py --variant lstm --seed 11                 # a run of the final protocol (8,000 updates)
    python benchmarks/learning.py --variant lstm --seed 11 --resume        # continue it in a later sitting
    python benchmarks/learning.py --variant lstm --seed 11 --final         # its row of learning_final.csv
    python benchmarks/learning.py --report                                 # curves + table only
    python benchmarks/learning.py --variant lstm --seed 11 --diagnose      # sigma, entropy, kl_dyn... per 500 updates
    python benchmarks/learning.py --runs-dir runs/experiment/trials --variant gru --seed 12 --final
    python benchmarks/learning.py --final-report                           # learning_final.md from the CSVs
    python benchmarks/learning.py --evaluate runs/learning/<run>/checkpoints/latest.pt --first-track 10100 --tracks 20
    python benchmarks/learning.py --calibrate runs/learning/<run>/checkpoints/latest.pt   # optimistic critic/model?
    python benchmarks/learning.py --variant lstm --seed 11 --return-norm --screen 3100 \\
        --reference-runs-dir runs/experiment/trials                   # an ablation against the default run
    python benchmarks/learning.py --runs-dir runs/experiment/trials --policy-rule   # sampled or mean action?
    python benchmarks/learning.py --export runs/learning/<run>/checkpoints/latest.pt pretrained/lstm_cpu.pt

Trains `dreamer_<variant>.py --preset cpu` on the single-car race (stage ``single``, one torch thread, so two runs
share two cores) until ``--updates`` updates or ``--hours`` of wall time (resumable: a run may span sittings),
evaluating every 5 races on the 10 held-out tracks (seeds 10000..10009) and keeping each evaluated policy
(``checkpoints/eval_<race>.pt``). It writes, under ``benchmarks/results/``:

* ``learning_<variant>_seed<S>.csv``: evaluation return and progress against env steps, updates and hours;
* ``baselines.json``: random actions and the pure-pursuit driver on the same 10 tracks;
* ``baselines_fresh.json`` (with ``--final``): the same on the 20 fresh tracks 10100..10119;
* ``learning.png`` and ``learning.md``: every curve, with the baselines;
* with ``--screen``: rows of ``screening/screens.csv``, an ablation and the default run at the same update count;
* with ``--policy-rule``: ``policy_rule.csv`` and ``.md``, the final policies sampled and with their mean action on
  the screening tracks, and the evaluation policy the rule of docs/learning.md picks from them;
* with ``--calibrate``: a row of ``calibration.csv``, the agent's value and imagined return of real states against
  what the real episodes returned from them;
* with ``--final``: the run's row of ``learning_final.csv`` (its final and best policies on the 20 fresh tracks
  10100..10119) and, in ``learning_final.md``, the IQM and mean over seeds with stratified-bootstrap intervals
  (rliable, descriptive), the parts of the bar each variant fails, and the LSTM minus the GRU and each variant
  minus the SB3 PPO peer (``ppo_peer.csv``), judged by the exact permutation test and Welch's t interval
  (benchmarks/stats.py); ``--final-report`` rewrites ``learning_final.md`` alone.

The bar, per variant over 3 seeds: final-policy mean return >= 600 with every seed >= 350, mean progress >= 0.65,
mean |steer| <= 0.3, and each run's last three evaluations within 150 of its best (docs/learning.md).

``benchmarks/experiment.py`` trains these same runs as its single stage (under ``<storage>/trials/``);
``--runs-dir`` points every mode at them.
"""

from __future__ import annotations

import argparse
import csv
import glob
import importlib
import json
import os
import re
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

RESULTS = os.path.join(ROOT, "benchmarks", "results")
RUNS = os.path.join(ROOT, "runs", "learning")
# The bar of the final protocol, per variant over its seeds: final-policy mean return and progress (the figure draws
# them), every seed's return, the mean |steer|; and each run holds: its last three evaluations average within
# BAR_HOLD of its best.
BAR_RETURN, BAR_PROGRESS, BAR_SEED_RETURN, BAR_STEER, BAR_HOLD = 600.0, 0.65, 350.0, 0.3, 150.0
VARIANTS = ("lstm", "gru")
FINAL_UPDATES = 8000  # the final protocol: every run trains for this many updates
FRESH_TRACKS = (10_100, 20)  # first seed and count of the fresh tracks the final policy is measured on
# What the benchmark adds to the scripts' CPU preset (--preset cpu): one car; decisions evaluated on the 10 held-out
# tracks every 5 races, each evaluated policy kept; the run ends at --updates; one thread, two runs on two cores.
LEARNING_CONFIG = {
    "stage": "single",
    "num_agents": 1,
    "eval_episodes": 10,
    "eval_checkpoints": True,
    "total_episodes": 1_000_000,  # --updates (or the time limit) ends the run
    "torch_threads": 1,
}


# Ablations: a flag of the dreamer scripts changed from the preset, and its tag in the run's name.
ABLATION_TAGS = {
    "entropy_coef": "alpha", "decoder_min_log_sigma": "logsigmamin", "norm": "norm", "return_norm": "retnorm",
    "dead_zone_start": "dzstart", "reward_nll_beta": "rbeta",
}  # fmt: skip


def experiment_name(variant: str, **ablation: float | str | bool | None) -> str:
    """``learning_<variant>``, plus ``_<tag><value>`` per ablated flag (e.g. ``learning_lstm_alpha0.03``)."""
    unknown = set(ablation) - set(ABLATION_TAGS)
    if unknown:
        raise ValueError(f"not an ablation flag: {', '.join(sorted(unknown))} (known: {', '.join(ABLATION_TAGS)})")
    tags = [
        f"_{tag}" if value is True else f"_{tag}{value:g}" if isinstance(value, float) else f"_{tag}{value}"
        for name, tag in ABLATION_TAGS.items()
        if (value := ablation.get(name)) is not None
    ]
    return f"learning_{variant}" + "".join(tags)


def learning_runs(runs_dir: str = RUNS, exp_name: str = "learning_*", seed: int | str = "*") -> list[str]:
    """Run directories of the learning benchmark under ``runs_dir``, at any depth (benchmarks/experiment.py keeps
    its single-stage runs, which are these runs, one directory per trial), oldest first."""
    pattern = os.path.join(runs_dir, "**", f"*__{exp_name}__{seed}__*")
    runs = [path for path in glob.glob(pattern, recursive=True) if os.path.isdir(path)]
    return sorted(runs, key=lambda run: (os.path.basename(run).split("__")[-1], run))


def find_run(exp_name: str, seed: int, runs_dir: str = RUNS) -> str | None:
    runs = learning_runs(runs_dir, exp_name, seed)
    return runs[-1] if runs else None


def run_args(
    variant: str, seed: int, hours: float, resume: bool, updates: int = FINAL_UPDATES, runs_dir: str = RUNS, **ablation
):
    """The dreamer script of ``variant``, the Args of this sitting and the fields they override: a new run at the
    CPU preset plus LEARNING_CONFIG with the ablated flags changed, or (``resume``) the latest run of the same name
    and seed, continued with its own settings (only the time limit and the update target are this sitting's)."""
    script = importlib.import_module(f"dreamer_{variant}")
    exp_name = experiment_name(variant, **ablation)
    existing = find_run(exp_name, seed, runs_dir)
    if resume and existing:
        args = script.Args(resume=existing, time_limit_hours=hours, total_updates=updates)
        return script, args, {"time_limit_hours", "total_updates"}
    if existing and not resume:
        print(f"note: {existing} exists; starting a new run (use --resume to continue it)")
    ablated = {name: value for name, value in ablation.items() if value is not None}
    args = script.preset_args(
        "cpu", seed=seed, exp_name=exp_name, runs_dir=runs_dir, time_limit_hours=hours, total_updates=updates,
        **LEARNING_CONFIG, **ablated,
    )  # fmt: skip
    return script, args, set()


EVENT_FILE_PROCESS = re.compile(r"events\.out\.tfevents\.\d+\.(?P<process>.+\.\d+)\.\d+")
"""The name SB3's TensorBoard logger gives an event file, ``events.out.tfevents.<time>.<host>.<pid>.<n>`` (no
suffix): host (which may hold dots) and pid name the process that wrote it."""


def sittings(run_dir: str) -> list[tuple[list, float, float]]:
    """Each sitting of a run with anything logged, in the order they ran: its event files as (event accumulator,
    scalar tags), and its first and last logged wall time.

    A sitting is one process. Each call of a script's ``main`` opens a new event file, and an experiment trial
    calls it again every few hundred updates in the same process, so consecutive files of one host and pid are
    one sitting and the time between them counts; the time between processes does not."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, last_process = [], None
    for events_file in sorted(glob.glob(os.path.join(run_dir, "events.out.tfevents.*"))):
        acc = EventAccumulator(events_file, size_guidance={"scalars": 0})
        acc.Reload()
        tags = acc.Tags()["scalars"]
        if not tags:
            continue
        wall_times = [e.wall_time for tag in tags for e in acc.Scalars(tag)]
        match = EVENT_FILE_PROCESS.fullmatch(os.path.basename(events_file))
        process = match["process"] if match else events_file
        if out and process == last_process:
            files, start, end = out[-1]
            out[-1] = (files + [(acc, tags)], min(start, min(wall_times)), max(end, max(wall_times)))
        else:
            out.append(([(acc, tags)], min(wall_times), max(wall_times)))
        last_process = process
    return out


def training_hours(run_dir: str) -> float:
    """A run's training time in hours up to its last logged scalar: each sitting from its first logged scalar to its
    last, added up (the time between sittings does not count), as ``eval_curve``'s hours."""
    return round(sum(end - start for _, start, end in sittings(run_dir)) / 3600, 4)


def eval_curve(run_dir: str) -> list[dict]:
    """Evaluation points of a run, with the update count and the training hours at each.

    Hours add up the sittings (each from its first logged scalar to its last; see ``sittings``), so the time
    between sittings does not count."""
    rows, hours_before = [], 0.0
    for files, start, end in sittings(run_dir):
        for acc, tags in files:
            if "car_0/eval/episodic_return" not in tags:
                continue
            progress = (
                {e.step: e.value for e in acc.Scalars("car_0/eval/progress")} if "car_0/eval/progress" in tags else {}
            )
            updates = acc.Scalars("car_0/perf/updates") if "car_0/perf/updates" in tags else []
            update_steps = np.array([e.step for e in updates])
            update_values = np.array([e.value for e in updates])
            for e in acc.Scalars("car_0/eval/episodic_return"):
                before = update_steps <= e.step
                rows.append(
                    {
                        "env_steps": int(e.step),
                        "updates": int(update_values[before][-1]) if before.any() else 0,
                        "wall_hours": round(hours_before + (e.wall_time - start) / 3600, 4),
                        "eval_return": round(float(e.value), 2),
                        "eval_progress": round(float(progress.get(e.step, float("nan"))), 4),
                    }
                )
        hours_before += (end - start) / 3600
    rows.sort(key=lambda row: row["env_steps"])
    return [row for i, row in enumerate(rows) if i == 0 or row["env_steps"] != rows[i - 1]["env_steps"]]


def baselines(
    eval_seed: int = 10_000, episodes: int = 10, results_dir: str = RESULTS, filename: str = "baselines.json"
) -> dict:
    """Random actions and the pursuit driver on the tracks ``eval_seed ..`` (by default the 10 held-out tracks of
    the evaluations; ``FRESH_TRACKS`` for the final policies' reference), with the env settings of training.
    Computed once, then read from ``results_dir/filename``."""
    path = os.path.join(results_dir, filename)
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)
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
        json.dump(results, f, indent=2)
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


def evaluate_checkpoint(
    path: str, first_track: int = 10_000, tracks: int = 10, policy: str = "stochastic", train_tracks: int = 0
) -> dict:
    """A saved agent (any variant, any stage; agent 0 of a multi-agent checkpoint) driving alone with `policy` on
    tracks ``first_track .. first_track + tracks - 1``, or (``train_tracks`` > 0) on the last ``train_tracks``
    tracks it trained on, with the env settings it was trained with (final dead zone): mean return, progress and
    |steer| (near 1: bang-bang steering), and the per-track values. The training runs' own evaluation is this on
    10000..10009; another block of tracks measures a best.pt without the bias of having been picked there."""
    if tracks < 1:
        raise ValueError(f"tracks must be >= 1, got {tracks}")
    from evaluate import evaluate_checkpoint as drive
    from race import read_checkpoint  # one reader of checkpoints: clear one-line errors naming the file

    script, checkpoint = read_checkpoint(path)
    variant = checkpoint["variant"]
    if policy not in script.EVAL_POLICIES:
        raise ValueError(f"policy must be one of {', '.join(script.EVAL_POLICIES)}, got {policy!r}")
    args = script.args_from_checkpoint(checkpoint, path, num_agents=1)
    seeds = None
    if train_tracks > 0:
        if args.stage != "single" or args.num_races != 1:
            raise ValueError(f"{path}: --train-tracks needs a single-stage run of one race at a time")
        races = int(checkpoint["counters"]["episode"])
        seeds = [script.race_seed(args.seed, e) for e in range(max(0, races - train_tracks), races)]
        tracks_name = f"training races {max(0, races - train_tracks)}..{races - 1}"
    else:
        tracks_name = f"{first_track}..{first_track + tracks - 1}"
    readings = drive(path, first_track, tracks, (policy,), seeds=seeds)[policy]
    returns, progress, abs_steer = (np.asarray(readings[key]) for key in ("return", "progress", "abs_steer"))
    result = {
        "checkpoint": path,
        "variant": variant,
        "updates": int(checkpoint["agents"][0]["num_updates"]),
        "policy": policy,
        "tracks": tracks_name,
        "eval_return": float(returns.mean()),
        "eval_progress": float(progress.mean()),
        "returns": [round(float(r), 2) for r in returns],
        "progress": [round(float(p), 4) for p in progress],
    }
    if args.env_id == "multi_car_racing":  # action 0 is the steer there (highway-env: the acceleration)
        result["mean_abs_steer"] = float(abs_steer.mean())
    return result


# --- Are the critic and the imagination optimistic on real episodes? ---------------------------------------
CALIBRATION_COLUMNS = (
    "checkpoint", "variant", "updates", "tracks", "horizon", "starts", "value", "realised_return", "bootstrap_weight",
    "imagined_task_return", "real_task_return", "horizon_starts", "eliminations", "elimination_reasons",
    "terminal_reward", "terminal_reward_predicted", "terminal_reward_sigma", "terminal_continue", "reward_sigma",
)  # fmt: skip


def realised_returns(rewards: np.ndarray, terminated: np.ndarray, bonus: np.ndarray, last_value: float,
                     gamma: float) -> np.ndarray:  # fmt: skip
    """What the critic estimates, realised on one real episode of T+1 frames (index t: frame t; rewards[t] and
    terminated[t] came with frame t): G_t = r_{t+1} + bonus_t + gamma (1 - terminated_{t+1}) G_{t+1} for t < T, with
    G_T = last_value (the critic's bootstrap where the episode was truncated; unused where it terminated). This is
    the lambda-return recursion of the scripts with real rewards, terminations and (bonus = -alpha log pi) actions in
    place of imagined ones. Returns G_0 .. G_{T-1}."""
    returns, following = np.zeros(len(rewards) - 1), float(last_value)
    for t in range(len(rewards) - 2, -1, -1):
        following = rewards[t + 1] + bonus[t] + gamma * (1.0 - float(terminated[t + 1])) * following
        returns[t] = following
    return returns


def horizon_task_returns(rewards: np.ndarray, terminated: np.ndarray, gamma: float, horizon: int) -> np.ndarray:
    """J_t = sum_{k < H} gamma^k r_{t+k+1} of one real episode (the real counterpart of an H-step imagination from
    frame t, task reward only); NaN where the episode was truncated before t + H (its rewards there are unknown).
    A terminated episode has no reward after its last frame."""
    last = len(rewards) - 1
    returns = np.full(last, np.nan)
    for t in range(last):
        if t + horizon <= last or terminated[last]:
            steps = rewards[t + 1 : t + 1 + horizon]
            returns[t] = float(np.sum(steps * gamma ** np.arange(len(steps))))
    return returns


def calibrate_checkpoint(path: str, first_track: int = 10_100, tracks: int = 5, horizon: int | None = None) -> dict:
    """Is the agent's value of real states, and its imagination from them, optimistic? The saved agent (a training
    checkpoint: it needs its critic and reward head) drives its sampled policy, as trained, on tracks
    ``first_track ..``; on every frame t of those real episodes (its posterior state, as imagination starts from):

    * ``value``: the critic's V(s_t), against ``realised_return``: G_t, the same quantity realised (real rewards and
      terminations, the entropy bonus -alpha log pi of a fresh action at s_t, the critic's own value of the last
      frame where the episode was truncated: ``bootstrap_weight`` is the mean weight gamma^(T - t) of that value);
    * ``imagined_task_return``: the world model's H-step discounted reward from s_t, imagining with the actor (H:
      the agent's imagination horizon), against ``real_task_return``: the H-step discounted reward that followed s_t
      in the real episode (starts whose episode was truncated before t + H left out: ``horizon_starts``).

    Means over all frames of all tracks, whatever happened after them (averages over windows picked by their
    outcome, such as those ending in an elimination, would look optimistic even for a perfect model). value >
    realised: the critic is optimistic; imagined > real: the actor gets more reward in the model than on the road.
    And the races that ended in an elimination (``eliminations``, ``elimination_reasons``: the env's reasons), on
    their terminal frame itself: the real reward (the penalty), the reward head's mean and sigma there and the
    continue head's probability, against the reward head's median sigma over all frames (``reward_sigma``)."""
    import torch

    from race import read_checkpoint
    from utils import make_vec_env

    script, checkpoint = read_checkpoint(path)
    agent = script.agent_from_checkpoint(path, 0)
    if agent.acting_only:
        raise ValueError(f"{path}: an acting-only export has no critic or reward head; give a training checkpoint")
    args = script.args_from_checkpoint(checkpoint, path, num_agents=1)
    horizon = horizon or args.imagination_horizon
    envs = make_vec_env(args.env_id, 1, None, **script.env_kwargs(args, args.dead_zone_end))
    torch.manual_seed(first_track)
    episodes, reasons = [], []
    try:
        for seed in range(first_track, first_track + tracks):
            envs.seed(seed)
            obs, state = envs.reset(), None
            episode = script.CarEpisode(script.preprocess_frames(obs, args.image_size)[0], agent.action_dim)
            while True:
                action, state = agent.act(script.preprocess_frames(obs, args.image_size), state, None, "stochastic")
                obs, reward, dones, infos, _ = script.step_with_repeat(envs, action, args.action_repeat)
                if dones[0]:  # (the vec env has reset: the episode's last frame is the terminal observation)
                    frame = script.preprocess_frames(infos[0]["terminal_observation"][None], args.image_size)[0]
                    episode.add(frame, action[0], reward[0], not infos[0]["TimeLimit.truncated"])
                    reasons.append(infos[0].get("eliminated"))  # None: a finished lap or the time limit
                    break
                episode.add(script.preprocess_frames(obs, args.image_size)[0], action[0], reward[0], False)
            episodes.append(episode.arrays())
    finally:
        envs.close()
    sums = dict.fromkeys(("value", "realised_return", "bootstrap_weight", "imagined", "real"), 0.0)
    starts = horizon_starts = 0
    terminal, sigmas = [], []  # per elimination: real reward, predicted mean, sigma, continue; every frame's sigma
    wm, actor, gamma = agent.world_model, agent.actor, args.gamma
    agent._set_training(False)  # running statistics, as when acting
    with torch.no_grad():
        for (frames, actions, rewards, terminated), reason in zip(episodes, reasons):
            is_first = torch.zeros(1, len(frames), dtype=torch.bool)
            is_first[0, 0] = True
            post = wm.observe(wm.encoder(torch.as_tensor(frames[None])), torch.as_tensor(actions[None]), is_first)
            features = torch.cat([post["z"], post["h"]], -1)[0]
            values = agent.critic(features)[0].numpy()
            reward_mean, reward_std = script.gaussian_params(wm.reward(features), script.HEAD_MIN_STD)
            sigmas.append(reward_std.squeeze(-1).numpy())
            if reason is not None:
                last_continue = torch.sigmoid(wm.cont(features[-1:]).float()).item()
                terminal.append((rewards[-1], reward_mean[-1].item(), reward_std[-1].item(), last_continue))
            mean, std = actor(features)
            log_pi = script.policy_log_prob(mean + std * torch.randn_like(std), mean, std).numpy()
            g = realised_returns(rewards, terminated, -float(agent.alpha()) * log_pi, values[-1], gamma)
            last = len(frames) - 1
            if not terminated[-1]:  # truncated: G_t carries gamma^(T - t) V(s_T)
                sums["bootstrap_weight"] += float(np.sum(gamma ** (last - np.arange(last))))
            state = tuple(s[0, :-1] for s in post["states"])
            imagined, _, _, _ = script.imagine_rollout(wm, actor, state, post["h"][0, :-1], post["z"][0, :-1], horizon)
            reward = script.gaussian_params(wm.reward(imagined[1:]), script.HEAD_MIN_STD)[0].squeeze(-1)
            continues = torch.sigmoid(wm.cont(imagined[1:]).float().squeeze(-1))
            i_task = (script.discount_weights(continues, gamma) * reward).sum(0).numpy()
            j_task = horizon_task_returns(rewards, terminated, gamma, horizon)
            valid = ~np.isnan(j_task)
            sums["value"] += values[:-1].sum()
            sums["realised_return"] += g.sum()
            sums["imagined"] += i_task[valid].sum()
            sums["real"] += j_task[valid].sum()
            starts, horizon_starts = starts + len(g), horizon_starts + int(valid.sum())
    named = sorted({r for r in reasons if r is not None})
    return {
        "checkpoint": path, "variant": checkpoint["variant"], "updates": int(checkpoint["agents"][0]["num_updates"]),
        "tracks": f"{first_track}..{first_track + tracks - 1}", "horizon": horizon, "starts": starts,
        **{k: round(float(sums[k] / max(starts, 1)), 3 if k == "bootstrap_weight" else 2)
           for k in ("value", "realised_return", "bootstrap_weight")},
        "imagined_task_return": round(float(sums["imagined"] / max(horizon_starts, 1)), 2),
        "real_task_return": round(float(sums["real"] / max(horizon_starts, 1)), 2),
        "horizon_starts": horizon_starts, "eliminations": len(terminal),
        "elimination_reasons": " ".join(f"{r}:{reasons.count(r)}" for r in named),
        **dict(zip(
            ("terminal_reward", "terminal_reward_predicted", "terminal_reward_sigma", "terminal_continue"),
            np.round(np.mean(terminal, axis=0), 3) if terminal else [float("nan")] * 4,
        )),
        "reward_sigma": round(float(np.median(np.concatenate(sigmas))), 3),
    }  # fmt: skip


def write_calibration_row(row: dict, path: str = os.path.join(RESULTS, "calibration.csv")) -> None:
    """Add `row` to calibration.csv, replacing an earlier row of the same checkpoint, tracks and horizon."""
    key = ("checkpoint", "tracks", "horizon")
    rows = []
    if os.path.exists(path):
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if tuple(str(r[k]) for k in key) != tuple(str(row[k]) for k in key)]
    rows.append(row)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CALIBRATION_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)


FINAL_COLUMNS = (
    "exp_name", "variant", "seed", "updates", "env_steps", "hours",
    "final_return", "final_progress", "final_mean_abs_steer",
    "best_return", "best_progress", "mean_action_return", "mean_action_progress", "mean_action_abs_steer",
    "best_eval_return", "last3_eval_return",
)  # fmt: skip


def final_row(
    variant: str, seed: int, exp_name: str | None = None, policy: str = "stochastic", runs_dir: str = RUNS,
    updates: int = FINAL_UPDATES,
) -> dict:
    """The final protocol's row of one run: its last policy (latest.pt) and its best evaluation (best.pt), both
    measured with `policy` on the fresh tracks FRESH_TRACKS; the last policy's mean action there too (how smoothly
    the policy means to steer, without the sampling noise); the run's updates, env steps and training hours; and
    its best and last-three-average evaluation returns (the 10 evaluation tracks), which say whether it holds.
    A run that has not reached `updates` is refused: the protocol's result is the policy after all of them."""
    run = find_run(exp_name or experiment_name(variant), seed, runs_dir)
    if run is None:
        raise ValueError(f"no run of {exp_name or experiment_name(variant)} seed {seed} in {runs_dir}")
    import race

    checkpoint = race.read_checkpoint(os.path.join(run, "checkpoints", "latest.pt"))[1]
    done = int(checkpoint["agents"][0]["num_updates"])
    if done < updates:
        raise ValueError(f"{run} has made {done} of its {updates} updates (--updates): not a final policy yet")
    curve = eval_curve(run)
    latest = os.path.join(run, "checkpoints", "latest.pt")
    final = evaluate_checkpoint(latest, *FRESH_TRACKS, policy)
    best = evaluate_checkpoint(os.path.join(run, "checkpoints", "best.pt"), *FRESH_TRACKS, policy)
    mean_action = evaluate_checkpoint(latest, *FRESH_TRACKS, "mean-action")
    evals = [r["eval_return"] for r in curve]
    return {
        "exp_name": exp_name or experiment_name(variant), "variant": variant, "seed": seed, "updates": final["updates"],
        # the whole run's, to its last update (not its last evaluation's)
        "env_steps": int(checkpoint["counters"]["global_step"]), "hours": training_hours(run),
        "final_return": round(final["eval_return"], 2), "final_progress": round(final["eval_progress"], 4),
        "final_mean_abs_steer": round(final["mean_abs_steer"], 4),
        "best_return": round(best["eval_return"], 2), "best_progress": round(best["eval_progress"], 4),
        "mean_action_return": round(mean_action["eval_return"], 2),
        "mean_action_progress": round(mean_action["eval_progress"], 4),
        "mean_action_abs_steer": round(mean_action["mean_abs_steer"], 4),
        "best_eval_return": round(max(evals), 2) if evals else float("nan"),
        "last3_eval_return": round(float(np.mean(evals[-3:])), 2) if evals else float("nan"),
    }  # fmt: skip


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


def write_final_row(row: dict, path: str = os.path.join(RESULTS, "learning_final.csv")) -> None:
    """Add `row` to learning_final.csv, replacing an earlier row of the same experiment (an ablation is its own) and
    seed."""
    rows = []
    if os.path.exists(path):
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if (r["exp_name"], int(r["seed"])) != (row["exp_name"], row["seed"])]
    rows.append(row)
    rows.sort(key=lambda r: (r["exp_name"], int(r["seed"])))
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FINAL_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)


def final_summary(
    path: str = os.path.join(RESULTS, "learning_final.csv"), reps: int = 2000, policy: str = "stochastic"
) -> str:
    """Markdown: per variant the IQM and mean of the final return, the final policy acting with `policy`, with
    stratified-bootstrap 95% intervals (rliable), the bar's numbers, and which parts of the bar (bar_verdict)
    fail."""
    from stats import interval_estimates

    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
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

    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["exp_name"] == experiment_name(r["variant"])]
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
    stats.MIN_RUNS runs). PPO's own mean has a stratified-bootstrap interval (rliable): a description. The
    variants' defaults only (an ablation is not the method); "" while ppo_peer.csv has no row."""
    from stats import MIN_RUNS, describe, interval_estimates, two_group_claim

    if not os.path.exists(peer_path):
        return ""
    with open(peer_path, newline="") as f:
        peer = list(csv.DictReader(f))
    if not peer:
        return ""
    ppo = np.array([float(r["final_return"]) for r in peer])
    with open(final_path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["exp_name"] == experiment_name(r["variant"])]
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


# A screen: an ablation against the default at the same point of training (same variant, seed and updates), on
# tracks of its own, so that what screening picks is not then reported on the tracks it was picked on.
SCREEN_TRACKS = (10_200, 20)
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
            result = evaluate_checkpoint(path, *tracks, policy)
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
    import fcntl

    def key(r: dict) -> tuple:
        return r["run"], int(r["updates"]), r["policy"], r["tracks"]

    def order(r: dict) -> tuple:
        default_last = r["exp_name"] != experiment_name(r["variant"])
        return r["variant"], int(r["seed"]), int(r["updates"]), default_last, r["exp_name"], *key(r)

    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path + ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        kept, new = [], set(map(key, rows))
        if os.path.exists(path):
            with open(path, newline="") as f:
                kept = [r for r in csv.DictReader(f) if key(r) not in new]
        table = sorted(kept + rows, key=order)
        with open(path + ".tmp", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=SCREEN_COLUMNS)
            writer.writeheader()
            writer.writerows(table)
        os.replace(path + ".tmp", path)
    shown = [c for c in SCREEN_COLUMNS if c not in ("run", "checkpoint")]
    lines = ["| " + " | ".join(shown) + " |", "|" + "---|" * len(shown)]
    lines += ["| " + " | ".join(str(r[c]) for c in shown) + " |" for r in table]
    return "\n".join(lines) + "\n"


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
        sampled = evaluate_checkpoint(latest, *tracks, "stochastic")
        mean_action = evaluate_checkpoint(latest, *tracks, "mean-action")
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


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = parser.add_mutually_exclusive_group()  # instead of training: one of these, or none
    parser.add_argument("--variant", choices=VARIANTS, default="lstm")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--hours", type=float, default=3.0, help="wall-clock budget of this sitting")
    parser.add_argument("--updates", type=int, default=FINAL_UPDATES, help="the run ends after this many updates")
    parser.add_argument("--resume", action="store_true", help="continue the latest run of this variant and seed")
    mode.add_argument("--report", action="store_true", help="only write the curves and the table")
    mode.add_argument(
        "--diagnose", action="store_true",
        help="only the run's diagnostics per 500 updates (returns, sigma, entropy, kl_dyn, reward NLL, imagined "
        "return, evaluations): printed and written to benchmarks/results/<experiment>_seed<S>_diagnostics.md",
    )  # fmt: skip
    parser.add_argument(
        "--runs-dir", default=RUNS,
        help="where the runs are, at any depth (e.g. runs/experiment/trials: the experiment's single stage)",
    )  # fmt: skip
    mode.add_argument(
        "--final", action="store_true",
        help="only evaluate the run's final and best policies on the fresh tracks; its row in learning_final.csv",
    )  # fmt: skip
    mode.add_argument(
        "--final-report", action="store_true",
        help="only rewrite learning_final.md from learning_final.csv and ppo_peer.csv (no evaluation)",
    )  # fmt: skip
    parser.add_argument(
        "--entropy-coef", type=float, default=None,
        help="an ablation: this alpha instead of the preset's (the run is named learning_<variant>_alpha<coef>)",
    )
    parser.add_argument(
        "--decoder-min-log-sigma", type=float, default=None,
        help="an ablation: floor of the decoder's learned log sigma (run named ..._logsigmamin<value>)",
    )
    parser.add_argument(
        "--norm", choices=["batch", "layer"], default=None,
        help="an ablation: this normalisation instead of BatchNorm (run named ..._norm<choice>)",
    )
    parser.add_argument(
        "--return-norm", action="store_const", const=True, default=None,
        help="an ablation: DreamerV3's return normalisation (run named ..._retnorm)",
    )
    parser.add_argument(
        "--reward-nll-beta", type=float, default=None,
        help="an ablation: the reward head's beta-NLL with this beta instead of the Gaussian NLL (run named "
        "..._rbeta<beta>)",
    )  # fmt: skip
    parser.add_argument(
        "--dead-zone-start", type=float, default=None,
        help="an ablation: the dead zone's first value (-0.5, the final one: no schedule; run named ..._dzstart<v>)",
    )  # fmt: skip
    mode.add_argument(
        "--screen", type=int, metavar="UPDATES",
        help="only compare the ablation given by the flags above with the default run of the same variant and seed "
        "(in --reference-runs-dir), each at the policy it kept at UPDATES updates, sampled and mean action on the "
        "20 screening tracks 10200..10219, with their diagnostics: rows of benchmarks/results/screening/screens.csv",
    )  # fmt: skip
    mode.add_argument(
        "--policy-rule", action="store_true",
        help="only apply the rule for the evaluation policy: every final policy of learning_final.csv (default "
        "method) sampled and with its mean action on the screening tracks 10200..10219; rows in "
        "benchmarks/results/policy_rule.csv, the decision in policy_rule.md",
    )  # fmt: skip
    parser.add_argument(
        "--reference-runs-dir", default=None, help="--screen: where the default run is (default: --runs-dir)"
    )
    mode.add_argument("--evaluate", metavar="CHECKPOINT", help="only evaluate this saved agent alone (no training)")
    mode.add_argument(
        "--calibrate", metavar="CHECKPOINT",
        help="only measure whether this agent's critic and imagination are optimistic on real episodes (its sampled "
        "policy on --tracks tracks from --first-track, default 10100); a row of benchmarks/results/calibration.csv",
    )  # fmt: skip
    parser.add_argument(
        "--horizon", type=int, default=None, help="--calibrate: imagination horizon (default: the agent's own)"
    )
    mode.add_argument(
        "--export", nargs=2, metavar=("CHECKPOINT", "OUT"),
        help="only write agent 0 of CHECKPOINT as an acting-only export OUT (e.g. pretrained/lstm_cpu.pt)",
    )  # fmt: skip
    parser.add_argument(
        "--first-track", type=int, default=None, help="--evaluate, --calibrate: seed of the first track (10000, 10100)"
    )
    parser.add_argument("--tracks", type=int, default=None, help="--evaluate, --calibrate: number of tracks (10, 5)")
    parser.add_argument(
        "--train-tracks", type=int, default=0, help="--evaluate: the last N tracks the run trained on instead",
    )  # fmt: skip
    parser.add_argument(
        "--policy", choices=["deterministic", "mean-action", "stochastic"], default=None,
        help="--evaluate: deterministic = posterior mean z and mean action; mean-action = sampled z, mean action "
        "(default, the scripts' --eval-policy); stochastic = both sampled, as trained. (--final always samples, "
        "for learning_final.csv's final and best columns, and measures the mean action into its own columns)",
    )  # fmt: skip
    args = parser.parse_args()
    if args.horizon is not None and not args.calibrate:
        parser.error("--horizon is the imagination horizon of --calibrate; give --calibrate CHECKPOINT")
    if args.reference_runs_dir is not None and args.screen is None:
        parser.error("--reference-runs-dir is the default run's place for --screen; give --screen UPDATES")
    if args.hours <= 0:
        parser.error(f"--hours must be > 0, got {args.hours}")
    if args.updates < 1:
        parser.error(f"--updates must be >= 1, got {args.updates}")
    ablation = {name: getattr(args, name) for name in ABLATION_TAGS}
    if args.export:
        from race import read_checkpoint

        try:
            script, _ = read_checkpoint(args.export[0])
        except ValueError as e:
            parser.error(str(e))
        from utils.checkpoint import export_policy

        size = export_policy(script, args.export[0], args.export[1])
        print(f"wrote {args.export[1]} ({size / 1e6:.1f} MB)")
        return
    if args.calibrate:
        tracks = 5 if args.tracks is None else args.tracks
        if tracks < 1 or (args.horizon is not None and args.horizon < 1):
            parser.error(f"--tracks and --horizon must be >= 1, got {tracks} and {args.horizon}")
        try:
            first = 10_100 if args.first_track is None else args.first_track
            row = calibrate_checkpoint(args.calibrate, first, tracks, args.horizon)
        except ValueError as e:
            parser.error(str(e))
        write_calibration_row(row)
        print(json.dumps(row, indent=1))
        return
    args.first_track = 10_000 if args.first_track is None else args.first_track
    args.tracks = 10 if args.tracks is None else args.tracks
    if args.evaluate:
        if args.tracks < 1 or args.train_tracks < 0:
            parser.error(f"--tracks must be >= 1 and --train-tracks >= 0, got {args.tracks} and {args.train_tracks}")
        try:
            result = evaluate_checkpoint(
                args.evaluate, args.first_track, args.tracks, args.policy or "mean-action", args.train_tracks
            )  # fmt: skip
        except ValueError as e:  # race.CheckpointError is a ValueError naming the file
            parser.error(str(e))
        print(json.dumps(result, indent=1))
        return
    if args.screen is not None:
        try:
            rows = screen_rows(
                args.variant, args.seed, args.screen, experiment_name(args.variant, **ablation), args.runs_dir,
                args.reference_runs_dir or args.runs_dir,
            )  # fmt: skip
        except ValueError as e:
            parser.error(str(e))
        print(write_screen_rows(rows))
        return
    if args.policy_rule:
        try:
            rows = policy_rule_rows(args.runs_dir)
        except ValueError as e:
            parser.error(str(e))
        table = policy_rule_table(rows, policy_rule(rows))
        with open(os.path.join(RESULTS, "policy_rule.md"), "w") as f:
            f.write(table)
        print(table)
        return
    if args.diagnose:
        name = experiment_name(args.variant, **ablation)
        run = find_run(name, args.seed, args.runs_dir)
        if run is None:
            parser.error(f"no run of {name} seed {args.seed} in {args.runs_dir}")
        table = diagnostics_table(diagnostics(run))
        with open(os.path.join(RESULTS, f"{name}_seed{args.seed}_diagnostics.md"), "w") as f:
            f.write(f"{os.path.basename(run)}\n\n{table}")
        print(table)
        return
    if args.final_report:
        print(write_final_report())
        return
    if args.final:
        if args.policy not in (None, "stochastic"):
            parser.error("--final measures the sampled policy in learning_final.csv's final and best columns; the "
                         "mean action has its own columns (--policy applies to --evaluate)")  # fmt: skip
        try:
            row = final_row(
                args.variant, args.seed, experiment_name(args.variant, **ablation), "stochastic", args.runs_dir,
                args.updates,
            )
        except ValueError as e:
            parser.error(str(e))
        write_final_row(row)
        print(json.dumps(row, indent=1))
        print(write_final_report())
        return
    if not args.report:
        script, script_args, overrides = run_args(
            args.variant, args.seed, args.hours, args.resume, args.updates, args.runs_dir, **ablation
        )
        from utils.checkpoint import UsageError
        from utils.run import validate_args

        try:  # an ablated value the script refuses ends here, before any work, naming the flag
            validate_args(script_args, script.LOG_SIGMA_RANGE)
        except UsageError as e:
            parser.error(str(e))
        script.main(script_args, overrides)
    report(args.runs_dir)


if __name__ == "__main__":
    main()
