"""``resireg-map``'s job: a language-queryable voxel map from a posed RGB-D recording (its door:
:mod:`resireg_train.cli.map`; ``conf/map.yaml``, docs/maps.md#robot-maps-semanticmap).

The steps, in order (:func:`map_job`): the config checked (:mod:`resireg_train.checks.map`);
the source (``source=<kind>``: ``conf/source/<kind>.yaml``, a kind of the table
:data:`resireg.specs.sources.SOURCE_SPECS`, read by :mod:`resireg.sources`) checked and opened
before the encoder loads (every missing topic is reported in a second, with the bag's topics);
the encoder and, for a variant that takes one, the prior; the map opened
(:func:`resireg.mapping.opening.open_map`, the live node's rule too): a fresh map in
``<output dir>/map``, or with ``resume=true`` the saved one continued from the last frame it
holds (a live source, ``source=ros2``: with the frames it receives now), or refused naming the
fields that differ (source, settings, ReSiReg parameters, encoder entry, a digest of the
encoder's weights); windows of ``window`` consecutive frames fused by
:meth:`resireg.mapping.SemanticMap.add` (a window whose encoder output is not finite is skipped
and counted), the map saved every ``save_every`` windows and at the end; then ``map.ply``.
``results.json`` records frames read / used / skipped (by kind, the first reason of each,
examples), corrupt messages, out-of-range depth, the map's voxels and bytes, and seconds per
stage; a run that maps nothing fails with the reason per kind.

Imported by :mod:`resireg_train.cli.map`.
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
from resireg.specs.sources import SOURCE_SPECS
from resireg_train.checks.map import check_map_config, check_source
from resireg_train.config.errors import config_path, encoder_arguments
from resireg_train.record.run_record import RunRecord

__all__ = ["SOURCES", "build_source", "make_map", "map_job"]

log = logging.getLogger(__name__)

#: ``source.kind`` values: the built-in kinds of the source table.
SOURCES = SOURCE_SPECS.names()


def build_source(spec: dict[str, Any], key: str = "source"):
    """The frame source of a ``source`` block (``conf/source/<kind>.yaml``): its keys and
    values checked against its kind's entry of :data:`~resireg.specs.sources.SOURCE_SPECS`
    (:func:`~resireg_train.checks.map.check_source`), then the entry's reader called with the
    block's keys; it opens the recording, so a missing file or topic fails here. Every refusal
    is a :class:`ConfigError` naming the config path: the library's own (``path='x': ...``) as
    ``source.path='x': ...``."""
    check_source(spec, key)
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
    """The empty :class:`~resireg.mapping.SemanticMap` of the config's map keys
    (conf/map.yaml); ``encoder=None``: a map for its settings only (its identity)."""
    from resireg.mapping import SemanticMap
    from resireg.mapping.opening import local_path
    from resireg.specs.variants import PARAM_VARIANTS  # the variant table's, with parameters

    params = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in PARAM_VARIANTS}
    storage = str(cfg.get("storage", "exact"))
    compact = None
    if storage == "compact":  # the basis path resolved (recorded absolute)
        compact = OmegaConf.to_container(cfg.compact, resolve=True)
        compact["basis"] = local_path(compact.get("basis"))
    try:
        return SemanticMap(encoder, str(cfg.variant), float(cfg.voxel_size), params=params,
                           prior=prior, points=str(cfg.points), lattice=str(cfg.lattice),
                           sum_dtype=str(cfg.sum_dtype), max_voxels=cfg.max_voxels,
                           short_side=cfg.short_side, storage=storage, compact=compact)  # fmt: skip
    except (ValueError, ResiregError) as err:
        raise ConfigError(str(err)) from err


def _identity(cfg: DictConfig, smap: Any, weights: str | None = None) -> dict[str, Any]:
    """The config's blocks of the map's identity (:func:`resireg.mapping.opening.map_identity`)."""
    from resireg.mapping.opening import map_identity

    every = OmegaConf.to_container(cfg, resolve=True)
    return map_identity(smap, encoder=every["encoder"], source=every["source"],
                        window=every["window"], prior=every.get("prior"), weights=weights)  # fmt: skip


def _viewer_file(cfg: DictConfig, out: Path) -> Path | None:
    """The Rerun recording to save (``viewer.save``): under the run folder unless absolute;
    recorded absolute."""
    if not cfg.viewer.save:
        return None
    rrd = Path(str(cfg.viewer.save)).expanduser()
    return (rrd if rrd.is_absolute() else out / rrd).resolve()


def _encoder_and_prior(cfg: DictConfig) -> tuple[Any, Any]:
    """The encoder of the ``encoder`` entry on ``device`` (seeded by ``seed``) and, for a
    variant that takes one, the prior of the ``prior`` block; errors name their config path."""
    import torch

    from resireg.models import build_encoder
    from resireg.models.factory import resolve_device
    from resireg.specs.variants import takes_prior

    torch.manual_seed(int(cfg.seed))
    entry = encoder_kwargs(OmegaConf.to_container(cfg.encoder, resolve=True))
    with config_path("encoder", encoder_arguments(entry)):
        encoder = build_encoder(**entry, device=resolve_device(str(cfg.device)))
    if not takes_prior(str(cfg.variant)):
        return encoder, None
    from resireg.priors import build_prior

    prior_spec = OmegaConf.to_container(cfg.prior, resolve=True) if cfg.get("prior") else {}
    with config_path("prior", {"spec": "prior"}):
        return encoder, build_prior(prior_spec, device=encoder.device)


def map_job(cfg: DictConfig, record: RunRecord) -> dict[str, Any]:
    """Map from a composed ``map.yaml`` config into ``record``'s folder (module docstring);
    returns the ``results.json`` content."""
    from resireg.mapping.opening import open_map
    from resireg.models.factory import weights_fingerprint
    from resireg.sources.frames import FrameCounts

    out = record.folder
    check_map_config(cfg)
    spec = OmegaConf.to_container(cfg.source, resolve=True)
    check_source(spec)  # before anything is written
    rrd = _viewer_file(cfg, out)
    params = {"source": spec, "identity": _identity(cfg, make_map(cfg, None))}
    record.update(params=params)
    timer: dict[str, float] = defaultdict(float)
    start = time.perf_counter()
    source = build_source(spec)  # a wrong path, a missing topic: one line, no traceback
    timer["open_source"] += time.perf_counter() - start
    encoder, prior = _encoder_and_prior(cfg)
    fresh = make_map(cfg, encoder, prior)
    t0 = time.perf_counter()
    identity = _identity(cfg, fresh, weights_fingerprint(encoder))
    timer["weights_digest"] += time.perf_counter() - t0
    record.update(params={**params, "identity": identity})
    smap, folder, resumed = open_map(out / "map", fresh, identity, resume=bool(cfg.resume),
                                     encoder=encoder, prior=prior)  # fmt: skip
    if resumed:
        log.info("resuming %s: %d frames, %d voxels", folder, smap.frames, len(smap))
    view = None
    if rrd is not None or cfg.viewer.spawn:
        from resireg.mapping.viewer import RerunView

        view = RerunView(str(rrd) if rrd else None, bool(cfg.viewer.spawn), cfg.viewer.query)
    counts = FrameCounts()
    _fuse(cfg, spec, source, smap, folder, view, counts, timer)
    return _finish(cfg, record, source, smap, folder, view, rrd, counts, timer)


def _fuse(cfg: DictConfig, spec: dict[str, Any], source: Any, smap: Any, folder: Path,
          view: Any, counts: Any, timer: dict[str, float]) -> None:  # fmt: skip
    """Every window of the source fused into ``smap`` (saved every ``save_every`` windows and
    at the end, also when the map is full); the frames a resumed map holds are not read again."""
    from resireg.mapping import MapFullError
    from resireg.mapping.semantic_map import ENCODER_OUTPUT
    from resireg.method.checks import NonFiniteError
    from resireg.sources.frames import SkippedFrame, windows

    window, save_every, max_depth = cfg.window, cfg.save_every, spec["max_depth"]
    done = int(smap.meta.get("kept_frames", 0))
    # A recording is read again from its start, so the frames a resumed map holds are skipped;
    # a live stream (a source whose ``live`` is true: ros2) goes on from now, every frame new.
    base, start = (done, 0) if getattr(source, "live", False) else (0, done)
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
                if added % max(1, int(cfg.viewer.map_every)) == 0:
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


def _finish(cfg: DictConfig, record: RunRecord, source: Any, smap: Any, folder: Path,
            view: Any, rrd: Path | None, counts: Any, timer: dict[str, float]) -> dict[str, Any]:  # fmt: skip
    """``map.ply``, the summary (console, log) and the record of a fused map; a map of no
    frame fails with the reason per kind."""
    out = record.folder
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


