"""The readers of the OVSS field's benchmarks (VOC21/VOC20, PC60/PC59, COCO-Stuff, COCO-Object,
Cityscapes, ADE20K from ADEChallengeData2016): each on a tiny copy in its real on-disk layout and
label encoding (tests/helpers/ovss8_fixtures.py), read back to the exact labels it wrote; the Context
conversion from trainval_merged.json; the class-name files; the errors naming the folder and what
it lacks."""

import json

import numpy as np
import pytest
from PIL import Image

from helpers.ovss8_fixtures import (
    COCO_IDS,
    write_ade,
    write_cityscapes,
    write_coco,
    write_context,
    write_voc,
)
from resireg_train.data.classes import read_class_names
from resireg_train.data.segmentation import build_segmentation_set, check_segmentation_source
from resireg_train.data.specs import dataset_conf


def _labels(ds):
    return {ds.describe(i): ds[i]["label"].numpy() for i in range(len(ds))}


def test_voc_palette_pngs_read_as_class_indices_with_the_255_boundary(tmp_path):
    """VOC's labels are palette PNGs: read as their indices (never colours), 255 kept for the
    metric to ignore; VOC21 scores 21 classes, VOC20 the same files with reduce_zero_label."""
    root = tmp_path / "VOC2012"
    written = write_voc(root)
    assert Image.open(root / "SegmentationClass" / "2007_000032.png").mode == "P"
    for config, classes, reduce in (("voc21", 21, False), ("voc20", 20, True)):
        ds = build_segmentation_set(dataset_conf(config, path=str(root)), patch_size=16)
        assert len(ds) == 2 and len(ds.classes) == classes and ds.reduce_zero_label is reduce
        for i, (stem, label) in enumerate(written.items()):
            assert ds.describe(i).endswith(f"JPEGImages/{stem}.jpg")
            np.testing.assert_array_equal(ds[i]["label"].numpy(), label)
            assert set(np.unique(label)) >= {0, 15, 255, 20}
    voc21 = build_segmentation_set(dataset_conf("voc21", path=str(root)), patch_size=16)
    assert voc21.classes[0] == "background" and voc21.classes[15] == "person"
    assert "sky" in voc21.names[0] and "person in shirt" in voc21.names[15]
    assert "background" not in voc21.names[0]  # the label, never a prompted name


def test_context_converted_labels_and_the_conversion_from_trainval_merged_json(tmp_path):
    """PC60 reads SegmentationClassContext's 0..59 as stored, PC59 ignores 0; the conversion
    of trainval_merged.json (COCO RLE masks painted in order, the 60 kept ids by rank) writes
    exactly those maps and the split's list."""
    from resireg_train.data.context import convert_context, main

    root = tmp_path / "VOCdevkit" / "VOC2010"
    written = write_context(root)
    for config, count, reduce in (("pc60", 60, False), ("pc59", 59, True)):
        ds = build_segmentation_set(dataset_conf(config, path=str(root)), patch_size=16)
        assert len(ds.classes) == count and ds.reduce_zero_label is reduce
        for i, label in enumerate(written.values()):
            np.testing.assert_array_equal(ds[i]["label"].numpy(), label)
    ds = build_segmentation_set(dataset_conf("pc60", path=str(root)), patch_size=16)
    assert ds.classes[:3] == ("background", "aeroplane", "bag") and ds.classes[-1] == "wood"

    # convert into a copy without the converted files: the same maps, the same list
    fresh = tmp_path / "fresh" / "VOCdevkit"
    (fresh / "VOC2010").mkdir(parents=True)
    (fresh / "VOC2010" / "trainval_merged.json").write_text(
        (root / "trainval_merged.json").read_text()
    )
    assert convert_context(fresh, phases=["val"]) == {"val": 2}
    for stem, label in written.items():
        got = np.asarray(Image.open(fresh / "VOC2010" / "SegmentationClassContext" / f"{stem}.png"))
        np.testing.assert_array_equal(got, label)
        assert set(np.unique(label)) == {0, 5 + list(written).index(stem), 59}
    assert (fresh / "VOC2010" / "ImageSets" / "SegmentationContext" / "val.txt").read_text() == (
        "".join(f"{s}\n" for s in sorted(written))
    )
    # the later annotation wins where two overlap (Detail's getMask paints in order)
    first = next(iter(written.values()))
    assert first[-1, -1] == 59 and first[0, 0] == 5  # wood over bench
    assert main([str(tmp_path / "nowhere")]) == 2  # a missing json: one line, no traceback


