"""Training losses of the 25M VLM: contrastive (DDP-aware), patch distillation, warm-up."""

from __future__ import annotations

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["ContrastiveLoss", "distill_loss", "warmup_factor", "gather_keep_local_grad"]


def gather_keep_local_grad(x: Tensor) -> Tensor:
    """All-gather ``x`` ``[B, D]`` from every rank -> ``[W*B, D]``; this rank's slice keeps its graph.

    The other ranks' slices are constants here (their gradients flow on their own ranks),
    which is open_clip's default ``gather_with_grad=False`` behaviour.
    """
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return x
    parts = [torch.empty_like(x) for _ in range(dist.get_world_size())]
    dist.all_gather(parts, x.detach().contiguous())
    parts[dist.get_rank()] = x
    return torch.cat(parts)


class ContrastiveLoss(nn.Module):
    """Bidirectional InfoNCE over in-batch negatives, gathered across DDP ranks.

    Every rank builds the logits of the whole global batch (``W*B x W*B``), so the loss
    equals the single-process loss on the same global batch.

    Args in ``forward``:
        image: ``[B, D]`` image embeddings (normalised here).
        text: ``[B, D]`` text embeddings (normalised here).
        logit_scale: scalar, the *exponentiated* scale.

    Returns:
        ``(loss, logits, targets)``: this rank's rows of the image->text logits and the
        column of each row's own caption (for retrieval accuracy).
    """

    def forward(
        self, image: Tensor, text: Tensor, logit_scale: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        image = F.normalize(image.float(), dim=-1)
        text = F.normalize(text.float(), dim=-1)
        all_image, all_text = gather_keep_local_grad(image), gather_keep_local_grad(text)
        logits_per_image = logit_scale * all_image @ all_text.T
        labels = torch.arange(logits_per_image.shape[0], device=image.device)
        loss = (
            F.cross_entropy(logits_per_image, labels) + F.cross_entropy(logits_per_image.T, labels)
        ) / 2
        b = image.shape[0]
        rank = dist.get_rank() if dist.is_available() and dist.is_initialized() else 0
        local = slice(rank * b, (rank + 1) * b)
        return loss, logits_per_image[local], labels[local]


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
