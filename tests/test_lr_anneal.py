"""The learning rates: a loaded state learns at its flags' rates, and --lr-anneal takes every rate linearly to 0 over
the last share of the run's budget (episodes, updates since the run's start, or CPU time), through pauses and
resumes."""

from __future__ import annotations

import dataclasses
import glob
import os
import types

import pytest
import utils.run as run_tools
from conftest import TINY, assert_same, tiny_args

# A tiny single-car run of 4 races, one update after each (the prefill race is 1 race: updates start after it).
RUN = dict(
    **TINY, max_steps=30, train_steps_per_episode=1, prefill_episodes=1, replay_capacity=500, eval_every=0,
    video_every=0, replay_save_every=1, torch_threads=1, total_episodes=10**9, total_updates=4, stage="single",
)  # fmt: skip


def rates(agent) -> dict[str, float]:
    optimisers = {"model": agent.model_optimizer, "actor": agent.actor_optimizer, "critic": agent.critic_optimizer}
    if agent.log_alpha is not None:
        optimisers["alpha"] = agent.alpha_optimizer
    return {name: [group["lr"] for group in o.param_groups] for name, o in optimisers.items()}


def test_lr_scale_is_one_until_the_last_share_of_the_budget_then_falls_linearly_to_zero(script):
    off = tiny_args(script)
    assert [script.lr_scale(off, spent) for spent in (0.0, 0.5, 0.99, 1.0, 1.5)] == [1.0] * 5  # the paper's
    quarter = tiny_args(script, lr_anneal=0.25)
    expected = {0.0: 1.0, 0.5: 1.0, 0.75: 1.0, 0.8125: 0.75, 0.875: 0.5, 0.9375: 0.25, 1.0: 0.0, 1.2: 0.0}
    for spent, scale in expected.items():
        assert script.lr_scale(quarter, spent) == pytest.approx(scale), spent
    whole = tiny_args(script, lr_anneal=1.0)  # SB3's linear schedule: from the start
    assert [script.lr_scale(whole, s) for s in (0.0, 0.25, 0.5, 1.0)] == pytest.approx([1.0, 0.75, 0.5, 0.0])


def test_a_loaded_state_learns_at_its_flags_rates_not_at_those_its_optimisers_were_saved_with(script):
    """A resumed run's --actor-lr etc. (and a --checkpoint run's) are the rates it learns at: Adam's own
    load_state_dict would bring back the saved ones."""
    saved = script.Agent(tiny_args(script, entropy_target=0.0), action_dim=2)
    saved.set_learning_rates(0.5)  # e.g. saved in the middle of an annealed run
    flags = dict(model_lr=3e-4, actor_lr=5e-5, critic_lr=2e-4, entropy_lr=2e-3)
    loaded = script.Agent(tiny_args(script, entropy_target=0.0, **flags), action_dim=2)
    loaded.load_state_dict(saved.state_dict())
    assert rates(loaded) == {"model": [3e-4], "actor": [5e-5], "critic": [2e-4], "alpha": [2e-3]}
    assert rates(saved) == {"model": [3e-4], "actor": [5e-5], "critic": [3e-4], "alpha": [5e-4]}  # 0.5 x defaults
    loaded.set_learning_rates(0.25)
    assert rates(loaded) == pytest.approx({"model": [7.5e-5], "actor": [1.25e-5], "critic": [5e-5], "alpha": [5e-4]})


@pytest.mark.parametrize(
    "limits, counters, updates, cpu_seconds, spent",
    [
        (dict(total_episodes=1000), {"episode": 251}, 99, 5.0, 0.25),  # races before the one just ended
        (dict(total_episodes=1000, total_updates=1000), {"episode": 10, "start_updates": 600}, 800, 0.0, 0.5),
        (dict(total_episodes=1000, total_updates=1000), {"episode": 10}, 800, 0.0, 0.8),  # a run from scratch
        (dict(total_episodes=1000, cpu_hours_limit=2.0), {"episode": 10}, 5, 5400.0, 0.75),  # CPU time
        (dict(total_episodes=10, pause_at_updates=6), {"episode": 2}, 5, 0.0, 0.1),  # a pause is not a budget
    ],
)
def test_budget_spent_is_the_largest_share_of_a_limit_counted_from_the_runs_start(limits, counters, updates,
                                                                                    cpu_seconds, spent):
    args = types.SimpleNamespace(**{"total_updates": 0, "cpu_hours_limit": 0.0, "pause_at_updates": 0, **limits})
    agents = [types.SimpleNamespace(num_updates=updates), types.SimpleNamespace(num_updates=updates + 3)]
    run = types.SimpleNamespace(args=args, counters=counters, agents=agents, cpu_checked=cpu_seconds)
    assert run_tools.Run.budget_spent(run) == pytest.approx(spent)


