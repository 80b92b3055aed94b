"""Exact point-to-mesh distance (`neus_l0.evaluation.surface`) against brute force."""

import math

import numpy as np
import pytest
import trimesh

import neus_l0.evaluation.surface as surface
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.surface import MeshDistance, point_mesh_distance


def closest_point_ericson(p, a, b, c):
    """Closest point on triangles abc to p, all (P, 3) (Ericson, Real-Time Collision
    Detection 5.1.5: Voronoi regions of vertices, edges and face), non-degenerate only."""
    dot = lambda x, y: np.einsum("ij,ij->i", x, y)  # noqa: E731
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        v_ab = d1 / (d1 - d3)
        w_ac = d2 / (d2 - d6)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        denom = 1.0 / (va + vb + vc)
        v_f, w_f = vb * denom, vc * denom
        out = a + v_f[:, None] * ab + w_f[:, None] * ac  # face interior
    conds = [
        (d1 <= 0) & (d2 <= 0),                              # vertex a
        (d3 >= 0) & (d4 <= d3),                             # vertex b
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),                  # edge ab
        (d6 >= 0) & (d5 <= d6),                             # vertex c
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),                  # edge ac
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),    # edge bc
    ]
    choices = [a, b, a + v_ab[:, None] * ab, c, a + w_ac[:, None] * ac,
               b + w_bc[:, None] * (c - b)]
    for cond, choice in zip(conds[::-1], choices[::-1]):
        out = np.where(cond[:, None], choice, out)
    # the first matching region wins, as in Ericson's sequence of early returns
    return out


def seg_dist(p, a, b):
    e = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, e) / np.maximum(np.einsum("ij,ij->i", e, e),
                                                              1e-300), 0, 1)
    return np.linalg.norm(p - a - t[:, None] * e, axis=1)


def brute_force(points, vertices, faces):
    """(N,) min over all triangles, one point at a time (degenerate triangles: edges)."""
    tri = vertices[faces]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    degenerate = np.linalg.norm(np.cross(b - a, c - a), axis=1) < 1e-12
    out = np.empty(len(points))
    for i, p in enumerate(points):
        pp = np.broadcast_to(p, a.shape)
        d = np.linalg.norm(pp - closest_point_ericson(pp, a, b, c), axis=1)
        if degenerate.any():
            g = degenerate
            d[g] = np.minimum.reduce([seg_dist(pp[g], a[g], b[g]), seg_dist(pp[g], b[g], c[g]),
                                      seg_dist(pp[g], c[g], a[g])])
        out[i] = d.min()
    return out


def random_mesh(rng, n_vertices=40, n_faces=70):
    v = rng.normal(size=(n_vertices, 3)) * 3
    f = rng.integers(0, n_vertices, size=(n_faces, 3))
    return v, f


def test_matches_brute_force_on_a_random_mesh():
    rng = np.random.default_rng(0)
    v, f = random_mesh(rng)
    f[:3, 1] = f[:3, 0]  # degenerate: segments
    f[3] = f[3, 0]  # a single point
    v[f[4, 2]] = (v[f[4, 0]] + v[f[4, 1]]) / 2  # collinear corners
    pts = np.concatenate([rng.normal(size=(400, 3)) * 5,
                          v[rng.integers(0, len(v), 50)],  # on vertices
                          (v[f[5:55, 0]] + v[f[5:55, 1]] + v[f[5:55, 2]]) / 3])  # on faces
    d = point_mesh_distance(pts, v, f)
    assert np.abs(d - brute_force(pts, v, f)).max() < 1e-9


def test_mixed_triangle_sizes_and_small_chunks(monkeypatch):
    rng = np.random.default_rng(1)
    small = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    v = np.concatenate([small.vertices, [[-50, -50, 3], [50, -50, 3], [0, 60, 3]],
                        small.vertices * 0.01 + [5, 5, 5]])
    n = len(small.vertices)
    f = np.concatenate([small.faces, [[n, n + 1, n + 2]], small.faces + n + 3])
    pts = rng.normal(size=(300, 3)) * 6
    expected = brute_force(pts, v, f)
    assert np.abs(MeshDistance(v, f).query(pts) - expected).max() < 1e-9  # classes merged
    monkeypatch.setattr(surface, "MIN_CLASS", 1)
    md = MeshDistance(v, f)
    assert len(md.classes) >= 2  # (the single huge triangle joins the unit-size class)
    monkeypatch.setattr(surface, "PAIR_BUDGET", 300)
    monkeypatch.setattr(surface, "K_START", 2)
    assert np.abs(md.query(pts, chunk=37) - expected).max() < 1e-9


def test_upper_bound_gives_inf_beyond_it():
    rng = np.random.default_rng(2)
    v, f = random_mesh(rng)
    pts = rng.normal(size=(300, 3)) * 5
    exact = brute_force(pts, v, f)
    d = point_mesh_distance(pts, v, f, upper_bound=1.5)
    assert np.array_equal(np.isinf(d), exact >= 1.5)
    near = exact < 1.5
    assert near.sum() > 50 and (~near).sum() > 50
    assert np.abs(d[near] - exact[near]).max() < 1e-9


def test_sphere_distance_is_radial():
    m = trimesh.creation.icosphere(subdivisions=5, radius=10.0)
    rng = np.random.default_rng(3)
    u = rng.normal(size=(5000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = rng.uniform(5, 15, size=len(u))
    d = point_mesh_distance(u * r[:, None], m.vertices, m.faces)
    # faces lie inside the sphere by at most the sagitta (< 0.01 here)
    assert np.abs(d - np.abs(r - 10.0)).max() < 0.01


def test_empty_mesh_and_bad_input():
    assert np.isinf(point_mesh_distance(np.zeros((4, 3)), np.zeros((0, 3)),
                                        np.zeros((0, 3), int))).all()
    assert point_mesh_distance(np.zeros((0, 3)), np.eye(3), [[0, 1, 2]]).shape == (0,)
    with pytest.raises(NeusL0Error, match="face indices outside"):
        MeshDistance(np.eye(3), [[0, 1, 3]])
    with pytest.raises(NeusL0Error, match="vertices must be"):
        MeshDistance(np.zeros((3, 2)), [[0, 1, 2]])
    with pytest.raises(NeusL0Error, match="non-finite"):
        MeshDistance(np.array([[0, 0, math.nan], [1, 0, 0], [0, 1, 0]]), [[0, 1, 2]])
    with pytest.raises(NeusL0Error, match="points must be"):
        point_mesh_distance(np.zeros(3), np.eye(3), [[0, 1, 2]])