def test_coco_stuff_182_to_171_and_coco_object_derived_from_the_stuff_maps(tmp_path):
    """COCO-Stuff: mmseg's *_labelTrainIds.png read as stored equal the raw maps mapped on read
    (182 ids -> 171: 12 -> 11, 26 -> 24, 91 -> 80, 181 -> 170, 255 kept); COCO-Object: things
    -> train id + 1, stuff and unlabelled -> 0, read from the OVSS converter's files or derived."""
    root = tmp_path / "coco_stuff164k"
    written = write_coco(root)
    for config, column, count in (("coco_stuff", 1, 171), ("coco_object", 2, 81)):
        for labels in ("converted", "raw"):
            spec = dataset_conf(config, path=str(root), labels=labels)
            ds = build_segmentation_set(spec, patch_size=16)
            assert len(ds.classes) == count and len(ds) == 2
            for i, (stem, maps) in enumerate(written.items()):
                assert ds.describe(i).endswith(f"{stem}.jpg")
                np.testing.assert_array_equal(
                    ds[i]["label"].numpy(), maps[column], (config, labels)
                )
    raw, stuff, obj = next(iter(written.values()))
    for value, (train, thing) in ((v, t) for v, t in COCO_IDS.items() if t):
        if (raw == value).any():
            assert set(np.unique(stuff[raw == value])) == {train}
            assert set(np.unique(obj[raw == value])) == {thing}


def test_cityscapes_label_ids_map_to_the_train_ids(tmp_path):
    """Cityscapes: *_labelTrainIds.png read as stored equal *_labelIds.png mapped on read (road
    7 -> 0, sidewalk 8 -> 1, car 26 -> 13, bicycle 33 -> 18; unlabeled 0 and parking 9 -> 255)."""
    root = tmp_path / "cityscapes"
    written = write_cityscapes(root)
    for labels in ("converted", "raw"):
        ds = build_segmentation_set(dataset_conf("cityscapes", path=str(root), labels=labels), 16)
        assert len(ds.classes) == 19 and ds.classes[13] == "car"
        for i, (stem, (ids, train)) in enumerate(sorted(written.items())):
            assert ds.describe(i).endswith(f"{stem}_leftImg8bit.png")
            got = ds[i]["label"].numpy()
            np.testing.assert_array_equal(got, train)
            np.testing.assert_array_equal(got[ids == 26], 13)
            np.testing.assert_array_equal(got[(ids == 0) | (ids == 9)], 255)


def test_ade20k_under_the_fields_protocol_reads_the_local_folder(tmp_path):
    root = tmp_path / "ADEChallengeData2016"
    written = write_ade(root)
    spec = dataset_conf("ade20k_ovss8", path=str(root))
    assert (spec["name"], spec["short_side"], spec["slide_crop"], spec["protocol"]) == (
        "ade20k", 336, 224, "ovss8")  # fmt: skip
    ds = build_segmentation_set(spec, patch_size=16)
    assert ds.reduce_zero_label and len(ds.classes) == 150
    for i, label in enumerate(written.values()):
        np.testing.assert_array_equal(ds[i]["label"].numpy(), label)


@pytest.mark.parametrize(
    ("config", "folder", "remove", "message"),
    [
        ("voc21", "VOC2012", None, r"dataset\.path='.*nowhere': no folder .*nowhere \(expected VOCdevkit/VOC2012"),
        ("voc21", "VOC2012", "SegmentationClass", r"no .*VOC2012/SegmentationClass folder \(the SegmentationClass label maps\)"),
        ("voc20", "VOC2012", "ImageSets/Segmentation/val.txt", r"dataset\.split='val': no .*ImageSets/Segmentation/val\.txt"),
        ("pc60", "VOC2010", "SegmentationClassContext/2008_000003.png", r"1 of 2 label maps of val\.txt missing: .*2008_000003\.png"),
        ("coco_stuff", "coco_stuff164k", "annotations/val2017/000000000285_labelTrainIds.png", r"1 of 2 _labelTrainIds\.png label maps missing: .*; run mmsegmentation's .*coco_stuff164k\.py, or set labels=raw"),
        ("coco_object", "coco_stuff164k", "images/val2017", r"no .*coco_stuff164k/images/val2017 folder \(the val2017 images, \*\.jpg\)"),
        ("cityscapes", "cityscapes", "gtFine", r"no .*cityscapes/gtFine/val folder"),
    ],
)  # fmt: skip
def test_a_wrong_folder_is_named_with_what_it_lacks_before_any_model_loads(
    tmp_path, config, folder, remove, message
):
    """The source check resireg-eval runs before the encoder loads names the key, the folder and
    what is missing; the build raises the same."""
    import shutil

    writers = {"VOC2012": write_voc, "VOC2010": write_context, "coco_stuff164k": write_coco,
               "cityscapes": write_cityscapes}  # fmt: skip
    root = tmp_path / folder
    writers[folder](root)
    path = root if remove is not None else tmp_path / "nowhere"
    if remove:
        target = root / remove
        shutil.rmtree(target) if target.is_dir() else target.unlink()
    spec = dataset_conf(config, path=str(path))
    with pytest.raises(FileNotFoundError, match=message):
        check_segmentation_source(spec)
    with pytest.raises(FileNotFoundError, match=message):
        build_segmentation_set(spec, patch_size=16)


