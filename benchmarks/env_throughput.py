"""Env steps per second of a two-car race against gymnasium's CarRacing-v3, in one process.

    python benchmarks/env_throughput.py [--seconds 10]

Both envs take uniformly random actions and reset when done. Prints steps/s of each and
the ratio (target: the two-car race at least 10x CarRacing-v3, i.e. 20x per car).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

import gymnasium
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from envs import MultiCarRacing  # noqa: E402
from utils.run import tyro_cli, usage_error  # noqa: E402


@dataclasses.dataclass
class Args:
    seconds: float = 10.0
    """measuring time per env (wall seconds)"""
    seed: int = 0
    """track seed of the first race in each env, and seed of its random actions"""


def carracing_sps(seconds: float, seed: int) -> float:
    env = gymnasium.make("CarRacing-v3")
    env.reset(seed=seed)
    env.action_space.seed(seed)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        steps += 1
        if term or trunc:
            env.reset()
    return steps / (time.perf_counter() - start)


def race_sps(seconds: float, seed: int, num_agents: int) -> float:
    env = MultiCarRacing(num_agents=num_agents)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        if not env.agents:
            env.reset()
        env.step({a: rng.uniform(-1, 1, 2) for a in env.agents})
        steps += 1
    return steps / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> None:
    args = tyro_cli(Args, argv, __doc__)
    if not args.seconds > 0:
        usage_error("env_throughput.py", f"--seconds must be > 0, got {args.seconds}")
    reference = carracing_sps(args.seconds, args.seed)
    race = race_sps(args.seconds, args.seed, num_agents=2)
    single = race_sps(args.seconds, args.seed, num_agents=1)
    print(f"gymnasium CarRacing-v3      {reference:8.1f} env steps/s")
    print(f"MultiCarRacing, 1 car       {single:8.1f} env steps/s   ratio {single / reference:5.1f}x")
    print(f"MultiCarRacing, 2 cars      {race:8.1f} env steps/s   ratio {race / reference:5.1f}x"
          f"   ({2 * race / reference:.1f}x per car step)")


if __name__ == "__main__":
    main()
