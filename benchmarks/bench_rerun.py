"""What ``resireg-runs rerun`` costs over the bare job it reruns (docs/benchmarks.md).

    python benchmarks/bench_rerun.py [--rounds 2] [--threads 2] [--out /tmp/bench_rerun]
        [overrides...]                  # default: experiment=smoke (6 epochs)

Each round runs the smoke training directly (``python -m resireg_train.cli.train
experiment=smoke ...``, the bare job), then ``resireg-runs rerun`` of that run into a new
folder, and times both processes from the outside (wall seconds). The rerun's extra is what
it adds around the same job: its own start, the recorded overrides checked and the config
composed, the drift check (the code's git state and digests, the data identity, the input
models' digests, the config against the run's), then the two records compared and the verdict
written. Rounds alternate the two, so a load change on a shared machine hits both; the ratio is
the median rerun's seconds over the median bare job's, from one invocation. As a load change
between the two processes can hide a second or two, each is also split by the job's own wall
seconds (its record's ``provenance.time.wall_seconds``): what is left outside the job in the
bare process (Python's start and imports) against the rerun process, whose difference is the
rerun's own cost.

Run it from a git checkout whose files do not change while it runs (an edit is drift: the
rerun is refused).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _timed(command: list[str], env: dict[str, str]) -> tuple[float, str]:
    start = time.perf_counter()
    proc = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(command)} exited {proc.returncode}:\n"
                         f"{proc.stdout[-2000:]}{proc.stderr[-2000:]}")  # fmt: skip
    return seconds, proc.stdout


def _job_seconds(folder: Path) -> float:
    """The job's own wall seconds, as its record measured them."""
    record = json.loads((folder / "results.json").read_text())
    return float(record["provenance"]["time"]["wall_seconds"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2, help="OMP_NUM_THREADS of both")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_rerun"))
    parser.add_argument("overrides", nargs="*", default=["experiment=smoke"])
    args = parser.parse_args()
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": str(args.threads),
           "MKL_NUM_THREADS": str(args.threads)}  # fmt: skip
    shutil.rmtree(args.out, ignore_errors=True)
    bare, again, verdicts, outside = [], [], [], ([], [])
    for i in range(args.rounds):
        run, new = args.out / f"run{i}", args.out / f"rerun{i}"
        seconds, _ = _timed([sys.executable, "-m", "resireg_train.cli.train", *args.overrides,
                             f"hydra.run.dir={run}"], env)  # fmt: skip
        bare.append(seconds)
        seconds, out = _timed([sys.executable, "-m", "resireg_train.cli.runs", "rerun", str(run),
                               "--out", str(new)], env)  # fmt: skip
        again.append(seconds)
        verdicts.append(next(x for x in out.splitlines() if x.startswith("verdict: ")))
        outside[0].append(bare[-1] - _job_seconds(run))
        outside[1].append(again[-1] - _job_seconds(new))
        print(
            f"round {i}: bare {bare[-1]:.2f} s ({outside[0][-1]:.2f} s outside the job), "
            f"rerun {again[-1]:.2f} s ({outside[1][-1]:.2f} s outside the job); {verdicts[-1]}",
            flush=True,
        )
    a, b = statistics.median(bare), statistics.median(again)
    oa, ob = statistics.median(outside[0]), statistics.median(outside[1])
    print(
        "\n| job | bare s | rerun s | ratio | outside the job: bare s | rerun s | rerun's own s |"
        "\n|---|---:|---:|---:|---:|---:|---:|"
        f"\n| {' '.join(args.overrides)} | {a:.2f} | {b:.2f} | {b / a:.3f} | {oa:.2f} | {ob:.2f} "
        f"| {ob - oa:+.2f} |"
    )


if __name__ == "__main__":
    main()
