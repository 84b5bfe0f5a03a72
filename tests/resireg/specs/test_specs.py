"""The spec tables (resireg.specs): one source of each kind's names, classes, rules, defaults.

The tables are compared with what they describe, read independently: the classes' signatures
(``inspect``), the composed ``conf/`` (Hydra's compose API), the ``conf/`` files on disk, and a
hand-written list of values each parameter must accept or refuse (the documented ranges of
docs/method.md#resireg), run through both readers of a rule: the class and the config check.
"""

import inspect
import math
import shutil

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from resireg.errors import ConfigError
from resireg.specs import load
from resireg.specs.encoders import ENCODER_SPECS
from resireg.specs.variants import PARAM_VARIANTS, VARIANT_SPECS, VARIANTS
from resireg_train.checks.eval import sweep_config_errors, validate_eval
from resireg_train.config.paths import CONFIG_DIR


def _eval_config(*overrides):
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose("eval", overrides=["model_path=x", *overrides])


def test_each_variant_entry_names_its_class_its_keywords_and_conf_defaults():
    """The table's classes load; their keywords are exactly the table's rules and the
    ``conf/resireg/default.yaml`` block's keys, and every keyword default equals conf/'s
    (``n_components=None``: tied, issue 23)."""
    cfg = _eval_config()
    cfg = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in ("variants", *VARIANTS)
           if k in cfg}  # fmt: skip
    assert VARIANTS == ("bb", "calib", "lite", "full")  # the paper's Table 1 order
    assert cfg["variants"] and all(v in VARIANTS for v in cfg["variants"])
    # the variants with a block of parameters (resireg-map's params, the callback's settings)
    assert PARAM_VARIANTS == tuple(n for n in VARIANTS if n in cfg) == ("calib", "lite", "full")
    for name, spec in VARIANT_SPECS.items():
        cls = spec.load()
        assert cls.__name__ == spec.target.rpartition(":")[2]
        keywords = {k: p.default for k, p in inspect.signature(cls).parameters.items()
                    if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)}  # fmt: skip
        assert set(keywords) == set(spec.params), name
        if not spec.params:
            assert name not in cfg
            continue
        assert set(cfg[name]) == set(spec.params), name  # conf/ holds every default
        assert spec.defaults == f"conf/resireg/default.yaml:{name}"
        for key, default in keywords.items():
            default = list(default) if isinstance(default, tuple) else default  # YAML: a list
            assert default == cfg[name][key], (name, key, default, cfg[name][key])


# (variant, parameter) -> values accepted, values refused (docs/method.md#resireg)
_VALUES = {
    ("full", "n_prototypes"): ([1, 36, "auto", "elbo"], [0, -2, 2.5, True, "36"]),
    ("full", "elbo_candidates"): ([None, [24, 36], [8]], [[], [0], [2.5], "24", 24]),
    ("full", "n_components"): ([None, 1, 24], [0, 2.0, False]),
    ("full", "alpha"): ([0.1, 5, 5.0], [0, -1.0, math.inf, math.nan, True, "5"]),
    ("full", "tau"): ([0, 0.5, 1], [-0.1, 1.5, math.nan, True]),
    ("full", "upscale"): ([1, 2], [0, 1.5]),
    ("full", "seed"): ([0, 7, -1], [0.5, True, "1"]),
    ("full", "max_iter"): ([1, 100], [0, 10.0]),
    ("full", "tol"): ([0, 1e-4, 0.01], [-1e-4, math.inf, math.nan, True, "1e-4"]),
    ("full", "elbo_max_points"): ([1, 4096], [0, 2.5, True]),
    ("full", "elbo_stop_after"): ([None, 1, 2], [0, 1.5, True]),
    ("full", "elbo_tol"): ([1e-3, 1], [0, -1.0, math.inf, True]),
    ("lite", "alpha"): ([10.0], [0.0, -1, math.inf]),
    ("lite", "tau"): ([0.0, 1.0], [1.01]),
    ("lite", "upscale"): ([1, 3], [0, True]),
    ("lite", "attention"): (["auto", "sdpa", "factorised"], ["flash", None]),
    ("calib", "n_neighbors"): ([1, 30], [0, 2.5, True]),
    ("calib", "contamination"): ([0, 0.05, 0.5], [-0.01, 0.6, math.nan]),
    ("calib", "threshold"): ([0, 0.4, 1], [-0.1, 1.5, "0.4"]),
}


