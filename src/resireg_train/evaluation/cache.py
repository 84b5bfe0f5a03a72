"""An on-disk cache of encoder outputs, for sweeps whose jobs must run in separate processes.

One job per ReSiReg setting is sometimes unavoidable (a SLURM array over settings, a sweep
of ``lite.alpha``): every job would re-run the backbone on the whole dataset although
nothing upstream of ReSiReg changed. With ``feature_cache=<dir>`` the first job stores each
image's ``intermediates`` and ``language`` tokens, later jobs read them instead of encoding
(docs/runs.md#run-records-and-faults).

**Key.** A cache folder is ``<dir>/<digest>``, the digest of everything the outputs depend
on: the encoder's config entry, a fingerprint of its weights (a hash of every parameter and
buffer, so re-trained or re-downloaded weights never read stale features), the dataset's
config entry (source, split, limit) and its resolution (``short_side``, patch size), the
evaluation precision and, for configurations on other blocks (``@layer:<block>``), the blocks
whose intermediates are stored beside the encoder's own. Change any of them and the jobs use
(and fill) a new folder; the old one is never read again (delete it to reclaim the disk).
``key.json`` in the folder says in words what it holds. Each stored image also records its
file name (``describe``): an entry whose file differs from the dataset's (a folder whose
images were added or renamed) is a miss and is encoded again.

**Layout.** ``shard-<writer>-<n>.safetensors`` holds the tensors of up to ``shard_images``
images (``<index>/intermediates``, ``<index>/language``, ``<index>/layer/<block>`` for each
block of the key, in the dtype the encoder produced) and ``shard-<writer>-<n>.json`` lists
them, with the shard's size and BLAKE2b digest. Both are written atomically (temporary file,
then rename; the listing after its shard), so concurrent jobs filling the same folder never
see a partial shard and never overwrite each other's files. A job interrupted mid-dataset
leaves its complete shards behind, and the next job encodes only what is missing.

**Integrity.** Atomic writes guard against crashes, not against what happens to a file
later (a bad disk block, a copy cut short, a user's tool). Every shard is therefore checked
against its listing's size and digest when a job first reads from it, before any tensor of
it is used: a shard that differs (or that safetensors cannot parse, or that lacks a listed
tensor) is *damaged*. It is named in a warning and in ``summary()["damaged"]``
(``results.json``), set aside as ``<shard>.damaged`` (its listing removed, so no later job
reads it), and its images count as missing: they are encoded again, so the scores equal
those of a clean cache.

Why not ``datasets``' own cache: its Arrow rows would have to hold ``[D, h, w]`` tensors of
differing grid sizes as nested lists, and its fingerprint is of the processing function, not
of model weights; safetensors shards read back zero-copy as torch tensors.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open
from safetensors.torch import save
from torch import Tensor

from resireg.integrity import atomic_write
from resireg.models import DenseOutput, factory

__all__ = ["FeatureCache", "file_digest"]

log = logging.getLogger(__name__)

#: 2: listings carry the shard's size and digest (folders of format 1 are never read).
_FORMAT = 2
_FIELDS = ("intermediates", "language")
_CHUNK = 1 << 22  # bytes hashed per read: 4 MiB


def file_digest(path: str | os.PathLike) -> str:
    """BLAKE2b (16-byte) hex digest of a file's bytes, read in chunks (a shard can be
    hundreds of MB; ``hashlib.file_digest`` needs Python 3.11)."""
    digest = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def _digest(key: Mapping[str, Any]) -> str:
    text = json.dumps(key, sort_keys=True, default=str)
    return hashlib.blake2b(text.encode(), digest_size=12).hexdigest()


class FeatureCache:
    """Encoder outputs of one (encoder, weights, dataset, resolution, precision), on disk.

    Args:
        root: the cache directory (``feature_cache``); the folder for this key is created in it.
        key: what the outputs depend on (see :meth:`key_for`); its digest names the folder.
        describe: ``index -> file name`` of the dataset, checked on every read.
        shard_images: images per shard file.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        key: Mapping[str, Any],
        describe: Callable[[int], str],
        shard_images: int = 64,
    ) -> None:
        if shard_images < 1:
            raise ValueError(f"shard_images must be >= 1, got {shard_images}")
        self.key = dict(key)
        self.folder = Path(root).expanduser() / _digest(self.key)
        self.folder.mkdir(parents=True, exist_ok=True)
        key_file = self.folder / "key.json"
        if not key_file.exists():
            atomic_write(key_file, json.dumps(self.key, indent=2, default=str), "cache key")
        self.describe = describe
        self.layers: tuple[int, ...] = tuple(self.key.get("layers") or ())
        self.shard_images = shard_images
        self._writer = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self._shards_written = 0
        self._pending: dict[int, dict[str, Tensor]] = {}
        self._entries: dict[int, tuple[str, str]] = {}  # index -> (shard file, file name)
        self._expected: dict[str, tuple[int, str]] = {}  # shard -> (size, digest) as listed
        self._handles: dict[str, Any] = {}  # shards verified and opened
        self._bad: set[str] = set()  # shards found damaged (never read again by this job)
        self.damaged: list[dict[str, str]] = []  # [{"file", "reason"}] found by this job
        self.hits = 0
        self.misses = 0
        self.bytes_written = 0
        self.refresh()

    @staticmethod
    def key_for(
        encoder: torch.nn.Module,
        encoder_spec: Mapping[str, Any],
        dataset_spec: Mapping[str, Any],
        patch_size: int,
        precision: str,
        layers: Sequence[int] = (),
    ) -> dict[str, Any]:
        """The cache key of ``encoder`` (built from ``encoder_spec``) on a dataset; ``layers``:
        the encoder blocks whose intermediates are stored too (``encode_layers``; the key of a
        cache without them is unchanged)."""
        key = {
            "format": _FORMAT,
            "encoder": dict(encoder_spec),
            "weights": factory.weights_fingerprint(encoder),
            "dataset": dict(dataset_spec),
            "resolution": {"short_side": dataset_spec.get("short_side"), "patch": patch_size},
            "precision": str(precision),
        }
        if layers:
            key["layers"] = sorted({int(b) for b in layers})
        return key

    def _fields(self) -> tuple[str, ...]:
        return _FIELDS + tuple(f"layer/{b}" for b in self.layers)

    def refresh(self) -> None:
        """Read the listings of every complete shard in the folder (other jobs' included)."""
        for listing in sorted(self.folder.glob("shard-*.json")):
            shard = listing.with_suffix(".safetensors").name
            if shard in self._bad:
                continue
            try:
                content = json.loads(listing.read_text())
                files, size, digest = content["images"], int(content["bytes"]), content["blake2b"]
            except (OSError, ValueError, KeyError, TypeError):
                continue  # unreadable listing: its images count as missing
            self._expected.setdefault(shard, (size, str(digest)))
            for index, name in files.items():
                self._entries.setdefault(int(index), (shard, name))

    def __len__(self) -> int:
        return len(self._entries)

    def _open(self, shard: str) -> Any:
        """The shard's safetensors handle, after checking its size and digest against its
        listing (once per shard and job); ``None`` if it is damaged (see :meth:`_damaged`)."""
        handle = self._handles.get(shard)
        if handle is not None:
            return handle
        path = self.folder / shard
        size, digest = self._expected[shard]
        try:
            actual = path.stat().st_size
            if actual != size:
                return self._damaged(shard, f"{actual} bytes, its listing says {size}")
            if file_digest(path) != digest:
                return self._damaged(shard, "content differs from its listing's digest")
            handle = safe_open(path, framework="pt")
        except Exception as err:  # noqa: BLE001 - I/O and safetensors parse errors alike
            return self._damaged(shard, f"unreadable ({type(err).__name__}: {err})")
        self._handles[shard] = handle
        return handle

    def _damaged(self, shard: str, reason: str) -> None:
        """Record a damaged shard, warn naming it, set it aside (``<shard>.damaged``, listing
        removed) and forget its images, which are then encoded again; other shards listing
        the same images (a concurrent job's) take their place."""
        path = self.folder / shard
        self._bad.add(shard)
        self.damaged.append({"file": str(path), "reason": reason})
        log.warning("feature cache: damaged shard %s (%s); set aside as %s.damaged, its images "
                    "are encoded again", path, reason, shard)  # fmt: skip
        try:  # set aside, for a look; another job may have done so already
            path.with_suffix(".json").unlink(missing_ok=True)
            path.replace(path.with_name(f"{shard}.damaged"))
        except OSError:
            pass
        self._entries = {i: e for i, e in self._entries.items() if e[0] != shard}
        self._expected.pop(shard, None)
        self.refresh()
        return None

    def _tensors(self, index: int) -> tuple[Tensor, ...] | None:
        entry = self._entries.get(index)
        if entry is None or entry[1] != self.describe(index):
            return None
        shard = entry[0]
        handle = self._open(shard)
        if handle is None:
            return None
        try:
            return tuple(handle.get_tensor(f"{index}/{f}") for f in self._fields())
        except Exception as err:  # noqa: BLE001 - a listed tensor the shard does not hold
            self._handles.pop(shard, None)
            return self._damaged(shard, f"unreadable ({type(err).__name__}: {err})")

    def get(self, indices: Sequence[int], device: torch.device | str = "cpu") -> DenseOutput | None:
        """The stored outputs of the images ``indices`` stacked as one batch on ``device``
        (``embedding`` is not stored: ``None``; ``layers`` when the key has blocks), or
        ``None`` if any is missing."""
        found = [self._tensors(i) for i in indices]
        if any(f is None for f in found):
            self.misses += 1
            return None
        self.hits += 1
        inter, lang, *blocks = (
            torch.stack([f[k] for f in found]).to(device)  # type: ignore[index]
            for k in range(len(self._fields()))
        )
        layers = dict(zip(self.layers, blocks, strict=True)) if self.layers else None
        return DenseOutput(inter, lang, None, layers)

    def put(self, indices: Iterable[int], out: DenseOutput) -> None:
        """Store one encoded batch (image ``i`` of ``indices`` is row ``i`` of ``out``); its
        ``layers`` must hold exactly the key's blocks."""
        if self.layers and sorted(out.layers or {}) != list(self.layers):
            raise ValueError(
                f"the feature cache {self.folder} stores blocks {list(self.layers)}, the batch "
                f"has {sorted(out.layers or {})}"
            )
        tensors = {f: getattr(out, f) for f in _FIELDS}
        tensors.update({f"layer/{b}": out.layers[b] for b in self.layers})  # type: ignore[index]
        for row, index in enumerate(indices):
            if index in self._entries or index in self._pending:
                continue
            self._pending[index] = {
                f: t[row].detach().to("cpu", copy=True).contiguous() for f, t in tensors.items()
            }
        if len(self._pending) >= self.shard_images:
            self.flush()

    def flush(self) -> None:
        """Write the pending images as one shard (and its listing)."""
        if not self._pending:
            return
        stem = f"shard-{self._writer}-{self._shards_written:05d}"
        tensors = {f"{i}/{f}": t for i, fields in self._pending.items() for f, t in fields.items()}
        data = save(tensors)
        atomic_write(self.folder / f"{stem}.safetensors", data, "feature cache shard")
        files = {str(i): self.describe(i) for i in self._pending}
        digest = hashlib.blake2b(data, digest_size=16).hexdigest()
        listing = {"images": files, "bytes": len(data), "blake2b": digest}
        atomic_write(self.folder / f"{stem}.json", json.dumps(listing), "cache listing")
        self._expected[f"{stem}.safetensors"] = (len(data), digest)
        self.bytes_written += len(data)
        for index in self._pending:
            self._entries[index] = (f"{stem}.safetensors", files[str(index)])
        self._pending.clear()
        self._shards_written += 1

    def disk_bytes(self) -> int:
        """Bytes of this key's shards on disk."""
        return sum(p.stat().st_size for p in self.folder.glob("shard-*.safetensors"))

    def summary(self) -> dict[str, Any]:
        return {
            "folder": str(self.folder),
            "images": len(self),
            "hits": self.hits,
            "misses": self.misses,
            "bytes_written": self.bytes_written,
            "disk_bytes": self.disk_bytes(),
            "damaged_shards": len(self.damaged),
            "damaged": list(self.damaged),
        }
