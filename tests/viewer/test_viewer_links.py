"""A run folder with a planted link (second attack of #33): a validation image linked to a
picture outside the run is not shown on the page (`neus_l0.viewer.run_files`)."""

from __future__ import annotations

import cv2
import numpy as np

from neus_l0.viewer.run_files import validation_images


def test_a_validation_image_linked_out_of_the_run_is_left_out(tmp_path):
    """validation/ holds one real image and one link to a file outside: only the real one."""
    run = tmp_path / "run"
    (run / "validation").mkdir(parents=True)
    secret = tmp_path / "private.png"
    cv2.imwrite(str(secret), np.zeros((4, 4, 3), np.uint8))
    cv2.imwrite(str(run / "validation" / "0000010_v000.png"), np.zeros((4, 4, 3), np.uint8))
    (run / "validation" / "0000020_v000.png").symlink_to(secret)
    assert [(i, v) for i, v, _p in validation_images(run)] == [(10, 0)]
