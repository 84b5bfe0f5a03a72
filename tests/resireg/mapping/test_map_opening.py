"""Opening the map a mapping run builds (resireg.mapping.opening.open_map, the one rule of
resireg-map and the live node): nothing saved gives the fresh map; a saved map of the same
identity resumes with the saved voxels (checked against the tensors of its file, read with
safetensors) and goes on as one run would; each field that differs is refused in one line
naming it, the saved value and today's; a map written with the identity resireg-map recorded
before the move still resumes."""

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from test_compact_map import frames, unit

from resireg.errors import ConfigError
from resireg.mapping import SemanticMap
from resireg.mapping.opening import map_identity, open_map

SOURCE = {"kind": "rosbag", "path": "run.bag", "limit": 6, "idle": 2.0, "tolerance": 0.02}
ENCODER = {"kind": "export", "path": "model"}


def identity(smap, **change):
    """The identity of ``smap`` with the test's source and encoder (``change``: fields
    replaced: ``source``, ``encoder``, ``window``, ``prior``, ``weights``)."""
    keys = {"source": SOURCE, "encoder": ENCODER, "window": 2, "prior": None, "weights": "abc"}
    return map_identity(smap, **{**keys, **change})


def fresh(**settings):
    return SemanticMap(None, settings.pop("configuration", "bb"), settings.pop("voxel", 0.1),
                       **settings)  # fmt: skip


def saved_map(folder, windows=1, **settings):
    """A map of ``windows`` windows of random features, opened fresh and saved to ``folder``
    (the first run); returns the map."""
    smap = fresh(**settings)
    opened = open_map(folder, smap, identity(smap), resume=False, encoder=None)
    assert opened.map is smap and not opened.resumed and smap.meta["kept_frames"] == 0
    for f in frames(windows, 0):
        smap.fuse(*f)
    smap.save(folder)
    return smap


def test_nothing_saved_gives_the_fresh_map_with_its_identity(tmp_path):
    smap = fresh()
    opened = open_map(tmp_path / "map", smap, identity(smap), resume=True, encoder=None)
    assert opened.map is smap and opened.folder == tmp_path / "map" and not opened.resumed
    assert smap.meta["identity"]["source"] == {"kind": "rosbag", "path": "run.bag",
                                               "tolerance": 0.02}  # stop rules left out
    assert smap.meta["identity"]["voxel_size"] == 0.1 and "max_voxels" not in smap.meta["identity"]


def test_same_identity_resumes_with_the_saved_voxels_and_goes_on_as_one_run(tmp_path):
    """The resumed map holds the file's voxels (unit sums / counts, row by row, recomputed
    with numpy from the safetensors file), and a second window fused into it equals one map
    of both windows."""
    saved_map(tmp_path / "map")
    now = fresh()
    smap, folder, resumed = open_map(tmp_path / "map", now, identity(now), resume=True,
                                     encoder=None)  # fmt: skip
    assert resumed and folder == tmp_path / "map" and smap is not now
    record = json.loads((folder / "map.json").read_text())
    tensors = load_file(folder / record["tensors"])
    sums, counts = tensors["features.sums"].numpy(), tensors["features.counts"].numpy()
    assert len(smap) == len(counts) == record["voxels"]
    np.testing.assert_allclose(smap.features()[1].double().numpy(),
                               unit(sums / counts[:, None]), rtol=0, atol=1e-6)  # fmt: skip
    both = fresh()
    for f in frames(2, 0):
        both.fuse(*f)
    smap.fuse(*frames(2, 0)[1])
    assert len(smap) == len(both) and smap.frames == both.frames == 4
    a, b = smap.features(), both.features()
    order_a, order_b = (np.lexsort(c.numpy().T) for c in (a[0], b[0]))
    np.testing.assert_array_equal(a[0].numpy()[order_a], b[0].numpy()[order_b])
    np.testing.assert_allclose(a[1].numpy()[order_a], b[1].numpy()[order_b], atol=1e-6)


def test_a_run_folder_names_its_map_and_max_voxels_may_change(tmp_path):
    """map_folder's rule: the run folder's ``map/``; max_voxels bounds the map, so a resumed
    map takes today's."""
    saved_map(tmp_path / "run" / "map")
    now = fresh(max_voxels=100_000)
    smap, folder, resumed = open_map(tmp_path / "run", now, identity(now), resume=True,
                                     encoder=None)  # fmt: skip
    assert resumed and folder == tmp_path / "run" / "map"
    assert smap.settings()["max_voxels"] == 100_000


