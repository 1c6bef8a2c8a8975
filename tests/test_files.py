"""Safe writes to a run's output folder: files written whole, one writer at a time."""

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from experiments.cli import main
from experiments.files import LOCK, FolderInUse, one_writer, replace_atomically

HOLDER = """
import sys, time
from experiments.files import one_writer
with one_writer(sys.argv[1], "test run"):
    print("held", flush=True)
    time.sleep(600)
"""


def test_a_ctrl_c_during_a_write_stops_the_run_once_the_whole_file_is_in_place(tmp_path):
    """SIGINT while numpy writes a zip: the file is written whole and replaces the old one,
    then KeyboardInterrupt (not the zip writer's error of being cut in half)."""
    path = tmp_path / "arrays.npz"
    np.savez(path, a=np.zeros(3))
    new = np.arange(100_000.0)

    def write(partial):
        with open(partial, "wb") as sink:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C mid-write: unheld, KeyboardInterrupt cuts it here
            np.savez_compressed(sink, a=new)

    # Python's own handler, as in a `racing` command (a test worker may have another one)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            replace_atomically(write, path)
        handler = signal.getsignal(signal.SIGINT)
    finally:
        signal.signal(signal.SIGINT, before)
    with np.load(path) as data:
        np.testing.assert_array_equal(data["a"], new)
    assert not path.with_name(path.name + ".partial").exists()
    assert handler is signal.default_int_handler  # the handler is back


@pytest.fixture
def held(tmp_path):
    """A folder that another process holds, as a run writing there does; yields the folder
    and the process."""
    out = tmp_path / "out"
    process = subprocess.Popen([sys.executable, "-c", HOLDER, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert process.stdout.readline().strip() == "held"
        yield out, process
    finally:
        process.kill()
        process.wait()


def test_a_folder_another_process_writes_to_is_refused_until_that_process_ends(held):
    out, holder = held
    with pytest.raises(FolderInUse, match="another process is writing a tournament to .*; wait for it to end"):
        with one_writer(out, "tournament"):
            pass
    # killed, not stopped cleanly: the operating system drops the lock, and no stale lock is left
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    assert (out / LOCK).exists()
    with one_writer(out, "tournament"):
        with pytest.raises(FolderInUse):  # held here now: a second writer in this process is refused too
            with one_writer(out, "tournament"):
                pass
    with one_writer(out, "tournament"):  # released at the end of the block
        pass


@pytest.mark.parametrize("command", [
    ["tournament", "--agents", "lane-keeping", "constant-speed", "--grids", "1", "--no-gif", "--no-report"],
    ["train", "--timesteps", "64", "--learner", "jax", "--envs", "2"],
    ["exploit", "--targets", "lane-keeping", "--seeds", "1", "--timesteps", "64"],
])
def test_the_commands_that_resume_from_their_folder_refuse_one_being_written(held, command, capsys):
    out, _ = held
    assert main([*command, "--out", str(out)]) == 2
    assert "another process is writing" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == [LOCK]  # nothing of its own written
