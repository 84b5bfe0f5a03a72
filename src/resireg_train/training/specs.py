"""The distillation teachers by ``kind`` (``conf/model/teacher/<name>.yaml``, ``model.teacher``):
one entry each, the only list of them, without importing torch.

The training module (:class:`resireg_train.training.module.ResiregModule`) builds the teacher
of its config in each process (:func:`resireg_train.training.teacher.build_teacher`: the
entry's class called with the other keys and the process's ``device``); the config check
(:func:`resireg_train.checks.train.validate`) reads the kinds before torch loads.

Adding a teacher:

1. a class in ``resireg_train/training/teacher.py`` (or a module of its own): a
   :class:`resireg_train.training.teacher.FrozenTeacher` with ``out_dim`` and
   ``dense(images) -> [B, out_dim, h, w]`` (the images normalised as the student's), built
   frozen from its keywords and ``device`` (where it runs);
2. one :class:`TeacherSpec` below: its ``kind``, the class as ``"module:Class"``, a one-line
   summary;
3. one ``conf/model/teacher/<name>.yaml``: ``kind: <kind>`` and every keyword;
   ``model/teacher=<name>`` then selects it (``model.loss.distill.scale`` > 0 loads it).

``tests/resireg/specs/test_tables.py`` checks the entry (its class loads, its file is found by scanning).
"""

from __future__ import annotations

from resireg.specs.table import KindSpec, SpecTable

__all__ = ["TEACHER_SPECS", "TeacherSpec"]


class TeacherSpec(KindSpec):
    """One kind of distillation teacher: its class (``"module:Class"``) and what it is."""


#: Teacher kinds of :func:`resireg_train.training.teacher.build_teacher`.
TEACHER_SPECS: SpecTable[TeacherSpec] = SpecTable(
    "teacher kind",
    (
        TeacherSpec("radseg", "resireg_train.training.teacher:RadSegTeacher",
                    "RADSeg's SigLIP 2-aligned dense features through torch.hub (stage 1)"),
        TeacherSpec("conv", "resireg_train.training.teacher:ConvTeacher",
                    "a small random conv net standing in for RADSeg offline (tests, smoke)"),
    ),
    name="kind",
    where="resireg_train.training.specs",
    conf="model/teacher",
)  # fmt: skip
