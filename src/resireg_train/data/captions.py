"""Caption data on Hugging Face ``datasets``: sources -> one ``{image, caption}`` stream -> batches.

Pipeline (docs/training.md#caption-data):

1. Each configured source is opened in streaming mode and reduced to
   ``{"image": bytes, "caption": [str, ...]}`` (:mod:`resireg_train.data.caption_sources`).
2. The sources are mixed by ``datasets.interleave_datasets`` with per-source
   probabilities, shuffled (shard order + a buffer; the same module), and split across DDP
   ranks with ``datasets.distributed.split_dataset_by_node``; ``DataLoader`` workers split each
   rank's shards further (``datasets`` does that itself).
3. :class:`CaptionStream` decodes, skips and counts undecodable or tiny images, picks one
   caption at random, resizes the shorter side to ``crop_size``, takes a random
   ``crop_size`` square and normalises. Every epoch yields exactly ``steps_per_epoch``
   batches; the stream restarts (reshuffled) whenever it runs out.

Determinism: epoch ``e`` of rank ``r`` sees the stream reshuffled with ``seed + e`` and
draws crops and captions from a generator seeded by ``(seed, e, r, worker)``, so an
epoch's batches depend only on the seed and the epoch: a run resumed from the checkpoint
of epoch ``e`` trains on the same batches as the uninterrupted run.
"""

from __future__ import annotations

import io
import logging
import math
import os
import warnings
from collections.abc import Callable, Iterator, Mapping
from itertools import count
from typing import Any

import lightning as L
import numpy as np
import torch
from datasets import IterableDataset
from datasets.distributed import split_dataset_by_node
from PIL import Image
from timm.data import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD
from torch.utils.data import DataLoader, default_collate, get_worker_info
from torchvision.transforms.v2 import functional as TF

from resireg.models.images import WIDE_GREY, pil_to_tensor
from resireg.sources.frames import DECODE_ERRORS
from resireg_train.data.caption_sources import mix_caption_sources

__all__ = ["CaptionDataModule", "CaptionStream", "available_cores", "loader_workers"]

log = logging.getLogger(__name__)


_EPOCH_PASSES = 10_000  # reshuffle seed of pass p in epoch e: e * _EPOCH_PASSES + p


