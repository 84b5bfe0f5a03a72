"""The OVSS field's protocol (conf/protocol/ovss8.yaml; docs/protocol.md section 6) against
hand-computed cases and independent references written from the peers' sources:

- the resize (mmcv's keep-ratio rescale with the longer side capped), the windows, the bilinear
  upsampling and the background threshold, each on a case worked out by hand;
- the sliding window against mmsegmentation's ``EncoderDecoder.slide_inference`` followed by
  SCLIP's / NACLIP's post-processing (transcribed below), on an encoder whose output is known
  (each patch's mean colour), through the whole engine;
- the metric against mmsegmentation's ``IoUMetric`` (``intersect_and_union`` with
  ``torch.histc`` and ``total_area_to_metrics``, transcribed in numpy below), absent classes,
  classes only predicted, ignored pixels and reduce_zero_label included.
"""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from resireg.method.variants import build_variants
from resireg.models import DenseEncoder, DenseOutput, InputRule
from resireg.ovss import SegmentationMetric
from resireg_train.data.segmentation import SegmentationSet
from resireg_train.data.windows import WindowRules, rescaled_size, window_rules
from resireg_train.evaluation.ovss.engine import OVSSEngine
from resireg_train.evaluation.ovss.slide import (
    classify,
    crop_windows,
    stitch,
    to_label,
    window_boxes,
    window_logits,
)


# ------------------------------------------------------------------ hand-computed cases
def test_resize_is_mmcvs_keep_ratio_rescale_with_the_longer_side_capped():
    """scale=(2048, 336): factor min(336 / short, 2048 / long), sides int(x * f + 0.5)."""
    assert rescaled_size((375, 500), 336, 2048) == (336, 448)  # 0.896: 336.0, 448.0
    assert rescaled_size((333, 500), 336, 2048) == (336, 505)  # 1.009009: 504.5 + 0.5 -> 505
    assert rescaled_size((100, 1000), 336, 2048) == (205, 2048)  # capped: 2.048 -> 204.8 -> 205
    assert rescaled_size((1024, 2048), 560, 2048) == (560, 1120)  # Cityscapes
    assert rescaled_size((7, 9), None, None) == (7, 9)
    ovss8, paper = window_rules("ovss8"), window_rules("paper")
    assert ovss8.resized_size((333, 500), 336, 16) == (336, 505)  # windows: any size
    # the whole image: sides rounded to the patch, as the paper's rule (patch_grid_size)
    from resireg.models.images import patch_grid_size

    for size in ((375, 500), (333, 500), (480, 640), (17, 900)):
        assert paper.resized_size(size, 576, 14) == patch_grid_size(size, 576, 14)
    capped = WindowRules(2048, False, None, None, "bilinear", None, None)
    assert capped.resized_size((100, 1000), 336, 16) == (208, 2048)  # 204.8 -> 13 patches


def test_windows_are_mmsegs_positions():
    """ceil((side - crop) / stride) + 1 windows per axis, the last moved back to the border; an
    image smaller than the window gets one window of its own size."""
    ys = [(0, 224), (112, 336)]
    xs = [(0, 224), (112, 336), (224, 448)]
    assert window_boxes(336, 448, 224, 112) == [(y1, y2, x1, x2) for y1, y2 in ys for x1, x2 in xs]
    assert window_boxes(224, 300, 224, 112) == [(0, 224, 0, 224), (0, 224, 76, 300)]
    assert window_boxes(100, 150, 224, 112) == [(0, 100, 0, 150)]


def test_windows_averaged_and_upsampled_bilinearly_by_hand():
    """Two windows of one class map, overlapping on one column: that column holds their mean;
    a 1 x 2 map resized bilinearly (align_corners=False) to 1 x 4 is [0, .25, .75, 1]."""
    boxes = window_boxes(1, 3, 2, 1)
    assert boxes == [(0, 1, 0, 2), (0, 1, 1, 3)]
    windows = [torch.tensor([[[1.0, 3.0]]]), torch.tensor([[[5.0, 7.0]]])]
    assert stitch(windows, boxes, (1, 3)).tolist() == [[[1.0, 4.0, 7.0]]]
    up = to_label(torch.tensor([[[0.0, 1.0]]]), (1, 4))
    assert up.tolist() == [[[0.0, 0.25, 0.75, 1.0]]]


