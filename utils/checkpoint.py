"""Checkpoints and replay saves of the dreamer scripts: atomic, resumable, loaded with ``weights_only=True``.

A *method* below is a dreamer script's module (``dreamer_lstm`` or ``dreamer_gru``): what these functions need of it
is ``VARIANT`` (the name written into its checkpoints), ``Args`` (its hyperparameter dataclass) and ``Agent``, whose
``state_dict()`` and ``load_state_dict()`` are ``agent_state_dict`` and ``load_agent`` (below). These read the Agent's
attributes by name: ``world_model`` (acting uses its ``ACTING_PARTS``: ``encoder``, ``recurrent_input``, ``cell``,
``representation``), ``actor``, ``critic``, ``targets``, the three optimisers, ``log_alpha`` and
``alpha_optimizer`` (with --entropy-target), ``return_scale``, ``num_updates``, ``nonfinite_updates``,
``nonfinite_in_a_row``, ``acting_only`` and ``args``' learning rates: a part renamed in a script is renamed here
too (else an export drives without it: test_acting_only_export_acts_exactly_like_its_checkpoint fails). The format:

* a checkpoint is a dict ``{"variant", "args" (dict), "counters", "agents" (one state dict per agent), "rng",
  "extra"}`` saved with ``torch.save`` and read back with ``weights_only=True`` (tensors, numbers, strings, lists
  and dicts only); an acting-only export has ``"kind": "policy"`` and no ``"rng"`` or ``"extra"``;
* a replay save is a directory of compressed ``chunk_<c>_<total steps>.npz`` files and ``meta.npz``, its manifest
  (counters and chunk files). A save writes only the chunks changed since the last save, each to a new file, so
  a checkpoint naming an earlier manifest still loads until ``prune_replay``.

Every file is written atomically (``atomic_write``): a kill at any moment leaves the old file or the new one.
``read_checkpoint`` reads a file of either variant (by the script that wrote it), for race.py, evaluate.py and the
benchmarks.
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import math
import os
import random

import numpy as np
import torch

CHECKPOINT_KEYS = ("variant", "args", "counters", "agents")  # and "rng", except in an acting-only export
# Options removed after their screens rejected them: the value the code now behaves as, the last commit that has the
# option and the notebook with its screen. A checkpoint saved with that value loads as before; one trained with
# another value loads with a note (acting, evaluating) but cannot be resumed (retired_args).
RETIRED_ARGS = {
    "reward_nll_beta": (0.0, "345bb5f", "docs/lab/learning_screens.md"),
    "action_noise_corr": (0.0, "345bb5f", "docs/lab/screens.md"),
    "lr_anneal": (0.0, "2790f96", "docs/lab/screens.md"),
    "terminal_weight": (1.0, "1d13134", "docs/lab/screens.md"),
}
REPLAY_FIELDS = ("obs", "action", "reward", "is_first", "terminated")  # the arrays of a Replay, one row per step


class UsageError(ValueError):
    """Bad input (an argument, a checkpoint file, a memory budget), found before any work starts; one-line message."""


class CheckpointError(UsageError):
    """A missing, truncated or foreign checkpoint (or replay) file; the message names the file."""


class WrongVariant(CheckpointError):
    """A checkpoint of the other variant's script (read_checkpoint then asks that script)."""


def first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


# --- Atomic files ----------------------------------------------------------------------------
def atomic_write(path: str, write) -> None:
    """Write a file so that a kill at any moment leaves the old file or the new one, never a part: write(f) into a
    temporary file beside it, flush and fsync it, rename it over `path` (os.replace), fsync the directory."""
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    tmp = path + ".tmp"
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    with contextlib.suppress(OSError):  # the rename itself reaches the disk (not possible on every platform)
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_npz(path: str, **arrays) -> None:
    atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


def atomic_torch_save(obj, path: str) -> None:
    atomic_write(path, lambda f: torch.save(obj, f))


