"""One-image segmentation (issue 39 item 3): ``resireg.segment`` against a reference computed
from the model's own passes with numpy, and ``resireg-segment`` on a scikit-image photograph
with the smoke (tiny) export: label map, overlay (size, legend) and similarity maps."""

import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from PIL import Image

import resireg
from resireg.models import ResiregVLM
from resireg.ovss import TEMPLATES

skdata = pytest.importorskip("skimage.data")
pytest.importorskip("matplotlib")

LABELS = ("person", "sky", "rocket")


@pytest.fixture(scope="module")
def photo():
    return skdata.astronaut()  # 512 x 512 RGB, shipped with scikit-image


def _reference(model, image, labels, variant):
    """The protocol by hand: features of the variant, text prototypes as the normalised mean
    of the normalised template embeddings, cosine, argmax (softmax keeps it), nearest
    upsampling by index arithmetic (PyTorch's 'nearest': floor(i * in / out))."""
    with torch.no_grad():
        dense = model.encode_image(torch.from_numpy(image).permute(2, 0, 1), variant)[0].numpy()
        prompts = [t(name) for name in labels for t in TEMPLATES]
        text = model.encode_text(prompts).numpy().reshape(len(labels), len(TEMPLATES), -1)
    text = text / np.linalg.norm(text, axis=2, keepdims=True)
    protos = text.mean(1)
    protos /= np.linalg.norm(protos, axis=1, keepdims=True)
    feats = dense / np.maximum(np.linalg.norm(dense, axis=0, keepdims=True), 1e-12)
    sim = np.einsum("dhw,kd->khw", feats, protos)
    h, w = image.shape[:2]
    rows = np.floor(np.arange(h) * sim.shape[1] / h).astype(int)
    cols = np.floor(np.arange(w) * sim.shape[2] / w).astype(int)
    return sim.argmax(0)[rows][:, cols], sim[:, rows][:, :, cols]


@pytest.mark.parametrize("variant", ["bb", "lite"])
def test_segment_is_the_protocols_prediction_at_the_images_size(tiny_export, photo, variant):
    model = ResiregVLM.from_pretrained(tiny_export)
    result = resireg.segment(photo, ",".join(LABELS), model, variant)
    assert isinstance(result, resireg.SegmentationResult) and result.labels == LABELS
    labels, sim = _reference(model, photo, LABELS, variant)
    assert result.label_map.shape == result.size == photo.shape[:2]
    np.testing.assert_array_equal(result.label_map, labels)
    np.testing.assert_allclose(result.similarity, sim, atol=1e-5)
    assert result.scores.shape == (3, *photo.shape[:2])
    np.testing.assert_allclose(result.scores.sum(0), 1.0, atol=1e-5)
    np.testing.assert_array_equal(result.scores.argmax(0), result.label_map)
    # the export folder itself is an encoder too (from_pretrained)
    again = resireg.segment(photo, list(LABELS), str(tiny_export), variant)
    np.testing.assert_array_equal(again.label_map, result.label_map)


@pytest.mark.slow
def test_segment_takes_any_encoder_of_the_zoo_by_its_build_keywords(photo):
    """A zoo encoder by its build_encoder keywords (CLIP ViT-B/16, random init: no download),
    against the reference on the same encoder built directly with the same seed."""
    from resireg.models import build_encoder

    spec = {"kind": "clip", "model_name": "ViT-B-16", "weights": None}
    image = np.ascontiguousarray(photo[::4, ::4])  # 128 x 128
    torch.manual_seed(0)
    result = resireg.segment(image, ["person", "sky"], spec, "lite")
    torch.manual_seed(0)
    model = build_encoder(**spec).eval()
    labels, sim = _reference(model, image, ("person", "sky"), "lite")
    np.testing.assert_array_equal(result.label_map, labels)
    np.testing.assert_allclose(result.similarity, sim, atol=1e-5)


def test_bad_labels_and_encoders_are_named():
    with pytest.raises(ValueError, match="labels='floor,,chair'"):
        resireg.segment(np.zeros((32, 32, 3), np.uint8), "floor,,chair", "x")
    with pytest.raises(ValueError, match="a label is repeated"):
        resireg.segment(np.zeros((32, 32, 3), np.uint8), ["a", "a"], "x")
    with pytest.raises(TypeError, match="encoder must be"):
        resireg.segment(np.zeros((32, 32, 3), np.uint8), ["a"], 3)