@pytest.mark.parametrize(("variant", "key"), sorted(_VALUES))
def test_one_rule_per_parameter_read_by_the_class_and_the_config_check(variant, key):
    """Each value is accepted or refused alike by the class (``ValueError`` naming the
    keyword) and by resireg-eval's config check (``<variant>.<key>=<value>``)."""
    good, bad = _VALUES[(variant, key)]
    cls = VARIANT_SPECS[variant].load()
    base = {"encoder": {"kind": "clip", "name": "c", "third_party": True}, "variants": ["bb"]}
    for value in good:
        if value != "auto":  # "auto" resolves a heuristic file (tests/resireg/method/test_reconstruct.py)
            cls(**{key: value})
        validate_eval({**base, variant: {key: value}})
    for value in bad:
        with pytest.raises(ValueError, match=rf"^{key} must be "):
            cls(**{key: value})
        with pytest.raises(ConfigError, match=rf"{variant}\.{key}="):
            validate_eval({**base, variant: {key: value}})
    assert set(_VALUES) == {(n, k) for n, s in VARIANT_SPECS.items() for k in s.params} - {
        ("full", "heuristic")
    }


def test_each_encoder_entry_names_its_builder_and_its_conf_files():
    """Every built-in kind's builder loads and takes ``device`` (and no config key); the
    table's configurations are exactly the ``conf/encoder/`` files, each of its kind."""
    on_disk = {p.stem: OmegaConf.load(p).kind for p in (CONFIG_DIR / "encoder").glob("*.yaml")}
    assert sorted(ENCODER_SPECS.all_configs()) == sorted(on_disk)
    for kind, spec in ENCODER_SPECS.items():
        builder = spec.load()
        parameters = set(inspect.signature(builder).parameters)
        assert "device" in parameters and "config_key" not in parameters, kind
        assert all(on_disk[name] == kind for name in spec.configs), kind
    assert [k for k, s in ENCODER_SPECS.items() if s.needs_model_path] == ["resireg_vlm"]
    with pytest.raises(ValueError, match="'package.module:attribute'"):
        load("resireg.method.variants.BackboneOnly")


def test_the_config_check_names_a_sweep_that_types_or_misspells_an_encoder(tmp_path):
    """``sweep_config_errors``: today's conf/ passes; a copy whose Table 1 sweep types its
    encoder list (instead of generating it from the table), whose Table 2 sweep misspells one,
    with a bad variant list, and an encoder file of an unknown kind is reported, each naming the
    file and the key. A new file of a known kind needs no list: scanning finds it."""
    assert sweep_config_errors(CONFIG_DIR) == []
    conf = tmp_path / "conf"
    shutil.copytree(CONFIG_DIR, conf)
    table1 = OmegaConf.load(conf / "sweep" / "table1.yaml")
    table1.hydra.sweeper.params.encoder = ",".join(ENCODER_SPECS.all_configs()[:-1])
    table1.variants = ["bb", "fulll"]
    OmegaConf.save(table1, conf / "sweep" / "table1.yaml")
    table2 = OmegaConf.load(conf / "sweep" / "table2.yaml")
    table2.hydra.sweeper.params.encoder = ",".join([*ENCODER_SPECS.all_configs(), "radio_v5"])
    OmegaConf.save(table2, conf / "sweep" / "table2.yaml")
    (conf / "encoder" / "clip_extra.yaml").write_text("name: clip_extra\nkind: clip\n")
    (conf / "encoder" / "clop.yaml").write_text("name: clop\nkind: clop\n")
    errors = sweep_config_errors(conf)
    assert len(errors) == 5, errors
    assert any(e.startswith("encoder/clop.yaml: kind='clop': unknown encoder kind 'clop'; "
                            "did you mean 'clip'?") for e in errors)  # fmt: skip
    assert any(e.startswith("sweep/table1.yaml: variants=['bb', 'fulll']") for e in errors)
    assert any(e.startswith("sweep/table1.yaml: hydra.sweeper.params.encoder=") and
               "${resireg_encoders:}" in e for e in errors)  # fmt: skip
    assert any(e.startswith("sweep/table2.yaml") and "${resireg_encoders:}" in e for e in errors)
    assert any(e.startswith("sweep/table2.yaml") and "['radio_v5']" in e for e in errors)
    assert not any("clip_extra" in e for e in errors)


