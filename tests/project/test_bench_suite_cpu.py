"""benchmarks/suite_cpu.py: a test's CPU seconds count its processes' too, and the summary
ranks what the plugin wrote."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time

import pytest

from helpers.paths import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
suite_cpu = pytest.importorskip("suite_cpu")

_BURN = "import time\nt = time.process_time()\nwhile time.process_time() - t < {s}: pass\n"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_live_child_and_a_reaped_one_are_counted_as_the_kernel_counts_them():
    """A child reaped meanwhile and one still running: the tree's CPU grows by this process's
    own time, the reaped child's (getrusage) and the live one's, within a few clock ticks."""
    me = os.getpid()
    before, own_before = suite_cpu.tree_cpu(me), time.process_time()
    children_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-c", _BURN.format(s=0.6)], check=True)
    live = subprocess.Popen([sys.executable, "-c", _BURN.format(s=0.6) + "time.sleep(60)\n"])
    try:
        deadline = time.monotonic() + 30
        while suite_cpu.tree_cpu(live.pid) < 0.6 and time.monotonic() < deadline:
            time.sleep(0.05)  # until its burn is done and it sleeps
        children = resource.getrusage(resource.RUSAGE_CHILDREN)
        reaped = (children.ru_utime + children.ru_stime
                  - children_before.ru_utime - children_before.ru_stime)  # fmt: skip
        live_cpu = suite_cpu.tree_cpu(live.pid)
        grown = suite_cpu.tree_cpu(me) - before
        own = time.process_time() - own_before
        assert reaped >= 0.59 and live_cpu >= 0.6
        assert grown == pytest.approx(own + reaped + live_cpu, abs=0.1)
    finally:
        live.kill()
        live.wait()


def test_the_summary_ranks_files_and_tests_by_cpu(tmp_path):
    (tmp_path / "run.gw0.tsv").write_text("a.py::x\t1.50\t2.00\nb.py::y\t4.00\t4.10\n")
    (tmp_path / "run.gw1.tsv").write_text("a.py::z\t3.00\t3.20\n")
    text = suite_cpu.summary(str(tmp_path / "run"))
    lines = text.splitlines()
    assert lines[0] == "3 tests: 8 CPU s, 9 wall s"
    assert lines[3:5] == ["    4.5     5.2      2  a.py", "    4.0     4.1      1  b.py"]
    assert lines[-3:] == ["    4.0     4.1  b.py::y", "    3.0     3.2  a.py::z",
                          "    1.5     2.0  a.py::x"]  # fmt: skip
    with pytest.raises(SystemExit, match="no .*nothing\\.\\*\\.tsv"):
        suite_cpu.summary(str(tmp_path / "nothing"))


def test_a_damaged_line_or_an_unwritable_prefix_is_named_in_one_line(tmp_path):
    """A line cut short in a worker's file: the summary names the file and the line. A
    SUITE_CPU prefix in a folder that does not exist: pytest refuses it as a usage error naming
    the variable, before any test runs."""
    (tmp_path / "run.gw0.tsv").write_text("a.py::x\t1.50\t2.00\nb.py::y\t4.0")
    with pytest.raises(SystemExit, match=r"run\.gw0\.tsv:2: expected '<test> TAB <cpu s> TAB "
                       r"<wall s>', not 'b\.py::y\\t4\.0'$"):  # fmt: skip
        suite_cpu.summary(str(tmp_path / "run"))
    test = tmp_path / "test_one.py"
    test.write_text("def test_one():\n    pass\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT / "benchmarks"),
           "SUITE_CPU": str(tmp_path / "missing" / "run")}  # fmt: skip
    proc = subprocess.run([sys.executable, "-m", "pytest", "-p", "suite_cpu", "-p", "no:xdist",
                           "-p", "no:cacheprovider", "-c", os.devnull, str(test)],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)  # fmt: skip
    assert proc.returncode != 0 and "Traceback" not in proc.stdout + proc.stderr
    assert f"SUITE_CPU='{tmp_path / 'missing' / 'run'}': cannot write " in proc.stdout + proc.stderr
    assert not (tmp_path / "missing").exists()
