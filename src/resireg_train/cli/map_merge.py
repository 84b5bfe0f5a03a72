"""``resireg-map-merge``: one map of several mapping runs (Hydra main; ``conf/map_merge.yaml``,
docs/guide.md#merging-maps).

    resireg-map-merge A B --out C            # A, B: map folders or resireg-map run folders
    resireg-map-merge A B --out C 'transform=[[0,-1,0,2.0],[1,0,0,0],[0,0,1,0],[0,0,0,1]]'

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

``--out`` is checked before anything is written into it (:class:`MergeFolderCheck`, before
Hydra writes its ``.hydra/`` files and the log): a folder that holds a map, or the record of
any other run (a ``resireg-map`` run, an evaluation, another merge), or lies inside such a
folder, is refused in one line and left as it was; the folder of this same merge that did not
complete (interrupted, killed, failed) is taken again, the temporary files a killed save left
in ``<out>/map`` removed.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError, DataError, MapError
from resireg_train.cli.job import error_text, hydra_entry_point, run_task
from resireg_train.record.run_record import RecordError, RunRecord, enclosing_run

__all__ = ["PROG", "MergeFolderCheck", "check_out", "hydra_arguments", "main"]

log = logging.getLogger(__name__)
PROG = "resireg-map-merge"


def _names(cfg: DictConfig) -> Any:
    """The ``maps`` of the config (the command's positional arguments); a
    :class:`ConfigError` when none were given."""
    if OmegaConf.is_missing(cfg, "maps"):
        raise ConfigError(f"maps: none given (usage: {PROG} A B [...] --out C)")
    return OmegaConf.to_container(cfg.maps, resolve=True)


def _folders(names: Any) -> list[Path]:
    """The saved maps of the ``maps`` arguments, resolved (:func:`resireg.mapping.map_folder`:
    a map folder or a run folder); a :class:`ConfigError` naming one that is neither."""
    from resireg.mapping import map_folder

    if not isinstance(names, list) or len(names) < 2:
        raise ConfigError(f"maps={names!r}: expected two or more map folders")
    try:
        return [map_folder(p).resolve() for p in names]
    except FileNotFoundError as err:
        raise ConfigError(f"maps: {err}") from None


def check_out(out: Path, names: Any) -> None:
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
            if recorded == [str(f) for f in _folders(names)]:
                return  # this merge, taken again
        except ConfigError:
            pass
    raise ConfigError(
        f"--out {out} holds the record of another run ({RunRecord(out).path}: "
        f"{previous.get('name')!r}, status {previous.get('status')!r}"
        + (f", maps {recorded}" if recorded else "")
        + "): a merge never writes into another run's folder; give another --out"
    )


class MergeFolderCheck(Callback):
    """Hydra callback (``conf/map_merge.yaml``, before the folder's lock): :func:`check_out`
    before Hydra writes anything into ``--out`` (``.hydra/``, the log file), so a refused
    merge leaves another run's folder exactly as it was."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        out = Path(str(config.hydra.run.dir))
        try:
            check_out(out, _names(config))
        except ConfigError as err:
            # Hydra turns a callback's exception into a warning and runs the job anyway: exit.
            sys.stderr.write(f"{PROG}: refused: {error_text(err)}\n")
            raise SystemExit(1) from None


def _merge(cfg: DictConfig, record: RunRecord) -> dict[str, Any]:
    from resireg.mapping import SemanticMap
    from resireg.mapping.semantic_map import remove_partial_saves

    out = record.folder
    names = _names(cfg)
    folders = _folders(names)
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
    target = out / "map"  # (--out was checked before the record started: run_merge)
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


def run_merge(cfg: DictConfig) -> dict[str, Any]:
    """Merge from a composed ``map_merge.yaml`` config; returns the ``results.json`` content.
    ``--out`` is checked first (:func:`check_out`; from the command line, before Hydra wrote
    into it)."""
    check_out(Path(cfg.paths.output_dir), _names(cfg))
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
