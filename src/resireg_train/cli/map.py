"""``resireg-map``: a language-queryable voxel map from a posed RGB-D recording (Hydra main;
``conf/map.yaml``, docs/method.md#robot-maps-semanticmap).

    resireg-map source=rosbag source.path=run.bag model_path=<export> source.world_frame=odom
    resireg-map source=tum source.path=rgbd_dataset_freiburg1_desk source.camera=fr1
    resireg-map source=scannet source.path=/datasets/scannet/scene0011_00 rerun.save=map.rrd
    resireg-map source=nerfstudio source.path=data/scene
    resireg-map source=ros2 source.world_frame=odom     # live topics, until idle or Ctrl-C

The source (``source=<kind>``: ``conf/source/<kind>.yaml``, a kind of the table
:data:`resireg.specs.sources.SOURCE_SPECS`, read by :mod:`resireg.sources`) is checked and
opened before the encoder loads (every missing topic is reported in a second, with the bag's
topics). Windows of ``window`` consecutive frames go through
:meth:`resireg.mapping.SemanticMap.add` (a window whose encoder output is not finite is skipped
and counted); the map is saved every ``save_every`` windows and at the end to
``<output dir>/map`` with its identity (source, settings, ReSiReg parameters, encoder entry, a
digest of the encoder's weights): ``resume=true`` continues it from the last frame it holds (a
live source, ``source=ros2``: with the frames it receives now), or is refused naming the keys
that differ. Then ``map.ply``; ``results.json`` records frames read
/ used / skipped (by kind, the first reason of each, examples), corrupt messages, out-of-range
depth, the map's voxels and bytes, and seconds per stage; a run that maps nothing fails with the
reason per kind.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError, ResiregError, argument_names, rename_arguments
from resireg.specs.encoders import encoder_kwargs
from resireg.specs.sources import SOURCE_SPECS, source_errors
from resireg.specs.tree import MISSING, differences
from resireg_train.cli.job import hydra_entry_point, run_task
from resireg_train.config.errors import block_errors, config_path, encoder_arguments
from resireg_train.record.run_record import RunRecord

__all__ = ["SOURCES", "build_source", "check_map_config", "make_map", "main"]

log = logging.getLogger(__name__)

#: ``source.kind`` values: the built-in kinds of the source table.
SOURCES = SOURCE_SPECS.names()


def build_source(spec: dict[str, Any], key: str = "source"):
    """The frame source of a ``source`` block (``conf/source/<kind>.yaml``): its keys and
    values checked against its kind's entry of :data:`~resireg.specs.sources.SOURCE_SPECS`,
    then the entry's reader called with the block's keys; it opens the recording, so a missing
    file or topic fails here. Every refusal is a :class:`ConfigError` naming the config path:
    the library's own (``path='x': ...``) as ``source.path='x': ...``."""
    errors = block_errors(source_errors(spec), key, spec)
    if errors:
        raise ConfigError("; ".join(errors))
    entry = SOURCE_SPECS.get(spec["kind"])
    try:
        return entry.load()(**entry.arguments(spec))
    except (ResiregError, ValueError, FileNotFoundError) as err:
        raise ConfigError(_under(str(err), key, entry.rules)) from err


def _under(message: str, key: str, names: Iterable[str]) -> str:
    """``message`` of the library with each of its arguments ``names`` written as the config
    path ``<key>.<name>`` (:func:`resireg.errors.rename_arguments`, the rule of every boundary):
    a source's refusal is always a config error of its block."""
    return rename_arguments(message, argument_names(key, tuple(names)))[0]


def make_map(cfg: DictConfig, encoder: Any, prior: Any = None):
    """The :class:`~resireg.mapping.SemanticMap` of the config's map keys (conf/map.yaml)."""
    from resireg.mapping import SemanticMap
    from resireg.specs.variants import PARAM_VARIANTS  # the variant table's, with parameters

    params = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in PARAM_VARIANTS}
    storage = str(cfg.get("storage", "exact"))
    compact = _compact(cfg) if storage == "compact" else None
    try:
        return SemanticMap(encoder, str(cfg.configuration), float(cfg.voxel_size), params=params,
                           prior=prior, points=str(cfg.points), lattice=str(cfg.lattice),
                           sum_dtype=str(cfg.sum_dtype), max_voxels=cfg.max_voxels,
                           short_side=cfg.short_side, storage=storage, compact=compact)  # fmt: skip
    except (ValueError, ResiregError) as err:
        raise ConfigError(str(err)) from err


