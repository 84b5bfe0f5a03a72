"""A compact map's classify (resireg.mapping.compact.CompactVoxelMap.classify) against an
independent float64 numpy recomputation of the 3D task's rule over the same stored features:
the cosine argmax and RayFronts' thresholded, prompt-denoised softmax, with tied classes, rows
under the threshold, classes the denoising removes, hot voxels and the denoising threshold below
0.5 (the float64 path)."""

import math

import numpy as np
import pytest
import torch

from resireg.mapping.compact import CompactVoxelMap

DIM, CLASSES, CHUNK = 16, 32, 64
TIED = (3, 7)  # class 7 is class 3's prototype: every row whose best is 3 ties with 7


@pytest.fixture(scope="module")
def scene():
    """600 voxels (three points each, then one more point for 80 of them, which stay hot).
    Half the prototypes spread around one direction ``u``, half clustered near it; a third of
    the voxels near ``u`` (probabilities spread over the clustered classes: under 0.1), the
    others near one prototype (clear winners, or near-ties among the clustered ones)."""
    g = torch.Generator().manual_seed(4)
    u = torch.nn.functional.normalize(torch.randn(DIM, generator=g), dim=0)
    spread = torch.where(torch.arange(CLASSES) % 2 == 0, 0.15, 0.03)[:, None]
    protos = u + spread * torch.randn(CLASSES, DIM, generator=g)
    protos[TIED[1]] = protos[TIED[0]]
    grid = torch.stack(torch.meshgrid(torch.arange(20), torch.arange(30), torch.arange(1),
                                      indexing="ij"), -1).reshape(-1, 3).float() * 0.1  # fmt: skip
    m = grid.shape[0]
    grid = grid[torch.randperm(m, generator=g)]  # rows not in key order
    pick = torch.randint(0, CLASSES, (m,), generator=g)
    at_u = (torch.arange(m) % 3 == 0)[:, None]
    base = torch.where(at_u, u, torch.nn.functional.normalize(protos[pick], dim=1))
    scale = torch.where(at_u, 0.01, 0.03)
    cm = CompactVoxelMap(0.1, DIM, hot_voxels=100)
    feats = base[:, None] + scale[:, None] * torch.randn(m, 3, DIM, generator=g)
    cm.add(grid.repeat_interleave(3, 0), feats.reshape(-1, DIM))
    cm.add(grid[:80], base[:80] + scale[:80] * torch.randn(80, DIM, generator=g))
    assert cm.hot_rows.numel() == 80
    return cm, protos


def reference(features, protos, threshold, denoise, chunk, none=-1):
    """The rule in float64 numpy: both sides normalised, ``softmax(100 cos)``, per chunk of
    ``chunk`` rows the classes whose largest probability is below ``denoise`` removed, the
    first largest remaining class, ``none`` below ``threshold``; or the cosine argmax."""
    f = np.asarray(features, dtype=np.float64)
    f = f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)
    p = np.asarray(protos, dtype=np.float64)
    p = p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-12)
    cos = f @ p.T
    if threshold is None and denoise is None:
        return cos.argmax(1)
    e = np.exp(100 * (cos - cos.max(1, keepdims=True)))
    prob = e / e.sum(1, keepdims=True)
    out = np.empty(len(f), dtype=np.int64)
    for s in range(0, len(f), chunk):
        q = prob[s : s + chunk].copy()
        if denoise is not None:
            q[:, q.max(0) < denoise] = -np.inf
        label = q.argmax(1)
        if threshold is not None:
            label[q.max(1) < threshold] = none
        out[s : s + chunk] = label
    return out


@pytest.mark.parametrize(
    ("threshold", "denoise"), [(None, None), (0.1, None), (None, 0.5), (0.1, 0.5), (0.1, 0.3)]
)
def test_classify_equals_the_float64_rule(scene, threshold, denoise):
    cm, protos = scene
    feats = cm.features()[1].numpy()  # the stored features, in indices order
    want = reference(feats, protos.numpy(), threshold, denoise, CHUNK)
    got = cm.classify(protos, threshold, denoise, none=-1, denoise_chunk=CHUNK)
    np.testing.assert_array_equal(got.numpy(), want)
    # the data reach every branch of the rule
    plain = reference(feats, protos.numpy(), None, None, CHUNK)
    assert (plain == TIED[0]).sum() >= 5 and not (plain == TIED[1]).any()
    if threshold is not None:
        assert 0 < (want == -1).sum() < len(want)
    if denoise is not None:
        masked = reference(feats, protos.numpy(), threshold, None, CHUNK)
        assert (want != masked).sum() >= 5  # the denoising changes labels
    assert len(set(want.tolist()) - {-1}) >= 4


def test_classify_ties_go_to_the_lowest_class_and_none_is_the_callers(scene):
    """A row whose feature is a prototype itself ties exactly with its duplicate; labels of
    another ``none`` id; the argmax without the rule on rows the bound leaves open."""
    cm, protos = scene
    got = cm.classify(protos, 0.1, 0.5, none=CLASSES, denoise_chunk=CHUNK)
    want = reference(cm.features()[1].numpy(), protos.numpy(), 0.1, 0.5, CHUNK, none=CLASSES)
    np.testing.assert_array_equal(got.numpy(), want)
    one = CompactVoxelMap(0.1, DIM)
    one.add(torch.zeros(1, 3), protos[TIED[0]][None])
    assert one.classify(protos).tolist() == [TIED[0]]
    for rule in ((0.1, None), (None, 0.5), (0.1, 0.5)):
        want = reference(one.features()[1].numpy(), protos.numpy(), *rule, CHUNK)
        assert one.classify(protos, *rule).tolist() == want.tolist()


@pytest.mark.parametrize(("others", "level", "rule"), [(10, 0.1, (0.1, None)),
                                                     (2, 0.5, (None, 0.5))])  # fmt: skip
def test_a_probability_at_the_threshold_is_decided_in_float64(others, level, rule):
    """One voxel whose best class's probability crosses the threshold (or the denoising level)
    within float32's error: the last class scores 1, ``others`` score ``c`` with ``c`` stepped
    by 2e-9 across the crossing (float32 cannot tell the steps apart). Every step's label is
    the float64 rule's, and both sides of the crossing are met."""
    cm = CompactVoxelMap(0.1, DIM)
    feature = torch.zeros(1, DIM)
    feature[0, 0] = 1.0
    cm.add(torch.zeros(1, 3), feature)
    crossing = 1 - math.log(others * level / (1 - level)) / 100  # probability = level
    got, want = [], []
    for step in range(-12, 13):
        c = crossing + (step + 0.5) * 2e-9  # never at the crossing itself
        protos = torch.zeros(others + 1, DIM, dtype=torch.float64)
        protos[others, 0] = 1.0
        for j in range(others):
            protos[j, 0], protos[j, j + 1] = c, math.sqrt(1 - c * c)
        got.append(int(cm.classify(protos, *rule)[0]))
        want.append(int(reference(cm.features()[1].numpy(), protos.numpy(), *rule, CHUNK)[0]))
    assert got == want
    assert set(want) == {others, -1 if rule[0] is not None else 0}


def test_classify_refuses_prototypes_of_another_dimension(scene):
    cm, protos = scene
    with pytest.raises(ValueError, match=r"prototypes of shape \(32, 8\)"):
        cm.classify(protos[:, :8])
