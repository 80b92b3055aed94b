"""Reading an image file whatever its name: OpenCV's own file open crashes on a path that is
not valid UTF-8, so the bytes are read by Python and decoded by OpenCV."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def imread_bytes(path: Path, flags: int) -> np.ndarray | None:
    """`cv2.imread` of the file's bytes: OpenCV's own open crashes on a path that is not
    valid UTF-8 (a name with a 0xff byte); None when the file does not read or decode."""
    try:
        data = np.fromfile(path, np.uint8)
    except (OSError, ValueError):
        return None
    return cv2.imdecode(data, flags) if data.size else None
