"""Training losses of the 25M VLM: contrastive (open_clip's, DDP-aware), patch distillation, warm-up."""

from __future__ import annotations

import torch
import torch.distributed as dist
import torch.nn.functional as F
from open_clip.loss import ClipLoss
from torch import Tensor

__all__ = ["ContrastiveLoss", "distill_loss", "warmup_factor"]


class ContrastiveLoss(ClipLoss):
    """open_clip's ``ClipLoss`` on the global batch, plus this rank's logits for retrieval.

    Bidirectional InfoNCE over in-batch negatives. Under DDP every rank gathers the
    features of all ranks (``local_loss=False``, ``gather_with_grad=False``: the other
    ranks' rows are constants, this rank's rows keep their graph), so the loss equals the
    single-process loss on the same global batch. ``ClipLoss`` reads the rank and world
    size at construction, before Lightning starts the process group, so they are refreshed
    on every call.

    Args in ``forward``:
        image: ``[B, D]`` image embeddings (normalised here).
        text: ``[B, D]`` text embeddings (normalised here).
        logit_scale: scalar, the *exponentiated* scale.

    Returns:
        ``(loss, logits, targets)``: this rank's rows of the image->text logits and the
        column of each row's own caption (the extra open_clip does not return; it gives the
        retrieval accuracy).
    """

    def __init__(self) -> None:
        super().__init__(local_loss=False, gather_with_grad=False, cache_labels=False)
        self._logits_per_image: Tensor | None = None

    def get_logits(self, *args, **kwargs):  # keep the global logits for the local rows
        logits_per_image, logits_per_text = super().get_logits(*args, **kwargs)
        self._logits_per_image = logits_per_image
        return logits_per_image, logits_per_text

    def forward(  # type: ignore[override]
        self, image: Tensor, text: Tensor, logit_scale: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        distributed = dist.is_available() and dist.is_initialized()
        self.rank = dist.get_rank() if distributed else 0
        self.world_size = dist.get_world_size() if distributed else 1
        image = F.normalize(image.float(), dim=-1)
        text = F.normalize(text.float(), dim=-1)
        loss = super().forward(image, text, logit_scale)
        logits, self._logits_per_image = self._logits_per_image, None
        b = image.shape[0]
        local = slice(self.rank * b, (self.rank + 1) * b)
        targets = torch.arange(logits.shape[0], device=image.device)[local]
        return loss, logits[local], targets


def distill_loss(student: Tensor, teacher: Tensor) -> Tensor:
    """Mean over patches of ``1 - cos(student, teacher)`` for ``[B, D, h, w]`` maps."""
    if student.shape != teacher.shape:
        raise ValueError(
            f"student {tuple(student.shape)} and teacher {tuple(teacher.shape)} shapes differ"
        )
    return (1.0 - F.cosine_similarity(student.float(), teacher.float(), dim=1)).mean()


def warmup_factor(epoch: float, warmup_epochs: float) -> float:
    """Linear ramp from 0 at epoch 0 to 1 at ``warmup_epochs`` (fractional epochs), then 1."""
    if warmup_epochs <= 0:
        return 1.0
    return float(min(1.0, max(0.0, epoch / warmup_epochs)))