def _compact(cfg: DictConfig) -> dict[str, Any]:
    """The ``compact`` block, its ``basis`` path resolved (recorded absolute)."""
    block = OmegaConf.to_container(cfg.compact, resolve=True)
    block["basis"] = _resolved(block.get("basis"))
    return block


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


def _resolved(value: Any) -> Any:
    """A local path as its absolute, resolved form (a Hugging Face repo id or a name stays)."""
    if isinstance(value, str) and value and Path(value).expanduser().exists():
        return str(Path(value).expanduser().resolve())
    return value


def _identity(cfg: DictConfig, weights: str | None = None) -> dict[str, Any]:
    """What a resumed run must share with the saved map: the source (its path resolved; but
    ``limit`` and a live source's ``idle``: a run cut short by them resumes without them), the
    map's settings, the ReSiReg configuration's parameters (``lite`` / ``full`` / ``calib``...), the encoder's entry (its
    path resolved) and a digest of its weights (:func:`resireg.models.factory.weights_fingerprint`:
    another model at the same path differs)."""
    from resireg.specs.variants import PARAM_VARIANTS

    every = OmegaConf.to_container(cfg, resolve=True)
    source = dict(every["source"])
    source.pop("limit", None)
    source.pop("idle", None)  # a live source's stop rule, as limit is
    source["path"] = _resolved(source.get("path"))
    encoder = {k: _resolved(v) if k == "path" else v for k, v in every["encoder"].items()}
    keep = ("configuration", "window", "voxel_size", "points", "lattice", "sum_dtype",
            "short_side")  # fmt: skip
    out = {"source": source, **{k: every[k] for k in keep}, "encoder": encoder,
           "resireg": {k: every[k] for k in PARAM_VARIANTS if k in every},
           "prior": every.get("prior")}  # fmt: skip
    if every.get("storage", "exact") != "exact":  # (an exact map's identity is as before)
        out["storage"] = every["storage"]
        out["compact"] = _compact(cfg)
    if weights is not None:
        out["weights"] = weights
    return out


def _differences(saved: Any, now: dict[str, Any]) -> list[str]:
    """``key: saved -> now`` for each leaf key that differs (a key one side lacks included)."""
    shown = {id(MISSING): "(not recorded)"}
    return [
        f"{key}: {shown.get(id(a), repr(a))} in the map, {shown.get(id(b), repr(b))} now"
        for key, a, b in differences(saved if isinstance(saved, dict) else {}, now)
    ]


