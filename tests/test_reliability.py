"""Reliability: bad input, crashes mid-run and numerical faults lose nothing.

Covers the dreamer scripts (both variants), race.py and plot.py: impossible arguments end with one line
before any work; a save killed halfway leaves the previous checkpoint; unreadable checkpoints get one-line
errors; a run killed mid-race and resumed ends exactly where the uninterrupted run ends; non-finite
losses or gradients skip the step and stop the run after --max-nonfinite-updates in a row; a replay that
cannot fit in memory is refused. (The env's bad-input fuzz test is tests/test_env_fuzz.py.)
Training runs use tiny networks, 30-step races and one torch thread, so each takes about a second.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import glob
import importlib
import io
import math
import os
import re
import subprocess
import sys
import types

import numpy as np
import pytest
import torch
import utils.checkpoint as ckpt
import utils.run as run_tools
from conftest import SCRIPTS, TINY, assert_same, random_batch, tiny_args

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RUN = dict(
    **TINY, max_steps=30, train_steps_per_episode=2, prefill_episodes=1, replay_capacity=500, eval_every=0,
    video_every=0, replay_save_every=1, torch_threads=1,
)  # fmt: skip


class Killed(BaseException):
    """Stands for a kill: nothing in the scripts catches it."""


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Tiny networks run fastest on one thread (two threads on a busy 2-core machine wait on each other);
    the rest of the suite keeps its own setting."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def flags(**kwargs) -> list[str]:
    return [part for key, value in kwargs.items() for part in (f"--{key.replace('_', '-')}", str(value))]


def assert_same_replays(a, b) -> None:
    """Two replay buffers hold the same episodes, step for step."""
    assert ckpt.saver_of(a).manifest() == ckpt.saver_of(b).manifest()
    for key in ("obs", "action", "reward", "is_first", "terminated"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)


def exit_message(script, argv) -> str:
    with pytest.raises(SystemExit) as exit_info:
        run_tools.cli(script, argv)
    text = str(exit_info.value.code)
    assert text.startswith(f"{script.__name__}.py: error: ") and "\n" not in text, text
    return text


# ------------------------------------------------------------------------------------------------
# 1. Arguments
# ------------------------------------------------------------------------------------------------
BAD_ARGUMENTS = [
    (["--num-agents", "0"], "--num-agents must be >= 1, got 0"),
    (["--batch-size", "0"], "--batch-size must be >= 1, got 0"),
    (["--seq-len", "1"], "--seq-len must be >= 2, got 1"),
    (["--batch-size", "2", "--seq-len", "4", "--imagination-starts", "9"],
     "--imagination-starts must be <= batch-size * seq-len = 8, got 9"),
    (["--model-lr", "-0.001"], "--model-lr must be > 0, got -0.001"),
    (["--critic-lr", "nan"], "--critic-lr must be a finite number, got nan"),
    (["--actor-lr", "0"], "--actor-lr must be > 0, got 0.0"),
    (["--env-id", "moon_buggy"],
     "--env-id must be one of ['highway-intersection', 'multi_car_racing'], got 'moon_buggy'"),
    (["--stage", "ghost"], "--stage ghost needs --checkpoint"),
    (["--tau", "-0.005"], "--tau must lie in (0, 1], got -0.005"),
    (["--gamma", "0"], "--gamma must lie in (0, 1], got 0.0"),
    (["--gamma", "1.01"], "--gamma must lie in (0, 1], got 1.01"),
    (["--lambda", "-0.5"], "--lambda must lie in [0, 1], got -0.5"),
    (["--entropy-coef", "-1"], "--entropy-coef must be >= 0, got -1.0"),
    (["--grad-clip", "inf"], "--grad-clip must be a finite number, got inf"),
    (["--replay-capacity", "40"], "--replay-capacity must be >= --seq-len (50), got 40"),
    (["--dead-zone-end", "0.2"], "--dead-zone-end must lie in [-1, 0], got 0.2"),
    (["--action-repeat", "0"], "--action-repeat must be >= 1, got 0"),
    (["--total-episodes", "0"], "--total-episodes must be >= 1, got 0"),
    (["--max-nonfinite-updates", "0"], "--max-nonfinite-updates must be >= 1, got 0"),
    (["--seed", "-3"], "--seed must lie in [0, 2**32), got -3"),
    (["--resume", "no/such/run"], "--resume must be a run directory with checkpoints/latest.pt or a checkpoint file"),
    (["--checkpoint", "no/such.pt"], "--checkpoint must be a checkpoint file, got 'no/such.pt'"),
    (["--fresh-replay"], "--fresh-replay applies to a run started from --checkpoint"),
]  # fmt: skip


@pytest.mark.parametrize("argv, message", BAD_ARGUMENTS, ids=[" ".join(a) for a, _ in BAD_ARGUMENTS])
def test_impossible_arguments_end_with_one_line_before_any_work(script, tmp_path, argv, message):
    text = exit_message(script, [*argv, "--runs-dir", str(tmp_path / "runs")])
    assert message in text
    assert not (tmp_path / "runs").exists()  # no run directory, nothing written


def test_validate_args_raises_value_error_naming_the_flag(script, tmp_path):
    run_tools.validate_args(script.Args(), script.LOG_SIGMA_RANGE)  # the defaults are valid
    with pytest.raises(ValueError, match=r"^--batch-size must be >= 1, got 0$"):
        run_tools.validate_args(script.Args(batch_size=0), script.LOG_SIGMA_RANGE)
    with pytest.raises(ValueError, match=r"^--decoder-min-log-sigma must lie in \[-5, 2\], got 3.0$"):
        run_tools.validate_args(script.Args(decoder_min_log_sigma=3.0), script.LOG_SIGMA_RANGE)
    for bad, message in [({"action_penalty": float("nan")}, "--action-penalty must be a finite number, got nan"),
                         ({"action_penalty": -1.0}, "--action-penalty must be >= 0, got -1.0"),
                         ({"entropy_target": float("inf")}, "--entropy-target must be a finite number, got inf"),
                         ({"entropy_lr": 0.0}, "--entropy-lr must be > 0, got 0.0")]:  # (optional floats too)
        with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
            run_tools.validate_args(script.Args(**bad), script.LOG_SIGMA_RANGE)
    with pytest.raises(ValueError, match="--tau"):  # main checks first, before it writes anything
        script.main(script.Args(tau=2.0, runs_dir=str(tmp_path / "runs")))
    assert not (tmp_path / "runs").exists()
    expected = f"{script.__name__}.py: error: --batch-size must be >= 1, got 0"
    assert exit_message(script, ["--batch-size", "0"]) == expected


def test_help_shows_each_flags_docstring_as_one_paragraph(monkeypatch, capsys):
    """tyro_cli: a field docstring wrapped over indented source lines reads as one paragraph in --help (tyro alone
    starts a help line at every source line); a blank line still separates paragraphs."""

    @dataclasses.dataclass
    class Args:
        speed: float = 1.0
        """how fast the car goes, in metres
        per second, before the
        dead zone (its flag
        --speed) and after"""
        mode: str = "a"
        """first paragraph

        second paragraph, then a list:
        - one
        - two"""

    monkeypatch.setenv("COLUMNS", "300")
    with pytest.raises(SystemExit):
        run_tools.tyro_cli(Args, ["--help"], "what the command does")
    text = capsys.readouterr().out
    assert "what the command does" in text
    assert "how fast the car goes, in metres per second, before the dead zone (its flag --speed) and after" in text
    lines = [line.strip(" │") for line in text.splitlines()]
    first = next(i for i, line in enumerate(lines) if "first paragraph" in line)
    assert lines[first].endswith("first paragraph") and lines[first + 1] == ""
    assert lines[first + 2] == "second paragraph, then a list:" and lines[first + 3].startswith("- one")


def test_the_command_line_prints_one_line_and_exits_1(tmp_path):
    result = subprocess.run(
        [sys.executable, "dreamer_lstm.py", "--batch-size", "0", "--runs-dir", str(tmp_path / "runs")],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == "dreamer_lstm.py: error: --batch-size must be >= 1, got 0"
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "runs").exists()


# ------------------------------------------------------------------------------------------------
# 2. Checkpoints: atomic writes, unreadable files, kill and resume
# ------------------------------------------------------------------------------------------------
def test_a_checkpoint_save_killed_halfway_leaves_the_previous_one(script, tmp_path, monkeypatch):
    args = script.Args(**TINY)
    agents = [script.Agent(args)]
    path = tmp_path / "checkpoints" / "latest.pt"
    counters = {"episode": 1, "global_step": 30, "best_eval_return": -math.inf}
    # The write order: the temporary file is fsynced, then renamed over latest.pt, then the directory fsynced.
    events, real_fsync, real_replace = [], os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))  # which file or directory
        real_fsync(fd)

    def replace(src, dst):
        events.append(("replace", str(src), str(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    ckpt.save_checkpoint(str(path), script.VARIANT, args, agents, counters)
    assert events == [("fsync", f"{path}.tmp"), ("replace", f"{path}.tmp", str(path)), ("fsync", str(path.parent))]
    before = path.read_bytes()

    real_save = torch.save

    def half_then_killed(obj, f, *a, **kw):
        buffer = io.BytesIO()
        real_save(obj, buffer, *a, **kw)
        f.write(buffer.getvalue()[: len(buffer.getvalue()) // 2])
        raise Killed

    monkeypatch.setattr(torch, "save", half_then_killed)
    agents[0].update(random_batch())  # something new to save
    with pytest.raises(Killed):
        ckpt.save_checkpoint(str(path), script.VARIANT, args, agents, {**counters, "episode": 2})
    monkeypatch.undo()
    assert path.read_bytes() == before  # the old checkpoint, whole
    assert script.load_checkpoint(str(path))["counters"]["episode"] == 1
    assert os.listdir(path.parent) == ["latest.pt"]  # and no temporary file left behind


def make_episode(length, episode_id, size=8):
    rng = np.random.default_rng(episode_id)
    terminated = np.zeros(length, bool)
    terminated[-1] = True
    obs = rng.integers(0, 256, (length, size, size, 3), dtype=np.uint8)
    action = rng.uniform(-1, 1, (length, 2)).astype(np.float32)
    return obs, action, rng.normal(size=length).astype(np.float32), terminated


def test_a_replay_save_killed_halfway_keeps_the_saved_replay(script, tmp_path, monkeypatch):
    directory = str(tmp_path / "replay_car_0")
    replay = script.Replay(capacity=50, image_size=8, chunk_size=16)
    for e in range(3):
        replay.add_episode(*make_episode(13, e))
    first = ckpt.save_replay(replay, directory)
    saved = {key: getattr(replay, key).copy() for key in ("obs", "action", "reward", "is_first", "terminated")}
    replay.add_episode(*make_episode(20, 7))  # wraps around: rewrites chunks that the first save holds

    real_savez, calls = np.savez_compressed, []

    def killed_on_second_file(f, **arrays):
        calls.append(1)
        if len(calls) == 2:
            f.write(b"PK\x03\x04 half a zip")
            raise Killed
        real_savez(f, **arrays)

    monkeypatch.setattr(np, "savez_compressed", killed_on_second_file)
    with pytest.raises(Killed):
        ckpt.save_replay(replay, directory)
    monkeypatch.undo()
    for manifest in (None, first):  # meta.npz, and the manifest a checkpoint would hold: both the first save
        loaded = script.Replay(capacity=50, image_size=8)
        ckpt.load_replay(loaded, directory, manifest)
        assert ckpt.saver_of(loaded).manifest() == first
        for key, value in saved.items():
            np.testing.assert_array_equal(getattr(loaded, key), value)
    second = ckpt.save_replay(replay, directory)  # a complete save; the first stays loadable until pruned
    loaded = script.Replay(capacity=50, image_size=8)
    ckpt.load_replay(loaded, directory, first)
    assert loaded.episodes == 3
    ckpt.prune_replay(directory, second)
    assert sorted(os.listdir(directory)) == sorted(second["files"] + ["meta.npz"])
    ckpt.load_replay(loaded, directory)
    np.testing.assert_array_equal(loaded.obs, replay.obs)
    assert loaded.episodes == 4


def test_unreadable_checkpoints_get_one_line_errors_naming_the_file(script, tmp_path):
    other = importlib.import_module(next(s for s in SCRIPTS if s != script.__name__))
    counters = {"episode": 1, "global_step": 30, "best_eval_return": 0.0}
    good = tmp_path / "good.pt"
    ckpt.save_checkpoint(str(good), script.VARIANT, script.Args(**TINY), [script.Agent(script.Args(**TINY))], counters)
    files = {"truncated": good.read_bytes()[: good.stat().st_size // 2], "text": b"not a checkpoint\n", "empty": b""}
    for name, content in files.items():
        (tmp_path / f"{name}.pt").write_bytes(content)
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    other_args = other.Args(**TINY)
    ckpt.save_checkpoint(str(tmp_path / "other.pt"), other.VARIANT, other_args, [other.Agent(other_args)], counters)
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    (tmp_path / "run" / "checkpoints" / "latest.pt").write_bytes(files["truncated"])
    expected = {
        "truncated.pt": "not a readable checkpoint", "text.pt": "not a readable checkpoint",
        "empty.pt": "not a readable checkpoint", "foreign.pt": "not a checkpoint of these scripts",
        "other.pt": f"holds a {other.VARIANT!r} agent, this script builds {script.VARIANT!r}",
    }  # fmt: skip
    runs = tmp_path / "runs"
    for name, reason in expected.items():
        path = str(tmp_path / name)
        for argv in (["--resume", path], ["--stage", "ghost", "--checkpoint", path]):
            text = exit_message(script, [*argv, "--runs-dir", str(runs)])
            assert f"{path}: {reason}" in text
    text = exit_message(script, ["--resume", str(tmp_path / "run"), "--runs-dir", str(runs)])  # a run directory
    assert f"{tmp_path / 'run' / 'checkpoints' / 'latest.pt'}: not a readable checkpoint" in text
    assert not runs.exists()


def last_row(run_dir) -> dict:
    with open(os.path.join(run_dir, "progress.csv")) as f:
        return list(csv.DictReader(f))[-1]


@pytest.mark.parametrize("amp", ["off", "on"])
def test_a_run_killed_mid_race_resumes_exactly(script, tmp_path, monkeypatch, capsys, amp):
    """Race stage, two agents: one run of 3 races; another killed while it trains after race 3, resumed from its
    race-2 checkpoint. Both end with the same counters, networks, optimisers, RNG states and replays. In float32
    and with bfloat16 updates (--amp on: auto's choice on a CPU with bfloat16 instructions)."""
    run = {**RUN, "amp": amp}
    whole = script.main(script.Args(stage="race", total_episodes=3, runs_dir=str(tmp_path / "a"), **run))
    assert "replay buffers: 2 x 500 steps x 12,302 B = 12.3 MB" in capsys.readouterr().out

    real_update, calls = script.Agent.update, []

    def update_then_killed(self, batch):
        calls.append(1)
        if len(calls) == 9:  # updates 1-4 follow race 1, 5-8 race 2: this is the first after race 3
            raise Killed
        return real_update(self, batch)

    monkeypatch.setattr(script.Agent, "update", update_then_killed)
    with pytest.raises(Killed):
        script.main(script.Args(stage="race", total_episodes=3, runs_dir=str(tmp_path / "b"), **run))
    monkeypatch.undo()
    (killed,) = glob.glob(str(tmp_path / "b" / "*"))
    assert script.load_checkpoint(f"{killed}/checkpoints/latest.pt")["counters"]["episode"] == 2
    script.main(script.Args(resume=killed, total_episodes=3, torch_threads=1))

    a = script.load_checkpoint(f"{whole}/checkpoints/latest.pt")
    b = script.load_checkpoint(f"{killed}/checkpoints/latest.pt")
    assert a["counters"] == b["counters"] and a["counters"]["episode"] == 3
    assert [s["num_updates"] for s in b["agents"]] == [6, 6]
    assert_same(a["agents"], b["agents"], "agents")  # networks, targets, optimisers: bit-exact
    assert_same(a["rng"], b["rng"], "rng")
    assert_same(a["extra"]["wins"], b["extra"]["wins"], "wins")
    for j in range(2):
        replays = []
        for run in (whole, killed):
            replay = script.Replay(RUN["replay_capacity"], RUN["image_size"])
            ckpt.load_replay(replay, f"{run}/checkpoints/replay_car_{j}")
            replays.append(replay)
            named = script.load_checkpoint(f"{run}/checkpoints/latest.pt")["extra"]["replays"][j]["files"]
            files = sorted(os.listdir(f"{run}/checkpoints/replay_car_{j}"))  # pruned: only what latest.pt names
            assert files == sorted([*named, "meta.npz"])
        assert_same_replays(*replays)
        assert replays[0].episodes == 3
    row_a, row_b = last_row(whole), last_row(killed)
    losses = [key for key in row_a if "/losses/" in key]
    assert losses and all(float(row_b[key]) == pytest.approx(float(row_a[key]), rel=1e-6) for key in losses)


# ------------------------------------------------------------------------------------------------
# 3. Numerical faults
# ------------------------------------------------------------------------------------------------
def test_a_nonfinite_loss_or_gradient_skips_that_step(script):
    torch.manual_seed(0)
    agent = script.Agent(script.Args(**TINY))
    agent.update(random_batch(seed=0))  # the optimisers have state
    before = copy.deepcopy(agent.state_dict())

    batch = random_batch(seed=1)
    batch["reward"][1, 3] = np.nan  # a NaN reward: the world model's loss is NaN, the behaviour losses are not
    metrics = agent.update(batch)
    after = agent.state_dict()
    assert math.isnan(metrics["reward"])
    assert_same(after["world_model"], before["world_model"], "world model")  # parameters and BatchNorm statistics
    assert_same(after["model_optimizer"], before["model_optimizer"], "model optimiser")
    for name in ("encoder", "representation", "transition"):  # no soft update toward an unchanged model either
        assert all(torch.equal(v, before["targets"][k]) for k, v in after["targets"].items() if k.startswith(name))
    assert not torch.equal(after["actor"]["net.net.0.weight"], before["actor"]["net.net.0.weight"])  # stepped
    assert (agent.nonfinite_updates, agent.nonfinite_in_a_row) == (1, 1)

    # A finite loss with a non-finite gradient: only the critic's step is skipped.
    before = copy.deepcopy(agent.state_dict())
    hook = agent.critic.net.net[0].weight.register_hook(lambda grad: torch.full_like(grad, float("nan")))
    metrics = agent.update(random_batch(seed=2))
    hook.remove()
    after = agent.state_dict()
    assert math.isfinite(metrics["critic"])
    assert_same(after["critic"], before["critic"], "critic")
    assert_same(after["critic_optimizer"], before["critic_optimizer"], "critic optimiser")
    critic_targets = [k for k in after["targets"] if k.startswith("critic.")]  # no soft update toward it either
    assert critic_targets and all(torch.equal(after["targets"][k], before["targets"][k]) for k in critic_targets)
    assert not torch.equal(after["world_model"]["decoder.fc.weight"], before["world_model"]["decoder.fc.weight"])
    assert (agent.nonfinite_updates, agent.nonfinite_in_a_row) == (2, 2)

    # The actor's: its parameters, optimiser and the running statistics its forward pass moved stay as they were.
    before = copy.deepcopy(agent.state_dict())
    hook = agent.actor.net.net[0].weight.register_hook(lambda grad: torch.full_like(grad, float("nan")))
    agent.update(random_batch(seed=3))
    hook.remove()
    after = agent.state_dict()
    assert any("running_mean" in k for k in after["actor"])  # (the statistics are there to be checked)
    assert_same(after["actor"], before["actor"], "actor")
    assert_same(after["actor_optimizer"], before["actor_optimizer"], "actor optimiser")
    assert not torch.equal(after["critic"]["net.net.0.weight"], before["critic"]["net.net.0.weight"])  # stepped
    assert (agent.nonfinite_updates, agent.nonfinite_in_a_row) == (3, 3)

    agent.update(random_batch(seed=4))  # a clean update ends the streak; the total stays
    assert (agent.nonfinite_updates, agent.nonfinite_in_a_row) == (3, 0)
    assert agent.state_dict()["nonfinite_updates"] == 3  # saved with the agent


def test_the_run_stops_after_max_nonfinite_updates_in_a_row(script, tmp_path, monkeypatch):
    real_sample = script.Replay.sample

    def sample_with_nan_reward(self, *args, **kwargs):
        batch = real_sample(self, *args, **kwargs)
        batch["reward"][0, 0] = np.nan
        return batch

    monkeypatch.setattr(script.Replay, "sample", sample_with_nan_reward)
    runs = tmp_path / "runs"
    settings = {**RUN, "train_steps_per_episode": 5, "max_nonfinite_updates": 3}
    argv = ["--stage", "single", "--total-episodes", "3", "--runs-dir", str(runs), *flags(**settings)]
    text = exit_message(script, argv)
    (run_dir,) = glob.glob(str(runs / "*"))
    latest = os.path.join(run_dir, "checkpoints", "latest.pt")
    assert "car_0: 3 updates in a row had a non-finite loss or gradient (--max-nonfinite-updates 3)" in text
    assert f"stopped after race 1 with the checkpoint {latest}" in text
    checkpoint = script.load_checkpoint(latest)
    assert checkpoint["counters"]["episode"] == 1  # stopped in the first training race ...
    agent = checkpoint["agents"][0]
    assert (agent["num_updates"], agent["nonfinite_updates"], agent["nonfinite_in_a_row"]) == (3, 3, 3)  # ... early
    assert agent["model_optimizer"]["state"] == {}  # the world model never took a step
    assert float(last_row(run_dir)["car_0/faults/nonfinite_updates"]) == 3


# ------------------------------------------------------------------------------------------------
# 4. Memory
# ------------------------------------------------------------------------------------------------
def test_a_replay_that_cannot_fit_in_memory_is_refused(script, tmp_path, capsys):
    assert script.Replay.bytes_per_step(96) == 96 * 96 * 3 + 4 * 2 + 4 + 1 + 1
    runs = tmp_path / "runs"
    text = exit_message(script, ["--replay-capacity", str(10**12), "--runs-dir", str(runs)])
    per_agent = 10**12 * script.Replay.bytes_per_step(96)
    assert f"--replay-capacity {10**12}: the replay buffers need 2 x {per_agent / 1e9:,.2f} GB =" in text
    assert "of memory is available" in text
    assert "replay buffers: 2 x 1,000,000,000,000 steps x 27,662 B" in capsys.readouterr().out
    assert not runs.exists()


def test_available_memory_reads_meminfo_or_falls_back(monkeypatch):
    available, source = run_tools.available_memory()
    assert available > 0 and ("MemAvailable" in source or "cgroup" in source)
    files = {"/proc/meminfo": "MemTotal: 9999 kB\nMemFree: 10 kB\nMemAvailable: 1000 kB\n"}

    def served(path, *args, **kwargs):  # the files of a machine made up here
        if path not in files:
            raise OSError(f"{path}: not here")
        return io.StringIO(files[path])

    monkeypatch.setattr(run_tools, "open", served, raising=False)
    assert run_tools.available_memory() == (1_024_000, "MemAvailable in /proc/meminfo")  # kB, and not MemTotal
    files |= {"/sys/fs/cgroup/memory.max": "500000\n", "/sys/fs/cgroup/memory.current": "100000\n"}
    assert run_tools.available_memory() == (400_000, "cgroup limit /sys/fs/cgroup/memory.max")  # the tighter
    files["/sys/fs/cgroup/memory.max"] = "5000000\n"  # a looser limit: meminfo's
    assert run_tools.available_memory() == (1_024_000, "MemAvailable in /proc/meminfo")
    files["/sys/fs/cgroup/memory.max"] = "max\n"  # no limit: meminfo's
    assert run_tools.available_memory() == (1_024_000, "MemAvailable in /proc/meminfo")

    def no_proc(path, *args, **kwargs):
        raise OSError(f"{path}: not here")

    monkeypatch.setattr(run_tools, "open", no_proc, raising=False)  # no /proc/meminfo, no cgroup files
    available, source = run_tools.available_memory()
    assert available > 0 and "sysconf" in source


# ------------------------------------------------------------------------------------------------
# race.py and plot.py
# ------------------------------------------------------------------------------------------------
TWO = ["--opponent", "pursuit", "--opponent", "pursuit"]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--opponent", "pursuit:nan", "--opponent", "pursuit"], "--opponent must be pursuit or pursuit:SPEED"),
        (["--opponent", "pursuit:inf", "--opponent", "pursuit"], "with a finite SPEED > 0"),
        ([*TWO, "--max-steps", "0"], "--max-steps must be >= 1, got 0"),
        ([*TWO, "--seed", "-1"], "--seed must be >= 0"),
        ([*TWO, "--races", "0"], "--races must be >= 1, got 0"),
        ([*TWO, "--train", "--episodes", "0"], "--episodes must be >= 1, got 0"),
    ],
)
def test_race_bad_arguments(argv, message, capsys):
    import race

    with pytest.raises(SystemExit) as exit_info:
        race.main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]


