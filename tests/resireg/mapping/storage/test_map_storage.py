"""The map's rooms (issue 52): the storage interface (exact and compact answer the same queries,
each against a float64 numpy recomputation of the voxel means), the fitted basis against a numpy
eigendecomposition, the lifted points' named fields, the ``variant=`` keyword and its
deprecated spelling, and an AST check that ``SemanticMap`` never branches on the storage kind."""

import ast
import dataclasses
import json
import warnings

import numpy as np
import pytest
import torch

from helpers.paths import ROOT
from resireg.mapping import SemanticMap
from resireg.mapping.lifting import LiftedPoints, lift_grid
from resireg.mapping.storage import STORAGE_TYPES
from resireg.mapping.storage.base import MapStorage
from resireg.specs.mapping import STORAGES

MAPPING = ROOT / "src" / "resireg" / "mapping"
B, D, H, W = 2, 8, 4, 6  # frames, channels, feature grid (= depth image, so no resampling)


@pytest.fixture(scope="module")
def window():
    """A window whose geometry is known without the lifting code: depth 1 m, identity
    intrinsics and poses, so patch ``(v, u)`` lands at ``(u, v, 1)``; with 2 m voxels on the
    ``floor`` lattice, voxel ``(u // 2, v // 2, 0)`` holds the patches of both frames."""
    g = torch.Generator().manual_seed(3)
    feats = torch.randn(B, D, H, W, generator=g, dtype=torch.float64).float()
    depth = torch.ones(B, H, W)
    k = torch.eye(3)
    pose = torch.eye(4).repeat(B, 1, 1)
    return feats, depth, k, pose


def reference_means(feats):
    """``{(i, j, k): float64 mean feature}`` of the window (numpy, from the docstring's rule)."""
    x = feats.double().numpy()
    sums, counts = {}, {}
    for b in range(B):
        for v in range(H):
            for u in range(W):
                key = (u // 2, v // 2, 0)
                sums[key] = sums.get(key, 0) + x[b, :, v, u]
                counts[key] = counts.get(key, 0) + 1
    keys = sorted(sums)
    return keys, np.stack([sums[c] / counts[c] for c in keys])


def unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def built(storage, window, **kw):
    smap = SemanticMap(None, "bb", 2.0, lattice="floor", storage=storage, colour=False, **kw)
    smap.fuse(*window)
    smap.fit_pending()
    return smap


@pytest.mark.parametrize("storage, atol", [("exact", 1e-6), ("compact", 2e-3)])
def test_each_storage_answers_the_numpy_similarities(window, storage, atol):
    """query, classify_features and top_k of an exact (float64 sums) and a compact (float16
    unit means, no projection) map equal the cosines of the float64 numpy voxel means; the
    storage object answers them (``similarities``), not the map."""
    keys, means = reference_means(window[0])
    smap = built(storage, window, compact={"dim": None} if storage == "compact" else None)
    assert type(smap.store) is STORAGE_TYPES[storage]
    assert smap.indices.tolist() == [list(c) for c in keys]
    queries = torch.randn(3, D, generator=torch.Generator().manual_seed(4))
    want = unit(means) @ unit(queries.double().numpy()).T
    np.testing.assert_allclose(smap.query(queries).double().numpy(), want, atol=atol)
    np.testing.assert_allclose(
        smap.store.similarities(torch.nn.functional.normalize(queries, dim=-1)).double().numpy(),
        want, atol=atol)  # fmt: skip
    labels = smap.classify_features(torch.nn.functional.normalize(queries, dim=-1))
    assert labels.tolist() == want.argmax(1).tolist()
    best = smap.top_k(queries[0], k=3)
    order = np.argsort(-want[:, 0], kind="stable")[:3]
    assert best.indices.tolist() == [list(keys[i]) for i in order]
    np.testing.assert_allclose(
        best.scores.numpy(), want[order, 0], atol=atol
    )  # of the stored means


def test_the_compact_basis_is_the_numpy_uncentred_pca(window):
    """A compact map with ``compact.dim = 3`` fits its basis on the window's features: its
    projector equals that of numpy's top-3 eigenvectors of ``X^T X`` (float64), and its
    similarities are the numpy means' in that basis's space."""
    smap = built("compact", window, compact={"dim": 3, "basis_rows": 10_000})
    x = window[0].double().permute(0, 2, 3, 1).reshape(-1, D).numpy()
    vals, vecs = np.linalg.eigh(x.T @ x)
    top = vecs[:, -3:]
    basis = smap.basis.double().numpy()
    np.testing.assert_allclose(basis @ basis.T, top @ top.T, atol=1e-5)
    assert smap.stored_dim == 3 and smap.store.stored_dim == 3
    _, means = reference_means(window[0])
    q = torch.randn(2, D, generator=torch.Generator().manual_seed(5))
    want = unit(means @ basis) @ unit(q.double().numpy() @ basis).T
    np.testing.assert_allclose(smap.query(q).double().numpy(), want, atol=2e-3)


def test_the_storage_table_is_the_storage_choices():
    """One storage class per ``storage=`` name, each a MapStorage; the interface is abstract."""
    assert tuple(STORAGE_TYPES) == STORAGES
    assert all(issubclass(cls, MapStorage) for cls in STORAGE_TYPES.values())
    with pytest.raises(TypeError, match="abstract"):
        MapStorage(0.1, "round", torch.device("cpu"), False, "float64", None)
    with pytest.raises(
        ValueError, match=r"storage='dense': expected one of \['exact', 'compact'\]"
    ):
        SemanticMap(None, "bb", 0.1, storage="dense")


@pytest.mark.parametrize("mode", ["patch", "pixel"])
def test_lifted_points_name_their_fields(window, mode):
    """A lifted window is a frozen dataclass of named fields: the patch mode's points (one per
    feature row), the pixel mode's (voxel, patch, count) pairs over every feature row; its
    voxels and its features once each are read from them, and a basis projects the features."""
    feats, depth, k, pose = window
    grid = lift_grid(mode, depth, k, pose, (H, W), 2.0, "floor")
    rows = feats.permute(0, 2, 3, 1)
    lifted = grid.with_features(rows, None)
    assert isinstance(lifted, LiftedPoints) and lifted.mode == mode
    index = lifted.voxel_index(2.0, "floor")
    if mode == "patch":
        assert lifted.index is None and lifted.patch is None and lifted.count is None
        v, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
        want = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3)
        np.testing.assert_allclose(lifted.points.numpy(), np.tile(want, (B, 1)), atol=1e-6)
        assert index.tolist() == np.tile(np.stack([want[:, 0] // 2, want[:, 1] // 2,
                                                   np.zeros(len(want), int)], 1), (B, 1)).tolist()  # fmt: skip
        assert torch.equal(lifted.features, rows.reshape(-1, D))
    else:
        assert lifted.points is None
        assert int(lifted.count.sum()) == B * H * W  # every pixel of every frame, once
        assert lifted.features.shape == (B * H * W, D)
        assert torch.equal(index, lifted.index)
    assert torch.equal(lifted.distinct_features(), rows.reshape(-1, D))
    basis = torch.randn(D, 3, generator=torch.Generator().manual_seed(6))
    np.testing.assert_allclose(lifted.projected(basis).features.numpy(),
                               rows.reshape(-1, D).numpy() @ basis.numpy(), atol=1e-5)  # fmt: skip
    assert lifted.projected(None) is lifted
    with pytest.raises(dataclasses.FrozenInstanceError):
        lifted.features = None


