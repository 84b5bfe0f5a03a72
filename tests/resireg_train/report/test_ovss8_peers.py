"""The published peers of `resireg-report`'s ovss8 table (conf/paper/ovss8.yaml): the figures
this test states, as read from each peer's source (Trident's and CASS's tables, Talk2DINO's
project page, FreeCP's README, ProxyCLIP as Trident quotes it), shown with their tier, the rows
with fewer than eight benchmarks marked, the peers that learn a text projection in a table of
their own; and a data file with a wrong peer row refused on one line naming the row, before
anything is written."""

import hashlib
import math
import re

import pandas as pd
import pytest
import yaml

from helpers.sweeps import make_job
from resireg_train.cli import report as report_cli
from resireg_train.config.paths import CONFIG_DIR
from resireg_train.report import ovss8, report

LABELS = ["VOC21", "PC60", "Object", "VOC20", "PC59", "Stuff", "City", "ADE"]
ENCODER = {"name": "clip_vit_b16", "kind": "clip", "third_party": True, "parameters": 150e6}
# (model, variant): tier, group and the eight figures in LABELS' order (None: not printed), as
# this test's author read them from the sources the data file names
EXPECTED = {
    ("Trident (CLIP ViT-B/16 + DINO ViT-B/16 + SAM ViT-B)", "paper (ICCV 2025)"):
        ("primary", "training-free", [67.1, 38.6, 41.1, 84.5, 42.2, 28.3, 42.9, 21.9]),
    ("Trident (OpenCLIP ViT-H/14 + DINO + SAM)", "paper (ICCV 2025)"):
        ("primary", "training-free", [70.8, 40.1, 42.2, 88.7, 44.3, 28.6, 47.6, 26.7]),
    ("CASS (CLIP ViT-B/16 + DINO ViT-B/8)", "paper (CVPR 2025)"):
        ("primary", "training-free", [65.8, 36.7, 37.8, 87.8, 40.2, 26.7, 39.4, 20.4]),
    ("ClearCLIP (CLIP ViT-B/16)", "paper (ECCV 2024)"):
        ("peer", "training-free", [51.8, 32.6, 33.0, 80.9, 35.9, 23.9, 30.0, 16.7]),
    ("ProxyCLIP (CLIP ViT-B/16 + DINO ViT-B/8)", "paper (ECCV 2024), as its peers quote it"):
        ("peer", "training-free", [61.3, 35.3, 37.5, 80.3, 39.1, 26.5, 38.1, 20.2]),
    ("Talk2DINO (DINOv2 ViT-B/14 (reg) + CLIP text)", "without mask refinement (ICCV 2025)"):
        ("primary", "text projection", [61.5, 35.1, 41.0, 87.1, 39.8, 28.1, 36.6, 21.1]),
    ("Talk2DINO (DINOv2 ViT-B/14 (reg) + CLIP text)", "with mask refinement (ICCV 2025)"):
        ("primary", "text projection", [65.8, 37.7, 45.1, 88.5, 42.4, 30.2, 38.1, 22.5]),
    ("dino.txt (DINOv2 ViT-L/14 (reg) + dino.txt text encoder)",
     "as Talk2DINO quotes it (no-background benchmarks only)"):
        ("peer", "text projection", [None, None, None, 62.1, 30.9, 20.9, 32.1, 20.6]),
}  # fmt: skip


@pytest.fixture
def sweep(tmp_path):
    """Two completed jobs of sweep=ovss8 (VOC21 and ADE20K), as Hydra and run_task leave them."""
    folder = tmp_path / "ovss8"
    for n, (name, config) in enumerate((("voc21", "voc21"), ("ade20k", "ade20k_ovss8"))):
        final = {
            f"val/ovss/{name}/miou_{v}": 0.25 + 0.125 * i for i, v in enumerate(("bb", "full"))
        }
        make_job(folder, n, {"sweep": "ovss8", "dataset": config},
                 {"status": "completed", "final": final, "encoder": ENCODER,
                  "protocol": {"name": "ovss8", "settings": {"short_side": 336}},
                  "params": {"dataset": {"name": name}, "variants": ["bb", "full"],
                             "encoder": ENCODER}})  # fmt: skip
    return folder