def test_an_annealed_run_ends_at_the_last_scale_and_a_pause_is_not_the_budgets_end(script, tmp_path):
    """--lr-anneal 1.0 over --total-updates 4: the races' updates run at 1, 3/4, 1/2, 1/4 of every rate (logged as
    charts/lr_scale). A run paused at 2 updates (--pause-at-updates, as experiment.py's trials) and resumed ends
    bit-exact where the run without the pause ends."""
    from test_dreamer import read_events

    whole = script.main(script.Args(runs_dir=str(tmp_path / "a"), lr_anneal=1.0, **RUN))
    scalars, _ = read_events(whole)
    assert [value for _, value in scalars["charts/lr_scale"]] == pytest.approx([1.0, 0.75, 0.5, 0.25])
    end = script.load_checkpoint(f"{whole}/checkpoints/latest.pt")
    assert end["agents"][0]["num_updates"] == 4
    actor_groups = end["agents"][0]["actor_optimizer"]["param_groups"]
    assert actor_groups[0]["lr"] == pytest.approx(0.25 * script.Args().actor_lr)

    script.main(script.Args(runs_dir=str(tmp_path / "b"), lr_anneal=1.0, pause_at_updates=2, **RUN))
    (paused,) = glob.glob(str(tmp_path / "b" / "*"))
    assert script.load_checkpoint(f"{paused}/checkpoints/latest.pt")["agents"][0]["num_updates"] == 2
    script.main(script.Args(resume=paused, pause_at_updates=0), {"pause_at_updates"})
    resumed = script.load_checkpoint(f"{paused}/checkpoints/latest.pt")
    assert_same(end["agents"], resumed["agents"], "agents")  # networks and optimisers, their rates included
    assert end["counters"] == resumed["counters"]
    scalars, _ = read_events(paused)
    assert [value for _, value in scalars["charts/lr_scale"]] == pytest.approx([1.0, 0.75, 0.5, 0.25])


def test_lr_anneal_outside_zero_to_one_is_refused(script, tmp_path):
    for value in (-0.1, 1.5):
        with pytest.raises(run_tools.UsageError, match="--lr-anneal must lie in"):
            script.main(script.Args(runs_dir=str(tmp_path), lr_anneal=value, **RUN))


def logged_scales(run_dir) -> list[float]:
    from test_dreamer import read_events

    scalars, _ = read_events(run_dir)
    return [value for _, value in scalars["charts/lr_scale"]]


def test_an_episode_budget_anneals_over_the_races_before_each_rounds_updates(script, tmp_path):
    """--total-episodes 5 and one prefill race: updates follow races 1..5, at 1 - (races before that one) / 5."""
    run_dir = script.main(script.Args(runs_dir=str(tmp_path), lr_anneal=1.0, **{**RUN, "total_episodes": 5,
                                                                               "total_updates": 0}))  # fmt: skip
    assert logged_scales(run_dir) == pytest.approx([1.0, 0.8, 0.6, 0.4, 0.2])


def test_a_cpu_budget_anneals_with_the_cpu_time_found_at_the_end_of_each_race(script, tmp_path, monkeypatch):
    """--cpu-hours-limit: the share is the process CPU time check_budget read at the end of the race before (here
    0.1 h per race finished), over the limit of 0.45 h; F = 0.5 anneals from 0.225 h on. The run stops once a race
    ends past the limit (race 5, at 0.5 h)."""
    monkeypatch.setattr(run_tools.Run, "cpu_seconds", lambda self: 0.1 * 3600 * self.counters["episode"])
    args = {**RUN, "total_updates": 0, "cpu_hours_limit": 0.45}
    run_dir = script.main(script.Args(runs_dir=str(tmp_path), lr_anneal=0.5, **args))
    shares = [0.0, 0.1 / 0.45, 0.2 / 0.45, 0.3 / 0.45, 0.4 / 0.45]  # before the updates after races 1..5
    assert logged_scales(run_dir) == pytest.approx([min(1.0, (1 - s) / 0.5) for s in shares])
    assert logged_scales(run_dir)[-2:] == pytest.approx([2 / 3, 2 / 9])


