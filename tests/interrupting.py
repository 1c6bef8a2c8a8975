"""Ctrl-C for a real `racing` process in tests: SIGINT to its whole process group, as a
terminal sends it, so that worker processes get it too."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from typing import Callable

import pytest


#: ``python -c`` code that runs the ``racing`` command line with Python's own SIGINT handler
#: installed first, as an interactive ``racing`` has it. A test run started as a shell's
#: background job has SIGINT ignored, and a child would inherit that and never see Ctrl-C.
RACING_WITH_CTRL_C = (
    "import signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "from experiments.cli import console_main; console_main()"
)


def racing_command(args: list[str]) -> list[str]:
    """The argv of a ``racing ARGS`` process that Ctrl-C reaches (:data:`RACING_WITH_CTRL_C`)."""
    return [sys.executable, "-c", RACING_WITH_CTRL_C, *args]


def start_racing(args: list[str]) -> subprocess.Popen:
    """``racing ARGS`` in a process group of its own, SIGINT handled; stderr captured."""
    return subprocess.Popen(racing_command(args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def ctrl_c_when(process: subprocess.Popen, ready: Callable[[], bool], timeout: float = 180.0) -> str:
    """Wait until ``ready()``, send SIGINT to the process group, wait for the process to
    exit and for every process of its group to be gone (else fail). Returns its stderr."""
    try:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and process.poll() is None and not ready():
            time.sleep(0.05)
        assert process.poll() is None, "the process ended before it could be interrupted"
        assert ready(), f"not ready to interrupt after {timeout} s"
        os.killpg(process.pid, signal.SIGINT)
        _, err = process.communicate(timeout=120)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                os.killpg(process.pid, 0)  # anyone left in the group?
            except ProcessLookupError:
                return err
            time.sleep(0.1)
        pytest.fail("processes of the interrupted run are still alive")
    finally:
        if process.poll() is None:
            process.kill()
