import pytest
import torch
import torch.nn.functional as F
from torchmetrics.classification import MulticlassJaccardIndex

from resireg.ovss import (
    ADE20K_CLASSES,
    ORAD3D_CLASSES,
    SCANNET_CLASSES,
    TEMPLATES,
    SegmentationMetric,
    predict,
    text_prototypes,
    vocabulary,
)


def test_vocabularies():
    assert len(ADE20K_CLASSES) == 150 and len(set(ADE20K_CLASSES)) == 150
    assert len(ORAD3D_CLASSES) == 10
    assert len(SCANNET_CLASSES) == 37 and not any(c.startswith("other") for c in SCANNET_CLASSES)
    assert len(TEMPLATES) == 80
    assert vocabulary("orad3d") == ORAD3D_CLASSES
    with pytest.raises(ValueError, match="'nope'"):
        vocabulary("nope")


def test_metric_matches_torchmetrics_over_batches():
    k = 7
    ours = SegmentationMetric(k, ignore_index=255)
    ref = MulticlassJaccardIndex(num_classes=k, ignore_index=255, average="none")
    g = torch.Generator().manual_seed(0)
    for _ in range(4):
        target = torch.randint(0, k - 1, (2, 20, 30), generator=g)  # class k-1 never in target
        target[torch.rand(target.shape, generator=g) < 0.1] = 255
        pred = torch.where(
            torch.rand(target.shape, generator=g) < 0.6,
            target,
            torch.randint(0, k - 2, target.shape, generator=g),
        )
        pred[pred == 255] = 0
        ours.update(pred, target)
        ref.update(pred, target)
    out = ours.compute()
    iou_ref = ref.compute()
    iou = torch.tensor(out["iou"])
    present = ~torch.isnan(iou)
    assert present.sum() == k - 1  # class k-1: never predicted nor labelled -> excluded
    assert torch.allclose(iou[present].float(), iou_ref[present].float(), atol=1e-6)
    assert out["miou"] == pytest.approx(iou_ref[present].mean().item(), abs=1e-6)


def test_metric_fmiou_accuracy_and_reduce_zero_label():
    m = SegmentationMetric(2, reduce_zero_label=True)
    target = torch.tensor([[0, 1, 1, 2, 2, 2, 255]])  # 0 -> ignore; 1 -> class 0; 2 -> class 1
    pred = torch.tensor([[1, 0, 1, 1, 1, 0, 0]])
    m.update(pred, target)
    out = m.compute()
    # class 0: tp=1, gt=2, pred=2 -> IoU 1/3 ; class 1: tp=2, gt=3, pred=3 -> IoU 2/4
    assert out["iou"] == pytest.approx([1 / 3, 0.5])
    assert out["miou"] == pytest.approx((1 / 3 + 0.5) / 2)
    assert out["fmiou"] == pytest.approx(2 / 5 * 1 / 3 + 3 / 5 * 0.5)
    assert out["acc"] == pytest.approx(3 / 5)


def test_metric_rejects_out_of_range_labels_naming_the_stored_value():
    m = SegmentationMetric(3)
    with pytest.raises(ValueError, match=r"class id 5; valid ids are 0\.\.2 and 255"):
        m.update(torch.zeros(4, dtype=torch.long), torch.tensor([0, 1, 5, 2]))
    # With ADE20K's zero-label shift the message names the value in the file (200, not 199),
    # ids 0..150 are valid (150 is class 149) and 255 stays ignored.
    ade = SegmentationMetric(150, reduce_zero_label=True)
    ade.update(torch.zeros(3, dtype=torch.long), torch.tensor([0, 150, 255]))
    assert ade.confusion[149, 0] == 1 and ade.confusion.sum() == 1
    with pytest.raises(ValueError, match=r"class ids 151, 200; valid ids are 0\.\.150 \(0 = other"):
        ade.update(torch.zeros(3, dtype=torch.long), torch.tensor([200, 151, 3]))


def test_metric_confusion_equals_sklearn_with_zero_label_reduction():
    """ADE20K's convention: label 0 is ignored, label c is class c - 1; 255 is ignored."""
    from sklearn.metrics import confusion_matrix

    metric = SegmentationMetric(4, reduce_zero_label=True)
    target = torch.randint(0, 5, (2, 30))
    target[0, :3] = 255
    preds = torch.randint(0, 4, (2, 30))
    for p, t in zip(preds, target, strict=True):
        metric.update(p, t)
    keep = (target != 0) & (target != 255)
    expected = confusion_matrix((target[keep] - 1).numpy(), preds[keep].numpy(), labels=range(4))
    assert torch.equal(metric.confusion, torch.from_numpy(expected))


def test_text_prototypes_average_normalised_template_embeddings():
    table = {}

    def encode(texts):
        return torch.stack([table.setdefault(t, torch.randn(16) * (1 + len(t))) for t in texts])

    templates = (lambda c: f"a {c}", lambda c: f"the {c}.", lambda c: f"photo of {c}")
    protos = text_prototypes(encode, ["cat", "dog"], templates, batch_size=2)
    assert protos.shape == (2, 16)
    for i, name in enumerate(["cat", "dog"]):
        ref = torch.stack([F.normalize(table[t(name)], dim=0) for t in templates]).mean(0)
        assert torch.allclose(protos[i], F.normalize(ref, dim=0), atol=1e-6)


def test_predict_equals_upsample_then_argmax():
    dense = torch.randn(2, 8, 5, 7)
    protos = torch.randn(4, 8)
    labels = predict(dense, protos, (23, 31))
    logits = torch.einsum("bdhw,kd->bkhw", F.normalize(dense, dim=1), F.normalize(protos, dim=1))
    ref = torch.softmax(100 * F.interpolate(logits, size=(23, 31), mode="nearest"), dim=1).argmax(1)
    assert torch.equal(labels, ref)


@pytest.mark.parametrize("reduce_zero_label", [False, True])
def test_update_grid_equals_update_of_the_upsampled_prediction(reduce_zero_label):
    """The engine's per-batch form (label blocks against the grid, then the grid prediction)
    gives the confusion matrix of upsampling the prediction to the label (predict + update),
    also for sizes that are not multiples of the grid and with ignored pixels."""
    from resireg.ovss import predict_grid

    g = torch.Generator().manual_seed(0)
    k = 6
    dense, protos = torch.randn(3, 8, 5, 7, generator=g), torch.randn(k, 8, generator=g)
    sizes = [(37, 53), (5, 7), (12, 30)]  # upsampling by 7.4 x 7.57, 1, 2.4 x 4.29
    top = k + 1 if reduce_zero_label else k
    labels = [torch.randint(0, top, size, generator=g) for size in sizes]
    labels[0][:4, :9] = 255  # ignored pixels
    reference = SegmentationMetric(k, reduce_zero_label=reduce_zero_label)
    for i, label in enumerate(labels):
        reference.update(predict(dense[i : i + 1], protos, label.shape)[0], label)
    ours = SegmentationMetric(k, reduce_zero_label=reduce_zero_label)
    pred = predict_grid(dense, protos)
    for i, label in enumerate(labels):
        ours.update_grid(pred[i], ours.blocks(label, (5, 7)))
    assert reference.confusion.sum() > 0
    assert torch.equal(ours.confusion, reference.confusion)
    # An invalid class id is rejected by blocks as by update.
    with pytest.raises(ValueError, match="class id 9"):
        ours.blocks(torch.full((4, 4), 9), (5, 7))
