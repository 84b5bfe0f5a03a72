"""Small file helpers shared by the data, evaluation and tracking code."""

from __future__ import annotations

import os
from pathlib import Path

from PIL import Image

__all__ = ["DECODE_ERRORS", "write_atomic"]

#: What PIL raises for an undecodable image file (skipped and counted, never fatal).
DECODE_ERRORS = (OSError, ValueError, SyntaxError, Image.DecompressionBombError)


def write_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename,
    so a reader (or a crash) never sees a half-written file under the final name."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)
    return path
