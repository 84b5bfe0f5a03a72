"""What the playground computes, without any web code: the encoder from an export or a
``conf/encoder/`` entry, ReSiReg's defaults from ``conf/resireg/default.yaml``, one query
(image + texts -> cosine maps and seconds per variant) and the coloured panels.

Everything goes through resireg's public API: :func:`resireg.models.build_encoder`,
:meth:`DenseEncoder.resized` / ``encode`` / ``encode_text`` and
:func:`resireg.method.variants.build_variant`. The encoder runs once per query and every variant is
applied to that one output (as the evaluation engine does), so the seconds of a variant are
its own ReSiReg step plus the shared encoder and text passes.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from resireg.errors import ConfigError
from resireg.method.variants import build_variant
from resireg.models import DenseEncoder, build_encoder
from resireg.sources.frames import DECODE_ERRORS
from resireg.specs.variants import VARIANT_SPECS
from resireg_train.config.errors import config_path, encoder_arguments
from resireg_train.playground.config import (
    SLIDERS,
    encoder_spec,
    protocol_short_side,
    resireg_defaults,
)

__all__ = [
    "LABELS",
    "PlaygroundError",
    "QueryResult",
    "Playground",
    "encoder_spec",
    "resireg_defaults",
    "protocol_short_side",
    "parse_queries",
    "load_image",
]

log = logging.getLogger(__name__)

#: Panel key -> title shown in the page (and in the timing table), in display order.
LABELS: dict[str, str] = {
    **{name: VARIANT_SPECS[name].title for name in ("bb", *SLIDERS)},  # the variant table's
    "full_prior": f"{VARIANT_SPECS['full'].title} + SAM 2 prior",
}


class PlaygroundError(ConfigError):
    """A problem with the user's input (an upload that is not an image, no query): its
    message is shown in the page as it is."""


def parse_queries(text: str | Sequence[str] | None) -> list[str]:
    """``"cat, wall"`` (or a list) -> ``["cat", "wall"]``; empty entries are dropped."""
    items = text.split(",") if isinstance(text, str) else list(text or [])
    queries = [q.strip() for q in items if q and q.strip()]
    if not queries:
        raise PlaygroundError("no text query: type one or more, separated by commas")
    return queries


def load_image(path: str | Path | None) -> Image.Image:
    """An uploaded file -> RGB PIL image; :class:`PlaygroundError` for an empty file or one
    that is not an image PIL can decode (truncated files included)."""
    if path is None:
        raise PlaygroundError("no image: upload one or pick an example")
    path = Path(path)
    name = path.name
    try:
        size = path.stat().st_size
    except OSError as err:
        raise PlaygroundError(f"cannot read the upload {name}: {err.strerror or err}") from err
    if size == 0:
        raise PlaygroundError(f"the uploaded file {name} is empty (0 bytes): not an image")
    try:
        with Image.open(path) as im:
            im.load()
            return im.copy()  # any mode: DenseEncoder.resized converts (16-bit grey too)
    except DECODE_ERRORS as err:
        raise PlaygroundError(
            f"the uploaded file {name} ({size} bytes) is not an image that can be decoded: {err}"
        ) from err


@dataclass
class QueryResult:
    """One query of the playground.

    Attributes:
        queries: the ``K`` text queries.
        maps: panel key -> cosine maps ``[K, h, w]`` (float32; each variant its own grid).
        seconds: ``encoder``, ``text``, ``prior`` (when used) and per panel key the
            variant's own ReSiReg step; :meth:`total` adds the shared passes.
        canvas: the image as encoded, RGB uint8 ``[H, W, 3]`` (resized to the patch grid).
    """

    queries: list[str]
    maps: dict[str, np.ndarray]
    seconds: dict[str, float]
    canvas: np.ndarray
    params: dict[str, dict[str, Any]] = field(default_factory=dict)

    def total(self, key: str) -> float:
        """Seconds from the image to the maps of ``key``: encoder + text (+ prior) + step."""
        shared = self.seconds["encoder"] + self.seconds["text"]
        if key == "full_prior":
            shared += self.seconds.get("prior", 0.0)
        return shared + self.seconds[key]


class Playground:
    """One encoder, ReSiReg's defaults and an optional segmentation-prior provider.

    Args:
        encoder: any :class:`DenseEncoder`.
        defaults: ``{"lite": {...}, "full": {...}}`` (:func:`resireg_defaults`).
        short_side: default shorter side of the encoded image (pixels).
        prior: a callable ``images -> LongTensor [B, H, W]`` of instance ids (0 = none),
            e.g. ``resireg.priors.SamPrior``; adds the ``full_prior`` panel.
    """

    def __init__(
        self,
        encoder: DenseEncoder,
        defaults: dict[str, dict[str, Any]],
        short_side: int | None,
        prior: Callable[[Any], torch.Tensor] | None = None,
    ) -> None:
        self.encoder = encoder.eval()
        self.defaults = {k: dict(v) for k, v in defaults.items()}
        self.short_side = short_side
        self.prior = prior
        self._lock = threading.Lock()  # one query at a time: torch already uses every core

    @classmethod
    def from_config(
        cls,
        encoder: str | None = None,
        model_path: str | None = None,
        device: str = "cpu",
        short_side: int | None = None,
        prior: Callable[[Any], torch.Tensor] | None = None,
        config_dir: str | Path | None = None,
    ) -> Playground:
        """Build the encoder of :func:`encoder_spec` on ``device`` with the YAML defaults."""
        spec = encoder_spec(encoder, model_path, config_dir)
        with config_path("encoder", encoder_arguments(spec)):
            model = build_encoder(**spec, device=device)
        model = model.to(device)
        if short_side is None:
            short_side = protocol_short_side(config_dir)
        return cls(model, resireg_defaults(config_dir), short_side, prior)

    @property
    def panels(self) -> list[str]:
        """Panel keys shown, in order."""
        return ["bb", "lite", "full"] + (["full_prior"] if self.prior is not None else [])

    def params(
        self, lite: dict[str, Any] | None = None, full: dict[str, Any] | None = None
    ) -> dict[str, dict[str, Any]]:
        """The YAML defaults updated with the slider values (integers where they must be)."""
        out = {"lite": {**self.defaults["lite"], **(lite or {})},
               "full": {**self.defaults["full"], **(full or {})}}  # fmt: skip
        for name in ("lite", "full"):
            out[name]["upscale"] = int(out[name]["upscale"])
        out["full"]["n_prototypes"] = int(out["full"]["n_prototypes"])
        return out

    @torch.no_grad()
    def compute(
        self,
        image: Image.Image,
        queries: str | Sequence[str],
        lite: dict[str, Any] | None = None,
        full: dict[str, Any] | None = None,
        short_side: int | None = None,
    ) -> QueryResult:
        """Cosine maps of every panel for one image and ``K`` queries, with seconds.

        Raises:
            PlaygroundError: no query. ``ValueError`` from ReSiReg names a bad parameter
            (e.g. more prototypes than points).
        """
        texts = parse_queries(queries)
        params = self.params(lite, full)
        size = int(short_side) if short_side else self.short_side
        variants = {"bb": build_variant("bb"), "lite": build_variant("lite", **params["lite"]),
                    "full": build_variant("full", **params["full"])}  # fmt: skip
        with self._lock:
            enc = self.encoder
            seconds: dict[str, float] = {}
            t = time.perf_counter()
            raw = enc.resized(image, size)  # [1, 3, H, W] float in [0, 1], the input rule
            out = enc.encode(enc.input_rule.normalize(raw))
            seconds["encoder"] = time.perf_counter() - t
            t = time.perf_counter()
            q = enc.encode_text(texts).float().to(out.language.device)  # [K, Dl]
            seconds["text"] = time.perf_counter() - t
            canvas = (raw[0].permute(1, 2, 0) * 255).round().byte().cpu().numpy()  # [H, W, 3]
            prior = None
            if self.prior is not None:  # on the resized images, as encode_image calls it
                t = time.perf_counter()
                prior = self.prior(raw).to(out.intermediates.device)  # [1, H, W] instance ids
                seconds["prior"] = time.perf_counter() - t
                variants["full_prior"] = build_variant("full", **params["full"])
            maps = {}
            for key, variant in variants.items():
                t = time.perf_counter()
                given = prior if key == "full_prior" else None
                dense = variant(out.intermediates, out.language, given)  # [1, Dl, h, w]
                sim = torch.einsum("bdhw,kd->bkhw", dense.float(), q)[0]  # [K, h, w]
                seconds[key] = time.perf_counter() - t
                maps[key] = sim.cpu().numpy()
        return QueryResult(texts, maps, seconds, canvas, params)


def _label(text: str, width: int, height: int = 18) -> np.ndarray:
    """A white strip ``[height, width, 3]`` with ``text`` written in black."""
    from PIL import ImageDraw

    strip = Image.new("RGB", (width, height), "white")
    ImageDraw.Draw(strip).text((4, 3), text, fill="black")
    return np.asarray(strip)


def render(result: QueryResult, tile_width: int = 320) -> dict[str, np.ndarray]:
    """Panel key -> RGB uint8 image ``[K * (h_t + 18), w_t, 3]``: the ``K`` maps one below
    the other (so the panels compare row by row), each above its query's name, nearest-upsampled to
    ``tile_width`` at the canvas' aspect (every patch stays a visible square) and coloured
    with matplotlib's ``inferno``. The colour scale of a
    query is shared by the panels (min to max over all of them), so equal colours mean equal
    cosines across BB, Lite and Full."""
    from matplotlib import colormaps

    cmap = colormaps["inferno"]
    h_img, w_img = result.canvas.shape[:2]
    w_t = tile_width
    h_t = max(1, round(h_img * w_t / w_img))
    lo = np.min([m.min(axis=(1, 2)) for m in result.maps.values()], axis=0)  # [K]
    hi = np.max([m.max(axis=(1, 2)) for m in result.maps.values()], axis=0)
    panels = {}
    for key, maps in result.maps.items():
        tiles = []
        for k, (query, m) in enumerate(zip(result.queries, maps, strict=True)):
            scaled = (m - lo[k]) / max(float(hi[k] - lo[k]), 1e-12)
            rgb = (cmap(scaled)[..., :3] * 255).round().astype(np.uint8)
            tile = np.asarray(Image.fromarray(rgb).resize((w_t, h_t), Image.NEAREST))
            tiles.append(np.concatenate([tile, _label(query, w_t)], axis=0))
        panels[key] = np.concatenate(tiles, axis=0)
    return panels


def timing_table(result: QueryResult, labels: dict[str, str] = LABELS) -> str:
    """Markdown: seconds of each panel (its ReSiReg step and the total from the image)."""
    s = result.seconds
    rows = ["| variant | ReSiReg step (s) | total (s) |", "|---|---:|---:|"]
    for key in result.maps:
        rows.append(f"| {labels[key]} | {s[key]:.3f} | {result.total(key):.3f} |")
    shared = f"encoder pass {s['encoder']:.3f} s, text {s['text']:.3f} s"
    if "prior" in s:
        shared += f", SAM 2 prior {s['prior']:.3f} s"
    h, w = result.canvas.shape[:2]
    return "\n".join(rows) + f"\n\nShared by every variant: {shared} (image {h} x {w} px)."