def test_the_report_shows_the_confirmed_peers_with_tier_count_and_group(sweep):
    files = report(sweep)
    table = pd.read_csv(files["ovss8_csv"])
    assert list(table.columns) == ["model", "variant", *LABELS, "Avg", "benchmarks", "group",
                                   "tier", "source"]  # fmt: skip
    for (model, variant), (tier, group, figures) in EXPECTED.items():
        (row,) = table[(table["model"] == model) & (table["variant"] == variant)].to_dict("records")
        got = [None if math.isnan(row[c]) else row[c] for c in LABELS]
        assert got == figures and (row["tier"], row["group"]) == (tier, group), model
        printed = [f for f in figures if f is not None]
        assert row["benchmarks"] == len(printed)
        if len(printed) == 8:
            assert row["Avg"] == pytest.approx(sum(printed) / 8)
        else:
            assert math.isnan(row["Avg"])
        assert row["source"].startswith("published, not rerun: ")
    trident = table[table["model"].str.startswith("Trident (CLIP")].iloc[0]
    assert trident["Avg"] == pytest.approx(45.825) and trident["source"].startswith(
        "published, not rerun: YuHengsss/Trident assets/data_result.png at a93b346d1b1dc55b"
    )
    ours = table[table["group"] == "this run"].set_index("variant")
    assert list(ours.index) == ["BB", "Full"] and ours.loc["Full", "VOC21"] == 37.5
    assert ours.loc["Full", "benchmarks"] == 2 and math.isnan(ours.loc["Full", "Avg"])

    text = files["ovss8_md"].read_text()
    first, rest = text.split("## Peers that learn a text projection")
    tables, sources = rest.split("## Sources")
    assert "Trident (CLIP" in first and "ClearCLIP (CLIP ViT-B/16)" in first
    assert "Talk2DINO" not in first and "dino.txt" not in first  # kept apart
    assert "| Talk2DINO (DINOv2 ViT-B/14 (reg) + CLIP text)" in tables
    (dino_line,) = [line for line in tables.splitlines() if line.startswith("| dino.txt")]
    assert "| 5 of 8 " in dino_line and "| peer " in dino_line
    (trident_line,) = [line for line in first.splitlines() if line.startswith("| Trident (CLIP")]
    assert re.search(r"\| 8\s+\| primary\s+\| published, not rerun \[(\d+)\]", trident_line)
    number = re.search(r"\[(\d+)\]", trident_line).group(1)
    assert re.search(rf"^{number}\. \(primary\) YuHengsss/Trident assets/data_result\.png at "
                     r"a93b346d1b1dc55bc6f547da5b7d361ad449ae44: .*'Trident \(Ours\)'", sources,
                     re.MULTILINE)  # fmt: skip
    assert "differs: CASS project page table" in sources  # ProxyCLIP's re-run by CASS, noted
    assert re.search(r"^- RADSeg \(.*\): .*prints no results table", text, re.MULTILINE)


def _digests(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir()
            if p.is_file()}  # fmt: skip


def _trident(data):
    return next(i for i, p in enumerate(data["peers"]) if p["method"] == "Trident")


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda p: p["miou"].update(voc21=123.4), r"miou\.voc21=123\.4: outside 0-100"),
        (lambda p: p["miou"].update(ade20k=-0.5), r"miou\.ade20k=-0\.5: outside 0-100"),
        (lambda p: p["miou"].update(voc2012=67.1),
         r"miou\.voc2012: not a benchmark of the table \(voc21, pc60, coco_object"),
        (lambda p: p.pop("source"), r"no source \(repository \+ path \+ commit, or document"),
        (lambda p: p["source"].pop("commit"),
         r"source names neither repository \+ path \+ commit nor document \+ table"),
        (lambda p: p.pop("tier"), r"tier=None: expected one of \['primary', 'peer'\]"),
        (lambda p: p["miou"].update(ade20k=27.9),  # a misread digit: 21.9
         r"printed_avg=45\.8: the row's figures average 46\.575"),
    ],
)  # fmt: skip
def test_a_wrong_peer_row_is_refused_on_one_line_naming_it_and_nothing_is_lost(
    sweep, tmp_path, monkeypatch, capsys, change, message
):
    report_cli.main([str(sweep)])
    before = _digests(sweep)
    data = yaml.safe_load((CONFIG_DIR / "paper" / "ovss8.yaml").read_text())
    i = _trident(data)
    change(data["peers"][i])
    wrong = tmp_path / "ovss8_wrong.yaml"
    wrong.write_text(yaml.safe_dump(data, sort_keys=False))
    monkeypatch.setattr(ovss8, "OVSS8_FILE", wrong)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        report_cli.main([str(sweep)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1, err
    assert re.fullmatch(
        rf"resireg-report: error: {re.escape(str(wrong))}: peers\[{i}\] \(Trident, CLIP "
        rf"ViT-B/16 \+ DINO ViT-B/16 \+ SAM ViT-B\): .*{message}.*\n", err
    ), err  # fmt: skip
    assert _digests(sweep) == before  # the previous report's files as they were


def test_a_data_file_cut_short_is_one_line_naming_it(sweep, tmp_path, monkeypatch, capsys):
    text = (CONFIG_DIR / "paper" / "ovss8.yaml").read_text()
    cut = tmp_path / "ovss8_cut.yaml"
    cut.write_text(text[: text.index("miou: {voc21: 67.1") + 25])  # inside Trident's figures
    monkeypatch.setattr(ovss8, "OVSS8_FILE", cut)
    with pytest.raises(SystemExit) as exit_:
        report_cli.main([str(sweep)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1, err
    assert re.fullmatch(
        rf"resireg-report: error: {re.escape(str(cut))} line \d+: not YAML .*\n", err
    )
    assert not (sweep / "ovss8.csv").exists()
