"""System metrics of a run: CPU, resident memory, disk and GPU use over time, sampled by a
background thread for the whole life of every training, evaluation and map run
(:class:`SystemSampler`, started and stopped by the run's
:class:`~resireg_train.record.run_record.RunRecord`), every ``system_metrics.interval`` seconds
(``conf/system_metrics/default.yaml``, 10 s).

- ``<run>/system.csv``: one row per sample (the local record, beside ``metrics.csv``);
- ``results.json``'s ``system`` block: the interval, the number of samples, the peak of every
  column, the bytes read and written in all, and the sampler's own CPU seconds (its cost:
  ``benchmarks/bench_system.py`` puts it against the run's);
- the trackers through their own facilities: MLflow's system-metrics monitor
  (``mlflow.system_metrics``: ``system/...`` metrics in the run's "System metrics" tab) and W&B's
  system panel (its ``x_stats_sampling_interval``), at the same interval
  (:mod:`resireg_train.record.trackers.mlflow`, :mod:`resireg_train.record.trackers.wandb`).

What a row holds (the run's processes: the job's own process and its children, such as data
loader workers and DDP ranks it started):

    time            seconds since the epoch (UTC) at the sample
    elapsed_s       seconds since the sampler started
    cpu_percent     CPU time of the run's processes over the interval, in % of one core
    rss_bytes       their resident memory (the sum over the processes)
    disk_read_bytes_per_s, disk_write_bytes_per_s    what they read from and wrote to storage
    gpu<i>_utilization_percent, gpu<i>_memory_bytes  each GPU this process sees (CUDA's
                    index i; ``CUDA_VISIBLE_DEVICES`` honoured), from NVML (``nvidia-ml-py``):
                    the whole device's use, as ``nvidia-smi`` shows it

psutil reads the processes; NVML the GPUs (none: no GPU columns). Nothing here fails a run: a
sample that cannot be read is skipped, a ``system.csv`` that cannot be written is a warning.
"""

from __future__ import annotations

import csv
import logging
import math
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from resireg.errors import ConfigError
from resireg.integrity import atomic_write

__all__ = [
    "SYSTEM_FILE",
    "SystemSampler",
    "merge_blocks",
    "read_system_csv",
    "system_settings",
]

log = logging.getLogger(__name__)

#: The per-sample file in the run folder.
SYSTEM_FILE = "system.csv"
_BASE = ("time", "elapsed_s", "cpu_percent", "rss_bytes", "disk_read_bytes_per_s",
         "disk_write_bytes_per_s")  # fmt: skip
#: Columns whose peak says nothing (the clock).
_NO_PEAK = ("time", "elapsed_s")


def system_settings(cfg: Any) -> tuple[bool, float]:
    """``(enabled, interval in seconds)`` of ``cfg.system_metrics``
    (``conf/system_metrics/default.yaml``); a config without the block (a caller outside the
    Hydra commands) samples nothing. A bad value is a :class:`ConfigError` naming the key."""
    block = cfg.get("system_metrics") if hasattr(cfg, "get") else None
    if not block:
        return False, 0.0
    enabled, interval = block.get("enabled", True), block.get("interval")
    if not isinstance(enabled, bool):
        raise ConfigError(f"system_metrics.enabled={enabled!r}: expected true or false")
    ok = isinstance(interval, (int, float)) and not isinstance(interval, bool)
    if not ok or not math.isfinite(interval) or interval < 0.1:
        raise ConfigError(f"system_metrics.interval={interval!r}: expected a number of seconds "
                          ">= 0.1 (W&B's smallest)")  # fmt: skip
    return enabled, float(interval)


def _visible(nvml: Any) -> list[tuple[int, Any]]:
    """``(CUDA index, NVML handle)`` of each GPU this process sees: ``CUDA_VISIBLE_DEVICES``'s
    entries (indices or ``GPU-<uuid>``) in its order, else every device NVML lists. An entry
    NVML cannot map (a MIG instance) leaves the list to NVML's whole set."""
    listed = os.environ.get("CUDA_VISIBLE_DEVICES")
    if listed is None:
        return [(i, nvml.nvmlDeviceGetHandleByIndex(i)) for i in range(nvml.nvmlDeviceGetCount())]
    handles = []
    for cuda, entry in enumerate(e.strip() for e in listed.split(",")):
        if not entry:
            continue
        if entry.lstrip("-").isdigit():
            if int(entry) < 0:  # CUDA stops at the first invalid index
                break
            handles.append((cuda, nvml.nvmlDeviceGetHandleByIndex(int(entry))))
        elif entry.startswith("GPU-"):
            handles.append((cuda, nvml.nvmlDeviceGetHandleByUUID(entry)))
        else:
            return [(i, nvml.nvmlDeviceGetHandleByIndex(i))
                    for i in range(nvml.nvmlDeviceGetCount())]  # fmt: skip
    return handles


