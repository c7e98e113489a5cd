"""race.py: Wilson intervals, races with a known winner, checkpoint errors."""

import importlib
import json
import math
import os
import types

import pytest
import torch
import utils.checkpoint as ckpt
from conftest import TINY_RUN

import race


def test_wilson_interval_against_published_values():
    # Wilson 95% intervals as tabulated (e.g. Newcombe 1998, Table I): 7/10 and 0/10, 15/148
    lo, hi = race.wilson_interval(7, 10)
    assert (round(lo, 4), round(hi, 4)) == (0.3968, 0.8922)
    lo, hi = race.wilson_interval(0, 10)
    assert lo == 0.0 and round(hi, 4) == 0.2775
    lo, hi = race.wilson_interval(15, 148)
    assert (round(lo, 4), round(hi, 4)) == (0.0624, 0.1605)


def test_schedule_rotates_the_grid_on_each_track():
    plans = [race.schedule(1, r, 2) for r in range(4)]
    assert plans[0][0] == plans[1][0] != plans[2][0] == plans[3][0]
    assert [p[1] for p in plans] == [[0, 1], [1, 0], [0, 1], [1, 0]]


def test_faster_pursuit_driver_wins_every_race(tmp_path):
    rows = race.main(
        ["--opponent", "pursuit:70", "--opponent", "pursuit:40", "--races", "4", "--max-steps", "3000",
         "--out", str(tmp_path)]
    )  # fmt: skip
    fast, slow = rows
    assert fast["wins"] == 4 and slow["wins"] == 0
    z = 1.959963984540054  # the two-sided 95% normal quantile; Wilson at p = 1: [n / (n + z^2), 1], at p = 0 the mirror
    assert (fast["win_rate_ci_low"], fast["win_rate_ci_high"]) == pytest.approx((4 / (4 + z * z), 1.0))
    assert (slow["win_rate_ci_low"], slow["win_rate_ci_high"]) == pytest.approx((0.0, z * z / (4 + z * z)))
    assert fast["mean_finish_step"] < slow["mean_finish_step"]
    assert fast["mean_progress"] == slow["mean_progress"] == 1.0
    assert json.loads((tmp_path / "results.json").read_text())[0]["wins"] == 4
    assert (tmp_path / "results.csv").read_text().startswith("racer,races,wins")
    assert (tmp_path / "race.mp4").stat().st_size > 10_000


def test_truncated_and_foreign_checkpoints_get_one_line_errors(tmp_path):
    foreign = tmp_path / "foreign.pt"
    import torch

    torch.save({"weights": torch.zeros(3)}, foreign)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(foreign.read_bytes()[:40])
    for path, message in [
        (foreign, "not a checkpoint of these scripts"),
        (truncated, "not a readable checkpoint"),
        (tmp_path / "missing.pt", "no such checkpoint file"),
    ]:
        with pytest.raises(SystemExit) as exit_info:
            race.main([str(path), "--opponent", "pursuit"])
        text = str(exit_info.value)
        assert str(path) in text and message in text and "\n" not in text


def test_an_agent_the_checkpoint_does_not_hold_gets_one_line():
    with pytest.raises(SystemExit) as exit_info:
        race.main(["pretrained/gru_cpu.pt:1", "--opponent", "pursuit"])  # an export holds agent 0 only
    assert str(exit_info.value).endswith("pretrained/gru_cpu.pt: has 1 agent(s), asked for agent 1")


def test_bad_arguments(capsys):
    for argv, message in [
        (["--opponent", "pursuit"], "need at least two racers"),  # one racer
        (["--opponent", "pursuit:fast", "--opponent", "pursuit"], "--opponent must be pursuit or pursuit:SPEED"),
        (["x.pt", "--train", "--out", "here"], "--out is where a race's results go; --train writes its run"),
    ]:
        with pytest.raises(SystemExit) as exit_info:
            race.main(argv)
        assert exit_info.value.code == 2
        assert message in capsys.readouterr().err
    assert math.isclose(race.wilson_interval(0, 0)[1], 1.0)


