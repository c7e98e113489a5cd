"""benchmarks/common.py: the blocks of tracks do not overlap, and a results CSV rewritten by replace_rows keeps every
row of its own and of writers beside it, and refuses a file of other columns."""

import csv
import json
import multiprocessing
import os

import pytest

import common

COLUMNS = ("seed", "tracks", "value")


def read(path) -> list[tuple]:
    with open(path, newline="") as f:
        return [(r["seed"], r["tracks"], r["value"]) for r in csv.DictReader(f)]


def key(r: dict) -> tuple:
    return int(r["seed"]), r["tracks"]


def test_the_blocks_of_tracks_are_disjoint_and_named_as_the_results_name_them():
    seen = [set(range(first, first + count)) for first, count in common.TRACKS.values()]
    assert sum(map(len, seen)) == len(set().union(*seen))  # no track serves two purposes
    assert common.track_block(*common.TRACKS["report"]) == "10300..10329"
    assert common.track_block(*common.TRACKS["eval"]) == "10000..10009"


def test_a_row_replaces_the_row_of_its_key_and_the_table_is_sorted(tmp_path):
    path = str(tmp_path / "rows.csv")
    common.replace_rows(path, [{"seed": 12, "tracks": "a", "value": 1}, {"seed": 3, "tracks": "a", "value": 2}],
                        COLUMNS, key)  # fmt: skip
    table = common.replace_rows(path, [{"seed": 12, "tracks": "a", "value": 5}], COLUMNS, key)
    assert read(path) == [("3", "a", "2"), ("12", "a", "5")]  # 3 before 12: the key's order, not the text's
    assert [int(r["seed"]) for r in table] == [3, 12]
    assert not [name for name in os.listdir(tmp_path) if name.endswith(".tmp")]  # no temporary file left


def test_a_file_of_other_columns_is_refused_and_left_as_it_is(tmp_path):
    path = tmp_path / "learning_final.csv"
    path.write_text("exp_name,seed\nlearning_lstm,11\n")
    before = path.read_bytes()
    with pytest.raises(ValueError, match=r"learning_final.csv has the columns exp_name,seed, not seed,tracks,value: "
                                         r"move it away"):  # fmt: skip
        common.replace_rows(str(path), [{"seed": 1, "tracks": "a", "value": 0}], COLUMNS, key,
                            other_header="move it away")  # fmt: skip
    assert path.read_bytes() == before


def test_a_row_with_a_field_outside_the_columns_is_refused_and_the_file_left_as_it_is(tmp_path):
    path = str(tmp_path / "rows.csv")
    common.replace_rows(path, [{"seed": 1, "tracks": "a", "value": 0}], COLUMNS, key)
    with pytest.raises(ValueError, match="fields not in fieldnames"):
        common.replace_rows(path, [{"seed": 2, "tracks": "a", "value": 0, "typo": 1}], COLUMNS, key)
    assert read(path) == [("1", "a", "0")] and not [name for name in os.listdir(tmp_path) if name.endswith(".tmp")]


def test_an_old_row_without_a_column_takes_its_default_before_the_key_sees_it(tmp_path):
    path = tmp_path / "peer.csv"  # written before the tracks column
    path.write_text("seed,value\n11,657.7\n")
    common.replace_rows(str(path), [{"seed": 11, "tracks": "new", "value": 700}], COLUMNS, key,
                        defaults={"tracks": "old"})  # fmt: skip
    assert read(path) == [("11", "new", "700"), ("11", "old", "657.7")]  # beside it, not over it
    common.replace_rows(str(path), [{"seed": 11, "tracks": "old", "value": 660}], COLUMNS, key)
    assert read(path) == [("11", "new", "700"), ("11", "old", "660")]


def test_a_table_is_read_by_name_with_defaults_for_missing_or_empty_cells_and_checked_only_when_asked(tmp_path):
    assert common.read_table(str(tmp_path / "none.csv"), COLUMNS, "advice") == []  # no file yet: no rows
    path = tmp_path / "rows.csv"
    path.write_text("seed,value\n11,1.5\n12,\n")
    assert common.read_table(str(path), defaults={"value": "0", "tracks": "old"}) == [
        {"seed": "11", "value": "1.5", "tracks": "old"}, {"seed": "12", "value": "0", "tracks": "old"}]
    with pytest.raises(ValueError, match=r"rows.csv has the columns seed,value, not seed,tracks,value: move it"):
        common.read_table(str(path), COLUMNS, other_header="move it")
    path.write_text("")  # empty: no header to refuse
    assert common.read_table(str(path), COLUMNS, other_header="move it") == []


def write_many(path: str, seed: int, n: int) -> None:
    for i in range(n):
        common.replace_rows(path, [{"seed": seed, "tracks": str(i), "value": i}], COLUMNS, key)


