"""``resireg-map-merge``'s job: one map of several mapping runs (its door:
:mod:`resireg_train.cli.map_merge`; ``conf/map_merge.yaml``, docs/mapping.md#merging-maps).

A map argument is a map folder or a run folder holding one in ``map/``
(:func:`resireg.mapping.map_folder`, the rule ``compact.basis`` follows too). The same map
given twice (by its path or by the SHA-256 of its tensor file: a copy) is refused, naming it:
merged with itself every point would count twice; so are two maps made of a same part (each map
records its parts in ``map.json``: its own id, or, for a merge, its inputs' parts; a map saved
before maps recorded them is one part, its tensor file's SHA-256), e.g. a run and a merge that
holds it, naming both and the part. The maps are loaded (memory-mapped) and
merged into the first, in place (:meth:`resireg.mapping.SemanticMap.merge`): maps of another
encoder (their weights' digest), other settings or another basis (by its SHA-256) are refused,
naming what differs, before anything is written. The result is saved to ``<out>/map``
(``--out``: the run folder, Hydra's ``hydra.run.dir``), with ``map.ply``; ``results.json``
records the maps merged (folder, voxels, frames, their files' SHA-256), the result and the
seconds per stage, through the run's record of every command
(:class:`~resireg_train.record.run_record.RunRecord`: status, provenance, trackers).

Imported by :mod:`resireg_train.cli.map_merge`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError, DataError, MapError
from resireg_train.checks.map import merge_folders, merge_names
from resireg_train.record.run_record import RunRecord

__all__ = ["merge_job"]

log = logging.getLogger(__name__)


def merge_job(cfg: DictConfig, record: RunRecord) -> dict[str, Any]:
    """Merge the config's ``maps`` into ``<run folder>/map`` (module docstring); returns the
    ``results.json`` content. ``--out`` was checked before the record started
    (:func:`~resireg_train.checks.map.check_merge_out`)."""
    from resireg.mapping import SemanticMap
    from resireg.mapping.map_file import remove_partial_saves

    out = record.folder
    names = merge_names(cfg)
    folders = merge_folders(names)
    for i, folder in enumerate(folders):  # merged with itself, every point would count twice
        if folder in folders[:i]:
            raise ConfigError(f"maps: {folder} is given twice ({names[folders.index(folder)]!r} "
                              f"and {names[i]!r}): a map merged with itself counts every point "
                              "twice")  # fmt: skip
    transform = OmegaConf.to_container(cfg.transform, resolve=True) if cfg.transform else None
    if transform is not None:
        import torch

        t = torch.as_tensor(transform, dtype=torch.float64)
        if t.shape != (4, 4) or not bool(torch.isfinite(t).all()):
            raise ConfigError(f"transform={transform!r}: expected a finite [4, 4] matrix")
    target = out / "map"
    remove_partial_saves(target)  # a killed save's temporary files (this merge's, taken again)
    timer: dict[str, float] = {}
    t0 = time.perf_counter()
    try:  # a damaged map: one line naming its file
        maps = [SemanticMap.load(f) for f in folders]
    except DataError as err:
        raise ConfigError(f"maps: {err}") from err
    timer["load"] = time.perf_counter() - t0
    contents = [_content(f) for f in folders]  # (verified by the load)
    for i, digest in enumerate(contents):
        if digest in contents[:i]:
            raise ConfigError(f"maps: {folders[i]} holds the same map as "
                              f"{folders[contents.index(digest)]} (tensor file SHA-256 {digest}): "
                              "a map merged with itself counts every point twice")  # fmt: skip
    for i, smap in enumerate(maps):  # a run and a merge that holds it: its points count twice
        for j in range(i):
            held = set(maps[j].parts)
            shared = next((p for p in smap.parts if p in held), None)
            if shared is not None:
                raise ConfigError(f"maps: {folders[i]} and {folders[j]} share the part {shared} "
                                  "(one is made of the other's map): merged, its points would "
                                  "count twice")  # fmt: skip
    inputs = [{"folder": str(f), "voxels": len(m), "frames": m.frames, "storage": m.storage,
               "sha256": _record(f).get("sha256"), "parts": m.parts}
              for f, m in zip(folders, maps, strict=True)]  # fmt: skip
    record.update(params={"maps": [str(f) for f in folders], "transform": transform},
                   inputs=inputs)  # fmt: skip
    merged, t0 = maps[0], time.perf_counter()
    for folder, other in zip(folders[1:], maps[1:], strict=True):
        try:  # another encoder, other settings, another basis: refused, naming them
            merged.merge(other, transform)
        except MapError as err:
            raise ConfigError(f"{folder} into {folders[0]}: {err}") from err
    timer["merge"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    merged.save(target)
    timer["save"] = time.perf_counter() - t0
    ply = None
    if cfg.ply and len(merged):
        t0 = time.perf_counter()
        ply = merged.to_ply(out / "map.ply", "rgb" if merged.keeps_colour else "pca")
        timer["ply"] = time.perf_counter() - t0
    log.info("merged %d maps: %d voxels, %.1f MiB, %d frames in all -> %s", len(maps),
             len(merged), merged.nbytes / 2**20, merged.frames, target)  # fmt: skip
    return record.update(
        map={
            "folder": str(target),
            "voxels": len(merged),
            "bytes": merged.nbytes,
            "frames": merged.frames,
            "windows": merged.windows,
            "storage": merged.storage,
            "ply": None if ply is None else str(ply),
        },  # fmt: skip
        seconds={k: round(v, 4) for k, v in sorted(timer.items())},
    )


def _record(folder: Path) -> dict[str, Any]:
    import json

    return json.loads((folder / "map.json").read_text())


def _content(folder: Path) -> str:
    """The SHA-256 of a saved map's tensor file: the one its record holds (verified when the
    map loaded), or, for a map saved before maps recorded it, computed."""
    from resireg.integrity import sha256_file

    record = _record(folder)
    name = record["tensors"]
    return (record.get("sha256") or {}).get(name) or sha256_file(folder / name)
