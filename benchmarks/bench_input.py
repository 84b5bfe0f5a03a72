"""The stage-1 input pipeline against its decode floor and one GPU step's appetite.

On webdataset shards of JPEG photos (generated: ``--images`` photos, long side log-uniform
from 320 to 4000 px, aspect 1:1 to 16:9 either way, quality 90; or ``--shards DIR``, your own
``*.tar``), one process on one core (``torch.set_num_threads(1)``, no workers) measures, in
images per second per core:

- **floor**: the JPEG decode itself at the reduced scale the crop allows (``Image.draft`` to
  the size of the image resized to a ``--crop`` shorter side, then ``load``), from bytes in
  memory;
- **pipeline**: the caption stream as training runs it (``CaptionDataModule`` on the shards:
  ``datasets`` reads the tars, ``CaptionStream`` decodes, resizes, crops, normalises, the
  ``DataLoader`` collates batches of ``--batch``), timed over its second pass;
- for reference, the full-size decode (``load`` without draft) and the stream's former
  preparation (full-size decode, torchvision's antialiased resize of the whole image, crop,
  normalise), from bytes in memory.

pipeline / floor (time per image) is the figure issue 54 asks <= 1.3. Beside them, one GPU
step's appetite: the FLOP per image of ``gpu_check.py``'s bf16 training step of the 25M model
(512 px crops; without and with the RADSeg-sized teacher), counted by ``FlopCounterMode`` over
one step at batch 2 on the CPU, against the card's published dense bf16 rate
(``--gpu-tflops``, default the H100 SXM's 989): an estimate (no GPU measured), the most images
per second the card could take at its peak, and the cores that would feed it.

Undecodable or truncated JPEGs and 0-byte shards are skipped and counted (both in the floor's
pass and by the stream).

    python benchmarks/bench_input.py                       # 120 generated photos
    python benchmarks/bench_input.py --images 24 --no-flops  # quick
    python benchmarks/bench_input.py --shards /data/pexels-568k --images 500
"""

from __future__ import annotations

import argparse
import io
import logging
import math
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

#: The published dense bf16 rate of an H100 SXM (NVIDIA's datasheet: 989 TFLOP/s; 1,979 is
#: with 2:4 sparsity).
H100_BF16_TFLOPS = 989.0


