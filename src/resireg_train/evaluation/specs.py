"""``resireg-eval``'s tasks by ``task`` (``conf/eval.yaml``): one entry each, the only list of
them (docs/architecture.md#adding-a-task).

Torch-free, like the spec tables of :mod:`resireg.specs`: the config check
(:func:`resireg_train.checks.eval.validate_eval`) reads the task names and each task's
configuration rules from here before anything heavy loads (the dataset kinds a task scores are
the dataset table's, :data:`resireg_train.data.specs.DATASET_SPECS`, each entry naming its
tasks); the protocol record (:func:`resireg_train.evaluation.protocol.protocol_record`) and the report
(:mod:`resireg_train.report.tables`) read a task's recorded keys, metric prefix and report
table from its entry. ``resireg-eval``
(:func:`resireg_train.cli.eval.evaluate`, through
:func:`resireg_train.evaluation.base.require_task`) builds the entry's task class
(:class:`resireg_train.evaluation.base.EvalTask`: ``check``, ``build``, ``run``, ``results``),
named lazily as ``"module:Class"``.

Adding a task: one task class (a :class:`resireg_train.evaluation.base.EvalTask`:
``check``, ``build``, ``run``, ``results``), one :class:`TaskSpec` below, and the dataset
kinds it scores naming it in their ``tasks`` (:data:`resireg_train.data.specs.DATASET_SPECS`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from resireg.specs.table import SpecTable
from resireg_train.data.specs import DATASET_SPECS, find_dataset

__all__ = [
    "PRECISIONS",
    "TASK_SPECS",
    "TaskSpec",
    "find_task",
    "task_config_errors",
    "task_names",
]

#: The precisions every task's pass may run in (``precision``) -> the torch dtype name of their
#: autocast (``None``: fp32, no autocast); the config check reads the names, the engines the
#: dtypes (:func:`resireg_train.evaluation.engine.inference`).
PRECISIONS: dict[str, str | None] = {
    "32": None, "32-true": None, "bf16": "bfloat16", "bf16-mixed": "bfloat16",
}  # fmt: skip


@dataclass(frozen=True)
class TaskSpec:
    """One ``resireg-eval`` task.

    Attributes:
        name: the ``task`` value.
        target: its class, ``"module:Class"``: a subclass of
            :class:`resireg_train.evaluation.base.EvalTask` (loaded after the config check).
        unit: what it scores and ``results.json``'s ``images`` counts (``image``, ``frame``).
        prior: whether it scores ``+prior`` configurations (a segmentation prior).
        layers: whether it scores ``@layer:`` configurations (an encoder block's intermediates).
        summary: one line for errors and docs.
        protocol_keys: the dataset entry's keys its ``results.json`` ``protocol`` records
            (:func:`resireg_train.evaluation.protocol.protocol_record`; docs/protocol.md).
        protocol_params: the run's parameters (``params``) that record records too.
        report: the ``resireg-report`` table its sweeps feed (``table1``, ``table2``;
            :data:`resireg_train.report.tables.REPORT_TABLES`), ``None``: none.
    """

    name: str
    target: str
    unit: str
    prior: bool
    layers: bool
    summary: str
    protocol_keys: tuple[str, ...] = ()
    protocol_params: tuple[str, ...] = ()
    report: str | None = None

    @property
    def dataset_kinds(self) -> tuple[str, ...]:
        """The ``dataset.kind`` values it scores: the dataset table's kinds naming it."""
        return tuple(k for k, d in DATASET_SPECS.items() if self.name in d.tasks)

    @property
    def dataset_configs(self) -> tuple[str, ...]:
        """The ``conf/dataset/`` files of its kinds (``dataset=<config>``)."""
        return tuple(c for d in DATASET_SPECS.values() if self.name in d.tasks for c in d.configs)

    @property
    def metric_prefix(self) -> str:
        """What its scores' names start with: ``val/<task>/`` (then ``<dataset>/<metric>``)."""
        return f"val/{self.name}/"

    def load(self) -> type:
        """The task class (imports torch and the task's engine)."""
        from resireg.specs.table import load

        return load(self.target)


#: Every task of ``resireg-eval`` (the ``task`` config key).
TASK_SPECS: SpecTable[TaskSpec] = SpecTable(
    "resireg-eval task",
    (
        TaskSpec(
            "ovss",
            "resireg_train.evaluation.ovss.task:OVSSTask",
            "image",
            prior=True,
            layers=True,
            summary="2D open-vocabulary segmentation (ade20k, orad3d, synthetic; Table 1; the "
            "eight OVSS benchmarks of sweep=ovss8)",
            # docs/protocol.md section 1; the entry's where it has them, the others the built set's
            protocol_keys=(
                "short_side",
                "resize",
                "templates",
                "reduce_zero_label",
                "classes",
                # the 2D protocol's (conf/protocol/paper.yaml, ovss8.yaml; docs/protocol.md 6)
                "long_side",
                "antialias",
                "slide_crop",
                "slide_stride",
                "upsample",
                "background_threshold",
                "background_logit_scale",
            ),  # fmt: skip
            protocol_params=("temperature",),
            report="table1",
        ),
        TaskSpec(
            "scannet3d",
            "resireg_train.evaluation.mapping.task:ScanNet3DTask",
            "frame",
            prior=False,
            layers=False,
            summary="3D semantic mapping of ScanNet scenes (dataset=scannet; Table 2), Replica "
            "and TartanAir (sweep=replica3d, sweep=tartanair3d)",
            # docs/protocol.md section 4 (conf/dataset/scannet.yaml)
            protocol_keys=(
                "frame_skip",
                "image_size",
                "short_side",
                "resize",
                "intrinsics",
                "gt_resolution",
                "gt_unlabelled",
                "points",
                "lattice",
                "voxel_size",
                "storage",
                "knn",
                "prediction_threshold",
                "prompt_denoising",
                "metric",
                "class_names",
                "classes_to_ignore",
                # TartanAir's (conf/dataset/tartanair.yaml)
                "data_partition",
                "sequence",
                "label_file",
                "depth_cutoff",
            ),  # fmt: skip
            report="table2",
        ),
    ),
    where="resireg_train.evaluation.specs",
)


def task_names() -> list[str]:
    """The ``task`` values of the table, in its order."""
    return list(TASK_SPECS.names())


def find_task(name: Any) -> TaskSpec | None:
    """The entry of ``name``, ``None`` for a name the table lacks (the config check's error,
    and :func:`resireg_train.evaluation.base.require_task`'s)."""
    return TASK_SPECS.find(str(name))


def task_config_errors(
    name: Any, kind: Any, prior_variants: Iterable[str], layer_variants: Iterable[str],
    variants: Any, key: str = "task",
) -> list[str]:  # fmt: skip
    """The errors of a ``task`` / ``dataset.kind`` / ``variants`` combination, from the table
    (``prior_variants`` / ``layer_variants``: the ``+prior`` / ``@layer:`` ones of ``variants``):
    an unknown task, a dataset kind the task does not score (the dataset table's entry of the
    kind names its tasks; an unknown kind is the dataset check's error), and
    ``+prior`` / ``@layer:`` configurations a task does not score."""
    spec = find_task(name)
    if spec is None:
        return [f"{TASK_SPECS.unknown(name, setting=key)} (resireg_train.evaluation.specs)"]
    errors = []
    dataset = find_dataset(kind)
    if dataset is not None and spec.name not in dataset.tasks:
        by = " or ".join(
            f"{key}={t}" + (f" ({TASK_SPECS[t].summary})" if t in TASK_SPECS else "")
            for t in dataset.tasks
        )  # fmt: skip
        fix = " or ".join(f"{key}={t}" for t in dataset.tasks)
        configs = " or ".join(f"dataset={c}" for c in spec.dataset_configs)
        errors.append(f"{key}={spec.name!r}: dataset.kind={kind!r} is scored by {by or 'no task'}; "
                      f"set {fix or 'another task'}, or choose a dataset of {key}={spec.name}"
                      f"{f' ({configs})' if configs else ''}")  # fmt: skip
    scored_by = [t.name for t in TASK_SPECS.values() if t.prior]
    if list(prior_variants) and not spec.prior:
        errors.append(f"variants={variants!r}: +prior configurations are scored by "
                      f"{' or '.join(f'{key}={t}' for t in scored_by)} only")  # fmt: skip
    scored_by = [t.name for t in TASK_SPECS.values() if t.layers]
    if list(layer_variants) and not spec.layers:
        errors.append(f"variants={variants!r}: @layer: configurations are scored by "
                      f"{' or '.join(f'{key}={t}' for t in scored_by)} only")  # fmt: skip
    return errors
