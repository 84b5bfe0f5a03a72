"""The check of a ``resireg-eval`` config (``conf/eval.yaml``) and of the sweeps over it
(``conf/sweep/``), before anything heavy loads.

:func:`validate_eval` reports every violation at once, each as ``key=value: expected ...``:
ReSiReg's parameters (the ``resireg`` config group; the variant table's rules, which the
classes check too), the pass settings (:func:`pass_rules`, shared with the training callback's
check in :mod:`resireg_train.checks.train`), the encoder, the prior, the task and its dataset
(the task and dataset tables, :data:`resireg_train.evaluation.specs.TASK_SPECS` and
:data:`resireg_train.data.specs.DATASET_SPECS`) and the report's sections. It reads the tables,
OmegaConf and nothing else: no torch.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError
from resireg.specs.encoders import ENCODER_SPECS
from resireg.specs.priors import PRIOR_KINDS, SAM_RULES
from resireg.specs.rules import (
    BATCH_SIZE,
    DEVICE,
    DEVICE_KINDS,
    Rule,
    integer,
    is_int,
    number,
    optional_int,
)
from resireg.specs.variants import (
    PRIOR_VARIANTS,
    VARIANT_SPECS,
    VARIANTS,
    parse_variant,
    takes_prior,
    variant_layer,
)
from resireg_train.config.keys import MISSING, config_errors, optional_str, value_at
from resireg_train.config.machine import needs_model_path
from resireg_train.data.specs import dataset_key_errors, dataset_value_errors, find_dataset
from resireg_train.evaluation.specs import PRECISIONS, TASK_SPECS, task_config_errors
from resireg_train.report.specs import ENCODER_SWEEPS, section_names

__all__ = [
    "EVAL_RULES",
    "EVERY_ENCODER",
    "TASKS",
    "every_encoder",
    "pass_rules",
    "sweep_config_errors",
    "validate_eval",
]

#: resireg-eval's tasks (the table :data:`resireg_train.evaluation.specs.TASK_SPECS`;
#: docs/architecture.md#adding-a-task).
TASKS = tuple(TASK_SPECS)


def _variant_ok(name: Any) -> bool:
    try:
        base = parse_variant(str(name))[0]
        variant_layer(str(name))  # @layer:<block> takes an integer
    except ValueError:
        return False
    return base in (PRIOR_VARIANTS if takes_prior(str(name)) else VARIANTS)


def _on_layer(name: Any) -> bool:
    """Whether configuration ``name`` runs on another encoder block (``lite@layer:5``)."""
    try:
        return variant_layer(str(name)) is not None
    except ValueError:
        return False  # reported by the variants rule


def pass_rules(prefix: str) -> dict[str, Rule]:
    """Rules of the keys resireg-eval and the ReSiRegEval callback share, under ``prefix``:
    the ``resireg`` group (variants and their parameters) and the pass settings."""
    return {
        f"{prefix}variants": (
            lambda v: isinstance(v, list) and len(v) > 0 and all(_variant_ok(n) for n in v),
            f"a non-empty list of {list(VARIANTS)}, each optionally with overrides "
            f"(full@n_prototypes:24); {list(PRIOR_VARIANTS)} also with the prior (full+prior); "
            "on another encoder block: lite@layer:5",
        ),
        # each variant's parameters, by the rules its class checks (resireg.specs.variants)
        **{
            f"{prefix}{name}.{key}": rule
            for name, spec in VARIANT_SPECS.items()
            for key, rule in spec.params.items()
        },  # fmt: skip
        f"{prefix}batch_size": BATCH_SIZE,
        f"{prefix}num_workers": integer(0),
        f"{prefix}precision": (lambda v: str(v) in PRECISIONS, f"one of {sorted(PRECISIONS)}"),
        f"{prefix}temperature": number(0, strict=True),
    }


#: key -> rule of ``conf/eval.yaml`` (a key absent from the config is not checked)
EVAL_RULES: dict[str, Rule] = {
    "seed": (is_int, "an integer"),
    "model_path": (
        optional_str,
        "null, an export folder, a Hugging Face repo id or "
        "models:/NAME@ALIAS (MLflow's model registry)",
    ),
    "encoder.kind": (
        lambda v: ENCODER_SPECS.find(v) is not None,
        f"one of {list(ENCODER_SPECS)} (resireg.specs.encoders) or a kind an installed package "
        "registers (entry points resireg.encoders)",
    ),
    "encoder.name": (lambda v: isinstance(v, str) and bool(v), "a name for reports"),
    "encoder.third_party": (lambda v: isinstance(v, bool), "true or false"),
    "device": DEVICE,
    **pass_rules(""),
    "dataset.short_side": optional_int(16),
    "dataset.limit": optional_int(1),
    "optimized_metric": (optional_str, "null or a metric name"),
    "feature_cache": (optional_str, "null or a directory for stored encoder outputs"),
    # the segmentation prior (conf/prior/sam2.yaml), absent with prior=null
    "prior.kind": (lambda v: v in PRIOR_KINDS, f"one of {list(PRIOR_KINDS)}"),
    "prior.model": (lambda v: isinstance(v, str) and bool(v), "a hub id or a local directory"),
    "prior.device": (
        lambda v: v is None or (isinstance(v, str) and v.split(":")[0] in DEVICE_KINDS),
        "null (the evaluation's device), auto, cpu, cuda, cuda:N or mps",
    ),
    **{f"prior.{name}": rule for name, rule in SAM_RULES.items()},  # resireg.specs.priors
    "task": (
        lambda v: v in TASK_SPECS,
        f"one of {list(TASK_SPECS)} (resireg_train.evaluation.specs)",
    ),
    # resireg-report's sections (resireg_train.report.specs)
    "report": (
        lambda v: v is None or (isinstance(v, list) and all(x in section_names() for x in v)),
        f"null or a list of {list(section_names())}",
    ),
}


def validate_eval(
    cfg: DictConfig | dict, added: Iterable[str] = (), top_level: Iterable[str] | None = None
) -> None:
    """Check a ``resireg-eval`` config (``conf/eval.yaml``); raise :class:`ConfigError` listing
    all. ``added`` and ``top_level``: see :func:`resireg_train.config.keys.unknown_key_errors`."""
    cfg, errors = config_errors(cfg, "eval", EVAL_RULES, added, top_level)
    if needs_model_path(value_at(cfg, "encoder.kind")) and not value_at(cfg, "model_path"):
        errors.append(
            "model_path=None: encoder=resireg_vlm needs an export folder (resireg-train's "
            "<run>/export) or a Hugging Face repo id; or choose another encoder= (conf/encoder/)"
        )
    task, kind = value_at(cfg, "task"), value_at(cfg, "dataset.kind")
    dataset = value_at(cfg, "dataset")
    if isinstance(dataset, dict):  # its kind and keys (the dataset table)
        errors += dataset_key_errors(dataset, "dataset")
    entry = find_dataset(kind)
    # the kind's own rules (the dataset table's entry), checked here with the others
    values = {n: value_at(cfg, f"dataset.{n}") for n in (entry.rules if entry is not None else {})}
    errors += dataset_value_errors(kind, {n: v for n, v in values.items() if v is not MISSING})
    variants = value_at(cfg, "variants")
    with_prior = [v for v in variants if takes_prior(str(v))] if isinstance(variants, list) else []
    if with_prior and value_at(cfg, "prior") in (None, MISSING):
        errors.append(
            f"prior=None: variants {with_prior} take a segmentation prior; choose one "
            "(prior=sam2, conf/prior/) or drop +prior"
        )
    # the task's dataset kinds and configurations (resireg_train.evaluation.specs; an unknown
    # task is the "task" rule's error)
    on_layer = [v for v in variants if _on_layer(v)] if isinstance(variants, list) else []
    if (task := "ovss" if task is MISSING else task) in TASK_SPECS:
        errors += task_config_errors(task, kind, with_prior, on_layer, variants)
    if errors:
        raise ConfigError("invalid config:\n  " + "\n  ".join(errors))


#: The ``encoder`` axis of a sweep over every encoder: the resolver (registered by the CLIs,
#: :func:`resireg_train.jobs.resolvers.register_resolvers`) joins the encoder table's configurations.
EVERY_ENCODER = "${resireg_encoders:}"


def every_encoder() -> str:
    """The value of ``${resireg_encoders:}``: every ``conf/encoder/`` configuration of the
    encoder table, comma-separated (a Hydra sweep axis)."""
    return ",".join(ENCODER_SPECS.all_configs())


# Registered on import, so a config composed outside the CLIs (a test, a notebook composing
# conf/ with Hydra's compose API) resolves the sweeps' encoder axis too.
if not OmegaConf.has_resolver("resireg_encoders"):
    OmegaConf.register_new_resolver("resireg_encoders", every_encoder)


def sweep_config_errors(conf_dir: str | os.PathLike) -> list[str]:
    """The config check of ``conf/sweep/``: every sweep's ``variants`` are valid configurations,
    the encoders on an ``encoder`` axis (``hydra.sweeper.params.encoder``) are configurations of
    the encoder table (:meth:`resireg.specs.table.SpecTable.all_configs`, found by scanning
    ``conf/encoder/``) and those of :data:`ENCODER_SWEEPS` generate the list from the table
    (``${resireg_encoders:}``) rather than type it. One message per problem, naming the file
    and the key."""
    conf, errors = Path(conf_dir), []
    known = ENCODER_SPECS.all_configs()
    for path in sorted((conf / "encoder").glob("*.yaml")):
        kind = OmegaConf.load(path).get("kind")
        if ENCODER_SPECS.find(kind) is None:
            errors.append(f"encoder/{path.name}: kind={kind!r}: "
                          f"{ENCODER_SPECS.unknown(kind)}")  # fmt: skip
    for path in sorted((conf / "sweep").glob("*.yaml")):
        sweep = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
        variants = sweep.get("variants")
        if variants is not None:
            check, expected = EVAL_RULES["variants"]
            if not check(variants):
                errors.append(f"sweep/{path.name}: variants={variants!r}: expected {expected}")
        axis = ((sweep.get("hydra") or {}).get("sweeper") or {}).get("params") or {}
        if "encoder" not in axis:
            continue
        text = str(axis["encoder"])
        if text.replace(" ", "") == EVERY_ENCODER:
            continue
        if path.stem in ENCODER_SWEEPS:
            errors.append(f"sweep/{path.name}: hydra.sweeper.params.encoder={text!r}: a sweep "
                          f"over every encoder generates its list from the table: "
                          f"{EVERY_ENCODER}")  # fmt: skip
        names = [n.strip() for n in text.split(",")]
        unknown = [n for n in names if n not in known]
        if unknown:
            errors.append(f"sweep/{path.name}: hydra.sweeper.params.encoder: {unknown} are not "
                          f"encoders of the table; known: {list(known)}")  # fmt: skip
    return errors
