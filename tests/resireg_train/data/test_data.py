"""Caption data on `datasets`: local formats, column mapping, mixing, sharding, skipping."""

import io
import tarfile
import time
from collections import Counter

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from PIL import Image

from resireg.models import WeightsUnavailableError
from resireg_train.data.caption_sources import mix_caption_sources, open_caption_source
from resireg_train.data.captions import CaptionDataModule


def _png(h=40, w=48, value=0):
    buf = io.BytesIO()
    Image.fromarray(np.full((h, w, 3), value, np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def _cauldron_parquet(path, n, files=1):
    """The_cauldron layout: `images` (list of images), `texts` (list of user/assistant turns)."""
    path.mkdir(parents=True, exist_ok=True)
    image_t = pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    turn_t = pa.struct([("user", pa.string()), ("assistant", pa.string())])
    for f in range(files):
        ids = range(f, n, files)
        table = pa.table({
            "images": pa.array([[{"bytes": _png(value=i), "path": None}] for i in ids],
                               pa.list_(image_t)),
            "texts": pa.array([[{"user": "Describe.", "assistant": f"cap {i}"}] for i in ids],
                              pa.list_(turn_t)),
        })  # fmt: skip
        pq.write_table(table, path / f"train-{f:05d}.parquet")
    return str(path)


def _source(path, image, caption):
    """A caption source entry holding every key conf/data/ gives one (split, columns, weight)."""
    return {"path": path, "split": "train", "image": image, "caption": caption, "probability": 1.0}


def _loader(sources, **kw):
    args = {"batch_size": 4, "steps_per_epoch": 3, "crop_size": 32, "min_image_size": 16,
            "num_workers": 0, "shuffle_buffer": 0, "pin_memory": False}  # fmt: skip
    args.update(kw)
    dm = CaptionDataModule(sources, **args)
    return dm, dm.train_dataloader()


def _epoch(loader, epoch=0):
    loader._epoch = lambda: epoch  # what the trainer's current_epoch provides
    return list(loader)


def test_nested_columns_of_a_local_parquet_source(tmp_path):
    folder = _cauldron_parquet(tmp_path / "cauldron", 12, files=3)
    spec = _source(folder, image="images.0", caption="texts.0.assistant")
    examples = list(open_caption_source("cauldron", spec))
    assert sorted(e["caption"][0] for e in examples) == sorted(f"cap {i}" for i in range(12))
    image = Image.open(io.BytesIO(examples[0]["image"]))
    assert image.size == (48, 40)
    with pytest.raises(ValueError, match=r"data\.sources\.cauldron\.caption='captions'"):
        open_caption_source("cauldron", {**spec, "caption": "captions"})
    with pytest.raises(ValueError, match=r"data\.sources\.cauldron: unknown keys \['colour'\]"):
        open_caption_source("cauldron", {**spec, "colour": 1})
    # conf/data/ holds every source's split and columns: a missing one is named, not assumed
    with pytest.raises(
        ValueError, match=r"data\.sources\.cauldron: no data\.sources\.cauldron\.split"
    ):
        open_caption_source("cauldron", {k: v for k, v in spec.items() if k != "split"})


def test_batches_are_cropped_normalised_and_exactly_steps_per_epoch(tmp_path):
    folder = _cauldron_parquet(tmp_path / "c", 20, files=4)
    spec = _source(folder, image="images.0", caption="texts.0.assistant")
    _, loader = _loader({"c": spec}, num_workers=2, steps_per_epoch=5, mean=(0.5,) * 3,
                        std=(0.25,) * 3)  # fmt: skip
    batches = _epoch(loader)
    assert len(batches) == len(loader) == 5
    assert batches[0]["image"].shape == (4, 3, 32, 32)
    # Images are constant grey value i/255: normalised pixels are (i/255 - 0.5) / 0.25.
    ids = [int(c.split()[1]) for b in batches for c in b["caption"]]
    expected = torch.tensor([(i / 255 - 0.5) / 0.25 for i in ids])
    got = torch.cat([b["image"][:, 0, 0, 0] for b in batches])
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=0)


def test_caption_lists_give_one_random_caption_and_epochs_reshuffle(tmp_path):
    """COCO-style: several captions per image (an image folder with a list column)."""
    folder = tmp_path / "coco"
    folder.mkdir()
    rows = []
    for i in range(8):
        (folder / f"{i}.png").write_bytes(_png(value=i))
        rows.append(f'{{"file_name": "{i}.png", "answer": ["a{i}", "b{i}", "c{i}"]}}')
    (folder / "metadata.jsonl").write_text("\n".join(rows) + "\n")
    spec = _source(str(folder), image="image", caption="answer")
    _, loader = _loader({"coco": spec}, steps_per_epoch=16, shuffle_buffer=8)
    first = [c for b in _epoch(loader, 0) for c in b["caption"]]
    assert {c[0] for c in first} == {"a", "b", "c"}  # every caption of the list gets drawn
    assert first == [c for b in _epoch(loader, 0) for c in b["caption"]]  # epoch-determined
    assert first != [c for b in _epoch(loader, 1) for c in b["caption"]]


def test_interleave_follows_probabilities(tmp_path):
    sources = {
        "a": {"path": "synthetic", "size": 400, "seed": 1, "probability": 3.0, "image_size": [32, 32],
              "noise": 12.0, "shards": 8},
        "b": {"path": "synthetic", "size": 400, "seed": 2, "probability": 1.0, "image_size": [40, 40],
              "noise": 12.0, "shards": 8},
    }  # fmt: skip
    stream = mix_caption_sources(sources, seed=0, shuffle_buffer=0)
    sizes = Counter(
        Image.open(io.BytesIO(e["image"])).size[0] for _, e in zip(range(400), stream, strict=False)
    )
    assert sizes[32] / 400 == pytest.approx(0.75, abs=0.07)
    with pytest.raises(ValueError, match=r"data\.sources\.b\.probability=0\.0"):
        mix_caption_sources({**sources, "b": {**sources["b"], "probability": 0.0}})
    # no default weight: conf/data/ sets every source's probability
    without = {k: v for k, v in sources["b"].items() if k != "probability"}
    with pytest.raises(ValueError, match=r"data\.sources\.b: no data\.sources\.b\.probability"):
        mix_caption_sources({**sources, "b": without})


def test_ranks_read_disjoint_shards(tmp_path):
    folder = _cauldron_parquet(tmp_path / "c", 16, files=4)
    spec = {
        "c": {
            "path": folder,
            "split": "train",
            "image": "images.0",
            "caption": "texts.0.assistant",
            "probability": 1.0,
        }
    }

    class _Trainer:
        world_size, current_epoch = 2, 0

        def __init__(self, rank):
            self.global_rank = rank

    seen = []
    for rank in (0, 1):
        dm = CaptionDataModule(spec, batch_size=8, steps_per_epoch=2, crop_size=32,
                               min_image_size=16, num_workers=0, shuffle_buffer=0,
                               pin_memory=False)  # fmt: skip
        dm.trainer = _Trainer(rank)
        batches = list(dm.train_dataloader())
        assert batches[0]["image"].shape[0] == 4  # the global batch is split over ranks
        seen.append({c for b in batches for c in b["caption"]})
    assert seen[0].isdisjoint(seen[1]) and len(seen[0] | seen[1]) == 16
    dm.trainer = type("T", (), {"world_size": 3, "global_rank": 0, "current_epoch": 0})()
    dm.train_set = None
    with pytest.raises(ValueError, match=r"data\.batch_size=8 \(global\) must be divisible"):
        dm.setup()


def test_corrupt_and_tiny_images_are_skipped_and_counted(tmp_path, caplog):
    """An image folder with captions in metadata.jsonl: 2 corrupt and 3 tiny images. The
    stream only counts them (the epoch's totals are reported once, by EpochLog)."""
    folder = tmp_path / "folder"
    folder.mkdir()
    lines = []
    for i in range(15):
        name = f"{i:02d}.png"
        if i in (3, 9):
            (folder / name).write_bytes(b"\x89PNG\r\n\x1a\n not really an image")
        else:
            size = 8 if i in (1, 5, 12) else 40
            (folder / name).write_bytes(_png(size, size, value=i))
        lines.append(f'{{"file_name": "{name}", "text": "image {i}"}}')
    (folder / "metadata.jsonl").write_text("\n".join(lines) + "\n")
    spec = {
        "path": str(folder),
        "split": "train",
        "image": "image",
        "caption": "text",
        "probability": 1.0,
    }
    _, loader = _loader({"folder": spec}, steps_per_epoch=5, batch_size=2)
    with caplog.at_level("INFO"):
        batches = _epoch(loader)
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    captions = [c for b in batches for c in b["caption"]]
    assert len(captions) == 10 and {3, 9, 1, 5, 12}.isdisjoint(int(c.split()[1]) for c in captions)
    assert sum(int(b["skipped_invalid"].sum()) for b in batches) == 2
    assert sum(int(b["skipped_small"].sum()) for b in batches) == 3


def test_webdataset_shards(tmp_path):
    for shard in range(2):
        with tarfile.open(tmp_path / f"shard-{shard}.tar", "w") as tar:
            for i in range(4):
                for ext, data in (("jpg", _jpeg()), ("txt", f"shard {shard} item {i}".encode())):
                    info = tarfile.TarInfo(f"{shard:02d}{i:04d}.{ext}")
                    info.size = len(data)
                    tar.addfile(info, io.BytesIO(data))
    spec = {
        "path": "webdataset",
        "data_files": str(tmp_path / "*.tar"),
        "split": "train",
        "image": "jpg",
        "caption": "txt",
        "probability": 1.0,
    }
    _, loader = _loader({"wds": spec}, steps_per_epoch=2)
    captions = {c for b in _epoch(loader) for c in b["caption"]}
    assert len(captions) == 8 and all(c.startswith("shard ") for c in captions)


def _jpeg():
    buf = io.BytesIO()
    Image.fromarray(np.full((36, 36, 3), 128, np.uint8)).save(buf, format="JPEG")
    return buf.getvalue()


def test_hub_source_offline_fails_at_once_naming_the_key():
    start = time.perf_counter()
    spec = {"path": "HuggingFaceM4/the_cauldron", "name": "textcaps"}
    with pytest.raises(WeightsUnavailableError, match=r"data\.sources\.textcaps\.path"):
        open_caption_source("textcaps", spec)
    assert time.perf_counter() - start < 5
    with pytest.raises(FileNotFoundError, match=r"data\.sources\.x\.path='/no/such/dir'"):
        open_caption_source("x", {"path": "/no/such/dir"})


# ------------------------------------------------- decoding at the crop's scale (issue 54 item 3)
def _photo_jpeg(w, h, seed=0, mode="RGB"):
    """A JPEG with a photo's spread of frequencies: smooth colour fields, grain, and a
    checkerboard of shading whose edges show any offset of the crop."""
    g = np.random.default_rng(seed)
    low = Image.fromarray((g.random((h // 64 + 2, w // 64 + 2, 3)) * 255).astype(np.uint8))
    arr = np.asarray(low.resize((w, h), Image.Resampling.BICUBIC)).astype(np.float32)
    arr += g.normal(0, 6, arr.shape)
    yy, xx = np.mgrid[0:h, 0:w]
    arr[((xx // max(1, w // 9)) + (yy // max(1, h // 7))) % 2 == 0] *= 0.6
    image = Image.fromarray(np.clip(arr, 0, 255).astype(np.uint8)).convert(mode)
    buf = io.BytesIO()
    image.save(buf, format="JPEG", quality=90)
    return buf.getvalue()


def _full_size_crop(data, crop, rng, mean, std):
    """Today's reference, independent of the stream's code: the whole image decoded at full
    size (plain PIL), torchvision's antialiased resize of the shorter side to ``crop``, the
    random crop drawn as the stream draws it (top, then left), normalised."""
    from torchvision.transforms.v2 import functional as TF

    with Image.open(io.BytesIO(data)) as im:
        pixels = torch.from_numpy(np.array(im.convert("RGB"))).permute(2, 0, 1)
    image = TF.resize(pixels, crop, antialias=True)
    h, w = image.shape[-2:]
    top = int(rng.integers(0, h - crop + 1))
    left = int(rng.integers(0, w - crop + 1))
    image = TF.to_dtype(TF.crop(image, top, left, crop, crop), torch.float32, scale=True)
    return TF.normalize(image, list(mean), list(std))


@pytest.mark.parametrize(
    ("size", "mode", "fmt", "scale"),
    [
        ((2800, 2100), "RGB", "JPEG", 4),  # decoded at 1/4: 700 x 525 holds 682 x 512
        ((1600, 1200), "RGB", "JPEG", 2),
        ((1200, 1800), "RGB", "JPEG", 2),  # portrait
        ((1100, 1000), "L", "JPEG", 1),  # grey; 1/2 would be 500 high, below 512
        ((400, 300), "RGB", "JPEG", 1),  # upsampled
        ((900, 700), "RGB", "PNG", 1),  # not a JPEG: decoded whole
    ],
)
def test_crops_equal_the_full_size_decode_within_resampling_tolerance(
    size, mode, fmt, scale, monkeypatch
):
    from resireg_train.data.captions import CaptionStream

    data = _photo_jpeg(*size, seed=size[0], mode=mode)
    if fmt == "PNG":
        with Image.open(io.BytesIO(data)) as im:
            buf = io.BytesIO()
            im.save(buf, format="PNG")
        data = buf.getvalue()
    decoded = []
    load = Image.Image.load

    def spy(self):  # the size each image is decoded at
        out = load(self)
        decoded.append(self.size)
        return out

    monkeypatch.setattr(Image.Image, "load", spy)
    mean, std = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
    stream = CaptionStream(None, steps_per_epoch=1, batch_size=1, crop_size=512, mean=mean, std=std)
    crop = stream._prepare({"image": data, "caption": ["c"]}, np.random.default_rng(7))
    sample = {"image": crop, "caption": "c", "skipped_invalid": 0, "skipped_small": 0}
    got = stream.collate([sample])["image"][0]  # the loader's batch, normalised
    monkeypatch.setattr(Image.Image, "load", load)
    ref = _full_size_crop(data, 512, np.random.default_rng(7), mean, std)
    assert got.shape == ref.shape == (3, 512, 512) and got.dtype == torch.float32
    assert decoded[0] == (-(-size[0] // scale), -(-size[1] // scale))
    err = ((got - ref) * torch.tensor(std).view(3, 1, 1) * 255).abs()  # in 8-bit levels
    psnr = 10 * torch.log10(255.0**2 / (err**2).mean())
    if scale == 1:  # the same pixels resized by the same function: float rounding only
        assert err.max() <= 1e-3, float(err.max())
    else:  # the DCT's reduced scale: resampling differences, no shift
        assert err.mean() <= 1.0 and psnr >= 40, (float(err.mean()), float(psnr))


def _wds_shards(folder, shards):
    """webdataset shards: ``shards`` is a list of lists of ``(key, jpeg bytes)``; ``None``
    for a 0-byte shard."""
    folder.mkdir()
    for s, items in enumerate(shards):
        path = folder / f"shard-{s}.tar"
        if items is None:
            path.write_bytes(b"")
            continue
        with tarfile.open(path, "w") as tar:
            for key, image in items:
                for ext, data in (("jpg", image), ("txt", f"caption {key}".encode())):
                    info = tarfile.TarInfo(f"{key}.{ext}")
                    info.size = len(data)
                    tar.addfile(info, io.BytesIO(data))
    return {"path": "webdataset", "data_files": str(folder / "*.tar"), "split": "train",
            "image": "jpg", "caption": "txt", "probability": 1.0}  # fmt: skip


@pytest.mark.parametrize("bad", ["undecodable", "truncated", "empty shard"])
def test_bad_jpegs_and_empty_shards_are_skipped_and_counted(bad, tmp_path, caplog):
    """Six good JPEGs in two shards, and one bad thing: a JPEG that is not one, a JPEG cut
    in half, or a third shard of 0 bytes. The epoch holds the six, the bad image is counted
    in ``skipped_invalid``, the empty shard in one warning naming it."""
    good = [(f"{s}{i}", _photo_jpeg(96, 80, seed=10 * s + i)) for s in range(2) for i in range(3)]
    shards = [good[:3], good[3:]]
    whole = _photo_jpeg(400, 300, seed=99)
    if bad == "empty shard":
        shards.append(None)
    else:
        shards[0].append(("bad", b"\xff\xd8\xff\xe0 not a JPEG" if bad == "undecodable"
                          else whole[: len(whole) // 2]))  # fmt: skip
    spec = _wds_shards(tmp_path / "wds", shards)
    _, loader = _loader({"wds": spec}, steps_per_epoch=3, batch_size=2)
    with caplog.at_level("WARNING"):
        batches = _epoch(loader)
    captions = sorted(c for b in batches for c in b["caption"])
    assert captions == sorted(f"caption {k}" for k, _ in good)
    invalid = sum(int(b["skipped_invalid"].sum()) for b in batches)
    warnings_ = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    if bad == "empty shard":
        assert invalid == 0
        assert warnings_ == ["data.sources.wds: skipped 1 empty (0-byte) shard(s): shard-2.tar"]
    else:
        assert invalid == 1 and not warnings_


def test_auto_workers_follow_the_cores_this_process_may_use(monkeypatch, tmp_path):
    """``data.num_workers: auto``: the affinity mask's cores shared by the node's processes,
    one left to each process, capped at the shards; the prefetch depth keeps >= 4 batches."""
    from resireg_train.data import captions

    monkeypatch.setattr(captions.os, "sched_getaffinity", lambda pid: set(range(16)))
    assert captions.loader_workers("auto", shards=100, processes=2) == (7, 2)
    assert captions.loader_workers("auto", shards=100, processes=1) == (15, 2)
    assert captions.loader_workers("auto", shards=3, processes=1) == (3, 2)
    monkeypatch.setattr(captions.os, "sched_getaffinity", lambda pid: {0, 1})
    assert captions.loader_workers("auto", shards=100) == (1, 4)  # 4 batches ahead from 1
    assert captions.loader_workers(0, shards=100) == (0, None)
    assert captions.loader_workers(8, shards=5) == (5, 2)
    folder = _cauldron_parquet(tmp_path / "c", 8, files=4)
    spec = _source(folder, image="images.0", caption="texts.0.assistant")
    _, loader = _loader({"c": spec}, num_workers="auto")
    assert (loader.num_workers, loader.prefetch_factor) == (1, 4)
