"""Fixtures shared by the mesh steps' tests."""

import numpy as np
import pytest


def _box_masks(P, boxes, height, width):
    """V (H, W) bool: the pixels whose centre ray meets any of the axis-aligned `boxes`
    (meshes; an exact slab test on their bounds), for projections `P` (V, 3, 4)."""
    xs, ys = np.meshgrid(np.arange(width), np.arange(height))
    pix = np.stack([xs.ravel(), ys.ravel(), np.ones(width * height)], 1)
    out = []
    for p in P:
        M, t = p[:, :3], p[:, 3]
        o = -np.linalg.solve(M, t)  # the camera centre
        d = pix @ np.linalg.inv(M).T  # each pixel's ray direction
        hit = np.zeros(width * height, bool)
        for b in boxes:
            with np.errstate(divide="ignore", invalid="ignore"):
                t0, t1 = (b.bounds[0] - o) / d, (b.bounds[1] - o) / d
            near = np.nanmax(np.minimum(t0, t1), axis=1)
            far = np.nanmin(np.maximum(t0, t1), axis=1)
            hit |= (far >= near) & (far > 0)
        out.append(hit.reshape(height, width))
    return out


@pytest.fixture(scope="session")
def box_masks():
    """``box_masks(P, boxes, height, width)``: exact masks of axis-aligned boxes."""
    return _box_masks
