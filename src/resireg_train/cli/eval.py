"""``resireg-eval``: OVSS of a dense encoder (Hydra main): our exported
:class:`~resireg.models.ResiregVLM` by default, or any encoder of ``conf/encoder/``.

    resireg-eval model_path=outputs/smoke/<time>/export dataset=synthetic
    resireg-eval encoder=clip_vit_b16 dataset=ade20k variants=[bb,calib,lite,full]
    resireg-eval sweep=table1                              # every encoder x dataset: Table 1
    resireg-eval model_path=<export> dataset=ade20k variants=[full] batch_size=16 \
        full.n_prototypes=60
    resireg-eval model_path=<export> dataset=ade20k sweep=prototype_batch      # the ablation grid
    resireg-eval model_path=<export> prior=sam2 variants=[full,full+prior]  # SAM 2.1 prior
    resireg-eval task=scannet3d dataset=scannet encoder=radseg paths.data_dir=/datasets  # 3D
    resireg-eval sweep=table2 paths.data_dir=/datasets          # 3D mapping: the paper's Table 2

The scores use the engine of the training callback (:mod:`resireg_train.ovss.engine`), so a
model's ``val/ovss/...`` numbers from training are recomputed exactly from its export.
ReSiReg's parameters (``variants``, ``lite.*``, ``full.*``) come from the ``resireg``
config group, which the training callback shares. An export written by ``resireg-train``
records the settings its training run evaluated it with (``resireg_eval.json``: variants,
``lite``, ``full``, ``batch_size``, ``precision``, ``temperature``); every one of them still at
its default here (not set on the command line, nor by an experiment or sweep file) takes
the recorded value, so ``resireg-eval`` reproduces the training score by default
(``export_settings=false`` turns this off).
``results.json`` in the output dir holds the status (and the error of a failed run), the
scores under ``final``, per-class IoU, the parameters, image counts, the batch-size
histogram and seconds per stage.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict

from resireg.specs.encoders import find_encoder
from resireg_train.cli.task import (
    CONFIG_DIR,
    added_keys,
    hydra_entry_point,
    run_task,
    top_level_keys,
)
from resireg_train.ovss.settings import SETTING_KEYS, SETTINGS_FILE, load_settings
from resireg_train.results import update_results
from resireg_train.validation import (
    ENCODER_SWEEPS,
    ConfigError,
    check_available,
    check_devices,
    encoder_kwargs,
    sweep_config_errors,
    validate_eval,
)

if TYPE_CHECKING:
    import torch

__all__ = ["evaluate", "main"]

log = logging.getLogger(__name__)


def _device(name: str) -> torch.device:
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _leaves(tree: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``("full.n_prototypes", 12)``... of a nested dict (lists are values)."""
    out = []
    for key, value in tree.items():
        if isinstance(value, dict):
            out += _leaves(value, f"{prefix}{key}.")
        else:
            out.append((f"{prefix}{key}", value))
    return out


def _command_line_keys() -> list[str]:
    """The keys the command line (or a sweeper) set for this job."""
    if not HydraConfig.initialized():
        return []
    return [o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task]


def _defaults() -> DictConfig:
    """``conf/eval.yaml`` as composed without any override."""
    if GlobalHydra.instance().is_initialized():
        return compose("eval")
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose("eval")


def with_export_settings(cfg: DictConfig) -> tuple[DictConfig, list[str]]:
    """``cfg`` with the export's recorded evaluation settings in place of the values still at
    their default (see the module docstring), and the keys that were taken."""
    spec = find_encoder(cfg.encoder.kind)
    if spec is None or not spec.needs_model_path or not cfg.model_path:  # not our VLM's export
        return cfg, []
    export = Path(str(cfg.model_path)).expanduser()
    if not cfg.get("export_settings", True) or not export.is_dir():
        return cfg, []
    recorded = load_settings(export)
    if not recorded:
        return cfg, []
    given, defaults = _command_line_keys(), _defaults()
    merged, taken = cfg.copy(), []
    with open_dict(merged):
        for key, value in _leaves(recorded):
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


def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """Evaluate from a composed ``eval.yaml`` config; returns the ``results.json`` content.

    A failure (bad value, missing model or dataset, too many prototypes for a batch) is
    recorded in ``results.json`` as ``"status": "failed"`` with its error, then re-raised.
    """
    return run_task(cfg, _evaluate)


def _check_sources(params: dict[str, Any], variants: Any) -> None:
    """Fail on a missing dataset folder or segmentation-prior model before the encoder loads
    (a large backbone takes minutes): the builders' own checks, run early."""
    from resireg.variant_names import takes_prior

    if params["task"] == "scannet3d":
        from resireg_train.data.scannet import check_scannet_spec

        check_scannet_spec(params["dataset"], "dataset")
    else:
        from resireg_train.data.segmentation import check_segmentation_source

        check_segmentation_source(params["dataset"], "dataset")
    if any(takes_prior(v) for v in variants):
        from resireg.priors import SAM_MODEL, check_sam_source

        check_sam_source(str(params["prior"].get("model") or SAM_MODEL), "prior")


