"""The evaluation datasets by ``kind`` (``dataset.kind``, ``conf/dataset/<config>.yaml``): one
entry each, the only place a kind's builder, keys and task are written (docs/architecture.md#spec-tables).

Torch-free, like the spec tables of :mod:`resireg.specs` and the task table
(:mod:`resireg_train.evaluation.specs`): the config check (:func:`resireg_train.checks.eval.validate_eval`)
reads the kinds, their keys and the task that scores each before anything heavy loads; the
task table derives each task's kinds from here (:attr:`resireg_train.evaluation.specs.TaskSpec.
dataset_kinds`); the builders (:func:`resireg_train.data.segmentation.build_segmentation_set`,
:func:`resireg_train.data.scannet.build_scannet`) check an entry's keys with
:func:`dataset_key_errors` and load the entry's builder, named lazily as ``"module:function"``.

``conf/dataset/`` is the one source of a dataset's defaults: an entry holds every key of its
kind (:attr:`DatasetSpec.keys`; a missing one is an error naming ``dataset.<key>``), and
:func:`dataset_conf` reads a ``conf/dataset/`` file for callers outside Hydra (tests,
benchmarks, notebooks), as :meth:`resireg_train.evaluation.mapping.engine.MappingSettings.from_conf` does.

Adding a dataset: one builder (``(name, spec, common) -> SegmentationSet`` for a 2D kind), one
:class:`DatasetSpec` below (its keys, the tasks that score it, the value rules of its keys),
one ``conf/dataset/<name>.yaml`` file with its ``kind`` and every key (found by scanning
``conf/dataset/``). ``resireg-eval dataset=<name>`` then builds and checks it;
``tests/resireg/specs/test_tables.py`` checks the entry against its file. The training captions (``conf/data/``) are not evaluation datasets: their source
keys are :data:`CAPTION_SOURCE_KEYS`, read by :func:`resireg_train.data.caption_sources.
open_caption_source`.

One idea: the dataset table. Every kind's entry sits beside the value rules of its keys (the
ScanNet, posed-frames and segmentation rules), so a kind's keys, rules and tasks are read in
one place, torch-free, by the config check and the builders alike; splitting the rules from the
entries would write a kind in two files.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from resireg.specs.mapping import MAP_RULES
from resireg.specs.metrics import VOXEL_METRICS
from resireg.specs.prompts import TEMPLATE_SET
from resireg.specs.rules import Rule, integer, is_int, is_num, number, one_of
from resireg.specs.table import SpecTable

__all__ = [
    "CAPTION_SOURCE_KEYS",
    "CLASS_NAMES",
    "DATASET_SPECS",
    "SEGMENTATION_KEYS",
    "WINDOW_RULE_KEYS",
    "SEGMENTATION_RULES",
    "UPSAMPLES",
    "DatasetSpec",
    "GT_RESOLUTIONS",
    "GT_RULES",
    "INTRINSICS",
    "METRICS",
    "RESIZES",
    "check_dataset_keys",
    "check_dataset_values",
    "dataset_conf",
    "dataset_key_errors",
    "dataset_kinds",
    "dataset_value_errors",
    "find_dataset",
    "missing_keys_error",
    "require_keys",
]


def _size(v: Any) -> bool:
    """``[height, width]``, two integers >= 1."""
    return isinstance(v, list) and len(v) == 2 and all(is_int(s) and s >= 1 for s in v)


#: ``image_size`` of the kinds that have one (synthetic scenes, ScanNet frames).
_IMAGE_SIZE: Rule = (_size, "[height, width], two integers >= 1")


def _open_unit(v: Any) -> bool:
    """``null`` or a number in (0, 1)."""
    return v is None or (is_num(v) and 0 < v < 1)


_BOOL: Rule = (lambda v: isinstance(v, bool), "true or false")


# The ScanNet protocol's named options (docs/protocol.md section 4), written once: the rules
# below and the code that reads each option (resireg_train.data.scannet,
# resireg_train.evaluation.mapping) take them from here; the mapping library's own (LATTICES, POINTS)
# from resireg.specs.mapping.
#: ``gt_resolution`` values besides ``[H, W]``.
GT_RESOLUTIONS = ("image", "label")
#: How ignored ground-truth pixels enter the voxel labels (``resireg_train.evaluation.mapping.engine``).
GT_RULES = ("rayfronts", "vote", "drop")
#: Nearest resize rules of depth and labels (``resireg_train.data.scannet``).
RESIZES = ("torch", "exact")
#: Intrinsics scaling rules (``resireg_train.data.scannet``).
INTRINSICS = ("multiply", "half_pixel")
#: Where the names of the classes come from (``resireg_train.data.scannet``).
CLASS_NAMES = ("label_map", "nyu40")
#: 3D metric definitions (the metric table's voxel scorers, :mod:`resireg.specs.metrics`).
METRICS = VOXEL_METRICS

#: The 3D protocol's value rules of a ScanNet entry (conf/dataset/scannet.yaml, docs/protocol.md
#: section 4), by key; checked by :func:`resireg_train.checks.eval.validate_eval` for that kind
#: only (2D entries may use some of the names).
_SCANNET_RULES: dict[str, Rule] = {
    "scenes": (
        lambda v: isinstance(v, list) and len(v) > 0 and all(isinstance(x, str) for x in v),
        "a non-empty list of scene names (scene0050_00, ...)",
    ),
    "frame_skip": integer(0),
    "image_size": _IMAGE_SIZE,
    "voxel_size": MAP_RULES["voxel_size"],
    "gt_resolution": (lambda v: v in GT_RESOLUTIONS or _size(v), "image, label or [height, width]"),
    "gt_unlabelled": one_of(GT_RULES),
    "resize": one_of(RESIZES),
    "intrinsics": one_of(INTRINSICS),
    "lattice": MAP_RULES["lattice"],
    "points": MAP_RULES["points"],
    "storage": MAP_RULES["storage"],
    "knn": integer(0),
    "prediction_threshold": (_open_unit, "null or a number in (0, 1)"),
    "prompt_denoising": (_open_unit, "null or a number in (0, 1)"),
    "metric": one_of(METRICS),
    "class_names": one_of(CLASS_NAMES),
    "classes_to_ignore": (
        lambda v: isinstance(v, list) and all(isinstance(c, str) for c in v),
        "a list of class names (NYU40 names, e.g. otherprop)",
    ),
    "protocol": (lambda v: isinstance(v, str) and bool(v), "a name for the protocol"),
}  # fmt: skip

#: The keys the posed RGB-D benchmarks beside ScanNet share (Replica, TartanAir:
#: resireg_train.data.posed3d): the entry's own, the frame reader's and the 3D task's
#: (resireg_train.evaluation.mapping.engine.TASK_KEYS).
_POSED_OWN = ("name", "kind", "path", "scenes", "protocol")
_POSED_READER = ("frame_skip", "image_size", "short_side", "resize", "intrinsics", "limit")
_MAPPING_TASK = ("voxel_size", "lattice", "gt_unlabelled", "points", "storage", "knn",
                 "prediction_threshold", "prompt_denoising", "metric")  # fmt: skip
_NAME: Rule = (lambda v: isinstance(v, str) and bool(v), "a non-empty name")
_PATH: Rule = (lambda v: isinstance(v, str) and bool(v), "a folder path")
_OPTIONAL_PATH: Rule = (lambda v: v is None or (isinstance(v, str) and bool(v)),
                        "null or a folder path")  # fmt: skip
#: The value rules of those keys (ScanNet's rules of the same keys; scene names are free).
_POSED_RULES: dict[str, Rule] = {
    k: v for k, v in _SCANNET_RULES.items()
    if k in {*_POSED_OWN, *_POSED_READER, *_MAPPING_TASK, "classes_to_ignore"}
}  # fmt: skip
_POSED_RULES["scenes"] = (
    lambda v: isinstance(v, list) and len(v) > 0 and all(isinstance(x, str) and x for x in v),
    "a non-empty list of scene names",
)

#: How predictions reach a label's resolution (``upsample``): ``nearest``, the argmax at the
#: feature grid brought to the label by nearest upsampling (the paper's); ``bilinear``, the logits
#: resized bilinearly (``align_corners=False``) to the input, then to the label, before the argmax
#: (mmsegmentation's, the OVSS field's: docs/protocol.md section 6).
UPSAMPLES = ("nearest", "bilinear")

#: The 2D protocol's keys every segmentation entry holds beside ``short_side``
#: (``conf/protocol/paper.yaml`` / ``ovss8.yaml`` give them; :mod:`resireg_train.data.windows`
#: reads them): the longer side's cap, the resize's antialiasing, the sliding window,
#: the upsampling, the background rule of the with-background sets and the protocol's name.
WINDOW_RULE_KEYS = (
    "long_side", "antialias", "slide_crop", "slide_stride", "upsample",
    "background_threshold", "background_logit_scale", "protocol",
)  # fmt: skip
#: The keys of every 2D segmentation entry (``SegmentationSet``; the ``ovss`` task): a kind
#: outside the project names them first (``(*SEGMENTATION_KEYS, "its", "own")``).
SEGMENTATION_KEYS = ("name", "kind", "short_side", "limit", *WINDOW_RULE_KEYS, "templates")
_SEGMENTATION = SEGMENTATION_KEYS


def _optional(rule: Rule) -> Rule:
    """``null`` or a value of ``rule``."""
    check, expected = rule
    return (lambda v: v is None or check(v)), f"null or {expected}"


#: The value rules of the protocol keys (every 2D kind's; ``dataset.<key>=<value>: expected``).
SEGMENTATION_RULES: dict[str, Rule] = {
    "long_side": _optional(integer(1)),
    "antialias": (lambda v: isinstance(v, bool), "true or false"),
    "slide_crop": _optional(integer(1)),
    "slide_stride": _optional(integer(1)),
    "upsample": one_of(UPSAMPLES),
    "background_threshold": (_open_unit, "null or a number in (0, 1)"),
    "background_logit_scale": _optional(number(0, strict=True, finite=True)),
    "protocol": (lambda v: v is None or (isinstance(v, str) and bool(v)),
                 "null or a name for the protocol"),
    "templates": TEMPLATE_SET,
}  # fmt: skip
#: The keys of the benchmarks read from a downloaded folder (VOC, Context, COCO, Cityscapes):
#: the folder, the split, the class-name file and (VOC, Context) whether label 0 is ignored.
_FOLDER = ("path", "split", "classes")
_LABELS = {"labels": one_of(("converted", "raw"))}


@dataclass(frozen=True)
class DatasetSpec:
    """One dataset kind.

    Attributes:
        kind: the ``dataset.kind`` value.
        builder: ``"module:function"`` building it (loaded when a task builds the dataset).
            The ``ovss`` task's kinds: ``(name, spec, key, common) -> SegmentationSet``, called
            by :func:`~resireg_train.data.segmentation.build_segmentation_set` (``common``: the
            ``SegmentationSet`` keywords shared by every kind, ``short_side``, ``patch_size``
            and the entry's 2D ``protocol``); the ``scannet3d`` task's: :func:`~resireg_train.data.scannet.
            build_scannet`.
        keys: every key of an entry of this kind; the entry holds each (``conf/dataset/``
            files are the defaults), except those of ``optional``.
        optional: the keys an entry may leave out (``name``: the kind, or the name the entry is
            listed under).
        tasks: the ``resireg-eval`` tasks that score it (:data:`resireg_train.evaluation.specs.TASK_SPECS`).
        check: ``"module:function"`` ``(spec, key) -> None`` raising the errors its build
            would on a missing source, run before the encoder loads; ``None``: none.
        summary: one line for errors and docs.
        rules: the value rules of its keys, ``key -> (check, expectation)``
            (:mod:`resireg.specs.rules`), checked by the config check
            (:func:`resireg_train.checks.eval.validate_eval`, as ``dataset.<key>=<value>:
            expected <expectation>``); keys without one are checked for presence only.
    """

    kind: str
    builder: str
    keys: tuple[str, ...]
    tasks: tuple[str, ...]
    summary: str
    optional: tuple[str, ...] = ("name",)
    check: str | None = None
    rules: Mapping[str, Rule] = field(default_factory=dict, hash=False)

    @property
    def configs(self) -> tuple[str, ...]:
        """Its ``conf/dataset/`` files (``dataset=<config>``), found by scanning for its kind."""
        return DATASET_SPECS.configs(self.kind)

    def load(self) -> Any:
        """The builder (imports torch and the dataset's readers)."""
        from resireg.specs.table import load

        return load(self.builder)

    def load_check(self) -> Any:
        """The source check, or ``None``."""
        from resireg.specs.table import load

        return load(self.check) if self.check else None


#: Every evaluation dataset kind (the ``dataset.kind`` config key).
DATASET_SPECS: SpecTable[DatasetSpec] = SpecTable(
    "dataset kind",
    (
        DatasetSpec(
            "synthetic",
            "resireg_train.data.segmentation:synthetic_source",
            (*_SEGMENTATION, "size", "image_size", "seed", "noise"),
            ("ovss",),
            "generated scenes with exact masks, 8 classes (tests, smoke runs)",
            rules={**SEGMENTATION_RULES, "image_size": _IMAGE_SIZE},
        ),
        DatasetSpec(
            "ade20k",
            "resireg_train.data.ade20k:ade20k_source",
            (*_SEGMENTATION, "path", "config", "revision", "split", "image", "label"),
            ("ovss",),
            "ADE20K-150 validation (hub parquet or ADEChallengeData2016 folder; Table 1)",
            check="resireg_train.data.ade20k:check_ade20k_source",
            rules=SEGMENTATION_RULES,
        ),
        DatasetSpec(
            "orad3d",
            "resireg_train.data.orad3d:orad3d_source",
            (*_SEGMENTATION, "path", "split", "polygon_tags", "gt_image_classes"),
            ("ovss",),
            "ORAD-3D validation from its local layout (Table 1)",
            check="resireg_train.data.orad3d:check_orad3d_source",
            rules=SEGMENTATION_RULES,
        ),
        DatasetSpec(
            "voc",
            "resireg_train.data.voc:voc_source",
            (*_SEGMENTATION, *_FOLDER, "reduce_zero_label"),
            ("ovss",),
            "Pascal VOC 2012 val from VOCdevkit/VOC2012 (VOC21; VOC20 with reduce_zero_label)",
            check="resireg_train.data.voc:check_voc_source",
            rules={**SEGMENTATION_RULES, "reduce_zero_label": _BOOL},
        ),
        DatasetSpec(
            "pascal_context",
            "resireg_train.data.context:context_source",
            (*_SEGMENTATION, *_FOLDER, "reduce_zero_label"),
            ("ovss",),
            "Pascal Context val, converted labels in VOC2010/SegmentationClassContext (PC60, PC59)",
            check="resireg_train.data.context:check_context_source",
            rules={**SEGMENTATION_RULES, "reduce_zero_label": _BOOL},
        ),
        DatasetSpec(
            "coco_stuff",
            "resireg_train.data.coco:coco_stuff_source",
            (*_SEGMENTATION, *_FOLDER, "labels"),
            ("ovss",),
            "COCO-Stuff 164k val, 171 classes (coco_stuff164k: images/, annotations/)",
            check="resireg_train.data.coco:check_coco_source",
            rules={**SEGMENTATION_RULES, **_LABELS},
        ),
        DatasetSpec(
            "coco_object",
            "resireg_train.data.coco:coco_object_source",
            (*_SEGMENTATION, *_FOLDER, "labels"),
            ("ovss",),
            "COCO-Object val: COCO-Stuff's things 1..80, the rest background (81 classes)",
            check="resireg_train.data.coco:check_coco_source",
            rules={**SEGMENTATION_RULES, **_LABELS},
        ),
        DatasetSpec(
            "cityscapes",
            "resireg_train.data.cityscapes:cityscapes_source",
            (*_SEGMENTATION, *_FOLDER, "labels"),
            ("ovss",),
            "Cityscapes val, 19 classes (leftImg8bit/, gtFine/ train ids or label ids)",
            check="resireg_train.data.cityscapes:check_cityscapes_source",
            rules={**SEGMENTATION_RULES, **_LABELS},
        ),
        DatasetSpec(
            "replica",
            "resireg_train.data.replica:build_replica",
            (*_POSED_OWN, "semantic_info", "gt_path", "classes_to_ignore", *_POSED_READER,
             *_MAPPING_TASK),
            ("scannet3d",),
            "Replica as NICE-SLAM renders it, scored against HOV-SG's ground-truth points "
            "(RayFronts' NiceReplicaDataset and semseg configs; sweep=replica3d)",
            check="resireg_train.data.replica:check_replica_spec",
            rules={**_POSED_RULES, "semantic_info": _OPTIONAL_PATH, "gt_path": _PATH},
        ),
        DatasetSpec(
            "replica_semnerf",
            "resireg_train.data.replica:build_replica_semnerf",
            (*_POSED_OWN, "classes_to_ignore", *_POSED_READER, *_MAPPING_TASK),
            ("scannet3d",),
            "Replica as Semantic-NeRF renders it, per-frame labels (RayFronts' "
            "SemanticNerfReplicaDataset)",
            check="resireg_train.data.replica:check_replica_semnerf_spec",
            rules=_POSED_RULES,
        ),
        DatasetSpec(
            "tartanair",
            "resireg_train.data.tartanair:build_tartanair",
            (*_POSED_OWN, "data_partition", "sequence", "label_file", "depth_cutoff",
             *_POSED_READER, *_MAPPING_TASK),
            ("scannet3d",),
            "TartanAir v2 / TartanGround front camera, per-frame labels (RayFronts' "
            "TartanAirDataset and semseg configs; sweep=tartanair3d)",
            check="resireg_train.data.tartanair:check_tartanair_spec",
            rules={**_POSED_RULES, "data_partition": _NAME, "sequence": _NAME,
                   "label_file": _NAME, "depth_cutoff": number(0, strict=True, finite=True)},
        ),
        DatasetSpec(
            "scannet",
            "resireg_train.data.scannet:build_scannet",
            (
                # the entry's own
                "name",
                "kind",
                "path",
                "scenes",
                "protocol",
                # the frame reader's (resireg_train.data.scannet.READER_KEYS)
                "label_map",
                "frame_skip",
                "image_size",
                "gt_resolution",
                "short_side",
                "limit",
                "resize",
                "intrinsics",
                "class_names",
                "classes_to_ignore",
                # the 3D task's (resireg_train.evaluation.mapping.engine.TASK_KEYS)
                "voxel_size",
                "lattice",
                "gt_unlabelled",
                "points",
                "storage",
                "knn",
                "prediction_threshold",
                "prompt_denoising",
                "metric",
            ),  # fmt: skip
            ("scannet3d",),
            "ScanNet v2 scenes exported by SensReader (posed RGB-D frames; Table 2)",
            check="resireg_train.data.scannet:check_scannet_spec",
            rules=_SCANNET_RULES,
        ),
    ),
    name="kind",
    where="resireg_train.data.specs",
    conf="dataset",
)

#: The keys of a training caption source (``data.sources.<name>``, ``conf/data/``), by what its
#: ``path`` names: ``synthetic`` (the generated scenes) or any other (a hub id, a local folder,
#: a ``datasets`` builder name). ``required``: those every source holds (``conf/data/`` files
#: are the defaults; ``probability``, its relative weight in the mix, included: no source
#: weighs 1 unless its file says so); ``optional``: those a source may leave out (nothing is
#: passed then).
CAPTION_SOURCE_KEYS: dict[str, dict[str, tuple[str, ...]]] = {
    "synthetic": {
        "required": ("path", "size", "image_size", "seed", "noise", "shards", "probability"),
        "optional": (),
    },
    "hub": {
        "required": ("path", "split", "image", "caption", "probability"),
        "optional": ("name", "data_files", "data_dir", "revision"),
    },
}


def dataset_kinds() -> list[str]:
    """The ``dataset.kind`` values of the table, in its order."""
    return list(DATASET_SPECS.names())


def find_dataset(kind: Any) -> DatasetSpec | None:
    """The entry of ``kind``; ``None`` for a kind the table lacks."""
    return DATASET_SPECS.find(str(kind))


def missing_keys_error(key: str, missing: Any, source: str) -> str:
    """The one message of keys an entry lacks: ``<key>: no <key>.<name>, ... (a value is
    required; <source> holds every one)`` (``source``: the config files holding them)."""
    return (f"{key}: no {', '.join(f'{key}.{n}' for n in missing)} (a value is required; "
            f"{source} holds every one)")  # fmt: skip


def require_keys(spec: Mapping[str, Any], names: Any, key: str, source: str) -> None:
    """A ValueError (:func:`missing_keys_error`) naming ``<key>.<name>`` for each of ``names``
    that ``spec`` lacks: the one error of a missing key, no silent default."""
    missing = [n for n in names if n not in spec]
    if missing:
        raise ValueError(missing_keys_error(key, missing, source))


def dataset_key_errors(spec: Mapping[str, Any], key: str = "dataset") -> list[str]:
    """The errors of an entry's keys against the table: an unknown kind (naming
    ``<key>.kind`` and the known ones), keys the kind does not read (naming them and the
    allowed keys) and keys it needs that the entry lacks (naming ``<key>.<name>``)."""
    kind = spec.get("kind")
    entry = find_dataset(kind)
    if entry is None:
        return [f"{DATASET_SPECS.unknown(kind, setting=f'{key}.kind')} "
                "(resireg_train.data.specs)"]  # fmt: skip
    errors = []
    unknown = set(spec) - set(entry.keys)
    if unknown:
        errors.append(f"{key}: unknown keys {sorted(unknown)} for kind {kind!r} "
                      f"({sorted(entry.keys)})")  # fmt: skip
    missing = [k for k in entry.keys if k not in spec and k not in entry.optional]
    if missing:
        files = ", ".join(f"conf/dataset/{c}.yaml" for c in entry.configs)
        errors.append(missing_keys_error(key, missing, files or "its conf/dataset/ file"))
    return errors


def dataset_value_errors(kind: Any, values: Mapping[str, Any], key: str = "dataset") -> list[str]:
    """``<key>.<name>=<value>: expected <...>`` for each of ``values`` that breaks its rule in
    the table entry of ``kind`` (:attr:`DatasetSpec.rules`; names without a rule, and every
    name of an unknown kind, pass): the config check and the classes that take these values
    from Python report them alike."""
    entry = find_dataset(kind)
    rules = entry.rules if entry is not None else {}
    return [
        f"{key}.{name}={value!r}: expected {rules[name][1]}"
        for name, value in values.items()
        if name in rules and not rules[name][0](value)
    ]


def check_dataset_values(kind: Any, values: Mapping[str, Any], key: str = "dataset") -> None:
    """A ValueError listing :func:`dataset_value_errors`, if any."""
    errors = dataset_value_errors(kind, values, key)
    if errors:
        raise ValueError("; ".join(errors))


def check_dataset_keys(spec: Mapping[str, Any], key: str = "dataset") -> DatasetSpec:
    """The table entry of ``spec``'s kind; a ValueError listing :func:`dataset_key_errors`."""
    errors = dataset_key_errors(spec, key)
    if errors:
        raise ValueError("; ".join(errors))
    entry = find_dataset(spec.get("kind"))
    assert entry is not None
    return entry


def dataset_conf(config: str, **overrides: Any) -> dict[str, Any]:
    """The entry of ``conf/dataset/<config>.yaml`` (the project's ``conf/``,
    :data:`resireg_train.config.paths.CONFIG_DIR`; its ``defaults`` composed, interpolations such as
    ``${paths.data_dir}`` left as written), ``overrides`` in place of its values: a Python
    caller's entry, with conf/'s defaults read rather than typed again."""
    from omegaconf import OmegaConf

    from resireg.specs.table import compose_conf
    from resireg_train.config.paths import CONFIG_DIR

    folder = CONFIG_DIR / "dataset"
    if not (folder / f"{config}.yaml").is_file():
        raise FileNotFoundError(f"dataset={config!r}: no {folder / f'{config}.yaml'}")
    load = lambda path: OmegaConf.to_container(OmegaConf.load(path), resolve=False)  # noqa: E731
    composed = {key: value for key, (value, _) in compose_conf(folder, config, load).items()}
    return {**composed, **overrides}
