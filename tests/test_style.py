"""The code stays within the line length `pyproject.toml` configures for ruff (120 columns)."""

from __future__ import annotations

import glob
import os
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_no_python_line_exceeds_the_configured_length():
    limit = tomllib.load(open(os.path.join(ROOT, "pyproject.toml"), "rb"))["tool"]["ruff"]["line-length"]
    folders = ["", "envs", "utils", "benchmarks", "tests", "docs"]  # the project's own code, not a venv or runs/
    files = [p for folder in folders for p in glob.glob(os.path.join(ROOT, folder, "*.py"))]
    assert len(files) > 20
    long = [f"{os.path.relpath(p, ROOT)}:{i}" for p in files for i, line in enumerate(open(p), 1)
            if len(line.rstrip("\n")) > limit]  # fmt: skip
    assert not long, f"lines over {limit} columns: {long}"


def test_every_command_line_parses_through_tyro_cli():
    """Every command line is a tyro Args dataclass (a docstring per flag, as CleanRL's), parsed by utils.run.tyro_cli:
    tyro.cli with each flag's wrapped docstring as one --help paragraph (tested in test_reliability.py); a command
    line that called tyro.cli itself would break every wrapped help line."""
    folders = ["", "envs", "utils", "benchmarks"]
    files = [p for folder in folders for p in glob.glob(os.path.join(ROOT, folder, "*.py"))]
    direct = [os.path.relpath(p, ROOT) for p in files
              if "tyro.cli(" in open(p).read() and not p.endswith(os.path.join("utils", "run.py"))]  # fmt: skip
    assert not direct, f"these call tyro.cli instead of utils.run.tyro_cli: {direct}"
    argparse = [os.path.relpath(p, ROOT) for p in files if "ArgumentParser(" in open(p).read()]
    assert not argparse, f"these parse with argparse, not a tyro Args dataclass: {argparse}"
    users = [p for p in files if "tyro_cli(" in open(p).read()]
    assert len(users) >= 12  # race, evaluate, plot, the run plumbing and the benchmarks' command lines
