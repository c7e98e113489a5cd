"""The random-action reference for the highway-env check: per-agent return on the evaluation seeds.

    python benchmarks/highway_random.py                  # seeds 10000..10004, 2 draws of actions each
    python benchmarks/highway_random.py --episodes 10 --repeats 3
    python benchmarks/highway_random.py --run runs/<highway run> --csv benchmarks/results/highway.csv

The dreamer scripts evaluate with ``--env-id highway-intersection`` on the scenarios
``eval_seed + e`` (``utils.collector.drive_races``: one race per seed, rewards of every slot summed until the race
resets). This runs the same loop with uniform random actions in [-1, 1]^2, so the agents' logged
``car_i/eval/episodic_return`` has a reference on exactly those scenarios. With ``--run`` it also
prints (and with ``--csv`` saves) that run's evaluations next to the random reference.
"""

from __future__ import annotations

import dataclasses
import glob
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from utils import make_vec_env  # noqa: E402
from utils.run import tyro_cli, usage_error  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import write_table  # noqa: E402
from runs import eval_curve  # noqa: E402


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


def agent_evaluations(run_dir: str) -> list[dict]:
    """A dreamer run's evaluations, read from its event files (runs.eval_curve): one row per evaluation (in
    env-step order) with ``env_steps``, ``updates`` (of car 0, the last logged at or before it) and ``car_i``
    returns."""
    if not glob.glob(os.path.join(run_dir, "events.out.tfevents.*")):
        raise FileNotFoundError(f"no TensorBoard event file in {run_dir!r} (expected a dreamer run directory)")
    rows = [{"env_steps": row["env_steps"], "updates": row["updates"]} | {k: v for k, v in row.items()
            if k.startswith("car_")} for row in eval_curve(run_dir, cars=True)]  # fmt: skip
    if not rows:
        raise ValueError(f"{run_dir!r} logged no evaluation (car_i/eval/episodic_return); is --eval-every set?")
    return rows


@dataclasses.dataclass
class Args:
    episodes: int = 5
    """scenarios eval_seed .. eval_seed + episodes - 1"""
    repeats: int = 2
    """independent draws of random actions per scenario"""
    eval_seed: int = 10_000
    """the first scenario's seed (the dreamer scripts' --eval-seed)"""
    run: str | None = None
    """a dreamer run on highway-intersection: print its evaluations too"""
    csv: str | None = None
    """with --run: write its evaluations and the random reference to this CSV"""
    num_agents: int | None = None
    """cars in the scenarios (default: the --run's, else 2)"""


def main(argv: list[str] | None = None) -> None:
    args = tyro_cli(Args, argv, __doc__)

    def error(message: str) -> None:
        usage_error("highway_random.py", message)

    if args.episodes < 1 or args.repeats < 1 or (args.num_agents is not None and args.num_agents < 1):
        error(f"--episodes, --repeats and --num-agents must be >= 1, got {args.episodes}, {args.repeats} and "
              f"{args.num_agents}")
    if args.csv and not args.run:
        error("--csv needs --run (it saves that run's evaluations)")
    try:
        evaluations = agent_evaluations(args.run) if args.run else []
    except (FileNotFoundError, ValueError) as exception:
        error(str(exception))
    cars = len({key for row in evaluations for key in row if key.startswith("car_")}) or None  # (none without --run)
    if cars is not None and args.num_agents not in (None, cars):
        error(f"--num-agents {args.num_agents}: the run {args.run!r} has {cars} cars")
    num_agents = cars or args.num_agents or 2
    returns = random_returns(args.episodes, args.repeats, args.eval_seed, num_agents)
    per_agent = returns.mean(axis=(0, 1))
    spread = returns.mean(axis=2).std()
    print(
        f"random actions, {args.episodes} scenarios x {args.repeats} draws: mean return per agent "
        + ", ".join(f"car_{i} {v:.1f}" for i, v in enumerate(per_agent))
        + f" (std over races {spread:.1f})"
    )
    random_row = {
        "env_steps": "random",
        "updates": "",
        **{f"car_{i}": round(float(v), 2) for i, v in enumerate(per_agent)},
    }
    for row in evaluations:
        print(
            f"{args.run}: after {row['env_steps']} env steps, {row['updates']} updates: "
            + ", ".join(f"{key} {value:.1f}" for key, value in row.items() if key.startswith("car_"))
        )
    if args.csv:
        write_table(args.csv, [*evaluations, random_row], list(random_row))
        print(f"wrote {args.csv}")


if __name__ == "__main__":
    main()
