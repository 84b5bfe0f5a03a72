"""The settings a run's record starts with, read from the job's config in one place.

:class:`RecordSettings` is built once from a job's composed config
(:meth:`RecordSettings.from_config`) and handed to
:meth:`~resireg_train.record.run_record.RunRecord.start`, which passes its parts down: the
trackers' blocks to :class:`~resireg_train.record.trackers.base.RunTrackers`, the provenance
settings and the resolved config to :func:`~resireg_train.record.provenance.block.start_provenance`,
the system metrics' settings to the sampler and the trackers' own monitors. No part of the
record reads the config again.

:func:`provenance_settings`: the ``provenance`` block (``conf/provenance/default.yaml``: the
heartbeat, what ``code.diff`` may hold, rerun's tolerance).

Imported by the record, its provenance and trackers, the job wrapper and the run tools (the
index, rerun); imports ``resireg``, the provenance's config digest, the system metrics'
settings check and, inside functions, OmegaConf.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from resireg_train.record.masking import masked_tree
from resireg_train.record.provenance.inputs import config_digest
from resireg_train.record.system import system_settings

__all__ = ["RecordSettings", "provenance_settings"]


def _plain(node: Any) -> Any:
    """A config node as plain values, resolved where it can be (an interpolation only Hydra's
    runtime resolves is kept as written)."""
    from omegaconf import OmegaConf

    if not OmegaConf.is_config(node):
        return node
    try:
        return OmegaConf.to_container(node, resolve=True)
    except Exception:
        return OmegaConf.to_container(node, resolve=False)


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


@dataclass(frozen=True)
class RecordSettings:
    """What a run's record needs from its job's config, read once (:meth:`from_config`).

    Attributes:
        name: the run's ``name``.
        trackers: the ``tracker.<name>`` blocks that are set, in their order, as plain values
            (resolved): the trackers the run reports to.
        training: whether the job trains (its config has a ``trainer``): Lightning then logs
            its curves through the trackers' loggers.
        resuming: whether the job resumes a checkpoint (``ckpt_path`` set): a tracker then
            continues the run its record names.
        provenance: the ``provenance`` block over its defaults (:func:`provenance_settings`).
        system_metrics: ``(enabled, interval in seconds)`` of ``system_metrics``
            (:func:`~resireg_train.record.system.system_settings`; a bad value is refused here,
            before the record is written).
        config: the composed config as plain values (resolved where it can be): what the
            provenance reads the seeds and inputs from. Its passwords are not masked:
            :attr:`masked_config` is what a tracker is given (neither it nor ``trackers``
            is in the settings' ``repr``).
        config_sha256: the SHA-256 of the resolved config as YAML (``provenance.environment``).
    """

    name: str | None = None
    trackers: dict[str, dict[str, Any]] = field(default_factory=dict, repr=False)
    training: bool = False
    resuming: bool = False
    provenance: dict[str, Any] = field(default_factory=provenance_settings)
    system_metrics: tuple[bool, float] = (False, 0.0)
    config: dict[str, Any] = field(default_factory=dict, repr=False)
    config_sha256: str | None = None

    @classmethod
    def from_config(cls, cfg: Any) -> RecordSettings:
        """The settings of the job whose composed config is ``cfg`` (a ``DictConfig``, or a
        mapping of plain values). Raises :class:`~resireg.errors.ConfigError` naming the key
        of a bad ``system_metrics`` value."""
        trackers = {str(name): dict(_plain(block))
                    for name, block in (cfg.get("tracker") or {}).items() if block}  # fmt: skip
        plain = _plain(cfg)
        return cls(
            name=cfg.get("name"),
            trackers=trackers,
            training="trainer" in cfg,
            resuming=cfg.get("ckpt_path") is not None,
            provenance=provenance_settings(cfg),
            system_metrics=system_settings(cfg),
            config=dict(plain) if isinstance(plain, Mapping) else {},
            config_sha256=config_digest(cfg),
        )

    @property
    def masked_config(self) -> dict[str, Any]:
        """:attr:`config` with the password of every URL in it masked: what a tracker is
        given (:func:`~resireg_train.record.masking.masked_tree`)."""
        return masked_tree(self.config)
