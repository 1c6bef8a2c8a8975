"""The append-only JSON Lines files that long runs write as they go."""

from experiments.jsonl import append_jsonl, drop_cut_line, open_run_log, read_jsonl


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


def test_a_cut_line_is_dropped_by_replacing_the_file_not_rewriting_it(tmp_path):
    """The rewrite goes to a new file renamed onto the log: a kill during it leaves the old
    file whole. A hard link to the old file shows it: an in-place rewrite would change it."""
    path = tmp_path / "records.jsonl"
    path.write_text('{"id": 1}\n{"id": 2')
    old = tmp_path / "old.jsonl"
    old.hardlink_to(path)
    drop_cut_line(path)
    assert path.read_text() == '{"id": 1}\n'
    assert old.read_text() == '{"id": 1}\n{"id": 2'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.jsonl", "records.jsonl"]  # no .partial left


def test_run_log_settings_are_replaced_and_fresh_discards_the_outputs(tmp_path):
    settings = tmp_path / "run.json"
    assert open_run_log(tmp_path, "log.jsonl", "run.json", '{"a": 1}', fresh=False, what="run") == {}
    append_jsonl(tmp_path / "log.jsonl", {"id": "x"})
    (tmp_path / "race.gif").write_bytes(b"stale")
    assert list(open_run_log(tmp_path, "log.jsonl", "run.json", '{"a": 1}', fresh=False, what="run",
                             outputs=("race.gif",))) == ["x"]
    assert (tmp_path / "race.gif").exists()  # a resumed run keeps its outputs
    old = tmp_path / "old.json"
    old.hardlink_to(settings)
    assert open_run_log(tmp_path, "log.jsonl", "run.json", '{"a": 2}', fresh=True, what="run",
                        outputs=("race.gif",)) == {}
    assert settings.read_text() == '{"a": 2}'
    assert old.read_text() == '{"a": 1}'  # replaced, not rewritten in place
    assert not (tmp_path / "race.gif").exists()
