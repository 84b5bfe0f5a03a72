"""Tiny ADE20K validation folders (ADEChallengeData2016's layout) written by the tests: a clean
one with an optional unreadable file (:func:`ade_folder`) and one with a sample of each fault
the reader skips (:func:`poisoned_ade_folder`), shared by the data, evaluation and fault tests."""

import numpy as np
from PIL import Image


def save_image(array, path):
    """``array`` written as an image at ``path`` (PIL picks the format by the suffix)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array).save(path)


def ade_folder(root, n=3, corrupt=True):
    """An ADEChallengeData2016 validation folder of ``n`` random images (40 x 56 and 56 x 40 by
    turns) and labels 0..150; with ``corrupt``, one more file that is not an image (and its
    label). Returns the labels written, in order."""
    rng = np.random.default_rng(0)
    labels = []
    for i in range(n):
        h, w = (40, 56) if i % 2 == 0 else (56, 40)
        image = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
        label = rng.integers(0, 151, (h, w), dtype=np.uint8)
        save_image(image, root / "images/validation" / f"ADE_val_{i:08d}.jpg")
        save_image(label, root / "annotations/validation" / f"ADE_val_{i:08d}.png")
        labels.append(label)
    if corrupt:
        (root / "images/validation/ADE_val_99999999.jpg").write_bytes(b"not a jpeg")
        save_image(np.zeros((8, 8), np.uint8), root / "annotations/validation/ADE_val_99999999.png")
    return labels


def poisoned_ade_folder(root):
    """An ADEChallengeData2016 folder of 48 x 64 images: five good ones (one ``.JPG``) and one
    of each fault: a label id past 150, an RGB label, a label of another size, a truncated
    image. Returns ``{file name: expected reason regex}`` of the bad ones."""
    rng = np.random.default_rng(0)

    def pair(stem, ext=".jpg", label=None):
        save_image(
            rng.integers(0, 255, (48, 64, 3), dtype=np.uint8),
            root / f"images/validation/{stem}{ext}",
        )
        label = rng.integers(0, 151, (48, 64), dtype=np.uint8) if label is None else label
        save_image(label, root / f"annotations/validation/{stem}.png")

    for i in range(4):
        pair(f"ADE_val_{i:08d}")
    out_of_range = rng.integers(0, 151, (48, 64), dtype=np.uint8)
    out_of_range[5, 7] = 200
    pair("ADE_val_00000010", label=out_of_range)
    pair("ADE_val_00000011", label=rng.integers(0, 151, (48, 64, 3), dtype=np.uint8))
    pair("ADE_val_00000012", label=rng.integers(0, 151, (40, 64), dtype=np.uint8))
    pair("ADE_val_00000013")
    jpeg = root / "images/validation/ADE_val_00000013.jpg"
    jpeg.write_bytes(jpeg.read_bytes()[: jpeg.stat().st_size // 2])
    pair("ADE_val_00000014", ext=".JPG")
    return {
        "ADE_val_00000010.jpg": r"class id 200; valid ids are 0\.\.150",
        "ADE_val_00000011.jpg": r"shape \(48, 64, 3\).*not a colour image",
        "ADE_val_00000012.jpg": r"label is 40 x 64 px but its image is 48 x 64 px",
        "ADE_val_00000013.jpg": r"unreadable: image file is truncated",
    }