def test_the_sweeps_over_every_encoder_resolve_to_the_table(monkeypatch, tmp_path):
    """Table 1's and Table 2's encoder axis, composed through Hydra, is every configuration the
    encoder table finds by scanning ``conf/encoder/``; a file added there joins the sweep with
    no list to edit."""
    from hydra import compose, initialize_config_dir

    from resireg_train.jobs.resolvers import register_resolvers

    register_resolvers()
    on_disk = sorted(p.stem for p in (CONFIG_DIR / "encoder").glob("*.yaml"))
    for sweep in ("table1", "table2"):
        with initialize_config_dir(str(CONFIG_DIR), version_base=None):
            cfg = compose("eval", [f"sweep={sweep}"], return_hydra_config=True)
        axis = cfg.hydra.sweeper.params.encoder.split(",")
        assert sorted(axis) == on_disk, sweep
    conf = tmp_path / "conf"
    shutil.copytree(CONFIG_DIR, conf)
    (conf / "encoder" / "clip_extra.yaml").write_text("name: clip_extra\nkind: clip\n")
    monkeypatch.setenv("RESIREG_CONFIG_DIR", str(conf))
    assert "clip_extra" in ENCODER_SPECS["clip"].configs
    assert ENCODER_SPECS.all_configs().count("clip_extra") == 1


_TOY_SPEC = """
from resireg.specs.encoders import EncoderSpec

SPEC = EncoderSpec("toy", "toy_encoder:ToyEncoder")
"""

_TOY_ENCODER = '''
import zlib

import torch
import torch.nn.functional as F
from torch import nn

from resireg.models import DenseEncoder, DenseOutput, InputRule


class ToyEncoder(DenseEncoder):
    """A patch-8 conv stem (intermediates) and a 1x1 conv (language tokens); text queries
    are fixed random directions keyed by the text."""

    def __init__(self, width=16, dim=24, device=None):
        super().__init__()
        torch.manual_seed(0)
        self.stem = nn.Conv2d(3, width, 8, stride=8)
        self.head = nn.Conv2d(width, dim, 1)
        self.dim = dim
        self.to(device or "cpu")

    @property
    def input_rule(self):
        return InputRule(8, (0.5, 0.5, 0.5), (0.25, 0.25, 0.25))

    def encode(self, images):
        x = self.stem(images)
        return DenseOutput(x, self.head(F.gelu(x)), None)

    def encode_text(self, texts):
        g = [torch.Generator().manual_seed(zlib.crc32(t.encode())) for t in texts]
        rows = [torch.randn(self.dim, generator=gen) for gen in g]
        return F.normalize(torch.stack(rows), dim=-1).to(self.stem.weight.device)
'''


@pytest.mark.slow
def test_an_encoder_registered_through_the_table_runs_through_resireg_eval(tmp_path):
    """The recipe of docs/architecture.md#spec-tables from outside the project: one module (a tiny
    real DenseEncoder), one table entry (an EncoderSpec, registered by an entry point of an
    installed distribution) and one conf/encoder/ file run ``resireg-eval`` on the synthetic
    set; without the entry (in this process) the config check refuses the kind, naming the key. The parameter
    count recorded is compared with the module's own, built here."""
    import json
    import os
    import sys

    from helpers.run import run

    site = tmp_path / "site"
    (site / "resireg_toy-0.1.dist-info").mkdir(parents=True)
    (site / "toy_spec.py").write_text(_TOY_SPEC)
    (site / "toy_encoder.py").write_text(_TOY_ENCODER)
    conf = tmp_path / "conf" / "encoder"
    conf.mkdir(parents=True)
    (conf / "toy.yaml").write_text("name: toy\nkind: toy\nthird_party: true\nwidth: 16\n")
    args = ["resireg-eval", "encoder=toy", "dataset=synthetic", "dataset.size=4",
            "num_workers=0", "batch_size=2", "variants=[bb,lite,full]", "full.n_prototypes=4",
            f"hydra.searchpath=[file://{tmp_path / 'conf'}]"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), *sys.path])}
    with pytest.raises(ConfigError, match=r"encoder\.kind='toy': expected one of"):
        validate_eval({"encoder": {"kind": "toy", "name": "toy", "third_party": True}})
    (site / "resireg_toy-0.1.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: resireg-toy\nVersion: 0.1\n"
    )
    (site / "resireg_toy-0.1.dist-info" / "entry_points.txt").write_text(
        "[resireg.encoders]\ntoy = toy_spec:SPEC\n"
    )
    run(*args, f"hydra.run.dir={tmp_path / 'out'}", env=env)
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert results["status"] == "completed"
    sys.path.insert(0, str(site))
    try:
        from toy_encoder import ToyEncoder
    finally:
        sys.path.remove(str(site))
    expected = sum(p.numel() for p in ToyEncoder(width=16).parameters())
    assert results["encoder"] == {"name": "toy", "kind": "toy", "third_party": True,
                                  "parameters": expected}  # fmt: skip
    for variant in ("bb", "lite", "full"):
        assert 0.0 <= results["final"][f"val/ovss/synthetic/miou_{variant}"] <= 1.0