class SystemSampler:
    """Samples the run's processes (and GPUs) every ``interval`` seconds in a daemon thread,
    appending each row to ``<folder>/system.csv`` (module docstring).

    Args:
        folder: the run folder.
        interval: seconds between samples.
        nvml: the NVML module (``pynvml`` of ``nvidia-ml-py``, imported when ``None``); a
            machine without the module, the driver or a GPU samples no GPU.
    """

    def __init__(self, folder: str | os.PathLike, interval: float, nvml: Any = None) -> None:
        import psutil

        self.folder = Path(folder)
        self.interval = float(interval)
        self.path = self.folder / SYSTEM_FILE
        self._psutil = psutil
        self._root = psutil.Process()
        self._nvml = nvml
        self._gpus: list[tuple[int, Any]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._last: dict[tuple[int, float], tuple[float, int, int]] = {}
        self._last_time = 0.0
        self._start = 0.0
        self._columns: list[str] = list(_BASE)
        self._file: Any = None
        self._writer: Any = None
        self.samples = 0
        self.peak: dict[str, float] = {}
        self.read_bytes = 0
        self.written_bytes = 0
        #: CPU seconds the sampler spent (its thread's and its calls from the job's thread).
        self.cpu_seconds = 0.0

    # -- the processes ------------------------------------------------------------------
    def _processes(self) -> list[Any]:
        try:
            return [self._root, *self._root.children(recursive=True)]
        except self._psutil.Error:
            return [self._root]

    def _counters(self) -> dict[tuple[int, float], tuple[float, int, int, int]]:
        """Per process (pid, start time): CPU seconds, bytes read, bytes written, RSS."""
        out = {}
        for proc in self._processes():
            try:
                with proc.oneshot():
                    times = proc.cpu_times()
                    try:
                        io = proc.io_counters()
                        read, written = io.read_bytes, io.write_bytes
                    except (AttributeError, self._psutil.AccessDenied):  # macOS has none
                        read = written = 0
                    out[(proc.pid, proc.create_time())] = (
                        times.user + times.system,
                        read,
                        written,
                        proc.memory_info().rss,
                    )
            except self._psutil.Error:  # it ended meanwhile
                continue
        return out

    # -- the GPUs -------------------------------------------------------------------------
    def _open_gpus(self) -> None:
        nvml = self._nvml
        if nvml is None:
            try:
                import pynvml as nvml  # nvidia-ml-py
            except ImportError:
                return
        try:
            nvml.nvmlInit()
        except Exception as err:  # NVMLError (no driver, no GPU) or the library missing
            log.debug("no GPU metrics: %s", err)
            return
        self._nvml = nvml
        try:
            self._gpus = _visible(nvml)
        except Exception as err:
            log.warning("system metrics: GPUs not sampled (%s)", err)
            self._gpus = []
        for i, _ in self._gpus:
            self._columns += [f"gpu{i}_utilization_percent", f"gpu{i}_memory_bytes"]

    def _gpu_values(self) -> dict[str, float]:
        values: dict[str, float] = {}
        for i, handle in self._gpus:
            try:
                values[f"gpu{i}_utilization_percent"] = float(
                    self._nvml.nvmlDeviceGetUtilizationRates(handle).gpu
                )
                values[f"gpu{i}_memory_bytes"] = float(
                    self._nvml.nvmlDeviceGetMemoryInfo(handle).used
                )
            except Exception as err:  # NVMLError: the device is gone or busy
                log.debug("GPU %d not sampled: %s", i, err)
        return values

    # -- sampling -------------------------------------------------------------------------
    def start(self, fresh: bool = False) -> SystemSampler:
        """Open ``system.csv`` (appended to: a resumed training continues it; ``fresh``, a job
        that never resumes, keeps an earlier run's as ``system.previous-<n>.csv``), take the
        baseline and start the thread."""
        began = time.thread_time()
        if fresh and self.path.is_file():
            n = 1
            while (kept := self.path.with_name(f"system.previous-{n}.csv")).exists():
                n += 1
            os.replace(self.path, kept)
        self._open_gpus()
        self._start = self._last_time = time.monotonic()
        self._last = {k: v[:3] for k, v in self._counters().items()}
        try:
            new = not self.path.is_file() or self.path.stat().st_size == 0
            if not new:
                self._continue_file()
            self._file = open(self.path, "a", newline="")
            self._writer = csv.DictWriter(self._file, fieldnames=self._columns,
                                          extrasaction="ignore")  # fmt: skip
            if new:
                self._writer.writeheader()
                self._file.flush()
        except (OSError, csv.Error, UnicodeDecodeError) as err:
            log.warning("system metrics: cannot write %s (%s); sampled for results.json only",
                        self.path, err)  # fmt: skip
            self._file = self._writer = None
        self.cpu_seconds += time.thread_time() - began
        self._thread = threading.Thread(target=self._loop, name="resireg-system-metrics",
                                        daemon=True)  # fmt: skip
        self._thread.start()
        return self

    def _continue_file(self) -> None:
        """A resumed run's ``system.csv`` whose columns differ from this process's (it sees
        other GPUs) is rewritten once with the columns of both, so every row stays readable."""
        with open(self.path, newline="") as f:
            reader = csv.DictReader(f)
            header, rows = list(reader.fieldnames or []), list(reader)
        if header == self._columns:
            return
        self._columns = list(dict.fromkeys([*header, *self._columns]))

        def rewrite(tmp: Path) -> None:
            with open(tmp, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=self._columns)
                writer.writeheader()
                writer.writerows(rows)

        atomic_write(self.path, rewrite, what="system metrics")

    def _loop(self) -> None:
        while not self._stop.wait(self.interval):
            began = time.thread_time()
            self.sample()
            self.cpu_seconds += time.thread_time() - began

    def sample(self) -> dict[str, float] | None:
        """Take one sample now (a row of ``system.csv``: the use since the previous one);
        ``None`` when no time has passed."""
        with self._lock:
            now = time.monotonic()
            span = now - self._last_time
            if span <= 0:
                return None
            counters = self._counters()
            cpu, read, written, rss = 0.0, 0, 0, 0
            for key, (seconds, r, w, resident) in counters.items():
                before = self._last.get(key, (0.0, 0, 0))
                cpu += max(0.0, seconds - before[0])
                read += max(0, r - before[1])
                written += max(0, w - before[2])
                rss += resident
            self._last = {k: v[:3] for k, v in counters.items()}
            self._last_time = now
            row = {"time": round(time.time(), 3), "elapsed_s": round(now - self._start, 3),
                   "cpu_percent": round(100 * cpu / span, 2), "rss_bytes": rss,
                   "disk_read_bytes_per_s": round(read / span, 1),
                   "disk_write_bytes_per_s": round(written / span, 1), **self._gpu_values()}  # fmt: skip
            self.samples += 1
            self.read_bytes += int(read)
            self.written_bytes += int(written)
            for key, value in row.items():
                if key not in _NO_PEAK:
                    self.peak[key] = max(self.peak.get(key, value), value)
            if self._writer is not None:
                try:
                    self._writer.writerow(row)
                    self._file.flush()
                except (OSError, ValueError) as err:
                    log.warning("system metrics: cannot write %s (%s)", self.path, err)
                    self._writer = None
            return row

    def stop(self) -> dict[str, Any]:
        """Stop the thread, take the last sample (the time since the previous one) and close
        the file and NVML; returns ``results.json``'s ``system`` block."""
        began = time.thread_time()
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self.sample()
        if self._file is not None:
            self._file.close()
            self._file = None
        if self._gpus:
            try:
                self._nvml.nvmlShutdown()
            except Exception:  # the driver went away: nothing left to release
                pass
        self.cpu_seconds += time.thread_time() - began
        return self.block()

    def block(self) -> dict[str, Any]:
        """``results.json``'s ``system`` block as it is now."""
        return {
            "interval_s": self.interval,
            "samples": self.samples,
            "file": SYSTEM_FILE,
            "gpus": [i for i, _ in self._gpus],
            "peak": {k: self.peak[k] for k in self._columns if k in self.peak},
            "total": {"disk_read_bytes": self.read_bytes,
                      "disk_write_bytes": self.written_bytes},
            "sampler_cpu_seconds": round(self.cpu_seconds, 6),
        }  # fmt: skip


def merge_blocks(before: Mapping[str, Any] | None, now: Mapping[str, Any]) -> dict[str, Any]:
    """The ``system`` block of a resumed run: this process's (``now``) with the earlier
    processes' (``before``) peaks (the larger), totals, samples and sampler seconds (summed)."""
    if not isinstance(before, Mapping) or not before:
        return dict(now)
    peak = dict(before.get("peak") or {})
    for key, value in (now.get("peak") or {}).items():
        old = peak.get(key)
        peak[key] = value if not isinstance(old, (int, float)) else max(old, value)
    total = {k: (before.get("total") or {}).get(k, 0) + v
             for k, v in (now.get("total") or {}).items()}  # fmt: skip
    return {**now, "peak": peak, "total": total,
            "samples": int(before.get("samples") or 0) + int(now.get("samples") or 0),
            "sampler_cpu_seconds": round(float(before.get("sampler_cpu_seconds") or 0)
                                         + float(now.get("sampler_cpu_seconds") or 0), 6)}  # fmt: skip


def read_system_csv(folder: str | os.PathLike) -> list[dict[str, float]]:
    """The rows of ``<folder>/system.csv`` as numbers (an empty cell left out)."""
    path = Path(folder) / SYSTEM_FILE
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return [{k: float(v) for k, v in row.items() if v not in (None, "")}
                for row in csv.DictReader(f)]  # fmt: skip
