"""Segmentation datasets: synthetic, ADE20K (local folder, hub parquet layout), ORAD-3D."""

import json
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from helpers.ade20k import ade_folder, poisoned_ade_folder, save_image
from resireg.models import WeightsUnavailableError
from resireg.ovss import ADE20K_CLASSES, ORAD3D_CLASSES
from resireg_train.data.orad3d import orad3d_label
from resireg_train.data.segmentation import build_segmentation_set, collate_segmentation
from resireg_train.data.specs import dataset_conf
from resireg_train.data.synthetic import SyntheticScenes


def test_synthetic_set_resizes_images_and_keeps_full_resolution_masks():
    ds = build_segmentation_set(
        dataset_conf("synthetic", size=5, image_size=[40, 56], seed=3, short_side=32),
        patch_size=16,
    )
    assert ds.name == "synthetic" and len(ds) == 5 and not ds.reduce_zero_label
    item = ds[2]
    scene = SyntheticScenes(5, (40, 56), seed=3)[2]
    # Short side 40 -> 32; long side 56 * 0.8 = 44.8 -> 48 (rounded to the patch size).
    assert item["image"].shape == (3, 32, 48)
    assert 0.0 <= item["image"].min() and item["image"].max() <= 1.0
    assert torch.equal(item["label"], torch.from_numpy(scene["mask"].astype(np.int64)))


def _mixed_sizes_set(sizes):
    from resireg_train.data.segmentation import SegmentationSet

    return SegmentationSet(
        "mixed", ("a", "b"), load=None, header_size=lambda i: sizes[i], length=len(sizes),
        short_side=None, patch_size=16,
    )  # fmt: skip


def test_batches_share_one_size_cover_every_image_once_and_shard_disjointly():
    sizes = [(32, 48), (48, 32), (32, 48), (32, 48), (48, 32), (32, 48), (32, 48), (64, 64)]
    ds = _mixed_sizes_set(sizes)
    batches = ds.batches(3)
    assert sorted(i for b in batches for i in b) == list(range(len(sizes)))
    for batch in batches:
        assert len({sizes[i] for i in batch}) == 1 and len(batch) <= 3
    # Full batches as they fill up, then each size's leftovers (sizes in order of appearance).
    assert batches == [[0, 2, 3], [1, 4], [5, 6], [7]]
    shards = [ds.batches(3, rank=r, world_size=2) for r in range(2)]
    assert shards == [[[0, 2, 3], [5, 6]], [[1, 4], [7]]]
    with pytest.raises(ValueError, match="batch_size"):
        ds.batches(0)


def test_ade20k_local_folder_reduces_zero_label_and_skips_corrupt_images(tmp_path):
    labels = ade_folder(tmp_path / "ADEChallengeData2016")
    ds = build_segmentation_set(
        dataset_conf("ade20k", path=str(tmp_path / "ADEChallengeData2016"), short_side=32),
        patch_size=16,
    )
    assert ds.classes == ADE20K_CLASSES and ds.reduce_zero_label and len(ds) == 4
    batches = ds.batches(2)
    assert [s.index for s in ds.unreadable] == [3]  # the corrupt file is counted, not fatal
    assert ds.unreadable[0].file.endswith("ADE_val_99999999.jpg")
    assert sorted(i for b in batches for i in b) == [0, 1, 2]
    assert torch.equal(ds[1]["label"], torch.from_numpy(labels[1].astype(np.int64)))
    assert ds[1]["image"].shape == (3, 48, 32)  # 56 x 40 -> short side 32
    batch = collate_segmentation([ds[0], ds[3], ds[2]])
    assert [s.index for s in batch["skipped"]] == [3] and batch["index"] == [0, 2]


def test_ade20k_hub_layout_from_a_local_parquet_folder(tmp_path):
    """The hub's parquet conversion (image / annotation columns) read from a local copy."""
    datasets = pytest.importorskip("datasets")
    labels = ade_folder(tmp_path / "src", n=2, corrupt=False)
    files = sorted((tmp_path / "src/images/validation").glob("*.jpg"))
    table = datasets.Dataset.from_dict(
        {
            "image": [{"bytes": f.read_bytes(), "path": None} for f in files],
            "annotation": [
                {"bytes": (tmp_path / "src/annotations/validation" / f"{f.stem}.png").read_bytes(),
                 "path": None} for f in files
            ],  # fmt: skip
            "scene_category": [0, 1],
        },
        features=datasets.Features({"image": datasets.Image(), "annotation": datasets.Image(),
                                    "scene_category": datasets.Value("int64")}),
    )  # fmt: skip
    (tmp_path / "hub/data").mkdir(parents=True)
    table.to_parquet(tmp_path / "hub/data/validation-00000-of-00001.parquet")
    ds = build_segmentation_set(
        dataset_conf("ade20k", path=str(tmp_path / "hub"), short_side=32), patch_size=16
    )
    assert len(ds) == 2 and ds.reduce_zero_label
    for i in range(2):
        assert torch.equal(ds[i]["label"], torch.from_numpy(labels[i].astype(np.int64)))
    with pytest.raises(ValueError, match=r"dataset\.label='gt'"):
        build_segmentation_set(dataset_conf("ade20k", path=str(tmp_path / "hub"), label="gt"), 16)