def test_race_out_must_be_a_directory(tmp_path, capsys):
    import race

    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit) as exit_info:
        race.main([*TWO, "--out", str(tmp_path / "file")])
    assert exit_info.value.code == 2
    assert f"--out '{tmp_path / 'file'}' exists and is not a directory" in capsys.readouterr().err
    assert (tmp_path / "file").read_text() == "x"


def test_an_acting_only_state_that_does_not_fit_and_a_wrong_agent_count_are_named_in_one_line(tmp_path):
    """An acting-only export whose world model lacks an acting part is one line naming the file and what is missing
    (a plain message, not a KeyError's quoted repr); a checkpoint whose agents do not match its own --num-agents is
    refused naming both counts."""
    lstm = importlib.import_module("dreamer_lstm")
    agent = lstm.Agent(lstm.Args(**TINY))
    state = ckpt.acting_state_dict(agent)
    state["world_model"] = {k: v for k, v in state["world_model"].items() if not k.startswith("encoder.")}
    with pytest.raises(ckpt.CheckpointError, match=r"^x\.pt: agent 0 does not fit the networks it names: acting-only "
                       r"state: missing \['encoder\."):  # fmt: skip
        ckpt.load_agent_state(lstm.Agent(lstm.Args(**TINY)), state, "x.pt", 0)
    run = types.SimpleNamespace(args=types.SimpleNamespace(num_agents=2))
    with pytest.raises(ckpt.CheckpointError, match=r"^y\.pt: holds 1 agent\(s\), its saved --num-agents is 2$"):
        run_tools.restore_run(run, {"agents": [state]}, "y.pt")


