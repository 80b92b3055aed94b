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


def texture(x, y):
    """A smooth grey texture on the plane z = 0, detail down to about 3 units (5 pixels of
    `plane_views`)."""
    return (0.5 + 0.15 * np.sin(1.3 * x + 0.4 * y) + 0.15 * np.cos(0.9 * y - 0.7 * x)
            + 0.1 * np.sin(2.1 * x * y / 7) + 0.1 * np.sin(2.2 * x - 1.1 * y))


@pytest.fixture(scope="session")
def plane_views():
    """Five cameras 60 above a textured plane z = 0 around the z axis, and their exact renders:
    (V, 3, 4) projections and (V, 48, 64) float32 grey images (each pixel's ray meets the
    plane where `texture` is read)."""
    from neus_l0.data.cameras import look_at, projection_matrix

    H, W = 48, 64
    K = np.array([[80.0, 0, (W - 1) / 2], [0, 80.0, (H - 1) / 2], [0, 0, 1]])
    xs, ys = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    P, images = [], []
    for k in range(5):
        a = 2 * np.pi * k / 5
        eye = np.array([12 * np.cos(a), 12 * np.sin(a), 60.0])
        w2c = look_at(eye, np.zeros(3), up=(0.0, 1.0, 0.0))
        Pk = projection_matrix(K, w2c)[:3]
        d = np.stack([xs, ys, np.ones_like(xs)], -1) @ (w2c[:3, :3].T @ np.linalg.inv(K)).T
        t = -eye[2] / d[..., 2]
        images.append(texture(eye[0] + t * d[..., 0], eye[1] + t * d[..., 1]))
        P.append(Pk)
    return np.stack(P), np.stack(images).astype(np.float32)
