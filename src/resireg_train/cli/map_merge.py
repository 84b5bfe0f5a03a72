"""``resireg-map-merge``: one map of several mapping runs (Hydra main; ``conf/map_merge.yaml``,
docs/guide.md#merging-maps).

    resireg-map-merge A B --out C            # A, B: map folders or resireg-map run folders
    resireg-map-merge A B --out C 'transform=[[0,-1,0,2.0],[1,0,0,0],[0,0,1,0],[0,0,0,1]]'

The maps are loaded (memory-mapped) and merged into the first, in place
(:meth:`resireg.mapping.SemanticMap.merge`): maps of another encoder (their weights' digest),
other settings or another basis are refused, naming what differs, before anything is
written. The result is saved to ``<out>/map`` (``--out``: the run folder, Hydra's
``hydra.run.dir``; a ``resireg-map ... resume=true`` of the same folder continues it), with
``map.ply``; ``results.json`` records the maps merged (folder, voxels, frames, their files'
SHA-256), the result and the seconds per stage, through the run's record of every command
(:class:`~resireg_train.runs.record.RunRecord`: status, provenance, trackers).
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError, DataError, MapError
from resireg_train.cli.job import hydra_entry_point, run_task
from resireg_train.runs.record import RunRecord

__all__ = ["PROG", "hydra_arguments", "main", "map_folder"]

log = logging.getLogger(__name__)
PROG = "resireg-map-merge"


def map_folder(path: str | Path) -> Path:
    """The saved map of ``path``: the folder itself when it holds ``map.json``, else its
    ``map`` folder (a ``resireg-map`` run folder); else a :class:`ConfigError` naming it."""
    path = Path(path).expanduser()
    for folder in (path, path / "map"):
        if (folder / "map.json").is_file():
            return folder.resolve()
    raise ConfigError(f"maps: {str(path)!r} is neither a saved map (no map.json) nor a "
                      "resireg-map run folder (no map/map.json)")  # fmt: skip


def _merge(cfg: DictConfig, record: RunRecord) -> dict[str, Any]:
    from resireg.mapping import SemanticMap

    out = record.folder
    names = OmegaConf.to_container(cfg.maps, resolve=True)
    if not isinstance(names, list) or len(names) < 2:
        raise ConfigError(f"maps={names!r}: expected two or more map folders")
    folders = [map_folder(p) for p in names]
    transform = OmegaConf.to_container(cfg.transform, resolve=True) if cfg.transform else None
    if transform is not None:
        import torch

        t = torch.as_tensor(transform, dtype=torch.float64)
        if t.shape != (4, 4) or not bool(torch.isfinite(t).all()):
            raise ConfigError(f"transform={transform!r}: expected a finite [4, 4] matrix")
    target = out / "map"
    if (target / "map.json").is_file():
        raise ConfigError(f"{target} holds a map: give another --out")
    timer: dict[str, float] = {}
    t0 = time.perf_counter()
    try:  # a damaged map: one line naming its file
        maps = [SemanticMap.load(f) for f in folders]
    except DataError as err:
        raise ConfigError(f"maps: {err}") from err
    timer["load"] = time.perf_counter() - t0
    inputs = [{"folder": str(f), "voxels": len(m), "frames": m.frames, "storage": m.storage,
               "sha256": _record(f).get("sha256")} for f, m in zip(folders, maps, strict=True)]  # fmt: skip
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


def run_merge(cfg: DictConfig) -> dict[str, Any]:
    """Merge from a composed ``map_merge.yaml`` config; returns the ``results.json`` content."""
    return run_task(cfg, _merge, fresh=True)


def _quoted(text: str) -> str:
    """A value as a quoted string of Hydra's override grammar (any path stays one value)."""
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def hydra_arguments(argv: list[str]) -> list[str]:
    """``A B --out C key=value ...`` as Hydra's arguments: ``maps=[A,B]``,
    ``hydra.run.dir=C``, the overrides as they are (Hydra's own flags too)."""
    maps, rest, out = [], [], None
    args = iter(argv)
    for arg in args:
        if arg == "--out" or arg.startswith("--out="):
            out = arg.split("=", 1)[1] if "=" in arg else next(args, None)
            if not out:
                raise SystemExit(f"{PROG}: error: --out needs a folder")
        elif arg.startswith("-") or "=" in arg:
            rest.append(arg)
        else:
            maps.append(arg)
    front = [f"maps=[{','.join(map(_quoted, maps))}]"] if maps else []
    if out is not None:
        front.append(f"hydra.run.dir={_quoted(out)}")
    return [*front, *rest]


_main = hydra_entry_point("map_merge", run_merge)


def main() -> float | None:
    sys.argv = [sys.argv[0], *hydra_arguments(sys.argv[1:])]
    return _main()


if __name__ == "__main__":
    main()
