"""`racing study run`: a study file of named sweeps, raced as one resumable run; a killed run
resumes without repeating a race; refused files."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest

from experiments import study as study_module
from experiments.cli import main
from experiments.jsonl import read_jsonl
from experiments.study import load_study, run_study
from experiments.sweep import load_sweep
from interrupting import start_racing

# Scripted cars on short races: the study's bookkeeping, not the driving, is under test here.
TINY_STUDY = """
name = "tiny"
question = "Does the lane keeper beat constant speed, in duels and in a field?"

[shared]
track = "straight"
race_distance = 120.0
[shared.parameters]
max_steps = [400]

[[part]]
name = "duels"
lineup = ["lane-keeping", "constant-speed"]
grids = 1
[part.parameters]
max_steps = [100, 400]

[[part]]
name = "field"
lineup = ["lane-keeping*2", "constant-speed"]
grids = 2
"""


@pytest.fixture()
def tiny(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_STUDY)
    return load_study(path)


def test_a_study_is_its_parts_sweeps_raced_as_one_run(tiny, tmp_path):
    duels, field = tiny.part("duels"), tiny.part("field")
    # the shared settings, where a part does not set its own
    assert (duels.track, duels.race_distance, field.track, field.race_distance) == ("straight", 120.0) * 2
    assert duels.parameters == (("max_steps", (100, 400)),) and field.parameters == (("max_steps", (400,)),)
    jobs = tiny.schedule()
    assert [job["id"] for job in jobs] == ([f"duels/{job['id']}" for job in duels.schedule()]
                                           + [f"field/{job['id']}" for job in field.schedule()])
    assert len(jobs) == 2 * 2 + 2  # two step caps x two rotations, then a field on each of two grids
    result = run_study(tiny, tmp_path / "out", progress=False)
    assert (result["races"], result["scheduled"], result["interrupted"]) == (len(jobs), len(jobs), False)
    records = read_jsonl(tmp_path / "out" / study_module.RESULTS)
    assert sorted(r["id"] for r in records) == sorted(job["id"] for job in jobs)
    assert {r["part"] for r in records} == {"duels", "field"}
    assert all((tmp_path / "out" / r["replay"]).exists() for r in records)
    summary = json.loads((tmp_path / "out" / study_module.SUMMARY).read_text())
    assert summary["races"] == len(jobs) and set(summary["parts"]) == {"duels", "field"}
    # a part's summary is its sweep's of the same races
    from experiments.sweep import summarize
    in_sweep = [{**r, "id": r["id"].removeprefix("duels/")} for r in records if r["part"] == "duels"]
    assert summary["parts"]["duels"] == json.loads(json.dumps(summarize(duels, in_sweep)))


@pytest.mark.slow  # a real local Ray instance (about 30 s to start); the sweep's Ray leg is slow too
def test_a_study_on_a_local_ray_cluster_records_what_one_in_this_process_does(tiny, tmp_path):
    pytest.importorskip("ray")
    runs = {name: run_study(tiny, tmp_path / name, progress=False, **options)
            for name, options in {"here": dict(), "ray": dict(backend="ray", workers=2)}.items()}
    assert runs["ray"]["interrupted"] is False and runs["ray"]["parts"] == runs["here"]["parts"]

    def records(name):  # without the action times, which differ run to run
        return {r["id"]: {**r, "agents": [{k: v for k, v in car.items() if not k.startswith("act_time")}
                                          for car in r["agents"]]}
                for r in read_jsonl(tmp_path / name / study_module.RESULTS)}

    assert records("ray") == records("here")
    (invocation,) = json.loads((tmp_path / "ray" / study_module.RUN_LOG).read_text())["invocations"]
    assert (invocation["backend"], invocation["workers"], invocation["races"]) == ("ray", 2, len(tiny.schedule()))


def test_a_killed_study_resumes_without_repeating_a_race(tmp_path):
    """SIGKILL to a real `racing study run` mid-run (no clean-up at all): rerun, every race
    is recorded once and the study is complete."""
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_STUDY.replace("grids = 1", "grids = 6").replace("grids = 2", "grids = 6"))
    out = tmp_path / "out"
    results = out / study_module.RESULTS
    process = start_racing(["study", "run", str(path), "--out", str(out), "--no-compile-cache"])
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and process.poll() is None and len(read_jsonl(results)) < 3:
            time.sleep(0.05)
        assert process.poll() is None, "the study ended before it could be killed"
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    before = [r["id"] for r in read_jsonl(results)]
    scheduled = [job["id"] for job in load_study(path).schedule()]
    assert 3 <= len(before) < len(scheduled)
    # the killed invocation logged its races as they ended: all of them, or all but one when the
    # kill fell between a record's line and the log's rewrite
    (killed,) = json.loads((out / study_module.RUN_LOG).read_text())["invocations"]
    assert len(before) - 1 <= killed["races"] <= len(before) and killed["seconds"] > 0
    assert main(["study", "run", str(path), "--out", str(out), "--no-compile-cache"]) == 0
    after = [r["id"] for r in read_jsonl(results)]
    assert after[: len(before)] == before  # the races run before the kill were kept, not run again
    assert sorted(after) == sorted(scheduled) and len(set(after)) == len(after)
    resumed = json.loads((out / study_module.RUN_LOG).read_text())["invocations"][1]
    assert resumed["races"] == len(scheduled) - len(before)


@pytest.mark.parametrize("text, message", [
    ('name = "x"\nquestion = "q"\nlineups = []\n', "unknown keys"),
    ('name = "x"\nquestion = "q"\n', "at least one"),
    ('question = "q"\n[[part]]\nname = "a"\nlineup = ["lane-keeping"]\n[part.parameters]\ngrids_x = [1]\n',
     "name is a word"),
    ('name = "x"\n[[part]]\nname = "a"\nlineup = ["lane-keeping"]\n[part.parameters]\nmax_steps = [10]\n', "question"),
    ('name = "x"\nquestion = "q"\n[[part]]\nlineup = ["lane-keeping"]\n', "part 1: a part needs a name"),
    ('name = "x"\nquestion = "q"\n[[part]]\nname = "a/b"\nlineup = ["lane-keeping"]\n[part.parameters]\nmax_steps = [10]\n',
     "name is a word"),
    ('name = "x"\nquestion = "q"\n[[part]]\nname = "a"\nlineup = ["lane-keeping"]\n[part.parameters]\nmax_steps = [10]\n'
     '[[part]]\nname = "a"\nlineup = ["lane-keeping"]\n[part.parameters]\nmax_steps = [20]\n', "repeated: ['a']"),
    ('name = "x"\nquestion = "q"\n[[part]]\nname = "a"\nlineup = ["lane-keeping"]\ngridz = 2\n', "part 'a': unknown keys"),
    ('name = "x"\nquestion = "q"\n[shared]\nname = "s"\n[[part]]\nname = "a"\nlineup = ["lane-keeping"]\n', "[shared]"),
    ("name = [", "not valid TOML"),
])
def test_bad_study_files_are_refused_naming_what_is_wrong(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as error:
        load_study(path)
    assert message in str(error.value)


def test_the_command_line_refuses_a_missing_file_an_unknown_agent_and_another_studys_folder(tiny, tmp_path, capsys):
    assert main(["study", "run", str(tmp_path / "nowhere.toml")]) == 2
    assert "no study file" in capsys.readouterr().err
    unknown = tmp_path / "unknown.toml"
    unknown.write_text(TINY_STUDY.replace('"constant-speed"]', '"warp-drive"]'))
    assert main(["study", "run", str(unknown), "--out", str(tmp_path / "unknown")]) == 2
    assert "unknown agent spec 'warp-drive'" in capsys.readouterr().err
    assert not (tmp_path / "unknown" / study_module.RESULTS).exists()  # refused before any race
    other = tmp_path / "other.toml"
    other.write_text(TINY_STUDY.replace('name = "tiny"', 'name = "other"').replace("grids = 2", "grids = 1"))
    run_study(load_study(other), tmp_path / "out", progress=False)
    path = tmp_path / "tiny.toml"
    assert main(["study", "run", str(path), "--out", str(tmp_path / "out"), "--no-compile-cache"]) == 2
    assert "different study" in capsys.readouterr().err


def test_the_outlook_study_declares_every_pair_on_every_circuit_fields_and_place_weights():
    """docs/studies/outlook.toml: at least 1,000 races; every pair of the five agents on all
    25 circuits with both cars and both slots; 6-car fields on 8 circuits; each game planner
    with place-switched weights against itself."""
    from pathlib import Path

    from racing_env.track import circuit_names

    outlook = load_study(Path(__file__).parents[1] / "docs" / "studies" / "outlook.toml")
    jobs = outlook.schedule()
    assert len(jobs) >= 1000
    duels = [sweep for name, sweep in outlook.parts if name.startswith("duel-")]
    pairs = {frozenset(spec.split(":")[0] for spec in sweep.specs) for sweep in duels}
    agents = {"ilqr", "ilqgame-ol", "ilqgame-fb", "ilqgame-leader", "raceline"}
    assert pairs == {frozenset((a, b)) for a in agents for b in agents if a != b}
    for sweep in duels:
        points = sweep.points()
        assert {p["track"] for p in points} == set(circuit_names()) and {p["car"] for p in points} == {"av21", "paper"}
        assert len(sweep.schedule()) == 25 * 2 * 2  # circuits x cars x slots
    fields = outlook.part("fields")
    assert fields.cars == 6 and len({p["track"] for p in fields.points()}) >= 8
    for planner in ("ilqgame-ol", "ilqgame-fb", "ilqgame-leader"):
        switched, plain = outlook.part(f"place-{planner.split('-')[1]}").specs
        assert switched.startswith(plain) and "trailing." in switched and "leading." in switched
