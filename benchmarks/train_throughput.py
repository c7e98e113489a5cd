"""Training throughput of the Dreamer scripts: time per update as a ratio to a bare-encoder reference.

One update = world-model step + imagination + actor step + critic step (`Agent.update`). Every time
is printed next to its ratio to the reference measured in the same process with the same thread
setting: a bare 4-layer conv encoder (3-32-64-128-256, kernel 4, stride 2) forward + backward on
750 frames of 96x96 (one paper-size batch, B*L = 15*50), so figures compare across machines
(peers spend 4-12x the reference per update; docs/agent.md).
Each configuration also prints its matmul/conv FLOPs per update as a ratio to the reference's: the time
ratio it would have if it ran at the reference's efficiency (paper size, 100 starts: 3.1x).

Also measured: env steps per second of one two-car race while both agents act at every env step (and
with random actions, for reference).

    python benchmarks/train_throughput.py                      # CPU size only (quick)
    python benchmarks/train_throughput.py --configs paper-100 paper-all cpu
    python benchmarks/train_throughput.py --amp-ratio --threads 1  # --amp on against off: CPU time per update
    python benchmarks/train_throughput.py --compile-ratio --threads 1 --warmup 4  # --compile against without

``--amp-ratio`` times what a run's CPU budget buys: the process CPU time of one update with ``--amp on`` and with
``--amp off``, two agents of the same configuration from the same weights updating in turn on the same batches in
one process (so that load on the machine weighs on both alike), their ratio, and their losses at the last update
(the same random draws for both: they differ by bfloat16's rounding alone). ``--compile-ratio`` does the same for
``--compile`` against without, at ``--amp`` (its compiling falls in the warm-up updates, untimed; the losses differ
by the compiled kernels' rounding alone).
"""

from __future__ import annotations

import dataclasses
import importlib
import itertools
import os
import sys
import time
from typing import Literal

import numpy as np
import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from utils.run import cpu_has_bf16, keep_freed_memory, resolve_amp, tyro_cli  # noqa: E402  (keep_freed_memory: malloc)

CONFIGS = {
    "paper-100": {"imagination_starts": 100},  # the paper authors' setting
    "paper-all": {},  # the default: all B*L starts
    "cpu": None,  # the script's own --preset cpu (each variant has its own batch size and horizon)
}


def config_of(script, name: str) -> dict:
    return dict(script.PRESETS["cpu"]) if CONFIGS[name] is None else CONFIGS[name]


@dataclasses.dataclass
class Args:
    script: str = "dreamer_lstm"
    """module of the agent to measure (dreamer_lstm or dreamer_gru)"""
    configs: tuple[Literal["paper-100", "paper-all", "cpu"], ...] = ("cpu",)
    """configurations to time: paper size with 100 / all imagination starts, the CPU size"""
    updates: int = 5
    """timed updates per configuration (after the warm-up updates); the median is reported"""
    warmup: int = 2
    """untimed updates first (the first updates of a process page-fault while the heap grows; compiling)"""
    reference_repeats: int = 3
    """timed repeats of the bare-encoder reference (after one warm-up); the median is reported"""
    threads: int = 0
    """torch threads (0: torch's default)"""
    malloc_fix: bool = True
    """glibc mallopt setting of the scripts (--malloc-fix), applied once for the reference and the agents alike"""
    compile: bool = False
    """torch.compile the agents' networks (the scripts' --compile)"""
    amp: Literal["auto", "on", "off", "cuda"] = "auto"
    """bfloat16 autocast of the update (the scripts' --amp; auto: where bfloat16 is in hardware, a CUDA device of
    Ampere or newer or a CPU with bfloat16 instructions)"""
    env_steps: int = 300
    """env steps for the acting throughput (0: skip)"""
    amp_ratio: bool = False
    """instead: process CPU seconds per update with --amp on and off, interleaved in this process, per configuration"""
    compile_ratio: bool = False
    """instead: the same with --compile and without (at --amp), the compiling in the warm-up updates"""


