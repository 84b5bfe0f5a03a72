"""The playground (``resireg-playground``): its computation against numpy references, its
error handling, and the real page in a real headless browser (Chromium + Selenium)."""

from __future__ import annotations

import base64
import contextlib
import io
import os
import shutil
import signal
import socket
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from PIL import Image

from helpers.paths import ROOT
from helpers.run import Child, started
from resireg import ReSiRegFull, ReSiRegLite

TINY_VLM = ROOT / "tests" / "conf" / "encoder" / "tiny_vlm.yaml"
DEFAULTS = yaml.safe_load((ROOT / "conf" / "resireg" / "default.yaml").read_text())
CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
BROWSER_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--window-size=1400,1400"]  # fmt: skip
INSTALL = "no headless browser: apt-get install -y chromium chromium-driver"


def _np_normalise(x: np.ndarray, axis: int) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=axis, keepdims=True), 1e-12)


@pytest.fixture(scope="module")
def playground(tiny_export):
    from resireg_train.playground.core import Playground

    return Playground.from_config(str(TINY_VLM), str(tiny_export), short_side=64)


@pytest.fixture(scope="module")
def model(tiny_export):
    from resireg.models import ResiregVLM

    return ResiregVLM.from_pretrained(tiny_export).eval()


def _reference(model, image, texts, short_side, full=None, lite=None):
    """BB, Lite and Full cosine maps [K, h, w] computed here: the encoder's output, the
    ReSiReg modules built directly, numpy for normalisation and cosines."""
    with torch.no_grad():
        out = model.encode(model.preprocess(image, short_side))
        q = _np_normalise(model.encode_text(texts).float().numpy(), 1)  # [K, Dl]
        dense = {
            "bb": out.language.float().numpy()[0],
            "lite": ReSiRegLite(**(lite or DEFAULTS["lite"]))(out.intermediates, out.language),
            "full": ReSiRegFull(**(full or DEFAULTS["full"]))(out.intermediates, out.language),
        }
    maps = {}
    for key, d in dense.items():
        d = d if isinstance(d, np.ndarray) else d.float().numpy()[0]  # [Dl, h, w]
        maps[key] = np.einsum("dhw,kd->khw", _np_normalise(d.astype(np.float64), 0), q)
    return maps


def test_compute_gives_the_reference_maps_with_seconds_per_variant(playground, model):
    from resireg_train.playground.examples import example_image

    image = example_image("chelsea")  # 300 x 451: 64 x 96 px at short side 64, a 4 x 6 grid
    result = playground.compute(image, " cat, wall , ,")
    assert result.queries == ["cat", "wall"]
    ref = _reference(model, image, ["cat", "wall"], 64)
    assert result.maps["bb"].shape == (2, 4, 6)
    assert result.maps["lite"].shape == result.maps["full"].shape == (2, 8, 12)  # upscale 2
    for key in ("bb", "lite", "full"):
        np.testing.assert_allclose(result.maps[key], ref[key], atol=2e-5, err_msg=key)
    # BB and Full differ: Full against BB nearest-upsampled to Full's grid.
    bb_up = result.maps["bb"].repeat(2, axis=1).repeat(2, axis=2)
    assert np.abs(bb_up - result.maps["full"]).max() > 0.01
    # The defaults are conf/resireg/default.yaml's; seconds of every pass are reported.
    assert result.params["full"] == DEFAULTS["full"] and result.params["lite"] == DEFAULTS["lite"]
    s = result.seconds
    assert all(s[k] > 0 for k in ("encoder", "text", "bb", "lite", "full"))
    assert result.total("full") == pytest.approx(s["encoder"] + s["text"] + s["full"])
    assert result.canvas.shape == (64, 96, 3) and result.canvas.dtype == np.uint8


def test_slider_values_reach_the_variants(playground, model):
    from resireg_train.playground.examples import example_image

    image = example_image("coffee")
    full = {"n_prototypes": 3, "alpha": 2.0, "tau": 0.1, "upscale": 1}
    lite = {"alpha": 4.0, "tau": 0.0, "upscale": 3}
    result = playground.compute(image, ["cup"], lite=lite, full=full, short_side=48)
    ref = _reference(model, image, ["cup"], 48, full={**DEFAULTS["full"], **full},
                     lite={**DEFAULTS["lite"], **lite})  # fmt: skip
    assert result.maps["full"].shape == result.maps["bb"].shape == (1, 3, 4)  # upscale 1
    assert result.maps["lite"].shape == (1, 9, 12)
    for key in ("lite", "full"):
        np.testing.assert_allclose(result.maps[key], ref[key], atol=2e-5, err_msg=key)


