"""What a config asks of this machine, checked before torch and the models load: the devices
(:func:`check_devices`), and the files and packages it names (:func:`check_available`).

Separate from the config checks (:func:`resireg_train.checks.train.validate`,
:func:`resireg_train.checks.eval.validate_eval`): a valid config names devices, files and
packages that another machine may have. Torch is imported only to ask about a GPU or MPS.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError
from resireg.specs.encoders import ENCODER_SPECS, Needs
from resireg.specs.exports import export_source_problem
from resireg_train.config.keys import value_at

__all__ = [
    "ENCODER_IMPORTS",
    "check_available",
    "check_cluster",
    "check_devices",
    "config_rank",
    "encoder_import_errors",
    "init_from_problem",
    "needs_model_path",
    "process_rank",
]

#: ``kind -> modules its code imports`` beyond the core install (``Needs``; the encoder table,
#: :data:`resireg.specs.encoders.ENCODER_SPECS`, holds them): :func:`encoder_import_errors`
#: (through :func:`check_available`) checks them before a model loads.
ENCODER_IMPORTS: dict[str, tuple[Needs, ...]] = {
    kind: spec.imports for kind, spec in ENCODER_SPECS.items() if spec.imports
}


def encoder_import_errors(entry: Any, key: str = "encoder") -> list[str]:
    """One message per module the encoder ``entry`` needs (:data:`ENCODER_IMPORTS`) that is
    not installed (found with ``importlib.util.find_spec``, nothing is imported), naming who
    imports it and the extra that installs it."""
    import importlib.util

    if not isinstance(entry, dict):
        return []
    errors = []
    spec = ENCODER_SPECS.find(entry.get("kind"))
    for module, dist, who, when in spec.imports if spec is not None else ():
        if when is not None and not when(entry):
            continue
        if importlib.util.find_spec(module) is None:
            errors.append(
                f"{key}.kind={entry.get('kind')!r}: {who} imports {module}, which is not "
                f'installed: pip install -e ".[encoders]" (or pip install {dist})'
            )
    return errors


def needs_model_path(kind: Any) -> bool:
    """Whether encoder ``kind`` reads ``model_path`` (our VLM's export; the encoder table)."""
    spec = ENCODER_SPECS.find(kind) if isinstance(kind, str) else None
    return spec is not None and spec.needs_model_path


def init_from_problem(source: str | os.PathLike) -> str | None:
    """Why ``model.init_from`` cannot be loaded (``None`` when it can be tried): it must be a
    training checkpoint file or an export folder (``ResiregModule.load_trained``)."""
    path = Path(source).expanduser()
    if path.is_file():
        return None
    if path.is_dir():
        if (path / "model.safetensors").is_file():
            return None
        return "a folder without model.safetensors: not a ResiregVLM export"
    return ("no such file or folder: expected a training checkpoint (<run>/checkpoints/last.ckpt) "
            "or an export folder (<run>/export)")  # fmt: skip


def check_available(cfg: DictConfig | dict) -> None:
    """Check that this machine has what a config names, before torch loads: the export of
    ``model_path`` (resireg-eval, ``encoder=resireg_vlm``; :func:`resireg.specs.
    exports.export_source_problem`), the checkpoint or export of ``model.init_from`` (resireg-train;
    :func:`init_from_problem`) and the modules the encoder's code imports
    (:func:`encoder_import_errors`); raise :class:`ConfigError` listing every problem."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    errors = []
    model_path = value_at(cfg, "model_path")
    if (
        needs_model_path(value_at(cfg, "encoder.kind"))
        and isinstance(model_path, str)
        and model_path
    ):
        if problem := export_source_problem(model_path):
            errors.append(f"model_path={model_path!r}: {problem}")
    init_from = value_at(cfg, "model.init_from")
    if isinstance(init_from, str) and (problem := init_from_problem(init_from)):
        errors.append(f"model.init_from={init_from!r}: {problem}")
    errors += encoder_import_errors(value_at(cfg, "encoder"))
    if errors:
        raise ConfigError("this machine does not have what the config names:\n  "
                          + "\n  ".join(errors))  # fmt: skip


def _device_errors(
    key: str, device: Any, fix: str = "use cpu, or auto to take a GPU only where there is one"
) -> list[str]:
    """A device this machine does not have (checked before any model is built; torch is
    imported only to ask about a GPU or MPS)."""
    if not isinstance(device, str):
        return []
    kind, _, index = device.partition(":")
    if kind not in ("cuda", "gpu", "mps"):
        return []
    import torch

    if kind in ("cuda", "gpu"):
        if not torch.cuda.is_available():
            return [f"{key}={device!r}: this machine has no CUDA GPU "
                    f"(torch.cuda.is_available() is False); {fix}"]  # fmt: skip
        if index.isdigit() and int(index) >= torch.cuda.device_count():
            return [
                f"{key}={device!r}: this machine has {torch.cuda.device_count()} CUDA device(s)"
            ]
    if kind == "mps" and not torch.backends.mps.is_available():
        return [f"{key}={device!r}: MPS is not available on this machine; {fix}"]
    return []


def check_devices(cfg: DictConfig | dict) -> None:
    """Check that this machine has the devices a config asks for (``device`` of
    resireg-eval, ``trainer.accelerator`` of resireg-train); raise :class:`ConfigError`
    naming the key and the fix. A config valid on a GPU node is still valid on a laptop, it
    just cannot run there."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    errors = _device_errors("device", value_at(cfg, "device"))
    accelerator = value_at(cfg, "trainer.accelerator")
    if accelerator in ("gpu", "cuda"):
        fix = "use trainer=cpu (or trainer=ddp_cpu), or trainer.accelerator=auto"
        errors += _device_errors("trainer.accelerator", accelerator, fix)
    if errors:
        raise ConfigError("this machine cannot run the config:\n  " + "\n  ".join(errors))


def _env_int(name: str) -> int | None:
    value = os.environ.get(name, "")
    return int(value) if value.isdigit() else None


def config_rank(cfg: Any) -> int:
    """:func:`process_rank` with the processes per node from a config's ``trainer.devices``
    (when a count)."""
    if cfg is not None and not OmegaConf.is_config(cfg):
        cfg = OmegaConf.create(cfg)
    devices = value_at(cfg, "trainer.devices") if cfg is not None else None
    per_node = devices if isinstance(devices, int) and devices > 0 else None
    return process_rank(per_node)


def process_rank(per_node: int | None = None) -> int:
    """This process's global rank from the environment its launcher or cluster set, before
    Lightning (not imported) is: torchrun's ``RANK``; Lightning's own variables
    (``NODE_RANK`` or ``GROUP_RANK``, and ``LOCAL_RANK``: a node started by hand or by a
    script, and the processes Lightning re-launches for ranks > 0), as ``node rank * processes
    per node + local rank``; SLURM's ``SLURM_PROCID`` (``srun``); LSF's
    ``JSM_NAMESPACE_RANK``; else 0 (a single process). The processes per node are
    ``per_node`` (the trainer's ``devices``) or ``LOCAL_WORLD_SIZE``; without either the
    number is exact on node 0 and non-zero on every other node, which is all the run folder's
    lock and record ask (global rank 0 alone writes them)."""
    rank = _env_int("RANK")
    if rank is not None:
        return rank
    node = _env_int("NODE_RANK")
    node = _env_int("GROUP_RANK") if node is None else node
    local = _env_int("LOCAL_RANK")
    if node is not None or local is not None:
        local = local or 0
        per = per_node or _env_int("LOCAL_WORLD_SIZE") or local + 1
        return (node or 0) * max(per, local + 1) + local
    for name in ("SLURM_PROCID", "JSM_NAMESPACE_RANK"):
        rank = _env_int(name)
        if rank is not None:
            return rank
    return 0


def check_cluster(cfg: DictConfig | dict) -> None:
    """Refuse, before any work, a process whose cluster environment contradicts the trainer
    it runs (``trainer.num_nodes``, ``trainer.devices``): a node rank (``NODE_RANK``,
    ``GROUP_RANK``, ``SLURM_NODEID``) not below the node count, a global rank (``RANK``,
    ``SLURM_PROCID``) not below ``WORLD_SIZE`` / ``SLURM_NTASKS``. Such a process would wait
    in the rendezvous for peers that never come, or join another run's; :class:`ConfigError`
    names the variable, its value and the setting it contradicts."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    trainer = value_at(cfg, "trainer")
    if not isinstance(trainer, (dict, DictConfig)):
        return
    nodes = value_at(cfg, "trainer.num_nodes")
    nodes = nodes if isinstance(nodes, int) and not isinstance(nodes, bool) else 1
    errors = []
    for name in ("NODE_RANK", "GROUP_RANK", "SLURM_NODEID"):
        value = _env_int(name)
        if value is not None and value >= nodes:
            errors.append(
                f"{name}={value}: this node's rank is not below trainer.num_nodes={nodes} "
                f"(node ranks run 0..{nodes - 1}); start it with a rank the job has, or set "
                "trainer.num_nodes to the job's node count"
            )
    for rank_name, size_name in (("RANK", "WORLD_SIZE"), ("SLURM_PROCID", "SLURM_NTASKS")):
        rank, size = _env_int(rank_name), _env_int(size_name)
        if rank is not None and size is not None and rank >= size:
            errors.append(f"{rank_name}={rank}: not below {size_name}={size}")
    if errors:
        raise ConfigError("this process's cluster environment contradicts the trainer: "
                          + "; ".join(errors))  # fmt: skip
