"""The method: ReSiReg's variants and what they compute with (docs/method.md).

- :mod:`~resireg.method.full`: ReSiReg Full (:class:`~resireg.method.full.ReSiRegFull`, the
  PCA of the upsampled points from the grid, the work configurations of one batch share),
- :mod:`~resireg.method.lite`: ReSiReg Lite (:class:`~resireg.method.lite.ReSiRegLite`),
- :mod:`~resireg.method.grid`: the grid helpers Full and Lite share (resizes, normalisation,
  masked means, a prior's instances),
- :mod:`~resireg.method.calib`: Calib, SC-CLIP's self-calibration made backbone-generic,
- :mod:`~resireg.method.pca`, :mod:`~resireg.method.kmeans`, :mod:`~resireg.method.elbo`: the
  clustering (PCA, k-means, the prototype count by the evidence lower bound), knowing nothing of
  the variants; :mod:`~resireg.method.heuristic`: the prototype count as a function of the batch
  size,
- :mod:`~resireg.method.checks`: the input checks every variant runs,
- :mod:`~resireg.method.variants`: the variant factory, building each entry of the variant table
  (:data:`resireg.specs.variants.VARIANT_SPECS`, whose ``target`` names the classes above).

Imports only torch, :mod:`resireg.specs` and :mod:`resireg.errors`. May be imported by the rest of
``resireg`` above it (``mapping``, ``deploy``, ``ros2``), by ``resireg_train``, benchmarks and
tests; ``resireg.models`` and ``resireg.sources`` use only :mod:`~resireg.method.checks`, and
``resireg.specs`` and ``resireg.errors`` none of it (the layers of ``[tool.importlinter]`` in
pyproject.toml). ``from resireg import ReSiRegFull,
ReSiRegLite, build_variant`` are the public names.
"""
