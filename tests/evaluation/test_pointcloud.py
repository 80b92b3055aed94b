"""DTU-style mesh sampling and radius thinning (neus_l0.evaluation.pointcloud)."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from neus_l0.evaluation.pointcloud import radius_pairs, sample_mesh, thin_mask, thin_points


def sequential_thin(points, radius, seed):
    """Plain reference: DTU port's loop (visit in a seeded random order, drop neighbours)."""
    n = len(points)
    order = np.random.default_rng(seed).permutation(n)
    tree = cKDTree(points)
    dropped = np.zeros(n, dtype=bool)
    for i in order:
        if dropped[i]:
            continue
        for j in tree.query_ball_point(points[i], radius):
            if j != i:
                dropped[j] = True
    return ~dropped


def square(n=1, size=10.0):
    """A flat square [0, size]^2 at z = 0, triangulated as an n x n grid of 2n^2 triangles."""
    g = np.linspace(0, size, n + 1)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    v = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                        np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, f


@pytest.mark.parametrize("seed", [0, 1, 7])
def test_thin_matches_sequential_reference(seed):
    pts = np.random.default_rng(seed).uniform(0, 2, (2000, 3))
    pts = np.concatenate([pts, pts[:100]])  # exact duplicates too
    got = thin_mask(pts, 0.2, seed=seed, slab=300)
    assert np.array_equal(got, sequential_thin(pts, 0.2, seed))


def test_thin_properties():
    pts = np.random.default_rng(3).uniform(0, 3, (5000, 3))
    kept = thin_points(pts, 0.25, seed=0)
    d, _ = cKDTree(kept).query(kept, k=2)
    assert d[:, 1].min() > 0.25  # no two kept points within the radius
    d_all, _ = cKDTree(kept).query(pts)
    assert d_all.max() <= 0.25 + 1e-12  # every dropped point has a kept point nearby


def test_radius_pairs_slabs_agree_with_brute_force():
    pts = np.random.default_rng(5).uniform(0, 1, (800, 3))
    pairs = radius_pairs(pts, 0.1, slab=97)
    got = {tuple(sorted(p)) for p in pairs.tolist()}
    assert len(got) == len(pairs)  # each pair once
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    i, j = np.nonzero(np.triu(d <= 0.1, k=1))
    assert got == set(zip(i.tolist(), j.tolist(), strict=True))


def test_thin_empty_and_single():
    assert thin_points(np.zeros((0, 3))).shape == (0, 3)
    assert thin_points(np.ones((1, 3))).shape == (1, 3)


def test_sample_density_on_a_square():
    v = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]], float)
    f = np.array([[0, 1, 3], [2, 3, 1]])  # right angle at each face's first vertex
    pts = sample_mesh(v, f, 0.2)
    # Legs of 10 = 50 steps of 0.2: each triangle holds the (i, j) in [0, 50]^2 with
    # (i + 0.5) / 50 + (j + 0.5) / 50 < 1, i.e. i + j < 49: sum_{i=0}^{48} (49 - i) = 1225.
    assert len(pts) == 4 + 2 * 1225
    assert np.allclose(pts[:, 2], 0)
    assert pts[:, :2].min() >= 0 and pts[:, :2].max() <= 10


def test_sample_chunking_does_not_change_points():
    v, f = square(7, 10.0)
    a = sample_mesh(v, f, 0.2)
    b = sample_mesh(v, f, 0.2, chunk=100)  # smaller than one triangle's candidate grid
    assert np.array_equal(a, b)


def test_sample_points_lie_on_the_triangles():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(30, 3)) * 3
    f = rng.integers(0, 30, size=(40, 3))
    pts = sample_mesh(v, f, 0.2)[30:]
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    # every grid point lies on the plane of some triangle, inside its bounding box
    ok = np.zeros(len(pts), dtype=bool)
    for t, nn in zip(tri, n, strict=True):
        if np.linalg.norm(nn) == 0:
            continue
        on = np.abs((pts - t[0]) @ nn) / np.linalg.norm(nn) < 1e-9
        inb = np.all((pts >= t.min(0) - 1e-9) & (pts <= t.max(0) + 1e-9), axis=1)
        ok |= on & inb
    assert ok.all()


def test_degenerate_triangles_give_only_vertices():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)
    pts = sample_mesh(v, np.array([[0, 1, 2], [0, 0, 1]]), 0.2)
    assert len(pts) == 3


def test_sample_rejects_bad_density():
    v, f = square(1)
    with pytest.raises(ValueError):
        sample_mesh(v, f, 0.0)
