"""Optional references whose import can fail for a reason other than a missing package."""

import pytest


def open3d():
    """open3d (the dev extra), or a skip that names what is missing: its library links the
    system's libusb (Debian: ``apt-get install libusb-1.0-0``, which ``.ci/run`` does), and a
    missing system library is an ``ImportError``, not the ``ModuleNotFoundError`` that
    ``pytest.importorskip`` skips on by default."""
    return pytest.importorskip(
        "open3d", exc_type=ImportError,
        reason="open3d does not import (pip install -e '.[dev]'; it needs libusb-1.0-0 from apt)",
    )  # fmt: skip
