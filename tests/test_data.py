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
from resireg_train.data.captions import CaptionDataModule, mix_caption_sources, open_caption_source


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
