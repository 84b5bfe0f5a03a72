"""Fake torch.hub repositories of the encoder zoo, shared by every test (no network), one module
per upstream repository a fake writes.

Each fake exposes the real entry point(s) with their signatures and returns tiny random
modules with the real attribute layout and output structure, so an adapter runs its real
loading path (``torch.hub.load(..., source="local")``) and the tests recompute expected values
from a second, independently loaded copy through the fake's own modules:

- ``radio``: NVlabs/RADIO (``FAKE_RADIO``, ``radio_repo``);
- ``radseg``: RADSeg-OVSS/RADSeg (``FAKE_RADSEG``, the ``RADSEG_STANDIN``, ``radseg_repo``);
- ``dinov2``: facebookresearch/dinov2 for OTAS (``DINOV2_HUBCONF`` over ``DINOV2_VIT``,
  ``dinov2_repo``, dropping and restoring the imported ``dinov2`` package);
- ``dinotxt``: facebookresearch/dinov2's dino.txt code (``DINOTXT_FILES``, ``dinotxt_repo``);
- ``tips``: TIPSv2's release files (no hub: ``.npz`` state dicts, a tokenizer);
- ``common``: what they share: writing a repository, the offline hub cache
  (``offline_hub``, ``build_offline``, ``refuse_network``) and ``token_grid``.
"""
