"""The machine that ran: the ``machine`` part of a run's provenance and what is read at its end.

- :func:`machine_provenance`: host, CPU model, cores, memory, PID and world size;
- :func:`package_versions`: the versions of the packages that change numbers (read with
  :mod:`importlib.metadata`, no import);
- :func:`cpu_seconds` and :func:`gpu_provenance`: the CPU time used so far and, where the run
  imported torch, its CUDA / cuDNN versions and the GPUs CUDA ran on (no import of torch here).

Imported by :mod:`resireg_train.record.provenance.block`, which joins the parts.
"""

from __future__ import annotations

import importlib.metadata as md
import os
import platform
import socket
import sys
from pathlib import Path
from typing import Any

__all__ = ["PACKAGES", "cpu_seconds", "gpu_provenance", "machine_provenance", "package_versions"]


#: Distributions whose versions can change a number (those installed are recorded).
PACKAGES = (
    "resireg", "torch", "torchvision", "lightning", "hydra-core", "omegaconf", "timm",
    "open_clip_torch", "transformers", "tokenizers", "numpy", "scipy", "scikit-learn",
    "safetensors", "datasets", "huggingface_hub", "pillow", "torchmetrics", "einops",
    "segment-anything", "optuna", "mlflow", "wandb", "rosbags", "rerun-sdk", "onnx",
    "onnxruntime",
)  # fmt: skip


def package_versions(names: tuple[str, ...] = PACKAGES) -> dict[str, str]:
    """``{distribution: version}`` of the installed ones among ``names``."""
    versions = {}
    for name in names:
        try:
            versions[name] = md.version(name)
        except md.PackageNotFoundError:
            continue
    return versions


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_provenance() -> dict[str, Any]:
    """Host, CPU model and cores, memory (GiB), PID, OS and the world size (``WORLD_SIZE``,
    set by Lightning's and torchrun's launchers; 1 otherwise)."""
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        memory = None
    return {
        "host": socket.gethostname(),
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "memory_gib": round(memory, 1) if memory else None,
        "pid": os.getpid(),
        "os": platform.platform(),
        "world_size": int(os.environ.get("WORLD_SIZE", "1")),
    }


def gpu_provenance() -> tuple[list[dict[str, Any]], dict[str, Any]]:
    torch = sys.modules.get("torch")  # only if the run imported it: no import here
    if torch is None:
        return [], {}
    versions = {"cuda": torch.version.cuda}
    if torch.backends.cudnn.is_available():
        versions["cudnn"] = torch.backends.cudnn.version()
    if not torch.cuda.is_initialized():
        return [], versions
    gpus = []
    for i in range(torch.cuda.device_count()):
        props = torch.cuda.get_device_properties(i)
        gpus.append({"name": props.name, "memory_gib": round(props.total_memory / 2**30, 1)})
    return gpus, versions


def cpu_seconds() -> float:
    import resource

    usage = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    return sum(u.ru_utime + u.ru_stime for u in usage)
