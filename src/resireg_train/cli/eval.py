"""``resireg-eval``: OVSS of a dense encoder (Hydra main): our exported
:class:`~resireg.models.ResiregVLM` by default, or any encoder of ``conf/encoder/``.

    resireg-eval model_path=outputs/smoke/<time>/export dataset=synthetic
    resireg-eval encoder=clip_vit_b16 dataset=ade20k variants=[bb,calib,lite,full]
    resireg-eval sweep=table1                              # every encoder x dataset: Table 1
    resireg-eval model_path=<export> dataset=ade20k variants=[full] batch_size=16 \
        full.n_prototypes=60
    resireg-eval model_path=<export> dataset=ade20k sweep=prototype_batch      # the ablation grid
    resireg-eval model_path=<export> prior=sam2 variants=[full,full+prior]  # SAM 2.1 prior
    resireg-eval task=scannet3d dataset=scannet encoder=radseg paths.data_dir=/datasets  # 3D
    resireg-eval sweep=table2 paths.data_dir=/datasets          # 3D mapping: the paper's Table 2

``task`` names an entry of the task table (:data:`resireg_train.evaluation.specs.TASK_SPECS`: ``ovss``,
``scannet3d``) whose class (:class:`resireg_train.evaluation.base.EvalTask`) the job
(:func:`resireg_train.jobs.eval.evaluate_body`) drives with no task switch of its own: ``check``
the sources, load the encoder, ``build`` the
dataset and engine, ``run`` the pass, write the results (:func:`resireg_train.evaluation.base.
write_results` with the task's ``results``); docs/architecture.md#adding-a-task.
The 2D scores use the engine of the training callback (:mod:`resireg_train.evaluation.ovss.engine`), so a
model's ``val/ovss/...`` numbers from training are recomputed exactly from its export.
ReSiReg's parameters (``variants``, ``lite.*``, ``full.*``) come from the ``resireg``
config group, which the training callback shares. An export written by ``resireg-train``
records the settings its training run evaluated it with (``resireg_eval.json``: variants,
``lite``, ``full``, ``batch_size``, ``precision``, ``temperature``); every one of them still at
its default here (not set on the command line, nor by an experiment or sweep file) takes
the recorded value, so ``resireg-eval`` reproduces the training score by default
(``export_settings=false`` turns this off).
``results.json`` in the output dir holds the status (and the error of a failed run), the
scores under ``final``, per-class IoU, the parameters, image counts, the batch-size
histogram and seconds per stage.
"""


from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from resireg_train.cli.job import hydra_entry_point, run_task
from resireg_train.jobs.eval import evaluate_body

__all__ = ["evaluate", "main"]


def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """Evaluate from a composed ``eval.yaml`` config; returns the ``results.json`` content.

    A failure (bad value, missing model or dataset, too many prototypes for a batch) is
    recorded in ``results.json`` as ``"status": "failed"`` with its error, then re-raised.
    """
    return run_task(cfg, evaluate_body, fresh=True)


main = hydra_entry_point("eval", evaluate)

if __name__ == "__main__":
    main()