# ----------------------------------------------------------------------- torch stream
class CaptionStream(torch.utils.data.IterableDataset):
    """One rank's training samples: exactly ``steps_per_epoch`` batches per epoch.

    Each sample is ``{"image": [3, S, S] uint8, "caption": str, "skipped_invalid": int,
    "skipped_small": int}``, and :meth:`collate` makes batches of them with the images
    normalised (``[B, 3, S, S]`` float, what the loader yields); the two counters hold how many examples were dropped
    (undecodable image / no caption, or shorter side < ``min_image_size``) just before it,
    so summing them over batches counts every skip exactly once.

    Args:
        stream: the mixed ``datasets`` stream of this rank.
        steps_per_epoch: batches per epoch.
        batch_size: samples per batch (this rank).
        crop_size: side of the square random crop.
        min_image_size: smaller images (shorter side) are skipped.
        mean, std: normalisation (the backbone's).
        seed, rank: seed the crop/caption generator with the epoch and worker.
    """

    def __init__(
        self,
        stream: IterableDataset,
        steps_per_epoch: int,
        batch_size: int,
        crop_size: int,
        min_image_size: int = 64,
        mean: tuple[float, ...] = IMAGENET_DEFAULT_MEAN,
        std: tuple[float, ...] = IMAGENET_DEFAULT_STD,
        seed: int = 0,
        rank: int = 0,
    ) -> None:
        super().__init__()
        self.stream = stream
        self.steps_per_epoch = steps_per_epoch
        self.batch_size = batch_size
        self.crop_size = crop_size
        self.min_image_size = min_image_size
        self.mean, self.std = list(mean), list(std)
        self.seed, self.rank = seed, rank
        self.epoch = 0
        # (x / 255 - mean) / std as x * gain + bias per channel (CaptionStream.collate)
        self._gain = torch.tensor([1.0 / (255.0 * s) for s in self.std])
        self._bias = torch.tensor([-m / s for m, s in zip(self.mean, self.std, strict=True)])

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.steps_per_epoch * self.batch_size

    def _examples(self) -> Iterator[dict]:
        """The rank's stream, restarted (reshuffled) whenever it runs out."""
        for p in count():
            self.stream.set_epoch(self.epoch * _EPOCH_PASSES + p)
            n = 0
            for n, example in enumerate(self.stream, 1):  # noqa: B007
                yield example
            if n == 0:
                raise RuntimeError(
                    "the caption stream yielded no examples for this worker: it has fewer "
                    "shards than processes x data.num_workers, or the sources are empty"
                )

    def _prepare(self, example: dict, rng: np.random.Generator) -> torch.Tensor | str:
        """Decoded, cropped, normalised image, or the reason it was skipped.

        The image resized (shorter side ``crop_size``, aspect kept, antialiased: torchvision's
        ``resize``), cropped at a random position. A JPEG is decoded at the smallest of its 1/2,
        1/4, 1/8 scales that still holds the resized size (``Image.draft``: the DCT scaled in
        the decoder, so a large photo never exists at full size) and resized from there; other
        formats are decoded whole. The decoded pixels are read in place (channels last, the
        layout of torch's vectorised uint8 resize); the crop stays uint8 (a view) until
        :meth:`collate` stacks and normalises the batch."""
        if example["image"] is None or not example["caption"]:
            return "invalid"
        size = self.crop_size
        try:
            with Image.open(io.BytesIO(example["image"])) as im:
                w, h = im.size
                if min(w, h) < self.min_image_size:
                    return "small"
                # torchvision's resized size: the shorter side `size`, the longer truncated
                out_w, out_h = (size, int(size * h / w)) if w <= h else (int(size * w / h), size)
                if im.mode in WIDE_GREY:  # 16/32-bit grey: scaled by pil_to_tensor, rare
                    pixels = pil_to_tensor(im)
                else:
                    im.draft("RGB", (out_w, out_h))  # JPEG: decode at a reduced scale
                    rgb = im.convert("RGB") if im.mode != "RGB" else im
                    with warnings.catch_warnings():  # read-only (PIL's bytes): only read
                        warnings.simplefilter("ignore", UserWarning)
                        pixels = torch.from_numpy(np.asarray(rgb)).permute(2, 0, 1)
        except DECODE_ERRORS:
            return "invalid"
        image = TF.resize(pixels, [out_h, out_w], antialias=True)
        top = int(rng.integers(0, out_h - size + 1))
        left = int(rng.integers(0, out_w - size + 1))
        return TF.crop(image, top, left, size, size)  # uint8 [3, S, S], a view

    def collate(self, samples: list[dict]) -> dict:
        """Samples -> a batch: the uint8 crops stacked (a quarter of the float bytes) and
        normalised together, ``(x / 255 - mean) / std`` computed as ``x * gain + bias`` straight
        into the float batch ``[B, 3, S, S]``; the other fields as ``default_collate``."""
        images = torch.stack([s["image"] for s in samples])
        batch = default_collate([{k: v for k, v in s.items() if k != "image"} for s in samples])
        out = torch.empty(0, dtype=torch.float32)
        if get_worker_info() is not None:  # in shared memory, as default_collate does: the
            # batch reaches the main process without a copy
            out = out.new(out._typed_storage()._new_shared(images.numel(), device=out.device))
        out = out.resize_(images.shape)
        torch.mul(images, self._gain.view(1, 3, 1, 1), out=out)
        batch["image"] = out.add_(self._bias.view(1, 3, 1, 1))
        return batch

    def __iter__(self) -> Iterator[dict]:
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info else (0, 1)
        # DataLoader takes batches from the workers in turn: worker w builds batches
        # w, w + W, ... so the epoch has exactly steps_per_epoch batches.
        quota = len(range(worker, self.steps_per_epoch, workers)) * self.batch_size
        rng = np.random.default_rng([self.seed, self.epoch, self.rank, worker])
        skipped = {"invalid": 0, "small": 0}
        examples = self._examples()
        produced = 0
        while produced < quota:
            example = next(examples)
            image = self._prepare(example, rng)
            if isinstance(image, str):
                # Counted in the next sample; the epoch's totals (over workers and ranks)
                # are reported once per epoch (resireg_train.training.epoch_log).
                skipped[image] += 1
                log.debug("caption data: skipped an example (%s)", image)
                continue
            captions = example["caption"]
            yield {
                "image": image,
                "caption": captions[int(rng.integers(len(captions)))],
                "skipped_invalid": skipped["invalid"],
                "skipped_small": skipped["small"],
            }
            skipped = {"invalid": 0, "small": 0}
            produced += 1


class _EpochDataLoader(DataLoader):
    """A ``DataLoader`` that tells its dataset the trainer's epoch when a pass starts.

    Lightning calls ``set_epoch`` on samplers only, and an ``IterableDataset`` has none.
    The epoch is read at the first batch, not when the iterator is made: on resume,
    Lightning makes the iterator before it restores the epoch counter from the checkpoint.
    """

    def __init__(self, dataset: CaptionStream, epoch: Callable[[], int], **kwargs: Any) -> None:
        super().__init__(dataset, **kwargs)
        self._epoch = epoch

    def __iter__(self) -> Iterator[dict]:
        def batches() -> Iterator[dict]:
            self.dataset.set_epoch(self._epoch())
            yield from super(_EpochDataLoader, self).__iter__()

        return batches()


