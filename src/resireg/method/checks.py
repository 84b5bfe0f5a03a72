"""Checks on tensors that enter the method, the maps and the evaluation engines.

One place for the rule "a feature tensor is floating-point and finite", so every entry point
(:class:`resireg.ReSiRegFull`, :class:`resireg.ReSiRegLite`, :class:`resireg.method.calib.Calib`,
:meth:`resireg.mapping.SemanticMap.fuse`, the engines' encoder outputs) refuses the same inputs
with the same words. A NaN that enters ReSiReg Full spreads to every patch of the batch (PCA
and k-means mix all points), and one NaN patch in Lite spreads to its whole image, so the check
runs before any of them. Inside a traced graph (``torch.export``, the ONNX export,
``torch.compile``) it is skipped: a graph cannot branch on tensor values. Its cost is one sum over the tensor when it is finite
(``benchmarks/bench_checks.py``: well under 1% of Full's or Lite's forward).

:func:`check_variant_inputs` is the whole input rule of the variants (Full, Lite, Calib: shapes,
batch sizes, the prior, then :func:`check_features`), and :func:`check_positive_int` the rule of
their integer settings.
"""

from __future__ import annotations

import torch
from torch import Tensor

from resireg.errors import DataError

__all__ = [
    "NonFiniteError",
    "check_features",
    "check_positive_int",
    "check_variant_inputs",
    "count_nonfinite",
]


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


def check_positive_int(name: str, value: object) -> int:
    """``value`` itself when it is an ``int`` (not a ``bool``) ``>= 1``; otherwise a
    :class:`ValueError` naming ``name`` and the value."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return value


def check_variant_inputs(intermediates: Tensor, language: Tensor, prior: Tensor | None) -> None:
    """The rules every variant's inputs follow (:class:`resireg.ReSiRegFull`,
    :class:`resireg.ReSiRegLite` and :class:`resireg.method.calib.Calib`): floating-point and finite
    features (:func:`check_features`; a NaN would spread to the whole batch in Full and to the
    whole image in Lite), four dimensions, none of them empty (a batch of 0 images, 0 channels
    or a 0-cell grid has nothing to reconstruct), one batch size, and an integer prior of the
    same batch. Each error is a :class:`ValueError` (:class:`TypeError` for a non-tensor or a
    non-floating dtype) naming the argument and its shape."""
    for name, x, dims in (
        ("intermediates", intermediates, "[B, Dv, Hv, Wv]"),
        ("language", language, "[B, Dl, Hl, Wl]"),
    ):
        if not isinstance(x, Tensor):  # the shape test below needs a tensor
            check_features(name, x)
        if x.ndim != 4:
            raise ValueError(f"{name} must have shape {dims}, got shape {tuple(x.shape)}")
        if 0 in x.shape:
            raise ValueError(
                f"{name} must have no empty dimension ({dims}: at least one image, channel and "
                f"grid cell), got shape {tuple(x.shape)}"
            )
    if language.shape[0] != intermediates.shape[0]:
        raise ValueError(
            f"language batch size {language.shape[0]} does not match intermediates batch size "
            f"{intermediates.shape[0]}"
        )
    if prior is not None:
        if not isinstance(prior, Tensor) or prior.ndim != 3:
            shape = tuple(prior.shape) if isinstance(prior, Tensor) else type(prior).__name__
            raise ValueError(f"prior must have shape [B, H, W], got {shape}")
        if prior.shape[0] != intermediates.shape[0]:
            raise ValueError(
                f"prior batch size {prior.shape[0]} does not match intermediates batch size "
                f"{intermediates.shape[0]}"
            )
        if 0 in prior.shape:
            raise ValueError(f"prior must have a non-empty grid, got shape {tuple(prior.shape)}")
        if prior.is_floating_point() or prior.is_complex():
            raise ValueError(f"prior must hold integer instance ids, got dtype {prior.dtype}")
    # Last: the finiteness test reads every value, the shape tests above are free.
    check_features("intermediates", intermediates)
    check_features("language", language)
