"""Shared fixtures."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """A small built-in `demo` scene (8 views, 64x48, coarse ground truth): its folder Path.

    Built once per test session (a couple of seconds); treat it as read-only.
    """
    from neus_l0.data.synthetic import make_scene

    out = tmp_path_factory.mktemp("tiny_scene") / "demo"
    return make_scene("demo", out, views=8, width=64, height=48, seed=0, gt_voxel=4.0,
                      point_spacing=2.0, progress=False)