def _map(cfg: DictConfig, record: RunRecord) -> dict[str, Any]:
    import torch

    from resireg.mapping import MapFullError, SemanticMap
    from resireg.mapping.semantic_map import ENCODER_OUTPUT
    from resireg.method.checks import NonFiniteError
    from resireg.models import build_encoder
    from resireg.models.factory import resolve_device
    from resireg.sources.frames import FrameCounts, SkippedFrame, windows

    out = record.folder
    check_map_config(cfg)
    window, save_every = cfg.window, cfg.save_every
    spec = OmegaConf.to_container(cfg.source, resolve=True)
    errors = block_errors(source_errors(spec), "source", spec)  # before anything is written
    if errors:
        raise ConfigError("; ".join(errors))
    max_depth = spec["max_depth"]
    rrd = None
    if cfg.rerun.save:  # under the run folder unless absolute; recorded absolute
        rrd = Path(str(cfg.rerun.save)).expanduser()
        rrd = (rrd if rrd.is_absolute() else out / rrd).resolve()
    params = {"source": spec, "identity": _identity(cfg)}
    record.update(params=params)
    timer: dict[str, float] = defaultdict(float)
    start = time.perf_counter()
    source = build_source(spec)  # a wrong path, a missing topic: one line, no traceback
    timer["open_source"] += time.perf_counter() - start
    torch.manual_seed(int(cfg.seed))
    entry = encoder_kwargs(OmegaConf.to_container(cfg.encoder, resolve=True))
    with config_path("encoder", encoder_arguments(entry)):
        encoder = build_encoder(**entry, device=resolve_device(str(cfg.device)))
    prior = None
    from resireg.specs.variants import takes_prior

    if takes_prior(str(cfg.configuration)):
        from resireg.priors import build_prior

        prior_spec = OmegaConf.to_container(cfg.prior, resolve=True) if cfg.get("prior") else {}
        with config_path("prior", {"spec": "prior"}):
            prior = build_prior(prior_spec, device=encoder.device)
    from resireg.models.factory import weights_fingerprint

    t0 = time.perf_counter()
    identity = _identity(cfg, weights_fingerprint(encoder))
    timer["weights_digest"] += time.perf_counter() - t0
    record.update(params={**params, "identity": identity})
    folder = out / "map"
    if cfg.resume and (folder / "map.json").is_file():
        smap = SemanticMap.load(folder, encoder, prior, max_voxels=cfg.max_voxels)
        differ = _differences(smap.meta.get("identity"), identity)
        if differ:
            raise ConfigError(
                f"resume=true: {folder} was made with other settings ({len(differ)} differ): "
                + "; ".join(differ)
                + ". Start a new run folder, or resume with the map's values"
            )
        log.info("resuming %s: %d frames, %d voxels", folder, smap.frames, len(smap))
    else:
        if (folder / "map.json").is_file():
            raise ConfigError(f"{folder} holds a map: resume=true continues it, or use a new "
                              "run folder")  # fmt: skip
        smap = make_map(cfg, encoder, prior)
        smap.meta = {"identity": identity, "kept_frames": 0}
    done = int(smap.meta.get("kept_frames", 0))
    # A recording is read again from its start, so the frames a resumed map holds are skipped;
    # a live stream (a source whose ``live`` is true: ros2) goes on from now, every frame new.
    base, start = (done, 0) if getattr(source, "live", False) else (0, done)
    view = None
    if rrd is not None or cfg.rerun.spawn:
        from resireg.mapping.viewer import RerunView

        view = RerunView(str(rrd) if rrd else None, bool(cfg.rerun.spawn), cfg.rerun.query)
    counts = FrameCounts()
    added = 0
    # start: the frames the resumed map holds are skipped, whatever window they fell in
    frames = iter(windows(source, window, counts, int(spec["frame_skip"]), spec["limit"],
                          start=start, max_depth=max_depth))  # fmt: skip
    try:
        while True:
            t0 = time.perf_counter()
            batch = next(frames, None)
            timer["read"] += time.perf_counter() - t0
            if batch is None:
                break
            t0 = time.perf_counter()
            try:
                smap.add(batch["image"], batch["depth"], batch["intrinsics"], batch["pose"])
            except NonFiniteError as err:
                if not str(err).startswith(ENCODER_OUTPUT):
                    raise
                for name in batch["name"]:  # the window is left out, the map unchanged
                    counts.skip(SkippedFrame(name, f"window of {len(batch['name'])} frames: "
                                             f"{err}", "non_finite"))  # fmt: skip
                log.warning("window %s .. %s skipped: %s", batch["name"][0],
                            batch["name"][-1], err)  # fmt: skip
                smap.meta["kept_frames"] = base + batch["first"] + len(batch["name"])
                continue
            except ValueError as err:  # e.g. points beyond the voxel lattice: name the frames
                bound = "null" if max_depth is None else max_depth
                raise ValueError(
                    f"window {batch['name'][0]} .. {batch['name'][-1]}: {err} (depth beyond "
                    f"source.max_depth={bound} is dropped; a pose may be wrong)"
                ) from err
            timer["map"] += time.perf_counter() - t0
            counts.used += len(batch["name"])
            added += 1
            smap.meta["kept_frames"] = base + batch["first"] + len(batch["name"])
            if view is not None:
                t0 = time.perf_counter()
                view.log_window(batch, base + batch["first"])
                if added % max(1, int(cfg.rerun.map_every)) == 0:
                    view.log_map(smap)
                timer["rerun"] += time.perf_counter() - t0
            if save_every and added % save_every == 0:
                t0 = time.perf_counter()
                smap.save(folder)
                timer["save"] += time.perf_counter() - t0
    except MapFullError:
        smap.save(folder)  # the map so far (the window that did not fit is not in it)
        raise
    t0 = time.perf_counter()
    smap.save(folder)
    timer["save"] += time.perf_counter() - t0
    source_record = _source_record(source, counts)
    if not len(smap):
        why = "; ".join(f"{kind}: {reason}" for kind, reason in sorted(counts.reasons.items()))
        why = why or "the source has no candidate frame"
        for line in _source_warnings(source_record):
            log.warning("%s", line)
        record.update(frames=counts.as_dict(), **source_record)
        raise RuntimeError(f"no frame was mapped ({counts.line()}); why, per kind: {why}")
    t0 = time.perf_counter()
    ply = smap.to_ply(out / "map.ply", str(cfg.ply.colour_by), cfg.ply.text,
                      list(cfg.ply.classes) if cfg.ply.classes else None)  # fmt: skip
    timer["ply"] += time.perf_counter() - t0
    if view is not None:
        view.log_map(smap)
        view.close()
    summary = (f"{counts.line()}; unpaired colour messages: "
               f"{getattr(source, 'unpaired_colour', 0)}; map: {len(smap)} voxels, "
               f"{smap.nbytes / 2**20:.1f} MiB, {smap.frames} frames in all")  # fmt: skip
    log.info(summary)  # to the console (stdout) and map.log, once: Hydra's handlers
    for kind, reason in sorted(counts.reasons.items()):
        log.warning("skipped %d %s, e.g. %s", counts.skipped[kind], kind, reason)
    for line in _source_warnings(source_record):
        log.warning("%s", line)
    return record.update(
        status="completed",
        frames=counts.as_dict(),
        **source_record,
        map={
            "folder": str(folder),
            "voxels": len(smap),
            "bytes": smap.nbytes,
            "storage": smap.storage,
            "basis_sha256": smap.basis_sha256,
            "frames": smap.frames,
            "windows": smap.windows,
            "ply": str(ply),
            "rerun": str(rrd) if rrd else None,
        },  # fmt: skip
        seconds={k: round(v, 4) for k, v in sorted(timer.items())},
    )


