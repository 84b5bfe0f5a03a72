"""The old import paths of this release's moves keep working for one release: each name comes
from its new home, with a ``DeprecationWarning`` naming it (CHANGELOG.md, "Deprecated")."""

from __future__ import annotations

import importlib
import warnings

import pytest

MOVED = [  # (old module, name, new module)
    ("resireg.variant_names", "parse_variant", "resireg.specs.variants"),
    ("resireg.priors.settings", "SAM_RULES", "resireg.specs.priors"),
    ("resireg.models.encoder", "DenseEncoder", "resireg.models.interface"),
    ("resireg.models.encoders", "build_encoder", "resireg.models.factory"),
    ("resireg.deploy.card", "model_card", "resireg.models.vlm.card"),
    ("resireg.cluster", "kmeans", "resireg.method.kmeans"),
    ("resireg.cluster", "pca", "resireg.method.pca"),
    ("resireg.cluster", "elbo_prototype_count", "resireg.method.elbo"),
    ("resireg.sources", "export_source_problem", "resireg.specs.exports"),
    ("resireg_train.data.rgbd", "RGBDFrame", "resireg.sources.frames"),
    ("resireg_train.data.rosbag", "BagSource", "resireg.sources.rosbag"),
    ("resireg_train.data.tum", "TumSource", "resireg.sources.tum"),
    ("resireg_train.evaluation.mapping.metric", "scores", "resireg.mapping.metric"),
    ("resireg_train.protocol", "protocol_record", "resireg_train.evaluation.protocol"),
    ("resireg_train.cli.task", "run_task", "resireg_train.cli.job"),
    ("resireg_train.evaluation.cache", "weights_fingerprint", "resireg.models.factory"),
]
RENAMED = [  # (module, old name, new name)
    ("resireg_train.evaluation.ovss.engine", "OVSSTask", "OVSSEngine"),
    ("resireg_train.evaluation.mapping.engine", "MappingTask", "MappingEngine"),
    ("resireg_train.evaluation.mapping.engine", "MappingProtocol", "MappingSettings"),
]


@pytest.mark.parametrize(("old", "name", "new"), MOVED)
def test_a_moved_name_still_imports_with_a_warning(old, name, new):
    module = importlib.import_module(old)
    with pytest.warns(DeprecationWarning, match=new.replace(".", r"\.")):
        found = getattr(module, name)
    assert found is getattr(importlib.import_module(new), name)


@pytest.mark.parametrize(("module", "old", "new"), RENAMED)
def test_a_renamed_class_still_imports_with_a_warning(module, old, new):
    loaded = importlib.import_module(module)
    with pytest.warns(DeprecationWarning, match=new):
        assert getattr(loaded, old) is getattr(loaded, new)


def test_the_new_homes_import_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        for new in {n for _, _, n in MOVED} | {m for m, _, _ in RENAMED}:
            importlib.import_module(new)
