"""Example images of the playground and the demo notebook: real photographs that
scikit-image ships inside its wheel (``skimage.data``), loaded at run time (nothing is
generated, downloaded or committed)."""

from __future__ import annotations

from PIL import Image

__all__ = ["EXAMPLES", "example_image"]

#: Example name -> (``skimage.data`` function, suggested comma-separated queries).
EXAMPLES: dict[str, tuple[str, str]] = {
    "astronaut": ("astronaut", "astronaut, flag, rocket"),
    "coffee": ("coffee", "coffee cup, spoon, table"),
    "chelsea": ("chelsea", "cat, wall"),
}


def example_image(name: str) -> Image.Image:
    """The example ``name`` (a key of :data:`EXAMPLES`) as an RGB PIL image ``H x W``."""
    if name not in EXAMPLES:
        raise ValueError(f"unknown example image {name!r}; choose from {sorted(EXAMPLES)}")
    import skimage.data  # scikit-image: the `playground` extra

    return Image.fromarray(getattr(skimage.data, EXAMPLES[name][0])()).convert("RGB")
