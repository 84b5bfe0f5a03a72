"""Caption sources on Hugging Face ``datasets``: each configured source opened as one
``{image, caption}`` stream, and the sources mixed into one (docs/training.md#caption-data; the
stream's batches are :mod:`resireg_train.data.captions`).

1. Each configured source is opened in streaming mode (a hub id, a local folder of
   parquet / image files / webdataset shards, a ``datasets`` builder name with
   ``data_files``, or the generated ``synthetic`` source). Image decoding is switched
   off (``IterableDataset.decode(False)``), and one ``map`` reduces each example to
   ``{"image": bytes, "caption": [str, ...]}`` through the source's column paths
   (``"texts.0.assistant"`` walks lists and dicts).
2. The sources are mixed by ``datasets.interleave_datasets`` with per-source
   probabilities and shuffled (shard order + a buffer).
"""

from __future__ import annotations

import io
import logging
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from datasets import Features, IterableDataset, List, Value, interleave_datasets, load_dataset
from datasets import Image as HFImage

from resireg.models.hub import require_online
from resireg_train.data.specs import CAPTION_SOURCE_KEYS, require_keys
from resireg_train.data.synthetic import SyntheticScenes

__all__ = ["CAPTION_FEATURES", "mix_caption_sources", "open_caption_source"]

log = logging.getLogger(__name__)


#: The one schema every source is mapped to before mixing.
CAPTION_FEATURES = Features({"image": Value("binary"), "caption": List(Value("string"))})
_LOCAL_BUILDERS = {"parquet", "imagefolder", "webdataset", "json", "csv", "arrow"}


def _pluck(example: Mapping[str, Any], path: str) -> Any:
    """Walk ``"texts.0.assistant"`` through nested dicts and lists."""
    value: Any = example
    for part in path.split("."):
        value = value[int(part)] if isinstance(value, (list, tuple)) else value[part]
    return value


def _image_bytes(value: Any) -> bytes | None:
    """Undecoded image value (``{"bytes", "path"}``, raw bytes or a local path) -> bytes."""
    if isinstance(value, dict):
        if value.get("bytes"):
            return value["bytes"]
        value = value.get("path")
    if isinstance(value, (bytes, bytearray)):
        return bytes(value)
    if isinstance(value, str) and os.path.isfile(value):
        return Path(value).read_bytes()
    return None


def _captions(value: Any) -> list[str]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, (list, tuple)):
        return []
    return [c.strip() for c in value if isinstance(c, str) and c.strip()]


def _to_schema(image_path: str, caption_path: str) -> Callable[[dict], dict]:
    def convert(example: dict) -> dict:
        try:
            image = _image_bytes(_pluck(example, image_path))
        except (KeyError, IndexError, TypeError):
            image = None
        try:
            captions = _captions(_pluck(example, caption_path))
        except (KeyError, IndexError, TypeError):
            captions = []
        return {"image": image, "caption": captions}

    return convert


def _synthetic_examples(shards: list[tuple[int, int]], size: int, image_size, seed, noise):
    scenes = SyntheticScenes(size=size, image_size=tuple(image_size), seed=seed, noise=noise)
    for start, step in shards:
        for i in range(start, size, step):
            scene = scenes[i]
            buf = io.BytesIO()
            scene["image"].save(buf, format="PNG")
            yield {"image": {"bytes": buf.getvalue(), "path": None}, "caption": scene["caption"]}


def _is_local(path: str) -> bool:
    return path in _LOCAL_BUILDERS or os.path.exists(path)


def open_caption_source(name: str, spec: Mapping[str, Any]) -> IterableDataset:
    """Open one caption source (streaming) mapped to ``{"image": bytes, "caption": [str]}``.

    Args:
        name: the source's name (``data.sources.<name>``; used in error messages).
        spec: the keys of :data:`resireg_train.data.specs.CAPTION_SOURCE_KEYS`, each required
            one present (``conf/data/`` holds them): ``path`` (hub id, local folder, builder
            name such as ``parquet`` / ``webdataset`` / ``imagefolder``, or ``synthetic``),
            ``split``, column paths ``image`` and ``caption``, ``probability`` (its weight in
            the mix, :func:`mix_caption_sources`), optional ``name``, ``data_files``,
            ``data_dir``, ``revision``. Synthetic: ``size``, ``image_size``, ``noise``,
            ``seed``, ``shards``, ``probability`` (its columns are ``image`` and ``caption``).
    """
    key = f"data.sources.{name}"
    kind = "synthetic" if spec.get("path") == "synthetic" else "hub"
    allowed = {*CAPTION_SOURCE_KEYS[kind]["required"], *CAPTION_SOURCE_KEYS[kind]["optional"]}
    unknown = set(spec) - allowed
    if unknown:
        raise ValueError(f"{key}: unknown keys {sorted(unknown)} (allowed: {sorted(allowed)})")
    if "path" not in spec:
        raise ValueError(f"{key}.path is required (hub id, local folder or 'synthetic')")
    path = str(spec["path"])
    if path == "synthetic":
        require_keys(spec, CAPTION_SOURCE_KEYS[kind]["required"], key, "conf/data/synthetic.yaml")
        size, n_shards = int(spec["size"]), int(spec["shards"])
        ds = IterableDataset.from_generator(
            _synthetic_examples,
            features=Features({"image": HFImage(), "caption": Value("string")}),
            gen_kwargs={
                "shards": [(s, n_shards) for s in range(min(n_shards, size))],
                "size": size,
                "image_size": tuple(spec["image_size"]),
                "seed": int(spec["seed"]),
                "noise": float(spec["noise"]),
            },
        )
        image_col, caption_col = "image", "caption"
    else:
        if not _is_local(path):
            if path.startswith(("/", ".", "~")):
                raise FileNotFoundError(f"{key}.path={path!r} does not exist")
            _require_hub_dataset(key, path)
        require_keys(spec, CAPTION_SOURCE_KEYS[kind]["required"], key, "conf/data/")
        kwargs = {k: spec[k] for k in CAPTION_SOURCE_KEYS[kind]["optional"] if spec.get(k)}
        if _is_local(path):
            kwargs = _without_empty_shards(key, path, kwargs)
        ds = load_dataset(path, split=spec["split"], streaming=True, **kwargs)
        image_col, caption_col = spec["image"], spec["caption"]
    ds = ds.decode(False)
    columns = ds.column_names
    if columns is not None:
        for role, col in (("image", image_col), ("caption", caption_col)):
            if col.split(".")[0] not in columns:
                raise ValueError(f"{key}.{role}={col!r}: no such column; columns are {columns}")
    return ds.map(
        _to_schema(image_col, caption_col), remove_columns=columns, features=CAPTION_FEATURES
    )