# --- Random streams --------------------------------------------------------------------------
def rng_state() -> dict:
    """python, numpy and torch RNG states as tensors (restorable with set_rng_state)."""
    np_state = np.random.get_state()
    py_state = random.getstate()
    state = {
        "torch": torch.get_rng_state(),
        "numpy_key": torch.from_numpy(np_state[1].astype(np.int64)),
        "numpy_meta": torch.tensor([np_state[2], np_state[3]], dtype=torch.int64),
        "numpy_gauss": torch.tensor(np_state[4], dtype=torch.float64),
        "python": torch.tensor(py_state[1], dtype=torch.int64),
        "python_gauss": torch.tensor(float("nan") if py_state[2] is None else py_state[2], dtype=torch.float64),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.stack(torch.cuda.get_rng_state_all())
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    meta = state["numpy_meta"].tolist()
    key = state["numpy_key"].numpy().astype(np.uint32)
    np.random.set_state(("MT19937", key, meta[0], meta[1], float(state["numpy_gauss"])))
    gauss = float(state["python_gauss"])
    random.setstate((3, tuple(state["python"].tolist()), None if math.isnan(gauss) else gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(list(state["cuda"]))


# --- Checkpoints -----------------------------------------------------------------------------
def save_checkpoint(path: str, variant: str, args, agents: list, counters: dict, extra: dict | None = None) -> None:
    """The one checkpoint format: variant, args (dict), counters, every agent's networks and optimisers, RNG states."""
    checkpoint = {
        "variant": variant,
        "args": dataclasses.asdict(args),
        "counters": dict(counters),
        "agents": [agent.state_dict() for agent in agents],
        "rng": rng_state(),
        "extra": extra or {},
    }
    atomic_torch_save(checkpoint, path)


def load_checkpoint(path: str, variant: str, map_location="cpu", training: bool = False, mmap: bool = False) -> dict:
    """Load a checkpoint (or an acting-only export) of the script that writes `variant` with weights_only=True; a
    missing, truncated or foreign file (or one of another variant, or an export when `training`) raises
    CheckpointError, whose one-line message names the file. `mmap`: map the file's tensors instead of reading them
    (for a look at its settings: a paper-size checkpoint's weights are not copied)."""
    if os.path.isdir(path):  # (--resume takes a run directory; the readers of a saved agent want its file)
        raise CheckpointError(f"{path}: a directory, not a checkpoint file (a run's are checkpoints/best.pt, the best "
                              "evaluated policy, and checkpoints/latest.pt)")
    if not os.path.isfile(path):
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except Exception as e:  # truncated zip, not a torch file, a pickle weights_only refuses, ...
        reason = first_line(e)
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or not a torch file): {reason}") from None
    export = isinstance(checkpoint, dict) and checkpoint.get("kind") == "policy"
    keys = CHECKPOINT_KEYS if export else (*CHECKPOINT_KEYS, "rng")
    if not isinstance(checkpoint, dict) or not all(key in checkpoint for key in keys):
        raise CheckpointError(f"{path}: not a checkpoint of these scripts (needs entries {', '.join(keys)})")
    if checkpoint["variant"] != variant:
        raise WrongVariant(f"{path}: holds a {checkpoint['variant']!r} agent, this script builds {variant!r}")
    if not isinstance(checkpoint["agents"], list) or not checkpoint["agents"]:
        raise CheckpointError(f"{path}: holds no agents")
    if training and checkpoint.get("kind") == "policy":
        raise CheckpointError(f"{path}: is an acting-only export (no critic, optimisers or replay): it cannot train")
    return checkpoint


def retired_args(checkpoint: dict) -> dict[str, str]:
    """The retired options (RETIRED_ARGS) a checkpoint was trained with at another value than the one the code now
    behaves as: {name: what to say of it}. Such a run would go on differently, so it is not resumed."""
    saved = checkpoint["args"] if isinstance(checkpoint["args"], dict) else {}
    return {
        name: f"{name}={saved[name]!r} (removed after its screen, {notebook}; `git checkout {commit}` runs it)"
        for name, (neutral, commit, notebook) in RETIRED_ARGS.items()
        if saved.get(name) not in (neutral, None)  # None: saved before the option existed
    }


def args_from_checkpoint(args_class, checkpoint: dict, path: str, **overrides):
    """The Args a checkpoint was trained with (new flags keep their defaults, flags removed since are dropped: a note
    names each with its saved value, since a run trained with another value than the one the code now behaves as
    would go on differently; a retired option at its neutral value goes without a note). --amp: a run saves the
    on or off it resolved (utils/run.py resolve_amp); a checkpoint holding auto was saved when auto meant bfloat16
    on CUDA only and goes on with that rule (cuda), one without --amp was saved before it existed, in float32 (off)."""
    names = {field.name for field in dataclasses.fields(args_class)}
    saved = checkpoint["args"] if isinstance(checkpoint["args"], dict) else {}
    if "amp" in names and saved.get("amp", "auto") == "auto":
        saved = {**saved, "amp": "cuda" if "amp" in saved else "off"}
    retired = retired_args(checkpoint)
    dropped = sorted(set(saved) - names - (set(RETIRED_ARGS) - set(retired)))
    if dropped:
        listed = ", ".join(retired.get(name, f"{name}={saved[name]!r}") for name in dropped)
        print(f"note: {path} has arguments this script does not know (ignored): {listed}")
    try:
        return args_class(**{**{k: v for k, v in saved.items() if k in names}, **overrides})
    except TypeError as e:
        raise CheckpointError(f"{path}: its arguments do not fit this script: {first_line(e)}") from None


# --- An agent's state ----------------------------------------------------------------------
# What an Agent of either script saves: its networks, targets and optimisers by these attribute names, and with
# --entropy-target its log alpha and alpha's optimiser; the return scale and the update counters.
AGENT_PARTS = ("world_model", "actor", "critic", "targets", "model_optimizer", "actor_optimizer", "critic_optimizer")
ACTING_PARTS = ("encoder.", "recurrent_input.", "cell.", "representation.")  # the world model's share of acting


def agent_state_dict(agent) -> dict:
    """Everything an Agent learns and counts (Agent.state_dict): a resumed agent continues as if never stopped."""
    return {name: getattr(agent, name).state_dict() for name in AGENT_PARTS} | {
        "return_scale": agent.return_scale.clone(), "num_updates": agent.num_updates,
        "nonfinite_updates": agent.nonfinite_updates, "nonfinite_in_a_row": agent.nonfinite_in_a_row,
    } | ({} if agent.log_alpha is None else {
        "log_alpha": agent.log_alpha.detach().clone(), "alpha_optimizer": agent.alpha_optimizer.state_dict(),
    })  # fmt: skip


def acting_state_dict(agent) -> dict:
    """What acting needs and nothing else: encoder, posterior, recurrent core (with its input layer), actor.
    No decoder, reward, continue, prior or critic, no targets, optimisers or replay (an exported policy)."""
    world_model = {k: v for k, v in agent.world_model.state_dict().items() if k.startswith(ACTING_PARTS)}
    return {"world_model": world_model, "actor": agent.actor.state_dict(), "num_updates": agent.num_updates}


def set_learning_rates(agent) -> None:
    """Every optimiser's learning rate: its flag's value (--model-lr, --actor-lr, --critic-lr, --entropy-lr). Set
    after a state is loaded, whose optimisers hold the rates they were saved with, so that a resumed run's or a
    --checkpoint run's flags are the rates it learns at."""
    args = agent.args
    pairs = [(agent.model_optimizer, args.model_lr), (agent.actor_optimizer, args.actor_lr),
             (agent.critic_optimizer, args.critic_lr)]  # fmt: skip
    if agent.log_alpha is not None:
        pairs.append((agent.alpha_optimizer, args.entropy_lr))
    for optimizer, lr in pairs:
        for group in optimizer.param_groups:
            group["lr"] = lr


def load_agent(agent, state: dict) -> None:
    """Agent.load_state_dict: a full state (agent_state_dict; alpha starts at --entropy-coef if the state has none)
    or an acting-only export (acting_state_dict: the agent drives, it cannot learn). The optimisers then learn at
    the flags' rates (set_learning_rates)."""
    if "critic" not in state:
        missing, unexpected = agent.world_model.load_state_dict(state["world_model"], strict=False)
        missing = [k for k in missing if k.startswith(ACTING_PARTS)]
        if missing or unexpected:
            raise ValueError(f"acting-only state: missing {missing[:3]}, unexpected {unexpected[:3]}")
        agent.actor.load_state_dict(state["actor"])
        agent.num_updates, agent.acting_only = int(state["num_updates"]), True
        return
    for name in AGENT_PARTS:
        getattr(agent, name).load_state_dict(state[name])
    if "return_scale" in state:
        agent.return_scale.copy_(state["return_scale"])
    if agent.log_alpha is not None and "log_alpha" in state:
        with torch.no_grad():
            agent.log_alpha.copy_(state["log_alpha"])
        agent.alpha_optimizer.load_state_dict(state["alpha_optimizer"])
    agent.num_updates = int(state["num_updates"])
    agent.nonfinite_updates = int(state.get("nonfinite_updates", 0))
    agent.nonfinite_in_a_row = int(state.get("nonfinite_in_a_row", 0))
    set_learning_rates(agent)


def load_agent_state(agent, state, path: str, index: int) -> None:
    """agent.load_state_dict, with a one-line CheckpointError naming the file when the state does not fit."""
    try:
        agent.load_state_dict(state)
    except (RuntimeError, KeyError, TypeError, ValueError, AttributeError) as e:
        raise CheckpointError(f"{path}: agent {index} does not fit the networks it names: {first_line(e)}") from None


def action_dim_of(agent_state: dict, path: str, index: int) -> int:
    """The action size a saved agent was built for: its actor's output layer (the last ``.bias`` of its ``actor``
    state) gives a mean and a sigma per action. A state without one is a CheckpointError naming the file."""
    try:
        last = max((k for k in agent_state["actor"] if k.endswith(".bias")), key=lambda k: int(k.split(".")[2]))
        return int(agent_state["actor"][last].shape[0]) // 2
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
        raise CheckpointError(f"{path}: agent {index} has no actor output layer to read its action size from "
                              f"({type(e).__name__}: {first_line(e)})") from None  # fmt: skip


VARIANT_SCRIPTS = {"lstm": "dreamer_lstm", "gru": "dreamer_gru"}  # the script that builds each variant's agent


def read_checkpoint(path: str, device="cpu", training: bool = False) -> tuple:
    """(script module, checkpoint) of a checkpoint or acting-only export of either variant, read by the script of its
    variant (``load_checkpoint``, with ``weights_only=True``); every failure is a one-line CheckpointError naming the
    file."""
    import importlib

    for name in VARIANT_SCRIPTS.values():
        script = importlib.import_module(name)
        try:
            return script, script.load_checkpoint(path, device, training)
        except WrongVariant:
            continue  # the other script's file
    raise CheckpointError(f"{path}: unknown variant; known: {sorted(VARIANT_SCRIPTS)}")


def agent_from_checkpoint(method, path: str, index: int = 0, device="cpu", checkpoint: dict | None = None):
    """Build agent `index` of a checkpoint of `method` with the sizes it was trained with (race.py, evaluate.py);
    `checkpoint`: the file at `path` already loaded on `device` (load_checkpoint, read_checkpoint), not read again."""
    if checkpoint is None:
        checkpoint = load_checkpoint(path, method.VARIANT, map_location=device)
    if not 0 <= index < len(checkpoint["agents"]):
        raise CheckpointError(f"{path}: has {len(checkpoint['agents'])} agent(s), asked for agent {index}")
    state = checkpoint["agents"][index]
    args = args_from_checkpoint(method.Args, checkpoint, path)
    agent = method.Agent(args, action_dim_of(state, path, index), device=device)
    load_agent_state(agent, state, path, index)
    return agent


def export_policy(method, checkpoint_path: str, out: str, index: int = 0) -> int:
    """Write agent `index` of a checkpoint as an acting-only export (acting_state_dict, with its args and
    counters): what race.py and evaluate.py need to drive, small enough for git. Returns its size in bytes."""
    checkpoint = load_checkpoint(checkpoint_path, method.VARIANT)
    agent = agent_from_checkpoint(method, checkpoint_path, index, checkpoint=checkpoint)
    export = {
        "variant": method.VARIANT, "kind": "policy", "args": checkpoint["args"], "counters": checkpoint["counters"],
        "agents": [acting_state_dict(agent)],
    }  # fmt: skip
    atomic_torch_save(export, out)
    return os.path.getsize(out)


def resolve_checkpoint(path: str) -> str:
    """A run directory means its checkpoints/latest.pt."""
    return os.path.join(path, "checkpoints", "latest.pt") if os.path.isdir(path) else path


def ghost_to_tensors(trajectory: dict) -> dict:
    return {k: torch.as_tensor(np.asarray(v)) if isinstance(v, np.ndarray) else v for k, v in trajectory.items()}


def ghost_from_tensors(trajectory: dict) -> dict:
    return {k: v.numpy() if isinstance(v, torch.Tensor) else v for k, v in trajectory.items()}


# --- Replay saves ----------------------------------------------------------------------------
class ReplaySaver:
    """Saves one Replay (a ring buffer with ``capacity, chunk_size, next_index, size, total_steps, episodes`` and the
    arrays REPLAY_FIELDS) as chunked compressed .npz files, writing only the chunks changed since its last save to
    the same directory: the steps added since then, which the buffer's counters locate."""

    def __init__(self, replay):
        self.replay = replay
        self.directory: str | None = None
        self.files: dict[int, str] = {}  # chunk -> its file in directory
        self.saved_steps = 0  # replay.total_steps at the last save or load

    def changed_chunks(self) -> list[int]:
        """Chunks holding a step added since the last save (all filled chunks for a new directory)."""
        replay = self.replay
        num_chunks = math.ceil(replay.size / replay.chunk_size)  # filled steps: [0, size) until the buffer wraps
        added = min(replay.total_steps - self.saved_steps, replay.capacity)
        idx = (replay.next_index - added + np.arange(added)) % replay.capacity
        return sorted(c for c in np.unique(idx // replay.chunk_size).tolist() if c < num_chunks)

    def save(self, directory: str) -> dict:
        """Save to `directory`; returns the manifest (counters and chunk files) that `load_replay` takes.

        Each changed chunk goes to a new file (named by total_steps), then meta.npz with the manifest. Files of
        earlier saves stay until `prune_replay`, so a checkpoint holding an earlier manifest still loads."""
        replay = self.replay
        os.makedirs(directory, exist_ok=True)
        if self.directory != directory:
            self.files, changed = {}, range(math.ceil(replay.size / replay.chunk_size))
        else:
            changed = self.changed_chunks()
        for c in changed:
            name = f"chunk_{c:05d}_{replay.total_steps:012d}.npz"
            part = slice(c * replay.chunk_size, min(replay.size, (c + 1) * replay.chunk_size))
            atomic_npz(os.path.join(directory, name), **{key: getattr(replay, key)[part] for key in REPLAY_FIELDS})
            self.files[c] = name
        manifest = self.manifest()
        meta = {k: np.asarray(v, dtype=str) if k == "files" else np.asarray(v) for k, v in manifest.items()}
        atomic_npz(os.path.join(directory, "meta.npz"), **meta)
        self.directory, self.saved_steps = directory, replay.total_steps
        return manifest

    def load(self, directory: str, manifest: dict | None = None) -> None:
        """Restore a save: `manifest` (as a checkpoint holds it) or else the directory's meta.npz (the newest save)."""
        replay = self.replay
        if manifest is None:
            with np.load(os.path.join(directory, "meta.npz")) as meta:
                manifest = {k: meta[k].tolist() for k in meta.files}
        if int(manifest["capacity"]) != replay.capacity:
            raise ValueError(f"replay in {directory} has capacity {manifest['capacity']}, this buffer "
                             f"{replay.capacity}")  # fmt: skip
        chunk_size = int(manifest["chunk_size"])
        if "files" in manifest:
            files = list(manifest["files"])
        else:  # the layout before chunk files were versioned
            files = [f"chunk_{c:05d}.npz" for c in range(manifest["num_chunks"])]
        for c, name in enumerate(files):
            with np.load(os.path.join(directory, name)) as chunk:
                start = c * chunk_size
                for key in REPLAY_FIELDS:
                    getattr(replay, key)[start : start + len(chunk[key])] = chunk[key]
        replay.next_index, replay.size = int(manifest["next_index"]), int(manifest["size"])
        replay.total_steps, replay.episodes = int(manifest["total_steps"]), int(manifest["episodes"])
        replay.chunk_size = chunk_size
        self.files, self.directory, self.saved_steps = dict(enumerate(files)), directory, replay.total_steps

    def manifest(self) -> dict:
        """What the last save holds, in plain types (a checkpoint names it): counters and chunk files."""
        replay = self.replay
        return {
            "capacity": replay.capacity, "chunk_size": replay.chunk_size, "next_index": replay.next_index,
            "size": replay.size, "total_steps": replay.total_steps, "episodes": replay.episodes,
            "files": [self.files[c] for c in range(len(self.files))],
        }  # fmt: skip


def save_replay(replay, directory: str) -> dict:
    """Save `replay` to `directory` (only what changed since its last save there); returns the manifest."""
    return saver_of(replay).save(directory)


def load_replay(replay, directory: str, manifest: dict | None = None) -> None:
    """Restore `replay` from a save in `directory` (as `manifest` names it, else the newest)."""
    saver_of(replay).load(directory, manifest)


def saver_of(replay) -> ReplaySaver:
    """The ReplaySaver that remembers what was saved of `replay` (made on first use)."""
    if getattr(replay, "saver", None) is None:
        replay.saver = ReplaySaver(replay)
    return replay.saver


def prune_replay(directory: str, keep: dict) -> None:
    """Delete the chunk files (and leftover temporary files) of `directory` that manifest `keep` does not name."""
    keep_files = set(keep["files"])
    for path in glob.glob(os.path.join(directory, "chunk_*.npz*")):
        if os.path.basename(path) not in keep_files:
            with contextlib.suppress(OSError):
                os.remove(path)


def replay_dir_of(path: str, index: int) -> str:
    """The replay of agent `index` saved beside a checkpoint: ``<stem>_replay_car_<index>`` (race.py --train) or
    ``replay_car_<index>`` (a training run's ``checkpoints/``)."""
    own = f"{os.path.splitext(path)[0]}_replay_car_{index}"
    return own if os.path.isdir(own) else os.path.join(os.path.dirname(os.path.abspath(path)), f"replay_car_{index}")


def restore_replay(replay, directory: str, manifest: dict | None, races: int) -> dict | None:
    """Resume: load an agent's replay as the checkpoint names it (else the newest save in `directory`), say what
    it lacks, and return the manifest loaded (None: nothing saved, the replay starts empty)."""
    if manifest is not None and not all(os.path.isfile(os.path.join(directory, f)) for f in manifest["files"]):
        print(f"note: {directory} no longer holds the replay save the checkpoint names; loading its newest save")
        manifest = None
    if manifest is None and not os.path.isfile(os.path.join(directory, "meta.npz")):
        print(f"note: no replay saved in {directory}: it starts empty")
        return None
    try:
        load_replay(replay, directory, manifest)
    except Exception as e:  # a chunk file damaged outside this program (the writes themselves are atomic)
        raise CheckpointError(f"{directory}: replay not readable: {first_line(e)}") from None
    if replay.episodes < races:
        print(f"note: {directory} was saved {races - replay.episodes} race(s) before the checkpoint"
              " (--replay-save-every): the transitions of those races are not restored")  # fmt: skip
    return saver_of(replay).manifest()
