"""Deployment of the 25M VLM: ONNX graphs for onnxruntime and TensorRT (:mod:`.onnx_export`;
:func:`open_graph` opens one, verified against its manifest: :mod:`.runtime`),
Hugging Face Hub folders and model cards (:mod:`.card`), and one-image open-vocabulary
segmentation (:mod:`.segment`). Needs the core install only; ONNX needs the ``export`` extra
(onnx, onnxscript, onnxruntime) and the segmentation figures matplotlib (the same extra).
The names load on first use, so ``import resireg.deploy`` stays light.

Nothing else in ``resireg`` imports it. May be imported by ``resireg_train``, ``hubconf.py``,
the console scripts ``resireg-export`` / ``resireg-segment`` and tests.
"""

from __future__ import annotations

from resireg import lazy_names

__all__ = [
    "ImageGraph",
    "OnnxExport",
    "SegmentationResult",
    "TextGraph",
    "export_onnx",
    "hub_folder",
    "model_card",
    "open_graph",
    "segment",
]

__getattr__ = lazy_names(
    "resireg.deploy",
    {
        "ImageGraph": "resireg.deploy.onnx_export",
        "TextGraph": "resireg.deploy.onnx_export",
        "OnnxExport": "resireg.deploy.onnx_export",
        "export_onnx": "resireg.deploy.onnx_export",
        "hub_folder": "resireg.models.vlm.card",
        "model_card": "resireg.models.vlm.card",
        "open_graph": "resireg.deploy.runtime",
        "SegmentationResult": "resireg.deploy.segment",
        "segment": "resireg.deploy.segment",
    },
)
