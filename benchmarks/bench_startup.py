"""Seconds until each entry point answers what needs no model: ``--help``, ``--cfg job`` and
a bad config value (median of ``--repeats`` runs in fresh processes).

    python benchmarks/bench_startup.py [--repeats 5]

Before/after a change, point ``PYTHONPATH`` at the other checkout's ``src`` and run again.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

COMMANDS = {
    "resireg-train --help": ["resireg-train", "--help"],
    "resireg-eval --cfg job": ["resireg-eval", "--cfg", "job", "model_path=x"],
    "resireg-train model.optimizer.lr=-1": ["resireg-train", "experiment=smoke",
                                            "model.optimizer.lr=-1"],
    "resireg-report --help": ["resireg-report", "--help"],
}  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    print("| command | median s | runs |\n|---|---:|---|")
    for label, command in COMMANDS.items():
        exe = shutil.which(command[0]) or sys.executable
        times = []
        for _ in range(args.repeats):
            with tempfile.TemporaryDirectory() as out:
                start = time.perf_counter()
                subprocess.run([exe, *command[1:], f"hydra.run.dir={out}"] if "--help" not in
                               command else [exe, *command[1:]], capture_output=True)  # fmt: skip
                times.append(time.perf_counter() - start)
        runs = ", ".join(f"{t:.2f}" for t in times)
        print(f"| `{label}` | {statistics.median(times):.2f} | {runs} |")


if __name__ == "__main__":
    main()
