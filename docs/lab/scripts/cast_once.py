"""usage: python docs/lab/scripts/cast_once.py [dreamer_lstm|dreamer_gru] [UPDATES]

A lead checked and not adopted (docs/lab/final_protocol.md, 51st sitting). Under CPU autocast a weight's bfloat16
copy is cached only for leaf tensors that require grad; imagination runs the world model frozen
(`requires_grad_(False)`), so the recurrent input's, the cell's and the prior's weights are cast again at every
imagined step. This times one update (process CPU seconds, median of UPDATES after 4 warm-up ones, `--preset cpu`,
`--amp on`, one thread) of two agents from the same weights, batches and random draws, updating in turn: one as the
script is, one whose imagination runs on weights cast once per update (the norms' weights left float32: CPU autocast
runs LayerNorm and BatchNorm in their input's dtype). It checks that the two end bit-identical.
"""

import contextlib
import importlib
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", ".."))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "..", "benchmarks"))
import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch import nn  # noqa: E402
from train_throughput import filled_replay  # noqa: E402

NORMS = (nn.LayerNorm, nn.BatchNorm1d, nn.BatchNorm2d)


@contextlib.contextmanager
def cast_once(modules, dtype):
    """Inside the block the float32 parameters of `modules` (norms excepted) are `dtype` copies."""
    swapped = []
    for module in modules:
        for sub in module.modules():
            if isinstance(sub, NORMS):
                continue
            for key, param in list(sub._parameters.items()):
                if param is not None and param.dtype == torch.float32:
                    swapped.append((sub, key, param))
                    sub._parameters[key] = param.detach().to(dtype)
    try:
        yield
    finally:
        for sub, key, param in swapped:
            sub._parameters[key] = param


def flat(state, prefix=""):
    out = {}
    for key, value in state.items():
        if isinstance(value, dict):
            out.update(flat(value, f"{prefix}{key}."))
        elif torch.is_tensor(value):
            out[f"{prefix}{key}"] = value
    return out


def main(name: str, updates: int) -> None:
    torch.set_num_threads(1)
    script = importlib.import_module(name)
    plain = script.imagine_rollout

    def cast_rollout(world_model, actor, *args, **kwargs):
        with cast_once([world_model.recurrent_input, world_model.cell, world_model.transition], torch.bfloat16):
            return plain(world_model, actor, *args, **kwargs)

    agents = [script.Agent(script.Args(**{**script.PRESETS["cpu"], "amp": "on"})) for _ in range(2)]
    agents[1].load_state_dict(agents[0].state_dict())
    args = agents[0].args
    replay = filled_replay(script, args)
    times, losses = [[], []], [None, None]
    for step in range(4 + updates):
        batch = replay.sample(args.batch_size, args.seq_len)
        for i, agent in enumerate(agents):
            script.imagine_rollout = cast_rollout if i else plain
            torch.manual_seed(step)
            started = time.process_time()
            losses[i] = agent.update(batch)
            if step >= 4:
                times[i].append(time.process_time() - started)
    a, b = flat(agents[0].state_dict()), flat(agents[1].state_dict())
    identical = a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a) and losses[0] == losses[1]
    plain_s, cast_s = np.median(times[0]), np.median(times[1])
    print(f"{name}: {plain_s:.3f} s per update as it is, {cast_s:.3f} s cast once (ratio {cast_s / plain_s:.3f}); "
          f"{len(a)} state tensors and the losses bit-identical: {identical}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "dreamer_lstm", int(sys.argv[2]) if len(sys.argv) > 2 else 12)
