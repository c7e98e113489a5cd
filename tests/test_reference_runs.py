"""The scripts compute what they computed before a refactor, and resume run directories written before it.

tests/fixtures/record_reference_runs.py recorded, at the commit before the run plumbing left the scripts, a tiny
race-stage run of each script: its run directory after race 2 and what it ended with after race 3. A new run with
the same arguments must end with the same networks, optimisers, counters and logged losses, and the old directory
must resume to that same end. (Tolerances allow other CPUs' float rounding; a changed computation, such as one
random draw more or less, moves the numbers by orders of magnitude more.)"""

import json
import os
import shutil
import sys

import pytest
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "fixtures"))
from conftest import TINY_RUN
from record_reference_runs import REFERENCE_RUN, logged_rows

FIXTURES = os.path.join(os.path.dirname(os.path.abspath(__file__)), "fixtures")
# scalars logged since the reference was recorded: readings of the same evaluations, nothing computed differently
LOGGED_SINCE = ("/eval/speed", "/eval/laps_finished", "/eval/eliminated")


def assert_close(a, b, where=""):
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{where}: keys {sorted(a)} != {sorted(b)}"
        for key in a:
            assert_close(a[key], b[key], f"{where}/{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), f"{where}: {len(a)} != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_close(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert (a.dtype, a.shape) == (b.dtype, b.shape), f"{where}: {a.dtype} {tuple(a.shape)}, {b.dtype} {b.shape}"
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5, msg=lambda m: f"{where}: {m}")
    elif isinstance(a, str):
        try:
            assert float(a) == pytest.approx(float(b), rel=1e-4, abs=1e-5), f"{where}: {a} != {b}"
        except ValueError:
            assert a == b, f"{where}: {a!r} != {b!r}"
    else:
        assert a == pytest.approx(b, rel=1e-4, abs=1e-5), f"{where}: {a!r} != {b!r}"


def check_against_reference(script, run_dir: str) -> None:
    reference = torch.load(os.path.join(FIXTURES, f"reference_{script.VARIANT}.pt"), weights_only=True)
    checkpoint = script.load_checkpoint(os.path.join(run_dir, "checkpoints", "latest.pt"))
    counters, expected = checkpoint["counters"], reference["counters"]
    assert {k: v for k, v in counters.items() if k != "best_eval_return"} == {
        k: v for k, v in expected.items() if k != "best_eval_return"}, "the run's length differs from the reference's"
    assert counters["best_eval_return"] == expected["best_eval_return"], "computed: best_eval_return"
    assert [agent["num_updates"] for agent in checkpoint["agents"]] == [6, 6]
    assert_close(checkpoint["agents"], reference["agents"], "agents")
    rows, known = logged_rows(run_dir), set().union(*reference["rows"])
    assert all(key.endswith(LOGGED_SINCE) for row in rows for key in row.keys() - known)  # nothing else is new
    assert_close([{k: v for k, v in row.items() if not k.endswith(LOGGED_SINCE)} for row in rows], reference["rows"],
                 "progress.csv")


def test_a_new_run_computes_what_the_reference_run_computed(script, tmp_path):
    run_dir = script.main(script.Args(**REFERENCE_RUN, runs_dir=str(tmp_path)))
    check_against_reference(script, run_dir)


def test_a_run_directory_written_before_the_refactor_resumes_to_the_same_end(script, tmp_path, monkeypatch):
    """Also on a CPU with bfloat16 instructions: the directory was saved with --amp auto, when auto meant bfloat16
    on CUDA only, and resumes with that rule (--amp cuda), in float32 on the CPU as the reference computed, saved
    resolved from then on."""
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True)
    run_dir = str(tmp_path / "run")
    shutil.copytree(os.path.join(FIXTURES, f"reference_{script.VARIANT}"), run_dir)
    assert torch.load(os.path.join(run_dir, "checkpoints", "latest.pt"), weights_only=True)["args"]["amp"] == "auto"
    script.main(script.Args(resume=run_dir, total_episodes=3, torch_threads=1), {"total_episodes"})
    check_against_reference(script, run_dir)
    assert script.load_checkpoint(os.path.join(run_dir, "checkpoints", "latest.pt"))["args"]["amp"] == "off"


@pytest.mark.parametrize("instructions", [True, False])
def test_a_new_run_saves_what_amp_auto_chose(script, tmp_path, monkeypatch, instructions):
    """--amp auto is resolved when a run starts, by this CPU's bfloat16 instructions, and saved as on or off (in
    config.json and the checkpoint), so that the run computes alike wherever it is resumed."""
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: instructions)
    run_dir = script.main(script.Args(**{**TINY_RUN, "amp": "auto", "stage": "single"}, runs_dir=str(tmp_path)))
    chosen = "on" if instructions else "off"
    with open(os.path.join(run_dir, "config.json")) as f:
        assert json.load(f)["amp"] == chosen
    assert script.load_checkpoint(os.path.join(run_dir, "checkpoints", "latest.pt"))["args"]["amp"] == chosen


def test_the_reference_check_fails_for_a_changed_computation(script, tmp_path):
    """A test that cannot fail is no test: a run with another batch size (the same networks, other numbers) fails it."""
    run_dir = script.main(script.Args(**{**REFERENCE_RUN, "batch_size": REFERENCE_RUN["batch_size"] + 1},
                                      runs_dir=str(tmp_path)))  # fmt: skip
    with pytest.raises(AssertionError, match=r"^computed: |^agents\["):  # what it computed, not its length
        check_against_reference(script, run_dir)