def test_class_files_synonyms_counts_and_their_errors(tmp_path):
    """A class file's lines are the classes (label before a colon, else the first name), every
    name prompted; the count must match the labels'; an empty line between classes, or a file
    that does not exist, is an error naming the key and the file."""
    classes, names = read_class_names("voc21")
    assert len(classes) == 21 and classes[20] == "television monitor"
    assert names[20] == ("television monitor", "tv monitor", "monitor", "television", "screen")
    assert [len(read_class_names(n)[0]) for n in ("voc20", "pc60", "pc59", "coco_object",
            "coco_stuff", "cityscapes")] == [20, 60, 59, 81, 171, 19]  # fmt: skip
    mine = tmp_path / "mine.txt"
    mine.write_text("# two classes\ncat, kitty\n\ndog\n")
    with pytest.raises(ValueError, match=r"mine\.txt line 3 holds an empty class name"):
        read_class_names(str(mine))
    with pytest.raises(FileNotFoundError, match=r"dataset\.classes='vocc21': no .*vocc21\.txt "
                       r"\(a name of conf/classes/: \[.*'voc21'"):  # fmt: skip
        read_class_names("vocc21")
    root = tmp_path / "VOC2012"
    write_voc(root)
    mine.write_text("cat, kitty\ndog\n")
    with pytest.raises(ValueError, match=r"dataset\.classes='.*mine\.txt' names 2 classes; VOC "
                       r"labels with reduce_zero_label=False need 21"):  # fmt: skip
        build_segmentation_set(dataset_conf("voc21", path=str(root), classes=str(mine)), 16)


def _digests(folder):
    """``{path: sha256}`` of every file under ``folder``."""
    import hashlib

    return {p.relative_to(folder): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


def test_a_split_list_naming_a_missing_image_or_listing_none_is_one_line_at_resireg_eval(tmp_path):
    """Issue 51, item 8: resireg-eval over a VOC folder whose split list names an image that is
    not there, or lists none, ends in the reader's one line (no traceback), before any model
    loads; the dataset's files and another run's folder are as they were."""
    from helpers.run import run_side_by_side

    roots = {}
    for case in ("missing", "empty"):
        roots[case] = tmp_path / case / "VOC2012"
        write_voc(roots[case])
    (roots["missing"] / "JPEGImages" / "2007_000039.jpg").unlink()
    (roots["empty"] / "ImageSets" / "Segmentation" / "val.txt").write_text("\n \n")
    other = tmp_path / "other_run"
    other.mkdir()
    (other / "results.json").write_text('{"status": "completed"}')
    before = _digests(tmp_path)
    procs = run_side_by_side(*(
        ("resireg-eval", "encoder=clip_vit_b16", "dataset=voc21", f"dataset.path={root}",
         f"hydra.run.dir={tmp_path / 'runs' / case}")
        for case, root in roots.items()
    ), check=False)  # fmt: skip
    expected = {
        "missing": (f"FileNotFoundError: dataset.path='{roots['missing']}': 1 of 2 images listed "
                    f"in val.txt missing: {roots['missing']}/JPEGImages/2007_000039.jpg"),
        "empty": (f"resireg.errors.ConfigError: dataset.split='val': {roots['empty']}/ImageSets/"
                  "Segmentation/val.txt lists no image"),
    }  # fmt: skip
    for (case, line), proc in zip(expected.items(), procs, strict=True):
        assert proc.returncode == 1, proc.stderr[-2000:]
        assert "Traceback" not in proc.stderr + proc.stdout, case
        assert line in proc.stderr.splitlines(), (case, proc.stderr[-2000:])
        record = json.loads((tmp_path / "runs" / case / "results.json").read_text())
        assert record["status"] == "failed" and record["error"] == line
    after = _digests(tmp_path)
    assert {p: d for p, d in after.items() if p.parts[0] != "runs"} == before
