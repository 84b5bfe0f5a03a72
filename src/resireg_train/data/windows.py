"""The resize and window rules of a segmentation entry (the keys its 2D protocol sets): how an
image is resized, which windows the encoder sees, how predictions reach the label's resolution
and which pixels fall back to background (docs/protocol.md sections 1 and 6).

Every 2D entry holds the keys (:data:`resireg_train.data.specs.WINDOW_RULE_KEYS`);
``conf/protocol/paper.yaml`` gives the paper's values (one pass over the whole image at shorter
side 576, argmax at the feature grid, nearest upsampling), ``conf/protocol/ovss8.yaml`` the OVSS
field's (shorter side 336 capped at 2048 on the longer side, 224 px windows every 112 px, logits
resized bilinearly to the label, a background threshold on the with-background sets). The
dataset (:class:`~resireg_train.data.segmentation.SegmentationSet`) resizes by it; the engine
(:class:`resireg_train.evaluation.ovss.engine.OVSSEngine`) windows, upsamples and thresholds by it.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from types import MappingProxyType
from typing import Any

from resireg_train.data.specs import (
    SEGMENTATION_RULES,
    WINDOW_RULE_KEYS,
    missing_keys_error,
)

__all__ = ["WindowRules", "protocol_conf", "window_rules", "rescaled_size"]


def rescaled_size(
    size: tuple[int, int], short_side: int | None, long_side: int | None
) -> tuple[int, int]:
    """``(H, W)`` after mmcv's keep-ratio rescale to ``scale=(long_side, short_side)``: the
    factor ``min(short_side / shorter side, long_side / longer side)`` (a missing bound imposes
    nothing; neither: the size itself), each side ``int(side * factor + 0.5)``, at least 1
    (mmcv ``rescale_size`` / ``imrescale``, which mmseg's ``Resize(keep_ratio=True)`` calls)."""
    h, w = size
    factors = []
    if short_side is not None:
        factors.append(short_side / min(h, w))
    if long_side is not None:
        factors.append(long_side / max(h, w))
    if not factors:
        return (h, w)
    factor = min(factors)
    return (max(1, int(h * factor + 0.5)), max(1, int(w * factor + 0.5)))


@dataclass(frozen=True)
class WindowRules:
    """The resize and window rules of one 2D entry, checked (:meth:`from_spec`).

    Attributes:
        long_side: cap on the longer side after the shorter side's resize (``None``: none).
        antialias: the bilinear resize antialiases (the paper's) or not (mmcv's cv2 resize).
        slide_crop, slide_stride: the sliding window's side and step in pixels of the resized
            image (``None``: one pass over the whole image).
        upsample: ``nearest`` (argmax at the feature grid, nearest to the label) or
            ``bilinear`` (logits bilinear to the input, then to the label, then the argmax).
        background_threshold: a pixel whose highest class probability is below it is class 0
            (background; the with-background sets), ``None``: no fallback.
        background_logit_scale: the probability's scale: ``softmax(scale * cosine)`` over
            every class name.
        name: the protocol's name in the run's record (``None``: ``ovss/<kind>``).
    """

    long_side: int | None
    antialias: bool
    slide_crop: int | None
    slide_stride: int | None
    upsample: str
    background_threshold: float | None
    background_logit_scale: float | None
    name: str | None = None

    @property
    def sliding(self) -> bool:
        """Sliding windows (``slide_crop`` set), else one pass over the whole image."""
        return self.slide_crop is not None

    @classmethod
    def from_spec(
        cls, spec: Mapping[str, Any], key: str = "dataset", patch_size: int | None = None
    ) -> WindowRules:
        """The rules of entry ``spec``; a ValueError naming ``<key>.<name>`` for a missing
        key, a value against its rule, or a combination that cannot run: a window without a
        stride (or the reverse), a stride larger than the window, windows with ``nearest``
        upsampling (windows are averaged at pixel resolution), a threshold without its scale,
        a window not a multiple of the encoder's ``patch_size``."""
        missing = [k for k in WINDOW_RULE_KEYS if k not in spec]
        if missing:
            raise ValueError(missing_keys_error(key, missing, "conf/protocol/ (paper.yaml, "
                                                "ovss8.yaml, merged by its defaults)"))  # fmt: skip
        errors = [
            f"{key}.{name}={spec[name]!r}: expected {SEGMENTATION_RULES[name][1]}"
            for name in WINDOW_RULE_KEYS
            if not SEGMENTATION_RULES[name][0](spec[name])
        ]
        crop, stride = spec["slide_crop"], spec["slide_stride"]
        if (crop is None) != (stride is None):
            errors.append(f"{key}.slide_crop={crop!r}, {key}.slide_stride={stride!r}: set both "
                          "(sliding windows) or neither (the whole image)")  # fmt: skip
        elif crop is not None and not errors:
            if stride > crop:
                errors.append(f"{key}.slide_stride={stride!r}: expected at most "
                              f"{key}.slide_crop={crop!r} (windows must cover the image)")  # fmt: skip
            if spec["upsample"] != "bilinear":
                errors.append(f"{key}.upsample={spec['upsample']!r}: sliding windows average "
                              f"logits at pixel resolution; set {key}.upsample=bilinear or "
                              f"{key}.slide_crop=null")  # fmt: skip
            if patch_size and crop % patch_size:
                errors.append(f"{key}.slide_crop={crop!r}: expected a multiple of the encoder's "
                              f"patch size {patch_size}")  # fmt: skip
        threshold, scale = spec["background_threshold"], spec["background_logit_scale"]
        if (threshold is None) != (scale is None):
            errors.append(f"{key}.background_threshold={threshold!r}, "
                          f"{key}.background_logit_scale={scale!r}: the threshold applies to "
                          "softmax(scale x cosine); set both or neither")  # fmt: skip
        if errors:
            raise ValueError("; ".join(errors))
        return cls(
            long_side=None if spec["long_side"] is None else int(spec["long_side"]),
            antialias=bool(spec["antialias"]),
            slide_crop=None if crop is None else int(crop),
            slide_stride=None if stride is None else int(stride),
            upsample=str(spec["upsample"]),
            background_threshold=None if threshold is None else float(threshold),
            background_logit_scale=None if scale is None else float(scale),
            name=spec["protocol"],
        )

    def resized_size(
        self, size: tuple[int, int], short_side: int | None, patch_size: int
    ) -> tuple[int, int]:
        """``(H, W)`` of an image of ``size`` after the resize: with windows, mmcv's rescale
        (:func:`rescaled_size`, the windows take any size); over the whole image, every side
        also rounded to a multiple of ``patch_size`` (at least one patch), so the encoder runs
        on whole patches (without a cap this is :func:`resireg.models.images.patch_grid_size`,
        the paper's rule)."""
        if self.sliding:
            return rescaled_size(size, short_side, self.long_side)
        h, w = size
        scale = short_side / min(h, w) if short_side else 1.0
        if self.long_side is not None:
            scale = min(scale, self.long_side / max(h, w))
        p = patch_size
        return (max(p, round(h * scale / p) * p), max(p, round(w * scale / p) * p))

    def settings(self) -> dict[str, Any]:
        """The keys as the entry names them (``results.json``'s protocol record)."""
        out = asdict(self)
        out["protocol"] = out.pop("name")
        return out


@functools.cache
def protocol_conf(name: str) -> Mapping[str, Any]:
    """The settings of the protocol ``conf/protocol/<name>.yaml`` (``paper``, ``ovss8``): what a
    :class:`~resireg_train.data.segmentation.SegmentationSet` built in Python without an entry
    (a test's, a benchmark's) follows (``paper``), read from conf/ rather than typed again; read
    once, and read-only (the one copy every caller shares)."""
    import yaml

    from resireg_train.config.paths import CONFIG_DIR

    path = CONFIG_DIR / "protocol" / f"{name}.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"protocol {name!r}: no {path}")
    return MappingProxyType(yaml.safe_load(path.read_text()))


@functools.cache
def window_rules(name: str) -> WindowRules:
    """The rules of the protocol ``conf/protocol/<name>.yaml`` (:func:`protocol_conf`)."""
    return WindowRules.from_spec(protocol_conf(name), f"protocol/{name}.yaml")