def test_variant_keyword_and_its_deprecated_spelling(tmp_path, window):
    """``variant=`` is the keyword; ``configuration=`` still works for one release with a
    FutureWarning naming ``variant=``; both given are refused in one line naming both. The
    saved record keeps its field ``settings.configuration``, so old and new maps load alike."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        new = SemanticMap(None, variant="bb", voxel_size=2.0)
    with pytest.warns(FutureWarning, match=r"configuration=.*deprecated.*use variant="):
        old = SemanticMap(None, configuration="bb", voxel_size=2.0)
    assert old.settings() == new.settings() and old.variant_name == "bb"
    with pytest.raises(TypeError, match=r"variant='bb' and configuration='lite' both given") as err:
        SemanticMap(None, "bb", 2.0, configuration="lite")
    assert "\n" not in str(err.value)
    with pytest.raises(TypeError, match="needs variant="):
        SemanticMap(None, voxel_size=2.0)
    new.fuse(*window)
    new.save(tmp_path / "m")
    record = json.loads((tmp_path / "m" / "map.json").read_text())
    assert record["settings"]["configuration"] == "bb" and "variant" not in record["settings"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = SemanticMap.load(tmp_path / "m")
    assert back.variant_name == "bb" and torch.equal(back.indices, new.indices)


STORAGE_CLASSES = {"VoxelMap", "CompactVoxelMap", "SparseVoxels", "MapStorage", "ExactStorage",
                   "CompactStorage"}  # fmt: skip


def storage_branches(source: str) -> list[str]:
    """``isinstance`` calls naming a storage class, and comparisons with a storage kind's name
    (``"exact"``, ``"compact"``), in ``source``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "isinstance":
            names = {n.id for n in ast.walk(node.args[1]) if isinstance(n, ast.Name)}
            names |= {n.attr for n in ast.walk(node.args[1]) if isinstance(n, ast.Attribute)}
            found += [f"isinstance(..., {n})" for n in sorted(names & STORAGE_CLASSES)]
        if isinstance(node, ast.Compare):
            consts = [n.value for n in ast.walk(node) if isinstance(n, ast.Constant)]
            found += [f"compare with {c!r}" for c in consts if c in STORAGES]
    return found


def test_semantic_map_never_branches_on_the_storage_kind():
    """No ``isinstance`` on a storage class and no comparison with a storage kind in
    ``semantic_map.py`` (the storage object answers); the scanner finds planted ones."""
    assert storage_branches((MAPPING / "semantic_map.py").read_text()) == []
    planted = ("if isinstance(self.voxels, CompactVoxelMap):\n    pass\n"
               "if isinstance(v, (mapping.VoxelMap, int)):\n    pass\n"
               "if self.storage == 'compact':\n    pass\n")  # fmt: skip
    assert storage_branches(planted) == ["isinstance(..., CompactVoxelMap)",
                                         "isinstance(..., VoxelMap)", "compare with 'compact'"]  # fmt: skip


def test_mapping_modules_are_one_idea_each():
    """Every module of resireg/mapping is under 500 lines, or says in its docstring, in a
    paragraph starting ``One idea:``, why it is one idea; ``semantic_map.py`` is under 500."""
    long = []
    for path in sorted(MAPPING.rglob("*.py")):
        text = path.read_text()
        doc = ast.get_docstring(ast.parse(text)) or ""
        if len(text.splitlines()) >= 500 and "\nOne idea:" not in f"\n{doc}":
            long.append(path.name)
    assert long == []
    assert len((MAPPING / "semantic_map.py").read_text().splitlines()) < 500
