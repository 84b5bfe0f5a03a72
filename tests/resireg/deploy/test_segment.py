"""One-image segmentation (issue 39 item 3): ``resireg.segment`` against a reference computed
from the model's own passes with numpy, and ``resireg-segment`` on a scikit-image photograph
with the smoke (tiny) export: label map, overlay (size, legend) and similarity maps."""

import subprocess
import sys

import numpy as np
import pytest
import torch
from PIL import Image

import resireg
from helpers.run import run
from resireg.models import ResiregVLM
from resireg.ovss import TEMPLATES

skdata = pytest.importorskip("skimage.data")
pytest.importorskip("matplotlib")
from matplotlib import colormaps  # noqa: E402
from scipy.special import softmax  # noqa: E402

LABELS = ("person", "sky", "rocket")


@pytest.fixture(scope="module")
def photo():
    return skdata.astronaut()  # 512 x 512 RGB, shipped with scikit-image


def _reference(model, image, labels, variant, templates=TEMPLATES):
    """The protocol by hand: features of the variant, text prototypes as the normalised mean
    of the normalised template embeddings, cosine, argmax (softmax keeps it), nearest
    upsampling by index arithmetic (PyTorch's 'nearest': floor(i * in / out))."""
    with torch.no_grad():
        dense = model.encode_image(torch.from_numpy(image).permute(2, 0, 1), variant)[0].numpy()
        prompts = [t(name) for name in labels for t in templates]
        text = model.encode_text(prompts).numpy().reshape(len(labels), len(templates), -1)
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
    # the scores: softmax of 100 x the reference's cosines over the labels (scipy)
    np.testing.assert_allclose(result.scores, softmax(100.0 * sim, axis=0), atol=1e-3)
    # the export folder itself is an encoder too (from_pretrained)
    again = resireg.segment(photo, list(LABELS), str(tiny_export), variant)
    np.testing.assert_array_equal(again.label_map, result.label_map)


@pytest.mark.slow
def test_segment_takes_any_encoder_of_the_zoo_by_its_build_keywords(photo):
    """A zoo encoder by its build_encoder keywords (CLIP ViT-B/16, random init: no download),
    against the reference on the same encoder built directly with the same seed. (open_clip's
    7 simple templates: the ViT-B/16 text tower on 2 x 80 prompts, twice, was most of the
    test's 28 s.)"""
    import open_clip

    from resireg.models import build_encoder

    spec = {"kind": "clip", "model_name": "ViT-B-16", "weights": None}
    image = np.ascontiguousarray(photo[::4, ::4])  # 128 x 128
    templates = open_clip.SIMPLE_IMAGENET_TEMPLATES
    torch.manual_seed(0)
    result = resireg.segment(image, ["person", "sky"], spec, "lite", templates=templates)
    torch.manual_seed(0)
    model = build_encoder(**spec).eval()
    labels, sim = _reference(model, image, ("person", "sky"), "lite", templates)
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
    proc = run(sys.executable, "-m", "resireg.deploy.cli", "segment", image, "--labels",
               ",".join(LABELS), "--model-path", tiny_export, "--variant", "lite", "--out", out)  # fmt: skip
    with Image.open(image) as im:  # the JPEG as decoded, the command's input
        decoded = np.asarray(im.convert("RGB"))
        expected = resireg.segment(im, LABELS, str(tiny_export), "lite")
    with Image.open(out) as im:
        assert im.mode == "P"
        np.testing.assert_array_equal(np.asarray(im), expected.label_map)
    # the overlay: the photo blended half and half with matplotlib's tab10 colour of each
    # pixel's label, within PNG rounding everywhere but under the legend (upper right)
    with Image.open(out.with_name("seg.overlay.png")) as im:
        overlay = np.asarray(im.convert("RGB")).astype(float)
    tab10 = np.asarray(colormaps["tab10"].colors[:3])
    blend = np.round(255 * (0.5 * decoded / 255.0 + 0.5 * tab10[expected.label_map]))
    assert overlay.shape == blend.shape
    rows, cols = np.nonzero(np.abs(overlay - blend).max(-1) > 2)
    h, w = decoded.shape[:2]
    assert rows.max() < h // 4 and cols.min() > w // 2, (rows.max(), cols.min())  # the legend
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


# ------------------------------------------------------- image bombs (issue 44 item 11)
def _png(path, width, height, pixels=True):
    """An RGB PNG declaring ``width`` x ``height``, written row by row through zlib, so the
    file is small and the test never holds the image: each row is a ramp (a gradient image),
    or, with ``pixels=False``, no pixel data at all (the header alone, as a bomb's)."""
    import struct
    import zlib

    def chunk(kind, data):
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    packer = zlib.compressobj(9)
    row = b"\x00" + np.linspace(0, 255, 3 * width).astype(np.uint8).tobytes()  # filter 0, ramp
    data = b"".join(packer.compress(row) for _ in range(height)) if pixels else b""
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n")
        f.write(chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)))
        f.write(chunk(b"IDAT", data + packer.flush()))
        f.write(chunk(b"IEND", b""))
    return path


