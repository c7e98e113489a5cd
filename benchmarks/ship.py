"""The shipped agents (``learning.py --protocol-ship``): ``pretrained/<variant>_cpu.pt`` is replaced by the final
policy (latest.pt at the budget) of the final protocol's seed that drives best on the screening tracks, never the
report tracks, with the evaluation policy (the mean action, the scripts' --eval-policy), if it beats the shipped agent
on the same tracks; acting-only (evaluate.py --export), loadable with weights_only=True, at most SHIP_MAX_BYTES.
``ship_<variant>.csv`` records every decision: the candidates, their readings and which one the file holds after it.
"""

from __future__ import annotations

import os

from common import RESULTS, TRACKS, read_table, track_block, write_table
from final_protocol import POLICY_NAMES, PROTOCOL_SEEDS, check_finite, protocol_cpu_hours, protocol_run

SHIP_TRACKS = TRACKS["screening"]  # the shipped agents are chosen on the screening tracks
SHIP_POLICY = "mean-action"
SHIP_MAX_BYTES = 10_000_000
SHIP_COLUMNS = ("decision", "variant", "candidate", "checkpoint", "return", "progress", "abs_steer", "shipped")


def read_record(path: str) -> list[dict]:
    """The shipping record at `path` (none yet: []): its rows as SHIP_COLUMNS, those written before the ``decision``
    column existed as decision 1. A record with another column is refused, naming it, before anything is measured."""
    rows = read_table(path, SHIP_COLUMNS, defaults={"decision": "1"})
    foreign = sorted({key for row in rows for key in row} - set(SHIP_COLUMNS))
    if foreign:
        raise ValueError(f"{path}: not a shipping record (columns {', '.join(foreign)} are not of "
                         f"{', '.join(SHIP_COLUMNS)}); move it aside")  # fmt: skip
    return rows


def record_decision(path: str, kept: list[dict], rows: list[dict]) -> None:
    """Write the record at `path`: its `kept` rows (read_record), then one shipping decision's `rows`, numbered one
    after the last (``decision``), so that no earlier decision is lost: the shipped file's content changes, and
    the record is all that says what it held when."""
    decision = 1 + max((int(r["decision"]) for r in kept), default=0)
    write_table(path, kept + [{**row, "decision": decision} for row in rows], SHIP_COLUMNS)


def ship_rows(variant: str, runs_dir: str, shipped: str, seeds: tuple[int, ...] = PROTOCOL_SEEDS) -> list[dict]:
    """The shipped agent and the final policy of each of `seeds` (refused, naming it, while a run is short of its
    budget and not stopped by the non-finite guard: protocol_cpu_hours) driven with SHIP_POLICY on SHIP_TRACKS: one
    row each (SHIP_COLUMNS, ``shipped`` False), the shipped agent first. A missing shipped file is a candidate that
    lost already."""
    import evaluate
    from utils.checkpoint import read_checkpoint

    candidates = []
    for seed in seeds:
        run = protocol_run(variant, seed, runs_dir)
        latest = os.path.join(run, "checkpoints", "latest.pt")
        protocol_cpu_hours(run, read_checkpoint(latest)[1])  # before any driving
        candidates.append((f"seed {seed}", latest))
    rows = []
    for name, path in ([("shipped", shipped)] if os.path.exists(shipped) else []) + candidates:
        means = evaluate.track_means(evaluate.evaluate_checkpoint(path, *SHIP_TRACKS, (SHIP_POLICY,))[SHIP_POLICY])
        rows.append({"variant": variant, "candidate": name, "checkpoint": path, "return": round(means["return"], 2),
                     "progress": round(means["progress"], 4), "abs_steer": round(means["abs_steer"], 4),
                     "shipped": False})  # fmt: skip
    return rows


def ship(variant: str, runs_dir: str, shipped: str, results_dir: str = RESULTS,
         seeds: tuple[int, ...] = PROTOCOL_SEEDS) -> str:
    """Measure the candidates (ship_rows: the final policies of `seeds`); if the best seed's return beats the shipped
    agent's, export it over `shipped` (atomically; refused above SHIP_MAX_BYTES, the shipped file unchanged).
    ``ship_<variant>.csv`` in `results_dir` gets the rows as a new decision (record_decision), its ``shipped`` column
    marking the agent `shipped` holds afterwards. Returns a markdown table of the rows."""
    from utils.checkpoint import export_policy, read_checkpoint

    record = os.path.join(results_dir, f"ship_{variant}.csv")
    kept = read_record(record)  # (refused before anything is driven)
    rows = ship_rows(variant, runs_dir, shipped, seeds)
    check_finite(rows, ("return",), f"ship_{variant}")
    current = next((r for r in rows if r["candidate"] == "shipped"), None)
    best = max((r for r in rows if r["candidate"] != "shipped"), key=lambda r: r["return"])
    winner = best if current is None or best["return"] > current["return"] else current
    os.makedirs(results_dir, exist_ok=True)
    if winner is best:
        script = read_checkpoint(best["checkpoint"])[0]
        os.makedirs(os.path.dirname(os.path.abspath(shipped)), exist_ok=True)
        size = export_policy(script, best["checkpoint"], shipped + ".new")
        if size > SHIP_MAX_BYTES:
            os.remove(shipped + ".new")
            if current is not None:  # the record says what stays shipped
                current["shipped"] = True
            record_decision(record, kept, rows)
            raise ValueError(f"{best['checkpoint']} exports to {size / 1e6:.1f} MB, over the {SHIP_MAX_BYTES / 1e6:g}"
                             f" MB a shipped agent may take; {shipped} is unchanged (ship_{variant}.csv)")
    winner["shipped"] = True
    try:
        record_decision(record, kept, rows)  # the record before the file it names
    except BaseException:
        if winner is best:
            os.remove(shipped + ".new")
        raise
    if winner is best:
        os.replace(shipped + ".new", shipped)
    lines = [f"{variant}: {POLICY_NAMES[SHIP_POLICY]} on tracks {track_block(*SHIP_TRACKS)}", "",
             "| candidate | return | progress | \\|steer\\| | shipped |", "|---|---|---|---|---|"]  # fmt: skip
    lines += [f"| {r['candidate']} | {r['return']:.1f} | {r['progress']:.2f} | {r['abs_steer']:.2f} | "
              f"{'yes' if r['shipped'] else ''} |" for r in rows]  # fmt: skip
    if winner is best and os.path.basename(os.path.dirname(os.path.abspath(shipped))) == "pretrained":  # the pages
        lines += ["", f"{shipped} is now {best['candidate']}'s final policy: update what README.md and docs/races.md "
                  "say of the shipped agents"]  # fmt: skip
    return "\n".join(lines) + "\n"
