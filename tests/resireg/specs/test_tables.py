"""One contract for every spec table (:class:`resireg.specs.table.SpecTable`): every entry's
code loads, its ``conf/`` files exist and are found by scanning, unknown names are answered
with the closest ones, and each entry's rules refuse what they should."""

from __future__ import annotations

import inspect

import pytest
import torch
import yaml

from resireg.specs.encoders import ENCODER_SPECS
from resireg.specs.metrics import METRIC_SPECS, SCORE_SPECS, direction
from resireg.specs.priors import PRIOR_SPECS
from resireg.specs.table import SpecTable, UnknownNameError, conf_dir
from resireg.specs.text import TEXT_SPECS
from resireg.specs.variants import VARIANT_SPECS
from resireg_train.data.specs import DATASET_SPECS
from resireg_train.evaluation.specs import TASK_SPECS
from resireg_train.report.specs import SECTION_SPECS
from resireg_train.training.specs import TEACHER_SPECS

TABLES = {
    "variants": VARIANT_SPECS,
    "encoders": ENCODER_SPECS,
    "priors": PRIOR_SPECS,
    "metrics": METRIC_SPECS,
    "datasets": DATASET_SPECS,
    "tasks": TASK_SPECS,
    "text towers": TEXT_SPECS,
    "teachers": TEACHER_SPECS,
    "report sections": SECTION_SPECS,
}
try:  # the map sources' table lands with resireg.sources
    from resireg.specs.sources import SOURCE_SPECS

    TABLES["sources"] = SOURCE_SPECS
except ImportError:
    pass


def _takes_what_it_is_given(kind, entry, target):
    """``target``, the loaded code of a ``kind`` entry, is what its call site needs: the base
    class it must have, a signature that binds the call's arguments (a TypeError names the
    argument it does not take)."""
    from resireg.models.interface import DenseEncoder
    from resireg_train.evaluation.base import EvalTask

    def takes(*args, **kwargs):
        inspect.signature(target).bind_partial(*args, **kwargs)

    if kind == "variants":  # resireg.specs.variants.build_variant: load()(**rule keywords)
        assert inspect.isclass(target) and issubclass(target, torch.nn.Module), target
        takes(**dict.fromkeys(entry.params))
    elif kind == "encoders":  # resireg.models.factory.build_encoder: load()(device=, **keys)
        assert not inspect.isclass(target) or issubclass(target, DenseEncoder), target
        takes(device="cpu")
    elif kind == "priors":  # resireg.priors.sam.build_prior: model, device, rule keywords
        takes(**dict.fromkeys(["model", "device", *entry.params]))
    elif kind == "metrics":  # a torchmetrics-style class; (matrix, metric) in the mapping engine
        if entry.unit == "pixel":
            takes(num_classes=2, ignore_index=255)
        else:
            takes(None, entry.name)
    elif kind == "datasets":  # segmentation: load()(name, spec, key, common); ScanNet's
        if "ovss" in entry.tasks:  # builder: build_scannet(spec, patch_size, key)
            takes(entry.kind, {}, "dataset", {})
        else:
            takes({}, 16, "dataset")
    elif kind == "tasks":  # resireg_train.cli.eval: load()(spec, cfg, params, out)
        assert inspect.isclass(target) and issubclass(target, EvalTask), target
        takes(entry, None, {}, None)
    elif kind == "sources":  # resireg_train.jobs.map: load()(**entry.arguments(block))
        takes(**dict.fromkeys([*entry.common, *entry.keys]))
    elif kind in ("text towers", "teachers"):  # the keys of each of its conf/ files:
        for stem in TABLES[kind].configs(entry.kind):  # FrozenTextTower.from_spec: the builder
            path = conf_dir() / TABLES[kind].conf / f"{stem}.yaml"  # (**keys, cache_size=);
            keys = {k: v for k, v in yaml.safe_load(path.read_text()).items()  # build_teacher:
                    if k not in ("kind", "defaults", "cache_size")}  # fmt: skip
            if kind == "text towers":  # load()(device=, **keys)
                takes(**keys, cache_size=None)
            else:
                takes(device="cpu", **keys)
    elif kind == "report sections":  # report.writer: writer(**the inputs it names), detector
        from resireg_train.report.specs import SECTION_INPUTS  # (the same)

        for function in (target, entry.detector()):
            if function is not None:
                takes(**dict.fromkeys(inspect.signature(function).parameters))
                assert set(inspect.signature(function).parameters) <= set(SECTION_INPUTS)
    else:
        raise AssertionError(f"{kind}: no call site known to this test")


