"""System metrics (issue 47, item 3): the sampler's CPU, memory and disk figures against the
kernel's own counters, its GPU columns through a fake NVML that checks what the real one would
be called with, and the run's record and trackers: ``system.csv``, ``results.json``'s peaks,
MLflow's system metrics and W&B's system panel (offline, with the documented ``wandb sync``)."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from resireg.errors import ConfigError
from resireg_train.record.system import (
    SYSTEM_FILE,
    SystemSampler,
    merge_blocks,
    read_system_csv,
    system_settings,
)


def _proc_io() -> dict[str, int]:
    """/proc/self/io as the kernel writes it (the reference for the disk columns)."""
    return {k: int(v) for k, v in (line.split(": ") for line in
                                    Path("/proc/self/io").read_text().splitlines())}  # fmt: skip


def _vm(key: str) -> int:
    """A /proc/self/status memory line (kB) in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{key}:"):
            return int(line.split()[1]) * 1024
    raise KeyError(key)


def _spans(rows: list[dict[str, float]]) -> list[float]:
    """The seconds each row covers (its elapsed_s less the previous row's)."""
    ends = [r["elapsed_s"] for r in rows]
    return [b - a for a, b in zip([0.0, *ends[:-1]], ends, strict=True)]


def _rows(folder: Path) -> list[dict[str, str]]:
    with open(folder / SYSTEM_FILE, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.skipif(not Path("/proc/self/io").is_file(), reason="Linux /proc counters")
def test_cpu_memory_and_disk_agree_with_the_kernels_counters(tmp_path):
    """CPU seconds summed from the rows' cpu_percent x interval equal os.times()'s over the
    same span; the peak RSS covers a 200 MiB buffer held while sampling (VmRSS then); the
    bytes written equal /proc/self/io's write_bytes."""
    io_before, times_before = _proc_io(), os.times()
    sampler = SystemSampler(tmp_path, 0.05).start()
    deadline = time.process_time() + 0.6
    while time.process_time() < deadline:  # 0.6 s of CPU on this thread
        sum(i * i for i in range(1000))
    buffer = bytearray(200 << 20)
    buffer[::4096] = b"x" * len(buffer[::4096])  # touch every page: resident
    time.sleep(0.3)
    held = _vm("VmRSS")
    with open(tmp_path / "data.bin", "wb") as f:
        f.write(os.urandom(16 << 20))
        f.flush()
        os.fsync(f.fileno())
    time.sleep(0.15)
    block = sampler.stop()
    times_after, io_after = os.times(), _proc_io()
    del buffer

    rows = [{k: float(v) for k, v in r.items()} for r in _rows(tmp_path)]
    assert len(rows) == block["samples"] >= 10
    spans = _spans(rows)
    sampled_cpu = sum(r["cpu_percent"] / 100 * s for r, s in zip(rows, spans, strict=True))
    kernel_cpu = (times_after.user + times_after.system) - (times_before.user + times_before.system)
    assert sampled_cpu == pytest.approx(kernel_cpu, rel=0.1, abs=0.05)
    assert block["peak"]["rss_bytes"] == max(r["rss_bytes"] for r in rows)
    assert block["peak"]["rss_bytes"] >= 0.97 * held
    written = io_after["write_bytes"] - io_before["write_bytes"]
    assert written >= 16 << 20
    # system.csv's own appends may reach the disk after the last sample: a few KiB at most
    assert block["total"]["disk_write_bytes"] == pytest.approx(written, abs=256 << 10)
    assert block["sampler_cpu_seconds"] > 0


class _Nvml:
    """A stand-in for ``pynvml`` (nvidia-ml-py) that checks each call as the real library
    would take it: nvmlInit first, handles only from nvmlDeviceGetHandleByIndex/ByUUID, one
    nvmlShutdown per nvmlInit; its devices' utilisation and memory step through given lists."""

    class NVMLError(Exception):
        pass

    def __init__(self, uuids, util, used, total=80 << 30):
        self.uuids, self.util, self.used, self.total = uuids, util, used, total
        self.calls: list[tuple] = []
        self.initialised = False
        self.handles: dict[int, int] = {}  # id(handle) -> device index
        self.reads = dict.fromkeys(range(len(uuids)), 0)

    def _handle(self, index):
        handle = object()
        self.handles[id(handle)] = index
        return handle

    def _device(self, handle):
        assert self.initialised, "NVML used before nvmlInit"
        assert id(handle) in self.handles, "not a handle NVML gave"
        return self.handles[id(handle)]

    def nvmlInit(self):
        assert not self.initialised
        self.initialised = True
        self.calls.append(("init",))

    def nvmlShutdown(self):
        assert self.initialised, "nvmlShutdown without nvmlInit"
        self.initialised = False
        self.calls.append(("shutdown",))

    def nvmlDeviceGetCount(self):
        assert self.initialised
        return len(self.uuids)

    def nvmlDeviceGetHandleByIndex(self, index):
        assert self.initialised and isinstance(index, int) and 0 <= index < len(self.uuids)
        self.calls.append(("index", index))
        return self._handle(index)

    def nvmlDeviceGetHandleByUUID(self, uuid):
        assert self.initialised and uuid in self.uuids, uuid
        self.calls.append(("uuid", uuid))
        return self._handle(self.uuids.index(uuid))

    def nvmlDeviceGetUtilizationRates(self, handle):
        device = self._device(handle)
        step = min(self.reads[device], len(self.util[device]) - 1)
        return type("Utilization", (), {"gpu": self.util[device][step], "memory": 0})()

    def nvmlDeviceGetMemoryInfo(self, handle):
        device = self._device(handle)
        step = min(self.reads[device], len(self.used[device]) - 1)
        self.reads[device] += 1
        return type("Memory", (), {"used": self.used[device][step], "total": self.total,
                                   "free": self.total - self.used[device][step]})()  # fmt: skip


def test_gpu_columns_follow_cuda_visible_devices_through_nvml(tmp_path, monkeypatch):
    """CUDA_VISIBLE_DEVICES=2,GPU-<uuid of device 0>: CUDA's gpu0 is NVML's device 2 (by
    index), gpu1 device 0 (by UUID); each row holds what NVML gave at that sample, the peaks
    are the largest of what it gave, NVML is shut down once."""
    uuids = ["GPU-aaaa", "GPU-bbbb", "GPU-cccc"]
    util = {0: [10, 95, 40, 40], 1: [0, 0, 0, 0], 2: [70, 20, 88, 5]}
    used = {
        0: [1 << 30, 7 << 30, 3 << 30, 3 << 30],
        1: [0] * 4,
        2: [5 << 30, 9 << 30, 2 << 30, 1 << 30],
    }
    nvml = _Nvml(uuids, util, used)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,GPU-aaaa")
    sampler = SystemSampler(tmp_path, 3600, nvml=nvml).start()
    for _ in range(3):
        time.sleep(0.01)
        sampler.sample()
    block = sampler.stop()  # the fourth sample
    assert nvml.calls[0] == ("init",) and nvml.calls[-1] == ("shutdown",)
    assert [c for c in nvml.calls if c[0] in ("index", "uuid")] == [
        ("index", 2),
        ("uuid", "GPU-aaaa"),
    ]
    assert nvml.reads == {0: 4, 1: 0, 2: 4}  # device 1 is not this process's
    rows = _rows(tmp_path)
    assert [float(r["gpu0_utilization_percent"]) for r in rows] == util[2]
    assert [float(r["gpu0_memory_bytes"]) for r in rows] == used[2]
    assert [float(r["gpu1_utilization_percent"]) for r in rows] == util[0]
    assert [float(r["gpu1_memory_bytes"]) for r in rows] == used[0]
    assert block["gpus"] == [0, 1]
    assert block["peak"]["gpu0_utilization_percent"] == 88
    assert block["peak"]["gpu0_memory_bytes"] == 9 << 30
    assert block["peak"]["gpu1_utilization_percent"] == 95
    assert block["peak"]["gpu1_memory_bytes"] == 7 << 30


def test_no_gpu_columns_where_nvml_cannot_start(tmp_path, monkeypatch):
    class Broken(_Nvml):
        def nvmlInit(self):
            raise self.NVMLError("NVML Shared Library Not Found")

    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    nvml = Broken(["GPU-aaaa"], {0: [1]}, {0: [1]})
    block = SystemSampler(tmp_path, 3600, nvml=nvml).start().stop()
    assert block["gpus"] == [] and not any(k.startswith("gpu") for k in block["peak"])
    assert list(_rows(tmp_path)[0]) == ["time", "elapsed_s", "cpu_percent", "rss_bytes",
                                        "disk_read_bytes_per_s", "disk_write_bytes_per_s"]  # fmt: skip
    # without the variable, every device NVML lists
    nvml = _Nvml(["GPU-aaaa", "GPU-bbbb"], {0: [3], 1: [4]}, {0: [5], 1: [6]})
    assert SystemSampler(tmp_path / "all", 3600, nvml=nvml).start().stop()["gpus"] == [0, 1]


def test_a_resumed_run_keeps_the_larger_peaks_and_sums_the_rest():
    before = {
        "samples": 3,
        "peak": {"cpu_percent": 90.0, "rss_bytes": 5},
        "total": {"disk_read_bytes": 10, "disk_write_bytes": 20},
        "sampler_cpu_seconds": 0.5,
    }
    now = {"interval_s": 10.0, "samples": 2, "peak": {"cpu_percent": 50.0, "rss_bytes": 7,
                                                      "gpu0_memory_bytes": 3},
           "total": {"disk_read_bytes": 1, "disk_write_bytes": 2}, "sampler_cpu_seconds": 0.25}  # fmt: skip
    merged = merge_blocks(before, now)
    assert merged["peak"] == {"cpu_percent": 90.0, "rss_bytes": 7, "gpu0_memory_bytes": 3}
    assert merged["total"] == {"disk_read_bytes": 11, "disk_write_bytes": 22}
    assert merged["samples"] == 5 and merged["sampler_cpu_seconds"] == 0.75


@pytest.mark.parametrize("block, message", [
    ({"interval": 0}, "system_metrics.interval=0: expected a number of seconds >= 0.1"),
    ({"interval": "10s"}, "system_metrics.interval='10s': expected a number of seconds"),
    ({"interval": 10, "enabled": "yes"}, "system_metrics.enabled='yes': expected true or false"),
])  # fmt: skip
def test_a_bad_setting_is_named(block, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        system_settings({"system_metrics": block})
    assert system_settings({}) == (False, 0.0)
    assert system_settings({"system_metrics": {"enabled": True, "interval": 10}}) == (True, 10.0)


def _stats(path: Path) -> list[tuple[float, dict[str, float]]]:
    """The system-panel samples (``stats`` records) of an offline W&B run file."""
    from helpers.wandb_log import records

    out = []
    for record in records(path):
        if record.WhichOneof("record_type") == "stats":
            values = {i.key: json.loads(i.value_json) for i in record.stats.item}
            out.append((record.stats.timestamp.seconds + record.stats.timestamp.nanos / 1e9,
                        values))  # fmt: skip
    return out


@pytest.mark.slow
def test_an_evaluation_records_its_system_metrics_in_csv_mlflow_and_wandb(
    tmp_path, tiny_export, monkeypatch
):
    """One resireg-eval with tracker=[csv,mlflow,wandb] (a local MLflow store, W&B offline):
    system.csv's rows, results.json's peaks (the rows' maxima), MLflow's own system metrics
    series in its run, W&B's system panel at the configured interval with the same peak
    memory, and `wandb sync --dry-run` (the documented command) finding the offline run."""
    pytest.importorskip("mlflow")
    pytest.importorskip("wandb")
    from mlflow import MlflowClient

    from helpers.run import evaluate_export

    for key, value in {"WANDB_MODE": "offline", "WANDB_SILENT": "true",
                       "WANDB_CONFIG_DIR": str(tmp_path / "wandb_config"),
                       "WANDB_CACHE_DIR": str(tmp_path / "wandb_cache")}.items():  # fmt: skip
        monkeypatch.setenv(key, value)
    store = f"sqlite:///{tmp_path}/mlflow.db"
    out = tmp_path / "eval"
    import wandb

    try:
        evaluate_export(tiny_export, out, "tracker=[csv,mlflow,wandb]", "dataset.size=12",
                        f"tracker.mlflow.tracking_uri={store}", "system_metrics.interval=0.2",
                        f"tracker.wandb.save_dir={out}")  # fmt: skip
    finally:  # the W&B service this process started stops, and WANDB_SERVICE (which the
        wandb.teardown()  # later tests' subprocesses would inherit) leaves the environment
    record = json.loads((out / "results.json").read_text())
    rows = read_system_csv(out)
    block = record["system"]
    assert block["samples"] == len(rows) >= 2 and block["interval_s"] == 0.2
    for column in ("cpu_percent", "rss_bytes", "disk_read_bytes_per_s", "disk_write_bytes_per_s"):
        assert block["peak"][column] == max(r[column] for r in rows), column
    written = sum(r["disk_write_bytes_per_s"] * s for r, s in zip(rows, _spans(rows), strict=True))
    assert block["total"]["disk_write_bytes"] == pytest.approx(written, rel=0.01, abs=4096)

    client = MlflowClient(store)
    (run,) = client.search_runs([client.get_experiment_by_name("resireg").experiment_id])
    assert run.info.run_id == record["tracking"]["mlflow_run_id"]
    assert run.info.status == "FINISHED"
    history = client.get_metric_history(run.info.run_id, "system/cpu_utilization_percentage")
    assert len(history) >= 2 and sorted(m.step for m in history) == list(range(len(history)))
    assert {"system/system_memory_usage_megabytes", "system/disk_usage_megabytes"} <= set(
        run.data.metrics
    )

    (wandb_file,) = out.glob("wandb/offline-run-*/run-*.wandb")
    stats = _stats(wandb_file)
    assert len(stats) >= 2  # (a median gap needs two)
    gaps = sorted(b[0] - a[0] for a, b in zip(stats[:-1], stats[1:], strict=True))
    assert 0.1 <= gaps[len(gaps) // 2] <= 1.0  # W&B's default is 15 s
    wandb_peak = max(v["proc.memory.rssMB"] for _, v in stats) * 2**20
    assert wandb_peak == pytest.approx(block["peak"]["rss_bytes"], rel=0.15)
    sync = subprocess.run([sys.executable, "-m", "wandb", "sync", "--dry-run",
                           str(wandb_file.parent)], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "WANDB_MODE": "offline"})  # fmt: skip
    assert sync.returncode == 0, sync.stderr
    assert "Would sync 1 run(s)" in sync.stdout + sync.stderr
    assert wandb_file.name in sync.stdout + sync.stderr


@pytest.mark.slow
def test_a_training_run_sends_system_metrics_to_its_mlflow_run(tmp_path):
    """The smoke training with tracker=mlflow: the run Lightning logs its curves to also holds
    MLflow's system metrics, and results.json's peaks are system.csv's maxima."""
    pytest.importorskip("mlflow")
    from mlflow import MlflowClient

    from helpers.run import run

    store = f"sqlite:///{tmp_path}/mlflow.db"
    out = tmp_path / "train"
    run("resireg-train", "experiment=smoke", "trainer.max_epochs=1", "data.steps_per_epoch=2",
        "export=false", "tracker=mlflow", f"tracker.mlflow.tracking_uri={store}",
        "system_metrics.interval=0.5", f"hydra.run.dir={out}", threads=1)  # fmt: skip
    record = json.loads((out / "results.json").read_text())
    rows = read_system_csv(out)
    assert record["system"]["samples"] == len(rows) >= 1
    assert record["system"]["peak"]["rss_bytes"] == max(r["rss_bytes"] for r in rows)
    client = MlflowClient(store)
    trained = client.get_run(record["tracking"]["mlflow_run_id"])
    assert "train/loss" in trained.data.metrics  # Lightning's run ...
    assert client.get_metric_history(trained.info.run_id, "system/cpu_utilization_percentage")


@pytest.mark.slow
def test_a_map_run_records_its_system_metrics(tmp_path, tiny_export):
    """resireg-map (a 4-frame room bag) samples its system metrics as training and evaluation
    do: system.csv's rows, and results.json's system block with as many samples and, for each
    column, the rows' maximum as its peak."""
    from helpers.run import run
    from resireg_train.data.room_bag import TOPICS, room_frames, write_bag

    bag = write_bag(tmp_path / "room", room_frames(4))
    out = tmp_path / "map"
    run("resireg-map", f"model_path={tiny_export}", "device=cpu", f"source.path={bag}",
        "source=rosbag", f"source.colour_topic={TOPICS['colour']}",
        f"source.depth_topic={TOPICS['depth']}", f"source.camera_info_topic={TOPICS['info']}",
        "variant=bb", "window=2", "system_metrics.interval=0.1", f"hydra.run.dir={out}",
        threads=1)  # fmt: skip
    record = json.loads((out / "results.json").read_text())
    rows = read_system_csv(out)
    block = record["system"]
    assert record["status"] == "completed" and block["interval_s"] == 0.1
    assert block["samples"] == len(rows) >= 1
    for column in ("cpu_percent", "rss_bytes"):
        assert block["peak"][column] == max(r[column] for r in rows), column
