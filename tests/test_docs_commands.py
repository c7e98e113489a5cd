"""Every command the README and docs/ show must run as written: each `python <file> ...` line is parsed by its own
program's command-line parser (argparse or tyro), which stops there (a dry run). A renamed or removed flag, a wrong
value type or a file that no longer exists fails here, naming the page and the command."""

from __future__ import annotations

import argparse
import glob
import os
import re
import runpy
import shlex
import sys

import pytest
import tyro

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAGES = ["README.md", *sorted(os.path.relpath(p, ROOT) for p in glob.glob(os.path.join(ROOT, "docs", "*.md")))]
SHELL_VARIABLES = {"$v": "lstm", "${v}": "lstm", "$seed": "1", "${seed}": "1"}  # the docs' loops, one iteration


def commands(page: str) -> list[str]:
    """`python ...` commands of a page: in fenced or indented code blocks and in inline code, continuation lines
    joined, shell prompts and trailing comments removed."""
    text = open(os.path.join(ROOT, page)).read()
    blocks = re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S)
    blocks += ["\n".join(re.findall(r"^(?: {4}|\t)(.*)$", text, flags=re.M))]
    blocks += re.findall(r"`(python [^`]+)`", text)
    found = []
    for block in blocks:
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip().removeprefix("$ ")
            if line.startswith("python ") and not line.startswith("python -m pytest"):
                found.append(line.split(" #")[0].strip())
    return found


ALL = sorted({(page, command) for page in PAGES for command in commands(page)})


class Parsed(Exception):
    """The program's parser accepted the command line (raised instead of running it)."""


def test_the_pages_show_commands():
    assert len([c for p, c in ALL if p == "README.md"]) >= 5 and len(ALL) >= 30


@pytest.mark.parametrize("page, command", ALL, ids=[f"{p}: {c[:60]}" for p, c in ALL])
def test_a_documented_command_parses(page, command, monkeypatch):
    for variable, value in SHELL_VARIABLES.items():
        command = command.replace(variable, value)
    argv = shlex.split(command)[1:]
    path = os.path.join(ROOT, argv[0])
    assert os.path.isfile(path), f"{page}: `{command}` names a file that does not exist"

    real_parse, real_cli = argparse.ArgumentParser.parse_args, tyro.cli

    def parse_args(self, args=None, namespace=None):
        real_parse(self, args, namespace)
        raise Parsed

    def cli(*args, **kwargs):
        real_cli(*args, **kwargs)
        raise Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_args)
    monkeypatch.setattr(tyro, "cli", cli)
    monkeypatch.setattr(sys, "argv", argv)
    monkeypatch.chdir(ROOT)
    try:
        runpy.run_path(path, run_name="__main__")
    except Parsed:
        return
    except SystemExit as e:
        if e.code in (0, None) and ("--help" in argv or "-h" in argv):
            return  # the parser printed its help, as asked
        pytest.fail(f"{page}: `{command}` is refused by its parser (exit {e.code})")
    pytest.fail(f"{page}: `{command}` ran without parsing a command line")


@pytest.mark.parametrize("page", PAGES)
def test_code_fences_open_and_close_on_their_own_lines(page):
    """A fence glued to text (e.g. "``` more prose") renders the rest of the page as code."""
    lines = open(os.path.join(ROOT, page)).read().splitlines()
    fences = [i for i, line in enumerate(lines, 1) if "```" in line]
    glued = [i for i in fences if not re.fullmatch(r"```[a-z]*", lines[i - 1].strip())]
    assert not glued and len(fences) % 2 == 0, f"{page}: fences glued to text at lines {glued} or left open"


@pytest.mark.parametrize("page", PAGES)
def test_links_and_images_point_at_files_that_exist(page):
    text = open(os.path.join(ROOT, page)).read()
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)  # [text](path#anchor) and ![alt](path)
    local = [t for t in targets if not re.match(r"[a-z]+://", t)]
    missing = [t for t in local if not os.path.exists(os.path.join(ROOT, os.path.dirname(page), t))]
    assert not missing, f"{page}: links to files that do not exist: {missing}"
