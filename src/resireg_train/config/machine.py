"""What a config asks of this machine, checked before torch and the models load: the devices
(:func:`check_devices`), and the files and packages it names (:func:`check_available`).

Separate from the config checks (:func:`resireg_train.config.train.validate`,
:func:`resireg_train.config.eval.validate_eval`): a valid config names devices, files and
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
    "check_devices",
    "encoder_import_errors",
    "init_from_problem",
    "needs_model_path",
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
