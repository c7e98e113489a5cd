"""The benchmarks, tools and utils reach into the dreamer scripts by name (``script = importlib.import_module(...)``,
then ``script.Agent``, ``script.PRESETS``...; utils/ as ``method`` or ``run.method``): every such name exists in both
scripts, so a helper moved out of the scripts (as ``keep_freed_memory`` moved to utils/run.py) cannot leave a
benchmark that fails only when run."""

from __future__ import annotations

import ast
import glob
import os

import pytest

import dreamer_gru
import dreamer_lstm

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FILES = sorted(glob.glob(os.path.join(ROOT, "benchmarks", "*.py")) + glob.glob(os.path.join(ROOT, "utils", "*.py"))
               + [os.path.join(ROOT, name) for name in ("race.py", "evaluate.py", "plot.py")])  # fmt: skip
MODULE_NAMES = ("script", "method")  # how the tools (script) and utils/ (method, run.method) hold a dreamer script


def script_names(path: str) -> set[str]:
    """Attributes read from a variable, or an attribute, named as in MODULE_NAMES."""

    def holds_a_script(node: ast.AST) -> bool:
        return (isinstance(node, ast.Name) and node.id in MODULE_NAMES) or (
            isinstance(node, ast.Attribute) and node.attr in MODULE_NAMES)  # fmt: skip

    tree = ast.parse(open(path).read(), path)
    return {node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute) and holds_a_script(node.value)}


def test_the_reader_finds_the_names_a_tool_uses():
    names = script_names(os.path.join(ROOT, "benchmarks", "train_throughput.py"))
    assert {"Agent", "Args", "PRESETS", "Replay"} <= names  # (the reader itself can fail)
    assert {"VARIANT", "dead_zone_at", "LOG_SIGMA_RANGE"} <= script_names(os.path.join(ROOT, "utils", "run.py"))
    assert "load_checkpoint" in script_names(os.path.join(ROOT, "utils", "checkpoint.py"))


@pytest.mark.parametrize("path", FILES, ids=lambda p: os.path.relpath(p, ROOT))
def test_every_script_name_a_tool_uses_exists_in_both_scripts(path):
    missing = {module.__name__: sorted(n for n in script_names(path) if not hasattr(module, n))
               for module in (dreamer_lstm, dreamer_gru)}  # fmt: skip
    assert not any(missing.values()), f"{os.path.relpath(path, ROOT)} uses names the scripts lack: {missing}"