def _compose_train(*overrides):
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose("train", overrides=list(overrides))


def test_library_defaults_equal_the_conf_files_they_stand_for():
    """conf/ is the source of defaults; the Python API's own defaults equal it: the caption
    cache of every text tower (``conf/model/text/*.yaml``), SAM 2's automatic-mask settings
    (``conf/prior/sam2.yaml``, composed as resireg-eval does) and the evaluation engines' batch
    size and temperature (``conf/eval.yaml``)."""
    from resireg.models.vlm.text import CAPTION_CACHE_SIZE, FrozenTextTower
    from resireg.priors.sam import SamPrior
    from resireg.specs.priors import SAM_DEFAULTS, SAM_MODEL

    for path in sorted((CONFIG_DIR / "model" / "text").glob("*.yaml")):
        assert OmegaConf.load(path).cache_size == CAPTION_CACHE_SIZE, path.name
    for factory in (FrozenTextTower, FrozenTextTower.tiny, FrozenTextTower.pretrained):
        assert inspect.signature(factory).parameters["cache_size"].default == CAPTION_CACHE_SIZE
    prior = OmegaConf.to_container(_eval_config("prior=sam2").prior, resolve=True)
    signature = inspect.signature(SamPrior).parameters
    keys = set(prior) - {"kind", "device"}
    assert keys == {"model", *SAM_DEFAULTS}
    assert {k: signature[k].default for k in keys} == {k: prior[k] for k in keys}
    assert prior["model"] == SAM_MODEL
    # the evaluation engines' pass settings (conf/eval.yaml)
    from resireg_train.evaluation.mapping.engine import MappingEngine
    from resireg_train.evaluation.ovss.engine import OVSSEngine

    evaluation = _eval_config()
    for engine in (OVSSEngine, MappingEngine):
        signature = inspect.signature(engine).parameters
        assert signature["batch_size"].default == evaluation.batch_size, engine
        assert signature["num_workers"].default == evaluation.num_workers == 2, engine
    assert inspect.signature(OVSSEngine).parameters["temperature"].default == evaluation.temperature
    # the training callback's (conf/callbacks/default.yaml) and the caption data module's
    # (conf/data/stage1.yaml, the default data=): every keyword default equals the composed key
    from resireg_train.data.captions import CaptionDataModule
    from resireg_train.evaluation.ovss.callback import ReSiRegEval

    train = _compose_train()
    for cls, node in ((ReSiRegEval, train.callbacks.resireg_eval), (CaptionDataModule, train.data)):
        node = OmegaConf.to_container(node, resolve=True)
        defaults = {k: p.default for k, p in inspect.signature(cls).parameters.items()
                    if p.default is not p.empty and k in node and k != "seed"}  # fmt: skip
        assert defaults and defaults == {k: node[k] for k in defaults}, cls.__name__
    assert train.data.num_workers == "auto" and train.callbacks.resireg_eval.num_workers == 2


