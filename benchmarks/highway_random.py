"""The random-action reference for the highway-env check: per-agent return on the evaluation seeds.

    python benchmarks/highway_random.py                  # seeds 10000..10004, 2 draws of actions each
    python benchmarks/highway_random.py --episodes 10 --repeats 3

The dreamer scripts evaluate with ``--env-id highway-intersection`` on the scenarios
``eval_seed + e`` (``evaluate()``: one race per seed, rewards of every slot summed until the race
resets). This runs the same loop with uniform random actions in [-1, 1]^2, so the agents' logged
``car_i/eval/episodic_return`` has a reference on exactly those scenarios.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from utils import make_vec_env  # noqa: E402


def random_returns(episodes: int, repeats: int, eval_seed: int = 10_000, num_agents: int = 2) -> np.ndarray:
    """Returns (repeats, episodes, num_agents) of uniform random actions on scenarios eval_seed + e."""
    venv = make_vec_env("highway-intersection", 1, None, num_agents=num_agents)
    returns = np.zeros((repeats, episodes, num_agents))
    try:
        for r in range(repeats):
            rng = np.random.default_rng(r)
            for e in range(episodes):
                venv.seed(eval_seed + e)
                venv.reset()
                while True:
                    _, rewards, _, infos = venv.step(rng.uniform(-1, 1, (num_agents, 2)).astype(np.float32))
                    returns[r, e] += rewards
                    if infos[0]["is_first"]:
                        break
    finally:
        venv.close()
    return returns


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=5, help="scenarios eval_seed .. eval_seed + episodes - 1")
    parser.add_argument("--repeats", type=int, default=2, help="independent draws of random actions per scenario")
    parser.add_argument("--eval-seed", type=int, default=10_000)
    args = parser.parse_args()
    if args.episodes < 1 or args.repeats < 1:
        parser.error(f"--episodes and --repeats must be >= 1, got {args.episodes} and {args.repeats}")
    returns = random_returns(args.episodes, args.repeats, args.eval_seed)
    per_agent = returns.mean(axis=(0, 1))
    spread = returns.mean(axis=2).std()
    print(f"random actions, {args.episodes} scenarios x {args.repeats} draws: mean return per agent "
          + ", ".join(f"car_{i} {v:.1f}" for i, v in enumerate(per_agent)) + f" (std over races {spread:.1f})")


if __name__ == "__main__":
    main()
