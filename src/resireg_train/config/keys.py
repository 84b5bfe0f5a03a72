"""Reading a composed config key by key: the value at a dotted key, the keys left ``???``, the
rules a value breaks, and the keys nothing would read. What the config checks
(:mod:`resireg_train.checks.train`, :mod:`resireg_train.checks.eval`,
:mod:`resireg_train.config.machine`) share; OmegaConf only, no torch."""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Sequence
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.specs.rules import Rule

__all__ = [
    "ADDABLE",
    "MISSING",
    "config_errors",
    "missing_keys",
    "optional_str",
    "rule_errors",
    "unknown_key_errors",
    "value_at",
]

#: What :func:`value_at` answers for a key the config lacks.
MISSING: Any = object()


def optional_str(v: Any) -> bool:
    """The check of a key that is ``null`` or a string (a path, a name)."""
    return v is None or isinstance(v, str)


def value_at(cfg: DictConfig, key: str) -> Any:
    """The resolved plain value at ``key`` (:data:`MISSING` when absent; ``None`` when ``???``)."""
    value = OmegaConf.select(cfg, key, default=MISSING, throw_on_missing=False)
    if OmegaConf.is_config(value):
        return OmegaConf.to_container(value, resolve=True)
    return value


def missing_keys(node: Any, prefix: str = "") -> list[str]:
    """Keys holding ``???`` (found without resolving interpolations)."""
    if isinstance(node, dict):
        return [m for k, v in node.items() for m in missing_keys(v, f"{prefix}{k}.")]
    return [prefix[:-1]] if node == "???" else []


def rule_errors(cfg: DictConfig, rules: dict[str, Rule]) -> list[str]:
    """One message per ``???`` key and per rule a present value breaks."""
    missing = missing_keys(OmegaConf.to_container(cfg, resolve=False))
    errors = [
        f"{key}=???: a value is required (e.g. {key}=... on the command line)" for key in missing
    ]
    for key, (check, expected) in rules.items():
        value = value_at(cfg, key)
        if key not in missing and value is not MISSING and not check(value):
            errors.append(f"{key}={value!r}: expected {expected}")
    return errors


#: Where a ``+key=value`` override may add a key (a new callback or tracker, a Lightning
#: ``Trainer`` or optimizer argument: their constructors reject unknown ones; the stage-2 start,
#: README "Stage 2"), per entry point; ``_CLOSED`` parts of them are read key by key.
ADDABLE = {
    "train": ("callbacks.", "tracker.", "trainer.", "model.optimizer.", "model.init_from"),
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
        errors.append(f"{key}={value_at(cfg, key)!r}: no such key, nothing would read it{hint}; "
                      "set existing keys without +")  # fmt: skip
    if top_level is not None:
        known = set(top_level)
        for key in cfg:
            if key not in known and key not in added:
                hint = _nearest(str(key), known, everywhere)
                errors.append(f"{key}={value_at(cfg, str(key))!r}: no such key, nothing would "
                              f"read it{hint}")  # fmt: skip
    return errors


def config_errors(
    cfg: DictConfig | dict,
    command: str,
    rules: dict[str, Rule],
    added: Iterable[str] = (),
    top_level: Iterable[str] | None = None,
) -> tuple[DictConfig, list[str]]:
    """``cfg`` (a ``DictConfig``) and the errors every config check of ``command`` (``train``,
    ``eval``) starts with: the keys nothing reads (:func:`unknown_key_errors`, ``+`` allowed in
    ``ADDABLE[command]``), then the ``???`` keys and the values that break ``rules``
    (:func:`rule_errors`)."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    errors = unknown_key_errors(cfg, added, ADDABLE[command], top_level)
    return cfg, errors + rule_errors(cfg, rules)
