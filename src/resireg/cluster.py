"""Deprecated: the clustering's public names, kept importable here for one release.

``resireg.cluster`` held the PCA, the k-means and the ELBO prototype count in one module; each
now has its own: :mod:`resireg.pca`, :mod:`resireg.kmeans` and :mod:`resireg.elbo`. Importing
this module warns (:class:`DeprecationWarning`), and so does every name taken from it, naming
the module it moved to. ``import resireg`` does not import this module, so it does not warn.
"""

from __future__ import annotations

import warnings

from resireg.deprecation import moved

# every public name of the former module -> the module that holds it now
_MOVED = {
    "PCAResult": "resireg.pca",
    "PCASpectrum": "resireg.pca",
    "pca": "resireg.pca",
    "pca_from_moments": "resireg.pca",
    "gram": "resireg.pca",
    "KMeansResult": "resireg.kmeans",
    "kmeans": "resireg.kmeans",
    "kmeans_plusplus": "resireg.kmeans",
    "sq_distances": "resireg.kmeans",
    "VBGMMResult": "resireg.elbo",
    "vb_gmm": "resireg.elbo",
    "ELBO_MAX_POINTS": "resireg.elbo",
    "elbo_subsample": "resireg.elbo",
    "elbo_fits": "resireg.elbo",
    "elbo_prototype_count": "resireg.elbo",
}

__all__ = list(_MOVED)

warnings.warn(
    "resireg.cluster is deprecated and will be removed in the next release: import from "
    "resireg.pca (PCA), resireg.kmeans (k-means) or resireg.elbo (the ELBO prototype count)",
    DeprecationWarning,
    stacklevel=2,
)


__getattr__ = moved(__name__, _MOVED)


def __dir__() -> list[str]:
    return sorted([*globals(), *_MOVED])
