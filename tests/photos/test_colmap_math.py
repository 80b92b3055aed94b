"""Pure math of the own-photos pipeline: Umeyama alignment, axes convergence, the sphere."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neus_l0.data.cameras import axes_convergence
from neus_l0.experiments.photos_align import pose_errors, rotation_angle_deg, umeyama
from neus_l0.formats.preview import sphere_outline
from neus_l0.formats.sphere import choose_sphere


def _random_sim(rng):
    return float(rng.uniform(0.1, 10.0)), Rotation.random(random_state=rng).as_matrix(), \
        rng.normal(size=3) * 5


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(0)
    for _ in range(20):
        s, R, t = _random_sim(rng)
        src = rng.normal(size=(30, 3))
        dst = s * src @ R.T + t
        s2, R2, t2 = umeyama(src, dst)
        assert s2 == pytest.approx(s, rel=1e-10)
        np.testing.assert_allclose(R2, R, atol=1e-10)
        np.testing.assert_allclose(t2, t, atol=1e-9)
        assert np.linalg.det(R2) == pytest.approx(1.0)


def test_umeyama_rigid_and_errors():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(10, 3))
    _, R, t = _random_sim(rng)
    s2, R2, _ = umeyama(src, src @ R.T + t, with_scale=False)
    assert s2 == 1.0
    np.testing.assert_allclose(R2, R, atol=1e-10)
    with pytest.raises(ValueError):
        umeyama(src[:2], src[:2])
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError):
        umeyama(line, line)


def test_umeyama_reflection_is_not_returned():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image: best proper rotation, det +1
    _, R, _ = umeyama(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_pose_errors_zero_for_exact_similarity():
    rng = np.random.default_rng(3)
    n = 12
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    c2w[:, :3, 3] = rng.normal(size=(n, 3)) * 100
    s, R, t = _random_sim(rng)
    est = c2w.copy()
    est[:, :3, :3] = R.T @ c2w[:, :3, :3]
    est[:, :3, 3] = (c2w[:, :3, 3] - t) @ R / s  # so that s R est + t = true
    e = pose_errors(est, c2w, object_size=100.0)
    assert e["center_err_max_rel"] < 1e-9
    assert e["rot_err_max_deg"] < 1e-5
    assert rotation_angle_deg(np.eye(3), Rotation.from_euler("z", 30, degrees=True)
                              .as_matrix()) == pytest.approx(30.0)


def test_axes_convergence_exact_and_parallel():
    rng = np.random.default_rng(4)
    target = np.array([1.0, -2.0, 3.0])
    centres = rng.normal(size=(15, 3)) * 10
    dirs = (target - centres) * rng.uniform(0.5, 2.0, (15, 1))
    np.testing.assert_allclose(axes_convergence(centres, dirs), target, atol=1e-9)
    with pytest.raises(ValueError):
        axes_convergence(centres, np.tile([0.0, 0.0, 1.0], (15, 1)))


def _ring_cameras(n=20, dist=10.0, aim=(0.0, 0.0, 0.0)):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    centres = np.stack([dist * np.cos(a), dist * np.sin(a), 3.0 + 0 * a], -1)
    return centres, np.asarray(aim) - centres


def test_choose_sphere_robust_to_background_and_strays():
    rng = np.random.default_rng(5)
    centres, dirs = _ring_cameras()
    obj = rng.normal(size=(2000, 3))
    obj = obj / np.linalg.norm(obj, axis=-1, keepdims=True) * rng.uniform(0, 1, (2000, 1))
    obj += [0.3, -0.2, 0.1]
    background = rng.normal(size=(500, 3)) * 50  # far away
    strays = rng.uniform(-5, 5, (30, 3))
    pts = np.concatenate([obj, background, strays])
    track = np.concatenate([np.full(2000, 5), np.full(500, 5), np.full(30, 2)])
    ch = choose_sphere(pts, track, centres, dirs)
    assert np.linalg.norm(ch.center - [0.3, -0.2, 0.1]) < 0.1
    assert 1.0 <= ch.radius < 1.5
    assert np.linalg.norm(obj - ch.center, axis=-1).max() <= ch.radius
    assert "automatic" in ch.explain()


def test_choose_sphere_keeps_cameras_outside_and_falls_back():
    centres, dirs = _ring_cameras(dist=2.0)
    pts = np.random.default_rng(6).normal(size=(100, 3)) * 1.5
    ch = choose_sphere(pts, np.full(100, 4), centres, dirs)
    assert ch.radius < np.linalg.norm(centres - ch.center, axis=-1).min()
    empty = choose_sphere(np.zeros((0, 3)), np.zeros(0), *_ring_cameras())
    assert empty.n_points == 0 and empty.radius > 0


def test_sphere_outline_touches_projected_sphere():
    K = np.array([[500.0, 0, 200], [0, 500.0, 150], [0, 0, 1]])
    P = K @ np.hstack([np.eye(3), [[0.0], [0.0], [10.0]]])  # camera at (0, 0, -10)
    ring = sphere_outline(P, np.zeros(3), 1.0)
    r = np.linalg.norm(ring - [200, 150], axis=-1)
    expected = 500.0 * np.tan(np.arcsin(0.1))
    np.testing.assert_allclose(r, expected, rtol=1e-9)
    assert sphere_outline(P, np.array([0.0, 0.0, -10.0]), 1.0) is None
