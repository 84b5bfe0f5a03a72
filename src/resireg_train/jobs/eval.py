"""The evaluation job's body (``resireg-eval``'s door is :mod:`resireg_train.cli.eval`): the
export's recorded evaluation settings (:func:`with_export_settings`), the config check, then the
task's check, build and run (:func:`evaluate_body`)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from hydra import compose
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict

from resireg.errors import ConfigError
from resireg.specs.encoders import ENCODER_SPECS, encoder_kwargs
from resireg.specs.exports import registry_model
from resireg.specs.tree import flatten
from resireg_train.checks.eval import sweep_config_errors, validate_eval
from resireg_train.config.errors import config_path, encoder_arguments
from resireg_train.config.machine import check_available, check_devices
from resireg_train.config.paths import CONFIG_DIR, composing
from resireg_train.evaluation.base import require_task, write_results
from resireg_train.evaluation.ovss.settings import SETTING_KEYS, SETTINGS_FILE, load_settings
from resireg_train.jobs.overrides import added_keys, top_level_keys
from resireg_train.record.run_record import RunRecord
from resireg_train.report.specs import ENCODER_SWEEPS

__all__ = ["evaluate_body", "with_export_settings"]

log = logging.getLogger(__name__)


def _command_line_keys() -> list[str]:
    """The keys the command line (or a sweeper) set for this job."""
    if not HydraConfig.initialized():
        return []
    return [o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task]


def _defaults() -> DictConfig:
    """``conf/eval.yaml`` as composed without any override."""
    with composing():
        return compose("eval")


def with_export_settings(cfg: DictConfig) -> tuple[DictConfig, list[str]]:
    """``cfg`` with the export's recorded evaluation settings in place of the values still at
    their default (see the module docstring), and the keys that were taken."""
    spec = ENCODER_SPECS.find(cfg.encoder.kind)
    if spec is None or not spec.needs_model_path or not cfg.model_path:  # not our VLM's export
        return cfg, []
    export = Path(str(cfg.model_path)).expanduser()
    if registry_model(str(cfg.model_path)) is not None:  # models:/NAME@ALIAS: its local copy
        from resireg.models.vlm.registry import registry_export, registry_timeout

        export = registry_export(str(cfg.model_path), registry_timeout(cfg))
    if not cfg.get("export_settings", True) or not export.is_dir():
        return cfg, []
    recorded = load_settings(export)
    if not recorded:
        return cfg, []
    given, defaults = _command_line_keys(), _defaults()
    merged, taken = cfg.copy(), []
    with open_dict(merged):
        for key, value in flatten(recorded).items():
            on_command_line = any(
                key == g or key.startswith(f"{g}.") or g.startswith(f"{key}.") for g in given
            )
            current = OmegaConf.select(cfg, key, default=None)
            default = OmegaConf.select(defaults, key, default=None)
            if OmegaConf.is_config(current):
                current = OmegaConf.to_container(current)
            if OmegaConf.is_config(default):
                default = OmegaConf.to_container(default)
            if on_command_line or current != default or current == value:
                continue
            OmegaConf.update(merged, key, value, merge=False)
            taken.append(key)
    if taken:
        log.info(
            "evaluation settings from %s: %s", export / SETTINGS_FILE,
            ", ".join(f"{k}={OmegaConf.select(merged, k)}" for k in taken),
        )  # fmt: skip
    return merged, taken


def evaluate_body(cfg: DictConfig, record: RunRecord) -> dict[str, Any]:
    """The evaluation of a composed ``eval.yaml`` config with its run's ``record``: the
    export's settings, the config check, the task's ``check``, the encoder, ``build``, ``run``
    and the results (:func:`~resireg_train.evaluation.base.write_results`)."""
    out = record.folder
    cfg, from_export = with_export_settings(cfg)
    validate_eval(cfg, added_keys(), top_level_keys("eval") if HydraConfig.initialized() else None)
    if cfg.get("name") in ENCODER_SWEEPS and (errors := sweep_config_errors(CONFIG_DIR)):
        raise ConfigError("conf/ disagrees with the encoder table:\n  " + "\n  ".join(errors))
    check_available(cfg)
    check_devices(cfg)
    params = OmegaConf.to_container(cfg, resolve=True)
    params = {k: params[k] for k in ("model_path", "encoder", "dataset", *SETTING_KEYS)}
    params["task"] = str(cfg.get("task", "ovss"))
    params["prior"] = OmegaConf.to_container(cfg.prior, resolve=True) if cfg.get("prior") else None
    spec = require_task(params["task"])  # the task's entry (resireg_train.evaluation.specs)
    record.update(params=params, settings_from_export=from_export)
    # The models, datasets and torch load only now, after the config check.
    import torch

    from resireg.method.variants import build_variants
    from resireg.models import build_encoder, count_parameters
    from resireg.models.factory import resolve_device
    from resireg_train.evaluation.engine import StageTimer

    torch.manual_seed(cfg.seed)
    with config_path("variants", {"names": "variants"}):
        variants = build_variants(list(cfg.variants), params)
    task = spec.load()(spec, cfg, params, out)
    task.check(variants)  # the dataset's and the prior's sources, before the encoder loads
    entry = encoder_kwargs(params["encoder"])
    with config_path("encoder", encoder_arguments(entry)):
        encoder = build_encoder(**entry, device=resolve_device(cfg.device))
    # a hub encoder's hub_ref: the code loaded ("owner/name:<ref>"; None for a local clone)
    hub = {"hub_ref": encoder.hub_ref} if hasattr(encoder, "hub_ref") else {}
    record.update(encoder={"name": cfg.encoder.name, "kind": cfg.encoder.kind,
                           "third_party": bool(cfg.encoder.third_party),
                           "parameters": count_parameters(encoder), **hub})  # fmt: skip
    record.update(**task.build(encoder, variants))
    timer = StageTimer()
    result = task.run(encoder, variants, timer)
    return write_results(record, task, result, variants, timer)

