"""benchmarks/ppo_peer.py: the zoo's wrappers, resumable training runs of PPO and RecurrentPPO, the evaluation row
(an LSTM's state carried), the sample-efficiency snapshots and their curve, the evaluation tracks."""

import csv
import os

import gymnasium
import numpy as np
import pytest
import torch

import ppo_peer


def parameters(policy) -> torch.Tensor:
    """A policy's weights as one vector."""
    return torch.cat([p.detach().flatten() for p in policy.parameters()])


def test_frame_skip_sums_rewards_and_stops_at_the_end():
    class Count(gymnasium.Env):
        observation_space = gymnasium.spaces.Box(0, 1, (1,))
        action_space = gymnasium.spaces.Box(-1, 1, (1,))

        def reset(self, *, seed=None, options=None):
            self.t = 0
            return np.zeros(1, np.float32), {}

        def step(self, action):
            self.t += 1
            return np.zeros(1, np.float32), float(self.t), self.t == 3, False, {"t": self.t}

    env = ppo_peer.FrameSkip(Count(), 2)
    env.reset()
    assert env.step(np.zeros(1))[1] == 1 + 2
    _, reward, terminated, _, info = env.step(np.zeros(1))
    assert (reward, terminated, info["t"]) == (3, True, 3)  # the episode ended inside the skip


def test_the_env_is_the_single_car_race_at_64_px_grayscale():
    env = ppo_peer.make_env()
    obs, _ = env.reset(seed=0)
    assert obs.shape == (64, 64, 1) and obs.dtype == np.uint8 and env.action_space.shape == (2,)
    assert env.unwrapped.race.dead_zone == -0.5  # the Dreamer runs' final dead zone
    env.close()