def test_background_threshold_and_synonyms_by_hand():
    """Names [background, cat, kitty] (cat and kitty are class 1), scale 10, threshold 0.5:
    softmax(10 x logits) worked out by hand per pixel."""
    name_class = torch.tensor([0, 1, 1])
    logits = torch.tensor([
        [0.1, 0.5, 0.45],   # p = e^1, e^5, e^4.5 / sum = .011, .616, .373: class 1, kept
        [0.3, 0.35, 0.34],  # p = 20.09, 33.12, 29.96 / 83.17: best .398 < .5 -> background
        [0.6, 0.2, 0.1],    # background anyway
        [0.2, 0.1, 0.4],    # kitty: p = 7.39, 2.72, 54.60 / 64.71 = .844 -> class 1
    ]).T.reshape(3, 1, 4)  # fmt: skip
    assert classify(logits, name_class).tolist() == [[1, 1, 0, 1]]
    assert classify(logits, name_class, 0.5, 10.0).tolist() == [[1, 0, 0, 1]]
    assert classify(logits, name_class, 0.3, 10.0).tolist() == [[1, 1, 0, 1]]  # .398 >= .3


def test_the_protocols_impossible_combinations_name_their_keys():
    spec = {**{k: v for k, v in vars(window_rules("ovss8")).items() if k != "name"},
            "protocol": "ovss8"}  # fmt: skip
    assert WindowRules.from_spec(spec, patch_size=16).sliding
    bad = [({"slide_stride": None}, r"dataset\.slide_crop=224, dataset\.slide_stride=None: set both"),
           ({"slide_stride": 300}, r"dataset\.slide_stride=300: expected at most dataset\.slide_crop=224"),
           ({"upsample": "nearest"}, r"dataset\.upsample='nearest': sliding windows average"),
           ({"background_threshold": 0.1}, r"background_logit_scale=None: the threshold applies"),
           ({"background_threshold": 1.5, "background_logit_scale": 40},
            r"dataset\.background_threshold=1\.5: expected null or a number in \(0, 1\)"),
           ({"slide_crop": 100, "slide_stride": 50}, r"dataset\.slide_crop=100: expected a multiple "
            r"of the encoder's patch size 16")]  # fmt: skip
    for change, message in bad:
        with pytest.raises(ValueError, match=message):
            WindowRules.from_spec({**spec, **change}, patch_size=16)


# -------------------------------------------------- the slide, against mmseg's own loop
def mmseg_slide_inference(inputs, crop, stride, encode_decode, out_channels):
    """mmsegmentation 1.x ``EncoderDecoder.slide_inference`` (mmseg/models/segmentors/
    encoder_decoder.py), transcribed: the windows' logits padded into place, summed, divided by
    the count of windows over each pixel."""
    h_stride, w_stride = stride, stride
    h_crop, w_crop = crop, crop
    batch_size, _, h_img, w_img = inputs.size()
    h_grids = max(h_img - h_crop + h_stride - 1, 0) // h_stride + 1
    w_grids = max(w_img - w_crop + w_stride - 1, 0) // w_stride + 1
    preds = inputs.new_zeros((batch_size, out_channels, h_img, w_img))
    count_mat = inputs.new_zeros((batch_size, 1, h_img, w_img))
    for h_idx in range(h_grids):
        for w_idx in range(w_grids):
            y1 = h_idx * h_stride
            x1 = w_idx * w_stride
            y2 = min(y1 + h_crop, h_img)
            x2 = min(x1 + w_crop, w_img)
            y1 = max(y2 - h_crop, 0)
            x1 = max(x2 - w_crop, 0)
            crop_img = inputs[:, :, y1:y2, x1:x2]
            crop_seg_logit = encode_decode(crop_img)
            preds += F.pad(crop_seg_logit, (int(x1), int(preds.shape[3] - x2), int(y1),
                                            int(preds.shape[2] - y2)))  # fmt: skip
            count_mat[:, :, y1:y2, x1:x2] += 1
    assert (count_mat == 0).sum() == 0
    return preds / count_mat


def sclip_postprocess(seg_logits, query_idx, logit_scale, prob_thd):
    """SCLIP clip_segmentor.py / NACLIP naclip.py ``postprocess_result`` for one image: softmax
    over the queries at ``logit_scale``, each class's best query, argmax, class 0 below
    ``prob_thd``."""
    seg_logits = (seg_logits * logit_scale).softmax(0)
    num_cls, num_queries = max(query_idx) + 1, len(query_idx)
    if num_cls != num_queries:
        seg_logits = seg_logits.unsqueeze(0)
        cls_index = F.one_hot(torch.tensor(query_idx))
        cls_index = cls_index.T.view(num_cls, num_queries, 1, 1)
        seg_logits = (seg_logits * cls_index).max(1)[0]
    seg_pred = seg_logits.argmax(0, keepdim=True)
    seg_pred[seg_logits.max(0, keepdim=True)[0] < prob_thd] = 0
    return seg_pred[0]


