"""The check of a ``resireg-train`` config (``conf/train.yaml``), before anything heavy loads.

Hydra/OmegaConf check structure; they do not know that a learning rate must be positive or that
``min_lr`` must not exceed ``lr``. :func:`validate` does, and reports every violation at once,
each as ``key=value: expected ...``: the data, model, loss, trainer keys, the training
callback's evaluation (the pass rules of :func:`resireg_train.checks.eval.pass_rules`, under
``callbacks.resireg_eval.``, and its datasets by the dataset table), the teacher's and text
tower's kinds by their tables (:data:`resireg_train.training.specs.TEACHER_SPECS`,
:data:`resireg.specs.text.TEXT_SPECS`), and the cross-field rules. OmegaConf and the tables only: no torch.
"""

from __future__ import annotations

from collections.abc import Iterable

from omegaconf import DictConfig

from resireg.errors import ConfigError
from resireg.specs.rules import BATCH_SIZE, Rule, integer, is_int, is_num, number
from resireg.specs.text import CACHE_SIZE, TEXT_SPECS
from resireg.specs.variants import takes_prior
from resireg_train.checks.eval import pass_rules
from resireg_train.config.keys import MISSING, config_errors, optional_str, value_at
from resireg_train.data.specs import dataset_key_errors, missing_keys_error
from resireg_train.training.specs import TEACHER_SPECS

__all__ = ["TRAIN_RULES", "validate"]

_PRECISIONS = {
    "32-true", "32", "bf16-mixed", "16-mixed", "bf16-true", "16-true", "64-true", "64",
    "transformer-engine", "transformer-engine-float16",
}  # fmt: skip

#: key -> rule of ``conf/train.yaml`` (a key absent from the config is not checked)
TRAIN_RULES: dict[str, Rule] = {
    "seed": (is_int, "an integer"),
    "data.batch_size": BATCH_SIZE,
    "data.steps_per_epoch": integer(1),
    "data.crop_size": integer(16),
    "data.min_image_size": integer(1),
    "data.num_workers": (
        lambda v: v == "auto" or is_int(v) and v >= 0,
        "'auto' or an integer >= 0",
    ),
    "data.shuffle_buffer": integer(0),
    "data.sources": (lambda v: isinstance(v, dict) and len(v) > 0, "a non-empty mapping"),
    "model.optimizer._target_": (lambda v: isinstance(v, str), "an optimizer class path"),
    "model.optimizer.lr": number(0, strict=True),
    "model.optimizer.weight_decay": number(0),
    "model.scheduler.min_lr": number(0),
    "model.loss.contrastive.scale": number(0),
    "model.loss.contrastive.warmup_epochs": number(0),
    "model.loss.distill.scale": number(0),
    "model.loss.distill.warmup_epochs": number(0),
    "model.logit_scale.init": number(0, strict=True),
    "model.logit_scale.max": number(0, strict=True),
    "model.head.drop_path": (lambda v: is_num(v) and 0 <= v < 1, "a number in [0, 1)"),
    "model.head.out_dim": integer(1),
    "model.head.depth": integer(1),
    "model.init_from": (optional_str, "null or a path"),
    "model.intermediate_layer": (lambda v: v is None or is_int(v), "null or a block index"),
    "model.text.kind": (
        lambda v: TEXT_SPECS.find(v) is not None,
        f"one of {list(TEXT_SPECS)} (resireg.specs.text)",
    ),
    "model.text.cache_size": CACHE_SIZE,  # the text tower table's
    "model.teacher.kind": (
        lambda v: TEACHER_SPECS.find(v) is not None,
        f"one of {list(TEACHER_SPECS)} (resireg_train.training.specs)",
    ),
    "trainer.max_epochs": integer(1),
    "trainer.precision": (lambda v: str(v) in _PRECISIONS, f"one of {sorted(_PRECISIONS)}"),
    "ckpt_path": (optional_str, "null, 'last' or a checkpoint path"),
    "optimized_metric": (optional_str, "null or a metric name"),
    **pass_rules("callbacks.resireg_eval."),
    "callbacks.resireg_eval.every_n_epochs": integer(1),
}


def validate(
    cfg: DictConfig | dict, added: Iterable[str] = (), top_level: Iterable[str] | None = None
) -> None:
    """Check value types and ranges of a training config; raise :class:`ConfigError` listing all.

    Also checks the cross-field rules: ``min_lr <= lr``, ``logit_scale.init <= max``, a
    teacher config whenever the distillation scale is > 0, and a source ``probability`` > 0;
    and keys nothing reads (``added``, ``top_level``: see
    :func:`resireg_train.config.keys.unknown_key_errors`).
    """
    cfg, errors = config_errors(cfg, "train", TRAIN_RULES, added, top_level)
    values = {k: value_at(cfg, k) for k in (
        "model.optimizer.lr", "model.scheduler.min_lr", "model.logit_scale.init",
        "model.logit_scale.max", "model.loss.distill.scale", "model.teacher", "data.sources",
    )}  # fmt: skip
    lr, min_lr = values["model.optimizer.lr"], values["model.scheduler.min_lr"]
    if is_num(lr) and is_num(min_lr) and min_lr > lr:
        errors.append(f"model.scheduler.min_lr={min_lr!r}: expected <= model.optimizer.lr={lr!r}")
    init, top = values["model.logit_scale.init"], values["model.logit_scale.max"]
    if is_num(init) and is_num(top) and init > top:
        errors.append(f"model.logit_scale.init={init!r}: expected <= model.logit_scale.max={top!r}")
    distill = values["model.loss.distill.scale"]
    if is_num(distill) and distill > 0 and values["model.teacher"] in (None, MISSING):
        errors.append(
            f"model.loss.distill.scale={distill!r}: distillation needs a model.teacher config "
            "(or set the scale to 0)"
        )
    text = value_at(cfg, "model.text")
    if isinstance(text, dict) and text.get("kind") == "pretrained":
        weights = text.get("weights")
        if not (isinstance(weights, str) and weights):
            errors.append(
                f"model.text.weights={weights!r}: expected an open_clip pretrained tag of "
                f"model.text.model_name={text.get('model_name')!r} (e.g. webli) or a local "
                "open_clip checkpoint file"
            )
    callback = value_at(cfg, "callbacks.resireg_eval.variants")
    if isinstance(callback, list) and any(takes_prior(str(v)) for v in callback):
        errors.append(
            f"callbacks.resireg_eval.variants={callback!r}: the training callback has no "
            "segmentation prior; score +prior configurations with resireg-eval prior=sam2"
        )
    datasets = value_at(cfg, "callbacks.resireg_eval.datasets")
    if isinstance(datasets, dict):  # the callback's datasets: kinds and keys (the dataset table)
        for name, entry in datasets.items():
            if isinstance(entry, dict):
                errors += dataset_key_errors(entry, f"callbacks.resireg_eval.datasets.{name}")
    sources = values["data.sources"]
    if isinstance(sources, dict):
        for name, spec in sources.items():
            p = spec.get("probability", MISSING) if isinstance(spec, dict) else None
            if p is MISSING:  # no default weight: conf/data/ sets every source's
                errors.append(missing_keys_error(f"data.sources.{name}", ["probability"],
                                                 "conf/data/"))  # fmt: skip
            elif not (is_num(p) and p > 0):
                errors.append(f"data.sources.{name}.probability={p!r}: expected a number > 0")
    if errors:
        raise ConfigError("invalid config:\n  " + "\n  ".join(errors))
