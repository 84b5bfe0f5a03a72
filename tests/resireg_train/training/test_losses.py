import pytest
import torch
from open_clip.loss import ClipLoss

from resireg_train.training.losses import ContrastiveLoss, distill_loss, warmup_factor


def test_contrastive_equals_open_clip_clip_loss():
    image, text = torch.randn(12, 32), torch.randn(12, 32)
    scale = torch.tensor(1 / 0.07)
    ours, logits, targets = ContrastiveLoss()(image, text, scale)
    ref = ClipLoss()(
        torch.nn.functional.normalize(image, dim=-1),
        torch.nn.functional.normalize(text, dim=-1),
        scale,
    )
    assert torch.allclose(ours, ref, atol=1e-6)
    assert logits.shape == (12, 12)
    assert torch.equal(targets, torch.arange(12))


def test_contrastive_gradients_flow_to_both_towers():
    image, text = torch.randn(4, 8, requires_grad=True), torch.randn(4, 8, requires_grad=True)
    loss, _, _ = ContrastiveLoss()(image, text, torch.tensor(10.0))
    loss.backward()
    assert image.grad.abs().sum() > 0 and text.grad.abs().sum() > 0


def test_distill_loss():
    a = torch.randn(2, 8, 3, 4)
    assert distill_loss(a, 3 * a).item() == pytest.approx(0.0, abs=1e-6)
    assert distill_loss(a, -a).item() == pytest.approx(2.0, abs=1e-6)
    with pytest.raises(ValueError, match="shapes differ"):
        distill_loss(a, a[:, :4])


def test_warmup_ramp():
    assert [warmup_factor(e, 4) for e in (0, 1, 2, 4, 10)] == [0.0, 0.25, 0.5, 1.0, 1.0]
    assert warmup_factor(0, 0) == 1.0
