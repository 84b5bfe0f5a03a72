"""Deprecated: the clustering's public names, kept importable here for one release.

``resireg.cluster`` held the PCA, the k-means and the ELBO prototype count in one module; each
now has its own: :mod:`resireg.method.pca`, :mod:`resireg.method.kmeans` and :mod:`resireg.method.elbo`. Importing
this module warns (:class:`DeprecationWarning`), and so does every name taken from it, naming
the module it moved to. ``import resireg`` does not import this module, so it does not warn.
"""

from __future__ import annotations

import warnings

from resireg.deprecation import moved

# every public name of the former module -> the module that holds it now
_MOVED = {
    "PCAResult": "resireg.method.pca",
    "PCASpectrum": "resireg.method.pca",
    "pca": "resireg.method.pca",
    "pca_from_moments": "resireg.method.pca",
    "gram": "resireg.method.pca",
    "KMeansResult": "resireg.method.kmeans",
    "kmeans": "resireg.method.kmeans",
    "kmeans_plusplus": "resireg.method.kmeans",
    "sq_distances": "resireg.method.kmeans",
    "VBGMMResult": "resireg.method.elbo",
    "vb_gmm": "resireg.method.elbo",
    "ELBO_MAX_POINTS": "resireg.method.elbo",
    "elbo_subsample": "resireg.method.elbo",
    "elbo_fits": "resireg.method.elbo",
    "elbo_prototype_count": "resireg.method.elbo",
}

__all__ = list(_MOVED)

warnings.warn(
    "resireg.cluster is deprecated and will be removed in the next release: import from "
    "resireg.method.pca (PCA), resireg.method.kmeans (k-means) or resireg.method.elbo (the ELBO prototype count)",
    DeprecationWarning,
    stacklevel=2,
)


__getattr__ = moved(__name__, _MOVED)


def __dir__() -> list[str]:
    return sorted([*globals(), *_MOVED])