def test_ade20k_from_the_hub_offline_fails_at_once_naming_the_key():
    start = time.perf_counter()
    with pytest.raises(WeightsUnavailableError, match=r"dataset\.path.*ADEChallengeData2016"):
        build_segmentation_set(dataset_conf("ade20k"), patch_size=16)
    assert time.perf_counter() - start < 10


def _orad_sequence(root, seq, stem, base, shapes):
    folder = root / "validation" / seq
    save_image(np.zeros((*base.shape[:2], 3), np.uint8) + 90, folder / "image_data" / f"{stem}.png")
    save_image(base, folder / "gt_image" / f"{stem}_fillcolor.png")
    (folder / "gt_image_multi_seg").mkdir(parents=True, exist_ok=True)
    (folder / "gt_image_multi_seg" / f"{stem}.json").write_text(json.dumps({"shapes": shapes}))


def test_orad3d_labels_polygons_over_the_gt_image(tmp_path):
    base = np.zeros((20, 30, 3), np.uint8)  # background (black)
    base[10:] = 255  # road (white), bottom half
    base[0:2, 0:2] = (7, 7, 7)  # a colour with no class -> ignored
    shapes = [
        {"label": "safe-road", "points": [[0, 12], [14, 12], [14, 19], [0, 19]], "shape_type": "polygon"},
        {"label": "people", "points": [[20, 2], [25, 2], [25, 8], [20, 8]], "shape_type": "polygon"},
    ]  # fmt: skip
    _orad_sequence(tmp_path, "seq_a", "0001", base, shapes)
    _orad_sequence(tmp_path, "seq_b", "0002", base, [])
    # Image "1" must not take the labels of image "10" (same prefix, sorted first).
    _orad_sequence(tmp_path, "seq_c", "1", np.zeros_like(base), [])
    _orad_sequence(tmp_path, "seq_c", "10", base, [])
    ds = build_segmentation_set(dataset_conf("orad3d", path=str(tmp_path), short_side=None), 16)
    assert ds.classes == ORAD3D_CLASSES and len(ds) == 4
    assert (ds[2]["label"] == ORAD3D_CLASSES.index("background")).all()  # seq_c/1
    label = ds[0]["label"].numpy()
    idx = {c: i for i, c in enumerate(ORAD3D_CLASSES)}
    assert label[15, 5] == idx["traversable ground"]  # polygon over road
    assert label[15, 25] == idx["road"]  # gt_image road, no polygon
    assert label[5, 22] == idx["person"]  # polygon over background
    assert label[5, 10] == idx["background"]
    assert label[0, 0] == 255  # unmapped colour
    assert ds[0]["image"].shape == (3, 16, 32)  # sides rounded to the patch size
    entry = dataset_conf("orad3d")  # the mappings' one source, conf/dataset/orad3d.yaml
    direct = orad3d_label(
        tmp_path / "validation/seq_a/gt_image/0001_fillcolor.png",
        tmp_path / "validation/seq_a/gt_image_multi_seg/0001.json",
        entry["polygon_tags"],
        entry["gt_image_classes"],
    )
    assert np.array_equal(direct, label)


