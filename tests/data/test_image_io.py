"""`imread_bytes`: images read whatever their file name (OpenCV's own open crashes on names
that are not UTF-8), and None where `cv2.imread` gives None."""

import os

import cv2
import numpy as np

from neus_l0.data.image_io import imread_bytes


def test_a_name_that_is_not_utf8_reads_as_cv2_would(tmp_path):
    img = (np.arange(4 * 5 * 3) % 256).astype(np.uint8).reshape(4, 5, 3)
    plain = tmp_path / "plain.png"
    assert cv2.imwrite(str(plain), img)
    odd = os.path.join(os.fsencode(tmp_path), b"view_\xff.png")
    with open(odd, "wb") as f:
        f.write(plain.read_bytes())
    got = imread_bytes(os.fsdecode(odd), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(got, cv2.imread(str(plain), cv2.IMREAD_UNCHANGED))


def test_missing_empty_and_garbage_files_give_none(tmp_path):
    (tmp_path / "empty.png").write_bytes(b"")
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    for name in ("missing.png", "empty.png", "junk.png"):
        assert imread_bytes(tmp_path / name, cv2.IMREAD_COLOR) is None
    assert imread_bytes(tmp_path, cv2.IMREAD_COLOR) is None  # a folder