def test_full_with_the_sam_prior_is_the_reference_on_the_encoded_image(tmp_path, model):
    pytest.importorskip("transformers", reason="the SAM 2 prior needs transformers")
    from helpers.sam import save_tiny_sam
    from resireg.models.images import pil_to_tensor, resize_to_patch_grid
    from resireg.priors import SamPrior
    from resireg_train.playground.core import Playground, resireg_defaults
    from resireg_train.playground.examples import example_image

    # A random tiny SAM 2 with its filters off, so that it finds masks at all.
    sam = SamPrior(model=str(save_tiny_sam(tmp_path / "sam")), points_per_side=8,
                   pred_iou_thresh=0.0, stability_score_thresh=0.0)  # fmt: skip
    playground = Playground(model, resireg_defaults(), 64, prior=sam)
    assert playground.panels == ["bb", "lite", "full", "full_prior"]
    image = example_image("chelsea")
    result = playground.compute(image, "cat")
    canvas = resize_to_patch_grid(pil_to_tensor(image), 64, 16)  # the encoder's input rule
    np.testing.assert_array_equal(result.canvas, (canvas * 255).round().byte().permute(1, 2, 0))
    ids = sam(canvas[None])  # [1, 64, 96]
    assert ids.max() >= 1
    with torch.no_grad():
        out = model.encode(model.preprocess(image, 64))
        dense = ReSiRegFull(**DEFAULTS["full"])(out.intermediates, out.language, ids)[0].numpy()
        q = _np_normalise(model.encode_text(["cat"]).numpy(), 1)
    ref = np.einsum("dhw,kd->khw", _np_normalise(dense.astype(np.float64), 0), q)
    np.testing.assert_allclose(result.maps["full_prior"], ref, atol=2e-5)
    assert np.abs(result.maps["full_prior"] - result.maps["full"]).max() > 0.01
    assert result.seconds["prior"] > 0
    assert result.total("full_prior") == pytest.approx(
        sum(result.seconds[k] for k in ("encoder", "text", "prior", "full_prior"))
    )


def test_bad_uploads_and_queries_raise_readable_errors(tmp_path, playground):
    from resireg_train.playground.core import PlaygroundError, load_image

    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(PlaygroundError, match=r"empty.png is empty \(0 bytes\)"):
        load_image(empty)
    text = tmp_path / "notes.txt"
    text.write_text("not a picture\n")
    with pytest.raises(PlaygroundError, match="notes.txt .* is not an image"):
        load_image(text)
    good = np.random.default_rng(0).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    Image.fromarray(good).save(tmp_path / "good.png")
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes((tmp_path / "good.png").read_bytes()[:200])
    with pytest.raises(PlaygroundError, match="truncated.png .* is not an image"):
        load_image(truncated)
    np.testing.assert_array_equal(np.asarray(load_image(tmp_path / "good.png")), good)
    with pytest.raises(PlaygroundError, match="no text query"):
        playground.compute(Image.fromarray(good), " , ")


def test_encoder_configs_resolve_or_name_what_is_missing(tiny_export):
    from resireg_train.playground.core import encoder_spec

    entry = yaml.safe_load((ROOT / "conf" / "encoder" / "clip_vit_b16.yaml").read_text())
    expected = {k: v for k, v in entry.items() if k not in ("name", "third_party")}
    assert encoder_spec("clip_vit_b16") == expected
    assert encoder_spec(str(TINY_VLM), str(tiny_export)) == {
        "kind": "resireg_vlm",
        "path": str(tiny_export),
    }
    with pytest.raises(ValueError, match="--model-path is required"):
        encoder_spec(None, None)
    with pytest.raises(ValueError, match=r"--encoder='nope'.*'clip_vit_b16'"):
        encoder_spec("nope")