#: The colour encoder's vocabulary: one direction per name (RGB), the names per class.
NAMES = {"grey": (1.0, 1.0, 1.0), "red": (1.0, 0.0, 0.0), "crimson": (0.9, 0.1, 0.2),
         "green": (0.0, 1.0, 0.0), "blue": (0.0, 0.0, 1.0)}  # fmt: skip
CLASSES = (("grey",), ("red", "crimson"), ("green",), ("blue",))


class MeanColour(DenseEncoder):
    """Known output: each 8 x 8 patch's mean colour (intermediates and language tokens), and
    for a prompt the colour of the name it holds."""

    def __init__(self):
        super().__init__()
        self.anchor = torch.nn.Parameter(torch.zeros(1))

    @property
    def input_rule(self):
        return InputRule(8, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))

    def encode(self, images):
        pooled = F.avg_pool2d(images, 8) + 0.05  # never a zero vector
        return DenseOutput(pooled, pooled, None)

    def encode_text(self, texts):
        out = []
        for text in texts:
            (name,) = [n for n in NAMES if f" {n}" in f" {text}".replace(".", " ")][:1] or ["?"]
            out.append(torch.tensor(NAMES[name]))
        return F.normalize(torch.stack(out), dim=-1)


def _scene(seed, size=(48, 80)):
    """A blocky image (red, crimson-ish, green, blue, grey blocks, noise) and its label."""
    rng = np.random.default_rng(seed)
    h, w = size
    colours = np.array(
        [[128, 128, 128], [230, 20, 20], [200, 30, 50], [20, 200, 30], [30, 30, 220]]
    )
    classes = np.array([0, 1, 1, 2, 3])
    pick = rng.integers(0, 5, size=(h // 16, w // 16))
    image = colours[pick].repeat(16, 0).repeat(16, 1) + rng.normal(0, 25, (h, w, 3))
    label = classes[pick].repeat(16, 0).repeat(16, 1).astype(np.uint8)
    label[::7, :] = 255  # ignored rows
    return Image.fromarray(np.clip(image, 0, 255).astype(np.uint8)), label


@pytest.mark.parametrize("crop", [32, None])
def test_the_engines_slide_equals_mmsegs_slide_inference_and_the_peers_postprocessing(crop):
    """The engine's sliding windows (ovss8's rule, 32 px windows every 16 px here) on the colour
    encoder with BB, against the transcribed mmseg loop and SCLIP's post-processing on the same
    resized images: the confusion matrices are equal, pixel for pixel. Without windows (NACLIP's
    VOC configs, ``slide_crop=0``): the whole input's logits, bilinear to the input, then to the
    label (NACLIP's ``forward_feature`` and ``predict``)."""
    scenes = [_scene(s) for s in range(3)]
    protocol = WindowRules(None, False, crop, crop and 16, "bilinear", 0.5, 40.0, "ovss8")
    ds = SegmentationSet("colours", [c[0] for c in CLASSES], lambda i: scenes[i],
                         lambda i: (48, 80), 3, short_side=40, patch_size=8,
                         windows=protocol, names=CLASSES)  # fmt: skip
    encoder = MeanColour().eval()
    variants = build_variants(["bb"], {})
    engine = OVSSEngine(ds, batch_size=1, num_workers=0)
    result = engine.run(encoder, variants)
    assert result.images == 3

    query_idx = [k for k, names in enumerate(CLASSES) for _ in names]
    protos = F.normalize(torch.tensor([NAMES[n] for names in CLASSES for n in names]), dim=-1)

    def forward_feature(crop):  # SCLIP's forward_feature with the known features
        feats = F.normalize(F.avg_pool2d(crop, 8) + 0.05, dim=1)
        logits = torch.einsum("bdhw,qd->bqhw", feats, protos)
        return F.interpolate(logits, size=crop.shape[-2:], mode="bilinear")

    confusion = np.zeros((4, 4), dtype=np.int64)
    for i in range(3):
        image = ds[i]["image"][None]  # the resized image the engine saw
        if crop:
            assert tuple(image.shape[-2:]) == (40, 67)  # mmcv's size: windows take any
            preds = mmseg_slide_inference(image, 32, 16, forward_feature, len(query_idx))
        else:
            assert tuple(image.shape[-2:]) == (40, 64)  # whole patches: 67 -> 64
            preds = forward_feature(image)
        logits = F.interpolate(preds, size=(48, 80), mode="bilinear")[0]
        pred = sclip_postprocess(logits, query_idx, 40.0, 0.5).numpy()
        label = scenes[i][1]
        keep = label != 255
        confusion += np.bincount(label[keep].astype(np.int64) * 4 + pred[keep],
                                 minlength=16).reshape(4, 4)  # fmt: skip
    np.testing.assert_array_equal(result.metrics["bb"].confusion.numpy(), confusion)
    assert confusion[0, 0] > 0 and confusion[1, 1] > 0 and np.trace(confusion) > confusion.sum() / 2


def test_a_window_larger_than_the_image_is_padded_to_whole_patches_and_cut_back():
    """An image smaller than the window: one window, padded to the patch size at the bottom /
    right for the encoder, its logits cut back before stitching: the stitched logits equal the
    logits of the unpadded image's features upsampled over the padded size and cut."""
    torch.manual_seed(0)
    image = torch.rand(1, 3, 20, 30)
    boxes = window_boxes(20, 30, 32, 16)
    crops = crop_windows(image, boxes, 32, 8)
    assert crops.shape == (1, 3, 24, 32) and torch.equal(crops[0, :, :20, :30], image[0])
    assert crops[0, :, 20:].abs().sum() == 0 and crops[0, :, :, 30:].abs().sum() == 0
    protos = F.normalize(torch.rand(5, 3), dim=-1)
    dense = F.avg_pool2d(crops, 8) + 0.05
    logits = stitch([window_logits(dense, protos, (24, 32))[0]], boxes, (20, 30))
    expected = F.interpolate(torch.einsum("bdhw,qd->bqhw", F.normalize(dense, dim=1), protos),
                             size=(24, 32), mode="bilinear")[0, :, :20, :30]  # fmt: skip
    torch.testing.assert_close(logits, expected)


# --------------------------------------------------- the metric, against mmseg's IoUMetric
def mmseg_iou_metric(pairs, num_classes, ignore_index=255, reduce_zero_label=False):
    """mmsegmentation 1.x ``IoUMetric`` (mmseg/evaluation/metrics/iou_metric.py) transcribed in
    numpy: ``LoadAnnotations``' reduce_zero_label (0 -> 255, c -> c - 1, 254 -> 255), per image
    ``intersect_and_union`` (pixels of ``ignore_index`` dropped, areas by ``torch.histc`` with
    ``bins=num_classes, min=0, max=num_classes - 1``: np.histogram over the same range), areas
    summed over the dataset, ``IoU = intersect / union`` (NaN where the union is 0), ``aAcc``,
    and the ``nanmean``."""
    totals = np.zeros((4, num_classes))
    for pred, label in pairs:
        label = label.astype(np.int64)
        if reduce_zero_label:
            label = label.copy()
            label[label == 0] = 255
            label = label - 1
            label[label == 254] = 255
        mask = label != ignore_index
        pred, label = pred[mask], label[mask]
        intersect = pred[pred == label]
        hist = lambda x: np.histogram(x.astype(float), bins=num_classes,  # noqa: E731
                                      range=(0, num_classes - 1))[0]  # fmt: skip
        area_i, area_p, area_l = hist(intersect), hist(pred), hist(label)
        totals += np.stack([area_i, area_p + area_l - area_i, area_p, area_l])
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = totals[0] / totals[1]
    return {"iou": iou, "miou": np.nanmean(iou), "aAcc": totals[0].sum() / totals[3].sum()}


@pytest.mark.parametrize("reduce_zero_label", [False, True])
def test_the_metric_equals_mmsegs_iou_metric(reduce_zero_label):
    """Six images of random labels and predictions over 7 classes: class 5 appears nowhere
    (NaN, left out of the mean), class 6 only in predictions (IoU 0, counted), a band of ignored
    pixels; with reduce_zero_label (ADE20K, VOC20, PC59) label 0 is ignored too."""
    rng = np.random.default_rng(3)
    k = 7
    metric = SegmentationMetric(k, 255, reduce_zero_label)
    pairs = []
    for _ in range(6):
        size = (int(rng.integers(9, 20)), int(rng.integers(9, 20)))
        stored = rng.choice([0, 1, 2, 3, 4, 5], size=size) if reduce_zero_label else (
            rng.choice([0, 1, 2, 3, 4], size=size))  # fmt: skip
        stored[:, 2] = 255
        pred = rng.choice([0, 1, 2, 3, 4, 6], size=size, p=[0.2, 0.2, 0.2, 0.2, 0.1, 0.1])
        metric.update(torch.from_numpy(pred), torch.from_numpy(stored))
        pairs.append((pred, stored))
    ours, ref = metric.compute(), mmseg_iou_metric(pairs, k, reduce_zero_label=reduce_zero_label)
    np.testing.assert_allclose(np.array(ours["iou"]), ref["iou"], rtol=1e-12, equal_nan=True)
    assert math.isnan(ours["iou"][5]) and ours["iou"][6] == 0.0
    assert ours["miou"] == pytest.approx(ref["miou"], rel=1e-12)
    assert ours["acc"] == pytest.approx(ref["aAcc"], rel=1e-12)
