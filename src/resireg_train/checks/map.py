"""The checks of ``resireg-map`` and ``resireg-map-merge`` before anything is loaded or written:
the map's settings by their rules, the source block by its kind's, the merge's maps and its
``--out`` folder. Each refusal is one :class:`~resireg.errors.ConfigError` naming the key.

Imported by :mod:`resireg_train.jobs.map`, :mod:`resireg_train.jobs.map_merge` and
:mod:`resireg_train.cli.map_merge` (the Hydra callback that checks ``--out`` first).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError
from resireg.specs.sources import source_errors
from resireg_train.config.errors import block_errors
from resireg_train.record.run_record import RecordError, RunRecord, enclosing_run

__all__ = ["MERGE", "check_map_config", "check_merge_out", "check_source", "merge_folders",
           "merge_names"]  # fmt: skip

#: resireg-map-merge's name, in its usage line
MERGE = "resireg-map-merge"


def check_map_config(cfg: DictConfig) -> None:
    """The map's settings by their rules (:data:`resireg.specs.mapping.MAP_RULES`, the live
    node's too), every violation in one :class:`ConfigError`, before anything is loaded."""
    from resireg.specs.mapping import MAP_RULES, map_errors

    every = OmegaConf.to_container(cfg, resolve=True)
    values = {k: every[k] for k in MAP_RULES if "." not in k and k in every}
    if "compact" in every:
        values["compact"] = every["compact"]
    errors = map_errors(values)
    if errors:
        raise ConfigError("; ".join(errors))


def check_source(spec: dict[str, Any], key: str = "source") -> None:
    """A ``source`` block's keys and values by its kind's entry of
    :data:`~resireg.specs.sources.SOURCE_SPECS`, every violation in one :class:`ConfigError`
    naming the config path (``source.path=...``)."""
    errors = block_errors(source_errors(spec), key, spec)
    if errors:
        raise ConfigError("; ".join(errors))


def merge_names(cfg: DictConfig) -> Any:
    """The ``maps`` of the config (the command's positional arguments); a
    :class:`ConfigError` when none were given."""
    if OmegaConf.is_missing(cfg, "maps"):
        raise ConfigError(f"maps: none given (usage: {MERGE} A B [...] --out C)")
    return OmegaConf.to_container(cfg.maps, resolve=True)


def merge_folders(names: Any) -> list[Path]:
    """The saved maps of the ``maps`` arguments, resolved (:func:`resireg.mapping.map_folder`:
    a map folder or a run folder); a :class:`ConfigError` naming one that is neither."""
    from resireg.mapping import map_folder

    if not isinstance(names, list) or len(names) < 2:
        raise ConfigError(f"maps={names!r}: expected two or more map folders")
    try:
        return [map_folder(p).resolve() for p in names]
    except FileNotFoundError as err:
        raise ConfigError(f"maps: {err}") from None


def check_merge_out(out: Path, names: Any) -> None:
    """Refuse ``--out`` (the run folder ``out``) before anything is written into it: a
    :class:`ConfigError` when it holds a map, lies inside a folder that holds one or a run's
    record, or holds the record (``results.json``) of any run but this merge's own that did
    not complete (a merge of the same maps ``names``, or one that failed before it recorded
    them)."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: not a folder: give another --out")
    target = out / "map"
    for held in (out, target):
        if (held / "map.json").is_file():
            raise ConfigError(f"--out {out} holds a map ({held}): give another --out")
    if (above := enclosing_run(out)) is not None:
        raise ConfigError(
            f"--out {out} is inside the folder of another run or map ({above}): "
            "a merge never writes into another run's folder; give another --out"
        )
    try:
        previous = RunRecord.read(out)
    except RecordError as err:
        raise ConfigError(f"--out {out}: {err}: give another --out") from None
    if not previous:
        return
    recorded = (previous.get("params") or {}).get("maps")
    if previous.get("name") == "map_merge" and previous.get("status") != "completed":
        if recorded is None:
            return  # a merge that failed before it recorded its maps
        try:
            if recorded == [str(f) for f in merge_folders(names)]:
                return  # this merge, taken again
        except ConfigError:
            pass
    raise ConfigError(
        f"--out {out} holds the record of another run ({RunRecord(out).path}: "
        f"{previous.get('name')!r}, status {previous.get('status')!r}"
        + (f", maps {recorded}" if recorded else "")
        + "): a merge never writes into another run's folder; give another --out"
    )
