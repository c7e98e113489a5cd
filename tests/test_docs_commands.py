"""Every command the README and docs/ show must run as written: each `python <file> ...` line is parsed by its own
program's command-line parser (argparse or tyro), which stops there (a dry run). A renamed or removed flag, a wrong
value type, or a script or an input file in the repository (a path to a .pt, .csv, ... that no placeholder marks)
that no longer exists fails here, naming the page and the command."""

from __future__ import annotations

import argparse
import csv
import glob
import os
import re
import runpy
import shlex
import sys

import pytest
import tyro

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAGES = ["README.md", "benchmarks/README.md",
         *sorted(os.path.relpath(p, ROOT) for p in glob.glob(os.path.join(ROOT, "docs", "*.md")))]
LAB_PAGES = sorted(os.path.relpath(p, ROOT) for p in glob.glob(os.path.join(ROOT, "docs", "lab", "*.md")))
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


OUTPUT_FLAGS = {"--out", "--results", "--export", "--json", "--csv"}  # a path after one is written, not read


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
    tokens = [part for token in argv for part in (token.split("=", 1) if token.startswith("--") else [token])]
    inputs = [token for before, token in zip(["", *tokens], tokens) if before not in OUTPUT_FLAGS and "/" in token
              and re.search(r"\.(pt|csv|json|zip|pkl)$", token) and not re.search(r"[<>*$]", token)]  # fmt: skip
    missing = [token for token in inputs if not os.path.exists(os.path.join(ROOT, token))]
    assert not missing, f"{page}: `{command}` reads files that do not exist: {missing}"

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


@pytest.mark.parametrize("page", PAGES + LAB_PAGES)
def test_code_fences_open_and_close_on_their_own_lines(page):
    """A fence glued to text (e.g. "``` more prose") renders the rest of the page as code."""
    lines = open(os.path.join(ROOT, page)).read().splitlines()
    fences = [i for i, line in enumerate(lines, 1) if "```" in line]
    glued = [i for i in fences if not re.fullmatch(r"```[a-z]*", lines[i - 1].strip())]
    assert not glued and len(fences) % 2 == 0, f"{page}: fences glued to text at lines {glued} or left open"


@pytest.mark.parametrize("page", PAGES + LAB_PAGES)
def test_links_and_images_point_at_files_that_exist(page):
    text = open(os.path.join(ROOT, page)).read()
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)  # [text](path#anchor) and ![alt](path)
    targets += re.findall(r'<img src="([^"]+)"', text)
    local = [t for t in targets if not re.match(r"[a-z]+://", t)]
    missing = [t for t in local if not os.path.exists(os.path.join(ROOT, os.path.dirname(page), t))]
    assert not missing, f"{page}: links to files that do not exist: {missing}"


def heading_anchors(path: str) -> set[str]:
    """The anchors GitHub gives a Markdown page's headings: lower case, spaces to hyphens, every character but
    letters, digits, hyphens and underscores dropped (code fences' comment lines are not headings)."""
    text = re.sub(r"```.*?```", "", open(path).read(), flags=re.S)
    headings = re.findall(r"^#{1,6} +(.+?) *$", text, flags=re.M)
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in headings}


def test_heading_anchors_follow_github():
    page = os.path.join(ROOT, "docs", "deviations.md")
    assert "the-cpu-preset---preset-cpu" in heading_anchors(page)  # "## The CPU preset (`--preset cpu`)"
    history = os.path.join(ROOT, "docs", "lab", "learning_history.md")
    assert "the-8000-update-protocols-results" in heading_anchors(history)  # "### The 8,000-update protocol's results"


@pytest.mark.parametrize("page", PAGES + LAB_PAGES)
def test_links_to_a_section_name_one_that_exists(page):
    text = open(os.path.join(ROOT, page)).read()
    links = re.findall(r"\]\(([^)#\s]*)#([^)\s]+)\)", text)  # [text](path#anchor), [text](#anchor)
    broken = [f"{target}#{anchor}" for target, anchor in links if not re.match(r"[a-z]+://", target)
              and anchor not in heading_anchors(os.path.join(ROOT, os.path.dirname(page), target) if target
                                         else os.path.join(ROOT, page))]
    assert not broken, f"{page}: links to sections that do not exist: {broken}"