def test_race_checkpoint_that_builds_no_agent_is_one_line(tmp_path):
    import race

    lstm = importlib.import_module("dreamer_lstm")
    path = str(tmp_path / "mismatch.pt")
    agent = lstm.Agent(lstm.Args(**TINY))
    ckpt.save_checkpoint(path, "lstm", lstm.Args(**{**TINY, "cnn_depth": 8}), [agent], {"episode": 0})  # no fit
    with pytest.raises(SystemExit) as exit_info:
        race.main([path, "--opponent", "pursuit"])
    text = str(exit_info.value.code)
    assert text.startswith(f"race.py: {path}: agent 0 does not fit the networks it names") and "\n" not in text
    no_actor = types.SimpleNamespace(state_dict=lambda: {"world_model": {}})  # a saved agent without an actor
    ckpt.save_checkpoint(path, "lstm", lstm.Args(**TINY), [no_actor], {"episode": 0})
    with pytest.raises(SystemExit) as exit_info:
        race.main([path, "--opponent", "pursuit"])
    text = str(exit_info.value.code)
    assert text == f"race.py: {path}: agent 0 has no actor output layer to read its action size from (KeyError: " \
                   "'actor')"


def test_plot_bad_input(tmp_path, capsys):
    import plot

    run = tmp_path / "runs" / "multi_car_racing__lstm__1__1"
    run.mkdir(parents=True)
    (run / "events.out.tfevents.1").write_bytes(b"garbage")
    (run / "config.json").write_text("{not json")
    with pytest.raises(SystemExit) as exit_info:
        plot.main([str(tmp_path / "runs"), "--out", str(tmp_path / "figures")])
    assert str(exit_info.value.code).startswith(f"plot.py: {run / 'config.json'}: not a readable run config")
    bad = [
        (["--sigma", "nan"], "--sigma must be a finite number >= 0"),
        (["--sigma", "-1"], "--sigma must be a finite number >= 0"),
        (["--sigma", "abc"], "--sigma"),  # tyro's own message for a value that is no float names the option
        (["--out", str(run / "config.json")], "is not a directory"),
        (["--head-to-head", str(tmp_path / "missing.csv")], "is not a file"),
        (["--head-to-head"], "--head-to-head needs at least one CSV"),
    ]
    for argv, message in bad:
        with pytest.raises(SystemExit) as exit_info:
            plot.main([str(tmp_path / "runs"), *argv])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err, argv


