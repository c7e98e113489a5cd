"""Memory soak: a long two-car race with both agents acting, watching resident memory.

Both cars are driven by CPU-sized agents of a dreamer script (``Agent.act``, sampled actions, recurrent state
carried and reset at every new race) at every env step, without action repeat; every car's finished episodes go to
its agent's replay as in training (``CarEpisode`` -> ``Replay.add_episode``), one transition per env step (so, at
the CPU preset's action repeat 2, twice as fast as a training run fills it). Resident memory (VmRSS of
/proc/self/status) is reported at the start, every ``--report-every`` env steps and at the end, beside the bytes the
replays have filled: a healthy run grows by the replays' own fill and nothing else.

    python benchmarks/memory_soak.py                       # 50,000 env steps
    python benchmarks/memory_soak.py --steps 5000 --report-every 1000

(Not a test: minutes of stepping. Races are 1000 steps unless a car is out earlier.)
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from utils.run import env_kwargs, keep_freed_memory, tyro_cli  # noqa: E402  (glibc keeps freed memory: --malloc-fix)


@dataclasses.dataclass
class Args:
    script: str = "dreamer_lstm"
    """module of the agents (dreamer_lstm or dreamer_gru)"""
    steps: int = 50_000
    """env steps to run (each steps both cars)"""
    report_every: int = 5_000
    """report resident memory every this many env steps"""
    replay_capacity: int = 100_000
    """replay capacity per agent, in steps (the scripts' default)"""
    seed: int = 0
    """seed of the tracks and of the agents"""
    threads: int = 1
    """torch threads (0: torch's default)"""
    malloc_fix: bool = True
    """the scripts' glibc setting (keep freed memory in the process)"""


def rss_bytes() -> int:
    """Resident set size of this process, from VmRSS in /proc/self/status (Linux)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def main(args: Args) -> dict:
    script = importlib.import_module(args.script)
    from utils import make_vec_env
    from utils.collector import CarEpisode, preprocess_frames

    if args.malloc_fix:
        keep_freed_memory()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    config = script.preset_args("cpu", replay_capacity=args.replay_capacity)  # the scripts' CPU preset
    agents = [script.Agent(config) for _ in range(2)]
    replays = [script.Replay(config.replay_capacity, config.image_size) for _ in range(2)]
    step_bytes = script.Replay.bytes_per_step(config.image_size)
    envs = make_vec_env("multi_car_racing", 1, args.seed, **env_kwargs(config, config.dead_zone_end))

    def filled() -> int:
        return sum(len(r) for r in replays) * step_bytes

    rows = []

    def report(step: int, started: float) -> None:
        rss, fill = rss_bytes(), filled()
        rows.append({"step": step, "rss": rss, "replay": fill, "other": rss - fill})
        grown = (rss - fill) - rows[0]["other"]
        print(
            f"step {step:>7,}  {time.time() - started:7.0f} s  RSS {rss / 2**20:8.1f} MiB  replays filled"
            f" {fill / 2**20:7.1f} MiB  RSS - replays {(rss - fill) / 2**20:7.1f} MiB"
            f" ({grown / 2**20:+.1f} since start)",
            flush=True,
        )

    obs = envs.reset()
    frames = preprocess_frames(obs, config.image_size)
    states, is_first = [None, None], np.ones(2, dtype=bool)
    episodes = [CarEpisode(frames[i]) for i in range(2)]
    races = 0
    started = time.time()
    report(0, started)
    for step in range(1, args.steps + 1):
        actions = np.zeros((2, 2), dtype=np.float32)
        for i, agent in enumerate(agents):
            actions[i : i + 1], states[i] = agent.act(frames[i : i + 1], states[i], is_first[i : i + 1])
        obs, rewards, dones, infos = envs.step(actions)
        frames = preprocess_frames(obs, config.image_size)
        for i, info in enumerate(infos):
            if not info["alive"]:
                continue
            if dones[i]:
                last = preprocess_frames(info["terminal_observation"][None], config.image_size)[0]
                episodes[i].add(last, actions[i], rewards[i], terminated=not info["TimeLimit.truncated"])
                replays[i].add_episode(*episodes[i].arrays())
            else:
                episodes[i].add(frames[i], actions[i], rewards[i], terminated=False)
        is_first = np.array([info["is_first"] for info in infos], dtype=bool)
        if is_first.any():
            races += 1
            episodes = [CarEpisode(frames[i]) for i in range(2)]
        if step % args.report_every == 0 or step == args.steps:
            report(step, started)
    envs.close()

    first, last = rows[0], rows[-1]
    # The first race's allocations (buffers of torch, Box2D, the renderer) settle in the first interval.
    settled = rows[1] if len(rows) > 2 else first
    print(
        f"\n{args.steps:,} env steps, {races} races, {args.steps / (time.time() - started):.0f} env steps/s."
        f"\nRSS {first['rss'] / 2**20:.1f} -> {last['rss'] / 2**20:.1f} MiB;"
        f" replays filled {last['replay'] / 2**20:.1f} MiB"
        f" (capacity {2 * config.replay_capacity * step_bytes / 2**20:,.0f} MiB)."
        f"\nGrowth beyond the replays: {(last['other'] - first['other']) / 2**20:+.1f} MiB since the start,"
        f" {(last['other'] - settled['other']) / 2**20:+.1f} MiB since step {settled['step']:,}"
        f" ({(last['other'] - settled['other']) / max(1, last['step'] - settled['step']):+.1f} B per env step)."
    )
    return {"rows": rows, "races": races}


if __name__ == "__main__":
    main(tyro_cli(Args))
