"""The camera and frame functions of `neus_l0.data.cameras` against closed forms."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.data.cameras import (
    camera_z_depth,
    depth_projection,
    look_at,
    pixel_indices,
    projection_matrix,
    read_world_mats,
    scale_projection,
    to_normalised,
    to_world,
    world_scale,
)
from neus_l0.errors import NeusL0Error

K = np.array([[300.0, 0.0, 40.0], [0.0, 300.0, 30.0], [0.0, 0.0, 1.0]])


def _camera(eye=(0.0, -60.0, 20.0)) -> np.ndarray:
    return projection_matrix(K, look_at(np.array(eye), np.zeros(3)))


@settings(max_examples=30, deadline=None)
@given(st.floats(0.1, 10.0), st.sampled_from([1.0, -1.0]))
def test_depth_is_the_distance_along_the_optical_axis(k, sign):
    """Any non-zero multiple of P gives the same depth, which is z in the camera frame."""
    world_mat = _camera()
    w2c = look_at(np.array([0.0, -60.0, 20.0]), np.zeros(3))
    pts = np.random.default_rng(0).normal(scale=10.0, size=(50, 3))
    xy, z = camera_z_depth(sign * k * world_mat, pts)
    cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
    np.testing.assert_allclose(z, cam[:, 2], rtol=1e-12)
    np.testing.assert_allclose(xy, (cam @ K.T)[:, :2] / cam[:, 2:], rtol=1e-12)
    P_n = depth_projection(world_mat)
    np.testing.assert_allclose(depth_projection(P_n), P_n, rtol=1e-15)
    batched = depth_projection(np.stack([world_mat, -2.0 * world_mat]))
    np.testing.assert_allclose(batched, np.stack([P_n, P_n]), rtol=1e-14)


def test_pixel_indices_round_and_miss():
    world_mat = _camera()
    w2c = look_at(np.array([0.0, -60.0, 20.0]), np.zeros(3))
    c2w = np.linalg.inv(w2c)
    # points at camera-frame (x, y, z) whose pixels are known
    cam = np.array([[0.0, 0.0, 50.0],            # principal point (40, 30)
                    [50.0 / 300 * 9.6, 0.0, 50.0],  # x = 49.6 -> column 50
                    [0.0, 0.0, -5.0],            # behind the camera
                    [50.0, 0.0, 50.0]])          # x = 340: outside an 80-wide image
    pts = cam @ c2w[:3, :3].T + c2w[:3, 3]
    col, row, z = pixel_indices(world_mat, pts)
    assert col.tolist() == [40, 50, -1, 340] and row.tolist() == [30, 30, -1, 30]
    np.testing.assert_allclose(z, cam[:, 2], atol=1e-9)
    col, row, _ = pixel_indices(world_mat, pts, height=60, width=80)
    assert col.tolist() == [40, 50, -1, -1] and row.tolist() == [30, 30, -1, -1]


@pytest.mark.parametrize("factor", [1, 2, 3])
def test_scale_projection_keeps_pixel_centres_at_integers(factor):
    """Old pixel (x, y) covers new pixels factor * x .. factor * x + factor - 1."""
    world_mat = _camera()
    pts = np.random.default_rng(1).normal(scale=5.0, size=(20, 3))
    xy, _ = camera_z_depth(world_mat, pts)
    xy2, _ = camera_z_depth(scale_projection(world_mat, factor), pts)
    np.testing.assert_allclose(xy2, factor * xy + (factor - 1) / 2, rtol=1e-12)


def test_frame_conversion_round_trip():
    S = np.diag([12.5, 12.5, 12.5, 1.0])
    S[:3, 3] = [3.0, -4.0, 100.0]
    x = np.random.default_rng(2).uniform(-1, 1, size=(7, 5, 3))
    w = to_world(x, S)
    np.testing.assert_allclose(w, 12.5 * x + [3.0, -4.0, 100.0], rtol=1e-14)
    np.testing.assert_allclose(to_normalised(w, S), x, atol=1e-13)
    np.testing.assert_allclose(to_normalised(w[0, 0], S), x[0, 0], atol=1e-13)
    assert world_scale(S) == pytest.approx(12.5, rel=1e-14)


def test_read_world_mats(tmp_path):
    with pytest.raises(NeusL0Error, match="cameras_sphere.npz: file not found"):
        read_world_mats(tmp_path)
    mats = {f"world_mat_{i}": _camera((10.0 * i, -60.0, 20.0)) for i in range(3)}
    np.savez(tmp_path / "cameras.npz", **mats, world_mat_inv_0=np.eye(4))
    got = read_world_mats(tmp_path)  # the legacy name, the *_inv keys ignored
    assert got.shape == (3, 3, 4)
    np.testing.assert_array_equal(got[2], mats["world_mat_2"][:3])
    np.savez(tmp_path / "cameras_sphere.npz", world_mat_0=np.eye(4), world_mat_2=np.eye(4))
    with pytest.raises(NeusL0Error, match="world_mat_i indices are not 0..1"):
        read_world_mats(tmp_path)