CHANGES = [
    ({"voxel": 0.2}, {}, "voxel_size: 0.1 in the map, 0.2 now"),
    ({"configuration": "lite"}, {}, "configuration: 'bb' in the map, 'lite' now"),
    ({"points": "pixel"}, {}, "points: 'patch' in the map, 'pixel' now"),
    ({"sum_dtype": "float32"}, {}, "sum_dtype: 'float64' in the map, 'float32' now"),
    ({"short_side": 224}, {}, "short_side: None in the map, 224 now"),
    ({"colour": False}, {}, "colour: True in the map, False now"),
    ({"params": {"lite": {"alpha": 0.5}}}, {}, "params.lite.alpha: (not recorded) in the map, 0.5 now"),
    ({"storage": "compact", "compact": {"dim": 8, "basis_rows": 10}}, {},
     "storage: 'exact' in the map, 'compact' now"),
    ({}, {"weights": "def"}, "weights: 'abc' in the map, 'def' now"),
    ({}, {"window": 4}, "window: 2 in the map, 4 now"),
    ({}, {"prior": {"kind": "sam2"}},
     "prior: None in the map, (not recorded) now; prior.kind: (not recorded) in the map, "
     "'sam2' now"),
    ({}, {"encoder": {**ENCODER, "path": "other"}}, "encoder.path: 'model' in the map, 'other' now"),
    ({}, {"source": {**SOURCE, "tolerance": 0.05}}, "source.tolerance: 0.02 in the map, 0.05 now"),
]  # fmt: skip


@pytest.mark.parametrize(("settings", "change", "named"), CHANGES,
                         ids=[c[2].split(":")[0] for c in CHANGES])  # fmt: skip
def test_each_field_that_differs_is_refused_naming_it(tmp_path, settings, change, named):
    saved_map(tmp_path / "map")
    before = (tmp_path / "map" / "map.json").read_bytes()
    now = fresh(**settings)
    with pytest.raises(ConfigError) as err:
        open_map(tmp_path / "map", now, identity(now, **change), resume=True, encoder=None)
    text = str(err.value)
    # a block one side lacks: the key and each of its leaves (a compact map's 5 keys)
    count = {"storage": 7, "prior": 2}.get(named.split(":")[0], 1)
    assert "\n" not in text and f"({count} differ): " in text and named in text, text
    assert text.startswith(f"resume=true: {tmp_path / 'map'} was made with other settings")
    assert (tmp_path / "map" / "map.json").read_bytes() == before


def test_every_difference_is_named_shallowest_first(tmp_path):
    saved_map(tmp_path / "map")
    now = fresh(voxel=0.2)
    change = {"weights": "def", "encoder": {**ENCODER, "path": "other"}}
    with pytest.raises(ConfigError, match=r"\(3 differ\): voxel_size: 0\.1 in the map, 0\.2 "
                       r"now; weights: 'abc' in the map, 'def' now; encoder\.path: "):  # fmt: skip
        open_map(tmp_path / "map", now, identity(now, **change), resume=True, encoder=None)


def test_a_saved_map_without_resume_is_refused_in_the_callers_words(tmp_path):
    saved_map(tmp_path / "map")
    now = fresh()
    with pytest.raises(ConfigError, match=r"map holds a map: -p resume:=true continues it, or "
                       r"set another -p output_dir:=\.\.\.$"):  # fmt: skip
        open_map(tmp_path / "map", now, identity(now), resume=False, encoder=None,
                 resume_flag="-p resume:=true", elsewhere="set another -p output_dir:=...")  # fmt: skip


def test_a_map_recorded_before_the_move_resumes(tmp_path):
    """The identity resireg-map recorded before the one opening rule (the map's settings
    copied under their config names, the variants' parameters as ``resireg``) and the node's
    (no window, no prior): both resume with today's identity, the map's settings then read
    from its record; a field it records still counts."""
    for name, old in {
        "map": {"source": {"kind": "rosbag", "path": "run.bag", "tolerance": 0.02},
                "configuration": "bb", "window": 2, "voxel_size": 0.1, "points": "patch",
                "lattice": "round", "sum_dtype": "float64", "short_side": None,
                "encoder": ENCODER, "resireg": {"full": {}, "lite": {}, "calib": {}},
                "prior": None, "weights": "abc"},
        "node": {"encoder": ENCODER, "weights": "abc",
                 "source": {"kind": "rosbag", "path": "run.bag", "tolerance": 0.02}},
    }.items():  # fmt: skip
        smap = fresh()
        for f in frames(1, 0):
            smap.fuse(*f)
        smap.meta = {"identity": old, "kept_frames": 2}
        smap.save(tmp_path / name)
        now = fresh()
        opened = open_map(tmp_path / name, now, identity(now), resume=True, encoder=None)
        assert opened.resumed and opened.map.meta["kept_frames"] == 2
        assert opened.map.meta["identity"] == identity(now)
        with pytest.raises(ConfigError, match=r"\(1 differ\): weights: 'abc' in the map"):
            open_map(tmp_path / name, now, identity(now, weights="x"), resume=True, encoder=None)


def test_torch_state_is_not_touched_by_opening(tmp_path):
    """Opening builds no module: the global RNG a resumed run's mapping draws from is the
    one an uninterrupted run's has."""
    saved_map(tmp_path / "map")
    torch.manual_seed(0)
    expected = torch.rand(3)
    now = fresh()
    torch.manual_seed(0)
    open_map(tmp_path / "map", now, identity(now), resume=True, encoder=None)
    assert torch.equal(torch.rand(3), expected)
