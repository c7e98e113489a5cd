"""Are the agent's critic and imagination optimistic on real episodes? (``benchmarks/learning.py --calibrate``)

A saved training checkpoint drives its sampled policy on a block of tracks; on every real frame, its critic's value
and its world model's imagined return are set against what the real episode returned from there
(``calibrate_checkpoint``); the row is kept in ``benchmarks/results/calibration.csv``.
"""

from __future__ import annotations

import os

import numpy as np

from common import RESULTS, TRACKS, checkpoint_updates, replace_rows, track_block


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


def posterior(agent, frames: np.ndarray, actions: np.ndarray) -> dict:
    """The world model's posterior over one race's `frames` observed with `actions` (world_model.observe from the
    learned initial state; BatchNorm with its running statistics, as when acting)."""
    import torch

    wm = agent.world_model
    agent._set_training(False)
    with torch.no_grad():
        is_first = torch.zeros(1, len(frames), dtype=torch.bool, device=agent.device)
        is_first[0, 0] = True
        embed = wm.encoder(torch.as_tensor(frames[None], device=agent.device))
        return wm.observe(embed, torch.as_tensor(actions[None], device=agent.device), is_first)


def calibrate_checkpoint(path: str, first_track: int = TRACKS["fresh"][0], tracks: int = 5, horizon: int | None = None
                         ) -> dict:
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
    continue head's probability, against the reward head's median sigma over all frames (``reward_sigma``; of a
    two-hot head the std of its softmax, which the tiny mass on its +-4.9e8 bins dominates: not a Gaussian's sigma,
    compare its means instead)."""
    import torch

    import evaluate  # (the repository's evaluate.py)

    script, checkpoint, args, agent, envs = evaluate.single_car(path)
    if agent.acting_only:
        envs.close()
        raise ValueError(f"{path}: an acting-only export has no critic or reward head; give a training checkpoint")
    horizon = horizon or args.imagination_horizon
    records = evaluate.sampled_episodes(agent, args, envs, first_track, tracks)  # as training stores them
    episodes = [cars[0].arrays() for cars in records]
    reasons = [cars[0].final_info.get("eliminated") for cars in records]  # None: a finished lap or the time limit
    sums = dict.fromkeys(("value", "realised_return", "bootstrap_weight", "imagined", "real"), 0.0)
    starts = horizon_starts = 0
    terminal, sigmas = [], []  # per elimination: real reward, predicted mean, sigma, continue; every frame's sigma
    wm, actor, gamma = agent.world_model, agent.actor, args.gamma
    agent._set_training(False)  # running statistics, as when acting
    with torch.no_grad():
        for (frames, actions, rewards, terminated), reason in zip(episodes, reasons):
            post = posterior(agent, frames, actions)
            features = torch.cat([post["z"], post["h"]], -1)[0]
            values = agent.critic.dist(features).mean.numpy()
            reward = wm.reward.dist(features)  # the head's distribution (a Gaussian, or two-hot: its std)
            reward_mean, reward_std = reward.mean, reward.std
            sigmas.append(reward_std.numpy())
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
            reward = wm.reward.dist(imagined[1:]).mean
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
        "checkpoint": path, "variant": checkpoint["variant"], "updates": checkpoint_updates(checkpoint),
        "tracks": track_block(first_track, tracks), "horizon": horizon, "starts": starts,
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
    """Add `row` to calibration.csv, replacing an earlier row of the same checkpoint, tracks and horizon (kept in
    the order they were measured; locked and replaced atomically: common.replace_rows)."""
    def key(r: dict) -> tuple:
        return tuple(str(r[k]) for k in ("checkpoint", "tracks", "horizon"))

    replace_rows(path, [row], CALIBRATION_COLUMNS, key, order=lambda r: ())