def test_writers_side_by_side_lose_no_row(tmp_path):
    path = str(tmp_path / "rows.csv")
    processes = [multiprocessing.get_context("fork").Process(target=write_many, args=(path, s, 40)) for s in (1, 2)]
    for p in processes:
        p.start()
    for p in processes:
        p.join()
    assert all(p.exitcode == 0 for p in processes)
    assert sorted(read(path)) == sorted((str(s), str(i), str(i)) for s in (1, 2) for i in range(40))


def test_a_whole_table_is_written_at_once_or_not_at_all(tmp_path):
    path = str(tmp_path / "table.csv")
    common.write_table(path, [{"seed": 1, "score": 2.5}], ("seed", "score"))
    with open(path, newline="") as f:
        assert list(csv.DictReader(f)) == [{"seed": "1", "score": "2.5"}]
    before = open(path).read()
    with pytest.raises(ValueError, match="fields not in fieldnames"):  # a field outside the columns, after a good row
        common.write_table(path, [{"seed": 3, "score": 1.0}, {"seed": 4, "bogus": 0}], ("seed", "score"))
    assert open(path).read() == before and os.listdir(tmp_path) == ["table.csv"]
    common.write_table(path, [], ("seed", "score"))  # no rows: the header alone
    assert open(path).read().splitlines() == ["seed,score"]
    full = OSError(28, "No space left on device")  # a file that cannot be opened: its own error, not the clean-up's

    def refuse(*args, **kwargs):
        raise full

    monkeypatch_open = pytest.MonkeyPatch()
    monkeypatch_open.setattr(common.os, "fdopen", refuse)
    try:
        with pytest.raises(OSError) as raised:
            common.write_table(path, [{"seed": 5, "score": 0.0}], ("seed", "score"))
    finally:
        monkeypatch_open.undo()
    assert raised.value is full and open(path).read().splitlines() == ["seed,score"]
    assert os.listdir(tmp_path) == ["table.csv"]  # the temporary file is gone


def test_a_json_file_is_written_whole_with_the_permissions_open_gives(tmp_path):
    path = str(tmp_path / "spec.json")
    umask = os.umask(0o022)
    try:
        common.write_json(path, {"seeds": [21, 22]})
    finally:
        os.umask(umask)
    assert json.load(open(path)) == {"seeds": [21, 22]} and os.stat(path).st_mode & 0o777 == 0o644  # not mkstemp's 0600
    with pytest.raises(TypeError, match="not JSON serializable"):  # the file stays as it was, no temporary file left
        common.write_json(path, {"seeds": {21}})
    assert json.load(open(path)) == {"seeds": [21, 22]} and os.listdir(tmp_path) == ["spec.json"]


def test_a_report_is_written_whole_and_replaces_the_last(tmp_path):
    path = str(tmp_path / "learning_final.md")
    common.write_text(path, "# old\n")
    common.write_text(path, "# new\n\n| a |\n")
    assert open(path).read() == "# new\n\n| a |\n" and os.listdir(tmp_path) == ["learning_final.md"]
    with pytest.raises(TypeError):  # not text: the report stays as it was, no temporary file left
        common.write_text(path, b"bytes")
    assert open(path).read() == "# new\n\n| a |\n" and os.listdir(tmp_path) == ["learning_final.md"]


@pytest.mark.parametrize("tool, work", [("norm_gap", "norm_gap"), ("pedal_response", "pedal_response"),
                                        ("learning", "run_mode")])  # fmt: skip
def test_the_measuring_tools_take_their_torch_threads_before_the_work_and_refuse_a_negative_count(tool, work,
                                                                                                  monkeypatch):
    """--torch-threads N sets torch's threads before the tool measures anything (0, the default, leaves torch's own);
    a negative count ends in the tool's one-line error before any work."""
    import importlib

    import torch

    module = importlib.import_module(tool)
    calls = []
    monkeypatch.setattr(torch, "set_num_threads", lambda n: calls.append(("threads", n)))
    monkeypatch.setattr(module, work, lambda *a, **k: calls.append(("work",)) or ({} if tool == "norm_gap" else []))
    monkeypatch.setattr(module, "table", lambda *a, **k: "", raising=False)
    main = module.cli if tool == "learning" else module.main
    argv = ["--protocol-report"] if tool == "learning" else ["a.pt"]
    main([*argv, "--torch-threads", "1"])
    main(argv)
    assert calls == [("threads", 1), ("work",), ("work",)]
    with pytest.raises(SystemExit, match=rf"^{tool}.py: error: --torch-threads must be >= 0 \(0: torch's default\), "
                                         r"got -1$"):  # fmt: skip
        main([*argv, "--torch-threads", "-1"])
    assert calls == [("threads", 1), ("work",), ("work",)]
