"""``resireg-eval task=scannet3d``: 3D semantic mapping of ScanNet, Replica or TartanAir scenes
(the dataset table's kinds scored by ``scannet3d``, each read by its own builder) as an evaluation task
(:class:`resireg_train.evaluation.base.EvalTask`; the entry ``scannet3d`` of
:data:`resireg_train.evaluation.specs.TASK_SPECS`) over the engine
:class:`~resireg_train.evaluation.mapping.engine.MappingEngine` (docs/maps.md#3d-semantic-mapping). Beside the
fields every task writes, ``results.json`` holds ``per_scene``, ``per_scene_csv`` (the CSVs of
:meth:`~resireg_train.evaluation.mapping.result.MappingResult.write_csv`), ``frames`` and
``frames_dropped``."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from torch import nn

from resireg.models import DenseEncoder
from resireg_train.data.specs import check_dataset_keys
from resireg_train.evaluation.base import EvalTask
from resireg_train.evaluation.engine import StageTimer
from resireg_train.evaluation.mapping.engine import MappingEngine, MappingSettings
from resireg_train.evaluation.mapping.result import MappingResult
from resireg_train.evaluation.protocol import protocol_record

__all__ = ["ScanNet3DTask"]

log = logging.getLogger(__name__)


class ScanNet3DTask(EvalTask):
    """3D semantic mapping of the configured ScanNet scenes (module docstring)."""

    def check(self, variants: Mapping[str, nn.Module]) -> None:
        """The dataset kind's own source check (the dataset table's ``check``: ScanNet,
        Replica, TartanAir), before the encoder loads."""
        entry = check_dataset_keys(self.params["dataset"], "dataset")
        source_check = entry.load_check()
        if source_check is not None:
            source_check(self.params["dataset"], "dataset")
        super().check(variants)

    def build(self, encoder: DenseEncoder, variants: Mapping[str, nn.Module]) -> dict[str, Any]:
        spec = self.params["dataset"]
        builder = check_dataset_keys(spec, "dataset").load()  # the kind's (the dataset table)
        self.dataset = builder(spec, encoder.input_rule.patch_size, key="dataset")
        self.classes = self.dataset.classes
        self.engine = MappingEngine(self.dataset, int(self.cfg.batch_size),
                                  MappingSettings.from_spec(spec),
                                  num_workers=int(self.cfg.num_workers))  # fmt: skip
        self.check_batches(self.engine, variants)
        return {"protocol": protocol_record(self.params)}

    def run(self, encoder: DenseEncoder, variants: Mapping[str, nn.Module],
            timer: StageTimer) -> MappingResult:  # fmt: skip
        return self.engine.run(encoder, variants, precision=str(self.cfg.precision), timer=timer)

    def results(self, result: MappingResult) -> dict[str, Any]:
        """``per_scene``, ``per_scene_csv`` (written into the output folder), ``frames``,
        ``frames_dropped``, ``skipped`` and ``skipped_samples`` (the dropped frames first)."""
        dropped = result.dropped_samples + result.skipped_samples
        if dropped:
            log.warning(
                "%s: %d frames dropped (non-finite pose) and %d skipped (unreadable, or a "
                "non-finite encoder output): %s",
                self.dataset.name, len(result.dropped_samples), len(result.skipped_samples),
                "; ".join(f"{s.file}: {s.reason}" for s in dropped),
            )  # fmt: skip
        return {
            "per_scene": result.per_scene(),
            "per_scene_csv": result.write_csv(self.out),
            "frames": dict(result.frames),
            "frames_dropped": len(result.dropped_samples),
            "skipped": len(result.skipped_samples),
            "skipped_samples": [s.as_dict() for s in dropped],
        }