def test_render_shares_one_colour_scale_per_query():
    from matplotlib import colormaps

    from resireg_train.playground.core import QueryResult, render

    maps = {"bb": np.array([[[0.0, 0.5]]]), "full": np.array([[[0.5, 1.0], [0.25, 0.75]]])}
    result = QueryResult(["q"], maps, {}, np.zeros((2, 4, 3), np.uint8))
    panels = render(result, tile_width=8)  # tiles 8 x 4 above an 18-px label
    assert panels["bb"].shape == panels["full"].shape == (22, 8, 3)
    inferno = (colormaps["inferno"](np.array([0.0, 0.5, 1.0, 0.25]))[:, :3] * 255).round()
    np.testing.assert_array_equal(panels["bb"][0, 0], inferno[0])  # 0.0: the scale's low end
    np.testing.assert_array_equal(panels["bb"][3, 7], inferno[1])  # 0.5
    np.testing.assert_array_equal(panels["full"][0, 7], inferno[2])  # 1.0: its high end
    np.testing.assert_array_equal(panels["full"][3, 0], inferno[3])  # 0.25, second row
    assert panels["full"][4:].mean() > 200  # the white label strip


def test_run_button_outputs_and_errors_without_a_browser(tmp_path, playground):
    pytest.importorskip("gradio", reason='the playground extra: pip install -e ".[dev]"')
    from resireg_train.playground.app import build_app, run_query

    build_app(playground)  # the page builds
    sliders = [DEFAULTS["lite"][k] for k in ("alpha", "tau", "upscale")] + [
        DEFAULTS["full"][k] for k in ("n_prototypes", "alpha", "tau", "upscale")
    ]
    status, canvas, bb, lite, full, timings = run_query(playground, None, "astronaut", "flag", 64,
                                                        *sliders)  # fmt: skip
    assert status.startswith("Done: example 'astronaut'")
    assert canvas.shape == (64, 64, 3) and bb.shape == full.shape and bb.dtype == np.uint8
    assert np.abs(bb.astype(int) - full.astype(int)).mean() > 5
    for label in ("BB (language tokens)", "ReSiReg Lite", "ReSiReg Full", "encoder pass"):
        assert label in timings
    empty = tmp_path / "empty.jpg"
    empty.write_bytes(b"")
    out = run_query(playground, str(empty), "astronaut", "flag", 64, *sliders)
    assert out[0] == "**Error:** the uploaded file empty.jpg is empty (0 bytes): not an image"
    assert out[1:] == [None, None, None, None, ""]
    too_many = sliders[:3] + [10_000] + sliders[4:]  # more prototypes than points
    out = run_query(playground, None, "astronaut", "flag", 64, *too_many)
    assert out[0].startswith("**Error:**") and "10000" in out[0]


# ------------------------------------------------------------------ the real browser


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_until_serving(url: str, proc: Child, log: Path, timeout: float = 120):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"the playground exited ({proc.returncode}):\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(url, timeout=2) as response:
                if response.status == 200:
                    return
        except OSError:
            time.sleep(0.5)
    pytest.fail(f"the playground did not serve {url} in {timeout} s:\n{log.read_text()[-3000:]}")


@contextlib.contextmanager
def _serving(export: Path, port: int, log: Path):
    """``resireg-playground`` on the tiny VLM export at 127.0.0.1:``port`` for the ``with``
    block (output to ``log``; see :func:`helpers.run.started`)."""
    cmd = [sys.executable, "-m", "resireg_train.cli.playground", "--encoder", TINY_VLM,
           "--model-path", export, "--host", "127.0.0.1", "--port", port, "--device", "cpu",
           "--short-side", "96"]  # fmt: skip
    with started(cmd, stdout=log, env={**os.environ, "GRADIO_ANALYTICS_ENABLED": "False"}) as proc:
        yield proc


@pytest.mark.slow
def test_the_playground_stops_on_sigterm_as_on_ctrl_c(tiny_export, tmp_path):
    """``kill <pid>`` (what a service manager, a container's stop or a job's end sends) closes
    the serving playground as Ctrl-C does: it exits 0 at once (not killed by the signal) and
    frees its port."""
    pytest.importorskip("gradio", reason='the playground extra: pip install -e ".[dev]"')
    port = _free_port()
    log = tmp_path / "playground.log"
    with _serving(tiny_export, port, log) as proc:
        _wait_until_serving(f"http://127.0.0.1:{port}/", proc, log)
        assert proc.stop(signal.SIGTERM, timeout=30) == 0, log.read_text()[-3000:]
    with socket.socket() as s:  # no one listens on the port any more
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # past closed connections
        s.bind(("127.0.0.1", port))
        s.listen()


_PIXELS = """
const img = document.querySelector(arguments[0] + ' img');
if (!img || !img.complete || img.naturalWidth === 0) return null;
const c = document.createElement('canvas');
c.width = img.naturalWidth; c.height = img.naturalHeight;
c.getContext('2d').drawImage(img, 0, 0);
return [img.getAttribute('src'), c.toDataURL('image/png')];
"""


