"""Inputs the variants refuse or accept (ReSiReg Full, Lite and Calib share one check).

Before the check, one NaN token in ``language`` made Full's whole batch NaN, a NaN in
``intermediates`` failed inside PCA/k-means with an unrelated error, one NaN patch spread to
Lite's whole image, integer inputs returned zeros, a batch of 0 images raised ``IndexError``,
inputs with ``requires_grad`` failed inside an ``out=`` call and empty grids raised raw torch
errors.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from resireg import ReSiRegFull, ReSiRegLite
from resireg.method.calib import Calib
from resireg.method.checks import NonFiniteError, check_features, count_nonfinite

VARIANTS = {
    "full": lambda: ReSiRegFull(n_prototypes=4),
    "lite": lambda: ReSiRegLite(attention="factorised"),
    "lite_sdpa": lambda: ReSiRegLite(attention="sdpa"),
    "calib": lambda: Calib(n_neighbors=4),
}


def _inputs(b: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return torch.randn(b, 16, 6, 8, generator=g), torch.randn(b, 12, 6, 8, generator=g)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("argument", ["intermediates", "language"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_variants_refuse_non_finite_features(variant, argument, bad):
    inter, lang = _inputs()
    target = inter if argument == "intermediates" else lang
    target[1, 3, 2, 5] = bad  # one value of one image
    with pytest.raises(NonFiniteError, match=rf"^{argument} holds 1 non-finite value"):
        VARIANTS[variant]()(inter, lang)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("dtype", [torch.int64, torch.uint8, torch.bool])
def test_variants_refuse_non_floating_features(variant, dtype):
    inter, lang = _inputs()
    with pytest.raises(TypeError, match=f"language must be a floating-point tensor.*{dtype}"):
        VARIANTS[variant]()(inter, lang.to(dtype))
    with pytest.raises(TypeError, match="intermediates must be a floating-point"):
        VARIANTS[variant]()(inter.to(dtype), lang.to(dtype))


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize(
    ("argument", "index", "shape"),
    [
        ("intermediates", slice(0, 0), r"\(0, 16, 6, 8\)"),  # a batch of 0 images
        ("intermediates", (slice(None), slice(0, 0)), r"\(2, 0, 6, 8\)"),  # 0 channels
        ("intermediates", (slice(None), slice(None), slice(0, 0)), r"\(2, 16, 0, 8\)"),
        ("language", (slice(None), slice(None), slice(None), slice(0, 0)), r"\(2, 12, 6, 0\)"),
        ("language", (slice(None), slice(0, 0)), r"\(2, 0, 6, 8\)"),
    ],
)
def test_variants_refuse_empty_dimensions(variant, argument, index, shape):
    inter, lang = _inputs()
    if argument == "intermediates":
        inter = inter[index]
        if inter.shape[0] == 0:
            lang = lang[:0]
    else:
        lang = lang[index]
    with pytest.raises(ValueError, match=rf"^{argument} must have no empty dimension.*{shape}"):
        VARIANTS[variant]()(inter, lang)


@pytest.mark.parametrize("variant", VARIANTS)
def test_variants_refuse_an_empty_prior(variant):
    inter, lang = _inputs()
    with pytest.raises(ValueError, match=r"prior must have a non-empty grid.*\(2, 0, 4\)"):
        VARIANTS[variant]()(inter, lang, torch.zeros(2, 0, 4, dtype=torch.long))


@pytest.mark.parametrize("variant", VARIANTS)
def test_variants_compute_under_no_grad_when_inputs_require_grad(variant):
    """ReSiReg has no parameters: inputs that require grad give the result of the same
    inputs detached (the reference), and the result does not require grad."""
    inter, lang = _inputs()
    reference = VARIANTS[variant]()(inter, lang)
    with torch.enable_grad():
        out = VARIANTS[variant]()(inter.clone().requires_grad_(), lang.clone().requires_grad_())
    assert not out.requires_grad
    assert torch.equal(out, reference)


def test_check_features_counts_like_numpy_and_returns_the_tensor():
    rng = np.random.default_rng(3)
    values = rng.standard_normal((3, 5, 7)).astype(np.float32)
    values[rng.random(values.shape) < 0.1] = np.nan
    values[0, 0, :2] = [np.inf, -np.inf]
    expected = int((~np.isfinite(values)).sum())
    x = torch.from_numpy(values)
    assert count_nonfinite(x) == expected
    with pytest.raises(NonFiniteError, match=rf"^feats holds {expected} non-finite .* of 105 "):
        check_features("feats", x)
    clean = torch.from_numpy(np.nan_to_num(values, posinf=0.0, neginf=0.0))
    assert check_features("feats", clean) is clean
    with pytest.raises(TypeError, match="feats must be a torch.Tensor, got ndarray"):
        check_features("feats", values)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_check_features_accepts_finite_values_whose_sum_overflows(dtype):
    """The check's fast path is a sum; finite values whose sum overflows must still pass and
    one inf among them must still be caught (numpy's isfinite is the reference)."""
    top = torch.finfo(dtype).max
    x = torch.full((4, 3), top, dtype=dtype)
    x[0, 0] = -top  # +max + -max ...: the sum is inf or nan in this dtype
    assert np.isfinite(x.double().numpy()).all()
    assert check_features("x", x) is x
    x[2, 1] = float("inf")
    with pytest.raises(NonFiniteError, match="x holds 1 non-finite"):
        check_features("x", x)
