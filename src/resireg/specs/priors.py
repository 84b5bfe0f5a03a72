"""The segmentation priors by ``kind`` (``conf/prior/<kind>.yaml``): one entry each, their
provider classes, settings and the rules of those settings, without importing torch.

The evaluation's config checks (``resireg_train.checks.eval``) read them before anything heavy
is loaded, so a bad ``prior.<name>`` value is reported at once; :class:`resireg.priors.SamPrior`
checks its keywords against the same rules.

Adding a prior: a provider class (``prior(images) -> [B, H, W]`` instance ids, see
:class:`resireg.priors.SamPrior`), one :class:`PriorSpec` below with its keywords' rules, one
``conf/prior/<kind>.yaml`` file with its ``kind`` and defaults. ``+prior`` configurations of
the variants that take one (``full+prior``) then run with it (``prior=<kind>``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from resireg.specs.rules import Rule, finite, integer, interval
from resireg.specs.table import SpecTable

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

_UNIT = interval(0, 1)

#: What each keyword of :data:`SAM_DEFAULTS` accepts: ``name -> (check, expectation)``, one
#: source for :class:`resireg.priors.SamPrior` and the evaluation's ``prior.<name>`` checks.
SAM_RULES: dict[str, Rule] = {
    "points_per_side": integer(1),
    "points_per_batch": integer(1),
    "pred_iou_thresh": _UNIT,
    "stability_score_thresh": _UNIT,
    "stability_score_offset": finite(),
    "mask_threshold": finite(),
    "box_nms_thresh": _UNIT,
    "crop_n_layers": integer(0),
    "crop_overlap_ratio": _UNIT,
    "crop_n_points_downscale_factor": integer(1),
}


@dataclass(frozen=True)
class PriorSpec:
    """One prior kind: its provider class (``"module:Class"``) and its keywords' rules."""

    kind: str
    target: str
    params: dict[str, Rule]

    @property
    def configs(self) -> tuple[str, ...]:
        """The ``conf/prior/`` files of this kind (found by scanning)."""
        return PRIOR_SPECS.configs(self.kind)

    @property
    def defaults(self) -> str:
        """Where its defaults live (the first ``conf/prior/`` file of its kind)."""
        return f"conf/prior/{(self.configs or (self.kind,))[0]}.yaml"

    def load(self) -> Any:
        """The provider class (imports torch)."""
        from resireg.specs.table import load

        return load(self.target)


#: Prior kinds of :func:`resireg.priors.build_prior` (``kind`` of ``conf/prior/*.yaml``).
PRIOR_SPECS: SpecTable[PriorSpec] = SpecTable(
    "prior kind",
    (PriorSpec("sam2", "resireg.priors.sam:SamPrior", SAM_RULES),),
    name="kind",
    where="resireg.specs.priors",
    conf="prior",
)
PRIOR_KINDS: tuple[str, ...] = PRIOR_SPECS.names()
