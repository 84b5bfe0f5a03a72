"""What a job's command line gave: the top-level keys a config defines (so a key it does not is
named), the keys its ``+key=value`` overrides added, and the instances of a config group."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from resireg_train.config.paths import CONFIG_DIR

__all__ = ["added_keys", "instantiate_group", "top_level_keys"]


def top_level_keys(config_name: str) -> set[str]:
    """The top-level keys ``conf/<config_name>.yaml`` defines: its own fields, its groups
    (``data``, ``model``...; ``experiment`` and ``sweep`` too), and the fields of the groups
    it places at the top level (``resireg@_here_``: ``variants``, ``lite``, ``full``...)."""
    raw = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / f"{config_name}.yaml"))
    keys = {k for k in raw if k not in ("defaults", "hydra")}
    for entry in raw.get("defaults") or []:
        if not isinstance(entry, dict):
            continue  # _self_
        for spec, option in entry.items():
            group, _, package = spec.partition("@")
            if package == "_here_" and option:
                placed = OmegaConf.load(CONFIG_DIR / group / f"{option}.yaml")
                keys |= {k for k in placed if k != "defaults"}
            else:
                keys.add(package.split(".")[0] if package else group.split("/")[0])
    return keys


def added_keys() -> list[str]:
    """The config keys this job's ``+key=value`` / ``++key=value`` overrides added (command
    line or sweep; not the ``+group=option`` of a config group), ``[]`` outside Hydra. A
    ``++`` override counts only if the config would not hold its key without it."""
    if not HydraConfig.initialized():
        return []
    from hydra import compose
    from hydra.core.override_parser.overrides_parser import OverridesParser

    runtime = HydraConfig.get()
    roots = [Path(src.path) for src in runtime.runtime.config_sources
             if src.schema == "file"] or [CONFIG_DIR]  # fmt: skip
    given = list(runtime.overrides.task)
    added, forced = [], []
    for override in OverridesParser.create().parse_overrides(given):
        key = override.key_or_group
        if not (override.is_add() or override.is_force_add()) or "/" in key:
            continue
        if any((root / key.replace(".", "/")).is_dir() for root in roots):
            continue  # a config group: +prior=sam2
        (forced if override.is_force_add() else added).append(key)
    if forced:
        plain = compose(runtime.job.config_name,
                        overrides=[o for o in given if not o.startswith("+")])  # fmt: skip
        added += [k for k in forced if OmegaConf.select(plain, k, default=None) is None]
    return added


def instantiate_group(group: DictConfig | None) -> list[Any]:
    """Instantiate every ``_target_`` entry of a config group (callbacks, loggers)."""
    if not group:
        return []
    return [hydra.utils.instantiate(c) for c in group.values() if c and "_target_" in c]

