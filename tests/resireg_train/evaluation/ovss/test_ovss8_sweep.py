"""`resireg-eval sweep=ovss8` end to end: the eight benchmarks written in their real layouts
(tests/helpers/ovss8_fixtures.py) under one paths.data_dir, a tiny export scored with BB, Calib, Lite
and Full on each, every figure in the job's tracker (tracker=csv) and in `resireg-report`'s
ovss8 table, beside the published peers of conf/paper/ovss8.yaml."""

import csv
import json
import re

import pandas as pd
import pytest
import yaml

from helpers.ovss8_fixtures import write_all
from helpers.run import report, run
from resireg_train.config.paths import CONFIG_DIR


def test_the_sweep_lists_the_data_files_benchmarks():
    """conf/sweep/ovss8.yaml's dataset axis is the data file's eight configs, in its order."""
    sweep = yaml.safe_load((CONFIG_DIR / "sweep" / "ovss8.yaml").read_text())
    data = yaml.safe_load((CONFIG_DIR / "paper" / "ovss8.yaml").read_text())
    axis = sweep["hydra"]["sweeper"]["params"]["dataset"].split(",")
    assert axis == [b["config"] for b in data["benchmarks"].values()] and len(axis) == 8
    assert sweep["report"] == ["ovss8"] and sweep["variants"] == ["bb", "calib", "lite", "full"]
    for peer in data["peers"]:  # a figure only with its source, tier and group
        source = peer["source"]
        assert peer["tier"] in ("primary", "peer") and peer["group"] in (
            "training-free", "text projection")  # fmt: skip
        assert source["row"] and (
            (source["repository"] and source["path"] and len(source["commit"]) == 40)
            if "repository" in source else (source["document"] and source["table"])
        )  # fmt: skip
        assert set(peer["miou"]) <= set(data["benchmarks"]) and peer["miou"]
    assert all(row["reason"] for row in data["unconfirmed"])


@pytest.mark.slow
def test_ovss8_sweep_scores_eight_benchmarks_and_reports_them_beside_the_peers(
    tmp_path, tiny_export
):
    data, logs = tmp_path / "datasets", tmp_path / "logs"
    write_all(data)
    run("resireg-eval", "sweep=ovss8", f"model_path={tiny_export}", f"paths.data_dir={data}",
        f"paths.log_dir={logs}", "num_workers=0", "tracker=csv", "full.n_prototypes=4",
        "calib.n_neighbors=3", "dataset.short_side=48", "dataset.slide_crop=32",
        "dataset.slide_stride=16", "dataset.templates=simple_imagenet", timeout=900)  # fmt: skip
    (sweep,) = (logs / "ovss8" / "multirun").iterdir()
    said = report(sweep)
    assert "8 jobs, 8 completed" in said and "ovss8_md" in said

    expected, tracked, records = {}, {}, {}
    for job in sorted(p for p in sweep.iterdir() if (p / "results.json").is_file()):
        record = json.loads((job / "results.json").read_text())
        protocol = record["protocol"]
        assert protocol["name"] == "ovss8" and record["images"] == 2
        # open_clip's 7 simple templates (9 of this test's 22 s went to prompting the eight
        # benchmarks' names with the protocol's 80)
        assert protocol["settings"]["templates"] == "open_clip SIMPLE_IMAGENET_TEMPLATES (7)"
        assert protocol["settings"]["slide_crop"] == 32 and protocol["settings"]["upsample"] == (
            "bilinear")  # fmt: skip
        name = record["params"]["dataset"]["name"]
        records[name] = record
        expected[name] = {k.rsplit("_", 1)[1]: 100 * v for k, v in record["final"].items()
                          if "/miou_" in k}  # fmt: skip
        with open(job / "metrics.csv", newline="") as f:
            (row,) = list(csv.DictReader(f))
        tracked[name] = {k: float(v) for k, v in row.items() if k.startswith("val/ovss/")}
        assert {k: v for k, v in record["final"].items()} == pytest.approx(tracked[name])
    assert sorted(expected) == sorted(["voc21", "pc60", "coco_object", "voc20", "pc59",
                                       "coco_stuff", "cityscapes", "ade20k"])  # fmt: skip
    for name in ("voc21", "pc60", "coco_object"):  # the with-background sets' rule
        assert records[name]["protocol"]["settings"]["background_threshold"] == 0.1
    assert records["voc20"]["protocol"]["settings"]["background_threshold"] is None
    assert records["coco_stuff"]["protocol"]["settings"]["classes"] == "coco_stuff (171)"
    model = records["voc21"]["encoder"]["name"]

    table = pd.read_csv(sweep / "ovss8.csv")
    labels = {
        "voc21": "VOC21",
        "pc60": "PC60",
        "coco_object": "Object",
        "voc20": "VOC20",
        "pc59": "PC59",
        "coco_stuff": "Stuff",
        "cityscapes": "City",
        "ade20k": "ADE",
    }
    assert list(table.columns) == ["model", "variant", *labels.values(), "Avg", "benchmarks",
                                   "group", "tier", "source"]  # fmt: skip
    ours = table[table["model"] == model].set_index("variant")
    assert list(ours.index) == ["BB", "Calib", "Lite", "Full"]
    for variant, short in (("BB", "bb"), ("Calib", "calib"), ("Lite", "lite"), ("Full", "full")):
        cells = [expected[name][short] for name in labels]
        assert [ours.loc[variant, c] for c in labels.values()] == pytest.approx(cells)
        assert ours.loc[variant, "Avg"] == pytest.approx(sum(cells) / 8)
        assert ours.loc[variant, "source"] == "this run, protocol ovss8"
    naclip = table[table["variant"] == "official repository, default setup (PAMR on)"].iloc[0]
    assert naclip["model"] == "NACLIP (CLIP ViT-B/16)" and naclip["tier"] == "primary"
    assert naclip["VOC21"] == 64.07 and naclip["Avg"] == pytest.approx(42.455)
    assert naclip["source"].startswith("published, not rerun: sinahmr/NACLIP README.md")
    text = (sweep / "ovss8.md").read_text()
    assert re.search(rf"\| {model}\s+\| Full\s+\|", text)
    assert "published, not rerun [4]" in text and "## Sources" in text
    assert "4. (primary) sinahmr/NACLIP README.md at 0cac3a6" in text
    assert "Protocol (jobs" in text and "ovss8: short_side=48" in text
