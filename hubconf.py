"""torch.hub entry points of the ReSiReg repository.

    import torch
    model = torch.hub.load("<owner>/resireg", "resireg_vlm", path_or_repo="<owner>/<export repo>")
    model = torch.hub.load("/path/to/checkout", "resireg_vlm", path_or_repo="run/export", source="local")

``resireg_vlm`` returns :meth:`resireg.models.ResiregVLM.from_pretrained` of an export folder or
Hugging Face repo id (file digests verified); ``resireg_segment`` is :func:`resireg.segment`.
torch.hub puts the checkout on ``sys.path``; the package is imported from its ``src/`` folder
when it is not installed.
"""

import os
import sys

# torch.hub checks that these import before it calls an entry point (the core install's
# imports; pip install the repository for the rest of its dependencies)
dependencies = ["torch", "timm", "open_clip", "safetensors", "huggingface_hub", "transformers"]

_SRC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "src")
if os.path.isdir(os.path.join(_SRC, "resireg")) and _SRC not in sys.path:
    sys.path.insert(0, _SRC)


def resireg_vlm(path_or_repo, map_location="cpu"):
    """The 25M dense VLM from an export folder or Hugging Face repo id (``ResiregVLM``)."""
    from resireg.models import ResiregVLM

    return ResiregVLM.from_pretrained(path_or_repo, map_location=map_location)


def resireg_segment(image, labels, path_or_repo, variant="lite", **kwargs):
    """One image segmented into ``labels`` (:func:`resireg.segment`) with the VLM of
    ``path_or_repo``; returns a ``SegmentationResult``."""
    from resireg.deploy.segment import segment

    return segment(image, labels, resireg_vlm(path_or_repo), variant, **kwargs)
