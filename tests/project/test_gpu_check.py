"""benchmarks/gpu_check.py --dry-run: every section at tiny size on the CPU, so the GPU check
is known to run before a GPU is lent (issue 26, item 5)."""

from __future__ import annotations

import json
import sys

import pytest
import torch

from helpers.paths import ROOT

_BENCH = ROOT / "benchmarks"


@pytest.fixture
def gpu_check(monkeypatch):
    monkeypatch.syspath_prepend(str(_BENCH))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny ops: one thread is faster on a shared 2-core machine
    import gpu_check

    yield gpu_check
    torch.set_num_threads(threads)
    sys.modules.pop("gpu_check", None)


@pytest.mark.slow
def test_dry_run_writes_every_section(gpu_check, tmp_path, capsys):
    reference = tmp_path / "cpu.json"
    written = gpu_check.main(["--write-cpu-reference", str(reference), "--dry-run"])
    assert json.loads(reference.read_text()) == written and written["seconds"] > 0

    out = tmp_path / "check"
    report = gpu_check.main(["--dry-run", "--out", str(out), "--cpu-reference", str(reference)])
    on_disk = json.loads((out / "gpu_check.json").read_text())
    assert on_disk["dry_run"] is True and on_disk["device"]["name"] == "CPU"
    assert set(report) >= {"peak", "throughput", "lite", "clustering", "train"}
    assert report["peak"]["bfloat16"] > 0 and report["peak"]["float32"] > 0

    rows = report["throughput"]["throughput"]
    assert [r["variant"] for r in rows] == ["VLM", "VLM + Lite", "VLM + Full"]
    assert all(r["status"] == "ok" and r["images_per_s"] > 0 for r in rows)
    stages = report["throughput"]["stages"]
    assert {s["stage"] for s in stages} == {"backbone", "head", "lite", "full"}
    for s in stages:
        assert s["of_bf16_peak"] == pytest.approx(s["gflops"] / report["peak"]["bfloat16"])

    lite = {(r["dtype"], r["path"], r["backend"]): r for r in report["lite"]}
    # The CPU has the flash and math kernels; the CUDA-only ones are rows, not crashes.
    for backend in ("flash", "math"):
        row = lite[("float32", "sdpa", backend)]
        assert row["status"] == "ok" and row["max_abs_diff"] <= 1e-5
    assert lite[("float32", "sdpa", "efficient")]["status"].startswith("not eligible")
    fact = lite[("float32", "factorised", "")]
    assert fact["status"] == "ok" and fact["max_abs_diff"] == 0.0
    assert fact["gflop"] < lite[("float32", "sdpa", "flash")]["gflop"]

    cluster = report["clustering"]
    assert cluster["device_seconds"] > 0 and cluster["host_cpu"]["seconds"] > 0
    assert cluster["reference_cpu"] == written

    train = {r["step"]: r for r in report["train"]}
    alone, taught = train["without teacher"], train["with RADSeg-sized teacher"]
    assert alone["status"] == taught["status"] == "ok"
    assert alone["images_per_s"] > 0 and taught["images_per_s"] > 0
    # The teacher's forward (ViT, MLP) and the distillation head add matrix products.
    assert taught["gflop_per_step"] > alone["gflop_per_step"] > 0

    text = (out / "gpu_check.md").read_text()
    for header in ("## Throughput protocol", "## Lite", "## Full's clustering",
                   "## One bf16 training step", "reference CPU"):  # fmt: skip
        assert header in text
    assert "[gpu_check] train" in capsys.readouterr().out


def test_without_cuda_a_full_run_is_refused(gpu_check):
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    with pytest.raises(SystemExit):
        gpu_check.main(["--out", "unused"])