def median_time(fn, repeats: int, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def counted_flops(fn) -> int:
    """Matmul and conv FLOPs of one call: how much arithmetic the method itself needs, at any efficiency."""
    with FlopCounterMode(display=False) as counter:
        fn()
    return counter.get_total_flops()


def bare_encoder_reference(repeats: int) -> tuple[float, int]:
    """4-layer conv (3-32-64-128-256, k4 s2) + ReLU, forward and backward on 750 frames of 96x96: time, FLOPs."""
    layers, channels = [], [3, 32, 64, 128, 256]
    for c_in, c_out in itertools.pairwise(channels):
        layers += [nn.Conv2d(c_in, c_out, 4, 2), nn.ReLU()]
    encoder = nn.Sequential(*layers)
    frames = torch.rand(750, 3, 96, 96)

    def step():
        encoder.zero_grad(set_to_none=True)
        encoder(frames).sum().backward()

    return median_time(step, repeats), counted_flops(step)


def filled_replay(script, args, steps: int = 3000):
    rng = np.random.default_rng(0)
    replay = script.Replay(steps, args.image_size)
    for _ in range(steps // 500):
        obs = rng.integers(0, 256, (500, args.image_size, args.image_size, 3), dtype=np.uint8)
        action = rng.uniform(-1, 1, (500, 2)).astype(np.float32)
        terminated = np.zeros(500, bool)
        terminated[-1] = True
        replay.add_episode(obs, action, rng.normal(size=500).astype(np.float32), terminated)
    return replay


def time_update(script, overrides: dict, repeats: int, warmup: int) -> dict:
    args = script.Args(**overrides)
    agent = script.Agent(args)
    replay = filled_replay(script, args)
    batch = replay.sample(args.batch_size, args.seq_len)
    total = median_time(lambda: agent.update(batch), repeats, warmup)

    def world_model_step():  # the update's world-model part, as Agent.update runs it (--amp included)
        agent._set_training(True)
        with agent.autocast():
            loss, _, _ = agent.world_model_loss(*agent._batch_tensors(batch))
        agent._step(agent.model_optimizer, loss, agent.world_model.parameters())

    world_model = median_time(world_model_step, repeats)
    flops = counted_flops(lambda: agent.update(batch))
    starts = args.imagination_starts or args.batch_size * args.seq_len
    return {
        "total": total,
        "world_model": world_model,
        "behaviour": total - world_model,
        "flops": flops,
        "starts": starts,
        "args": args,
    }


def paired_cpu_seconds(script, overrides: dict, flag: str, values: tuple, updates: int, warmup: int
                       ) -> tuple[dict, dict]:  # fmt: skip
    """Median process CPU seconds of one update with the scripts' `flag` at each of its two `values` (--amp on and
    off, --compile and not), and each one's losses at its last update: two agents of the same configuration, from
    the same weights, on the same batches and random draws, updating in turn (`warmup` untimed updates each first:
    with --compile, its compiling)."""
    agents = {value: script.Agent(script.Args(**{**overrides, flag: value})) for value in values}
    agents[values[1]].load_state_dict(agents[values[0]].state_dict())
    args = agents[values[0]].args
    replay = filled_replay(script, args)
    times, losses = {value: [] for value in agents}, {}
    for step, timed in enumerate([False] * warmup + [True] * updates):
        batch = replay.sample(args.batch_size, args.seq_len)
        for value, agent in agents.items():
            torch.manual_seed(step)  # the same latent and action noise for both
            started = time.process_time()
            losses[value] = agent.update(batch)
            if timed:
                times[value].append(time.process_time() - started)
    return {value: float(np.median(t)) for value, t in times.items()}, losses


def env_throughput(script, overrides: dict, steps: int) -> tuple[float, float]:
    """Env steps/s of one two-car race: both agents acting at every env step (no action repeat: the cost of acting
    at its most; a run at the CPU preset acts every 2nd step), and random actions."""
    from utils import make_vec_env
    from utils.collector import preprocess_frames

    args = script.Args(**overrides)
    agents = [script.Agent(args) for _ in range(2)]
    envs = make_vec_env("multi_car_racing", 1, 0, num_agents=2)

    def run(act: bool) -> float:
        obs, states, is_first = envs.reset(), [None, None], np.ones(2, bool)
        t = time.perf_counter()
        for _ in range(steps):
            frames = preprocess_frames(obs, args.image_size)
            actions = np.random.uniform(-1, 1, (2, 2)).astype(np.float32)
            if act:
                for i, agent in enumerate(agents):
                    actions[i : i + 1], states[i] = agent.act(frames[i : i + 1], states[i], is_first[i : i + 1])
            obs, _, _, infos = envs.step(actions)
            is_first = np.array([info["is_first"] for info in infos])
        return steps / (time.perf_counter() - t)

    acting, random_actions = run(True), run(False)
    envs.close()
    return acting, random_actions


def main(args: Args) -> None:
    script = importlib.import_module(args.script)
    if args.malloc_fix:
        print(f"malloc fix: {keep_freed_memory()}")
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, script {args.script}")
    if args.amp_ratio and args.compile_ratio:
        raise SystemExit("train_throughput.py: error: --amp-ratio and --compile-ratio each time a pair: give one")
    if args.amp_ratio or args.compile_ratio:
        flag, values = ("amp", ("on", "off")) if args.amp_ratio else ("compile", (True, False))
        names = {"on": "--amp on", "off": "--amp off", True: "--compile", False: "--no-compile"}
        print(f"bfloat16 in this CPU's instructions (AVX512-BF16, --amp auto's rule): {cpu_has_bf16()}")
        fixed = {"compile": args.compile} if args.amp_ratio else {"amp": args.amp}
        print(f"both with {', '.join(f'--{k} {v}' for k, v in fixed.items())}"
              + ("" if args.amp_ratio else f" ({resolve_amp(args.amp, torch.device('cpu'))})"))  # fmt: skip
        for name in args.configs:
            seconds, losses = paired_cpu_seconds(script, {**config_of(script, name), **fixed}, flag, values,
                                                 args.updates, args.warmup)  # fmt: skip
            first, second = (seconds[v] for v in values)
            print(f"{name:10s} CPU seconds per update: {names[values[0]]} {first:.3f}, {names[values[1]]} "
                  f"{second:.3f}; {names[values[1]]} / {names[values[0]]} = {second / first:.2f}", flush=True)
            for key in ("model_loss", "kl_dyn", "actor", "critic"):  # from the same weights and batches
                print(f"  {key} at update {args.warmup + args.updates}: "
                      + ", ".join(f"{names[v]} {losses[v][key]:.4f}" for v in values))  # fmt: skip
        return
    reference, reference_flops = bare_encoder_reference(args.reference_repeats)
    print(f"bare encoder reference (750 frames 96x96, fwd+bwd): {reference:.2f} s")
    for name in args.configs:
        config = {**config_of(script, name), "compile": args.compile, "amp": args.amp}
        r = time_update(script, config, args.updates, args.warmup)
        a = r["args"]
        print(
            f"{name:10s} B={a.batch_size} L={a.seq_len} H={a.imagination_horizon} {a.image_size}px depth={a.cnn_depth} "
            f"deter={a.deter_size} hidden={a.hidden_size} starts={r['starts']} "
            f"amp={resolve_amp(a.amp, torch.device('cpu'))}: update {r['total']:.2f} s "
            f"= {r['total'] / reference:.2f}x reference (world model {r['world_model']:.2f} s = "
            f"{r['world_model'] / reference:.2f}x, imagination+actor+critic {r['behaviour']:.2f} s = "
            f"{r['behaviour'] / reference:.2f}x); its FLOPs are {r['flops'] / reference_flops:.2f}x the reference's",
            flush=True,
        )
    if args.env_steps:
        for name in args.configs:
            acting, random_actions = env_throughput(script, config_of(script, name), args.env_steps)
            print(
                f"env steps/s, one two-car race, {name} agents acting: {acting:.0f} "
                f"(random actions: {random_actions:.0f})"
            )


if __name__ == "__main__":
    main(tyro_cli(Args))
