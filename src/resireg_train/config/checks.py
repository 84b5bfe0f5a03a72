"""The checks a run's config must pass before anything starts.

Hydra/OmegaConf check structure; they do not know that a learning rate must be positive or
that ``min_lr`` must not exceed ``lr``. :func:`validate` (``resireg-train``) and
:func:`validate_eval` (``resireg-eval``) do, and report every violation at once, each as
``key=value: expected ...``, before any model or dataset is loaded. ReSiReg's parameters
(the ``resireg`` config group) and the evaluation pass settings are checked by one rule set
in both, under their prefix.

This module is imported before anything heavy: it needs only OmegaConf and the spec tables
(``resireg.specs``: the variants' names and parameter rules, which the classes check too; the
encoder kinds and what they import; ``resireg_train.evaluation.tasks`` and ``resireg_train.data.specs``:
the tasks and the dataset kinds with their keys and value rules), no torch: a bad value is reported before torch loads
(``check_devices`` imports torch when it runs).
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.errors import (
    Arguments,
    ConfigError,
    add_note,
    argument_names,
    raised_by,
    renamed,
)
from resireg.specs.encoders import ENCODER_REPORT_KEYS, ENCODER_SPECS, Needs, encoder_kwargs
from resireg.specs.exports import export_source_problem
from resireg.specs.priors import PRIOR_KINDS, SAM_RULES
from resireg.specs.rules import (
    BATCH_SIZE,
    DEVICE,
    DEVICE_KINDS,
    Rule,
    integer,
    interval,
    is_int,
    is_num,
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
from resireg_train.data.specs import (
    dataset_key_errors,
    dataset_value_errors,
    find_dataset,
    missing_keys_error,
)
from resireg_train.evaluation.tasks import TASK_SPECS, task_config_errors

__all__ = [
    "ADDABLE",
    "ConfigError",
    "ENCODER_IMPORTS",
    "ENCODER_SWEEPS",
    "ENCODER_REPORT_KEYS",
    "PRECISIONS",
    "TASKS",
    "check_devices",
    "check_available",
    "config_path",
    "encoder_arguments",
    "error_message",
    "encoder_import_errors",
    "encoder_kwargs",
    "init_from_problem",
    "unknown_key_errors",
    "validate",
    "sweep_config_errors",
    "validate_eval",
]

#: Evaluation precisions -> the torch dtype name of their autocast (``None``: fp32, no autocast).
PRECISIONS: dict[str, str | None] = {
    "32": None, "32-true": None, "bf16": "bfloat16", "bf16-mixed": "bfloat16",
}  # fmt: skip


_MISSING = object()
#: Device kinds of ``device`` / ``prior.device`` (``cuda:N`` included).
#: What ``resireg-report`` can write for a sweep beyond its summary (``report: [...]`` in a
#: ``conf/sweep/`` file names them; ``null`` leaves the choice to the jobs' overrides).
REPORT_SECTIONS = ("table1", "table2", "prototype_grid", "layer_sweep")
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


@contextmanager
def config_path(prefix: str, arguments: Arguments = ()) -> Iterator[None]:
    """The config path ``prefix`` added to the errors of the library calls inside: resireg's
    messages name the function's own argument (``path='x': ...``), the config names the entry.

    An error of resireg's code that names one of ``arguments`` (``name=...``, or a message that
    starts with the name: :func:`resireg.errors.rename_arguments`) names ``<prefix>.<name>``
    instead (``arguments`` may map a name to its whole config path: ``{"names": "variants"}``);
    one whose message starts with it comes back a :class:`ConfigError` (still of its own type:
    a ``FileNotFoundError`` stays one). Any other error gets the note ``config: <prefix>`` and
    goes on as it was. Errors of ``resireg_train``'s own code name their config paths already
    and pass untouched.

    Used where a config entry meets the library: ``encoder`` (``build_encoder``), ``prior``
    (``build_prior``), ``variants`` (``build_variants``), ``model.teacher`` (RADSeg)."""
    try:
        yield
    except Exception as err:
        if raised_by(err, "resireg_train"):
            raise
        new = renamed(err, argument_names(prefix, arguments))
        if new is not None:
            raise new from err
        add_note(err, f"config: {prefix}")
        raise


def encoder_arguments(entry: Any) -> tuple[str, ...]:
    """What the messages of ``build_encoder(**entry)`` may name: the entry's keys and
    :func:`resireg.models.factory.encoder_arguments` (``kind``, ``device``, the builder's
    arguments; the builder is imported, as ``build_encoder`` would, and one that does not
    import leaves them out: ``build_encoder`` reports that)."""
    from resireg.models.factory import encoder_arguments as of_kind

    keys = tuple(entry) if isinstance(entry, dict) else ()
    try:
        named = of_kind(entry.get("kind")) if isinstance(entry, dict) else ()
    except Exception:
        named = ("kind", "device")
    return tuple(dict.fromkeys((*keys, *named)))


def error_message(err: BaseException) -> str:
    """``str(err)`` and its notes (``config: encoder``), one per line."""
    return "\n".join([str(err), *map(str, getattr(err, "__notes__", None) or ())])


_PRECISIONS = {
    "32-true", "32", "bf16-mixed", "16-mixed", "bf16-true", "16-true", "64-true", "64",
    "transformer-engine", "transformer-engine-float16",
}  # fmt: skip


_int, _num, _integer, _optional_int = is_int, is_num, integer, optional_int


def _opt_str(v: Any) -> bool:
    return v is None or isinstance(v, str)


def _number(minimum: float, strict: bool = False) -> Rule:
    return number(minimum, strict=strict)


# key -> (check, what is expected). A key absent from the config is not checked.
_RULES: dict[str, Rule] = {
    "seed": (_int, "an integer"),
    "data.batch_size": BATCH_SIZE,
    "data.steps_per_epoch": _integer(1),
    "data.crop_size": _integer(16),
    "data.min_image_size": _integer(1),
    "data.num_workers": _integer(0),
    "data.shuffle_buffer": _integer(0),
    "data.sources": (lambda v: isinstance(v, dict) and len(v) > 0, "a non-empty mapping"),
    "model.optimizer._target_": (lambda v: isinstance(v, str), "an optimizer class path"),
    "model.optimizer.lr": _number(0, strict=True),
    "model.optimizer.weight_decay": _number(0),
    "model.scheduler.min_lr": _number(0),
    "model.loss.contrastive.scale": _number(0),
    "model.loss.contrastive.warmup_epochs": _number(0),
    "model.loss.distill.scale": _number(0),
    "model.loss.distill.warmup_epochs": _number(0),
    "model.logit_scale.init": _number(0, strict=True),
    "model.logit_scale.max": _number(0, strict=True),
    "model.head.drop_path": (lambda v: _num(v) and 0 <= v < 1, "a number in [0, 1)"),
    "model.head.out_dim": _integer(1),
    "model.head.depth": _integer(1),
    "model.init_from": (_opt_str, "null or a path"),
    "model.intermediate_layer": (lambda v: v is None or _int(v), "null or a block index"),
    "model.text.cache_size": _optional_int(0),
    "trainer.max_epochs": _integer(1),
    "trainer.precision": (lambda v: str(v) in _PRECISIONS, f"one of {sorted(_PRECISIONS)}"),
    "ckpt_path": (_opt_str, "null, 'last' or a checkpoint path"),
    "optimized_metric": (_opt_str, "null or a metric name"),
}


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


_unit = interval(0, 1)[0]


#: resireg-eval's tasks (the table :data:`resireg_train.evaluation.tasks.TASK_SPECS`;
#: docs/architecture.md#adding-a-task).
TASKS = tuple(TASK_SPECS)


def _ovss_rules(prefix: str) -> dict[str, Rule]:
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
        f"{prefix}num_workers": _integer(0),
        f"{prefix}precision": (lambda v: str(v) in PRECISIONS, f"one of {sorted(PRECISIONS)}"),
        f"{prefix}temperature": _number(0, strict=True),
    }


_RULES.update(_ovss_rules("callbacks.resireg_eval."))
_RULES["callbacks.resireg_eval.every_n_epochs"] = _integer(1)

# resireg-eval (conf/eval.yaml)
_EVAL_RULES: dict[str, Rule] = {
    "seed": (_int, "an integer"),
    "model_path": (
        _opt_str,
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
    **_ovss_rules(""),
    "dataset.short_side": _optional_int(16),
    "dataset.limit": _optional_int(1),
    "optimized_metric": (_opt_str, "null or a metric name"),
    "feature_cache": (_opt_str, "null or a directory for stored encoder outputs"),
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
        f"one of {list(TASK_SPECS)} (resireg_train.evaluation.tasks)",
    ),
    "report": (
        lambda v: v is None or (isinstance(v, list) and all(x in REPORT_SECTIONS for x in v)),
        f"null or a list of {list(REPORT_SECTIONS)}",
    ),
}


def _get(cfg: DictConfig, key: str) -> Any:
    """The resolved plain value at ``key`` (``_MISSING`` when absent; ``None`` when ``???``)."""
    value = OmegaConf.select(cfg, key, default=_MISSING, throw_on_missing=False)
    if OmegaConf.is_config(value):
        return OmegaConf.to_container(value, resolve=True)
    return value


def _missing(node: Any, prefix: str = "") -> list[str]:
    """Keys holding ``???`` (found without resolving interpolations)."""
    if isinstance(node, dict):
        return [m for k, v in node.items() for m in _missing(v, f"{prefix}{k}.")]
    return [prefix[:-1]] if node == "???" else []


def _errors(cfg: DictConfig, rules: dict[str, Rule]) -> list[str]:
    """One message per ``???`` key and per rule a present value breaks."""
    missing = _missing(OmegaConf.to_container(cfg, resolve=False))
    errors = [
        f"{key}=???: a value is required (e.g. {key}=... on the command line)" for key in missing
    ]
    for key, (check, expected) in rules.items():
        value = _get(cfg, key)
        if key not in missing and value is not _MISSING and not check(value):
            errors.append(f"{key}={value!r}: expected {expected}")
    return errors


#: Where a ``+key=value`` override may add a key (a new callback or logger, a Lightning
#: ``Trainer`` or optimizer argument: their constructors reject unknown ones; the stage-2 start,
#: README "Stage 2"), per entry point; ``_CLOSED`` parts of them are read key by key.
ADDABLE = {
    "train": ("callbacks.", "logger.", "trainer.", "model.optimizer.", "model.init_from"),
    "eval": (),
}
_CLOSED = ("callbacks.resireg_eval.",)


def _addable(key: str, addable: Sequence[str]) -> bool:
    if key.startswith(_CLOSED):
        return False
    return any(key == a or (a.endswith(".") and key.startswith(a)) for a in addable)


def _nearest(key: str, known: Iterable[str], everywhere: Iterable[str] = ()) -> str:
    """`` (did you mean x?)``: the known sibling closest to ``key``'s last part, else the key
    anywhere in the config (``everywhere``: dotted keys) whose last part is closest; or ``""``."""
    parent, _, name = key.rpartition(".")
    match = difflib.get_close_matches(name, [k for k in known if k != name], n=1, cutoff=0.6)
    if match:
        return f" (did you mean {f'{parent}.' if parent else ''}{match[0]}?)"
    by_name: dict[str, str] = {}
    for full in sorted(everywhere, key=lambda k: (k.count("."), k)):  # the shallowest first
        if full != key:
            by_name.setdefault(full.rpartition(".")[2], full)
    match = difflib.get_close_matches(name, list(by_name), n=1, cutoff=0.6)
    return f" (did you mean {by_name[match[0]]}?)" if match else ""


def _paths(node: Any, prefix: str = "") -> list[str]:
    """Every dotted key of a plain nested dict (inner nodes included)."""
    if not isinstance(node, dict):
        return []
    return [p for k, v in node.items() for p in (f"{prefix}{k}", *_paths(v, f"{prefix}{k}."))]


def unknown_key_errors(
    cfg: DictConfig,
    added: Iterable[str] = (),
    addable: Sequence[str] = (),
    top_level: Iterable[str] | None = None,
) -> list[str]:
    """Keys that nothing reads, each named with the closest known one: every key a ``+``
    override added (``added``) outside ``addable`` sections (``+batchsize=4`` next to
    ``batch_size``), and, given ``top_level`` (the top-level keys ``conf/`` defines), every
    top-level key outside it, wherever it came from (an experiment, a sweep, a user's file)."""
    errors = []
    everywhere = _paths(OmegaConf.to_container(cfg, resolve=False))
    for key in added:
        if _addable(key, addable):
            continue
        parent = key.rpartition(".")[0]
        node = OmegaConf.select(cfg, parent) if parent else cfg
        siblings = [str(k) for k in node.keys()] if OmegaConf.is_dict(node) else []
        hint = _nearest(key, siblings, everywhere)
        errors.append(f"{key}={_get(cfg, key)!r}: no such key, nothing would read it{hint}; "
                      "set existing keys without +")  # fmt: skip
    if top_level is not None:
        known = set(top_level)
        for key in cfg:
            if key not in known and key not in added:
                hint = _nearest(str(key), known, everywhere)
                errors.append(f"{key}={_get(cfg, str(key))!r}: no such key, nothing would read "
                              f"it{hint}")  # fmt: skip
    return errors


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


def _needs_model_path(kind: Any) -> bool:
    """Whether encoder ``kind`` reads ``model_path`` (our VLM's export; the encoder table)."""
    spec = ENCODER_SPECS.find(kind) if isinstance(kind, str) else None
    return spec is not None and spec.needs_model_path


#: The sweeps over every encoder (the paper's Tables 1 and 2; their report is an encoder table).
ENCODER_SWEEPS = ("table1", "table2")
#: The ``encoder`` axis of a sweep over every encoder: the resolver (registered by the CLIs,
#: :func:`resireg_train.cli.job.register_resolvers`) joins the encoder table's configurations.
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
            check, expected = _EVAL_RULES["variants"]
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


def validate_eval(
    cfg: DictConfig | dict, added: Iterable[str] = (), top_level: Iterable[str] | None = None
) -> None:
    """Check a ``resireg-eval`` config (``conf/eval.yaml``); raise :class:`ConfigError` listing
    all. ``added`` and ``top_level``: see :func:`unknown_key_errors`."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    errors = unknown_key_errors(cfg, added, ADDABLE["eval"], top_level) + _errors(cfg, _EVAL_RULES)
    if _needs_model_path(_get(cfg, "encoder.kind")) and not _get(cfg, "model_path"):
        errors.append(
            "model_path=None: encoder=resireg_vlm needs an export folder (resireg-train's "
            "<run>/export) or a Hugging Face repo id; or choose another encoder= (conf/encoder/)"
        )
    task, kind = _get(cfg, "task"), _get(cfg, "dataset.kind")
    dataset = _get(cfg, "dataset")
    if isinstance(dataset, dict):  # its kind and keys (the dataset table)
        errors += dataset_key_errors(dataset, "dataset")
    entry = find_dataset(kind)
    # the kind's own rules (the dataset table's entry), checked here with the others
    values = {n: _get(cfg, f"dataset.{n}") for n in (entry.rules if entry is not None else {})}
    errors += dataset_value_errors(kind, {n: v for n, v in values.items() if v is not _MISSING})
    variants = _get(cfg, "variants")
    with_prior = [v for v in variants if takes_prior(str(v))] if isinstance(variants, list) else []
    if with_prior and _get(cfg, "prior") in (None, _MISSING):
        errors.append(
            f"prior=None: variants {with_prior} take a segmentation prior; choose one "
            "(prior=sam2, conf/prior/) or drop +prior"
        )
    # the task's dataset kinds and configurations (resireg_train.evaluation.tasks; an unknown task is the
    # "task" rule's error)
    on_layer = [v for v in variants if _on_layer(v)] if isinstance(variants, list) else []
    if (task := "ovss" if task is _MISSING else task) in TASK_SPECS:
        errors += task_config_errors(task, kind, with_prior, on_layer, variants)
    if errors:
        raise ConfigError("invalid config:\n  " + "\n  ".join(errors))


def validate(
    cfg: DictConfig | dict, added: Iterable[str] = (), top_level: Iterable[str] | None = None
) -> None:
    """Check value types and ranges of a training config; raise :class:`ConfigError` listing all.

    Also checks the cross-field rules: ``min_lr <= lr``, ``logit_scale.init <= max``, a
    teacher config whenever the distillation scale is > 0, and a source ``probability`` > 0;
    and keys nothing reads (``added``, ``top_level``: see :func:`unknown_key_errors`).
    """
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    errors = unknown_key_errors(cfg, added, ADDABLE["train"], top_level) + _errors(cfg, _RULES)
    values = {k: _get(cfg, k) for k in (
        "model.optimizer.lr", "model.scheduler.min_lr", "model.logit_scale.init",
        "model.logit_scale.max", "model.loss.distill.scale", "model.teacher", "data.sources",
    )}  # fmt: skip
    lr, min_lr = values["model.optimizer.lr"], values["model.scheduler.min_lr"]
    if _num(lr) and _num(min_lr) and min_lr > lr:
        errors.append(f"model.scheduler.min_lr={min_lr!r}: expected <= model.optimizer.lr={lr!r}")
    init, top = values["model.logit_scale.init"], values["model.logit_scale.max"]
    if _num(init) and _num(top) and init > top:
        errors.append(f"model.logit_scale.init={init!r}: expected <= model.logit_scale.max={top!r}")
    distill = values["model.loss.distill.scale"]
    if _num(distill) and distill > 0 and values["model.teacher"] in (None, _MISSING):
        errors.append(
            f"model.loss.distill.scale={distill!r}: distillation needs a model.teacher config "
            "(or set the scale to 0)"
        )
    text = _get(cfg, "model.text")
    if isinstance(text, dict) and text.get("kind") == "pretrained":
        weights = text.get("weights")
        if not (isinstance(weights, str) and weights):
            errors.append(
                f"model.text.weights={weights!r}: expected an open_clip pretrained tag of "
                f"model.text.model_name={text.get('model_name')!r} (e.g. webli) or a local "
                "open_clip checkpoint file"
            )
    callback = _get(cfg, "callbacks.resireg_eval.variants")
    if isinstance(callback, list) and any(takes_prior(str(v)) for v in callback):
        errors.append(
            f"callbacks.resireg_eval.variants={callback!r}: the training callback has no "
            "segmentation prior; score +prior configurations with resireg-eval prior=sam2"
        )
    datasets = _get(cfg, "callbacks.resireg_eval.datasets")
    if isinstance(datasets, dict):  # the callback's datasets: kinds and keys (the dataset table)
        for name, entry in datasets.items():
            if isinstance(entry, dict):
                errors += dataset_key_errors(entry, f"callbacks.resireg_eval.datasets.{name}")
    sources = values["data.sources"]
    if isinstance(sources, dict):
        for name, spec in sources.items():
            p = spec.get("probability", _MISSING) if isinstance(spec, dict) else None
            if p is _MISSING:  # no default weight: conf/data/ sets every source's
                errors.append(missing_keys_error(f"data.sources.{name}", ["probability"],
                                                 "conf/data/"))  # fmt: skip
            elif not (_num(p) and p > 0):
                errors.append(f"data.sources.{name}.probability={p!r}: expected a number > 0")
    if errors:
        raise ConfigError("invalid config:\n  " + "\n  ".join(errors))


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
    (:func:`encoder_import_errors`); raise :class:`ConfigError` listing every problem. Separate
    from :func:`validate`, as :func:`check_devices` is: a valid config names files and needs
    packages that another machine may have."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    errors = []
    model_path = _get(cfg, "model_path")
    if _needs_model_path(_get(cfg, "encoder.kind")) and isinstance(model_path, str) and model_path:
        if problem := export_source_problem(model_path):
            errors.append(f"model_path={model_path!r}: {problem}")
    init_from = _get(cfg, "model.init_from")
    if isinstance(init_from, str) and (problem := init_from_problem(init_from)):
        errors.append(f"model.init_from={init_from!r}: {problem}")
    errors += encoder_import_errors(_get(cfg, "encoder"))
    if errors:
        raise ConfigError("this machine does not have what the config names:\n  "
                          + "\n  ".join(errors))  # fmt: skip


def check_devices(cfg: DictConfig | dict) -> None:
    """Check that this machine has the devices a config asks for (``device`` of
    resireg-eval, ``trainer.accelerator`` of resireg-train); raise :class:`ConfigError`
    naming the key and the fix. Separate from :func:`validate`: a config valid on a GPU
    node is still valid on a laptop, it just cannot run there."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    errors = _device_errors("device", _get(cfg, "device"))
    accelerator = _get(cfg, "trainer.accelerator")
    if accelerator in ("gpu", "cuda"):
        fix = "use trainer=cpu (or trainer=ddp_cpu), or trainer.accelerator=auto"
        errors += _device_errors("trainer.accelerator", accelerator, fix)
    if errors:
        raise ConfigError("this machine cannot run the config:\n  " + "\n  ".join(errors))
