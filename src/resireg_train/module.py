"""LightningModule training the 25M VLM's language head and text projection.

Frozen: EUPE backbone, text tower, RadSeg teacher (excluded from checkpoints; they are
rebuilt from their weights source). Trained: language head, text projection, logit
scale, and (stage 1) the distillation head mapping teacher features to the head width.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from resireg.models import ResiregVLM, build_teacher
from resireg_train.losses import ContrastiveLoss, distill_loss, warmup_factor

__all__ = ["ResiregModule"]

_FROZEN_PREFIXES = ("vlm.backbone.", "vlm.text.", "teacher.")


class ResiregModule(L.LightningModule):
    """Two-stage training of the dense VLM (DESIGN.md section 6).

    Args:
        backbone, head, text: model configs (see :meth:`ResiregVLM.build`).
        teacher: teacher config (``{"kind": "radseg" | "conv", ...}``); loaded only when the
            distillation scale is > 0.
        optimizer: ``{"name", "lr", "weight_decay", ...}``: a ``torch.optim`` class name
            (default ``AdamW``) and its keyword arguments.
        scheduler: ``{"min_lr"}``: per-step cosine from ``lr`` to ``min_lr``.
        loss: ``{"contrastive": {"scale", "warmup_epochs"}, "distill": {"scale", "warmup_epochs"}}``.
        logit_scale: ``{"init", "max"}`` (learned in log space, clamped after every step).
        steps_per_epoch: optimizer steps per epoch (for fractional-epoch warm-up).
    """

    def __init__(
        self,
        backbone: dict,
        head: dict,
        text: dict,
        teacher: dict | None = None,
        optimizer: dict | None = None,
        scheduler: dict | None = None,
        loss: dict | None = None,
        logit_scale: dict | None = None,
        steps_per_epoch: int = 1000,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.optim_cfg = {"name": "AdamW", "lr": 6e-4, "weight_decay": 0.05, **(optimizer or {})}
        if not isinstance(getattr(torch.optim, self.optim_cfg["name"], None), type):
            raise ValueError(
                f"model.optimizer.name={self.optim_cfg['name']!r} is not a torch.optim optimizer"
            )
        self.sched_cfg = {"min_lr": 1e-6, **(scheduler or {})}
        loss = loss or {}
        self.contrastive_cfg = {"scale": 1.0, "warmup_epochs": 0.0, **loss.get("contrastive", {})}
        self.distill_cfg = {"scale": 0.0, "warmup_epochs": 0.0, **loss.get("distill", {})}
        ls = {"init": 1 / 0.07, "max": 100.0, **(logit_scale or {})}
        self.max_log_scale = math.log(ls["max"])
        self.steps_per_epoch = steps_per_epoch

        self.vlm = ResiregVLM.build(backbone, head, text)
        self.logit_scale = nn.Parameter(torch.tensor(math.log(ls["init"])))
        self.contrastive = ContrastiveLoss()
        self.teacher = None
        self.distill_head = None
        if self.distill_cfg["scale"] > 0:
            if teacher is None:
                raise ValueError("model.loss.distill.scale > 0 needs a model.teacher config")
            self.teacher = build_teacher(**teacher)
            self.distill_head = nn.Linear(self.teacher.out_dim, self.vlm.head.out_dim)

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
        out = self.vlm.head(self.vlm.backbone(images))
        text = self.vlm.text_proj(self.vlm.text(captions).to(images.device))
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
                self.teacher(images, out.patches.shape[-2:]).permute(0, 2, 3, 1)
            )
            loss_d = distill_loss(out.patches, target.permute(0, 3, 1, 2))
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
        # Examples the data pipeline dropped before this batch, summed over the epoch and ranks.
        for reason in ("invalid", "small"):
            if f"skipped_{reason}" in batch:
                self.log(
                    f"data/skipped_{reason}",
                    batch[f"skipped_{reason}"].sum().float(),
                    on_step=False,
                    on_epoch=True,
                    reduce_fx="sum",
                    sync_dist=True,
                )
        return loss

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        with torch.no_grad():
            self.logit_scale.clamp_(max=self.max_log_scale)

    # -------------------------------------------------------------- optimiser
    def build_optimizer(
        self, total_steps: int
    ) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler]:
        """The optimizer over the trained parameters and its per-step cosine schedule."""
        decay, no_decay = [], []
        for p in self.parameters():
            if not p.requires_grad:
                continue
            # No weight decay on norms, biases and the logit scale (all 0-/1-d tensors).
            (no_decay if p.ndim <= 1 else decay).append(p)
        cfg = {k: tuple(v) if isinstance(v, list) else v for k, v in self.optim_cfg.items()}
        optimizer = getattr(torch.optim, cfg.pop("name"))(
            [{"params": decay}, {"params": no_decay, "weight_decay": 0.0}], **cfg
        )
        total = max(1, int(total_steps))
        floor = self.sched_cfg["min_lr"] / cfg["lr"]

        def cosine(step: int) -> float:
            progress = min(1.0, step / total)
            return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress))

        return optimizer, torch.optim.lr_scheduler.LambdaLR(optimizer, cosine)

    def configure_optimizers(self) -> dict:
        optimizer, scheduler = self.build_optimizer(self.trainer.estimated_stepping_batches)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "step"},
        }

    # ------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """Frozen parts are rebuilt from their weights source, never stored.

        The RNG states are stored so a resumed run draws the same drop-path masks as an
        uninterrupted one (the data pipeline seeds itself from the epoch).
        """
        checkpoint["state_dict"] = {
            k: v for k, v in checkpoint["state_dict"].items() if not k.startswith(_FROZEN_PREFIXES)
        }
        checkpoint["rng_states"] = {"torch": torch.get_rng_state()}
        if torch.cuda.is_available():
            checkpoint["rng_states"]["cuda"] = torch.cuda.get_rng_state_all()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        own = self.state_dict()
        checkpoint["state_dict"].update(
            {k: v for k, v in own.items() if k.startswith(_FROZEN_PREFIXES)}
        )
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
        path = Path(source)
        if path.is_dir():
            return [f"vlm.{k}" for k in self.vlm.load_trained(path)]
        if not path.is_file():
            raise FileNotFoundError(
                f"model.init_from={str(source)!r} is neither a checkpoint nor an export directory"
            )
        state = torch.load(path, map_location="cpu", weights_only=False)["state_dict"]
        wanted = ("vlm.head.", "vlm.text_proj.", "logit_scale")
        trained = {k: v for k, v in state.items() if k.startswith(wanted)}
        if not any(k.startswith("vlm.head.") for k in trained):
            raise ValueError(f"model.init_from={str(source)!r} holds no language-head weights")
        missing, _ = self.load_state_dict(trained, strict=False)
        absent = [k for k in missing if k.startswith(wanted)]
        if absent:
            raise ValueError(f"model.init_from={str(source)!r} lacks {absent[:5]}")
        return sorted(trained)
