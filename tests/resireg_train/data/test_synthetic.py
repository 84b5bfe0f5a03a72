import numpy as np
import pytest

from resireg_train.data.synthetic import SYNTHETIC_CLASSES, SyntheticScenes


def test_scenes_are_deterministic_and_consistent():
    scenes = SyntheticScenes(size=20, image_size=(64, 96), seed=3)
    a, b = scenes[7], scenes[7]
    assert (
        np.array_equal(np.asarray(a["image"]), np.asarray(b["image"]))
        and a["caption"] == b["caption"]
    )
    assert not np.array_equal(np.asarray(scenes[8]["image"]), np.asarray(a["image"]))
    for scene in scenes:
        assert scene["image"].size == (96, 64) and scene["mask"].shape == (64, 96)
        present = {SYNTHETIC_CLASSES[c] for c in np.unique(scene["mask"])}
        # The caption names exactly the classes present in the mask.
        named = {c for c in SYNTHETIC_CLASSES if c in scene["caption"]}
        assert named == present, (scene["caption"], present)


def test_mask_matches_image_colours():
    scene = SyntheticScenes(size=1, image_size=(64, 64), noise=0.0)[0]
    image = np.asarray(scene["image"]).astype(float)
    for c in np.unique(scene["mask"]):
        region = image[scene["mask"] == c]
        others = image[scene["mask"] != c]
        if len(others):
            assert np.abs(region.mean(0) - others.mean(0)).max() > 10  # classes look different


def test_bad_index():
    with pytest.raises(IndexError):
        SyntheticScenes(size=2)[2]