def test_a_run_resumes_in_a_later_sitting_and_writes_its_row(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(ppo_peer.ZOO, "n_envs", 2)
    monkeypatch.setitem(ppo_peer.ZOO, "n_steps", 32)
    monkeypatch.setitem(ppo_peer.ZOO, "batch_size", 32)
    monkeypatch.setitem(ppo_peer.ZOO, "n_epochs", 1)
    argv = ["--seed", "3", "--cpu-hours", "1", "--budget-steps", "64", "--tracks", "1", "--runs-dir", str(tmp_path),
            "--results", str(tmp_path / "ppo_peer.csv")]  # fmt: skip
    first = ppo_peer.main(argv)
    assert (first["env_steps"], first["updates"]) == (2 * 64, 1)  # one rollout of 2 x 32 steps, frame skip 2
    assert "continuing from" not in capsys.readouterr().out
    second = ppo_peer.main([*argv[:4], "--budget-steps", "128", *argv[6:]])  # the budget grows: it continues
    assert (second["env_steps"], second["updates"]) == (2 * 128, 2)
    # (a fresh start would reach the same counts: the sitting must have started from the first one's save)
    assert f"continuing from {tmp_path / 'ppo__3' / 'model.zip'} at 128 env steps" in capsys.readouterr().out
    with open(tmp_path / "ppo_peer.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1 and rows[0]["variant"] == "ppo" and int(rows[0]["env_steps"]) == 256  # replaced, not added
    assert -200 < float(rows[0]["final_return"]) < 1000 and 0 <= float(rows[0]["final_mean_abs_steer"]) <= 1
    for argv, message in ((["--cpu-hours", "0"], "--cpu-hours must be > 0, got 0.0"),
                          (["--tracks", "0"], "--tracks must be >= 1, got 0"),
                          (["--snapshot-steps", "100", "0"], "--snapshot-steps must be >= 1, got 0")):
        with pytest.raises(SystemExit):
            ppo_peer.main(argv)
        assert message in capsys.readouterr().err


def tiny(monkeypatch, config, race_steps=None):
    """2 envs, rollouts of 32 steps (64 PPO steps, 128 env steps), one epoch of one minibatch; races cut to
    `race_steps` decisions (training and evaluation) when given."""
    for key, value in (("n_envs", 2), ("n_steps", 32), ("batch_size", 32), ("n_epochs", 1)):
        monkeypatch.setitem(config, key, value)
    if race_steps:
        make_env = ppo_peer.make_env
        cut = lambda: gymnasium.wrappers.TimeLimit(make_env(), race_steps)  # noqa: E731
        monkeypatch.setattr(ppo_peer, "make_env", cut)


def test_recurrent_ppo_has_the_zoo_entry():
    # rl-baselines3-zoo, hyperparams/ppo_lstm.yml, CarRacing-v0 (read at commit 038ab16), as written there: FrameSkip
    # skip 2, ResizeObservation 64, GrayScaleObservation keep_dim, "# normalize: True" commented out, a constant
    # learning rate
    zoo = dict(
        frame_skip=2, image_size=64, frame_stack=2, normalize=False, n_envs=8, n_timesteps=2e6, policy="CnnLstmPolicy",
        batch_size=128, n_steps=512, gamma=0.99, gae_lambda=0.9, n_epochs=20, ent_coef=0.0, sde_sample_freq=4,
        max_grad_norm=0.5, vf_coef=0.5, learning_rate=3e-5, lr_schedule="constant", use_sde=True, clip_range=0.4,
        policy_kwargs=dict(log_std_init=-2, ortho_init=False, enable_critic_lstm=False, activation_fn="GELU",
                           lstm_hidden_size=128),
    )  # fmt: skip
    assert ppo_peer.ZOO_LSTM == zoo
    assert all(ppo_peer.ZOO_LSTM[k] == ppo_peer.ZOO[k] for k in ("frame_skip", "image_size", "frame_stack"))
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.vec_env import VecNormalize

    norm = VecNormalize(ppo_peer.make_venv(0, 8), norm_obs=False, norm_reward=False)
    model = ppo_peer.make_model(0, norm, None, "recurrent-ppo")  # what the constructor made of it
    assert isinstance(model, RecurrentPPO) and model.n_envs == 8 and model.observation_space.shape == (2, 64, 64)
    assert (model.n_steps, model.batch_size, model.n_epochs, model.gamma, model.gae_lambda) == (512, 128, 20, 0.99, 0.9)
    assert (model.ent_coef, model.vf_coef, model.max_grad_norm, model.clip_range(1.0)) == (0.0, 0.5, 0.5, 0.4)
    assert model.lr_schedule(1.0) == model.lr_schedule(0.0) == 3e-5
    assert model.use_sde and model.sde_sample_freq == 4 and model.policy.ortho_init is False
    assert model.policy.lstm_actor.hidden_size == 128 and model.policy.lstm_critic is None
    assert model.policy.activation_fn.__name__ == "GELU" and float(model.policy.log_std.detach().mean()) == -2
    norm.close()


def test_a_recurrent_run_resumes_writes_its_row_and_its_curve(tmp_path, monkeypatch, capsys):
    tiny(monkeypatch, ppo_peer.ZOO_LSTM, race_steps=40)
    argv = ["--algo", "recurrent-ppo", "--seed", "3", "--cpu-hours", "1", "--tracks", "1", "--runs-dir", str(tmp_path),
            "--results", str(tmp_path / "recurrent_ppo_peer.csv"), "--snapshot-steps", "100", "300"]  # fmt: skip
    first = ppo_peer.main([*argv, "--budget-steps", "64"])
    assert (first["variant"], first["env_steps"], first["updates"]) == ("recurrent_ppo", 2 * 64, 1)
    capsys.readouterr()
    from sb3_contrib import RecurrentPPO

    saved = RecurrentPPO.load(tmp_path / "recurrent_ppo__3" / "model.zip", device="cpu")
    started, learn = [], RecurrentPPO.learn

    def spy(self, *args, **kwargs):  # what the second sitting learns from: the first sitting's weights and counts
        started.append((self.num_timesteps, self._n_updates, parameters(self.policy)))
        return learn(self, *args, **kwargs)

    monkeypatch.setattr(RecurrentPPO, "learn", spy)
    second = ppo_peer.main([*argv, "--budget-steps", "256"])  # continues: rollouts start at 128, 256, 384 env steps
    assert (second["env_steps"], second["updates"]) == (2 * 256, 4)
    assert "continuing from " in capsys.readouterr().out
    assert started[0][:2] == (64, 1) and torch.equal(started[0][2], parameters(saved.policy))  # (a fresh start: 0, 0)
    with open(tmp_path / "recurrent_ppo_peer.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1 and tuple(rows[0]) == ppo_peer.COLUMNS and rows[0]["variant"] == "recurrent_ppo"
    assert -200 < float(rows[0]["final_return"]) < 1000 and 0 <= float(rows[0]["final_mean_abs_steer"]) <= 1
    files = sorted(name for name in os.listdir(tmp_path / "recurrent_ppo__3") if "." in name)  # (not tensorboard's)
    assert files == [
        "model.zip", "model_100.zip", "model_300.zip", "record.json", "vecnormalize.pkl", "vecnormalize_100.pkl",
        "vecnormalize_300.pkl",
    ]  # fmt: skip  (100: the weights of the rollout over env steps 1..128; 300: of the rollout over 257..384)
    seen = []
    monkeypatch.setattr(ppo_peer, "evaluate", lambda model, first, n: seen.append((model.num_timesteps, first, n))
                        or {"return": 1.0, "progress": 0.5, "abs_steer": 0.25})  # fmt: skip
    curve_argv = ["--algo", "recurrent-ppo", "--seed", "3", "--curve", "--runs-dir", str(tmp_path), "--results",
                  str(tmp_path / "recurrent_ppo_peer.csv")]  # fmt: skip
    for _ in range(2):  # a second time replaces the seed's rows on those tracks
        ppo_peer.main([*curve_argv, "--first-track", "10100", "--tracks", "20"])
    ppo_peer.main(curve_argv)  # the default tracks (the report tracks): rows beside them
    assert seen[:2] == [(50, 10_100, 20), (150, 10_100, 20)] and seen[4:] == [(50, 10_300, 30), (150, 10_300, 30)]
    with open(tmp_path / "recurrent_ppo_peer_curve.csv") as f:
        curve = list(csv.DictReader(f))
    assert tuple(curve[0]) == ppo_peer.CURVE_COLUMNS
    assert [(r["variant"], r["snapshot"], r["env_steps"], r["tracks"]) for r in curve] == [
        ("recurrent_ppo", "100", "0", "10100..10119"), ("recurrent_ppo", "300", "256", "10100..10119"),
        ("recurrent_ppo", "100", "0", "10300..10329"), ("recurrent_ppo", "300", "256", "10300..10329"),
    ]  # fmt: skip


def test_the_evaluation_carries_the_lstm_state_and_resets_it_at_each_race(monkeypatch):
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.vec_env import VecNormalize

    tiny(monkeypatch, ppo_peer.ZOO_LSTM, race_steps=6)
    norm = VecNormalize(ppo_peer.make_venv(0, 1), norm_obs=False, norm_reward=False)
    model = ppo_peer.make_model(0, norm, None, "recurrent-ppo")
    calls, predict = [], RecurrentPPO.predict

    def spy(self, observation, state=None, episode_start=None, deterministic=False):
        action, new_state = predict(self, observation, state, episode_start, deterministic)
        calls.append((state, episode_start.copy(), new_state, deterministic))
        return action, new_state

    monkeypatch.setattr(RecurrentPPO, "predict", spy)
    ppo_peer.evaluate(model, 10_100, 2)
    assert len(calls) == 2 * 6 and all(deterministic for *_, deterministic in calls)
    for i, (state, start, _, _) in enumerate(calls):
        assert start.tolist() == [i % 6 == 0]  # True on each race's first step only
        assert state is None if i % 6 == 0 else state is calls[i - 1][2]  # from zeros, then the previous state
    assert not np.allclose(calls[1][2][0], calls[0][2][0])  # the state moves: carrying it matters


def test_snapshots_are_written_once_at_the_thresholds_over_sittings(tmp_path, monkeypatch):
    tiny(monkeypatch, ppo_peer.ZOO)
    writes, atomic_save = [], ppo_peer.atomic_save
    monkeypatch.setattr(ppo_peer, "atomic_save", lambda save, path: writes.append(path) or atomic_save(save, path))
    thresholds = (100, 128, 300, 10_000)
    ppo_peer.train(3, hours=1.0, budget_steps=128, run_dir=str(tmp_path), snapshots=thresholds)  # 0 .. 256 env steps
    lost = tmp_path / "model_10000.zip"  # as if a killed sitting had passed 10,000 after its last save
    lost.write_bytes((tmp_path / "model.zip").read_bytes())
    ppo_peer.train(3, hours=1.0, budget_steps=256, run_dir=str(tmp_path), snapshots=thresholds)  # 256 .. 512
    assert not lost.exists()  # a resumed run takes it again when it gets there (here: never)
    snapshots = [os.path.basename(p) for p in writes if "_" in os.path.basename(p)]
    assert snapshots == ["vecnormalize_100.pkl", "model_100.zip", "vecnormalize_128.pkl", "model_128.zip",
                         "vecnormalize_300.pkl", "model_300.zip"]  # fmt: skip  (10_000 is never passed)
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    models = {n: PPO.load(path) for n, path in ppo_peer.snapshot_paths(str(tmp_path))}
    # kept right after the step that passed each threshold (4 env steps per step of the 2 envs), by the weights that
    # took it: rollouts of 128 env steps (1..128, 129..256, 257..384, ...) of the weights trained on those before
    assert {n: m.num_timesteps * 2 for n, m in models.items()} == {100: 100, 128: 128, 300: 300}
    assert {n: m._n_updates * 128 for n, m in models.items()} == {100: 0, 128: 0, 300: 256}  # (1 epoch a rollout)
    assert VecNormalize.load(str(tmp_path / "vecnormalize_300.pkl"), ppo_peer.make_venv(0, 2)).norm_reward
    assert not [name for name in os.listdir(tmp_path) if ".tmp" in name]


def test_a_later_sitting_races_other_tracks_than_the_first(tmp_path, monkeypatch):
    """Loading a model reseeds it with the run's seed: a later sitting must not race the first sitting's tracks
    again (the seeds its envs reset with)."""
    tiny(monkeypatch, ppo_peer.ZOO, race_steps=40)
    seeds, make_env = [], ppo_peer.make_env

    class RecordSeeds(gymnasium.Wrapper):
        def reset(self, *, seed=None, options=None):
            seeds.append(seed)
            return self.env.reset(seed=seed, options=options)

    monkeypatch.setattr(ppo_peer, "make_env", lambda: RecordSeeds(make_env()))
    sittings = []
    for budget in (64, 128, 192):  # a rollout (64 PPO steps) per sitting
        seeds.clear()
        ppo_peer.train(3, hours=1.0, budget_steps=budget, run_dir=str(tmp_path))
        sittings.append({s for s in seeds if s is not None})
    assert len(sittings[0]) == 2 and all(len(s) == 2 for s in sittings)  # each sitting seeds its 2 envs once
    assert sittings[0].isdisjoint(sittings[1]) and sittings[1].isdisjoint(sittings[2])
    assert sittings[0].isdisjoint(sittings[2])


def test_the_cpu_budget_stops_a_sitting_and_keeps_no_snapshot_of_a_step_it_did_not_take(tmp_path, monkeypatch):
    """The budget is the process's CPU time: a clock of 20 CPU-minutes a reading ends the sitting at its 1 CPU-hour
    budget 12 env steps into its first rollout, whatever the wall clock says (it would have run 4 rollouts), and the
    record counts the CPU hours. A snapshot threshold the rollout would have reached is not kept; one it reached is."""
    tiny(monkeypatch, ppo_peer.ZOO)
    readings = iter(range(10**6))
    monkeypatch.setattr(ppo_peer.time, "process_time", lambda: 1200.0 * next(readings))
    record = ppo_peer.train(3, hours=1.0, budget_steps=256, run_dir=str(tmp_path), snapshots=(8, 100))
    assert record["env_steps"] == 12 and record["cpu_hours"] >= 1.0
    assert [n for n, _ in ppo_peer.snapshot_paths(str(tmp_path))] == [8]


def test_a_run_killed_before_its_first_save_starts_again_without_its_snapshots(tmp_path, monkeypatch):
    tiny(monkeypatch, ppo_peer.ZOO)
    stale = tmp_path / "model_100.zip"  # kept by a first sitting killed before it saved model.zip
    stale.write_bytes(b"from the killed sitting")
    ppo_peer.train(3, hours=1.0, budget_steps=64, run_dir=str(tmp_path), snapshots=(100,))  # 128 env steps
    from stable_baselines3 import PPO

    assert PPO.load(str(stale)).num_timesteps * 2 == 100  # taken again by this run


def test_the_evaluation_tracks_are_parameters(tmp_path, monkeypatch):
    from stable_baselines3.common.vec_env import VecNormalize

    run_dir = tmp_path / "ppo__3"
    model = ppo_peer.make_model(0, VecNormalize(ppo_peer.make_venv(0, 1), norm_obs=False), None)
    model.save(run_dir / "model.zip")
    (run_dir / "record.json").write_text('{"env_steps": 0, "hours": 0.25, "updates": 0}')  # the first version's
    seen = []
    monkeypatch.setattr(ppo_peer, "evaluate", lambda model, first, n: seen.append((first, n))
                        or {"return": 1.0, "progress": 0.5, "abs_steer": 0.25})  # fmt: skip
    argv = ["--seed", "3", "--evaluate-only", "--runs-dir", str(tmp_path), "--results", str(tmp_path / "p.csv")]
    ppo_peer.main(argv)  # the default: the final protocol's report tracks
    ppo_peer.main([*argv, "--first-track", "10100", "--tracks", "20"])  # the 8,000-update protocol's tracks
    assert seen == [ppo_peer.FINAL_TRACKS, ppo_peer.FRESH_TRACKS] == [(10_300, 30), (10_100, 20)]
    assert [(r["seed"], r["tracks"], r["cpu_hours"]) for r in ppo_peer.read_rows(str(tmp_path / "p.csv"))] == [
        ("3", "10100..10119", "0.25"), ("3", "10300..10329", "0.25")
    ]  # the seed's row on each block of tracks, with the record's CPU hours


def test_a_row_replaces_only_the_row_of_its_seed_and_tracks_and_old_rows_are_the_fresh_tracks(tmp_path):
    path = tmp_path / "ppo_peer.csv"  # as benchmarks/results holds it: written before the tracks column
    path.write_text(",".join(ppo_peer.COLUMNS[:-1]) + "\nppo,11,4870,4011296,3.1,657.7,0.7973,0.1571\n"
                    "ppo,12,4700,3859728,3.1,854.78,0.9529,0.0972\n")  # fmt: skip
    assert [(r["seed"], r["tracks"]) for r in ppo_peer.read_rows(str(path))] == [("11", "10100..10119"),
                                                                                 ("12", "10100..10119")]  # fmt: skip

    def row(seed, final_return, tracks):
        return {"variant": "ppo", "seed": seed, "updates": 4800, "env_steps": 3900000, "cpu_hours": 3.1,
                "final_return": final_return, "final_progress": 0.9, "final_mean_abs_steer": 0.1, "tracks": tracks}

    def written():
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            return tuple(reader.fieldnames), [(r["seed"], r["tracks"], r["final_return"]) for r in reader]

    ppo_peer.write_row(row(11, 700.0, "10300..10329"), str(path))  # beside seed 11's row of the fresh tracks
    ppo_peer.write_row(row(13, 500.0, "10300..10329"), str(path))
    ppo_peer.write_row(row(11, 710.0, "10300..10329"), str(path))  # measured again there: replaces that row only
    assert written() == (ppo_peer.COLUMNS, [
        ("11", "10100..10119", "657.7"), ("11", "10300..10329", "710.0"), ("12", "10100..10119", "854.78"),
        ("13", "10300..10329", "500.0"),
    ])  # fmt: skip
    ppo_peer.write_row(row(12, 860.0, "10100..10119"), str(path))  # the old row's tracks: replaces it
    assert written()[1] == [("11", "10100..10119", "657.7"), ("11", "10300..10329", "710.0"),
                            ("12", "10100..10119", "860.0"), ("13", "10300..10329", "500.0")]  # fmt: skip
