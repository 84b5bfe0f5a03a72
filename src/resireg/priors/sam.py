"""SAM 2.1 automatic masks as a ReSiReg segmentation prior (Hugging Face ``transformers``).

:class:`SamPrior` loads a SAM 2 checkpoint in ``transformers`` format (``Sam2Model`` and
``Sam2ImageProcessor``; a hub id such as ``facebook/sam2.1-hiera-tiny`` or a local
directory) and runs ``transformers``' ``mask-generation`` pipeline on every image: a grid of
``points_per_side**2`` point prompts, three masks per point, the predicted-IoU and
stability filters, box NMS. The surviving masks overlap (SAM returns wholes, parts and
subparts); :func:`masks_to_instances` turns them into one instance-id map per image.

Thresholds default to SAM 2's automatic mask generator (``SAM2AutomaticMaskGenerator``:
32 points per side, ``pred_iou_thresh`` 0.8, ``stability_score_thresh`` 0.95, offset 1.0,
mask threshold 0.0, box NMS 0.7, no crop layers), not to the pipeline's own defaults
(``pred_iou_thresh`` 0.88 is SAM 1's).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from resireg.errors import ConfigError, arguments_under, parameters
from resireg.models.factory import resolve_device
from resireg.models.hub import WeightsUnavailableError, require_hf_files
from resireg.specs.priors import PRIOR_KINDS, SAM_DEFAULTS, SAM_MODEL, SAM_RULES

__all__ = [
    "check_sam_source",
    "PRIOR_KINDS",
    "SAM_DEFAULTS",
    "SAM_RULES",
    "SamPrior",
    "build_prior",
    "masks_to_instances",
]


def masks_to_instances(masks: Tensor, scores: Tensor | None = None) -> Tensor:
    """Overlapping binary masks -> one instance-id map; **the smaller mask wins**.

    Each pixel takes the mask with the fewest pixels among those covering it; masks of
    equal area are ordered by higher ``scores`` (SAM's predicted IoU), then by their
    position in ``masks``. Pixels no mask covers are 0. A mask that owns no pixel after
    this (covered entirely by smaller masks) gets no id; the others are numbered
    ``1..m`` in their input order, so the ids are contiguous.

    Smaller-wins keeps parts and small objects, which a larger mask containing them
    (SAM returns whole, part and subpart masks per point) would otherwise swallow; the
    larger mask keeps the pixels no smaller mask claims.

    Args:
        masks: ``[M, H, W]`` bool (any dtype; nonzero = inside).
        scores: ``[M]`` predicted IoU, or ``None`` (ties then go by input order).

    Returns:
        ``[H, W]`` int64 on ``masks``' device.
    """
    if masks.ndim != 3:
        raise ValueError(f"masks must have shape [M, H, W], got shape {tuple(masks.shape)}")
    m = masks.shape[0]
    if scores is not None and tuple(scores.shape) != (m,):
        raise ValueError(f"scores must have shape [{m}], got shape {tuple(scores.shape)}")
    inside = masks.bool()
    out = torch.zeros(masks.shape[1:], dtype=torch.int64, device=masks.device)
    if m == 0:
        return out
    area = inside.flatten(1).sum(1).tolist()
    score = scores.float().tolist() if scores is not None else [0.0] * m
    # Highest priority first: smallest area, then highest score, then input order.
    priority = sorted(range(m), key=lambda i: (area[i], -score[i], i))
    for i in reversed(priority):  # paint the lowest priority first; the winner paints last
        out[inside[i]] = i + 1
    owns = torch.zeros(m + 1, dtype=torch.bool, device=masks.device)
    owns[out.flatten()] = True
    owns[0] = False
    ids = torch.cumsum(owns.long(), 0) * owns  # surviving masks -> 1..m in input order
    return ids[out]


def _to_pil(image: Any) -> Image.Image:
    """PIL image, or RGB tensor ``[3, H, W]`` (uint8, or float in [0, 1]) -> PIL RGB image.

    Float images are quantised to 8 bits (``round(255 x)``); SAM's processor reads 8-bit
    RGB and rescales by 1/255 itself."""
    if isinstance(image, Image.Image):
        return image.convert("RGB")
    if not isinstance(image, Tensor) or image.ndim != 3 or image.shape[0] != 3:
        shape = tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__
        raise ValueError(f"images must be PIL images or RGB tensors [3, H, W], got {shape}")
    if image.is_floating_point():
        image = (image.detach().float().clamp(0, 1) * 255).round().to(torch.uint8)
    elif image.dtype != torch.uint8:
        raise ValueError(f"integer images must be uint8, got dtype {image.dtype}")
    return Image.fromarray(image.permute(1, 2, 0).cpu().numpy())


def _as_list(images: Any) -> list[Any]:
    """One image or a batch -> a list of single images."""
    if isinstance(images, Image.Image):
        return [images]
    if isinstance(images, Tensor):
        if images.ndim == 3:
            return [images]
        if images.ndim == 4:
            return list(images)
        raise ValueError(
            f"image tensors must be [3, H, W] or [B, 3, H, W], got shape {tuple(images.shape)}"
        )
    return list(images)


def _is_local(model: str) -> bool:
    return os.path.isdir(os.path.expanduser(model))


#: How to do without the hub (the offline errors' hint).
_SAM_HINT = (
    "Pass model=/path/to/sam2, a local directory holding a transformers SAM 2 checkpoint "
    "(Sam2Model.save_pretrained + Sam2ImageProcessor.save_pretrained), or download it "
    "once with network access (it is then cached)."
)


def check_sam_source(model: str) -> bool:
    """Whether ``model`` is a local directory (``True``) or a hub id that is cached or
    reachable (``False``); otherwise the error :class:`SamPrior` would raise, so a caller can
    fail before loading anything else (``resireg-eval`` checks it before the encoder). No
    model is loaded.

    Raises:
        FileNotFoundError: a path (not an ``org/name`` hub id) that is not a directory.
        WeightsUnavailableError: a hub id neither cached nor reachable (names ``model``).
    """
    if _is_local(model):
        return True
    if model.startswith((".", "/", "~", os.sep)) or model.count("/") > 1:  # a path, not org/name
        raise FileNotFoundError(f"model={model!r}: no such directory")
    require_hf_files(model, ["config.json"], f"model={model!r} (SAM 2 weights)", _SAM_HINT)
    return False


class SamPrior:
    """SAM 2.1 automatic masks -> instance-id maps, a prior provider for ReSiReg.

    ``provider(images)`` runs ``transformers``' ``mask-generation`` pipeline on each image
    and resolves the overlapping masks with :func:`masks_to_instances` (smaller mask
    wins). Images are processed one at a time (SAM resizes each to its 1024 x 1024 input;
    the masks come back at the image's own size).

    Args:
        model: a Hugging Face hub id of a SAM 2 checkpoint in ``transformers`` format
            (default ``facebook/sam2.1-hiera-tiny``) or a local directory holding one
            (``config.json``, weights and ``preprocessor_config.json``).
        device: ``"cpu"``, ``"cuda"``, ``"cuda:N"``, ``"mps"``, a ``torch.device``, or
            ``"auto"`` (CUDA where available).
        points_per_side: point prompts per image side (``points_per_side**2`` prompts).
        points_per_batch: prompts decoded per model call (memory vs speed).
        pred_iou_thresh: keep masks whose predicted IoU exceeds it (0 keeps all).
        stability_score_thresh: keep masks whose stability score exceeds it (0 keeps all).
        stability_score_offset: logit offset of the stability score.
        mask_threshold: logit threshold that binarises a mask.
        box_nms_thresh: box IoU above which non-maximum suppression drops the lower-scored
            of two masks.
        crop_n_layers: extra layers of image crops (0: the whole image only).
        crop_overlap_ratio: overlap of the crops of the first crop layer.
        crop_n_points_downscale_factor: points per side shrink by it per crop layer.

    Raises:
        WeightsUnavailableError: the hub id is not cached and the hub cannot be reached
            (``HF_HUB_OFFLINE`` set, or no network); the message names ``model``.
        ConfigError: a bad keyword value (named as ``<name>=<value>``).
    """

    def __init__(
        self,
        model: str = SAM_MODEL,
        device: str | torch.device = "cpu",
        points_per_side: int = SAM_DEFAULTS["points_per_side"],
        points_per_batch: int = SAM_DEFAULTS["points_per_batch"],
        pred_iou_thresh: float = SAM_DEFAULTS["pred_iou_thresh"],
        stability_score_thresh: float = SAM_DEFAULTS["stability_score_thresh"],
        stability_score_offset: float = SAM_DEFAULTS["stability_score_offset"],
        mask_threshold: float = SAM_DEFAULTS["mask_threshold"],
        box_nms_thresh: float = SAM_DEFAULTS["box_nms_thresh"],
        crop_n_layers: int = SAM_DEFAULTS["crop_n_layers"],
        crop_overlap_ratio: float = SAM_DEFAULTS["crop_overlap_ratio"],
        crop_n_points_downscale_factor: int = SAM_DEFAULTS["crop_n_points_downscale_factor"],
    ) -> None:
        settings = {
            "points_per_side": points_per_side,
            "points_per_batch": points_per_batch,
            "pred_iou_thresh": pred_iou_thresh,
            "stability_score_thresh": stability_score_thresh,
            "stability_score_offset": stability_score_offset,
            "mask_threshold": mask_threshold,
            "box_nms_thresh": box_nms_thresh,
            "crop_n_layers": crop_n_layers,
            "crop_overlap_ratio": crop_overlap_ratio,
            "crop_n_points_downscale_factor": crop_n_points_downscale_factor,
        }
        self._check(settings)
        self.settings = settings
        if not isinstance(model, (str, os.PathLike)) or not str(model):
            raise ConfigError(f"model={model!r}: expected a hub id or a local directory")
        self.model_name = str(model)
        self.device = resolve_device(device)
        self._generator = self._load(self.model_name)

    def _check(self, settings: dict[str, Any]) -> None:
        for name, (ok, expected) in SAM_RULES.items():
            if not ok(settings[name]):
                raise ConfigError(f"{name}={settings[name]!r}: expected {expected}")

    def _load(self, model: str) -> Any:
        """The ``mask-generation`` pipeline of ``Sam2Model`` + ``Sam2ImageProcessor``."""
        try:
            from transformers import Sam2ImageProcessor, Sam2Model, pipeline
        except ImportError as err:  # transformers missing or without SAM 2
            raise ImportError(
                "the SAM 2 prior needs transformers with SAM 2 (pip install 'resireg[priors]')"
            ) from err
        local = check_sam_source(model)
        source = os.path.expanduser(model) if local else model
        try:
            net = Sam2Model.from_pretrained(source)
            processor = Sam2ImageProcessor.from_pretrained(source)
        except OSError as err:
            raise WeightsUnavailableError(
                f"model={model!r}: cannot load a transformers SAM 2 checkpoint ({err}). {_SAM_HINT}"
            ) from err
        net = net.to(self.device).eval()
        return pipeline("mask-generation", model=net, image_processor=processor, device=self.device)

    def masks(self, image: Any) -> tuple[Tensor, Tensor]:
        """SAM's masks of one image (PIL, or RGB tensor ``[3, H, W]`` uint8 / float in [0, 1]).

        Returns:
            ``(masks, scores)``: ``[M, H, W]`` bool and ``[M]`` float32 predicted IoU, on
            the CPU, in the pipeline's order (after NMS: by descending score).
        """
        pil = _to_pil(image)
        s = self.settings
        # SAM runs in fp32 even inside an evaluation's bf16 autocast region.
        with torch.inference_mode(), torch.autocast(self.device.type, enabled=False):
            out = self._generator(
                pil,
                points_per_batch=s["points_per_batch"],
                points_per_crop=s["points_per_side"],
                pred_iou_thresh=s["pred_iou_thresh"],
                stability_score_thresh=s["stability_score_thresh"],
                stability_score_offset=s["stability_score_offset"],
                mask_threshold=s["mask_threshold"],
                crops_nms_thresh=s["box_nms_thresh"],
                crops_n_layers=s["crop_n_layers"],
                crop_overlap_ratio=s["crop_overlap_ratio"],
                crop_n_points_downscale_factor=s["crop_n_points_downscale_factor"],
            )
        h, w = pil.height, pil.width
        found = [torch.as_tensor(np.asarray(m)).bool().cpu() for m in out["masks"]]
        masks = torch.stack(found) if found else torch.zeros(0, h, w, dtype=torch.bool)
        scores = torch.as_tensor(out["scores"]).float().cpu().reshape(-1)
        return masks, scores

    def __call__(self, images: Any) -> Tensor:
        """Instance-id maps of a batch.

        Args:
            images: a PIL image or a list of them, or RGB tensors: ``[3, H, W]``,
                ``[B, 3, H, W]`` or a list of ``[3, H, W]``; uint8, or float in [0, 1]
                (quantised to 8 bits). All images must share one size.

        Returns:
            LongTensor ``[B, H, W]`` on the CPU: per image, 0 where no mask lies and
            ``1..m`` the instances (:func:`masks_to_instances`, smaller mask wins).
        """
        items = _as_list(images)
        if not items:
            raise ValueError("images: an empty batch")
        sizes = {
            (im.height, im.width) if isinstance(im, Image.Image) else tuple(im.shape[-2:])
            for im in items
        }
        if len(sizes) != 1:
            raise ValueError(f"images of one batch must share a size, got {sorted(sizes)}")
        maps = []
        for image in items:
            masks, scores = self.masks(image)
            maps.append(masks_to_instances(masks, scores))
        return torch.stack(maps)

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.settings.items())
        return f"SamPrior(model={self.model_name!r}, device={str(self.device)!r}, {args})"


def build_prior(spec: dict[str, Any], device: str | torch.device = "cpu") -> SamPrior:
    """A prior provider from a config entry (``conf/prior/sam2.yaml``).

    Args:
        spec: ``kind`` (``sam2``), ``model``, ``device`` (``None``: ``device``) and the
            :class:`SamPrior` keywords; errors name them ``spec.<key>``.
        device: the device used when ``spec["device"]`` is ``None`` (the evaluation's).
    """
    spec = dict(spec)
    kind = spec.pop("kind", "sam2")
    if kind not in PRIOR_KINDS:
        raise ConfigError(f"spec.kind={kind!r}: expected one of {list(PRIOR_KINDS)}")
    unknown = sorted(set(spec) - {"model", "device", *SAM_DEFAULTS})
    if unknown:
        raise ConfigError(
            f"spec: unknown keys {unknown}; known: model, device, {list(SAM_DEFAULTS)}"
        )
    if spec.get("device") is None:
        spec["device"] = device
    with arguments_under("spec", parameters(SamPrior)):  # the keys of spec
        return SamPrior(**spec)