def test_overlay_legend_names_the_labels(tiny_export, photo):
    from resireg.deploy.segment import overlay_figure

    result = resireg.segment(photo, LABELS, str(tiny_export), "lite")
    fig = overlay_figure(photo, result)
    (ax,) = fig.axes
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    shares = np.bincount(result.label_map.ravel(), minlength=3) / result.label_map.size
    assert texts == [f"{n} ({100 * s:.0f}%)" for n, s in zip(LABELS, shares, strict=True)]
    w, h = fig.get_size_inches() * fig.dpi
    assert (round(h), round(w)) == photo.shape[:2]


def test_resireg_segment_writes_label_map_overlay_and_similarity_maps(tiny_export, photo, tmp_path):
    image = tmp_path / "astronaut.jpg"
    Image.fromarray(photo).save(image, quality=95)
    out = tmp_path / "seg" / "seg.png"
    proc = subprocess.run(
        [sys.executable, "-m", "resireg.deploy.cli", "segment", str(image), "--labels",
         ",".join(LABELS), "--model-path", str(tiny_export), "--variant", "lite", "--out", str(out)],
        capture_output=True, text=True, timeout=600, env={**os.environ, "HF_HUB_OFFLINE": "1"},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    with Image.open(image) as im:  # the JPEG as decoded, the command's input
        decoded = np.asarray(im.convert("RGB"))
        expected = resireg.segment(im, LABELS, str(tiny_export), "lite")
    with Image.open(out) as im:
        assert im.mode == "P"
        np.testing.assert_array_equal(np.asarray(im), expected.label_map)
    overlay = out.with_name("seg.overlay.png")
    with Image.open(overlay) as im:
        assert im.size == (decoded.shape[1], decoded.shape[0])
    for i, name in enumerate(LABELS):
        with Image.open(out.with_name(f"seg.similarity.{i}-{name}.png")) as im:
            assert im.size == (decoded.shape[1], decoded.shape[0])
            # viridis is monotone in lightness: the brightest pixel is where the label's
            # similarity peaks
            grey = np.asarray(im.convert("L")).astype(int)
            peak = np.unravel_index(grey.argmax(), grey.shape)
            assert expected.similarity[i][peak] >= expected.similarity[i].max() - 0.02
    for name, share in expected.shares().items():
        assert f"  {name}: {100 * share:.1f}% of the pixels" in proc.stdout


def test_resireg_segment_names_a_bad_argument(tmp_path, capsys):
    from resireg.deploy.cli import segment_main

    def run(*args):
        code = segment_main([str(a) for a in args])
        return code, capsys.readouterr().err

    out = ("--out", tmp_path / "s.png")
    code, err = run(tmp_path / "x.png", "--labels", "a,b", "--model-path", tmp_path, "--variant",
                    "nope", *out)  # fmt: skip
    assert code == 2 and "--variant='nope'" in err
    code, err = run(tmp_path / "x.png", "--labels", "a,,b", "--model-path", tmp_path, *out)
    assert code == 2 and "--labels='a,,b'" in err
    code, err = run(tmp_path / "x.png", "--labels", "a,b", *out)
    assert code == 2 and "--model-path" in err
    (tmp_path / "x.png").write_bytes(b"not an image")
    code, err = run(tmp_path / "x.png", "--labels", "a,b", "--model-path", tmp_path, *out)
    assert code == 2 and "x.png: not a readable image" in err
    Image.fromarray(np.zeros((32, 32, 3), np.uint8)).save(tmp_path / "y.png")
    code, err = run(tmp_path / "y.png", "--labels", "a,b", "--model-path", tmp_path / "nope", *out)
    assert code == 2 and "--model-path=" in err and "not an export folder" in err


def test_resireg_segment_reports_bad_arguments_before_torch_loads(tmp_path):
    code = (
        "import sys\n"
        "from resireg.deploy.cli import segment_main\n"
        f"code = segment_main(['{tmp_path / 'x.png'}', '--labels', 'a,,b', '--model-path', 'e',\n"
        f"                     '--out', '{tmp_path / 's.png'}'])\n"
        "print(code, 'torch' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "2 False", out.stdout + out.stderr
    assert "--labels='a,,b'" in out.stderr
