"""Deprecated: the configuration syntax moved to :mod:`resireg.specs.variants` (beside the variant
table it reads). This module re-exports its names, with a ``DeprecationWarning``, for one
release."""

from resireg.deprecation import moved

__getattr__ = moved(
    "resireg.variant_names",
    {
        "LAYER_KEY": "resireg.specs.variants",
        "LITE_ATTENTION": "resireg.specs.variants",
        "PRIOR_SUFFIX": "resireg.specs.variants",
        "PRIOR_VARIANTS": "resireg.specs.variants",
        "VARIANTS": "resireg.specs.variants",
        "parse_variant": "resireg.specs.variants",
        "takes_prior": "resireg.specs.variants",
        "variant_layer": "resireg.specs.variants",
    },
)