# --- The reference pages: short, and the lab notebook's notes in docs/lab/ ------------------------------
PAGE_LIMIT = 12_000  # bytes, as `wc -c` counts them
LAB_NOTES = ("sitting", "our runs", "these vms")  # a lab notebook's words; docs/lab/ may use them


@pytest.mark.parametrize("page", PAGES)
def test_a_reference_page_is_short_and_leaves_lab_notes_to_docs_lab(page):
    text = open(os.path.join(ROOT, page), "rb").read()
    assert len(text) <= PAGE_LIMIT, f"{page}: {len(text)} bytes, over {PAGE_LIMIT}: move lab notes to docs/lab/"
    found = [word for word in LAB_NOTES if re.search(rf"\b{word}", text.decode(), flags=re.I)]
    assert not found, f"{page}: {found} belong in docs/lab/, not on a reference page"


# --- The experiment as it was run, and the commands docs/experiment.md gives to reproduce it ---------------------
# Each value is hard-coded from what the results record (test_the_recorded_experiment_is_the_one_in_the_results
# reads them back from the files where it can):
AS_RUN = {
    "variants": ("lstm", "gru"),  # ghost_vs_control.csv, history/8000_updates/learning_final.csv (HISTORY)
    "seeds": (11, 12, 13),  # head_to_head.csv's seed pairs 11,11 12,12 13,13; ghost_vs_control.csv
    "preset": "cpu",  # learning_final.csv: the learning benchmark's --preset cpu runs (the code of commit 59e2cc7)
    "overrides": (),  # ditto: only a spec without overrides names its single trials learning_<variant>
    "single_updates": 8000,  # learning_final.csv: updates
    "ghost_updates": 2000,  # ghost_vs_control.csv: updates
    "race_episodes": 150,  # head_to_head.csv: the last tournament after 150 races
    "tournament_every": 50,  # head_to_head.csv: tournaments after 0, 50, 100, 150 races
    "tournament_races": 100,  # head_to_head.csv: eval_races
    "race_train_steps": 25,  # docs/deviations.md and docs/lab/experiment_log.md: 25 updates per agent per race
    "report_every": 500,  # docs/lab/experiment_log.md: a trial writes one event file per 500 updates
    "torch_threads": 1,  # docs/lab/experiment_log.md: one-thread trials, two (three in the race stage) on two cores
    "controls": False,  # benchmarks/results/experiment.md: "this experiment's ghost stage ran without controls"
}
# The evaluation policy per stage: the single stage's best.pt was chosen by the sampled evaluation (ghost_vs_control
# in docs/lab/experiment_log.md; experiment.FIELD_ORIGINS); policy_rule.md then chose the mean action, used from
# the ghost stage on (docs/lab/experiment_log.md), and the tables are measured with it.
EVAL_POLICY = {"single": "stochastic", "ghost": "mean-action", "race": "mean-action"}
SECOND_POLICY = "stochastic"  # head_to_head_stochastic.csv: the same tournaments raced sampled
FRESH_TRACKS = 20  # ghost_vs_control.csv: the 20 fresh tracks 10100..10119
HISTORY = os.path.join("history", "8000_updates")  # the single stage's rows and the rule, under benchmarks/results
RACE_NUM_CPUS = 3  # docs/lab/experiment_log.md: the race stage ran its three seed pairs at once (--num-cpus 3)