# --- signals: pygame (moviepy's import, highway-env's viewer) must not swallow Ctrl-C or kill ----------------
SIGNAL_PROBES = {
    "video logging": "from utils.logger import check_video_support; check_video_support()",
    "highway-env": "from envs.highway import HighwayIntersection; env = HighwayIntersection(); env.reset(seed=0)",
}


@pytest.mark.parametrize("probe", sorted(SIGNAL_PROBES))
def test_sigterm_still_ends_the_process_after_pygame_starts(probe):
    """SDL installs SIGINT/SIGTERM handlers that turn the signal into a quit event unless SDL_NO_SIGNAL_HANDLERS
    is set; then `kill` (or a cluster's pre-emption) would leave a training run going."""
    code = f"import os, signal, time\n{SIGNAL_PROBES[probe]}\nos.kill(os.getpid(), signal.SIGTERM)\ntime.sleep(5)\n"
    env = {k: v for k, v in os.environ.items() if k != "SDL_NO_SIGNAL_HANDLERS"}
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    result = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, timeout=120)
    assert result.returncode == -15, result.stderr.decode()[-500:]


# A real process killed with SIGKILL at a chosen moment: the n-th env step of race 2 (a prefill race), the
# n-th update (inside a training burst), or the n-th atomic write after its data is written and before its rename
# (inside a checkpoint or replay save). The script itself is unchanged; only the call is intercepted.
KILL_AT = r"""
import importlib, os, signal, sys
script = importlib.import_module(sys.argv[1])
where, n, argv = sys.argv[2], int(sys.argv[3]), sys.argv[4:]
calls = [0]

def kill_on_call(owner, name):
    real = getattr(owner, name)
    def wrapper(*args, **kwargs):
        calls[0] += 1
        if calls[0] == n:
            os.kill(os.getpid(), signal.SIGKILL)
        return real(*args, **kwargs)
    setattr(owner, name, wrapper)

if where == "step":  # the n-th env step of race 2 (a prefill race here)
    real_after_training = script.after_training
    def after_training(run, *args):
        real_after_training(run, *args)
        if run.counters["episode"] == 1:
            kill_on_call(type(run.envs), "step")
    script.after_training = after_training
elif where == "update":
    kill_on_call(script.Agent, "update")
else:  # "write": the temporary file is complete, the rename has not happened
    import utils.checkpoint
    real_write = utils.checkpoint.atomic_write
    def write_then_die(path, write):
        calls[0] += 1
        if calls[0] != n:
            return real_write(path, write)
        def write_and_die(f):
            write(f)
            f.flush()
            print(f"killed while writing {os.path.basename(path)}", file=sys.stderr, flush=True)
            os.kill(os.getpid(), signal.SIGKILL)
        return real_write(path, write_and_die)
    utils.checkpoint.atomic_write = write_then_die
import utils.run
utils.run.cli(script, argv)
"""
KILL_RUN = dict(
    TINY, max_steps=30, train_steps_per_episode=3, prefill_episodes=2, replay_capacity=500, eval_every=2,
    eval_episodes=1, video_every=0, total_episodes=5, torch_threads=1,
)  # fmt: skip


