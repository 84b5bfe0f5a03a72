"""``resireg-eval``'s tasks by ``task`` (``conf/eval.yaml``): one entry each, the only list of
them (docs/design.md section 10.4).

Torch-free, like the spec tables of :mod:`resireg.specs`: the config check
(:func:`resireg_train.validation.validate_eval`) reads the task names and each task's dataset
kinds and configuration rules from here before anything heavy loads, and ``resireg-eval``
(:func:`resireg_train.cli.eval.evaluate`, through
:func:`resireg_train.evaluation.require_task`) builds the entry's protocol class
(:class:`resireg_train.evaluation.TaskProtocol`: ``check``, ``build``, ``run``, ``results``),
named lazily as ``"module:Class"``. Adding a task: one protocol class, one entry here
(docs/design.md section 13).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

__all__ = ["TASK_SPECS", "TaskSpec", "find_task", "task_config_errors", "task_names"]


@dataclass(frozen=True)
class TaskSpec:
    """One ``resireg-eval`` task.

    Attributes:
        name: the ``task`` value.
        target: its protocol, ``"module:Class"``: a subclass of
            :class:`resireg_train.evaluation.TaskProtocol` (loaded after the config check).
        unit: what it scores and ``results.json``'s ``images`` counts (``image``, ``frame``).
        dataset_kinds: the ``dataset.kind`` values it scores; ``None``: every kind that no
            other task's entry names.
        prior: whether it scores ``+prior`` configurations (a segmentation prior).
        layers: whether it scores ``@layer:`` configurations (an encoder block's intermediates).
        summary: one line for errors and docs.
    """

    name: str
    target: str
    unit: str
    dataset_kinds: tuple[str, ...] | None
    prior: bool
    layers: bool
    summary: str

    def load(self) -> type:
        """The protocol class (imports torch and the task's engine)."""
        from resireg.specs import load

        return load(self.target)


#: Every task of ``resireg-eval`` (the ``task`` config key).
TASK_SPECS: dict[str, TaskSpec] = {
    "ovss": TaskSpec(
        "ovss",
        "resireg_train.ovss.task:OVSSProtocol",
        "image",
        None,
        prior=True,
        layers=True,
        summary="2D open-vocabulary segmentation (ade20k, orad3d, synthetic; Table 1)",
    ),
    "scannet3d": TaskSpec(
        "scannet3d",
        "resireg_train.mapping.task:ScanNet3DProtocol",
        "frame",
        ("scannet",),
        prior=False,
        layers=False,
        summary="3D semantic mapping of ScanNet scenes (dataset=scannet; Table 2)",
    ),
}


def task_names() -> list[str]:
    """The ``task`` values of the table, in its order."""
    return list(TASK_SPECS)


def find_task(name: Any) -> TaskSpec | None:
    """The entry of ``name``, ``None`` for a name the table lacks (the config check's error,
    and :func:`resireg_train.evaluation.require_task`'s)."""
    return TASK_SPECS.get(str(name))


def task_config_errors(
    name: Any, kind: Any, prior_variants: Iterable[str], layer_variants: Iterable[str],
    variants: Any, key: str = "task",
) -> list[str]:  # fmt: skip
    """The errors of a ``task`` / ``dataset.kind`` / ``variants`` combination, from the table
    (``prior_variants`` / ``layer_variants``: the ``+prior`` / ``@layer:`` ones of ``variants``):
    an unknown task, a dataset kind the task does not score (or one another task claims), and
    ``+prior`` / ``@layer:`` configurations a task does not score."""
    spec = find_task(name)
    if spec is None:
        return [f"{key}={name!r}: expected one of {task_names()} (resireg_train.tasks)"]
    errors = []
    if spec.dataset_kinds is not None and kind not in spec.dataset_kinds:
        needs = " or ".join(f"dataset={k}" for k in spec.dataset_kinds)
        errors.append(f"dataset.kind={kind!r}: {key}={spec.name} needs {needs} (or another config "
                      f"of kind {' or '.join(spec.dataset_kinds)})")  # fmt: skip
    if spec.dataset_kinds is None:
        for other in TASK_SPECS.values():
            if other.dataset_kinds and kind in other.dataset_kinds:
                errors.append(f"{key}={spec.name!r}: dataset.kind={kind!r} is scored by "
                              f"{key}={other.name} ({other.summary}); add {key}={other.name}")  # fmt: skip
    scored_by = [t.name for t in TASK_SPECS.values() if t.prior]
    if list(prior_variants) and not spec.prior:
        errors.append(f"variants={variants!r}: +prior configurations are scored by "
                      f"{' or '.join(f'{key}={t}' for t in scored_by)} only")  # fmt: skip
    scored_by = [t.name for t in TASK_SPECS.values() if t.layers]
    if list(layer_variants) and not spec.layers:
        errors.append(f"variants={variants!r}: @layer: configurations are scored by "
                      f"{' or '.join(f'{key}={t}' for t in scored_by)} only")  # fmt: skip
    return errors
