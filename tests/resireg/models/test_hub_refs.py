"""Hub code is pinned: each hub encoder's conf names a git ref, torch.hub loads
``"owner/name:<ref>"`` (from its cache here: the fake repositories of ``tests/helpers/fake_hubs/``
at ``<hub>/owner_name_<ref>``, the network failing the test), and results.json records it.

Before, ``torch.hub.load("NVlabs/RADIO", ...)`` (and RADSeg's, DINOv2's) followed each
repository's default branch: the code that ran could change under a run.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir

from helpers.fake_hubs.common import offline_hub
from helpers.fake_hubs.dinotxt import dinotxt_repo
from helpers.fake_hubs.dinov2 import dinov2_repo
from helpers.fake_hubs.radio import radio_repo
from helpers.fake_hubs.radseg import radseg_repo
from resireg.models.hub import PINNED_REFS, check_hub_ref, hub_target
from resireg.models.zoo.dinotxt import DINOTXT_CHECKPOINTS, DinoTxtEncoder
from resireg.models.zoo.otas import OTAS_CHECKPOINTS
from resireg.models.zoo.radio import RADIO_CHECKPOINTS, RadioEncoder
from resireg.models.zoo.radseg import RadSegEncoder
from resireg_train.config.paths import CONFIG_DIR

SHA = re.compile(r"^[0-9a-f]{40}$")
CONF = Path(CONFIG_DIR)
HUB_CONFS = {  # every conf of a hub encoder / teacher, and the repository it loads
    "encoder/radio_v3b_clip.yaml": "NVlabs/RADIO",
    "encoder/radio_v3b_siglip2.yaml": "NVlabs/RADIO",
    "encoder/radio_v4_siglip2.yaml": "NVlabs/RADIO",
    "encoder/radseg.yaml": "RADSeg-OVSS/RADSeg",
    "encoder/dinotxt.yaml": "facebookresearch/dinov2",
    "encoder/otas.yaml": "facebookresearch/dinov2",
    "model/teacher/radseg.yaml": "RADSeg-OVSS/RADSeg",
}


def _conf(name: str) -> dict:
    return yaml.safe_load((CONF / name).read_text())


def _ref(name: str, key: str = "ref") -> str:
    return _conf(name)[key]


@pytest.fixture
def calls(monkeypatch):
    """Every ``torch.hub.load`` call's first argument and ``source``, the real load run."""
    real, seen = torch.hub.load, []

    def load(repo_or_dir, *args, **kwargs):
        seen.append((repo_or_dir, kwargs.get("source", "github")))
        return real(repo_or_dir, *args, **kwargs)

    monkeypatch.setattr(torch.hub, "load", load)
    return seen


def test_every_hub_conf_pins_a_commit_and_the_encoder_table_knows_every_hub_conf():
    for name, repo in HUB_CONFS.items():
        conf = _conf(name)
        assert conf["repo"] == repo and conf["source"] == "github", name
        assert SHA.match(conf["ref"]), (name, conf["ref"])
        assert conf["ref"] == PINNED_REFS[repo], name  # the constructors' default
    for name in ("encoder/radseg.yaml", "model/teacher/radseg.yaml"):
        assert SHA.match(_conf(name)["radio_ref"])
        assert _conf(name)["radio_ref"] == PINNED_REFS["NVlabs/RADIO"]  # one RADIO
    # no other conf loads hub code without a ref
    for path in sorted((CONF / "encoder").glob("*.yaml")) + sorted(
        (CONF / "model" / "teacher").glob("*.yaml")
    ):
        conf = yaml.safe_load(path.read_text())
        if conf.get("source") == "github":
            assert str(path.relative_to(CONF)) in HUB_CONFS, path


def test_hub_target_and_ref_rules():
    assert hub_target("NVlabs/RADIO", "github", "abc123") == "NVlabs/RADIO:abc123"
    assert hub_target("/clones/RADIO", "local", "abc123") == "/clones/RADIO"
    assert hub_target("NVlabs/RADIO", "github", None) == "NVlabs/RADIO"
    for bad in ("", "a b", "main:x", 7):
        with pytest.raises(ValueError, match=r"^ref="):
            check_hub_ref(bad)
        with pytest.raises(ValueError, match=r"^radio_ref="):
            check_hub_ref(bad, "radio_ref")
    with pytest.raises(ValueError, match=r"^repo='NVlabs/RADIO:v1' names a ref"):
        hub_target("NVlabs/RADIO:v1", "github", "abc")


