"""``resireg-runs ls`` on many generated run folders: the whole command's wall time.

Writes ``--runs`` run folders (``results.json`` with a provenance block and metrics,
``.hydra/overrides.yaml`` and ``.hydra/config.yaml``, as a run leaves them; a tenth of them
jobs of multiruns, two levels deeper) into a temporary folder, then times ``resireg-runs ls``
over them in a fresh process (the user's command, imports included), ``--repeats`` times, and
the same with a ``--where`` filter on a config key (which reads every ``config.yaml``):

    python benchmarks/bench_runs.py --runs 1000 --repeats 5
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml


def make_runs(root: Path, count: int) -> None:
    for i in range(count):
        folder = root / "smoke" / (f"multirun/2026-12-03_{i // 10}/{i % 10}_lr={i}" if i % 10 == 0
                                   else f"2026-12-03_10-00-{i:04d}_{i:06x}")  # fmt: skip
        (folder / ".hydra").mkdir(parents=True)
        (folder / ".hydra" / "overrides.yaml").write_text(
            yaml.safe_dump([f"model.optimizer.lr={1e-4 * (1 + i % 7)}", "experiment=smoke"])
        )
        config = {"name": "smoke", "seed": i, "model": {"optimizer": {"lr": 1e-4 * (1 + i % 7)},
                  "head": {"depth": 2, "width": 384}}, "trainer": {"max_epochs": 6}}  # fmt: skip
        (folder / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
        record = {
            "name": "smoke", "status": "completed",
            "final": {"val/ovss/synthetic/miou_full": (i % 97) / 100, "train/loss": 1.0},
            "history": [{"epoch": e, "train/loss": 1.0} for e in range(6)],
            "provenance": {
                "run_id": f"{i:012x}", "cli": "resireg-train",
                "code": {"version": "0.1.0", "git": {"commit": "a" * 40, "dirty": False}},
                "machine": {"host": socket.gethostname(), "pid": 1},
                "time": {"start": f"2026-12-03T10:{i // 60 % 60:02d}:{i % 60:02d}+00:00",
                         "wall_seconds": 10.0},
                "environment": {"packages": {f"pkg{j}": "1.0" for j in range(25)}},
            },
        }  # fmt: skip
        (folder / "results.json").write_text(json.dumps(record, indent=2))


def timed(args: list[str], repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "resireg_train.cli.runs", *args], check=True,
                       capture_output=True)  # fmt: skip
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "outputs"
        make_runs(root, args.runs)
        for label, extra in (("ls", []),
                             ("ls --where model.optimizer.lr>=3e-4", ["--where",
                                                                      "model.optimizer.lr>=3e-4"])):  # fmt: skip
            times = timed(["ls", str(root), "--format", "csv", *extra], args.repeats)
            print(f"{label:40s} {args.runs} runs: median {statistics.median(times):.2f} s "
                  f"(min {min(times):.2f}, max {max(times):.2f}, {args.repeats} runs)")  # fmt: skip


if __name__ == "__main__":
    main()
