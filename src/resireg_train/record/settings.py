"""The settings a run's record starts with, read from the job's config in one place.

:func:`provenance_settings`: the ``provenance`` block (``conf/provenance/default.yaml``: the
heartbeat, what ``code.diff`` may hold, rerun's tolerance).

Imported by the record, its provenance and the run tools (the index, rerun); imports only
``resireg`` and, inside functions, OmegaConf.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["provenance_settings"]


def provenance_settings(cfg: Any = None) -> dict[str, Any]:
    """The ``provenance`` block of ``cfg`` over ``conf/provenance/default.yaml``'s values (all
    of them when ``cfg`` has none: a config composed without it, a call from Python)."""
    from resireg.specs.table import compose_conf, conf_dir

    settings = {k: v for k, (v, _) in compose_conf(conf_dir() / "provenance", "default").items()}
    block = cfg.get("provenance") if isinstance(cfg, Mapping) or hasattr(cfg, "get") else None
    if block:
        from omegaconf import OmegaConf

        settings.update(OmegaConf.to_container(block, resolve=True) if OmegaConf.is_config(block)
                        else block)  # fmt: skip
    return settings