@pytest.mark.slow
def test_playground_in_a_real_browser(tiny_export, tmp_path):
    if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
        pytest.skip(INSTALL)
    pytest.importorskip("gradio", reason='the playground extra: pip install -e ".[dev]"')
    webdriver = pytest.importorskip("selenium.webdriver", reason='pip install -e ".[dev]"')
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    port = _free_port()
    url = f"http://127.0.0.1:{port}/"
    log = tmp_path / "playground.log"
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    profile = tempfile.mkdtemp(prefix="chromium-", dir=tmp_path)
    for flag in [*BROWSER_FLAGS, f"--user-data-dir={profile}"]:
        options.add_argument(flag)
    driver = None
    with _serving(tiny_export, port, log) as proc:
        try:
            _wait_until_serving(url, proc, log)
            driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
            wait = WebDriverWait(driver, 90)
            driver.get(url)
            status = lambda: driver.find_element(By.ID, "status").text  # noqa: E731

            def upload(path: Path) -> None:
                box = "#upload input[type=file]"
                wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, box))
                driver.find_element(By.CSS_SELECTOR, box).send_keys(str(path))

            def pick_example(name: str) -> None:  # also clears the upload
                driver.find_element(
                    By.XPATH, f"//*[@id='example']//label[contains(., '{name}')]"
                ).click()

            def run(query: str, expect: str) -> str:
                box = driver.find_element(By.CSS_SELECTOR, "#queries textarea")
                box.clear()
                box.send_keys(query)
                driver.find_element(By.ID, "run").click()
                wait.until(lambda d: expect in status())
                return status()

            # 1. A good upload and two queries: the three panels appear, BB and Full differ.
            from resireg_train.playground.examples import example_image

            photo = tmp_path / "coffee.png"
            example_image("coffee").save(photo)
            upload(photo)
            wait.until(lambda d: "Loaded the upload (600 x 400 px)" in status())
            assert run("cup, table", "Done:") == "Done: upload coffee.png, queries 'cup', 'table'."
            shown = {}
            for key in ("map-bb", "map-lite", "map-full", "canvas"):
                src, data = wait.until(lambda d, key=key: d.execute_script(_PIXELS, f"#{key}"))
                png = base64.b64decode(data.split(",", 1)[1])
                shown[key] = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
            assert shown["canvas"].shape == (96, 144, 3)  # 400 x 600 at short side 96
            assert shown["map-bb"].shape == shown["map-full"].shape == (2 * (213 + 18), 320, 3)
            assert np.abs(shown["map-bb"] - shown["map-full"]).mean() > 5
            assert np.abs(shown["map-lite"] - shown["map-full"]).mean() > 1
            timings = driver.find_element(By.ID, "timings").text
            assert "ReSiReg Full" in timings and "encoder pass" in timings
            driver.save_screenshot(str(tmp_path / "playground.png"))
            if os.environ.get("RESIREG_ARTIFACTS"):
                artefacts = Path(os.environ["RESIREG_ARTIFACTS"])
                artefacts.mkdir(parents=True, exist_ok=True)
                shutil.copy(tmp_path / "playground.png", artefacts / "playground.png")

            # 2. Bad uploads: the page says why, the server goes on serving.
            empty = tmp_path / "empty.png"
            empty.write_bytes(b"")
            pick_example("chelsea")
            wait.until(lambda d: "Upload removed" in status())
            upload(empty)
            wait.until(lambda d: "Error:" in status())
            assert "empty.png is empty (0 bytes)" in status()
            text = tmp_path / "notes.txt"
            text.write_text("this is not an image\n")
            pick_example("astronaut")
            wait.until(lambda d: "Upload removed" in status())
            upload(text)
            wait.until(lambda d: "notes.txt" in status())
            assert "Error:" in status() and "is not an image" in status()
            assert "notes.txt" in run("cat", "Error:")  # Run with the bad upload: the same error
            assert proc.poll() is None

            # 3. A good query afterwards still works.
            pick_example("chelsea")
            wait.until(lambda d: "Upload removed" in status())
            assert run("cat, wall", "Done:") == "Done: example 'chelsea', queries 'cat', 'wall'."
            wait.until(lambda d: d.execute_script(_PIXELS, "#map-full"))
            driver.save_screenshot(str(tmp_path / "playground_after_errors.png"))
        finally:
            if driver is not None:
                driver.quit()
        assert proc.stop(signal.SIGTERM, timeout=30) == 0, log.read_text()[-3000:]
