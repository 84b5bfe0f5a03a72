"""Where the test suite's CPU goes: each test's CPU seconds, its own and its processes'.

A pytest plugin and its summary. The suite is CPU-bound on 2 cores (both cores ~97 % busy
through a full run), so the sum of the tests' CPU seconds, not their wall times, says what a
faster suite must cut. For each test it reads, before and after the test, the CPU time (user +
system, and the reaped children's) of every live process descending from the pytest process
(an xdist worker, its warm-start server and the commands it forks, the servers and rank
processes a test starts): the difference is what the test cost, whichever process spent it.
Each worker appends ``<test id> TAB <cpu s> TAB <wall s>`` lines to ``<prefix>.<worker>.tsv``.

    PYTHONPATH=benchmarks SUITE_CPU=/tmp/suite python -m pytest -p suite_cpu
    python benchmarks/suite_cpu.py /tmp/suite            # the files and tests that cost most

A process that is not a descendant (one started with a double fork) is not counted; one that
outlives its test is counted in the test during which it spent. The CPU seconds of a test grow
under load (two workers share two cores), so read them as shares, not as a test's cost alone.

Written by hand: pytest's ``--durations`` gives wall time only and psutil would add a
dependency for what one read of ``/proc`` does (Linux only).
"""

from __future__ import annotations

import collections
import glob
import os
import sys
import time

_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
_out = None


def tree_cpu(root: int) -> float:
    """CPU seconds (utime + stime + cutime + cstime) of ``root`` and its live descendants."""
    children: dict[int, list[int]] = collections.defaultdict(list)
    spent: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                stat = f.read()
        except OSError:  # the process ended meanwhile
            continue
        # the fields after the command name, which may hold spaces
        fields = stat[stat.rindex(")") + 2 :].split()
        children[int(fields[1])].append(int(entry))
        spent[int(entry)] = sum(int(x) for x in fields[11:15])
    total, todo = 0, [root]
    while todo:
        pid = todo.pop()
        total += spent.get(pid, 0)
        todo.extend(children.get(pid, ()))
    return total / _TICKS


def _hookwrapper():
    import pytest

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        global _out
        if _out is None:
            worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
            prefix = os.environ.get("SUITE_CPU", "suite_cpu")
            path = f"{prefix}.{worker}.tsv"
            try:
                _out = open(path, "a", buffering=1)  # noqa: SIM115 (kept open)
            except OSError as err:
                raise pytest.UsageError(f"SUITE_CPU={prefix!r}: cannot write {path}: "
                                        f"{err.strerror}") from None  # fmt: skip
        cpu, wall = tree_cpu(os.getpid()), time.perf_counter()
        yield
        cpu, wall = tree_cpu(os.getpid()) - cpu, time.perf_counter() - wall
        _out.write(f"{item.nodeid}\t{cpu:.2f}\t{wall:.2f}\n")

    return pytest_runtest_protocol


if "pytest" in sys.modules:  # loaded as a plugin (-p suite_cpu)
    pytest_runtest_protocol = _hookwrapper()


def summary(prefix: str, top: int = 25) -> str:
    """The totals, then the ``top`` files and tests by CPU seconds, of ``<prefix>.*.tsv``."""
    rows = []
    for path in sorted(glob.glob(f"{prefix}.*.tsv")):
        with open(path) as f:
            for number, line in enumerate(f, 1):
                try:
                    test, cpu, wall = line.rstrip("\n").split("\t")
                    rows.append((test, float(cpu), float(wall)))
                except ValueError:
                    raise SystemExit(f"{path}:{number}: expected '<test> TAB <cpu s> TAB "
                                     f"<wall s>', not {line.rstrip()!r}") from None  # fmt: skip
    if not rows:
        raise SystemExit(f"no {prefix}.*.tsv: run the suite with the plugin (module docstring)")
    files: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0, 0])
    for test, cpu, wall in rows:
        entry = files[test.split("::")[0]]
        entry[0] += cpu
        entry[1] += wall
        entry[2] += 1
    lines = [f"{len(rows)} tests: {sum(r[1] for r in rows):.0f} CPU s, "
             f"{sum(r[2] for r in rows):.0f} wall s", "", "  CPU s  wall s  tests  file"]  # fmt: skip
    for name, (cpu, wall, n) in sorted(files.items(), key=lambda kv: -kv[1][0])[:top]:
        lines.append(f"{cpu:7.1f} {wall:7.1f} {n:6d}  {name}")
    lines += ["", "  CPU s  wall s  test"]
    for test, cpu, wall in sorted(rows, key=lambda r: -r[1])[:top]:
        lines.append(f"{cpu:7.1f} {wall:7.1f}  {test}")
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        raise SystemExit("usage: python benchmarks/suite_cpu.py PREFIX [TOP]")
    print(summary(sys.argv[1], int(sys.argv[2]) if len(sys.argv) == 3 else 25))