#: Files that hold many examples each (a 0-byte one is an empty shard, not an empty image).
_SHARD_SUFFIXES = (".tar", ".tgz", ".tar.gz", ".parquet", ".arrow", ".jsonl", ".json", ".csv")


def _without_empty_shards(key: str, path: str, kwargs: dict[str, Any]) -> dict[str, Any]:
    """``load_dataset``'s keyword arguments with every 0-byte local shard left out of its data
    files (``datasets`` would fail on it in the middle of an epoch: ``tarfile.ReadError: empty
    file``); each one left out is counted in one warning naming the files. The arguments are
    returned unchanged when no shard is empty."""
    from datasets.data_files import DataFilesDict, get_data_patterns

    base = path if os.path.isdir(path) else None
    files = kwargs.get("data_files")
    if files is None:
        if base is None:
            return kwargs
        patterns = get_data_patterns(base)
    else:
        patterns = files if isinstance(files, Mapping) else {"train": files}
        patterns = {k: [v] if isinstance(v, str) else list(v) for k, v in patterns.items()}
    try:
        resolved = DataFilesDict.from_patterns(patterns, base_path=base or os.getcwd())
    except FileNotFoundError:
        return kwargs  # load_dataset reports the pattern that matches nothing
    empty = sorted({
        f for split in resolved.values() for f in split
        if str(f).endswith(_SHARD_SUFFIXES) and os.path.isfile(f) and os.path.getsize(f) == 0
    })  # fmt: skip
    if not empty:
        return kwargs
    log.warning(
        "%s: skipped %d empty (0-byte) shard(s): %s",
        key, len(empty), ", ".join(os.path.basename(f) for f in empty),
    )  # fmt: skip
    kept = {split: [f for f in fs if f not in empty] for split, fs in resolved.items()}
    if files is not None and not isinstance(files, Mapping):
        return {**kwargs, "data_files": kept["train"]}
    return {**kwargs, "data_files": kept}


def _require_hub_dataset(key: str, repo_id: str) -> None:
    """Fail at once (not after a minute of retries) when a hub dataset cannot be streamed."""
    require_online(
        f"the hub dataset {repo_id!r} ({key}.path)",
        "huggingface.co",
        f"Download it elsewhere (e.g. `datasets` save_to_disk / parquet, or img2dataset to "
        f"webdataset shards) and set {key}.path to the local folder.",
    )


def mix_caption_sources(
    sources: Mapping[str, Mapping[str, Any]], seed: int = 0, shuffle_buffer: int = 1000
) -> IterableDataset:
    """Open every source, interleave them with their ``probability`` (normalised; each source
    holds one, ``conf/data/`` files are the defaults), shuffle."""
    if not sources:
        raise ValueError("data.sources is empty: configure at least one caption source")
    names = list(sources)
    for n in names:
        require_keys(sources[n], ("probability",), f"data.sources.{n}", "conf/data/")
    weights = np.array([float(sources[n]["probability"]) for n in names])
    bad = [
        f"data.sources.{n}.probability={w}" for n, w in zip(names, weights, strict=True) if w <= 0
    ]
    if bad:
        raise ValueError(f"source probabilities must be > 0: {', '.join(bad)}")
    streams = [open_caption_source(n, sources[n]) for n in names]
    if len(streams) == 1:
        mixed = streams[0]
    else:
        mixed = interleave_datasets(
            streams,
            probabilities=(weights / weights.sum()).tolist(),
            seed=seed,
            stopping_strategy="all_exhausted",
        )
    return mixed.shuffle(seed=seed, buffer_size=shuffle_buffer) if shuffle_buffer > 1 else mixed
