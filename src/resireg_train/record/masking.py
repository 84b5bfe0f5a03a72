"""A run's config as its files and trackers keep it: the password of every URL masked
(:func:`resireg.secrets.mask_text`, the one rule).

- :func:`masked_tree`: a config tree with its strings masked (what records, trackers and the
  resume check compare and show);
- :func:`mask_saved_configs`: the config files Hydra saved for a run, masked in place.

Imported by the record, the trackers, the training CLI and the run tools (rerun).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from resireg.integrity import atomic_write
from resireg.secrets import mask_text

__all__ = ["mask_saved_configs", "masked_tree"]


def masked_tree(tree: Any) -> Any:
    """A copy of a config tree (mappings and lists) with the URL passwords of its strings
    masked: what records, trackers and the resume check compare and show."""
    if isinstance(tree, Mapping):
        return {k: masked_tree(v) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return [masked_tree(v) for v in tree]
    return mask_text(tree) if isinstance(tree, str) else tree


def mask_saved_configs(folder: Path) -> None:
    """Mask URL passwords in the config files Hydra saved for the run in ``folder``
    (``.hydra/config.yaml``, ``hydra.yaml``, ``overrides.yaml``) and, for a multirun job, in
    its sweep's ``multirun.yaml``: a tracking URI given on the command line would otherwise
    keep its password there. A resume compares configs with their URLs masked
    (:func:`resireg_train.cli.train.check_resume`)."""
    files = sorted((folder / ".hydra").glob("*.yaml"))
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
            files.append(Path(str(HydraConfig.get().sweep.dir)) / "multirun.yaml")
    except ImportError:  # pragma: no cover (Hydra is the train extra's)
        pass
    for path in files:
        try:
            text = path.read_text()
        except OSError:
            continue
        masked = mask_text(text)
        if masked != text:
            atomic_write(path, masked, what="saved config", mode=path.stat().st_mode & 0o777)