def run_script(argv: list[str], kill: tuple[str, int] | None = None, module: str = "dreamer_lstm"):
    """Run the script's command line in a fresh process (optionally killed with SIGKILL at `kill`)."""
    code = ["-c", KILL_AT, module, *map(str, kill)] if kill else [os.path.join(ROOT, f"{module}.py")]
    env = {**os.environ, "PYTHONPATH": ROOT}
    command = [sys.executable, *code, *argv]
    return subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The reference: the same tiny run, never killed."""
    runs = tmp_path_factory.mktemp("whole")
    done = run_script([*flags(**KILL_RUN), "--stage", "single", "--runs-dir", str(runs)])
    assert done.returncode == 0, done.stderr[-2000:]
    (run_dir,) = glob.glob(str(runs / "*"))
    return run_dir


@pytest.mark.parametrize(
    "kill, writing",
    [(("step", 5), None), (("update", 5), None), (("write", 5), "chunk_"), (("write", 10), "latest.pt")],
    ids=["during-prefill", "during-a-training-burst", "during-a-replay-save", "during-a-checkpoint-save"],
)  # fmt: skip
def test_a_run_killed_with_sigkill_resumes_with_nothing_but_resume(uninterrupted, tmp_path, kill, writing):
    """kill -9 anywhere, then `--resume <run>` alone: the run keeps every setting it was started with (5 races,
    one torch thread), acts randomly through the rest of its prefill, and ends with the counters, update count
    and replay of the run that was never killed."""
    killed = run_script([*flags(**KILL_RUN), "--stage", "single", "--runs-dir", str(tmp_path)], kill)
    assert killed.returncode == -9, killed.stderr[-2000:]
    if writing:  # the write that was cut is the one named
        assert f"killed while writing {writing}" in killed.stderr
    (run_dir,) = glob.glob(str(tmp_path / "*"))
    if not os.path.exists(os.path.join(run_dir, "checkpoints", "latest.pt")):
        pytest.fail(f"killed at {kill} before the first checkpoint: the kill point is too early")
    resumed = run_script(["--resume", run_dir])
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "resume: --" not in resumed.stdout  # nothing overridden
    assert "XDG_RUNTIME_DIR" not in resumed.stderr + killed.stderr  # SDL's display probing is quiet
    assert "evaluation after race 4" in resumed.stdout and "| charts/" not in resumed.stdout  # one line, no table
    assert "On this CPU one update takes" in resumed.stdout + killed.stdout  # after the second update
    script = importlib.import_module("dreamer_lstm")
    a = script.load_checkpoint(os.path.join(uninterrupted, "checkpoints", "latest.pt"))
    b = script.load_checkpoint(os.path.join(run_dir, "checkpoints", "latest.pt"))
    assert b["counters"] == a["counters"] and b["counters"]["episode"] == 5
    assert b["args"] == {**a["args"], "runs_dir": str(tmp_path), "resume": run_dir}
    assert (b["args"]["total_episodes"], b["args"]["torch_threads"]) == (5, 1)
    assert b["agents"][0]["num_updates"] == a["agents"][0]["num_updates"] == 3 * (5 - 2 + 1)
    assert_same(a["agents"], b["agents"], "agents")  # the same networks: the prefill stayed random, the RNG exact
    assert b["extra"]["replays"][0]["total_steps"] == a["extra"]["replays"][0]["total_steps"]
    replays = []
    for run in (uninterrupted, run_dir):
        replays.append(script.Replay(KILL_RUN["replay_capacity"], KILL_RUN["image_size"]))
        ckpt.load_replay(replays[-1], os.path.join(run, "checkpoints", "replay_car_0"))
    assert_same_replays(*replays)  # the same episodes, step for step


def test_an_explicit_flag_on_resume_overrides_and_says_so(uninterrupted, tmp_path):
    """`--resume <run> --total-episodes 6` extends the finished 5-race run by one race, and prints the change;
    a setting that fixes the networks or the replay cannot change, and a checkpoint outside a run is refused."""
    import shutil

    run_dir = shutil.copytree(uninterrupted, tmp_path / "run")
    extended = run_script(["--resume", str(run_dir), "--total-episodes", "6"])
    assert extended.returncode == 0, extended.stderr[-2000:]
    assert "resume: --total-episodes 5 -> 6" in extended.stdout
    checkpoint = importlib.import_module("dreamer_lstm").load_checkpoint(str(run_dir / "checkpoints" / "latest.pt"))
    assert checkpoint["counters"]["episode"] == 6 and checkpoint["args"]["total_episodes"] == 6
    assert checkpoint["args"]["torch_threads"] == 1  # not passed: kept
    for name, value in [("--deter-size", "32"), ("--replay-capacity", "700")]:  # (the saved replay holds 500 steps)
        refused = run_script(["--resume", str(run_dir), name, value])
        assert refused.returncode == 1 and f"{name} cannot change in a resumed run" in refused.stderr
    # a checkpoint outside a run's checkpoints/ has no run directory to go on in: refused, nothing written beside it
    copy = tmp_path / "copies" / "latest.pt"
    copy.parent.mkdir()
    shutil.copy(run_dir / "checkpoints" / "latest.pt", copy)
    refused = run_script(["--resume", str(copy)])
    assert refused.returncode == 1 and f"--resume {copy}: not in a run's checkpoints/ folder" in refused.stderr
    assert sorted(os.listdir(tmp_path)) == ["copies", "run"] and os.listdir(copy.parent) == ["latest.pt"]
    link = tmp_path / "links" / "latest.pt"  # a link to a run's checkpoint resumes that run, in its own directory
    link.parent.mkdir()
    os.symlink(run_dir / "checkpoints" / "latest.pt", link)
    followed = run_script(["--resume", str(link)])
    assert followed.returncode == 0 and f"run directory: {run_dir} " in followed.stdout, followed.stderr[-2000:]
    assert os.listdir(link.parent) == ["latest.pt"]


def test_saved_arguments_are_read_back_new_flags_default_and_removed_ones_are_named_with_their_values(capsys):
    """args_from_checkpoint: a checkpoint written before a flag existed gets the flag's default; one written with a
    flag this code no longer has is read without it, and the note names the flag and its saved value (a run trained
    with another value would go on differently); a saved argument the Args cannot take is a one-line error."""

    @dataclasses.dataclass
    class Args:
        seed: int = 1
        gamma: float = 0.99
        new_flag: int = 7

    saved = {"args": {"seed": 3, "gamma": 0.9, "old_noise": 0.9, "old_mode": "fast"}}
    args = ckpt.args_from_checkpoint(Args, saved, "run/latest.pt", gamma=0.95)
    assert (args.seed, args.gamma, args.new_flag) == (3, 0.95, 7)  # an override wins, the new flag keeps 7
    assert capsys.readouterr().out == ("note: run/latest.pt has arguments this script does not know (ignored): "
                                       "old_mode='fast', old_noise=0.9\n")  # fmt: skip
    with pytest.raises(ckpt.CheckpointError, match=r"^run/latest.pt: its arguments do not fit this script: "):
        ckpt.args_from_checkpoint(Args, {"args": {"seed": 3}}, "run/latest.pt", unknown_override=1)


def test_saved_amp_keeps_the_rule_its_run_computed_with(script, monkeypatch):
    """--amp as read back from a checkpoint, on a CPU with bfloat16 instructions (where auto now means on): a run
    saves what auto resolved to (kept); auto was saved when it meant bfloat16 on CUDA only (cuda: float32 on the
    CPU); no --amp at all, before it existed (off: float32 everywhere). An agent built from such a checkpoint
    (race.py --train continues one) computes its updates as that run did."""
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True)
    base = dataclasses.asdict(script.Args(seed=3))
    for saved, read in (("on", "on"), ("off", "off"), ("auto", "cuda"), (None, "off")):
        args = {k: v for k, v in base.items() if k != "amp"} | ({} if saved is None else {"amp": saved})
        assert ckpt.args_from_checkpoint(script.Args, {"args": args}, "run/latest.pt").amp == read
    old_run = os.path.join(ROOT, "tests", "fixtures", f"reference_{script.VARIANT}", "checkpoints", "latest.pt")
    assert torch.load(old_run, weights_only=True)["args"]["amp"] == "auto"
    assert script.agent_from_checkpoint(old_run).amp is False
    assert script.Agent(tiny_args(script, amp="auto")).amp is True  # (a new agent at auto: on, on such a CPU)


@pytest.mark.parametrize("name", sorted(ckpt.RETIRED_ARGS))
def test_a_retired_option_loads_quietly_at_its_neutral_value_and_another_value_is_not_resumed(script, name, capsys):
    """A run saved before an option was retired loads and resumes when it used the value the code now behaves as,
    with no note; one trained with another value still loads for acting, with a note naming the option, its value
    and the last commit that runs it, but is not resumed. The real Args of both scripts no longer have the option."""
    assert name not in {field.name for field in dataclasses.fields(script.Args)}
    neutral, commit, notebook = ckpt.RETIRED_ARGS[name]
    assert os.path.isfile(os.path.join(ROOT, notebook))
    args = script.Args(seed=3)
    for value in (neutral, None):
        saved = {"args": {**dataclasses.asdict(args), name: value}}
        assert ckpt.args_from_checkpoint(script.Args, saved, "run/latest.pt").seed == 3
        assert run_tools.resumed_args(script.Args, saved, "run/latest.pt", args, ()).seed == 3
        assert capsys.readouterr().out == ""
    saved = {"args": {**dataclasses.asdict(args), name: 0.5}}
    assert ckpt.args_from_checkpoint(script.Args, saved, "run/latest.pt").seed == 3
    note = f"{name}=0.5 (removed after its screen, {notebook}; `git checkout {commit}` runs it)"
    assert capsys.readouterr().out == f"note: run/latest.pt has arguments this script does not know (ignored): {note}\n"
    refusal = f"run/latest.pt: cannot be resumed by this code: trained with {note}"
    with pytest.raises(ckpt.CheckpointError, match=re.escape(refusal)):
        run_tools.resumed_args(script.Args, saved, "run/latest.pt", args, ())
