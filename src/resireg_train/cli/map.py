"""``resireg-map``: a language-queryable voxel map from a posed RGB-D recording (Hydra main;
``conf/map.yaml``, docs/design.md section 10.3).

    resireg-map source.kind=rosbag source.path=run.bag model_path=<export> source.world_frame=odom
    resireg-map source.kind=tum source.path=rgbd_dataset_freiburg1_desk source.camera=fr1
    resireg-map source.kind=scannet source.path=/datasets/scannet/scene0011_00 rerun.save=map.rrd

The source (:mod:`resireg_train.data.rosbag`, :mod:`resireg_train.data.tum`,
:func:`resireg_train.data.scannet.scannet_rgbd`) is opened and checked before the encoder loads
(a missing topic is reported in a second, with the bag's topics). Windows of ``window``
consecutive frames go through :meth:`resireg.mapping.SemanticMap.add`; the map is saved every
``save_every`` windows and at the end to ``<output dir>/map`` (``resume=true`` continues it:
the frames it holds are skipped, so a resumed run equals an uninterrupted one), then written as
``map.ply``; ``results.json`` records frames read / used / skipped (by kind, with examples), the
map's voxels and bytes, and seconds per stage.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg_train.cli.task import hydra_entry_point, run_task
from resireg_train.results import update_results
from resireg_train.validation import ConfigError, encoder_kwargs

__all__ = ["SOURCES", "build_source", "make_map", "main"]

log = logging.getLogger(__name__)

#: ``source.kind`` values.
SOURCES = ("rosbag", "tum", "scannet")
_COMMON = ("kind", "path", "tolerance", "max_pose_gap", "frame_skip", "limit")
_KEYS = {
    "rosbag": (*_COMMON, "colour_topic", "depth_topic", "camera_info_topic", "pose_topic",
               "tf_topic", "tf_static_topic", "world_frame", "camera_frame", "depth_scale"),
    "tum": (*_COMMON, "camera", "intrinsics"),
    "scannet": _COMMON,
}  # fmt: skip


def build_source(spec: dict[str, Any], key: str = "source"):
    """The frame source of a ``source`` entry (its kind's keys; the others' keys may stay at
    their defaults); opens it, so a missing file or topic fails here."""
    kind = spec.get("kind")
    if kind not in SOURCES:
        raise ConfigError(f"{key}.kind={kind!r}: expected one of {SOURCES}")
    if spec.get("path") in (None, "", "???"):
        raise ConfigError(f"{key}.path={spec.get('path')!r}: set the recording to map")
    if kind == "rosbag":
        from resireg_train.data.rosbag import BagSource, BagTopics

        topics = BagTopics(colour=spec["colour_topic"], depth=spec["depth_topic"],
                           camera_info=spec["camera_info_topic"], pose=spec["pose_topic"],
                           tf=spec["tf_topic"], tf_static=spec["tf_static_topic"],
                           world_frame=spec["world_frame"], camera_frame=spec["camera_frame"])  # fmt: skip
        return BagSource(spec["path"], topics, float(spec["tolerance"]),
                         float(spec["depth_scale"]), key, float(spec["max_pose_gap"]))  # fmt: skip
    if kind == "tum":
        from resireg_train.data.tum import TumSource

        intr = spec.get("intrinsics")
        return TumSource(spec["path"], float(spec["tolerance"]), str(spec["camera"]),
                         list(intr) if intr is not None else None, key=key,
                         max_pose_gap=float(spec["max_pose_gap"]))  # fmt: skip
    from resireg_train.data.scannet import scannet_rgbd

    folder = Path(str(spec["path"])).expanduser()
    frames = scannet_rgbd(folder, key)  # a generator: it checks the folder at its first frame
    first = next(frames, None)
    return frames if first is None else _chain(first, frames)


def _chain(first, rest):
    yield first
    yield from rest


def make_map(cfg: DictConfig, encoder: Any, prior: Any = None):
    """The :class:`~resireg.mapping.SemanticMap` of the config's map keys (conf/map.yaml)."""
    from resireg.mapping import SemanticMap
    from resireg.specs.variants import PARAM_VARIANTS  # the variant table's, with parameters

    params = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in PARAM_VARIANTS}
    try:
        return SemanticMap(encoder, str(cfg.configuration), float(cfg.voxel_size), params=params,
                           prior=prior, points=str(cfg.points), lattice=str(cfg.lattice),
                           sum_dtype=str(cfg.sum_dtype), max_voxels=cfg.max_voxels,
                           short_side=cfg.short_side)  # fmt: skip
    except ValueError as err:
        raise ConfigError(str(err)) from err


def _device(name: str):
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _identity(cfg: DictConfig) -> dict[str, Any]:
    """What a resumed run must share with the saved map: the source (but ``limit``: a run cut
    short by it resumes without it) and the map's settings."""
    source = OmegaConf.to_container(cfg.source, resolve=True)
    source.pop("limit", None)
    keep = ("configuration", "window", "voxel_size", "points", "lattice", "sum_dtype",
            "short_side")  # fmt: skip
    return {"source": source, **{k: OmegaConf.to_container(cfg, resolve=True)[k] for k in keep}}