@pytest.fixture(scope="module")
def tiny_checkpoints(tmp_path_factory):
    """A best.pt of each variant from a 1-race tiny single-stage run."""
    import importlib

    tiny = dict(TINY_RUN)
    paths = {}
    for variant in ("lstm", "gru"):
        script = importlib.import_module(f"dreamer_{variant}")
        root = tmp_path_factory.mktemp(variant)
        run_dir = script.main(script.Args(stage="single", runs_dir=str(root), **tiny))
        paths[variant] = f"{run_dir}/checkpoints/best.pt"
    return paths


def test_race_of_saved_agents_of_both_variants(tiny_checkpoints, tmp_path):
    rows = race.main(
        [tiny_checkpoints["lstm"], tiny_checkpoints["gru"], "--races", "2", "--max-steps", "30", "--no-video",
         "--out", str(tmp_path)]
    )  # fmt: skip
    runs = [os.path.basename(os.path.dirname(os.path.dirname(tiny_checkpoints[v]))) for v in ("lstm", "gru")]
    assert [r["racer"] for r in rows] == [f"lstm:{runs[0]}/best.pt:0", f"gru:{runs[1]}/best.pt:0"]
    assert all(r["races"] == 2 for r in rows) and sum(r["wins"] for r in rows) <= 2


def test_an_export_outside_a_run_is_named_by_its_folder(tiny_checkpoints, tmp_path):
    shipped = tmp_path / "pretrained"
    shipped.mkdir()
    ckpt.export_policy(importlib.import_module("dreamer_lstm"), tiny_checkpoints["lstm"], str(shipped / "lstm_tiny.pt"))
    rows = race.main([str(shipped / "lstm_tiny.pt"), "--opponent", "pursuit:70", "--races", "2", "--max-steps", "30",
                      "--no-video", "--out", str(tmp_path / "races")])  # fmt: skip
    assert [r["racer"] for r in rows] == ["lstm:pretrained/lstm_tiny.pt:0", "pursuit@70"]


