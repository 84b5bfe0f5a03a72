"""results.json is strict JSON: non-finite values are written as null, listed and explained."""

import json
import math

import pytest

from resireg_train.record.run_record import NON_FINITE, RunRecord


def _strict_load(text):
    """``json.loads`` that rejects NaN / Infinity as RFC 8259 (and jq, JSON.parse) do."""

    def refuse(name):
        raise ValueError(f"not strict JSON: {name}")

    return json.loads(text, parse_constant=refuse)


def _resolve(document, pointer):
    """RFC 6901 by hand (independent of the code under test): ~1 is /, ~0 is ~."""
    node = document
    for token in pointer.split("/")[1:]:
        token = token.replace("~1", "/").replace("~0", "~")
        node = node[int(token)] if isinstance(node, list) else node[token]
    return node


def test_non_finite_values_become_null_with_the_reason_and_read_back_as_numbers(tmp_path):
    nan, inf = float("nan"), float("inf")
    record = {
        "final": {"val/ovss/ade20k/miou_bb": nan, "val/ovss/ade20k/fmiou_bb": 0.25},
        "per_class_iou": {"bb": {"wall": 0.5, "a~b": nan}},
        "history": [{"epoch": 0, "train/loss": inf}, {"epoch": 1, "train/loss": -inf}],
    }
    RunRecord(tmp_path).update(status="failed", **record)
    text = (tmp_path / "results.json").read_text()
    written = _strict_load(text)  # no bare NaN / Infinity anywhere
    assert written["final"] == {"val/ovss/ade20k/miou_bb": None, "val/ovss/ade20k/fmiou_bb": 0.25}
    assert written["per_class_iou"]["bb"] == {"wall": 0.5, "a~b": None}
    listed = written[NON_FINITE]
    assert "strict JSON has no NaN" in listed["reason"] and "IoU of a class" in listed["reason"]
    assert sorted(listed["NaN"]) == ["/final/val~1ovss~1ade20k~1miou_bb", "/per_class_iou/bb/a~0b"]
    assert listed["Infinity"] == ["/history/0/train~1loss"]
    assert listed["-Infinity"] == ["/history/1/train~1loss"]
    for kind in ("NaN", "Infinity", "-Infinity"):
        assert all(_resolve(written, p) is None for p in listed[kind])

    back = RunRecord.read(tmp_path)
    assert NON_FINITE not in back and back["status"] == "failed"
    assert math.isnan(back["final"]["val/ovss/ade20k/miou_bb"])
    assert math.isnan(back["per_class_iou"]["bb"]["a~b"])
    assert [h["train/loss"] for h in back["history"]] == [inf, -inf]

    # A later merge that fixes a value drops it from the list; the others stay listed.
    RunRecord(tmp_path).update(final={"val/ovss/ade20k/miou_bb": 0.1})
    again = _strict_load((tmp_path / "results.json").read_text())
    assert again[NON_FINITE]["NaN"] == ["/per_class_iou/bb/a~0b"]
    RunRecord(tmp_path).update(per_class_iou={}, history=[])
    assert NON_FINITE not in _strict_load((tmp_path / "results.json").read_text())


def test_a_record_of_finite_values_is_written_unchanged(tmp_path):
    fields = {"status": "completed", "final": {"m": 0.5}, "images": 3, "error": None}
    assert RunRecord(tmp_path).update(**fields) == {**fields}
    assert _strict_load((tmp_path / "results.json").read_text()) == fields
    with pytest.raises(TypeError):  # what JSON cannot hold at all is still an error
        RunRecord(tmp_path).update(final={"m": object()})