def _source_record(source: Any, counts: Any) -> dict[str, Any]:
    """What ``results.json`` records of the source beyond the frames: unpaired colour
    messages, messages that could not be deserialised (by topic, with examples), colour images
    left out for their stamps, and the damage that stopped a bag's read (a
    :class:`~resireg.sources.frames.MessageSource`'s; its ``path=`` as ``source.path=``)."""
    from resireg.sources.frames import MessageSource

    out: dict[str, Any] = {"unpaired_colour": getattr(source, "unpaired_colour", 0)}
    if isinstance(source, MessageSource):
        out["corrupt_messages"] = {"by_topic": dict(source.corrupt),
                                   "examples": list(source.corrupt_examples)}  # fmt: skip
        out["colour_stamp_faults"] = {"count": len(source.colour_stamp_faults),
                                      "examples": list(source.colour_stamp_faults[:20])}  # fmt: skip
        damage = source.damage
        out["damage"] = None if damage is None else _under(damage, "source", ("path",))
    if counts.depth_out_of_range:
        out["depth_out_of_range"] = {"pixels": counts.depth_out_of_range,
                                     "frames": counts.depth_out_of_range_frames}  # fmt: skip
    return out


def _source_warnings(record: dict[str, Any]) -> list[str]:
    lines = []
    for topic, n in sorted(record.get("corrupt_messages", {}).get("by_topic", {}).items()):
        example = next(e for e in record["corrupt_messages"]["examples"] if e.startswith(topic))
        lines.append(f"{n} corrupt message(s) on {topic}, e.g. {example}")
    faults = record.get("colour_stamp_faults") or {}
    if faults.get("count"):
        lines.append(f"{faults['count']} colour image(s) left out for their header stamps, "
                     f"e.g. {faults['examples'][0]}")  # fmt: skip
    if record.get("damage"):
        lines.append(str(record["damage"]))
    if record.get("depth_out_of_range"):
        d = record["depth_out_of_range"]
        lines.append(f"{d['pixels']} depth pixels in {d['frames']} frames beyond "
                     "source.max_depth (or negative) taken as no depth")  # fmt: skip
    return lines


def run_map(cfg: DictConfig) -> dict[str, Any]:
    """Map from a composed ``map.yaml`` config; returns the ``results.json`` content."""
    return run_task(cfg, _map, resume_hint="resume=true with the same run folder "
                    "continues from the last save")  # fmt: skip


main = hydra_entry_point("map", run_map)

if __name__ == "__main__":
    main()