def test_every_dataset_entry_holds_its_kinds_keys_and_conf_is_their_one_source():
    """The dataset table (resireg_train.data.specs): every conf/dataset/ file, composed as
    resireg-eval composes it, holds exactly the keys of its kind's entry and is among the
    entry's configs (each named config a file); the task of its kind is its task table's. No
    builder has a default of its own: a synthetic entry without one of its keys is an error
    naming ``dataset.<key>`` (the builder, then the config check), not a silent value (the
    Python builder's were 64 images of 128 x 128 at short side 576; conf's are 32 of 72 x 88 at
    64). The caption sources of conf/data/ hold every key their kind requires."""
    from resireg_train.data.segmentation import build_segmentation_set
    from resireg_train.data.specs import CAPTION_SOURCE_KEYS, DATASET_SPECS, dataset_conf
    from resireg_train.evaluation.specs import TASK_SPECS

    files = sorted((CONFIG_DIR / "dataset").glob("*.yaml"))
    assert {p.stem for p in files} == {c for d in DATASET_SPECS.values() for c in d.configs}
    for path in files:
        entry = OmegaConf.to_container(_eval_config(f"dataset={path.stem}").dataset, resolve=False)
        spec = DATASET_SPECS[entry["kind"]]
        assert path.stem in spec.configs and set(entry) == set(spec.keys), path.name
        assert entry == dataset_conf(path.stem), path.name  # read outside Hydra alike
        assert all(t in TASK_SPECS for t in spec.tasks), path.name
    # a ScanNet entry's keys include every one its reader and the 3D task read
    from resireg_train.data.scannet import READER_KEYS
    from resireg_train.evaluation.mapping.engine import TASK_KEYS

    assert {*READER_KEYS, *TASK_KEYS} <= set(DATASET_SPECS["scannet"].keys)
    synthetic = dataset_conf("synthetic")
    assert (synthetic["size"], synthetic["image_size"], synthetic["short_side"]) == (
        32, [72, 88], 64,
    )  # fmt: skip
    assert len(build_segmentation_set(synthetic, 16)) == 32
    for key in DATASET_SPECS["synthetic"].keys:
        if key == "name":
            continue
        partial = {k: v for k, v in synthetic.items() if k != key}
        with pytest.raises((ValueError, KeyError), match=rf"dataset\.{key}"):
            build_segmentation_set(partial, 16)
        if key != "kind":
            with pytest.raises(ConfigError, match=rf"dataset: no dataset\.{key}\b"):
                validate_eval({"dataset": partial})
    train = OmegaConf.load(CONFIG_DIR / "data" / "synthetic.yaml")
    sources = {f"synthetic/{n}": s for n, s in train.sources.items()}
    for stage in ("stage1", "stage2"):
        cfg = _compose_train(f"data={stage}")
        sources.update({f"{stage}/{n}": s for n, s in cfg.data.sources.items()})
    for name, source in sources.items():
        kind = CAPTION_SOURCE_KEYS["synthetic" if source.path == "synthetic" else "hub"]
        assert set(kind["required"]) <= set(source), name
        assert set(source) <= {*kind["required"], *kind["optional"]}, name


def test_the_training_module_has_no_default_that_shadows_conf():
    """``ResiregModule``'s keywords are the ``model`` group's keys; those with a Python default
    (``intermediate_layer``) equal the composed config's, the training settings (loss scales
    and warm-ups, optimizer, schedule, logit scale, teacher) have none: a Python caller names
    them, Hydra passes conf/model/vlm25m.yaml's (distill 0.1 after 8 warm-up epochs, ...)."""
    from resireg_train.training.module import ResiregModule

    model = _compose_train().model
    params = inspect.signature(ResiregModule).parameters
    assert set(params) <= set(model)
    defaults = {k: p.default for k, p in params.items() if p.default is not p.empty}
    # optimizer=None: not given (a module restored from a checkpoint, which cannot train)
    assert defaults == {"intermediate_layer": None, "optimizer": None}
    assert model.intermediate_layer is None and model.optimizer.lr > 0
    with pytest.raises(ValueError, match=r"model\.loss\.distill\.warmup_epochs"):
        ResiregModule({}, {}, {}, teacher=None, optimizer=None, scheduler={"min_lr": 0.0},
                      loss={"contrastive": {"scale": 1.0, "warmup_epochs": 0},
                            "distill": {"scale": 0.0}},
                      logit_scale={"init": 1.0, "max": 2.0}, steps_per_epoch=1)  # fmt: skip
