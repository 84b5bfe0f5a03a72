"""Deprecated: the prior table and its settings moved to :mod:`resireg.specs.priors` (the
torch-free ground floor). This module re-exports them, with a ``DeprecationWarning``, for one
release."""

from resireg.deprecation import moved

__getattr__ = moved(
    "resireg.priors.settings",
    {
        "PRIOR_KINDS": "resireg.specs.priors",
        "PRIOR_SPECS": "resireg.specs.priors",
        "PriorSpec": "resireg.specs.priors",
        "SAM_DEFAULTS": "resireg.specs.priors",
        "SAM_MODEL": "resireg.specs.priors",
        "SAM_RULES": "resireg.specs.priors",
    },
)
