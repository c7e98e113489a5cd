"""What the benchmarks share: the blocks of tracks, with what each may decide, how a results CSV is read
(``read_table``) and written (``write_table``: whole, atomically; ``replace_rows``: some of its rows, locked), a
JSON file written atomically (``write_json``), the updates a checkpoint has made (``checkpoint_updates``) and the
torch threads of a measurement (``set_torch_threads``) (as Stable-Baselines3's ``common/``: small pieces the scripts
of ``benchmarks/`` import).

A track is an env seed; a block is ``(first, count)``, tracks ``first .. first + count - 1``. A result is reported on
a block that chose nothing: the block a choice was made on measures that choice with a bias in its favour.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import json
import os
import tempfile
from typing import Callable, Iterable, TextIO

TRACKS = {
    # every run's own evaluations during training (--eval-every): they choose its best.pt
    "eval": (10_000, 10),
    # the 8,000-update protocol's report (benchmarks/results/history/8000_updates/), the experiment's ghost and
    # control measurements, calibration
    "fresh": (10_100, 20),
    # screens (benchmarks/sweep.py) and the choice of the shipped agents
    "screening": (10_200, 20),
    # the CPU-budget protocol's report (benchmarks/final_protocol.py) and its peers: never used for a choice
    "report": (10_300, 30),
}
RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")  # benchmarks/results: every result
# The final protocol's budget per run, in process CPU-hours on one torch thread: each Dreamer run's
# (final_protocol.py) and each peer's (ppo_peer.py)
PROTOCOL_CPU_HOURS = 3.1


def checkpoint_updates(checkpoint: dict) -> int:
    """The updates a dreamer checkpoint (a loaded dict) has made: its first agent's (every agent of a run updates
    alike)."""
    return int(checkpoint["agents"][0]["num_updates"])


def set_torch_threads(threads: int) -> None:
    """Give torch `threads` CPU threads (0: leave torch's default, every core); ValueError below 0. One thread keeps
    a measurement beside training runs from taking their cores (the reported runs each had one)."""
    if threads < 0:
        raise ValueError(f"--torch-threads must be >= 0 (0: torch's default), got {threads}")
    if threads > 0:
        import torch

        torch.set_num_threads(threads)


def replace_file(path: str, write: Callable[[TextIO], None], newline: str | None = None) -> None:
    """Write the text file `path` atomically: write(f) into a temporary file of its own beside it (two writers never
    share one), flushed to disk, which replaces `path` once whole, so a reader or a kill never sees half of it. An
    error leaves `path` as it was and no temporary file. The file gets the permissions ``open`` would give it
    (mkstemp's are the owner's alone)."""
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(os.path.abspath(path)), suffix=".tmp")
    try:
        try:
            umask = os.umask(0)
            os.umask(umask)
            os.fchmod(fd, 0o666 & ~umask)
            f = os.fdopen(fd, "w", newline=newline)
        except BaseException:
            os.close(fd)  # (once fdopen has it, closing f closes it)
            raise
        with f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):  # (the error to raise is the write's)
            os.remove(tmp)
        raise


def write_json(path: str, data) -> None:
    """Write `data` as indented JSON to `path` atomically (replace_file)."""
    replace_file(path, lambda f: json.dump(data, f, indent=1))


def write_text(path: str, text: str) -> None:
    """Write `text` to `path` atomically (replace_file): the markdown reports."""
    replace_file(path, lambda f: f.write(text))


def track_block(first: int, count: int) -> str:
    """A block of tracks as the results name it: ``track_block(10_300, 30) == "10300..10329"``."""
    return f"{first}..{first + count - 1}"


def check_header(path: str, header, columns: tuple[str, ...], advice: str) -> None:
    """Refuse (a one-line ValueError naming the file and ending in `advice`) a CSV whose header is not `columns`; an
    empty file (no header) passes."""
    if header and tuple(header) != tuple(columns):
        raise ValueError(f"{path} has the columns {','.join(header)}, not {','.join(columns)}: {advice}")


def read_table(
    path: str, columns: tuple[str, ...] = (), other_header: str | None = None, defaults: dict[str, str] | None = None
) -> list[dict]:
    """The rows of the CSV at `path`, by column name (none while it does not exist or is empty). With `other_header`
    (advice for the user), a file whose header is not `columns` is refused as check_header refuses it: rows of two
    protocols must not be read as one table (without it, `columns` is not read). A column a row lacks or leaves empty
    takes its value in `defaults` (else it stays as it is)."""
    if not os.path.exists(path):
        return []
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if other_header is not None:
            check_header(path, reader.fieldnames, columns, other_header)
        return [{**r, **{k: v for k, v in (defaults or {}).items() if not r.get(k)}} for r in reader]


def write_table(path: str, rows: Iterable[dict], columns) -> None:
    """Write `rows` under the header `columns` as the CSV at `path` (no rows: the header alone), atomically
    (replace_file). A row with a field outside `columns` raises csv's ValueError and leaves the file as it was."""

    def write(f: TextIO) -> None:
        writer = csv.DictWriter(f, fieldnames=list(columns))
        writer.writeheader()
        writer.writerows(rows)

    replace_file(path, write, newline="")


def replace_rows(
    path: str,
    rows: Iterable[dict],
    columns: tuple[str, ...],
    key: Callable[[dict], tuple],
    order: Callable[[dict], tuple] | None = None,
    other_header: str | None = None,
    defaults: dict[str, str] | None = None,
) -> list[dict]:
    """Add `rows` to the CSV at `path` (header `columns`), replacing its rows of the same ``key(row)``, and return the
    table as written (sorted by `order`, default `key`). Measurements may finish side by side: the file is locked
    (``<path>.lock``) from the read to the write and replaced atomically, so neither a row nor the file is lost.

    With `other_header` (advice for the user), a file whose header is not `columns` is refused with a ValueError
    naming the file and its columns and ending in that advice, and left as it is: rows of two protocols must not be
    read as one table. Without it, the kept rows are read by name; a column a kept row lacks or leaves empty takes its
    value in `defaults` (else it stays empty), before `key` sees the row. A row with a field outside `columns` is
    refused (csv's ValueError), the file left as it is."""
    rows = list(rows)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path + ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        new = set(map(key, rows))
        kept = [r for r in read_table(path, columns, other_header, defaults) if key(r) not in new]
        table = sorted(kept + rows, key=order or key)
        write_table(path, table, columns)
    return table