def photo_jpeg(w: int, h: int, rng: np.random.Generator, quality: int = 90) -> bytes:
    """A JPEG with a photo's spread of frequencies: smooth colour fields, grain and shading
    with edges (noise alone would decode slower than photos and compress worse)."""
    low = Image.fromarray((rng.random((h // 64 + 2, w // 64 + 2, 3)) * 255).astype(np.uint8))
    arr = np.asarray(low.resize((w, h), Image.Resampling.BICUBIC)).astype(np.float32)
    arr += rng.normal(0, 6, arr.shape).astype(np.float32)
    yy, xx = np.ogrid[0:h, 0:w]
    arr[((xx // max(1, w // 9)) + (yy // max(1, h // 7))) % 2 == 0] *= 0.6
    buf = io.BytesIO()
    Image.fromarray(np.clip(arr, 0, 255).astype(np.uint8)).save(buf, "JPEG", quality=quality)
    return buf.getvalue()


def photo_sizes(n: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    """``n`` (w, h): long side log-uniform in [320, 4000], aspect 1:1, 4:3, 3:2 or 16:9,
    landscape or portrait."""
    sizes = []
    for _ in range(n):
        long = int(round(math.exp(rng.uniform(math.log(320), math.log(4000)))))
        short = int(round(long / rng.choice([1.0, 4 / 3, 3 / 2, 16 / 9])))
        sizes.append((long, short) if rng.random() < 0.75 else (short, long))
    return sizes


def write_shards(folder: Path, n: int, shards: int, seed: int) -> None:
    """``n`` generated photos with captions in ``shards`` webdataset tars."""
    rng = np.random.default_rng(seed)
    sizes = photo_sizes(n, rng)
    folder.mkdir(parents=True, exist_ok=True)
    for s in range(shards):
        with tarfile.open(folder / f"shard-{s:03d}.tar", "w") as tar:
            for i in range(s, n, shards):
                w, h = sizes[i]
                for ext, data in (("jpg", photo_jpeg(w, h, rng)), ("txt", f"photo {i}".encode())):
                    info = tarfile.TarInfo(f"{i:06d}.{ext}")
                    info.size = len(data)
                    tar.addfile(info, io.BytesIO(data))


def read_images(folder: Path, limit: int) -> tuple[list[bytes], int]:
    """The first ``limit`` ``.jpg`` members of the folder's ``*.tar`` (sorted), and the count of
    0-byte shards skipped."""
    images, empty = [], 0
    for path in sorted(folder.glob("*.tar")):
        if path.stat().st_size == 0:
            empty += 1
            continue
        with tarfile.open(path) as tar:
            for member in tar:
                if member.name.endswith(".jpg") and len(images) < limit:
                    images.append(tar.extractfile(member).read())
    return images, empty


def resized_size(w: int, h: int, crop: int) -> tuple[int, int]:
    """The image's size with its shorter side resized to ``crop`` (torchvision's rounding)."""
    return (crop, int(crop * h / w)) if w <= h else (int(crop * w / h), crop)


def decode_floor(data: bytes, crop: int) -> None:
    """The JPEG decoded at the reduced scale the crop allows, nothing else."""
    with Image.open(io.BytesIO(data)) as im:
        im.draft("RGB", resized_size(*im.size, crop))
        im.load()


def decode_full(data: bytes, crop: int) -> None:
    with Image.open(io.BytesIO(data)) as im:
        im.load()


def former_prepare(data: bytes, crop: int, rng: np.random.Generator) -> torch.Tensor:
    """The stream's preparation before issue 54: full-size decode, torchvision's antialiased
    resize of the whole image, crop, normalise."""
    from timm.data import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD
    from torchvision.transforms.v2 import functional as TF

    from resireg.models.images import pil_to_tensor

    with Image.open(io.BytesIO(data)) as im:
        pixels = pil_to_tensor(im)
    image = TF.resize(pixels, crop, antialias=True)
    h, w = image.shape[-2:]
    top, left = int(rng.integers(0, h - crop + 1)), int(rng.integers(0, w - crop + 1))
    image = TF.to_dtype(TF.crop(image, top, left, crop, crop), torch.float32, scale=True)
    return TF.normalize(image, list(IMAGENET_DEFAULT_MEAN), list(IMAGENET_DEFAULT_STD))


def per_image(fn, images: list[bytes], *args) -> tuple[float, int]:
    """``(seconds per decodable image, undecodable count)`` of ``fn`` over ``images``."""
    from resireg.sources.frames import DECODE_ERRORS

    total, bad = 0.0, 0
    for data in images:
        start = time.perf_counter()
        try:
            fn(data, *args)
        except DECODE_ERRORS:
            bad += 1
            continue
        total += time.perf_counter() - start
    return total / max(1, len(images) - bad), bad


def stream_rate(folder: Path, images: int, crop: int, batch: int) -> tuple[float, int, int]:
    """``(seconds per image, images, skipped)`` of the caption stream over the shards, one
    process, no workers, timed over its second pass (the first warms the page cache)."""
    from resireg_train.data.captions import CaptionDataModule

    spec = {"path": "webdataset", "data_files": str(folder / "*.tar"), "split": "train",
            "image": "jpg", "caption": "txt", "probability": 1.0}  # fmt: skip
    steps = max(1, images // batch)
    dm = CaptionDataModule({"src": spec}, batch_size=batch, steps_per_epoch=steps,
                           crop_size=crop, num_workers=0, shuffle_buffer=0,
                           pin_memory=False)  # fmt: skip
    loader = dm.train_dataloader()
    for _ in loader:  # first pass
        pass
    start = time.perf_counter()
    skipped = 0
    for b in loader:
        skipped += int(b["skipped_invalid"].sum())
    return (time.perf_counter() - start) / (steps * batch), steps * batch, skipped


def step_flops_per_image(crop: int) -> dict[str, float]:
    """FLOP per image of gpu_check.py's bf16 training step (one step at batch 2, CPU)."""
    import argparse as ap

    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.utils.flop_counter import FlopCounterMode

    import gpu_check

    args = ap.Namespace(dry_run=False, device="cpu")
    out = {}
    hub_dir = torch.hub.get_dir()
    with tempfile.TemporaryDirectory() as tmp:
        repo = gpu_check._teacher_repo(Path(tmp), tiny=False)
        torch.hub.set_dir(str(Path(tmp) / "hub"))
        try:
            for label, teacher in (
                ("without teacher", None),
                ("with RADSeg-sized teacher",
                 {"kind": "radseg", "repo": str(repo), "source": "local"}),
            ):  # fmt: skip
                torch.manual_seed(0)
                module = gpu_check._train_module(args, teacher)
                optimizer, _ = module.build_optimizer(100)
                module.train()
                batch = {"image": torch.randn(2, 3, crop, crop),
                         "caption": ["a photo of thing 0", "a photo of thing 1"]}  # fmt: skip
                counter = FlopCounterMode(display=False)
                # the math backend: FlopCounterMode has no formula for the CPU's fused SDPA
                # kernel; its two batched products are the ones a GPU's kernel computes
                with counter, sdpa_kernel(SDPBackend.MATH), torch.autocast("cpu", torch.bfloat16):
                    loss, _ = module.losses(batch, 0)
                    loss.backward()
                out[label] = counter.get_total_flops() / 2
                del module, optimizer
        finally:
            torch.hub.set_dir(hub_dir)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--images", type=int, default=120, help="photos generated / read")
    parser.add_argument("--shards", type=Path, default=None, help="a folder of *.tar shards")
    parser.add_argument("--n-shards", type=int, default=4, help="shards generated")
    parser.add_argument("--crop", type=int, default=512)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--gpu-tflops", type=float, default=H100_BF16_TFLOPS)
    parser.add_argument("--gpu-name", default="H100 SXM")
    parser.add_argument("--no-flops", action="store_true", help="skip the GPU step's FLOP count")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)

    from resireg_train.data.captions import available_cores, loader_workers

    with tempfile.TemporaryDirectory() as tmp:
        folder = args.shards
        if folder is None:
            folder = Path(tmp) / "shards"
            start = time.perf_counter()
            write_shards(folder, args.images, args.n_shards, args.seed)
            print(f"generated {args.images} photos in {args.n_shards} shards "
                  f"({time.perf_counter() - start:.0f} s)")  # fmt: skip
        images, empty = read_images(folder, args.images)
        if not images:
            raise SystemExit(f"--shards={str(folder)!r}: no .jpg in a non-empty *.tar")
        sizes = []
        for data in images:
            try:
                with Image.open(io.BytesIO(data)) as im:
                    sizes.append(max(im.size))
            except OSError:
                pass
        mb = sum(len(d) for d in images) / 2**20
        print(f"{len(images)} JPEGs ({mb:.1f} MiB), long side {min(sizes, default=0)} to "
              f"{max(sizes, default=0)} px (median {int(np.median(sizes or [0]))}), "
              f"{empty} empty (0-byte) shard(s) skipped; one process, 1 thread")  # fmt: skip
        floor, bad = per_image(decode_floor, images, args.crop)
        full, _ = per_image(decode_full, images, args.crop)
        former, _ = per_image(former_prepare, images, args.crop, np.random.default_rng(0))
        valid = len(images) - bad
        pipe, n, skipped = stream_rate(folder, valid, args.crop, args.batch)
        print(f"undecodable or truncated JPEGs skipped: {bad} (floor's pass), "
              f"{skipped} (the stream's counters)")  # fmt: skip

    rows = [
        ("floor: JPEG decode at the crop's reduced scale (draft)", floor),
        ("pipeline: the caption stream (read, decode, resize, crop, normalise, collate)", pipe),
        ("full-size JPEG decode", full),
        ("former preparation: full-size decode, resize, crop, normalise", former),
    ]
    print("\n| stage | ms / image | images/s/core | / floor |")
    print("| --- | ---: | ---: | ---: |")
    for label, seconds in rows:
        print(f"| {label} | {1e3 * seconds:.1f} | {1 / seconds:.1f} | {seconds / floor:.2f} |")
    print(f"\npipeline / floor: {pipe / floor:.2f} (over {n} images)")
    workers, prefetch = loader_workers("auto", shards=1 << 30)
    print(f"this machine: {available_cores()} cores -> data.num_workers=auto gives {workers} "
          f"worker(s), prefetch {prefetch} batches each, "
          f"~{workers / pipe:.0f} images/s per process")  # fmt: skip
    if not args.no_flops:
        flops = step_flops_per_image(args.crop)
        print(f"\nGPU appetite (ESTIMATE, no GPU measured): {args.gpu_name} at its published "
              f"dense bf16 {args.gpu_tflops:g} TFLOP/s, 100% of peak (an upper bound)")  # fmt: skip
        print("\n| step | GFLOP / image | images/s at peak | cores to feed it |")
        print("| --- | ---: | ---: | ---: |")
        for label, f in flops.items():
            rate = args.gpu_tflops * 1e12 / f
            print(f"| {label} | {f / 1e9:.0f} | {rate:.0f} | {rate * pipe:.0f} |")


if __name__ == "__main__":
    main()
