"""What produced a run: the ``provenance`` block of every ``results.json`` (``resireg-train``,
``resireg-eval``, ``resireg-map``, each job of a multirun or search), joined from its parts.

:func:`start_provenance` writes it when the run starts, before anything heavy is imported:

- ``run_id``: twelve hex digits drawn once per run folder (a resumed run keeps its own), and
  ``cli``: the command (``resireg-train``, ``resireg-eval``, ``resireg-map``);
- ``code``: the code that ran (:mod:`~resireg_train.record.provenance.code`);
- ``environment``: Python, the command line (URL passwords masked), the digest of the
  resolved config, and the versions of the packages that change numbers; never an
  environment variable;
- ``machine``: host, CPU model, cores, memory, PID and world size
  (:mod:`~resireg_train.record.provenance.machine`);
- ``seeds``, ``data``, ``models``: what the run reads
  (:mod:`~resireg_train.record.provenance.inputs`).

:func:`finish_provenance` completes it at the end (success or failure): end time, wall seconds,
CPU-hours (this process and its children, from ``getrusage``), GPU-hours where CUDA ran (wall
time x the GPUs the run's processes used), torch's CUDA / cuDNN versions, each GPU's name
and memory, and torch's intra-op thread count (``machine.torch_threads``: a CPU result can
change with it, so ``resireg-runs rerun`` runs with the same). Nothing here is typed twice:
exports copy their run's block (``provenance.json`` in the export folder,
:func:`write_export_provenance`), evaluations and maps read it from there.

Imported by the record (:class:`~resireg_train.record.run_record.RunRecord`) and the training
CLI (an export's provenance).
"""

from __future__ import annotations

import datetime as _dt
import json
import platform
import shlex
import sys
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from resireg.secrets import mask_text
from resireg_train.record.provenance.code import code_provenance
from resireg_train.record.provenance.inputs import (
    EXPORT_PROVENANCE,
    guarded,
    input_provenance,
    seeds,
)
from resireg_train.record.provenance.machine import (
    cpu_seconds,
    gpu_provenance,
    machine_provenance,
    package_versions,
)
from resireg_train.record.settings import RecordSettings

__all__ = ["finish_provenance", "start_provenance", "write_export_provenance"]

#: CPU seconds this process (and its children) had used when each run folder's run started.
_CPU_AT_START: dict[str, float] = {}


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


# ------------------------------------------------------------------------------- records
def _cli() -> str | None:
    """``resireg-train`` / ``resireg-eval`` / ``resireg-map``: the Hydra main running."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    return f"resireg-{HydraConfig.get().job.config_name}"


def start_provenance(
    run: RecordSettings, out: Path, previous: Mapping[str, Any] | None = None
) -> dict:
    """The provenance block written when a run starts (module docstring), from the run's
    settings ``run`` (its resolved config, its ``provenance`` settings, its config's digest).
    ``previous``: the block of the run this one resumes (its ``run_id`` is kept). The command
    line is recorded with every URL's password masked; environment variables are never
    recorded."""
    plain = run.config
    run_id = (previous or {}).get("run_id") or uuid.uuid4().hex[:12]
    _CPU_AT_START[str(Path(out).resolve())] = cpu_seconds()
    return {
        "run_id": run_id,
        "cli": _cli(),
        "code": guarded(lambda: code_provenance(out, settings=run.provenance)),
        "environment": {
            "python": platform.python_version(),
            # every URL's password masked (a search's storage, a tracking URI)
            "command": mask_text(shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])),
            "config_sha256": run.config_sha256,
            "packages": package_versions(),
        },
        "machine": machine_provenance(),
        "time": {"start": _now(), "end": None, "wall_seconds": None},
        "seeds": seeds(plain),
        **input_provenance(plain),
    }


def finish_provenance(block: Mapping[str, Any], out: Path | None = None) -> dict[str, Any]:
    """``block`` completed at the run's end: end time, wall seconds, CPU-hours (``getrusage``
    of this process and its children since the run in ``out`` started), GPU-hours (wall x the
    world size, where CUDA ran), torch's CUDA / cuDNN versions and the GPUs."""
    done = json.loads(json.dumps(block))  # a copy
    clock = done.setdefault("time", {})
    end = _dt.datetime.now(_dt.timezone.utc)
    wall = (end - _dt.datetime.fromisoformat(clock["start"])).total_seconds() if clock.get(
        "start") else None  # fmt: skip
    start_cpu = _CPU_AT_START.get(str(Path(out).resolve()), 0.0) if out is not None else 0.0
    used = cpu_seconds() - start_cpu
    gpus, versions = gpu_provenance()
    world = int((done.get("machine") or {}).get("world_size") or 1)
    clock.update(
        end=end.isoformat(timespec="milliseconds"),
        wall_seconds=round(wall, 3) if wall is not None else None,
        cpu_hours=round(used / 3600, 6),
        gpu_hours=round(wall * world / 3600, 6) if gpus and wall is not None else None,
    )
    done.setdefault("machine", {})["gpus"] = gpus
    torch = sys.modules.get("torch")  # only if the run imported it
    if torch is not None:
        done["machine"]["torch_threads"] = torch.get_num_threads()
    done.setdefault("environment", {}).update({f"torch_{k}": v for k, v in versions.items()})
    return done


def write_export_provenance(export: Path, out: Path, block: Mapping[str, Any]) -> Path:
    """``<export>/provenance.json``: the training run that wrote the export (its folder, its
    provenance block) and the SHA-256 of its last checkpoint, so an evaluation of the export
    can name the run, the code and the data that made it."""
    from resireg.integrity import atomic_write, sha256_file

    last = Path(out) / "checkpoints" / "last.ckpt"
    record = {
        "run_dir": str(Path(out).resolve()),
        "run_id": block.get("run_id"),
        "checkpoint": {
            "path": str(last.resolve()),
            "sha256": sha256_file(last) if last.is_file() else None,
        },  # fmt: skip
        "provenance": {k: v for k, v in block.items() if k != "time"},
    }
    return atomic_write(export / EXPORT_PROVENANCE, json.dumps(record, indent=2),
                        what="export provenance")  # fmt: skip
