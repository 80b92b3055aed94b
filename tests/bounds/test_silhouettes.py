"""The visual hull at pixel resolution (`neus_l0.bounds.silhouettes`): a plain loop, a ball,
and what it keeps of a thin rod that the grid hull widens."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.bounds.silhouettes import Silhouettes, in_silhouettes
from neus_l0.data.cameras import look_at
from neus_l0.data.scene import ray_matrices


def _cameras(V: int, W: int, H: int, f: float, seed: int):
    """V cameras on a ring around the origin at distance 3, looking at it (float32)."""
    rng = np.random.default_rng(seed)
    K = torch.tensor([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
    c2ws = []
    for i in range(V):
        a = 2 * math.pi * i / V + rng.uniform(0, 0.3)
        eye = np.array([3.0 * math.cos(a), 3.0 * math.sin(a), rng.uniform(-1.0, 1.5)])
        c2ws.append(torch.from_numpy(np.linalg.inv(look_at(eye, np.zeros(3)))).float())
    return K.expand(V, 3, 3).clone(), torch.stack(c2ws)


def _scene(masks: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor) -> SimpleNamespace:
    """What `Silhouettes.from_scene` reads of a `Scene`."""
    return SimpleNamespace(masks=masks, n_views=masks.shape[0], height=masks.shape[1],
                           width=masks.shape[2], ray_matrices=ray_matrices(K, c2w),
                           c2w=c2w, centres=c2w[:, :3, 3].contiguous())


def reference(points, masks, K, c2w, margin):
    """A plain float64 loop: a point is in when every view whose nearest pixel (rounding
    half up) holds it in front of the camera has a foreground pixel centre within `margin`
    (the distance floored to whole pixels, as the hull stores it); an empty mask is all in."""
    V, H, W = masks.shape
    out = []
    for p in points.double().numpy():
        inside = True
        for v in range(V):
            fg = np.argwhere(masks[v].numpy() > 0)
            if len(fg) == 0:
                continue
            T = c2w[v].double().numpy()
            cam = T[:3, :3].T @ (p - T[:3, 3])
            if cam[2] <= 0:
                continue
            uvw = K[v].double().numpy() @ cam
            x, y = math.floor(uvw[0] / uvw[2] + 0.5), math.floor(uvw[1] / uvw[2] + 0.5)
            if not (0 <= x < W and 0 <= y < H):
                continue
            dist = np.sqrt(((fg - np.array([y, x])) ** 2).sum(1)).min()
            if math.floor(dist + 1e-9) > margin:
                inside = False
                break
        out.append(inside)
    return np.array(out)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.0, 1.0, 2.0]), st.booleans())
def test_it_matches_a_plain_loop(seed, margin, one_empty):
    g = torch.Generator().manual_seed(seed)
    V, H, W = 4, 9, 11
    K, c2w = _cameras(V, W, H, 9.0, seed)
    K, c2w = K.double(), c2w.double()  # in float64 the two agree point for point
    masks = (torch.rand(V, H, W, generator=g) < 0.5).float()
    if one_empty:
        masks[1] = 0.0
    points = (torch.rand(200, 3, generator=g, dtype=torch.float64) * 2 - 1) * 1.2
    sil = Silhouettes.from_scene(_scene(masks, K, c2w), margin)
    got = in_silhouettes(points, sil).numpy()
    want = reference(points, masks, K, c2w, margin)
    assert np.array_equal(got, want)
    if margin == 0.0:
        assert want.sum() < len(want)  # some point is carved


def _ball_masks(K, c2w, H, W, radius):
    """Exact masks of a ball of `radius` at the origin (a pixel centre's ray meets it)."""
    masks = []
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    for v in range(c2w.shape[0]):
        T = c2w[v].double()
        d = torch.stack([(xs - K[v, 0, 2]) / K[v, 0, 0], (ys - K[v, 1, 2]) / K[v, 1, 1],
                         torch.ones_like(xs)], -1) @ T[:3, :3].T
        d = d / d.norm(dim=-1, keepdim=True)
        o = T[:3, 3]
        along = (-(o * d).sum(-1)).clamp_min(0)
        masks.append(((o + along[..., None] * d).norm(dim=-1) < radius).float())
    return torch.stack(masks)


def test_a_ball_is_inside_and_far_points_are_not():
    """Conservative: every point of a ball (and of its surface) is in; points well outside
    the views' cones are out."""
    V, H, W = 16, 60, 80
    K, c2w = _cameras(V, W, H, 70.0, 0)
    masks = _ball_masks(K, c2w, H, W, 0.5)
    sil = Silhouettes.from_scene(_scene(masks, K, c2w), 1.0)
    g = torch.Generator().manual_seed(1)
    dirs = torch.randn(4000, 3, generator=g)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    radii = torch.rand(4000, 1, generator=g) * 0.5
    assert in_silhouettes(dirs * radii, sil).all()
    assert in_silhouettes(dirs * 0.5, sil).all()
    assert not in_silhouettes(dirs * 0.9, sil).any()


def test_it_isolates_a_thin_rod_the_grid_hull_widens():
    """A vertical rod of radius 0.02 seen from 24 views: along a ray that sees it against the
    background, the points inside the silhouettes lie within a few pixels' width of the
    rod (here 3 px of margin ~ 0.07), however long the ray's span in the unit sphere."""
    V, H, W, f = 24, 120, 160, 140.0
    K, c2w = _cameras(V, W, H, f, 3)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    masks = []
    for v in range(V):  # the rod: points within 0.02 of the z axis, |z| < 0.6
        T = c2w[v].double()
        d = torch.stack([(xs - K[v, 0, 2]) / f, (ys - K[v, 1, 2]) / f, torch.ones_like(xs)],
                        -1) @ T[:3, :3].T
        o = T[:3, 3]
        # closest approach of the ray to the z axis (2D in x, y)
        dxy, oxy = d[..., :2], o[:2]
        t = -(oxy * dxy).sum(-1) / (dxy * dxy).sum(-1)
        p = o + t[..., None] * d
        masks.append(((p[..., :2].norm(dim=-1) < 0.02) & (p[..., 2].abs() < 0.6)).float())
    masks = torch.stack(masks)
    sil = Silhouettes.from_scene(_scene(masks, K, c2w), 1.0)
    # the ray of view 0 through the rod's middle
    T = c2w[0]
    o = T[:3, 3]
    toward = -o / o.norm()
    t = torch.linspace(2.0, 4.0, 2001)
    pts = o + t[:, None] * toward
    inside = in_silhouettes(pts, sil)
    assert inside.any()
    assert pts[inside, :2].norm(dim=-1).max() < 0.07
