"""LightningModule training the 25M VLM's language head and text projection.

Frozen: EUPE backbone, text tower, RadSeg teacher (excluded from checkpoints; they are
rebuilt from their weights source). Trained: language head, text projection, logit
scale, and (stage 1) the distillation head mapping teacher features to the head width.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import lightning as L
import torch
from timm.optim import param_groups_weight_decay
from torch import Tensor, nn

from resireg.models import ResiregVLM
from resireg_train.config.machine import init_from_problem
from resireg_train.training.checkpoints import load_weights_only
from resireg_train.training.losses import ContrastiveLoss, distill_loss, warmup_factor
from resireg_train.training.teacher import build_teacher

__all__ = ["ResiregModule"]

_FROZEN_PREFIXES = ("vlm.backbone.", "vlm.text.", "teacher.")


def _require(settings: Any, keys: tuple[str, ...], key: str) -> None:
    """A ValueError naming ``<key>.<k>`` for each of ``keys`` that ``settings`` lacks."""
    missing = [k for k in keys if not isinstance(settings, Mapping) or k not in settings]
    if missing:
        raise ValueError(f"{key}: missing {[f'{key}.{k}' for k in missing]} (conf/model/vlm25m."
                         "yaml sets them all)")  # fmt: skip


class ResiregModule(L.LightningModule):
    """Two-stage training of the dense VLM (docs/method.md#training-recipe).

    Args:
        backbone, head, text: model configs (see :meth:`ResiregVLM.build`).
        intermediate_layer: ReSiReg's intermediates in evaluation (see ``ResiregVLM``).
        teacher: teacher config (``{"kind": "radseg" | "conv", ...}``); loaded only when the
            distillation scale is > 0, and built on the rank's own device in :meth:`setup`.
        optimizer: a partial optimizer, ``params -> torch.optim.Optimizer`` (Hydra
            ``_partial_: true`` in ``conf/model``), with ``lr`` and ``weight_decay``; weight
            decay is applied to matrices only (timm's ``param_groups_weight_decay``). ``None``
            only for a module that does not train (``load_from_checkpoint``: the checkpoint's
            hyperparameters leave the partial out).
        scheduler: ``{"min_lr"}``: per-step cosine from ``lr`` to ``min_lr``.
        loss: ``{"contrastive": {"scale", "warmup_epochs"}, "distill": {"scale", "warmup_epochs"}}``.
        logit_scale: ``{"init", "max"}`` (learned in log space, clamped after every step).
        steps_per_epoch: optimizer steps per epoch (for fractional-epoch warm-up).

    Only the model parts and ``intermediate_layer`` have defaults (null, as in conf/): the
    training settings are required keywords, their values in ``conf/model/vlm25m.yaml``.
    """

    def __init__(
        self,
        backbone: dict,
        head: dict,
        text: dict,
        intermediate_layer: int | None = None,
        *,
        teacher: dict | None,
        optimizer: Callable[..., torch.optim.Optimizer] | None = None,
        scheduler: dict,
        loss: dict,
        logit_scale: dict,
        steps_per_epoch: int,
    ) -> None:
        super().__init__()
        # No defaults of its own (conf/model/vlm25m.yaml holds them; a default here would
        # shadow it): every setting is given, and a missing one is named.
        _require(scheduler, ("min_lr",), "model.scheduler")
        _require(logit_scale, ("init", "max"), "model.logit_scale")
        _require(loss, ("contrastive", "distill"), "model.loss")
        for part in ("contrastive", "distill"):
            _require(loss[part], ("scale", "warmup_epochs"), f"model.loss.{part}")
        # The optimizer partial stays out of the checkpoint's hyperparameters, which must load
        # with torch.load(weights_only=True); the run's .hydra/config.yaml records it.
        self.save_hyperparameters(ignore=["optimizer"])
        self.optimizer_factory = optimizer
        self.sched_cfg = dict(scheduler)
        self.contrastive_cfg = dict(loss["contrastive"])
        self.distill_cfg = dict(loss["distill"])
        ls = dict(logit_scale)
        self.max_log_scale = math.log(ls["max"])
        self.steps_per_epoch = steps_per_epoch
        self._schedule: dict[str, int] | None = None  # this run's cosine length (optimizer steps)
        self._resumed_schedule: dict[str, int] | None = None  # the checkpoint's, when resuming

        self.vlm = ResiregVLM.build(backbone, head, text, intermediate_layer)
        self.logit_scale = nn.Parameter(torch.tensor(math.log(ls["init"])))
        self.contrastive = ContrastiveLoss()
        self.teacher_cfg = None
        self.teacher = None
        self.distill_head = None
        if self.distill_cfg["scale"] > 0:
            if teacher is None:
                raise ValueError("model.loss.distill.scale > 0 needs a model.teacher config")
            self.teacher_cfg = dict(teacher)

    def setup(self, stage: str) -> None:
        """Build the teacher in each process, on that process's device.

        RADSeg's encoder is a plain object that fixes its device when it is built, so
        Lightning's ``.to()`` never reaches it: it must be built here, not in ``__init__``.
        Lightning calls ``setup`` before it moves the module, but with ``self.device``
        already reporting the rank's root device, which is where the teacher goes.
        """
        if self.teacher_cfg is None or self.teacher is not None:
            return
        self.teacher = build_teacher(**self.teacher_cfg, device=self.device)
        if self.distill_head is None:  # (a restored checkpoint may have built it already)
            self.distill_head = nn.Linear(self.teacher.out_dim, self.vlm.head.out_dim)
        elif self.distill_head.in_features != self.teacher.out_dim:
            raise ValueError(
                f"the checkpoint's distillation head takes {self.distill_head.in_features} "
                f"teacher channels; model.teacher gives {self.teacher.out_dim}"
            )
        self.distill_head.to(self.device)

    # ------------------------------------------------------------------ steps
    def loss_scales(self, epoch: float) -> tuple[float, float]:
        """Warmed-up (contrastive, distillation) scales at a fractional epoch."""
        c = self.contrastive_cfg["scale"] * warmup_factor(
            epoch, self.contrastive_cfg["warmup_epochs"]
        )
        d = self.distill_cfg["scale"] * warmup_factor(epoch, self.distill_cfg["warmup_epochs"])
        return c, d

    def losses(self, batch: dict, step: int) -> tuple[Tensor, dict[str, Tensor]]:
        """Total loss of a batch ``{"image": [B, 3, H, W], "caption": [str] * B}`` at optimizer
        step ``step`` (for the warm-up), and its detached parts for logging."""
        images, captions = batch["image"], batch["caption"]
        out = self.vlm.encode(images)
        text = self.vlm.text_embedding(captions)
        loss_c, logits, targets = self.contrastive(out.embedding, text, self.logit_scale.exp())
        scale_c, scale_d = self.loss_scales(step / self.steps_per_epoch)
        loss = scale_c * loss_c
        logs = {
            "train/loss_contrastive": loss_c.detach(),
            "train/logit_scale": self.logit_scale.exp().detach(),
            "train/retrieval_i2t": (logits.argmax(1) == targets).float().mean(),
        }
        if self.teacher is not None:
            target = self.distill_head(
                self.teacher(images, out.language.shape[-2:]).permute(0, 2, 3, 1)
            )
            loss_d = distill_loss(out.language, target.permute(0, 3, 1, 2))
            loss = loss + scale_d * loss_d
            logs["train/loss_distill"] = loss_d.detach()
        return loss, logs

    def training_step(self, batch: dict, batch_idx: int) -> Tensor:
        images = batch["image"]
        loss, logs = self.losses(batch, self.global_step)
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"non-finite training loss {loss.item()} at global step {self.global_step} "
                f"(contrastive {logs['train/loss_contrastive'].item()}); lower "
                "model.optimizer.lr or check the data"
            )
        self.log_dict(logs, on_step=True, on_epoch=True, batch_size=images.shape[0])
        self.log("train/lr", self.trainer.optimizers[0].param_groups[0]["lr"], on_step=True,
                 on_epoch=False, batch_size=images.shape[0])  # fmt: skip
        self.log("train/loss", loss.detach(), on_step=True, on_epoch=True, prog_bar=True,
                 batch_size=images.shape[0])  # fmt: skip
        self._log_skipped(batch)
        return loss

    def _log_skipped(self, batch: dict) -> None:
        """Examples the data pipeline dropped before this batch, summed over ranks here and
        over the epoch by the logger.

        The cross-rank sum is one explicit reduce that every rank issues at this same point
        of every step; a ``sync_dist`` metric would instead be reduced lazily by whichever
        rank first reads it (rank 0's progress bar), out of order with the other ranks'
        collectives.
        """
        keys = [
            f"skipped_{reason}" for reason in ("invalid", "small") if f"skipped_{reason}" in batch
        ]
        if not keys:
            return
        counts = torch.stack([batch[k].sum() for k in keys]).float().to(self.device)
        if self.trainer.world_size > 1:
            counts = self.trainer.strategy.reduce(counts, reduce_op="sum")
        for key, count in zip(keys, counts, strict=True):
            self.log(f"data/{key}", count, on_step=False, on_epoch=True, reduce_fx="sum")

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        with torch.no_grad():
            self.logit_scale.clamp_(max=self.max_log_scale)

    # -------------------------------------------------------------- optimiser
    def build_optimizer(
        self, total_steps: int
    ) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler]:
        """The optimizer over the trained parameters and its per-step cosine schedule.

        No weight decay on norms, biases and the logit scale (timm's rule: every tensor of
        at most one dimension, and every ``.bias``).
        """
        factory = self.optimizer_factory
        if factory is None:
            raise ValueError(
                "model.optimizer is required to train (a module restored from a "
                "checkpoint's hyperparameters has none; pass optimizer=...)"
            )
        weight_decay = getattr(factory, "keywords", {}).get("weight_decay", 0.0)
        optimizer = factory(param_groups_weight_decay(self, weight_decay))
        lr = optimizer.defaults["lr"]
        total = max(1, int(total_steps))
        floor = self.sched_cfg["min_lr"] / lr

        def cosine(step: int) -> float:
            progress = min(1.0, step / total)
            return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress))

        return optimizer, torch.optim.lr_scheduler.LambdaLR(optimizer, cosine)

    def configure_optimizers(self) -> dict:
        total = int(self.trainer.estimated_stepping_batches)
        self._schedule = {"total_steps": total, "max_epochs": int(self.trainer.max_epochs)}
        self._check_resumed_schedule()
        optimizer, scheduler = self.build_optimizer(total)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "step"},
        }

    def _check_resumed_schedule(self) -> None:
        """Refuse to resume with a different schedule length: the cosine would jump to the
        learning rate of another run's position (the smoke run: 1e-5 at the end of 2 epochs,
        1.36e-3 one step into a resume with 4)."""
        old, new = self._resumed_schedule, self._schedule
        if old is None or new is None or old["total_steps"] == new["total_steps"]:
            return
        raise ValueError(
            f"trainer.max_epochs={new['max_epochs']}: the checkpoint being resumed belongs to a "
            f"run planned for {old['max_epochs']} epochs ({old['total_steps']} optimizer steps "
            f"of its cosine learning-rate schedule), and this one would have "
            f"{new['total_steps']}, so its learning rate would jump mid-run. Resume with "
            f"trainer.max_epochs={old['max_epochs']} (and the same data settings); to train "
            "longer, start a new run from this one's weights: model.init_from=<its "
            "checkpoints/last.ckpt> (a fresh schedule over the new run's epochs)"
        )

    # ------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """Frozen parts are rebuilt from their weights source, never stored.

        The schedule's length is stored so a resume with another ``trainer.max_epochs`` is
        refused (see ``_check_resumed_schedule``). The RNG states are stored so a resumed run draws the same drop-path masks as an
        uninterrupted one (the data pipeline seeds itself from the epoch).
        """
        checkpoint["state_dict"] = {
            k: v for k, v in checkpoint["state_dict"].items() if not k.startswith(_FROZEN_PREFIXES)
        }
        if self._schedule is not None:
            checkpoint["lr_schedule"] = dict(self._schedule)
        checkpoint["rng_states"] = {"torch": torch.get_rng_state()}
        if torch.cuda.is_available():
            checkpoint["rng_states"]["cuda"] = torch.cuda.get_rng_state_all()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        weight = checkpoint["state_dict"].get("distill_head.weight")
        if weight is not None and self.distill_head is None:  # sized by the teacher in setup
            self.distill_head = nn.Linear(weight.shape[1], weight.shape[0])
        own = self.state_dict()
        checkpoint["state_dict"].update(
            {k: v for k, v in own.items() if k.startswith(_FROZEN_PREFIXES)}
        )
        self._resumed_schedule = checkpoint.get("lr_schedule")
        self._check_resumed_schedule()  # (strategies that restore after configure_optimizers)
        states = checkpoint.get("rng_states", {})
        if "torch" in states:
            torch.set_rng_state(states["torch"])
        if "cuda" in states and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(states["cuda"])

    # ----------------------------------------------------------------- stage 2
    def load_trained(self, source: str | os.PathLike) -> list[str]:
        """Start from an earlier stage's trained weights (not its optimizer state).

        Args:
            source: a training checkpoint (``.ckpt``: head, text projection and logit
                scale) or a ``ResiregVLM.save_pretrained`` export (head and text projection;
                the logit scale keeps its init).

        Returns:
            The names of the loaded tensors.
        """
        problem = init_from_problem(source)  # the config check's rule (resireg-train)
        if problem:
            raise FileNotFoundError(f"model.init_from={str(source)!r}: {problem}")
        path = Path(source).expanduser()
        if path.is_dir():
            return [f"vlm.{k}" for k in self.vlm.load_trained(path)]
        # weights-only: a pickle naming any other global is refused before it runs
        content = load_weights_only(path, f"model.init_from={str(source)!r}", map_location="cpu")
        if not isinstance(content, dict) or "state_dict" not in content:
            raise ValueError(
                f"model.init_from={str(source)!r} is not a Lightning training checkpoint "
                "(no state_dict) nor an export folder"
            )
        state = content["state_dict"]
        wanted = ("vlm.head.", "vlm.text_proj.", "logit_scale")
        trained = {k: v for k, v in state.items() if k.startswith(wanted)}
        if not any(k.startswith("vlm.head.") for k in trained):
            raise ValueError(f"model.init_from={str(source)!r} holds no language-head weights")
        missing, _ = self.load_state_dict(trained, strict=False)
        absent = [k for k in missing if k.startswith(wanted)]
        if absent:
            raise ValueError(f"model.init_from={str(source)!r} lacks {absent[:5]}")
        return sorted(trained)
