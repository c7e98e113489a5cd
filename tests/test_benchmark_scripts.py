"""The benchmarks and tools reach into the dreamer scripts by name (``script = importlib.import_module(...)``, then
``script.Agent``, ``script.PRESETS``...): every such name exists in both scripts, so a helper moved out of the
scripts (as ``keep_freed_memory`` moved to utils/run.py) cannot leave a benchmark that fails only when run."""

from __future__ import annotations

import ast
import glob
import os

import pytest

import dreamer_gru
import dreamer_lstm

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FILES = sorted(glob.glob(os.path.join(ROOT, "benchmarks", "*.py")) + [os.path.join(ROOT, name) for name in
               ("race.py", "evaluate.py", "plot.py")])  # fmt: skip


def script_names(path: str) -> set[str]:
    """Attributes read from a variable named ``script`` (how the tools hold a dreamer script module)."""
    tree = ast.parse(open(path).read(), path)
    return {node.attr for node in ast.walk(tree)
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "script"}


def test_the_reader_finds_the_names_a_tool_uses():
    names = script_names(os.path.join(ROOT, "benchmarks", "train_throughput.py"))
    assert {"Agent", "Args", "PRESETS", "Replay"} <= names  # (the reader itself can fail)


@pytest.mark.parametrize("path", FILES, ids=lambda p: os.path.relpath(p, ROOT))
def test_every_script_name_a_tool_uses_exists_in_both_scripts(path):
    missing = {module.__name__: sorted(n for n in script_names(path) if not hasattr(module, n))
               for module in (dreamer_lstm, dreamer_gru)}  # fmt: skip
    assert not any(missing.values()), f"{os.path.relpath(path, ROOT)} uses names the scripts lack: {missing}"