def _map(cfg: DictConfig, out: Path) -> dict[str, Any]:
    import torch

    from resireg.mapping import MapFullError, SemanticMap
    from resireg.models import build_encoder
    from resireg_train.data.rgbd import FrameCounts, windows

    window = cfg.window
    if isinstance(window, bool) or not isinstance(window, int) or window < 1:
        raise ConfigError(f"window={window!r}: expected an integer >= 1")
    save_every = cfg.save_every
    if isinstance(save_every, bool) or not isinstance(save_every, int) or save_every < 0:
        raise ConfigError(f"save_every={save_every!r}: expected an integer >= 0")
    spec = OmegaConf.to_container(cfg.source, resolve=True)
    unknown = set(spec) - {k for keys in _KEYS.values() for k in keys}
    if unknown:
        raise ConfigError(f"source: unknown keys {sorted(unknown)}")
    params = {"source": spec, "identity": _identity(cfg)}
    update_results(out, params=params)
    timer: dict[str, float] = defaultdict(float)
    start = time.perf_counter()
    try:  # a wrong path, a missing topic: the message says it all (no traceback)
        source = build_source(spec)
    except (FileNotFoundError, ValueError) as err:
        raise ConfigError(str(err)) from err
    timer["open_source"] += time.perf_counter() - start
    torch.manual_seed(int(cfg.seed))
    encoder = build_encoder(**encoder_kwargs(OmegaConf.to_container(cfg.encoder, resolve=True)),
                            device=_device(str(cfg.device)), config_key="encoder")  # fmt: skip
    prior = None
    from resireg.variant_names import takes_prior

    if takes_prior(str(cfg.configuration)):
        from resireg.priors import build_prior

        prior = build_prior(OmegaConf.to_container(cfg.prior, resolve=True) if cfg.get("prior")
                            else {}, device=encoder.device, key="prior")  # fmt: skip
    folder = out / "map"
    if cfg.resume and (folder / "map.json").is_file():
        smap = SemanticMap.load(folder, encoder, prior, max_voxels=cfg.max_voxels)
        if smap.meta.get("identity") != params["identity"]:
            raise ConfigError(
                f"resume=true: {folder} was made with {smap.meta.get('identity')}, this run "
                f"has {params['identity']}; start a new run folder instead"
            )
        log.info("resuming %s: %d frames, %d voxels", folder, smap.frames, len(smap))
    else:
        if (folder / "map.json").is_file():
            raise ConfigError(f"{folder} holds a map: resume=true continues it, or use a new "
                              "run folder")  # fmt: skip
        smap = make_map(cfg, encoder, prior)
        smap.meta = {"identity": params["identity"], "kept_frames": 0}
    done = int(smap.meta.get("kept_frames", 0))
    view = None
    if cfg.rerun.save or cfg.rerun.spawn:
        from resireg_train.mapping.viewer import RerunView

        view = RerunView(cfg.rerun.save, bool(cfg.rerun.spawn), cfg.rerun.query)
    counts = FrameCounts()
    added = 0
    frames = iter(windows(source, window, counts, int(spec["frame_skip"]), spec["limit"]))
    try:
        while True:
            t0 = time.perf_counter()
            batch = next(frames, None)
            timer["read"] += time.perf_counter() - t0
            if batch is None:
                break
            if batch["first"] < done:  # held by the resumed map
                continue
            t0 = time.perf_counter()
            smap.add(batch["image"], batch["depth"], batch["intrinsics"], batch["pose"])
            timer["map"] += time.perf_counter() - t0
            counts.used += len(batch["name"])
            added += 1
            smap.meta["kept_frames"] = batch["first"] + len(batch["name"])
            if view is not None:
                t0 = time.perf_counter()
                view.log_window(batch, batch["first"])
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
    if not len(smap):
        raise RuntimeError(f"no frame was mapped ({counts.line()}); results.json lists why")
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
    for s in counts.examples[:5]:
        log.warning("skipped %s (%s): %s", s.name, s.kind, s.reason)
    return update_results(
        out,
        status="completed",
        frames=counts.as_dict(),
        unpaired_colour=getattr(source, "unpaired_colour", 0),
        map={
            "folder": str(folder),
            "voxels": len(smap),
            "bytes": smap.nbytes,
            "frames": smap.frames,
            "windows": smap.windows,
            "ply": str(ply),
            "rerun": str(cfg.rerun.save) if cfg.rerun.save else None,
        },  # fmt: skip
        seconds={k: round(v, 4) for k, v in sorted(timer.items())},
    )


def run_map(cfg: DictConfig) -> dict[str, Any]:
    """Map from a composed ``map.yaml`` config; returns the ``results.json`` content."""
    return run_task(cfg, _map, resume_hint="resume=true with the same run folder continues "
                    "from the last save")  # fmt: skip


main = hydra_entry_point("map", run_map)

if __name__ == "__main__":
    main()
