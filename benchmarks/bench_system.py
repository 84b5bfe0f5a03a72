"""What sampling the system metrics costs a run: the sampler's CPU time over the run's.

    python benchmarks/bench_system.py [--epochs 6] [--intervals 10,1] [--mlflow-seconds 30]

1. The smoke training (``resireg-train experiment=smoke``, ``--epochs`` epochs, one torch
   thread) in a fresh process per interval of ``--intervals`` (``system_metrics.interval``;
   10 s is the default): its ``results.json`` holds the sampler's own CPU seconds
   (``system.sampler_cpu_seconds``: its thread's ``time.thread_time()``) and the run's
   (``provenance.time.cpu_hours``: the process and its children). The goal is a ratio of at
   most 1% at the default interval.
2. MLflow's own monitor (``mlflow.system_metrics``, what ``tracker=mlflow`` starts beside it):
   run for ``--mlflow-seconds`` at a 1 s interval on a local SQLite store, its thread's CPU
   seconds read from the kernel (psutil, by the thread's native id) per sample taken; a
   run pays that once per interval.

Figures are ratios from one run (these machines are noisy).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


def training(epochs: int, interval: float, folder: Path) -> dict[str, float]:
    out = folder / f"train-{interval:g}"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "HF_HUB_OFFLINE": "1"}
    subprocess.run(
        [sys.executable, "-m", "resireg_train.cli.train", "experiment=smoke",
         f"trainer.max_epochs={epochs}", "export=false", f"system_metrics.interval={interval}",
         f"hydra.run.dir={out}"],
        check=True, env=env, capture_output=True, text=True,
    )  # fmt: skip
    record = json.loads((out / "results.json").read_text())
    time_ = record["provenance"]["time"]
    run_cpu = float(time_["cpu_hours"]) * 3600
    sampler = float(record["system"]["sampler_cpu_seconds"])
    return {"interval": interval, "wall_s": float(time_["wall_seconds"]), "run_cpu_s": run_cpu,
            "samples": record["system"]["samples"], "sampler_cpu_s": sampler,
            "ratio": sampler / run_cpu}  # fmt: skip


def mlflow_monitor(seconds: float, folder: Path) -> dict[str, float]:
    import psutil
    from mlflow import MlflowClient
    from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

    uri = f"sqlite:///{folder}/mlflow.db"
    client = MlflowClient(uri)
    run_id = client.create_run(client.create_experiment("bench")).info.run_id
    monitor = SystemMetricsMonitor(run_id, sampling_interval=1, tracking_uri=uri)
    monitor.start()
    thread = next(t for t in threading.enumerate() if t.name == "SystemMetricsMonitor")
    time.sleep(seconds)
    cpu = next(t.user_time + t.system_time for t in psutil.Process().threads()
               if t.id == thread.native_id)  # fmt: skip
    monitor.finish()
    steps = len(client.get_metric_history(run_id, "system/cpu_utilization_percentage"))
    return {"seconds": seconds, "samples": steps, "cpu_s": cpu, "per_sample_ms": 1e3 * cpu / steps}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--epochs", type=int, default=6)
    parser.add_argument("--intervals", default="10,1")
    parser.add_argument("--mlflow-seconds", type=float, default=30)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        print("| interval | run wall | run CPU | samples | sampler CPU | sampler / run |")
        print("|---:|---:|---:|---:|---:|---:|")
        for interval in (float(i) for i in args.intervals.split(",")):
            r = training(args.epochs, interval, folder)
            print(f"| {r['interval']:g} s | {r['wall_s']:.1f} s | {r['run_cpu_s']:.1f} s | "
                  f"{r['samples']} | {1e3 * r['sampler_cpu_s']:.1f} ms | "
                  f"{100 * r['ratio']:.3f}% |")  # fmt: skip
        if args.mlflow_seconds > 0:
            m = mlflow_monitor(args.mlflow_seconds, folder)
            print(
                f"\nMLflow's monitor: {m['samples']} samples in {m['seconds']:g} s, "
                f"{1e3 * m['cpu_s']:.0f} ms CPU: {m['per_sample_ms']:.1f} ms per sample "
                f"({m['per_sample_ms'] / 100:.3f}% of one core at a 10 s interval)"
            )


if __name__ == "__main__":
    main()
