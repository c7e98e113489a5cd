"""A training run of a dreamer script: arguments, memory, env and device, run directory, resume, logging,
checkpoints, command line.

The scripts hold the method (networks, losses, replay, the agent's update and Algorithm 1's loop); this module holds
what every run needs around it. A *method* is a dreamer script's module; what is used of it: ``VARIANT``, ``Args``,
``PRESETS``, ``Agent``, ``Replay``, ``LOG_SIGMA_RANGE``, ``dead_zone_at`` and ``main`` (``cli``).

* the env and the device: ``env_kwargs`` (the racing env's options, from Args), ``races_seed`` (training tracks),
  ``next_dead_zone`` / ``set_next_dead_zone`` (the warm-up, race by race), ``resolve_amp`` and ``bf16_autocast``
  (--amp);
* ``setup_run`` checks everything, then builds the ``Run`` (a new one, or a saved one exactly as it stopped): seeds,
  device, envs, agents, replays, logger (TensorBoard, progress.csv), ``config.json``;
* after every race: ``log_race`` and ``log_updates`` (TensorBoard and progress.csv), ``after_training``
  (videos, evaluation and ``best.pt``, replay save, ``latest.pt``, the row of progress.csv);
* ``finish_run`` saves and closes; ``cli`` turns bad input into one line on stderr.

A resumed run keeps every setting it was started with except those its command line sets explicitly, which are
printed; what fixes its networks (``ARCHITECTURE``) or what it is (``IDENTITY``) cannot change.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import json
import math
import os
import platform
import random
import sys
import time
from collections import deque

import numpy as np
import torch

from utils.checkpoint import (
    CheckpointError,
    UsageError,
    args_from_checkpoint,
    atomic_write,
    ghost_from_tensors,
    ghost_to_tensors,
    load_agent_state,
    load_checkpoint,
    prune_replay,
    replay_dir_of,
    resolve_checkpoint,
    restore_replay,
    retired_args,
    save_checkpoint,
    save_replay,
    set_rng_state,
)
from utils.collector import drive_races

# Arguments that fix the networks' shapes (a --checkpoint brings its own; a resumed run cannot change them),
# and what a run is, with the size of the replay it reloads (a resumed run cannot change those either).
ARCHITECTURE = ("image_size", "cnn_depth", "deter_size", "hidden_size", "mlp_size", "latent_size", "norm", "heads")
IDENTITY = ("env_id", "num_agents", "num_races", "stage", "seed", "exp_name", "runs_dir", "checkpoint", "preset",
            "replay_capacity")


class NumericalFault(RuntimeError):
    """--max-nonfinite-updates updates in a row had a non-finite loss or gradient; the run stopped with a checkpoint."""


# --- Arguments -------------------------------------------------------------------------------
def flag(name: str) -> str:
    return "--lambda" if name == "lambda_" else "--" + name.replace("_", "-")


def explicit_fields(args_class, argv: list[str]) -> set[str]:
    """Names of the Args fields that a command line sets explicitly (`--flag v`, `--flag=v`, `--[no-]flag`)."""
    fields = {field.name: field for field in dataclasses.fields(args_class)}
    names = {flag(name)[2:]: name for name in fields}
    found = set()
    for token in argv:
        if not token.startswith("--"):
            continue
        name = token[2:].split("=", 1)[0].replace("_", "-")
        if name in names:
            found.add(names[name])
        elif name.startswith("no-") and name[3:] in names and fields[names[name[3:]]].type in (bool, "bool"):
            found.add(names[name[3:]])
    return found


def validate_args(args, log_sigma_range: tuple[float, float]) -> None:
    """Refuse impossible arguments before any work starts: raises UsageError (a ValueError) naming the flag."""

    def require(ok: bool, name: str, requirement: str) -> None:
        if not ok:
            raise UsageError(f"{flag(name)} {requirement}, got {getattr(args, name)!r}")

    for field in dataclasses.fields(args):
        value = getattr(args, field.name)
        if isinstance(value, float):
            require(math.isfinite(value), field.name, "must be a finite number")
    for minimum, names in {
        1: ("num_agents", "num_races", "max_steps", "action_repeat", "total_episodes", "replay_capacity", "batch_size",
            "imagination_horizon", "eval_episodes", "ghost_tracks", "video_length", "max_nonfinite_updates",
            "cnn_depth", "deter_size", "hidden_size", "mlp_size", "latent_size"),
        2: ("seq_len",),  # a sequence model learns from transitions: at least two steps
        0: ("torch_threads", "stall_steps", "dead_zone_episodes", "prefill_episodes", "train_steps_per_episode",
            "eval_every", "video_every", "checkpoint_every", "replay_save_every", "imagination_starts",
            "total_updates", "pause_at_updates",
            "time_limit_hours", "cpu_hours_limit", "entropy_coef", "free_bits", "kl_dyn_scale", "kl_rep_scale",
            "brake_speed_threshold", "collision_penalty", "offroad_penalty", "eval_seed", "ghost_seed"),
    }.items():  # fmt: skip
        for name in names:
            require(getattr(args, name) >= minimum, name, f"must be >= {minimum}")
    for name in ("model_lr", "critic_lr", "actor_lr", "entropy_lr", "grad_clip"):
        require(getattr(args, name) > 0, name, "must be > 0")
    require(0 < args.gamma <= 1, "gamma", "must lie in (0, 1]")
    require(0 <= args.lambda_ <= 1, "lambda_", "must lie in [0, 1]")
    require(args.head_sigma >= 0, "head_sigma", "must be >= 0 (0: learned)")
    if args.heads == "twohot":
        require(args.head_sigma == 0, "head_sigma", "is the Gaussian heads' sigma: leave it 0 with --heads twohot")
    require(args.action_penalty is None or args.action_penalty >= 0, "action_penalty", "must be >= 0")
    if args.entropy_target is not None:  # (finite, as every float above)
        require(args.entropy_coef > 0, "entropy_coef", "must be > 0 with --entropy-target (alpha starts there)")
    require(0 < args.tau <= 1, "tau", "must lie in (0, 1]")
    low, high = log_sigma_range
    require(low <= args.decoder_min_log_sigma <= high, "decoder_min_log_sigma", f"must lie in [{low:g}, {high:g}]")
    for name in ("dead_zone_start", "dead_zone_end"):
        require(-1 <= getattr(args, name) <= 0, name, "must lie in [-1, 0]")
    require(0 <= args.seed < 2**32, "seed", "must lie in [0, 2**32)")
    starts = args.batch_size * args.seq_len
    require(args.imagination_starts <= starts, "imagination_starts", f"must be <= batch-size * seq-len = {starts}")
    require(args.replay_capacity >= args.seq_len, "replay_capacity", f"must be >= --seq-len ({args.seq_len})")
    from utils.vec_env import ENV_IDS

    require(args.env_id in ENV_IDS, "env_id", f"must be one of {sorted(ENV_IDS)}")
    if args.stage == "ghost":
        require(args.env_id == "multi_car_racing", "env_id", "must be multi_car_racing for --stage ghost")
        if not args.checkpoint and not args.resume:
            raise UsageError("--stage ghost needs --checkpoint (e.g. runs/<run>/checkpoints/best.pt)")
    if args.resume is not None:
        require(os.path.isfile(resolve_checkpoint(args.resume)), "resume", "must be a run directory with "
                "checkpoints/latest.pt or a checkpoint file")  # fmt: skip
    elif args.checkpoint is not None:  # (a resumed run has its networks already)
        require(os.path.isfile(args.checkpoint), "checkpoint", "must be a checkpoint file")
    elif args.fresh_replay:
        raise UsageError("--fresh-replay applies to a run started from --checkpoint (give one, or drop the flag)")


def usage_error(program: str, message: str) -> None:
    """Exit as argparse does on bad input: status 2, `program: error: message` as stderr's last line."""
    print(f"{program}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def tyro_cli(args_class, argv: list[str] | None = None, description: str | None = None):
    """``tyro.cli(args_class, args=argv, description=description)``, with each field's docstring one paragraph in
    --help. tyro (1.0.16, pinned) joins a docstring's line to the one before only when the line starts with a letter,
    and looks before it removes the docstring's indentation: every indented continuation line, or one that starts
    with "(" or "--", would start a help line of its own. Here a docstring loses its indentation (inspect.cleandoc)
    and its lines are joined first, except before a blank line, an indented line or a list item ("- ", "* ", "1.")."""
    import inspect
    import re

    import tyro
    from tyro import _strings

    join = _strings.remove_single_line_breaks
    if not getattr(join, "cleans_first", False):
        def cleaned_then_joined(helptext: str) -> str:
            return join(re.sub(r"(?<=\S)\n(?![\s]|[-*] |\d+[.)] )", " ", inspect.cleandoc(helptext)))

        cleaned_then_joined.cleans_first = True
        _strings.remove_single_line_breaks = cleaned_then_joined
    return tyro.cli(args_class, args=argv, description=description)


def parse_args(method, argv: list[str] | None = None):
    """Args of a command line, with its --preset applied under the flags it sets, and the fields it sets. A new run
    from --checkpoint without --preset takes the preset the checkpoint was trained at, at this code's values of it
    (its action repeat, batch, horizon...; other flags the checkpoint's run set are not carried over)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    description = (f"{method.__doc__.splitlines()[0]} The defaults are the paper's (or its authors' code's); "
                   f"\"(ours)\" marks this project's own. --preset cpu: a configuration for a CPU (docs/agent.md).")
    args = tyro_cli(method.Args, argv, description)
    explicit = explicit_fields(method.Args, argv)
    if args.resume:
        return args, explicit
    if args.checkpoint and "preset" not in explicit and os.path.isfile(args.checkpoint):  # (else validate_args says)
        try:
            start = load_checkpoint(args.checkpoint, method.VARIANT, training=True, mmap=True)  # (only its args)
        except CheckpointError:  # (an export, a foreign file: the run's set-up says what is wrong with it)
            start = None
        trained_at = args.preset if start is None else args_from_checkpoint(method.Args, start, args.checkpoint).preset
        if trained_at != args.preset:
            print(f"--preset {trained_at}: the preset {args.checkpoint} was trained at (--preset chooses another)")
            args = dataclasses.replace(args, preset=trained_at)
    args = dataclasses.replace(args, **{k: v for k, v in method.PRESETS[args.preset].items() if k not in explicit})
    return args, explicit


def cli(method, argv: list[str] | None = None) -> str:
    """The command line: bad input and a run stopped by numerical faults end with a one-line error, no traceback."""
    try:
        args, explicit = parse_args(method, argv)
        return method.main(args, explicit)
    except (UsageError, NumericalFault) as e:
        message = " ".join(str(e).split())
        raise SystemExit(f"{os.path.basename(method.__file__)}: error: {message}") from None


# --- Memory ----------------------------------------------------------------------------------
def available_memory() -> tuple[int | None, str]:
    """Bytes of memory a new allocation can use, and where the number comes from: MemAvailable of /proc/meminfo
    (capped by a cgroup memory limit), else free physical pages (sysconf), else (None, "unknown")."""
    available, source = None, "unknown"
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    available, source = int(line.split()[1]) * 1024, "MemAvailable in /proc/meminfo"
    if available is None:
        with contextlib.suppress(OSError, ValueError, AttributeError):
            available, source = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "free pages (sysconf)"
    cgroup_files = [("memory.max", "memory.current"), ("memory/memory.limit_in_bytes", "memory/memory.usage_in_bytes")]
    for limit_file, usage_file in cgroup_files:
        with contextlib.suppress(OSError, ValueError):  # a container's limit ("max": none)
            with open(f"/sys/fs/cgroup/{limit_file}") as f, open(f"/sys/fs/cgroup/{usage_file}") as g:
                room = int(f.read()) - int(g.read())
            if available is None or room < available:
                available, source = room, f"cgroup limit /sys/fs/cgroup/{limit_file}"
    return available, source


def size_text(num_bytes: float) -> str:
    return f"{num_bytes / 1e9:,.2f} GB" if num_bytes >= 1e9 else f"{num_bytes / 1e6:,.1f} MB"


def check_replay_memory(args, step_bytes: int) -> int:
    """Print the replay buffers' size (all agents, `step_bytes` per step) and refuse a capacity that cannot fit in
    available memory. The buffers are allocated lazily (pages are touched as they fill), so a run that does not fit
    would only fail hours later; returns their size in bytes."""
    per_agent = args.replay_capacity * step_bytes
    total = args.num_agents * per_agent
    available, source = available_memory()
    room = "unknown" if available is None else size_text(available)
    print(f"replay buffers: {args.num_agents} x {args.replay_capacity:,} steps x {step_bytes:,} B = "
          f"{size_text(total)} (memory available: {room}, {source})")  # fmt: skip
    if available is not None and total > available:
        raise UsageError(
            f"--replay-capacity {args.replay_capacity}: the replay buffers need {args.num_agents} x "
            f"{size_text(per_agent)} = {size_text(total)} but only {size_text(available)} of memory is available "
            f"({source}); lower --replay-capacity"
        )  # fmt: skip
    return total


def keep_freed_memory() -> bool:
    """Stop glibc from returning freed memory to the OS (the scripts' --malloc-fix).

    Every update allocates and frees the same large blocks; by default glibc unmaps them and the
    kernel page-faults them in again on the next update.
    mallopt(M_TRIM_THRESHOLD, 2**31-1) and mallopt(M_MMAP_MAX, 0) keep them in the process.
    Linux/glibc only; returns whether both settings took effect.
    """
    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # from glibc's malloc.h
    return libc.mallopt(M_TRIM_THRESHOLD, 2**31 - 1) == 1 and libc.mallopt(M_MMAP_MAX, 0) == 1


# --- The run ---------------------------------------------------------------------------------
@dataclasses.dataclass
class Run:
    """What a training run carries from race to race; `setup_run` builds it, `save_latest` writes it."""

    method: object  # the dreamer script's module
    args: object
    run_dir: str
    device: torch.device
    agents: list
    replays: list
    counters: dict  # episode (races finished), global_step (env steps), best_eval_return
    logger: object
    envs: object
    eval_envs: object = None  # made at the first evaluation
    ghosts: dict = dataclasses.field(default_factory=dict)  # ghost stage: track seed -> the best run on it so far
    wins: list = dataclasses.field(default_factory=list)  # per agent, its last 100 race results
    manifests: list = dataclasses.field(default_factory=list)  # per agent, the replay save that latest.pt names
    from_checkpoint: bool = False  # the agents started from --checkpoint: no random prefill
    started: float = dataclasses.field(default_factory=time.time)
    cpu_started: float = dataclasses.field(default_factory=time.process_time)
    cpu_before: float = 0.0  # CPU seconds of the run's earlier invocations (a resumed run)
    fault: str | None = None  # set when an agent had --max-nonfinite-updates faulty updates in a row
    out_of_time: str | None = None  # the budget spent when last checked (set-up, the end of a race), or None
    update_seconds: list = dataclasses.field(default_factory=list)  # the first two updates' times (CPU report)
    pbar: object = None

    def cpu_seconds(self) -> float:
        """Process CPU time of the run so far, over all its invocations (--cpu-hours-limit)."""
        return self.cpu_before + time.process_time() - self.cpu_started

    @property
    def checkpoint_dir(self) -> str:
        return os.path.join(self.run_dir, "checkpoints")

    def replay_dir(self, j: int) -> str:
        return os.path.join(self.checkpoint_dir, f"replay_car_{j}")

    def finished(self) -> bool:
        """The run's end: --total-episodes races, --total-updates updates, the time or CPU budget (as found at the
        set-up or at the end of the last race: a race is never cut short, so a resume continues exactly), a fault."""
        return self.stop_reason() is not None

    def stop_reason(self) -> str | None:
        """Why the run stops now (None: it goes on), in words a user can act on."""
        args = self.args
        updates = min(agent.num_updates for agent in self.agents)
        if self.fault is not None:
            return self.fault
        if self.counters["episode"] >= args.total_episodes:
            return f"--total-episodes {args.total_episodes} races run (a --resume with more races continues it)"
        if args.total_updates > 0 and updates >= args.total_updates:
            return f"--total-updates {args.total_updates} updates made (a --resume with more continues it)"
        if args.pause_at_updates > 0 and updates >= args.pause_at_updates:
            return f"paused at --pause-at-updates {args.pause_at_updates} (a --resume continues it)"
        if self.out_of_time:
            return self.out_of_time
        return None

    def check_budget(self) -> None:
        """Set out_of_time: which of --cpu-hours-limit (the run, over all its invocations) and --time-limit-hours
        (this process) is spent, said as stop_reason says it, or None."""
        args = self.args
        self.out_of_time = None
        if args.time_limit_hours > 0 and time.time() - self.started > 3600 * args.time_limit_hours:
            self.out_of_time = f"--time-limit-hours {args.time_limit_hours:g} of this process spent (--resume goes on)"
        if args.cpu_hours_limit > 0 and self.cpu_seconds() > 3600 * args.cpu_hours_limit:
            self.out_of_time = f"--cpu-hours-limit {args.cpu_hours_limit:g} spent (a --resume with more continues it)"

    def acts_randomly(self) -> bool:
        """Random actions in the prefill races of a new single or race stage (also when resumed during them)."""
        args = self.args
        return self.counters["episode"] < args.prefill_episodes and not self.from_checkpoint and args.stage != "ghost"

    def learning_starts(self) -> int:
        """Updates start after the prefill races; a ghost-stage run first races every ghost track once with the
        starting policy (those runs are the first ghosts)."""
        return self.args.ghost_tracks if self.args.stage == "ghost" else self.args.prefill_episodes

    def learns_now(self) -> bool:
        """Whether the agents train after the race that just ended (counters["episode"] races are done)."""
        enough = all(r.can_sample(self.args.seq_len) for r in self.replays)
        return self.counters["episode"] >= self.learning_starts() and enough

    def print(self, message: str) -> None:
        """A line on stdout that does not break the progress bar."""
        if self.pbar is not None:
            self.pbar.write(message)
        else:
            print(message)


# --- The env and the device ------------------------------------------------------------------
ENV_FIELDS = ("max_steps", "stall_steps", "brake_speed_threshold", "collision_penalty", "offroad_penalty",
              "speed_reward_coef")  # the racing env's options, as Args fields of the same names


def env_kwargs(args, dead_zone: float) -> dict:
    """Keyword arguments of the env constructor (the racing env's options; other envs get num_agents only)."""
    if args.env_id != "multi_car_racing":
        return {"num_agents": args.num_agents}
    return {"num_agents": args.num_agents, **{k: getattr(args, k) for k in ENV_FIELDS}, "dead_zone": dead_zone}


def races_seed(seed: int, races_done: int) -> int:
    """A training track seed drawn from (run seed, races done). One race at a time: the track of race `races_done`
    (the scripts' start_race), so a resumed run drives the very tracks the uninterrupted run would have. K races
    side by side: the seed of their vec env built after `races_done` races; race k starts on the track of this
    seed + k (SB3's VecEnv.seed), its later tracks come from its env's own stream (a resumed run's tracks then
    differ from the uninterrupted run's, docs/reliability.md). (With seed + races_done, run seed 11's race 1 would
    be run seed 12's race 0, and a run resumed after e races would race the tracks of a new run of seed + e.)"""
    return int(np.random.SeedSequence([seed, races_done]).generate_state(1)[0])


def next_dead_zone(method, args, races_done: int) -> float:
    """The dead zone to set once `races_done` races have ended; the env applies it at its next reset. Every race
    races at method.dead_zone_at(the races ended when it starts). One race at a time resets after this
    (start_race): the next race gets dead_zone_at(races_done). K > 1 races side by side have already auto-reset
    the ended race's slot: the value is for the race that starts when the next one ends, dead_zone_at(races_done +
    1). (So with K side by side the warm-up lags by up to K - 1 races; races that end in the same step restart at
    one value.)"""
    return method.dead_zone_at(races_done + (args.num_races > 1), args)


def set_next_dead_zone(run: Run) -> None:
    """Give the racing env the dead zone of the race that starts next (next_dead_zone; other envs have none)."""
    if run.args.env_id == "multi_car_racing":
        run.envs.env_method("set_dead_zone", next_dead_zone(run.method, run.args, run.counters["episode"]))


def cpu_has_bf16() -> bool:
    """Whether this CPU has x86's bfloat16 instructions (AVX512-BF16, which AMX CPUs have too): there an update under
    bfloat16 autocast costs 1.3-1.4x less CPU time than in float32 (docs/performance.md); without them bfloat16 is
    emulated, slower than float32. (Other CPUs' bfloat16, such as ARM's, is not measured here: False.)"""
    return bool(getattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)())


def resolve_amp(amp: str, device: torch.device) -> str:
    """--amp as a run computes on `device`, "on" or "off". auto: on where bfloat16 is in hardware, a CUDA device of
    Ampere or newer (emulated bfloat16, before Ampere, is slower than float32) or a CPU with bfloat16 instructions
    (cpu_has_bf16); cuda: on such a CUDA device only (auto's rule until it took such CPUs in too). A new run saves
    what auto resolved to, and a run saved with auto before then resumes with cuda (args_from_checkpoint), so that
    each goes on computing as it did."""
    if amp in ("on", "off"):
        return amp
    if device.type == "cuda":
        with torch.cuda.device(device):  # (is_bf16_supported asks the current device)
            return "on" if torch.cuda.is_bf16_supported(including_emulation=False) else "off"
    return "on" if amp == "auto" and device.type == "cpu" and cpu_has_bf16() else "off"


def resolved_amp_args(args, device: torch.device):
    """`args` with --amp resolved (resolve_amp) for a run on `device`, saying so; and a warning where bfloat16 is on
    without it in hardware (after a move to another machine, a run saved with on computes emulated bfloat16, which
    is slower than float32: a CPU-hour budget buys fewer updates)."""
    if args.amp not in ("on", "off"):  # saved resolved: the run computes alike wherever it resumes
        resolved = resolve_amp(args.amp, device)
        rule = "" if args.amp == "auto" else " (auto's rule until it took in bfloat16 CPUs: a run saved with auto then)"
        print(f"--amp {args.amp}{rule} -> {resolved}: the updates in {'bfloat16' if resolved == 'on' else 'float32'}")
        args = dataclasses.replace(args, amp=resolved)
    if args.amp == "on" and resolve_amp("auto", device) == "off":
        print(f"warning: --amp on, and {device} has no bfloat16 in hardware: emulated, slower than float32 "
              "(docs/performance.md); --amp off computes otherwise, but faster")
    return args


def bf16_autocast(amp: str, device: torch.device) -> bool:
    """Whether an Agent on `device` runs its update under bfloat16 autocast, by --amp's rule (resolve_amp)."""
    return resolve_amp(amp, device) == "on"


def setup_run(method, args, overrides=()) -> Run:
    """Check everything, then build the run: a new one, or (args.resume) the saved one exactly as it stopped.
    Nothing is written before every check has passed."""
    from utils import make_vec_env
    from utils.logger import configure_logger, make_run_name

    validate_args(args, method.LOG_SIGMA_RANGE)
    resumed = start = None
    if args.resume:
        checkpoint_path = resolve_checkpoint(args.resume)
        resumed = load_checkpoint(checkpoint_path, method.VARIANT, training=True)
        args = resumed_args(method.Args, resumed, checkpoint_path, args, overrides)
        validate_args(args, method.LOG_SIGMA_RANGE)
        folder = os.path.dirname(os.path.abspath(checkpoint_path))
        if os.path.basename(folder) != "checkpoints":  # (a link to a run's checkpoint: that run)
            folder = os.path.dirname(os.path.realpath(checkpoint_path))
        if os.path.basename(folder) != "checkpoints":  # (the run goes on in the directory that holds checkpoints/)
            raise UsageError(f"--resume {args.resume}: not in a run's checkpoints/ folder, so no run directory to go "
                             f"on in; give the run directory (runs/<run>) or a checkpoint in its checkpoints/")
        run_dir = os.path.dirname(folder)
    else:
        args, start = new_run_args(method, args)
        validate_args(args, method.LOG_SIGMA_RANGE)  # again: a --checkpoint brings its networks' form (--heads)
        run_dir = os.path.join(args.runs_dir, make_run_name(args.env_id, args.exp_name, args.seed))
    check_replay_memory(args, method.Replay.bytes_per_step(args.image_size))
    if args.malloc_fix:
        keep_freed_memory()
    if args.torch_threads > 0:
        torch.set_num_threads(args.torch_threads)
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    args = resolved_amp_args(args, device)

    n, episode = args.num_agents, int(resumed["counters"]["episode"]) if resumed else 0
    kwargs = env_kwargs(args, method.dead_zone_at(episode, args))
    envs = make_vec_env(args.env_id, args.num_races, races_seed(args.seed, episode), args.use_subprocess, **kwargs)
    action_dim = int(envs.action_space.shape[0])
    run = Run(
        method, args, run_dir, device,
        agents=[method.Agent(args, action_dim, device) for _ in range(n)],
        replays=[method.Replay(args.replay_capacity, args.image_size, action_dim) for _ in range(n)],
        counters={"episode": 0, "global_step": 0, "best_eval_return": -math.inf},
        logger=None, envs=envs, wins=[deque(maxlen=100) for _ in range(n)], manifests=[None] * n,
        from_checkpoint=args.checkpoint is not None,
    )  # fmt: skip
    if resumed is not None:
        restore_run(run, resumed, checkpoint_path)
    elif start is not None:
        start_from_checkpoint(run, start)
    formats = ("stdout", "csv", "tensorboard") if args.print_table else ("csv", "tensorboard")
    run.logger = configure_logger(run_dir, dataclasses.asdict(args), formats)
    config = {"variant": method.VARIANT, **dataclasses.asdict(args)}  # plot.py groups runs by variant and stage
    atomic_write(os.path.join(run_dir, "config.json"), lambda f: f.write(json.dumps(config, indent=1).encode()))
    print(f"run directory: {run_dir} (device {device}); tensorboard --logdir {args.runs_dir}")
    if resumed is not None:
        print(f"resumed from {checkpoint_path} at race {run.counters['episode']}, step {run.counters['global_step']}")
        set_rng_state(resumed["rng"])  # last of the set-up: the random streams continue where they stopped
    elif args.checkpoint:
        print(f"agents start from {args.checkpoint}")
    run.check_budget()
    return run


def start_from_checkpoint(run: Run, start: dict) -> None:
    """A new run from --checkpoint (`start`, loaded): agent i takes the checkpoint's agent i (modulo its count) and,
    unless --fresh-replay, the replay saved beside it, so that it keeps learning from all it has seen (for a best.pt,
    the newest save of its run: all best.pt had seen and what came after)."""
    args = run.args
    for i, agent in enumerate(run.agents):
        source = i % len(start["agents"])
        load_agent_state(agent, start["agents"][source], args.checkpoint, source)
        directory = replay_dir_of(args.checkpoint, source)
        if args.fresh_replay or not os.path.isfile(os.path.join(directory, "meta.npz")):
            continue
        with np.load(os.path.join(directory, "meta.npz")) as meta:
            capacity = int(meta["capacity"])
        if capacity != args.replay_capacity:
            raise UsageError(f"--replay-capacity {args.replay_capacity}: the replay beside --checkpoint "
                             f"({directory}) holds {capacity}; give --replay-capacity {capacity}, or "
                             "--fresh-replay to start with an empty one")  # fmt: skip
        restore_replay(run.replays[i], directory, None, races=0)
        print(f"car {i}: continues with the replay in {directory} ({len(run.replays[i]):,} steps)")
        # (run.manifests stay None: the run's own replay directory holds no save until its first one)


def new_run_args(method, args):
    """A new run's Args with what its stage implies (one car for single and ghost, one race at a time for ghost)
    and the network sizes of --checkpoint, and that checkpoint (or None)."""
    if args.stage in ("single", "ghost") and args.num_agents != 1:
        print(f"stage {args.stage!r} races one car: --num-agents {args.num_agents} -> 1")
        args = dataclasses.replace(args, num_agents=1)
    if args.stage == "ghost" and args.num_races != 1:
        print(f"stage 'ghost' races one track at a time: --num-races {args.num_races} -> 1")
        args = dataclasses.replace(args, num_races=1)
    if not args.checkpoint:
        return args, None
    start = load_checkpoint(args.checkpoint, method.VARIANT, training=True)
    sizes = args_from_checkpoint(method.Args, start, args.checkpoint)
    changed = {key: getattr(sizes, key) for key in ARCHITECTURE if getattr(sizes, key) != getattr(args, key)}
    if changed:  # the networks must have the sizes they were trained with
        print(f"network sizes from {args.checkpoint}: {changed}")
        args = dataclasses.replace(args, **changed)
    return args, start


def resumed_args(args_class, checkpoint: dict, path: str, args, overrides):
    """The Args of a resumed run: every setting it was started with, except the fields named in `overrides` (those
    the resuming command line set explicitly), which come from `args`; prints each change (old -> new)."""
    retired = retired_args(checkpoint)
    if retired:
        raise CheckpointError(f"{path}: cannot be resumed by this code: trained with {'; '.join(retired.values())}")
    saved = args_from_checkpoint(args_class, checkpoint, path)
    if saved.pause_at_updates and "pause_at_updates" not in overrides:  # a pause holds for the invocation it stopped
        print(f"resume: the pause at {saved.pause_at_updates} updates is lifted (--pause-at-updates 0)")
        saved = dataclasses.replace(saved, pause_at_updates=0)
    changes = {name: getattr(args, name) for name in overrides if name != "resume"}
    fixed = sorted(n for n in changes if n in ARCHITECTURE + IDENTITY and changes[n] != getattr(saved, n))
    if fixed:
        raise UsageError(f"--resume: {', '.join(flag(n) for n in fixed)} cannot change in a resumed run")
    for name, value in changes.items():
        if value != getattr(saved, name):
            print(f"resume: {flag(name)} {getattr(saved, name)!r} -> {value!r}")
    return dataclasses.replace(saved, resume=args.resume, **changes)


def restore_run(run: Run, resumed: dict, path: str) -> None:
    """Put a checkpoint's agents, counters, ghosts, recent wins, CPU time and replays into `run`."""
    n = run.args.num_agents
    if len(resumed["agents"]) != n:
        raise CheckpointError(f"{path}: holds {len(resumed['agents'])} agent(s), its saved --num-agents is {n}")
    for i, (agent, state) in enumerate(zip(run.agents, resumed["agents"])):
        load_agent_state(agent, state, path, i)
    run.counters.update(resumed["counters"])
    extra = resumed.get("extra") or {}
    run.ghosts = {int(s): ghost_from_tensors(g) for s, g in extra.get("ghosts", {}).items()}
    for j, history in enumerate(extra.get("wins", [])[:n]):
        run.wins[j].extend(history)
    run.cpu_before = float(extra.get("cpu_seconds", 0.0))  # (0 for a checkpoint written before it was kept)
    saved = list(extra.get("replays") or []) + [None] * n
    for j, replay in enumerate(run.replays):
        run.manifests[j] = restore_replay(replay, run.replay_dir(j), saved[j], run.counters["episode"])


def checkpoint_extra(run: Run) -> dict:
    """The checkpoint's extra state: ghosts (ghost stage), the replay save of every agent, recent wins, CPU time."""
    return {
        "ghosts": {str(seed): ghost_to_tensors(g) for seed, g in run.ghosts.items()},
        "replays": list(run.manifests),
        "wins": [list(w) for w in run.wins],
        "cpu_seconds": run.cpu_seconds(),
    }


def save_run_checkpoint(run: Run, name: str, extra: dict | None = None) -> str:
    """checkpoints/<name>: the run's agents, arguments, counters and `extra` (default checkpoint_extra) (atomic)."""
    path = os.path.join(run.checkpoint_dir, name)
    extra = checkpoint_extra(run) if extra is None else extra
    save_checkpoint(path, run.method.VARIANT, run.args, run.agents, run.counters, extra)
    return path


def save_replays(run: Run) -> None:
    """Save every agent's replay (the new chunks) and keep what each save holds (run.manifests) for latest.pt."""
    run.manifests = [save_replay(replay, run.replay_dir(j)) for j, replay in enumerate(run.replays)]


def save_latest(run: Run) -> str:
    """checkpoints/latest.pt, naming each agent's replay save; then the replay files it does not name go."""
    path = save_run_checkpoint(run, "latest.pt")
    for j, manifest in enumerate(run.manifests):
        if manifest is not None:
            prune_replay(run.replay_dir(j), manifest)
    return path


def finish_run(run: Run) -> str:
    """Save the replays and latest.pt, close everything, say why the run stopped; raise NumericalFault if that is
    why."""
    reason = run.stop_reason()
    save_replays(run)
    latest = save_latest(run)
    if run.pbar is not None:
        run.pbar.close()
    run.envs.close()
    if run.eval_envs is not None:
        run.eval_envs.close()
    run.logger.close()
    print(f"{run.run_dir}: stopped after race {run.counters['episode']}: {reason}")
    if run.fault is not None:
        raise NumericalFault(f"{run.fault}; stopped after race {run.counters['episode']} with the checkpoint {latest}")
    return run.run_dir


# --- After every race ------------------------------------------------------------------------
def log_race(run: Run, cars: list, track_seed: int | None, env_sps: float) -> None:
    """Per car: return, progress, lap time and win rate (race stages; the ghost stage: beating the ghost, whose
    record the script's record_ghost keeps), and the env steps per second while the cars drove; charts/dead_zone is the
    schedule at the count of races ended (the next race's dead zone with one race at a time: next_dead_zone)."""
    from envs import race_winners

    args, logger = run.args, run.logger
    final_infos = [car.final_info or {} for car in cars]
    racing = args.env_id == "multi_car_racing"
    won = race_winners(final_infos) if len(cars) > 1 and racing else None  # (highway-env has no ranks)
    if args.stage == "ghost":  # a win is beating the ghost (races without a ghost yet do not count)
        won = [bool(final_infos[0]["ghost_beaten"])] if "ghost_beaten" in final_infos[0] else None
        logger.record("ghost/track_seed", track_seed)
        logger.record("ghost/ghosts_recorded", len(run.ghosts))
    for j, car in enumerate(cars):
        logger.record(f"car_{j}/perf/env_sps", env_sps)
        logger.record(f"car_{j}/charts/episodic_return", car.ret)
        logger.record(f"car_{j}/charts/progress", float(final_infos[j].get("progress", 0.0)))
        if final_infos[j].get("lap_finished"):
            logger.record(f"car_{j}/charts/lap_time", int(final_infos[j]["finish_step"]))
        if won is not None:
            run.wins[j].append(float(won[j]))
            logger.record(f"car_{j}/charts/win_rate", float(np.mean(run.wins[j])))
    logger.record("charts/episode", run.counters["episode"])
    if racing:
        logger.record("charts/dead_zone", run.method.dead_zone_at(run.counters["episode"], args))


def log_updates(run: Run, j: int, updates_per_s: float) -> None:
    """Agent j's training burst after a race; a run whose agent had --max-nonfinite-updates faulty updates in a row
    is marked to end (with its checkpoint)."""
    agent, args = run.agents[j], run.args
    run.logger.record(f"car_{j}/perf/updates_per_s", updates_per_s)
    run.logger.record(f"car_{j}/perf/updates", agent.num_updates)
    run.logger.record(f"car_{j}/faults/nonfinite_updates", agent.nonfinite_updates)
    if agent.nonfinite_in_a_row >= args.max_nonfinite_updates:
        run.fault = (f"car_{j}: {agent.nonfinite_in_a_row} updates in a row had a non-finite loss or gradient"
                     f" (--max-nonfinite-updates {args.max_nonfinite_updates})")  # fmt: skip


def progress_callback(run: Run, j: int):
    """What train_agent calls after each update of agent j: the progress bar, and on a CPU the time of one update
    reported after the second (the first warms up)."""
    burst_start, steps = time.time(), run.args.train_steps_per_episode

    def on_update(done: int, seconds: float) -> None:
        if len(run.update_seconds) < 2:
            run.update_seconds.append(seconds)
            if len(run.update_seconds) == 2 and run.device.type == "cpu":
                report_update_time(run)
        if run.pbar is not None:
            rate = done / max(time.time() - burst_start, 1e-9)
            run.pbar.set_postfix_str(f"training car_{j}: {done}/{steps} updates, {rate:.2f} updates/s", refresh=True)

    return on_update


def report_update_time(run: Run) -> None:
    """Say how long one update takes on this CPU and what that means per race, as soon as it is known (at the paper's
    size within a minute or two of the start)."""
    args, n = run.args, len(run.agents)
    per_update = run.update_seconds[1]
    minutes = per_update * args.train_steps_per_episode * n / 60
    message = (f"On this CPU one update takes {per_update:.2f} s: {args.train_steps_per_episode} updates x {n}"
               f" agent(s) = {minutes:.1f} min of training per race.")  # fmt: skip
    if args.preset == "paper":
        script = os.path.basename(run.method.__file__)
        message += f" For a CPU-sized run: python {script} --preset cpu --stage single --seed 1 (README.md)"
    run.print(message)


def log_videos(run: Run, cars: list) -> None:
    """Each car's race so far beside the model's reconstruction and an open-loop imagination."""
    from utils.logger import log_video

    for j, (agent, car) in enumerate(zip(run.agents, cars)):
        obs, actions, _, _ = car.arrays()
        length = min(len(obs), run.args.video_length)
        first = np.zeros(length, dtype=bool)
        first[0] = True
        video = agent.video(obs[:length], actions[:length], first)
        log_video(run.logger, f"car_{j}/videos/real_reconstruction_imagination", video, run.counters["global_step"], 25)


def evaluate_and_keep_best(run: Run) -> None:
    """Evaluate on the held-out tracks, log it, print one line, keep best.pt (and eval_<race>.pt if asked)."""
    from utils import make_vec_env

    args, counters = run.args, run.counters
    if run.eval_envs is None:
        run.eval_envs = make_vec_env(args.env_id, 1, None, **env_kwargs(args, args.dead_zone_end))
    readings = drive_races(run.agents, args, run.eval_envs)
    returns, progress, abs_steer = readings["return"], readings["progress"], readings["abs_steer"]
    for j in range(len(run.agents)):
        run.logger.record(f"car_{j}/eval/episodic_return", float(returns[:, j].mean()))
        run.logger.record(f"car_{j}/eval/progress", float(progress[:, j].mean()))
        if args.env_id == "multi_car_racing":  # highway-env's action 0 is the acceleration, and it has no laps
            run.logger.record(f"car_{j}/eval/mean_abs_steer", float(abs_steer[:, j].mean()))
            run.logger.record(f"car_{j}/eval/speed", float(readings["speed"][:, j].mean()))  # racing, not cruising
            run.logger.record(f"car_{j}/eval/laps_finished", float(readings["lap_finished"][:, j].mean()))
            run.logger.record(f"car_{j}/eval/eliminated", float(readings["eliminated"][:, j].mean()))
    updates = run.agents[0].num_updates
    run.print(f"evaluation after race {counters['episode']} ({updates} updates, {counters['global_step']} env steps):"
              f" return {returns.mean():.1f}, progress {progress.mean():.2f}, |steer| {abs_steer.mean():.2f}"
              f" ({args.eval_policy}, {len(returns)} held-out tracks)")  # fmt: skip
    extra = checkpoint_extra(run)
    if args.eval_checkpoints:
        save_run_checkpoint(run, f"eval_{counters['episode']:06d}.pt", extra)
    if returns.mean() > counters["best_eval_return"]:
        counters["best_eval_return"] = float(returns.mean())
        save_run_checkpoint(run, "best.pt", extra)


def after_training(run: Run, cars: list, env_sps: float) -> None:
    """The end of a race's turn: video, evaluation, replay save, checkpoint, the row of progress.csv, progress bar."""
    args, counters = run.args, run.counters
    episode = counters["episode"]
    if run.fault is None:
        if args.video_every and episode % args.video_every == 0:
            log_videos(run, cars)
        if args.eval_every and episode % args.eval_every == 0:
            evaluate_and_keep_best(run)
        # The replay first, then latest.pt naming it: a kill between the two leaves the previous pair intact.
        if args.replay_save_every and episode % args.replay_save_every == 0:
            save_replays(run)
        if args.checkpoint_every and episode % args.checkpoint_every == 0:
            save_latest(run)
    run.check_budget()
    run.logger.record("charts/cpu_hours", run.cpu_seconds() / 3600)  # after the race's training and evaluation
    run.logger.dump(counters["global_step"])
    if run.pbar is not None:
        run.pbar.update(1)
        run.pbar.set_postfix_str(f"race {episode}: return {np.mean([c.ret for c in cars]):.1f}, "
                                 f"{env_sps:.0f} env steps/s, {run.agents[0].num_updates} updates")  # fmt: skip
