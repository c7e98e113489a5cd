"""A loaded state learns at its flags' rates; a run paused (--pause-at-updates, as experiment.py's trials run in
chunks) and resumed goes on exactly as the run without the pause."""

from __future__ import annotations

import dataclasses
import glob
import os

import pytest
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


def test_a_loaded_state_learns_at_its_flags_rates_not_at_those_its_optimisers_were_saved_with(script):
    """A resumed run's --actor-lr etc. (and a --checkpoint run's) are the rates it learns at: Adam's own
    load_state_dict would bring back the saved ones."""
    saved = script.Agent(tiny_args(script, entropy_target=0.0), action_dim=2)
    for optimizer in (saved.model_optimizer, saved.actor_optimizer, saved.critic_optimizer, saved.alpha_optimizer):
        optimizer.param_groups[0]["lr"] = 0.125  # saved at rates its flags no longer give
    flags = dict(model_lr=3e-4, actor_lr=5e-5, critic_lr=2e-4, entropy_lr=2e-3)
    loaded = script.Agent(tiny_args(script, entropy_target=0.0, **flags), action_dim=2)
    loaded.load_state_dict(saved.state_dict())
    assert rates(loaded) == {"model": [3e-4], "actor": [5e-5], "critic": [2e-4], "alpha": [2e-3]}
    assert rates(saved) == {"model": [0.125], "actor": [0.125], "critic": [0.125], "alpha": [0.125]}


def test_a_run_paused_and_resumed_ends_bit_exact_where_the_run_without_the_pause_ends(script, tmp_path):
    """--total-updates 4; a run paused at 2 updates (--pause-at-updates) and resumed with the pause lifted ends with
    the same networks, optimisers (their rates included) and counters as the run never paused."""
    whole = script.main(script.Args(runs_dir=str(tmp_path / "a"), **RUN))
    end = script.load_checkpoint(f"{whole}/checkpoints/latest.pt")
    assert end["agents"][0]["num_updates"] == 4

    script.main(script.Args(runs_dir=str(tmp_path / "b"), pause_at_updates=2, **RUN))
    (paused,) = glob.glob(str(tmp_path / "b" / "*"))
    assert script.load_checkpoint(f"{paused}/checkpoints/latest.pt")["agents"][0]["num_updates"] == 2
    script.main(script.Args(resume=paused, pause_at_updates=0), {"pause_at_updates"})
    resumed = script.load_checkpoint(f"{paused}/checkpoints/latest.pt")
    assert_same(end["agents"], resumed["agents"], "agents")
    assert end["counters"] == resumed["counters"]


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
    trial's own target (--single-updates), or 0 under a CPU budget (--cpu-hours-limit then ends it)."""
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