def test_orad3d_unknown_polygon_tag_is_an_error_naming_the_mapping(tmp_path):
    base = np.zeros((8, 8, 3), np.uint8)
    _orad_sequence(
        tmp_path, "s", "1", base, [{"label": "tractor", "points": [[0, 0], [3, 0], [3, 3]]}]
    )
    with pytest.raises(ValueError, match=r"'tractor'.*dataset\.polygon_tags"):
        build_segmentation_set(dataset_conf("orad3d", path=str(tmp_path)), 16)
    spec = dataset_conf("orad3d", path=str(tmp_path), polygon_tags={"tractor": "car"})
    assert len(build_segmentation_set(spec, 16)) == 1


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ({"kind": "lidar"}, r"dataset\.kind='lidar'"),
        (dataset_conf("synthetic", colour=1), r"unknown keys \['colour'\]"),
        (dataset_conf("synthetic", short_side=8), r"dataset\.short_side=8"),
        (dataset_conf("orad3d", path="/nonexistent/orad"), r"dataset\.path='/nonexistent/orad'"),
        (dataset_conf("ade20k", path="/nonexistent/ade"), r"dataset\.path='/nonexistent/ade'"),
        (
            dataset_conf("synthetic", templates="imagenet"),
            r"^dataset\.templates='imagenet': expected one of \['openai_imagenet', 'simple_imagenet'\]$",
        ),
    ],
)
def test_bad_dataset_specs_name_the_key(spec, message):
    with pytest.raises((ValueError, FileNotFoundError), match=message):
        build_segmentation_set(spec, patch_size=16)


def test_bad_ade20k_samples_are_skipped_naming_file_and_reason(tmp_path):
    import re

    from resireg_train.data.segmentation import SkippedSample

    bad = poisoned_ade_folder(tmp_path)
    ds = build_segmentation_set(dataset_conf("ade20k", path=str(tmp_path), short_side=32), 16)
    assert len(ds) == 9  # the upper-case .JPG image is listed too
    items = [ds[i] for i in range(len(ds))]
    skipped = {Path(s.file).name: s.reason for s in items if isinstance(s, SkippedSample)}
    assert set(skipped) == set(bad)
    for name, pattern in bad.items():
        assert re.search(pattern, skipped[name]), (name, skipped[name])
    good = [s for s in items if not isinstance(s, SkippedSample)]
    assert len(good) == 5 and all(s["label"].shape == (48, 64) for s in good)


def test_sixteen_bit_png_images_are_scaled_not_saturated(tmp_path):
    """A 16-bit grey PNG (PIL mode I;16) comes out as v / 257 on all three channels, as numpy
    computes it; PIL's own convert("RGB") clips every value above 255 to white."""
    from resireg.models.images import pil_to_tensor

    wide = np.linspace(0, 65535, 48 * 64).astype(np.uint16).reshape(48, 64)
    Image.fromarray(wide).save(tmp_path / "wide.png")
    with Image.open(tmp_path / "wide.png") as image:
        assert image.mode.startswith("I")
        pixels = pil_to_tensor(image)
        clipped = np.asarray(image.convert("RGB"))
    expected = np.rint(wide / 257.0).astype(np.uint8)
    assert pixels.shape == (3, 48, 64) and pixels.dtype == torch.uint8
    for channel in pixels:
        assert np.array_equal(channel.numpy(), expected)
    assert (clipped == 255).mean() > 0.99  # what the images came out as before


def test_the_templates_key_picks_open_clips_set_and_the_protocol_record_names_it():
    """``dataset.templates`` names the prompt template set of the class prototypes: the
    engine's prompts are every class filled into each of open_clip's templates of that set, and
    the run's protocol record names the set last, as it named the 80 before the key existed."""
    import open_clip

    from resireg_train.evaluation.ovss.engine import OVSSEngine
    from resireg_train.evaluation.protocol import protocol_record

    for name, constant, count in (("simple_imagenet", "SIMPLE_IMAGENET_TEMPLATES", 7),
                                  ("openai_imagenet", "OPENAI_IMAGENET_TEMPLATES", 80)):  # fmt: skip
        spec = dataset_conf("synthetic", size=2, templates=name)
        dataset = build_segmentation_set(spec, patch_size=16)
        templates = getattr(open_clip, constant)
        want = [t(c) for c in dataset.classes for t in templates]
        assert OVSSEngine(dataset, batch_size=2, num_workers=0).text.prompts == want
        assert len(templates) == count
        settings = protocol_record({"task": "ovss", "dataset": spec}, dataset)["settings"]
        assert list(settings)[-1] == "templates"
        assert settings["templates"] == f"open_clip {constant} ({count})"
    assert dataset_conf("synthetic")["templates"] == "openai_imagenet"  # conf/protocol/paper.yaml


def test_the_config_check_refuses_a_template_set_it_does_not_know_naming_the_key():
    """What resireg-eval checks before anything loads: the key, the value and the choices."""
    from resireg.errors import ConfigError
    from resireg_train.checks.eval import validate_eval

    for bad in ("imagenet", None, 7):
        with pytest.raises(ConfigError, match=rf"dataset\.templates={bad!r}: expected one of "
                           r"\['openai_imagenet', 'simple_imagenet'\]"):  # fmt: skip
            validate_eval({"dataset": dataset_conf("synthetic", templates=bad)})
