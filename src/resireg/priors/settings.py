"""The prior providers' settings and what each accepts, without importing torch.

The evaluation's config checks (``resireg_train.validation``) read them before anything heavy
is loaded, so a bad ``prior.<name>`` value is reported at once; :class:`resireg.priors.SamPrior`
checks its keywords against the same rules.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["PRIOR_KINDS", "PRIOR_SPECS", "PriorSpec", "SAM_DEFAULTS", "SAM_MODEL", "SAM_RULES"]

#: The SAM 2 checkpoint of a prior whose ``model`` is unset (``conf/prior/sam2.yaml`` sets it).
SAM_MODEL = "facebook/sam2.1-hiera-tiny"

#: SAM 2's automatic-mask-generation defaults, keywords of :class:`resireg.priors.SamPrior`.
SAM_DEFAULTS: dict[str, Any] = {
    "points_per_side": 32,
    "points_per_batch": 64,
    "pred_iou_thresh": 0.8,
    "stability_score_thresh": 0.95,
    "stability_score_offset": 1.0,
    "mask_threshold": 0.0,
    "box_nms_thresh": 0.7,
    "crop_n_layers": 0,
    "crop_overlap_ratio": 512 / 1500,
    "crop_n_points_downscale_factor": 1,
}


def _is_int(v: Any, minimum: int) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= minimum


def _is_finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _integer(minimum: int) -> tuple[Callable[[Any], bool], str]:
    return (lambda v: _is_int(v, minimum)), f"an integer >= {minimum}"


_UNIT = ((lambda v: _is_finite(v) and 0 <= v <= 1), "a number in [0, 1]")
_FINITE = (_is_finite, "a finite number")

#: What each keyword of :data:`SAM_DEFAULTS` accepts: ``name -> (check, expectation)``, one
#: source for :class:`resireg.priors.SamPrior` and the evaluation's ``prior.<name>`` checks.
SAM_RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "points_per_side": _integer(1),
    "points_per_batch": _integer(1),
    "pred_iou_thresh": _UNIT,
    "stability_score_thresh": _UNIT,
    "stability_score_offset": _FINITE,
    "mask_threshold": _FINITE,
    "box_nms_thresh": _UNIT,
    "crop_n_layers": _integer(0),
    "crop_overlap_ratio": _UNIT,
    "crop_n_points_downscale_factor": _integer(1),
}


@dataclass(frozen=True)
class PriorSpec:
    """One prior kind (``resireg.specs``): its provider class, its keywords' rules and the
    file of its defaults."""

    kind: str
    target: str
    params: dict[str, tuple[Callable[[Any], bool], str]]
    defaults: str

    def load(self) -> Any:
        """The provider class (imports torch)."""
        from resireg.specs import load

        return load(self.target)


#: Prior kinds of :func:`resireg.priors.build_prior` (``kind`` of ``conf/prior/*.yaml``).
PRIOR_SPECS: dict[str, PriorSpec] = {
    "sam2": PriorSpec("sam2", "resireg.priors.sam:SamPrior", SAM_RULES, "conf/prior/sam2.yaml"),
}
PRIOR_KINDS: tuple[str, ...] = tuple(PRIOR_SPECS)