def _evaluate(cfg: DictConfig, out: Path) -> dict[str, Any]:
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
    update_results(out, params=params, settings_from_export=from_export)
    # The models, datasets and torch load only now, after the config check.
    import torch

    from resireg.models import build_encoder, count_parameters
    from resireg.variant_names import takes_prior
    from resireg.variants import build_variants
    from resireg_train.data.segmentation import build_segmentation_set
    from resireg_train.ovss.engine import OVSSTask, StageTimer
    from resireg_train.protocol import protocol_record

    torch.manual_seed(cfg.seed)
    variants = build_variants(list(cfg.variants), params)
    _check_sources(params, variants)
    spec = encoder_kwargs(params["encoder"])
    encoder = build_encoder(**spec, device=_device(cfg.device), config_key="encoder")
    n_parameters = count_parameters(encoder)
    update_results(out, encoder={"name": cfg.encoder.name, "kind": cfg.encoder.kind,
                                 "third_party": bool(cfg.encoder.third_party),
                                 "parameters": n_parameters})  # fmt: skip
    if params["task"] == "scannet3d":  # 3D semantic mapping (docs/design.md section 10)
        from resireg_train.mapping.engine import run_scannet3d

        return _require_scored(run_scannet3d(cfg, out, encoder, variants, params), "frame")
    patch = encoder.input_rule.patch_size
    dataset = build_segmentation_set(params["dataset"], patch, key="dataset")
    update_results(out, protocol=protocol_record(params, dataset))
    task = OVSSTask(dataset, cfg.batch_size, cfg.num_workers, temperature=cfg.temperature)
    try:  # a setting the dataset's batches cannot take (more prototypes than points)
        task.check_variants(variants)
    except ValueError as err:
        raise ConfigError(str(err)) from err
    cache = None
    if cfg.get("feature_cache"):
        from resireg_train.cache import FeatureCache
        from resireg_train.ovss.engine import requested_layers

        key = FeatureCache.key_for(encoder, params["encoder"], params["dataset"], patch,
                                   str(cfg.precision), requested_layers(encoder, variants))  # fmt: skip
        cache = FeatureCache(cfg.feature_cache, key, dataset.describe)
        log.info("feature cache %s: %d images stored", cache.folder, len(cache))
    timer = StageTimer()
    provider = None
    if any(takes_prior(v) for v in variants):  # SAM loads only for a +prior configuration
        from resireg.priors import build_prior

        provider = build_prior(params["prior"], device=encoder.device, key="prior")
    result = task.run(encoder, variants, precision=str(cfg.precision), timer=timer, cache=cache,
                      prior=provider)  # fmt: skip
    scores = result.scores()
    for name, value in scores.items():
        log.info("%s = %.4f", name, value)
    if result.skipped:
        log.warning(result.skip_report())
    classes = dataset.classes
    record = update_results(
        out,
        final=scores,
        per_class_iou={
            v: dict(zip(classes, ious, strict=True)) for v, ious in result.per_class_iou().items()
        },  # fmt: skip
        images=result.images,
        skipped=result.skipped,
        skipped_samples=[s.as_dict() for s in result.skipped_samples],
        batch_sizes={str(k): v for k, v in result.batch_sizes.items()},
        **_elbo_counts(variants),
        seconds={k: round(v, 4) for k, v in sorted(timer.seconds.items())},
        **({"feature_cache": cache.summary()} if cache is not None else {}),
    )
    _require_scored(record, "image")
    return update_results(out, status="completed")


def _elbo_counts(variants: dict[str, Any]) -> dict[str, Any]:
    """``{"elbo_prototypes": {configuration: {count: batches}}}`` of the ``full.n_prototypes=
    elbo`` configurations (the count each batch was given, docs/design.md section 4.4b); ``{}``
    when none ran."""
    from collections import Counter

    counts = {name: dict(sorted(Counter(str(n) for n in v.chosen).items(), key=lambda c: int(c[0])))
              for name, v in variants.items() if getattr(v, "chosen", None)}  # fmt: skip
    return {"elbo_prototypes": counts} if counts else {}


class NothingScoredError(RuntimeError):
    """Every image (3D: frame) of the dataset was skipped: there is no score to report."""


def _require_scored(record: dict[str, Any], unit: str) -> dict[str, Any]:
    """``record`` (a run's ``results.json``) if it scored at least one ``unit``; else raise
    :class:`NothingScoredError` with the skip counts: a score over nothing (mIoU NaN) is a
    failed run, never a completed one."""
    if record.get("images", 0) > 0:
        return record
    skipped, dropped = int(record.get("skipped") or 0), int(record.get("frames_dropped") or 0)
    samples = record.get("skipped_samples") or []
    counts = f"{skipped} of {skipped + dropped} {unit}s skipped (unreadable or invalid)"
    if dropped:
        counts += f", {dropped} dropped (non-finite pose)"
    first = f"; the first: {samples[0]['file']}: {samples[0]['reason']}" if samples else ""
    name = (record.get("params") or {}).get("dataset", {}).get("name")
    raise NothingScoredError(
        f"dataset={name}: no {unit} was scored: {counts}{first} (results.json's "
        "skipped_samples names each with its reason)"
    )


main = hydra_entry_point("eval", evaluate)

if __name__ == "__main__":
    main()
