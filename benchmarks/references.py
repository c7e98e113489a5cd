"""The references of the learning benchmark: random actions and the pure-pursuit driver (at speed 70) on a block of
tracks, driven once and kept as JSON beside the results (``baselines``; the final protocol's report puts them beside
its rows: ``references_report.json``).
"""

from __future__ import annotations

import json
import os

import numpy as np

from common import RESULTS, track_block, write_json


def baselines(eval_seed: int, episodes: int, results_dir: str = RESULTS, filename: str = "references.json") -> dict:
    """Random actions and the pursuit driver on the tracks ``eval_seed .. eval_seed + episodes - 1``, with the env
    settings of training. Computed once, then read from ``results_dir/filename``, which names its tracks (a file of
    other tracks is refused; one written before it named them is read as it is)."""
    path, tracks = os.path.join(results_dir, filename), track_block(eval_seed, episodes)
    if os.path.exists(path):
        with open(path) as f:
            saved = json.load(f)
        if saved.setdefault("tracks", tracks) != tracks:
            raise ValueError(f"{path} holds the references on tracks {saved['tracks']}, not {tracks}: give another "
                             "results_dir or filename")  # fmt: skip
        return {name: value for name, value in saved.items() if name != "tracks"}
    from envs import MultiCarRacing
    from envs.pursuit import PursuitDriver

    results = {}
    for reference in ("random", "pursuit@70"):
        returns, progress = [], []
        for e in range(episodes):
            env = MultiCarRacing(num_agents=1, dead_zone=-0.5)
            env.reset(seed=eval_seed + e)
            rng = np.random.default_rng(e)
            driver = PursuitDriver(env, "car_0", 70.0)
            total = 0.0
            while env.agents:
                action = driver.act() if reference.startswith("pursuit") else rng.uniform(-1, 1, 2)
                _, rewards, _, _, infos = env.step({"car_0": action})
                total += rewards["car_0"]
            returns.append(total)
            progress.append(infos["car_0"]["progress"])
        results[reference] = {"eval_return": float(np.mean(returns)), "eval_progress": float(np.mean(progress))}
    os.makedirs(results_dir, exist_ok=True)
    write_json(path, {**results, "tracks": tracks})  # atomic: final_protocol.py reads it as a cache
    return results