def test_radio_loads_the_pinned_commit_from_the_hub_cache(tmp_path, monkeypatch, calls):
    ref = _ref("encoder/radio_v3b_clip.yaml")
    hub = offline_hub(monkeypatch, tmp_path / "hub", RADIO_CHECKPOINTS.values())
    radio_repo(hub / f"NVlabs_RADIO_{ref}")  # where torch.hub keeps NVlabs/RADIO:<ref>
    enc = RadioEncoder(repo="NVlabs/RADIO", source="github", ref=ref, adaptor="clip")
    assert calls == [(f"NVlabs/RADIO:{ref}", "github")]
    assert enc.hub_ref == f"NVlabs/RADIO:{ref}" and enc.spec()["ref"] == ref
    # a local clone ignores the ref
    calls.clear()
    local = RadioEncoder(repo=radio_repo(tmp_path / "RADIO"), source="local", ref=ref)
    assert calls == [(str(tmp_path / "RADIO"), "local")] and local.hub_ref is None


def test_radseg_pins_its_own_code_and_the_radio_it_loads_itself(tmp_path, monkeypatch, calls):
    ref, radio_ref = _ref("encoder/radseg.yaml"), _ref("encoder/radseg.yaml", "radio_ref")
    hub = offline_hub(monkeypatch, tmp_path / "hub", RADIO_CHECKPOINTS.values())
    radseg_repo(hub / f"RADSeg-OVSS_RADSeg_{ref}")
    radio_repo(hub / f"NVlabs_RADIO_{radio_ref}")  # no NVlabs_RADIO_main: only the pin loads
    before = torch.hub.load
    enc = RadSegEncoder(repo="RADSeg-OVSS/RADSeg", source="github", ref=ref, radio_ref=radio_ref)
    assert [c[0] for c in calls] == [f"RADSeg-OVSS/RADSeg:{ref}", f"NVlabs/RADIO:{radio_ref}"]
    assert enc.hub_ref == f"RADSeg-OVSS/RADSeg:{ref}"
    assert enc.spec()["ref"] == ref and enc.spec()["radio_ref"] == radio_ref
    assert torch.hub.load is before  # the nested rewrite lasted only while RADSeg built


def test_dinov2_encoders_load_the_pinned_commit(tmp_path, monkeypatch, calls):
    from helpers.fake_hubs.dinotxt import DINOTXT_VOCAB
    from helpers.fake_hubs.dinov2 import drop_dinov2_modules, restore_dinov2_modules
    from resireg.models.zoo.otas import OtasEncoder

    ref = _ref("encoder/dinotxt.yaml")
    assert _ref("encoder/otas.yaml") == ref  # one DINOv2
    files = [*DINOTXT_CHECKPOINTS, *OTAS_CHECKPOINTS.values()]
    hub = offline_hub(monkeypatch, tmp_path / "hub", files)
    target = f"facebookresearch/dinov2:{ref}"
    folder = dinotxt_repo(hub / f"facebookresearch_dinov2_{ref}")
    saved = drop_dinov2_modules()
    try:
        enc = DinoTxtEncoder(repo="facebookresearch/dinov2", source="github", ref=ref,
                             vocab=folder / DINOTXT_VOCAB, image_size=None)  # fmt: skip
    finally:
        restore_dinov2_modules(saved)
    assert calls == [(target, "github")] and enc.hub_ref == target
    calls.clear()
    dinov2_repo(tmp_path / "otas_hub" / f"facebookresearch_dinov2_{ref}")
    offline_hub(monkeypatch, tmp_path / "otas_hub", files)
    otas = OtasEncoder(repo="facebookresearch/dinov2", source="github", ref=ref,
                       clip={"weights": None, "image_size": 64}, clip_input_size=64)  # fmt: skip
    assert calls == [(target, "github")] and otas.hub_ref == target
    assert otas.spec()["ref"] == ref


def test_resireg_eval_records_the_pinned_hub_code_in_results_json(tmp_path, monkeypatch, calls):
    from resireg_train.cli.eval import evaluate

    ref = _ref("encoder/radio_v3b_clip.yaml")
    hub = offline_hub(monkeypatch, tmp_path / "hub", RADIO_CHECKPOINTS.values())
    radio_repo(hub / f"NVlabs_RADIO_{ref}")
    out = tmp_path / "eval"
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("eval", overrides=["encoder=radio_v3b_clip", "dataset=synthetic",
                                         "dataset.size=2", "variants=[bb]", "num_workers=0",
                                         "batch_size=2", f"paths.output_dir={out}"])  # fmt: skip
    evaluate(cfg)
    results = json.loads((out / "results.json").read_text())
    assert results["status"] == "completed"
    assert calls == [(f"NVlabs/RADIO:{ref}", "github")]
    assert results["encoder"]["hub_ref"] == f"NVlabs/RADIO:{ref}"
    assert results["params"]["encoder"]["ref"] == ref