def test_tiny_train_run_logs_per_agent_win_rates(tiny_checkpoints, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    race.main(
        [tiny_checkpoints["lstm"], tiny_checkpoints["gru"], "--train", "--episodes", "2", "--train-steps", "1",
         "--max-steps", "30", "--runs-dir", str(tmp_path)]
    )  # fmt: skip
    (run_dir,) = list(tmp_path.iterdir())
    acc = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    for racer in ("racer_0_lstm", "racer_1_gru"):
        assert f"{racer}/charts/win_rate" in tags and f"{racer}/charts/episodic_return" in tags
        assert f"{racer}/losses/actor" in tags  # it kept learning
        assert len(acc.Scalars(f"{racer}/charts/win_rate")) == 2
    rates = [acc.Scalars(f"{racer}/charts/win_rate")[-1].value for racer in ("racer_0_lstm", "racer_1_gru")]
    assert all(rate in (0.0, 0.5, 1.0) for rate in rates) and sum(rates) <= 1.0  # 2 races: no lap, one winner at most
    for i, variant in enumerate(("lstm", "gru")):
        path = str(run_dir / "checkpoints" / f"racer_{i}.pt")
        script, checkpoint = ckpt.read_checkpoint(path)
        started = ckpt.read_checkpoint(tiny_checkpoints[variant])[1]["counters"]
        assert checkpoint["counters"]["episode"] == started["episode"] and script.VARIANT == variant  # its training
        assert checkpoint["counters"]["race_episodes"] == 2 and 2 <= checkpoint["counters"]["race_env_steps"] <= 2 * 30
        # its replay is saved beside it (named by the checkpoint) and a later sitting continues from both
        manifest = checkpoint["extra"]["replays"][0]
        assert ckpt.replay_dir_of(path, 0) == str(run_dir / "checkpoints" / f"racer_{i}_replay_car_0")
        replay = script.Replay(manifest["capacity"], 64)
        ckpt.load_replay(replay, ckpt.replay_dir_of(path, 0), manifest)
        first = script.Replay(500, 64)
        ckpt.load_replay(first, os.path.join(os.path.dirname(tiny_checkpoints[variant]), "replay_car_0"))
        assert replay.episodes == first.episodes + 2 and checkpoint["agents"][0]["num_updates"] == 1 + 2
    again = tmp_path / "again"
    race.main(
        [str(run_dir / "checkpoints" / "racer_0.pt"), str(run_dir / "checkpoints" / "racer_1.pt"), "--train",
         "--episodes", "1", "--train-steps", "1", "--max-steps", "30", "--runs-dir", str(again)]
    )  # fmt: skip
    (run_dir2,) = list(again.iterdir())
    script, checkpoint = ckpt.read_checkpoint(str(run_dir2 / "checkpoints" / "racer_0.pt"))
    assert checkpoint["agents"][0]["num_updates"] == 1 + 2 + 1  # continued, not restarted
    assert checkpoint["extra"]["replays"][0]["episodes"] == first.episodes + 3  # with the whole replay
    first_sitting = ckpt.read_checkpoint(str(run_dir / "checkpoints" / "racer_0.pt"))[1]["counters"]
    assert checkpoint["counters"]["race_episodes"] == 3  # env steps counted on from the first sitting's
    # one more race of at most --max-steps 30 (a count of this sitting alone would be below the first's two races)
    assert 0 < checkpoint["counters"]["race_env_steps"] - first_sitting["race_env_steps"] <= 30
    # plot.py: one race-stage curve per variant, the two sittings joined on the race count (1, 2, then 3)
    import plot

    groups = plot.group_runs(plot.load_runs(str(tmp_path)))
    assert set(groups) == {("lstm", "race"), ("gru", "race")}
    for (variant, _), runs in groups.items():
        ((races, values),) = runs[0].scalars["charts/episodic_return"]
        assert len(runs) == 1 and races.tolist() == [1.0, 2.0, 3.0] and runs[0].x_label == "races"


def test_dreamer_racer_decides_every_action_repeat_steps_and_records_summed_rewards(tiny_checkpoints):
    """A racer acts at its training rate: one decision per action_repeat env steps, one transition per decision;
    the pursuit driver beside it decides every step."""
    racer, pursuit = race.DreamerRacer(tiny_checkpoints["lstm"], "cpu", "deterministic"), race.PursuitRacer(60.0)
    racer.action_repeat = 3
    decisions, act = [], racer.agent.act

    def counting_act(obs, state, is_first, policy="stochastic"):
        decisions.append(bool(is_first[0]))
        return act(obs, state, is_first, policy)

    racer.agent.act = counting_act
    envs = race.make_env(race.Args(max_steps=31), [racer, pursuit])
    result = race.run_race(envs, [racer, pursuit], seed=3, grid=[0, 1])
    steps = result.final_infos[0]["step"]  # env steps car_0 raced
    assert steps > 3
    assert decisions == [True] + [False] * (math.ceil(steps / 3) - 1)  # is_first only at the race's first decision
    obs, actions, rewards, terminated = result.episodes[0].arrays()
    assert len(obs) == 1 + math.ceil(steps / 3)  # the first frame, then one frame per decision
    assert rewards.sum() == pytest.approx(result.returns[0], abs=1e-4)
    assert len(result.episodes[1].obs) == 1 + result.final_infos[1]["step"]  # the pursuit driver: every step


def test_train_continues_with_the_replay_saved_beside_the_checkpoint(tiny_checkpoints, tmp_path, capsys):
    import glob
    import os

    import numpy as np

    replay_dir = os.path.join(os.path.dirname(tiny_checkpoints["gru"]), "replay_car_0")
    with np.load(os.path.join(replay_dir, "meta.npz")) as meta:
        saved_steps = int(meta["size"])
    assert saved_steps > 0
    args = [tiny_checkpoints["gru"], "--opponent", "pursuit", "--train", "--episodes", "1", "--train-steps", "1",
            "--max-steps", "30"]  # fmt: skip
    race.main([*args, "--runs-dir", str(tmp_path / "kept")])
    assert f"continues with the replay in {replay_dir} ({saved_steps:,} steps)" in capsys.readouterr().out
    race.main([*args, "--runs-dir", str(tmp_path / "fresh"), "--fresh-replay"])
    assert "continues with the replay" not in capsys.readouterr().out
    sizes = {}  # the replay each run saved after its race: the kept one holds the saved steps and the race's
    for kind in ("kept", "fresh"):
        (meta_path,) = glob.glob(str(tmp_path / kind / "*" / "checkpoints" / "racer_0_replay_car_0" / "meta.npz"))
        with np.load(meta_path) as meta:
            sizes[kind] = int(meta["size"])
    assert sizes["fresh"] > 0 and sizes["kept"] == saved_steps + sizes["fresh"]


def test_the_same_train_command_trains_the_same_agents(tiny_checkpoints, tmp_path):
    """Head-to-head training is reproducible whatever ran before it in the process: the replay batches come from
    numpy's stream, which train() seeds from the seed and the races done, as it seeds torch's. (And it trains: the
    weights moved from the checkpoint's by the 2 updates.)"""
    import numpy as np
    import torch

    def flat(agent):
        return torch.cat([t.flatten().float() for net in ("world_model", "actor", "critic")
                          for t in agent[net].values()])  # fmt: skip

    start = ckpt.read_checkpoint(tiny_checkpoints["lstm"])[1]["agents"][0]
    weights = []
    for k, noise in enumerate((1, 2)):
        np.random.seed(noise)  # whatever the process drew before (a Ray worker, an earlier interval)
        np.random.rand(noise)
        runs_dir = tmp_path / f"run{k}"
        race.main([tiny_checkpoints["lstm"], tiny_checkpoints["gru"], "--train", "--episodes", "1",
                   "--train-steps", "2", "--max-steps", "30", "--runs-dir", str(runs_dir)])  # fmt: skip
        (run_dir,) = list(runs_dir.iterdir())
        agent = ckpt.read_checkpoint(str(run_dir / "checkpoints" / "racer_0.pt"))[1]["agents"][0]
        assert agent["num_updates"] == start["num_updates"] + 2
        weights.append(flat(agent))
    assert weights[0].numel() > 1000 and torch.equal(weights[0], weights[1])
    assert not torch.equal(weights[0], flat(start))


def test_racers_are_saved_as_a_pair_a_kill_while_saving_leaves_the_previous_pair(tmp_path, monkeypatch):
    """save_racers writes every racer's replay and a pending checkpoint before it replaces any saved checkpoint,
    so a kill (here: while racer 1's checkpoint is written, after racer 0's) leaves both racers as they were after
    the same race; a save that completes leaves no pending file and both racers at the new race."""
    written = []

    def save_replay(replay, directory):
        written.append(("replay", os.path.basename(directory)))
        return {"files": []}

    def save_checkpoint(path, variant, args, agents, counters, extra):
        torch.save({"counters": counters, "extra": extra}, path)
        written.append(("checkpoint", os.path.basename(path)))

    def prune_replay(directory, manifest):
        written.append(("prune", os.path.basename(directory)))

    for name, stand_in in (("save_replay", save_replay), ("save_checkpoint", save_checkpoint),
                           ("prune_replay", prune_replay)):  # fmt: skip
        monkeypatch.setattr(race.saved, name, stand_in)

    class Replay:
        pass

    rename = os.replace

    def replace(src, dst):
        rename(src, dst)
        written.append(("replace", os.path.basename(dst)))

    monkeypatch.setattr(race.os, "replace", replace)
    racer = types.SimpleNamespace(variant="lstm", args=None, agent=None, counters={"race_episodes": 50})
    learning = {0: (racer, Replay()), 1: (racer, Replay())}
    race.save_racers(learning, str(tmp_path), races=1, env_steps=10)
    saved = [torch.load(tmp_path / f"racer_{i}.pt")["counters"]["race_episodes"] for i in (0, 1)]
    assert saved == [51, 51] and not list(tmp_path.glob("*.pending"))
    # every replay and pending checkpoint is written before any checkpoint is replaced, and all are replaced before
    # any replay is pruned
    assert [kind for kind, _ in written] == ["replay", "checkpoint", "replay", "checkpoint", "replace", "replace",
                                             "prune", "prune"]  # fmt: skip

    def killed_at_racer_1(path, *rest):
        if "racer_1" in path:
            raise KeyboardInterrupt("killed")
        save_checkpoint(path, *rest)

    monkeypatch.setattr(race.saved, "save_checkpoint", killed_at_racer_1)  # a kill while the pair is being written
    with pytest.raises(KeyboardInterrupt):
        race.save_racers(learning, str(tmp_path), races=2, env_steps=20)
    saved = [torch.load(tmp_path / f"racer_{i}.pt")["counters"]["race_episodes"] for i in (0, 1)]
    assert saved == [51, 51]  # the previous pair, whole: racer 0's new checkpoint waits as a pending file
