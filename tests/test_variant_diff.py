"""dreamer_gru.py is dreamer_lstm.py with another recurrent cell and other defaults, nothing else.

The two scripts are duplicates on purpose (CleanRL style: each file stands alone). This test keeps
them from drifting apart: every line that differs must sit in the files' header (names of the
variant), on the VARIANT line, on a default that the paper gives differently per variant
(batch size, imagination horizon; also in the CPU preset's part marked as the variant's own, with the defaults
chosen for it), or inside the RecurrentCell class (the cell and its state). The bound of 44 changed lines is the
size of that difference today; a fix made in one file and not the other fails here.
"""

import ast
import difflib
import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MAX_CHANGED_LINES = 44
PER_VARIANT_DEFAULTS = ("batch_size", "imagination_horizon")
OWN_PART = "# this variant's own:"  # opens the CPU preset's per-variant lines (its trade, its chosen defaults)


def allowed_lines(source: str) -> set[int]:
    """1-based line numbers that may differ between the variants."""
    tree = ast.parse(source)
    lines = set(range(1, tree.body[1].end_lineno + 1))  # header comments and module docstring
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "VARIANT" for t in node.targets):
            lines.add(node.lineno)
        if isinstance(node, ast.AnnAssign) and getattr(node.target, "id", None) == "PRESETS":
            # the CPU preset's part of this variant's own: from the comment that opens it to the end of the preset
            text = source.splitlines()
            own = [n for n in range(node.lineno, node.end_lineno + 1) if OWN_PART in text[n - 1]]
            assert len(own) == 1, f"PRESETS has {len(own)} lines opening the variant's own part ({OWN_PART!r})"
            end = next(n for n in range(own[0], node.end_lineno + 1) if text[n - 1].strip() == "},")
            lines.update(range(own[0], end))
        if isinstance(node, ast.ClassDef) and node.name == "RecurrentCell":
            lines.update(range(node.lineno, node.end_lineno + 1))
        if isinstance(node, ast.ClassDef) and node.name == "Args":
            first = min([d.lineno for d in node.decorator_list] + [node.lineno])
            lines.add(first - 2)  # the section title naming the defaults column
            for field in node.body:
                if isinstance(field, ast.AnnAssign) and field.target.id in PER_VARIANT_DEFAULTS:
                    lines.add(field.lineno)
    return lines


def changed_lines(a: list[str], b: list[str]) -> tuple[list[int], list[int]]:
    """Line numbers (1-based) changed in a and in b."""
    in_a, in_b = [], []
    for tag, i1, i2, j1, j2 in difflib.SequenceMatcher(None, a, b, autojunk=False).get_opcodes():
        if tag != "equal":
            in_a += range(i1 + 1, i2 + 1)
            in_b += range(j1 + 1, j2 + 1)
    return in_a, in_b


def test_gru_script_differs_only_in_the_cell_and_defaults():
    lstm = open(os.path.join(ROOT, "dreamer_lstm.py")).read()
    gru = open(os.path.join(ROOT, "dreamer_gru.py")).read()
    in_lstm, in_gru = changed_lines(lstm.splitlines(), gru.splitlines())
    assert 0 < len(in_lstm) + len(in_gru) <= MAX_CHANGED_LINES
    stray_lstm = sorted(set(in_lstm) - allowed_lines(lstm))
    stray_gru = sorted(set(in_gru) - allowed_lines(gru))
    assert not stray_lstm, f"dreamer_lstm.py lines {stray_lstm} differ outside the cell and defaults"
    assert not stray_gru, f"dreamer_gru.py lines {stray_gru} differ outside the cell and defaults"


def test_the_allowed_regions_are_found():
    lstm = open(os.path.join(ROOT, "dreamer_lstm.py")).read()
    lines = lstm.splitlines()
    allowed = allowed_lines(lstm)
    assert any("nn.LSTMCell" in lines[i - 1] for i in allowed)
    assert any(lines[i - 1].strip().startswith("batch_size: int") for i in allowed)
    assert not any("def lambda_returns" in lines[i - 1] for i in allowed)


def test_both_presets_keep_the_papers_trade_at_equal_imagined_steps_per_update():
    """The LSTM imagines far (small batch, long horizon), the GRU near (large batch, short horizon), and each update
    imagines as many steps in both: (starts, or all B * L) * H, by hand: paper 15 * 50 * 50 = 50 * 50 * 15 = 37,500;
    CPU preset 80 * 48 = 256 * 15 = 3,840 (half of 5 * 32 and of 16 * 32 starts)."""
    import importlib

    lstm, gru = (importlib.import_module(name) for name in ("dreamer_lstm", "dreamer_gru"))
    for preset, steps in (("paper", 37_500), ("cpu", 3_840)):
        imagined = {}
        for script in (lstm, gru):
            args = script.preset_args(preset)
            starts = args.imagination_starts or args.batch_size * args.seq_len
            imagined[script.VARIANT] = starts * args.imagination_horizon
        assert imagined == {"lstm": steps, "gru": steps}, preset
        assert lstm.preset_args(preset).imagination_horizon > gru.preset_args(preset).imagination_horizon
        assert lstm.preset_args(preset).batch_size < gru.preset_args(preset).batch_size