def test_a_run_from_a_checkpoint_anneals_over_its_own_updates_from_its_flags_full_rates(script, tmp_path):
    """A --checkpoint run (a ghost or control stage) counts --total-updates from the checkpoint's updates (4 here)
    and starts at its flags' full rates, whatever rate the checkpoint was saved at (0.25 of them)."""
    first = script.main(script.Args(runs_dir=str(tmp_path / "a"), lr_anneal=1.0, **RUN))
    checkpoint = f"{first}/checkpoints/latest.pt"
    run_dir = script.main(script.Args(runs_dir=str(tmp_path / "b"), lr_anneal=1.0, checkpoint=checkpoint,
                                      **{**RUN, "total_updates": 8, "prefill_episodes": 0}))  # fmt: skip
    assert logged_scales(run_dir) == pytest.approx([1.0, 0.75, 0.5, 0.25])
    assert script.load_checkpoint(f"{run_dir}/checkpoints/latest.pt")["counters"]["start_updates"] == 4


def test_a_resume_lifts_a_pause_unless_it_is_given_again(script, tmp_path):
    script.main(script.Args(runs_dir=str(tmp_path), pause_at_updates=2, **RUN))
    (run_dir,) = glob.glob(str(tmp_path / "*"))
    script.main(script.Args(resume=run_dir, pause_at_updates=3), {"pause_at_updates"})
    assert script.load_checkpoint(f"{run_dir}/checkpoints/latest.pt")["agents"][0]["num_updates"] == 3
    script.main(script.Args(resume=run_dir))  # the pause at 3 is lifted: on to --total-updates 4
    assert script.load_checkpoint(f"{run_dir}/checkpoints/latest.pt")["agents"][0]["num_updates"] == 4


@pytest.mark.parametrize("cpu_hours, budget", [(0.0, 1000), (3.1, 0)])
def test_an_experiment_trial_pauses_in_chunks_and_keeps_its_budget(tmp_path, monkeypatch, cpu_hours, budget):
    """experiment.py's trial loop: each chunk of report_every updates is a --pause-at-updates; --total-updates is the
    trial's own target (--single-updates), or 0 under a CPU budget, so that --lr-anneal sees the trial's budget."""
    pytest.importorskip("ray")
    import experiment
    from ray import tune

    spec = dataclasses.asdict(experiment.Spec(storage=str(tmp_path), single_updates=1000, single_cpu_hours=cpu_hours,
                                              report_every=500))  # fmt: skip
    script, *_ = experiment.trial_args(spec, "single", "gru", 12)
    calls = []

    class Stop(Exception):
        pass

    def main(args, overrides=()):
        calls.append((args.resume is not None, args.total_updates, args.pause_at_updates, set(overrides)))
        raise Stop

    monkeypatch.setattr(script, "main", main)
    with pytest.raises(Stop):  # a new trial
        experiment.dreamer_trial({"trial": {"spec": spec, "stage": "single", "variant": "gru", "seed": 12}})
    checkpoints = os.path.join(experiment.trial_dir(spec, "single", "gru", 12), "run", "checkpoints")
    os.makedirs(checkpoints)
    open(f"{checkpoints}/latest.pt", "w").close()
    monkeypatch.setattr(script, "load_checkpoint", lambda path: {"agents": [{"num_updates": 500}], "extra": {}})
    monkeypatch.setattr(tune, "report", lambda metrics: None)
    monkeypatch.setattr(experiment, "latest_metrics", lambda run: {})
    with pytest.raises(Stop):  # its first chunk done: resumed for the second
        experiment.dreamer_trial({"trial": {"spec": spec, "stage": "single", "variant": "gru", "seed": 12}})
    assert calls == [(False, budget, 500, set()), (True, budget, 1000, {"total_updates", "pause_at_updates"})]


def test_an_older_checkpoint_run_without_its_first_updates_is_not_annealed_over_its_updates(script, tmp_path):
    """A --checkpoint run saved before counters kept start_updates cannot count --total-updates from its start: a
    resume with --lr-anneal is refused, naming the checkpoint; without it the run resumes."""
    import torch

    first = script.main(script.Args(runs_dir=str(tmp_path / "a"), **RUN))
    run_dir = script.main(script.Args(runs_dir=str(tmp_path / "b"), checkpoint=f"{first}/checkpoints/latest.pt",
                                      **{**RUN, "total_updates": 6, "prefill_episodes": 0}))  # fmt: skip
    latest = f"{run_dir}/checkpoints/latest.pt"
    saved = torch.load(latest, weights_only=True)
    del saved["counters"]["start_updates"]  # as the parent of this change wrote it
    torch.save(saved, latest)
    with pytest.raises(run_tools.UsageError, match="latest.pt: this --checkpoint run was started before"):
        script.main(script.Args(resume=run_dir, total_updates=8, lr_anneal=0.5), {"total_updates", "lr_anneal"})
    script.main(script.Args(resume=run_dir, total_updates=8), {"total_updates"})
    assert script.load_checkpoint(latest)["agents"][0]["num_updates"] == 8
