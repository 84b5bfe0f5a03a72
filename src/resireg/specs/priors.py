"""The segmentation priors by ``kind`` (``conf/prior/<kind>.yaml``): the table is
:data:`resireg.priors.settings.PRIOR_SPECS`, beside the settings and rules it names (torch-free,
read by :class:`resireg.priors.SamPrior` and the evaluation's ``prior.<name>`` checks)."""

from resireg.priors.settings import PRIOR_SPECS, PriorSpec

__all__ = ["PRIOR_SPECS", "PriorSpec"]
