"""The suite's own handling of the processes its tests start (tests/helpers/run.py ``started``): a child
takes Ctrl-C even when the suite runs in the background (SIGINT ignored, as ``nohup ... &`` and
some CI runners start it), a read never blocks past its timeout, and nothing a child started
outlives its test unnoticed."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from helpers import run as _run
from helpers import warm_start
from helpers.paths import ROOT
from helpers.run import started

WAIT = "import time\nprint('ready', flush=True)\ntime.sleep(600)"


def _ignore_sigint():
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.fixture
def sigint_ignored():
    """This process ignores SIGINT for the test (a suite started in the background)."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    yield
    signal.signal(signal.SIGINT, previous)


def test_a_child_takes_ctrl_c_when_the_suite_ignores_it(sigint_ignored):
    """The disposition a child inherits: SIGINT ignored in this process, default in the child
    (/proc's SigIgn mask), so the test's Ctrl-C interrupts it (Python's KeyboardInterrupt)."""
    with started([sys.executable, "-c", WAIT]) as child:
        assert child.readline(timeout=60) == "ready\n"
        ignored = int(Path(f"/proc/{child.pid}/status").read_text().split("SigIgn:")[1].split()[0],
                      16)  # fmt: skip
        assert not ignored & (1 << (signal.SIGINT - 1))
        assert child.stop(signal.SIGINT, timeout=30) == -signal.SIGINT
    assert "KeyboardInterrupt" in child.stdout


@pytest.mark.slow
def test_a_line_that_never_comes_fails_in_time_and_the_group_is_killed():
    """readline past its timeout is an AssertionError naming the command (not a hang); leaving
    the block kills the child and the process it started (one process group)."""
    code = "import subprocess, sys, time\nsubprocess.Popen([sys.executable, '-c', " \
           "'import time; time.sleep(600)'])\ntime.sleep(600)"  # fmt: skip
    start = time.monotonic()
    with pytest.raises(AssertionError, match=r"no line in 1 s") as err:
        with started([sys.executable, "-c", code]) as child:
            deadline = time.monotonic() + 60
            while len(_run._group(child.pid)) < 2 and time.monotonic() < deadline:
                time.sleep(0.1)
            group = _run._group(child.pid)
            assert len(group) == 2
            child.readline(timeout=1)
    assert f"(PID {child.pid})" in str(err.value)
    assert time.monotonic() - start < 60
    gone, alive = psutil.wait_procs(group, timeout=10)
    assert not alive and child.returncode == -signal.SIGKILL


def test_a_command_that_exits_leaving_a_process_running_fails_naming_it(monkeypatch):
    """A command that returns while a process it started still runs: the test fails naming
    that process (and it is killed), whether it holds the output pipe or not."""
    monkeypatch.setattr(_run, "GRACE", 1)
    for redirect in ("", " > /dev/null 2>&1"):
        with pytest.raises(AssertionError, match=r"left running.*'sleep 600'"):
            with started(["sh", "-c", f"sleep 600{redirect} & echo started"]) as child:
                child.wait(timeout=60)
        assert not _run._group(child.pid)


def test_a_timeout_of_run_kills_the_whole_group():
    """run() past its timeout: subprocess.TimeoutExpired, and no process of the command left."""
    # Children this test did not start (multiprocessing's resource tracker, started by an
    # earlier test of the same worker and living as long as it; the warm-start server the
    # worker's commands share) are not the command's.
    warm_start.server(warm_start.BASE_ENV)
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    with pytest.raises(subprocess.TimeoutExpired):
        _run.run("resireg-report", "--help", timeout=0.01)
    left = [p for p in psutil.Process().children(recursive=True) if p.pid not in before
            and p.is_running() and p.status() != psutil.STATUS_ZOMBIE]  # fmt: skip
    assert not left, [p.cmdline() for p in left]


@pytest.mark.slow
def test_the_playground_launch_test_passes_with_sigint_ignored(tmp_path, sigint_ignored):
    """The suite's test that Ctrl-Cs a child (the playground's launch), run by a pytest that
    ignores SIGINT as a background job does: it passes and leaves no process (before, it
    failed after 60 s and left Gradio serving, orphaned)."""
    pytest.importorskip("gradio")
    test = "tests/project/test_cli_hygiene.py::test_playground_launch_prints_its_address_and_no_share_hint"
    cmd = [sys.executable, "-m", "pytest", "-n", "0", "-q", "-p", "no:cacheprovider",
           f"--basetemp={tmp_path / 'inner'}", test]  # fmt: skip
    with started(cmd, cwd=ROOT, preexec=_ignore_sigint) as inner:
        code = inner.wait(timeout=540)
    assert code == 0, inner.stdout[-3000:]
    assert "1 passed" in inner.stdout
