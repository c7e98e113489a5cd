"""evaluate.py: a saved agent on a block of tracks with every policy asked for, and its acting-only export."""

import json
import os

import pytest
import torch
from conftest import TINY_RUN

import evaluate


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny single-car run whose own evaluation (track 10000, one race) used the deterministic policy."""
    import dreamer_lstm

    root = tmp_path_factory.mktemp("evaluate")
    args = dreamer_lstm.Args(stage="single", runs_dir=str(root), eval_policy="deterministic", **TINY_RUN)
    return dreamer_lstm.main(args)


def test_the_deterministic_policy_scores_what_the_runs_own_evaluation_logged(tiny_run):
    import csv

    with open(os.path.join(tiny_run, "progress.csv")) as f:
        logged = [float(r["car_0/eval/episodic_return"]) for r in csv.DictReader(f) if r["car_0/eval/episodic_return"]]
    path = os.path.join(tiny_run, "checkpoints", "latest.pt")
    results = evaluate.evaluate_checkpoint(path, 10_000, 1, ("deterministic",))
    assert results["deterministic"]["return"] == [pytest.approx(logged[-1], abs=1e-3)]


def test_an_export_drives_exactly_like_its_checkpoint_and_the_json_has_every_track(tiny_run, tmp_path, capsys):
    path, export = os.path.join(tiny_run, "checkpoints", "latest.pt"), str(tmp_path / "policy.pt")
    evaluate.cli([path, "--export", export])
    assert torch.load(export, weights_only=True)["kind"] == "policy"
    out = str(tmp_path / "readings.json")
    evaluate.cli([export, "--tracks", "2", "--json", out])
    printed = capsys.readouterr().out
    assert "| stochastic |" in printed and "| mean-action |" in printed
    with open(out) as f:
        from_export = json.load(f)
    from_checkpoint = evaluate.evaluate_checkpoint(path, 10_000, 2, ("stochastic", "mean-action"))
    for policy in ("stochastic", "mean-action"):
        assert from_export[policy] == from_checkpoint[policy]  # the same random stream, the same cars
        assert len(from_export[policy]["return"]) == 2 and set(from_export[policy]) >= {"gas", "speed", "eliminated"}


def test_a_missing_file_or_no_tracks_is_one_line(tiny_run):
    with pytest.raises(SystemExit, match=r"^evaluate.py: error: no/such.pt: no such checkpoint file$"):
        evaluate.cli(["no/such.pt"])
    with pytest.raises(SystemExit, match=r"^evaluate.py: error: pretrained/gru_cpu.pt: has 1 agent\(s\), asked for "
                                         r"agent 1$"):  # fmt: skip
        evaluate.cli(["pretrained/gru_cpu.pt", "--agent", "1"])  # an export holds agent 0 only
    with pytest.raises(SystemExit, match=r"^evaluate.py: error: .*: a directory, not a checkpoint file \(a run's are "
                                         r"checkpoints/best\.pt"):  # fmt: skip
        evaluate.cli([tiny_run])  # the run directory (what --resume takes)
    with pytest.raises(SystemExit, match=r"^evaluate.py: error: --torch-threads must be >= 0 \(0: torch's default\), "
                                         r"got -1$"):  # fmt: skip
        evaluate.cli([os.path.join(tiny_run, "checkpoints", "latest.pt"), "--torch-threads", "-1"])
    for flags, got in ((["--tracks", "0"], "0 and 10000"), (["--first-track", "-3"], "10 and -3")):
        with pytest.raises(SystemExit, match=rf"^evaluate.py: error: --tracks must be >= 1 and --first-track >= 0 "
                                             rf"\(a track's seed\), got {got}$"):  # fmt: skip
            evaluate.cli([os.path.join(tiny_run, "checkpoints", "latest.pt"), *flags])


def test_torch_threads_sets_torchs_threads(tiny_run, monkeypatch, tmp_path):
    threads = []
    monkeypatch.setattr(torch, "set_num_threads", threads.append)
    latest = os.path.join(tiny_run, "checkpoints", "latest.pt")
    evaluate.cli([latest, "--export", str(tmp_path / "policy.pt")])
    evaluate.cli([latest, "--export", str(tmp_path / "policy.pt"), "--torch-threads", "1"])
    assert threads == [1]


def test_each_policy_asked_for_drives_and_the_block_starts_at_first_track(tiny_run):
    """The readings of a policy are its own (the sampled policy steers otherwise than the mean action), and the
    tracks are first_track .. first_track + tracks - 1: the deterministic policy alone on track 10001 reads what it
    read there as the second of two tracks from 10000 (and otherwise than on 10000, so a block that ignored
    first_track would fail)."""
    path = os.path.join(tiny_run, "checkpoints", "latest.pt")
    both = evaluate.evaluate_checkpoint(path, 10_000, 2, ("stochastic", "mean-action", "deterministic"))
    assert both["stochastic"]["abs_steer"] != both["mean-action"]["abs_steer"]
    second = evaluate.evaluate_checkpoint(path, 10_001, 1, ("deterministic",))["deterministic"]
    first, later = both["deterministic"]["return"]
    assert first != later  # (the two tracks read apart: the check below can fail)
    assert second["return"] == [later] and second["progress"] == [both["deterministic"]["progress"][1]]
