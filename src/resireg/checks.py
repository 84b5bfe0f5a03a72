"""Checks on tensors that enter the method, the maps and the evaluation engines.

One place for the rule "a feature tensor is floating-point and finite", so every entry point
(:class:`resireg.ReSiRegFull`, :class:`resireg.ReSiRegLite`, :class:`resireg.calib.ReSiRegCalib`,
:meth:`resireg.mapping.SemanticMap.fuse`, the engines' encoder outputs) refuses the same inputs
with the same words. A NaN that enters ReSiReg Full spreads to every patch of the batch (PCA
and k-means mix all points), and one NaN patch in Lite spreads to its whole image, so the check
runs before any of them. Inside a traced graph (``torch.export``, the ONNX export,
``torch.compile``) it is skipped: a graph cannot branch on tensor values. Its cost is one sum over the tensor when it is finite
(``benchmarks/bench_checks.py``: well under 1% of Full's or Lite's forward).
"""

from __future__ import annotations

import torch
from torch import Tensor

from resireg.errors import DataError

__all__ = ["NonFiniteError", "check_features", "count_nonfinite"]


class NonFiniteError(DataError):
    """A feature tensor holds NaN or infinite values (the message names the argument)."""


def count_nonfinite(x: Tensor) -> int:
    """How many entries of the floating-point tensor ``x`` are NaN or infinite."""
    return int((~torch.isfinite(x)).sum())


def check_features(name: str, x: object) -> Tensor:
    """``x`` itself when it is a floating-point :class:`torch.Tensor` whose entries are all
    finite; otherwise a :class:`TypeError` (not a tensor, or an integer / bool / complex dtype)
    or a :class:`NonFiniteError` naming ``name``, the shape and how many entries are bad."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got dtype {x.dtype}")
    # Happy path: one sum. A NaN or an inf anywhere makes the sum NaN or inf (IEEE arithmetic
    # propagates both), so a finite sum proves every entry finite; a non-finite sum may also
    # be an overflow of finite values, so only then the exact test. Measured on 2 CPU cores
    # (4 x 384 x 36 x 48 floats): the sum 1-2 ms, isfinite(x).all() 45-80 ms (an elementwise
    # pass writing a bool tensor, then a reduction of it); benchmarks/bench_checks.py.
    if torch.compiler.is_compiling():
        return x  # a traced graph (torch.export, ONNX, torch.compile) cannot branch on values
    if x.numel() and not bool(torch.isfinite(x.sum())) and not bool(torch.isfinite(x).all()):
        bad = count_nonfinite(x)
        raise NonFiniteError(
            f"{name} holds {bad} non-finite value(s) (NaN or inf) of {x.numel()} "
            f"(shape {tuple(x.shape)})"
        )
    return x