@pytest.mark.parametrize("kind", sorted(TABLES))
def test_every_entry_loads_and_its_conf_files_hold_its_kind(kind):
    """Every entry's code loads and takes what the project passes it (its base class where
    the project needs one; a signature that binds the call's arguments)."""
    table = TABLES[kind]
    assert isinstance(table, SpecTable) and len(table) > 0
    for name, entry in table.items():
        assert table.get(name) is entry and table.find(name) is entry
        _takes_what_it_is_given(kind, entry, entry.load())
        if table.conf is None:
            continue
        configs = table.configs(name)
        assert configs, f"{kind}: {name} has no conf/{table.conf}/ file"
        for stem in configs:
            path = conf_dir() / table.conf / f"{stem}.yaml"
            data = yaml.safe_load(path.read_text())
            parents = [p for p in data.get("defaults") or [] if p != "_self_"]
            assert data.get("kind") == name or parents, (path, data.get("kind"))
    if table.conf is not None:  # every file of the folder belongs to one entry
        on_disk = sorted(p.stem for p in (conf_dir() / table.conf).glob("*.yaml")
                         if not p.stem.startswith("_"))  # fmt: skip
        assert sorted(table.all_configs()) == on_disk


@pytest.mark.parametrize("kind", sorted(TABLES))
def test_unknown_names_are_answered_with_the_closest(kind):
    table = TABLES[kind]
    first = table.names()[0]
    typo = first[:-1] + ("x" if first[-1] != "x" else "y")
    with pytest.raises(UnknownNameError) as err:
        table.get(typo)
    text = str(err.value)
    assert f"unknown {table.what} {typo!r}" in text and repr(first) in text
    assert isinstance(err.value, KeyError) and isinstance(err.value, ValueError)
    assert table.find(typo) is None and table.get(typo, None) is None
    assert table.unknown("zzzzzz", setting="x.kind") == (
        f"x.kind='zzzzzz': expected one of {list(table.everything())}"
    )


_BAD = {  # one value each rule must refuse, by (table, entry, key)
    ("variants", "full", "alpha"): -1.0,
    ("variants", "lite", "attention"): "flash",
    ("variants", "calib", "contamination"): 0.9,
    ("priors", "sam2", "points_per_side"): 0,
    ("priors", "sam2", "mask_threshold"): float("nan"),
    ("datasets", "scannet", "voxel_size"): 0,
    ("datasets", "scannet", "metric"): "dice",
}


def _shipped(kind, name, key):
    """The value ``conf/`` ships for ``key`` of entry ``name`` (read here with PyYAML)."""
    if kind == "variants":
        return yaml.safe_load((conf_dir() / "resireg" / "default.yaml").read_text())[name][key]
    folder = {"priors": "prior", "datasets": "dataset"}[kind]
    return yaml.safe_load((conf_dir() / folder / f"{name}.yaml").read_text())[key]


@pytest.mark.parametrize("where", sorted(_BAD))
def test_the_rules_refuse_what_they_should(where):
    """Each rule refuses its bad value and takes the value conf/ ships (so a rule that
    refuses everything fails here too)."""
    kind, name, key = where
    entry = TABLES[kind][name]
    rules = entry.params if hasattr(entry, "params") else entry.rules
    check, expected = rules[key]
    assert isinstance(expected, str) and expected
    assert check(_shipped(kind, name, key)), (where, _shipped(kind, name, key), expected)
    assert not check(_BAD[where]), (where, _BAD[where], expected)


def test_every_scorer_returns_exactly_its_keys():
    """Each scorer of the metric table, on one confusion, returns its keys; the values agree
    with a recomputation (numpy) of IoU and accuracy; every key is a score of the vocabulary."""
    import numpy as np

    cm = np.array([[3, 1, 0], [0, 2, 1]])  # 2 classes (+ "no prediction" column for voxels)
    for name, spec in METRIC_SPECS.items():
        assert set(spec.keys) <= set(SCORE_SPECS) and set(spec.logged) <= set(spec.keys)
        scorer = spec.load()
        if spec.unit == "pixel":
            metric = scorer(num_classes=2, ignore_index=255)
            assert "num_classes" in inspect.signature(scorer).parameters
            pred = torch.tensor([0, 0, 0, 1, 1, 1, 0])
            gt = torch.tensor([0, 0, 0, 0, 1, 1, 255])
            metric.update(pred, gt)
            out = metric.compute()
            tp, union = np.array([3, 2]), np.array([4, 3])
        else:
            out = scorer(torch.tensor(cm), name)
            tp = np.diag(cm[:, :2])
            union = cm.sum(1) + cm[:, :2].sum(0) - tp  # ground truth + false positives
        assert set(out) == set(spec.keys), name
        assert out["iou"] == pytest.approx(list(tp / union)), name
        assert out["miou"] == pytest.approx(float(np.mean(tp / union))), name
    assert direction("val/ovss/ade20k/miou_full") == "max"
    assert direction("val/ovss/ade20k/fmiou_full") == "max"
    assert direction("train/loss") == "min" and direction("epoch") is None
