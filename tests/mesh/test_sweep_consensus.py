"""`neus_l0.mesh.sweep_consensus`: the cells' pooling and the agreement rule against plain
loops; the local convexity against its closed form on a sphere and a plane."""

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.errors import NeusL0Error
from neus_l0.mesh import sweep_consensus as sc


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_cell_keys_name_the_cell_and_the_normals_signed_axis(seed):
    g = np.random.default_rng(seed)
    p, n = g.uniform(-50, 50, (30, 3)), g.normal(size=(30, 3))
    keys = sc.cell_keys(p, n, 7.0)
    for i in range(30):
        assert tuple(keys[i, :3]) == tuple(int(np.floor(x / 7.0)) for x in p[i])
        a = int(np.argmax(np.abs(n[i])))
        assert keys[i, 3] == 2 * a + int(n[i, a] > 0)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_consensus_pools_each_cell_as_a_plain_loop_does(seed):
    g = np.random.default_rng(seed)
    n = int(g.integers(1, 60))
    keys = sc.cell_keys(g.uniform(-20, 20, (n, 3)), g.normal(size=(n, 3)), 10.0)
    h, views = g.normal(2, 3, n), g.integers(0, 3, n)
    med, agree, count = sc.consensus(keys, h, views, 1.5)
    for i in range(n):
        same = [j for j in range(n) if (keys[j] == keys[i]).all()]
        m = float(np.median(h[same]))
        assert med[i] == pytest.approx(m)
        assert agree[i] == pytest.approx(np.mean([abs(h[j] - m) <= 1.5 for j in same]))
        assert count[i] == (len(same) if len({int(views[j]) for j in same}) >= 2 else 0)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_agreement_rule_is_the_plain_conjunction(seed):
    g = np.random.default_rng(seed)
    n = 50
    h, med = g.normal(3, 2, n), g.normal(3, 2, n)
    share, count = g.uniform(0, 1, n), g.integers(0, 12, n)
    got = sc.agreeing(h, med, share, count, 8, 0.3, 2.0, 1.5)
    for i in range(n):
        want = count[i] >= 8 and share[i] >= 0.3 and med[i] >= 2.0 and abs(h[i] - med[i]) <= 1.5
        assert got[i] == want


def test_no_rays_make_no_cells():
    med, share, count = sc.consensus(np.zeros((0, 4), np.int64), np.zeros(0), np.zeros(0), 1.0)
    assert len(med) == len(share) == len(count) == 0
    assert len(sc.local_convexity(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), 1.0)) == 0


def test_local_convexity_is_minus_r_over_4_rho_on_a_sphere_and_0_on_a_plane():
    """The mean height over the tangent plane of a sphere's cap of chord radius R, over R:
    -R / (4 rho) (uniform samples; the height is -chord^2 / (2 rho), chord^2 uniform in
    [0, R^2])."""
    rho, R = 10.0, 4.0
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=rho)
    samples, _ = trimesh.sample.sample_surface_even(sphere, 300000, seed=0)
    g = np.random.default_rng(0)
    n = g.normal(size=(20, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    got = sc.local_convexity(samples, rho * n, n, R)
    assert np.allclose(got, -R / (4 * rho), atol=0.01)
    xy = g.uniform(-20, 20, (200000, 2))
    plane = np.column_stack([xy, np.zeros(len(xy))])
    up = np.tile([0.0, 0.0, 1.0], (5, 1))
    flat = sc.local_convexity(plane, np.column_stack([g.uniform(-5, 5, (5, 2)),
                                                         np.zeros(5)]), up, R)
    assert np.allclose(flat, 0.0, atol=1e-12)
    assert np.isnan(sc.local_convexity(plane, np.array([[0.0, 0.0, 50.0]]), up[:1], R)[0])


def test_views_without_concave_pixels_sweep_nothing_and_carve_nothing():
    gray = torch.zeros((3, 8, 8))
    P = np.tile(np.eye(3, 4), (3, 1, 1))
    rays, carve, report = sc.consensus_rays([None, None, None], gray, P, np.arange(3.0), 1.0,
                                            np.zeros((10, 3)))
    assert report == {"swept": 0, "cells": 0, "agreeing": 0, "carving": 0}
    assert len(carve) == 0 and len(rays["z0"]) == 0


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_cell_codes_are_equal_exactly_when_the_keys_are(seed):
    g = np.random.default_rng(seed)
    keys = np.column_stack([g.integers(-3, 3, (200, 3)) * int(g.integers(1, 2**17)),
                            g.integers(0, 6, 200)])
    codes = sc._encode(keys)
    for i in range(0, 200, 7):
        same = (keys == keys[i]).all(1)
        assert ((codes == codes[i]) == same).all()
    with pytest.raises(NeusL0Error, match="--photo-carve: the mesh spans over 2"):
        sc._encode(np.array([[2**19, 0, 0, 1]]))
