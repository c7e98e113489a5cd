"""The learning rates: a loaded state learns at its flags' rates, and --lr-anneal takes every rate linearly to 0 over
the last share of the run's budget (episodes, updates since the run's start, or CPU time), through pauses and
resumes."""

from __future__ import annotations

import glob
import types

import pytest
import utils.run as run_tools
from conftest import TINY, assert_same, tiny_args

# A tiny single-car run that one update per race ends after 4 updates (the prefill race, then 4 races that learn).
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
        (dict(total_episodes=1000), {"episode": 250}, 99, 5.0, 0.25),  # races only
        (dict(total_episodes=1000, total_updates=1000), {"episode": 10, "start_updates": 600}, 800, 0.0, 0.5),
        (dict(total_episodes=1000, total_updates=1000), {"episode": 10}, 800, 0.0, 0.8),  # a run from scratch
        (dict(total_episodes=1000, cpu_hours_limit=2.0), {"episode": 10}, 5, 5400.0, 0.75),  # CPU time
        (dict(total_episodes=10, cpu_hours_limit=2.0, pause_at_updates=6), {"episode": 9}, 5, 5400.0, 0.9),
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