def _one_line(proc):
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("error: "), proc.stderr
    return proc.stderr.strip()


@pytest.mark.parametrize(
    ("side", "said"),
    [(30000, "exceeds limit of 178956970 pixels"),  # PIL's own refusal (twice its limit)
     (10000, "declares 10000 x 10000 = 100,000,000 pixels, more than PIL's decompression-bomb "
             "limit of 89,478,485")],  # PIL only warns here: refused from the header
)  # fmt: skip
def test_resireg_segment_refuses_an_image_bomb_in_one_line(tmp_path, side, said):
    from helpers.run import run

    bomb = _png(tmp_path / "bomb.png", side, side, pixels=False)
    assert bomb.stat().st_size < 100
    out = tmp_path / "seg" / "seg.png"
    proc = run("resireg-segment", bomb, "--labels", "a,b", "--model-path", tmp_path, "--out", out,
               check=False)  # fmt: skip
    assert _one_line(proc).startswith(f"error: {bomb}: refused (") and said in proc.stderr
    assert not out.parent.exists()


def _model_input(model):
    """The list the backbone's input shapes are appended to (a forward pre-hook)."""
    seen = []
    model.backbone.register_forward_pre_hook(lambda m, args: seen.append(tuple(args[0].shape)))
    return seen


def test_a_large_image_is_resized_before_the_model(tiny_export, tmp_path):
    """A 1000 x 1500 image with max_pixels=100,000: each side scaled by sqrt(1e5 / 1.5e6)
    and rounded down gives 258 x 387 (99,846 pixels), the size of every output; the model's
    input is that rounded to its 16-pixel patches, 256 x 384. A file takes the same path."""
    model = ResiregVLM.from_pretrained(tiny_export)
    seen = _model_input(model)
    image = np.random.default_rng(0).integers(0, 256, (1000, 1500, 3), dtype=np.uint8)
    result = resireg.segment(image, LABELS, model, "bb", max_pixels=100_000)
    assert result.size == result.label_map.shape == (258, 387) and 258 * 387 <= 100_000
    assert result.scores.shape == result.similarity.shape == (3, 258, 387)
    assert seen == [(1, 3, 256, 384)]
    png = _png(tmp_path / "wide.png", 1500, 1000)
    assert resireg.segment(png, LABELS, model, "bb", max_pixels=100_000).size == (258, 387)
    assert seen[-1] == (1, 3, 256, 384)
    with pytest.raises(ValueError, match=r"short_side=640: makes a 640 x 960 model input"):
        resireg.segment(image, LABELS, model, "bb", short_side=640, max_pixels=100_000)


def test_a_large_jpeg_is_decoded_small_and_matches_the_photo(photo, tmp_path):
    """The astronaut (512 x 512) enlarged 8 times to a 4096 x 4096 JPEG, read with
    max_pixels = 512 x 512: decoded at 1/8 scale (PIL's draft), it is the photo again up to
    the two resamplings and JPEG's loss (the reference: the original pixels)."""
    from resireg.deploy.photo import load_photo

    big = tmp_path / "big.jpg"
    Image.fromarray(photo).resize((4096, 4096), Image.Resampling.BICUBIC).save(big, quality=95)
    got = load_photo(big, 512 * 512)
    assert got.size == (512, 512) and got.mode == "RGB"
    diff = np.abs(np.asarray(got).astype(float) - photo)
    assert diff.mean() < 4.0, diff.mean()


def test_resireg_segment_writes_a_large_image_at_the_limits_size(tiny_export, tmp_path):
    from helpers.run import run

    png = _png(tmp_path / "wide.png", 4000, 3000)  # 12 MP
    out = tmp_path / "seg.png"
    run("resireg-segment", png, "--labels", "a,b", "--model-path", tiny_export,
               "--max-pixels", 120_000, "--variant", "bb", "--out", out)  # fmt: skip
    # sqrt(120000 / 12e6) = 0.1: 300 x 400 exactly
    for path in (out, tmp_path / "seg.overlay.png", tmp_path / "seg.similarity.0-a.png"):
        with Image.open(path) as im:
            assert im.size == (400, 300), path
    line = _one_line(run("resireg-segment", png, "--labels", "a,b", "--model-path", tiny_export,
                         "--max-pixels", 120_000, "--short-side", 600, "--out", tmp_path / "x.png",
                         check=False))  # fmt: skip
    assert line.startswith("error: --short-side=600: makes a 608 x 800 model input") and (
        "more than --max-pixels=120,000" in line
    )
    line = _one_line(run("resireg-segment", png, "--labels", "a", "--model-path", tiny_export,
                         "--max-pixels", 0, "--out", tmp_path / "x.png", check=False))  # fmt: skip
    assert line == "error: --max-pixels=0: expected a number of pixels >= 1"
    assert not (tmp_path / "x.png").exists()