class CaptionDataModule(L.LightningDataModule):
    """Image-caption training data (docs/training.md#caption-data).

    Args:
        sources: ``{name: spec}``; see :func:`~resireg_train.data.caption_sources.open_caption_source`. Each spec holds a
            ``probability`` (relative weight in the mix; no default, ``conf/data/`` sets it).
        batch_size: the *global* batch size (split evenly over DDP processes).
        steps_per_epoch: batches per epoch (each rank).
        crop_size: square crop side.
        min_image_size: images with a shorter side below this are skipped (counted).
        num_workers: ``DataLoader`` workers per process (capped at the stream's shards), or
            ``"auto"``: from the cores this process may use (:func:`loader_workers`, which also
            sets the prefetch depth).
        shuffle_buffer: ``datasets`` shuffle buffer (examples); <= 1 disables it.
        seed: data seed (shuffling, mixing, crops, caption choice).
        mean, std: image normalisation; the training entry point checks they match the
            backbone's.
    """

    def __init__(
        self,
        sources: Mapping[str, Mapping[str, Any]],
        batch_size: int = 48,
        steps_per_epoch: int = 1000,
        crop_size: int = 512,
        min_image_size: int = 64,
        num_workers: int | str = "auto",
        shuffle_buffer: int = 1000,
        seed: int = 0,
        mean: tuple[float, ...] = IMAGENET_DEFAULT_MEAN,
        std: tuple[float, ...] = IMAGENET_DEFAULT_STD,
        pin_memory: bool = True,
    ) -> None:
        super().__init__()
        self.sources = {k: dict(v) for k, v in sources.items()}
        self.batch_size = batch_size
        self.steps_per_epoch = steps_per_epoch
        self.crop_size = crop_size
        self.min_image_size = min_image_size
        self.num_workers = num_workers
        self.shuffle_buffer = shuffle_buffer
        self.seed = seed
        self.mean, self.std = tuple(mean), tuple(std)
        self.pin_memory = pin_memory
        self.train_set: CaptionStream | None = None

    def _world(self) -> tuple[int, int]:
        trainer = self.trainer
        return (trainer.global_rank, trainer.world_size) if trainer is not None else (0, 1)

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        rank, world = self._world()
        if self.batch_size % world:
            raise ValueError(
                f"data.batch_size={self.batch_size} (global) must be divisible by the "
                f"number of processes ({world})"
            )
        stream = mix_caption_sources(self.sources, self.seed, self.shuffle_buffer)
        if world > 1:
            stream = split_dataset_by_node(stream, rank=rank, world_size=world)
        self.train_set = CaptionStream(
            stream,
            steps_per_epoch=self.steps_per_epoch,
            batch_size=self.batch_size // world,
            crop_size=self.crop_size,
            min_image_size=self.min_image_size,
            mean=self.mean,
            std=self.std,
            seed=self.seed,
            rank=rank,
        )

    def _processes_per_node(self) -> int:
        trainer = self.trainer
        return max(1, int(getattr(trainer, "num_devices", 1))) if trainer is not None else 1

    def train_dataloader(self) -> DataLoader:
        self.setup()
        assert self.train_set is not None
        shards = self.train_set.stream.num_shards
        workers, prefetch = loader_workers(self.num_workers, shards, self._processes_per_node())
        if self.num_workers != "auto" and workers < self.num_workers:
            log.warning(
                "data.num_workers=%d capped at %d: the caption stream has only %d shards",
                self.num_workers, workers, shards,
            )  # fmt: skip
        return _EpochDataLoader(
            self.train_set,
            epoch=lambda: self.trainer.current_epoch if self.trainer is not None else 0,
            batch_size=self.train_set.batch_size,
            collate_fn=self.train_set.collate,
            num_workers=workers,
            prefetch_factor=prefetch,
            pin_memory=self.pin_memory,
            persistent_workers=False,  # workers must re-read the epoch every pass
        )


#: Batches each process keeps decoded ahead (over all its workers) at least: decode time
#: varies ~10x between a 320 px and a 4000 px photo, and a queue this deep absorbs a run of
#: large ones.
_MIN_BATCHES_AHEAD = 4


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity mask, e.g. a SLURM allocation's;
    ``os.cpu_count()`` where the platform has no mask)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def loader_workers(requested: int | str, shards: int, processes: int = 1) -> tuple[int, int | None]:
    """``(num_workers, prefetch_factor)`` of one process's caption loader.

    ``requested`` is ``data.num_workers``: an integer, or ``"auto"``: the cores this process
    may use (:func:`available_cores`) shared by the ``processes`` training processes of the
    node, less one for each process itself (at least one worker). Either is capped at the
    stream's ``shards`` (a worker reads whole shards). ``prefetch_factor`` (batches each worker
    keeps ahead) is the smallest >= 2 that keeps :data:`_MIN_BATCHES_AHEAD` batches ahead;
    ``None`` without workers (``DataLoader`` takes none then)."""
    if requested == "auto":
        requested = max(1, available_cores() // max(1, processes) - 1)
    workers = min(int(requested), shards)
    if workers == 0:
        return 0, None
    return workers, max(2, math.ceil(_MIN_BATCHES_AHEAD / workers))