def reproduction_commands(text: str) -> list[list[str]]:
    """The experiment.py command lines (arguments only) of the first code block under "## Reproducing the reported
    experiment"."""
    assert "\n## Reproducing the reported experiment\n" in text, "no section 'Reproducing the reported experiment'"
    section = text.split("\n## Reproducing the reported experiment\n", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```bash\n(.*?)```", section, flags=re.S)
    assert block, "the reproduction section has no bash block"
    lines = [line.split(" #")[0] for line in block.group(1).splitlines()]
    return [shlex.split(line)[2:] for line in lines if line.startswith("python benchmarks/experiment.py")]


def mismatches(argvs: list[list[str]]) -> list[str]:
    """What in these experiment.py command lines differs from the experiment as it was run (empty: nothing). They
    are parsed with today's experiment.py, while the page runs them at commit 59e2cc7 (both parse them; a flag
    renamed since would pass here, as the checkout that CI gets may lack the history to parse them as of then)."""
    import experiment

    specs = [tyro.cli(experiment.Spec, args=argv) for argv in argvs]
    runs = [s for s in specs if not s.aggregate_only and not s.status]
    found = []
    stages = [stage for s in runs for stage in s.stages]
    if stages != ["single", "ghost", "race"]:
        found.append(f"the commands run the stages {stages}, not single, ghost, race once each in order")
    if len({s.storage for s in specs}) > 1:
        found.append("the commands use different --storage")
    for s in runs:
        found += [f"{' '.join(s.stages)}: {k} {getattr(s, k)!r}, as run {v!r}" for k, v in AS_RUN.items()
                  if getattr(s, k) != v]  # fmt: skip
        found += [f"{stage}: --eval-policy {s.eval_policy}, as run {EVAL_POLICY[stage]}" for stage in s.stages
                  if s.eval_policy != EVAL_POLICY[stage]]  # fmt: skip
        if "race" in s.stages and s.num_cpus != RACE_NUM_CPUS:
            found.append(f"race: --num-cpus {s.num_cpus}, as run {RACE_NUM_CPUS}")
    tables = [s for s in specs if s.aggregate_only]
    if len(tables) != 1 or specs[-1] is not tables[0]:
        found.append("the last command must be the one --aggregate-only that writes the tables")
    for s in tables:
        wanted = {"eval_policy": EVAL_POLICY["race"], "second_policy": SECOND_POLICY, "fresh_tracks": FRESH_TRACKS,
                  "controls": AS_RUN["controls"]}  # fmt: skip
        found += [f"aggregation: {k} {getattr(s, k)!r}, as run {v!r}" for k, v in wanted.items() if getattr(s, k) != v]
    return found


def test_the_experiment_page_gives_the_commands_that_made_the_results():
    argvs = reproduction_commands(open(os.path.join(ROOT, "docs", "experiment.md")).read())
    assert not mismatches(argvs), f"docs/experiment.md's reproduction differs from the run: {mismatches(argvs)}"


@pytest.mark.parametrize("commands", [
    ["--seeds 11 12 13"],  # what the page showed before: every stage with the default (mean-action) evaluation
    ["--stages single ghost race --no-controls --num-cpus 3",
     "--aggregate-only --no-controls --second-policy stochastic"],  # one policy for every stage
    ["--stages single --eval-policy stochastic --no-controls", "--stages ghost race --eval-policy mean-action "
     "--no-controls --num-cpus 3 --race-train-steps 100", "--aggregate-only --no-controls --second-policy stochastic"],
    # the scripts' 100 updates per race instead of the experiment's 25
])  # fmt: skip
def test_the_check_refuses_commands_that_ran_another_experiment(commands):
    assert mismatches([shlex.split(c) for c in commands])


def test_the_recorded_experiment_is_the_one_in_the_results():
    results = os.path.join(ROOT, "benchmarks", "results")

    def rows(name):
        with open(os.path.join(results, name), newline="") as f:
            return list(csv.DictReader(f))

    seeds = {int(s) for s in AS_RUN["seeds"]}
    for name in ("head_to_head.csv", f"head_to_head_{SECOND_POLICY}.csv"):
        head = rows(name)
        assert {int(r["seed_pair"].split(",")[0]) for r in head} == seeds
        every, last = AS_RUN["tournament_every"], AS_RUN["race_episodes"]
        assert {int(r["races_trained"]) for r in head} == set(range(0, last + 1, every))
        assert {int(r["eval_races"]) for r in head} == {AS_RUN["tournament_races"]}
    ghost = rows("ghost_vs_control.csv")
    assert {(r["variant"], int(r["seed"])) for r in ghost} == {(v, s) for v in AS_RUN["variants"] for s in seeds}
    assert {int(r["updates"]) for r in ghost} == {AS_RUN["ghost_updates"]}
    single = rows(os.path.join(HISTORY, "learning_final.csv"))
    assert {(r["variant"], int(r["seed"])) for r in single} == {(v, s) for v in AS_RUN["variants"] for s in seeds}
    assert {int(r["updates"]) for r in single} == {AS_RUN["single_updates"]}
    rule = open(os.path.join(results, HISTORY, "policy_rule.md")).read()
    assert f"Evaluation policy: **{EVAL_POLICY['race']}**" in rule
    summary = open(os.path.join(results, "experiment.md")).read()
    assert ("ran without controls" in summary) == (not AS_RUN["controls"])
