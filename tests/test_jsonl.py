"""The append-only JSON Lines files that long runs write as they go."""

from experiments.jsonl import append_jsonl, drop_cut_line, read_jsonl


def test_a_cut_last_line_is_skipped_and_dropped_before_the_next_record(tmp_path):
    path = tmp_path / "records.jsonl"
    assert read_jsonl(path) == []
    drop_cut_line(path)  # no file: nothing to do
    assert not path.exists()
    append_jsonl(path, {"id": 1})
    append_jsonl(path, {"id": 2})
    whole = path.read_text()
    path.write_text(whole + '{"id": 3, "val')
    assert read_jsonl(path) == [{"id": 1}, {"id": 2}]
    drop_cut_line(path)
    assert path.read_text() == whole
    drop_cut_line(path)  # a whole file is left alone
    assert path.read_text() == whole
    append_jsonl(path, {"id": 3})
    assert read_jsonl(path) == [{"id": 1}, {"id": 2}, {"id": 3}]
    path.write_text('{"id": 1')  # a single cut line
    drop_cut_line(path)
    assert path.read_text() == ""
