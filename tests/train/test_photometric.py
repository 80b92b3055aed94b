"""`train.photo`: multi-view photometric consistency of the rendered surface (Geo-NeuS's NCC
term), against plain references and on an exactly rendered textured plane."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.config.load import load_config
from neus_l0.config.schema import PhotoConfig
from neus_l0.data.patches import ncc
from neus_l0.data.scene import Scene
from neus_l0.errors import ConfigError, NeusL0Error
from neus_l0.fields.encodings import HashGridEncoding
from neus_l0.fields.model import make_model
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.loop import train
from neus_l0.train.losses import LOSS_NAMES
from neus_l0.train.photometric import (
    PhotoContext,
    PhotoRays,
    best_cost,
    nearest_views,
    normal_fallback,
    normal_views,
    occluded,
    patch_offsets,
    photometric_term,
    plane_points,
    project,
    sample_gray,
    widened,
)
from neus_l0.train.step import (
    StepSetup,
    draw_step_inputs,
    make_optimizer,
    photo_widened,
    render_and_loss,
    schedule_length,
    train_step,
)


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) OpenCV camera-to-world (x right, y down, z forward) looking at `target`."""
    z = target - centre
    z = z / np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, y, z], axis=1)
    c2w[:3, 3] = centre
    return c2w


def random_camera(g: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """K (3, 3) and c2w (4, 4) of a camera 2-4 units out, looking near the origin."""
    d = g.normal(size=3)
    centre = d / np.linalg.norm(d) * g.uniform(2, 4)
    c2w = look_at(centre, g.uniform(-0.2, 0.2, size=3))
    f = g.uniform(50, 150)
    K = np.array([[f, 0, g.uniform(20, 40)], [0, f, g.uniform(15, 30)], [0, 0, 1.0]])
    return K, c2w


def texture(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """A smooth, textured grey pattern on the plane z = 0."""
    return (0.5 + 0.2 * torch.sin(9 * x + 2 * y) + 0.15 * torch.cos(7 * y - 3 * x)
            + 0.1 * torch.sin(13 * x * y))


def plane_scene(n_views: int = 5, size: tuple[int, int] = (48, 64)) -> Scene:
    """Views of the textured plane z = 0 from above (grey images, exact: every pixel's ray
    meets the plane and takes the texture there); the 'object' is the unit sphere's middle."""
    H, W = size
    g = np.random.default_rng(3)
    Ks, c2ws = [], []
    for i in range(n_views):
        ang = 2 * math.pi * i / n_views
        centre = np.array([1.2 * math.cos(ang), 1.2 * math.sin(ang), 2.5])
        c2ws.append(look_at(centre, g.uniform(-0.05, 0.05, size=3) * [1, 1, 0]))
        Ks.append(np.array([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]]))
    K = torch.tensor(np.stack(Ks), dtype=torch.float32)
    c2w = torch.tensor(np.stack(c2ws), dtype=torch.float32)
    A = c2w[:, :3, :3].double() @ torch.linalg.inv(K.double())
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    pix = torch.stack([xs, ys, torch.ones_like(xs)], -1)  # (H, W, 3)
    d = torch.einsum("vij,hwj->vhwi", A, pix)
    o = c2w[:, :3, 3].double()[:, None, None, :]
    t = -o[..., 2] / d[..., 2]
    p = o + t[..., None] * d
    gray = texture(p[..., 0], p[..., 1]).float()
    images = gray[..., None].expand(-1, -1, -1, 3).contiguous()
    return Scene(root=None, images=images, masks=torch.ones(n_views, H, W),
                 has_masks=False, intrinsics=K, c2w=c2w, scale_mat=np.eye(4),
                 image_names=[f"{i}.png" for i in range(n_views)])


def test_patch_offsets():
    off = patch_offsets(5, 2)
    assert off.shape == (25, 2)
    assert off.mean(0).tolist() == [0.0, 0.0]
    assert off.min().item() == -4.0 and off.max().item() == 4.0
    assert {tuple(r) for r in off.tolist()} == {(x, y) for x in (-4, -2, 0, 2, 4)
                                                 for y in (-4, -2, 0, 2, 4)}
    with pytest.raises(ValueError, match="odd"):
        patch_offsets(4, 1)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(2, 12), st.integers(1, 15))
def test_nearest_views_match_a_plain_sort(seed, v, k):
    g = torch.Generator().manual_seed(seed)
    c = torch.randn(v, 3, generator=g, dtype=torch.float64) * 3
    got = nearest_views(c, k)
    assert got.shape == (v, min(k, v - 1))
    u = c / c.norm(dim=-1, keepdim=True)
    for i in range(v):
        assert i not in got[i].tolist()
        angles = [math.acos(max(-1.0, min(1.0, float(u[i] @ u[j])))) for j in range(v)]
        want = sorted((j for j in range(v) if j != i), key=lambda j: angles[j])
        # the same angles in the same order (ties may swap indices)
        assert [angles[j] for j in got[i].tolist()] == pytest.approx(
            [angles[j] for j in want[:got.shape[1]]], abs=1e-9)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(3, 12), st.integers(0, 4), st.integers(1, 4))
def test_normal_views_match_a_plain_sort(seed, v, m, k):
    """Each point's k views of largest cos(normal, direction to the camera), never its own
    nor the taken ones: against a float64 loop."""
    m = min(m, v - 2)
    k = min(k, v - 1 - m)
    g = torch.Generator().manual_seed(seed)
    centres = torch.randn(v, 3, generator=g, dtype=torch.float64) * 3
    b = 6
    pts = torch.randn(b, 3, generator=g, dtype=torch.float64) * 0.3
    n = torch.randn(b, 3, generator=g, dtype=torch.float64)
    n = n / n.norm(dim=-1, keepdim=True)
    own = torch.randint(0, v, (b,), generator=g)
    taken = torch.stack([torch.tensor([j for j in torch.randperm(v, generator=g).tolist()
                                       if j != int(own[i])][:m], dtype=torch.long)
                         for i in range(b)]) if m else torch.zeros(b, 0, dtype=torch.long)
    got = normal_views(centres, pts, n, own, taken, k)
    assert got.shape == (b, k)
    for i in range(b):
        cos = {}
        for j in range(v):
            d = (centres[j] - pts[i]).tolist()
            cos[j] = sum(a * c for a, c in zip(d, n[i].tolist(), strict=True)) / math.sqrt(
                sum(a * a for a in d))
        allowed = [j for j in range(v) if j != int(own[i]) and j not in taken[i].tolist()]
        want = sorted(allowed, key=lambda j: -cos[j])[:k]
        assert set(got[i].tolist()) <= set(allowed)
        assert [cos[j] for j in got[i].tolist()] == pytest.approx([cos[j] for j in want],
                                                                  abs=1e-12)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_plane_points_lie_on_the_plane_and_on_their_pixels_rays(seed):
    g = np.random.default_rng(seed)
    K, c2w = random_camera(g)
    A = torch.tensor(c2w[:3, :3] @ np.linalg.inv(K))[None]
    o = torch.tensor(c2w[:3, 3])[None]
    point = torch.tensor(g.uniform(-0.3, 0.3, size=3))[None]
    n = torch.tensor(-(c2w[:3, 2]) + g.normal(size=3) * 0.2)  # roughly facing the camera
    n = (n / n.norm())[None]
    pix = torch.tensor(g.uniform(0, 60, size=(1, 9, 2)))
    pts = plane_points(o, A, pix, point, n)
    torch.testing.assert_close(((pts - point[:, None]) * n[:, None]).sum(-1),
                               torch.zeros(1, 9, dtype=torch.float64), atol=1e-9, rtol=0)
    uv, z = project(pts, torch.linalg.inv(A)[:, None], o[:, None])
    torch.testing.assert_close(uv[:, 0], pix, atol=1e-7, rtol=0)
    assert (z > 0).all()


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_project_is_the_pinhole_of_k_and_the_pose(seed):
    g = np.random.default_rng(seed)
    K, c2w = random_camera(g)
    X = g.uniform(-0.5, 0.5, size=(7, 3))
    cam = (X - c2w[:3, 3]) @ c2w[:3, :3]  # world -> camera (R^T (X - c))
    want = (cam @ K.T)[:, :2] / cam[:, 2:3]
    A = torch.tensor(c2w[:3, :3] @ np.linalg.inv(K))
    uv, z = project(torch.tensor(X)[None], torch.linalg.inv(A)[None, None],
                    torch.tensor(c2w[:3, 3])[None, None])
    torch.testing.assert_close(uv[0, 0], torch.tensor(want), atol=1e-8, rtol=1e-8)
    torch.testing.assert_close(z[0, 0], torch.tensor(cam[:, 2]), atol=1e-10, rtol=1e-10)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_sample_gray_is_exact_on_pixels_and_on_affine_images(seed):
    g = torch.Generator().manual_seed(seed)
    V, H, W = 3, 7, 9
    imgs = torch.rand(V, H, W, generator=g, dtype=torch.float64)
    view = torch.randint(0, V, (20,), generator=g)
    xi = torch.randint(0, W, (20,), generator=g)
    yi = torch.randint(0, H, (20,), generator=g)
    vals, inside = sample_gray(imgs.reshape(-1), H, W, view,
                               torch.stack([xi, yi], -1).double())
    torch.testing.assert_close(vals, imgs[view, yi, xi], atol=0, rtol=0)
    assert inside.all()
    # an affine image a x + b y + c is reproduced anywhere inside, with gradient (a, b)
    a, b, c = 0.3, -0.7, 0.2
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    aff = (a * xs + b * ys + c).expand(V, H, W).reshape(-1)
    uv = (torch.rand(20, 2, generator=g, dtype=torch.float64)
          * torch.tensor([W - 1.0, H - 1.0])).requires_grad_()
    vals, inside = sample_gray(aff, H, W, view, uv)
    torch.testing.assert_close(vals, a * uv[:, 0] + b * uv[:, 1] + c)
    vals.sum().backward()
    torch.testing.assert_close(uv.grad, torch.tensor([[a, b]] * 20, dtype=torch.float64))
    _, inside = sample_gray(aff, H, W, view[:2],
                            torch.tensor([[-0.5, 1.0], [2.0, H - 0.5]], dtype=torch.float64))
    assert not inside.any()
    nan = torch.tensor([[float("nan"), 1.0], [2.0, float("inf")]], dtype=torch.float64)
    vals, inside = sample_gray(aff, H, W, view[:2], nan)  # a diverged run's coordinates
    assert not inside.any() and torch.isfinite(vals).all()


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.1, 5.0), st.floats(-2, 2))
def test_ncc_against_a_float64_reference(seed, scale, shift):
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(4, 25, generator=g, dtype=torch.float64)
    src = torch.stack([scale * ref + shift, -scale * ref + shift,
                       torch.rand(4, 25, generator=g, dtype=torch.float64)], dim=1)
    got = ncc(ref, src, eps=0.0)
    assert got.shape == (4, 3)
    torch.testing.assert_close(got[:, 0], torch.ones(4, dtype=torch.float64))
    torch.testing.assert_close(got[:, 1], -torch.ones(4, dtype=torch.float64))
    for i in range(4):
        want = np.corrcoef(ref[i].numpy(), src[i, 2].numpy())[0, 1]
        assert got[i, 2].item() == pytest.approx(want, abs=1e-12)
    flat = ncc(torch.full((1, 25), 0.4, dtype=torch.float64), src[:1], eps=1e-4)
    assert torch.isfinite(flat).all() and flat.abs().max() < 1e-9


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 6))
def test_best_cost_is_the_mean_of_the_k_lowest_valid(seed, m):
    g = torch.Generator().manual_seed(seed)
    k = int(torch.randint(1, m + 1, (1,), generator=g))
    cost = torch.rand(10, m, generator=g, dtype=torch.float64)
    valid = torch.rand(10, m, generator=g) < 0.6
    got, any_valid = best_cost(cost, valid, k)
    for i in range(10):
        ok = sorted(cost[i, j].item() for j in range(m) if valid[i, j])
        assert bool(any_valid[i]) == bool(ok)
        want = sum(ok[:k]) / len(ok[:k]) if ok else 0.0
        assert got[i].item() == pytest.approx(want, abs=1e-12)


def plane_sdf(h: torch.Tensor):
    """The SDF of the plane z = h (a parameter), as `photometric_term` calls it."""
    return lambda x: x[:, 2] - h


def pixel_rays(scene: Scene, views: torch.Tensor, xy: torch.Tensor, depth: torch.Tensor,
               normal: torch.Tensor, use: torch.Tensor | None = None) -> PhotoRays:
    """`PhotoRays` through pixels `xy` (B, 2) of `views` (B,), as `rays_at` makes them."""
    xy1 = torch.nn.functional.pad(xy.float(), (0, 1), value=1.0)
    d = (scene.ray_matrices[views] @ xy1[..., None])[..., 0]
    d = d / d.norm(dim=-1, keepdim=True)
    use = torch.ones(len(xy), dtype=torch.bool) if use is None else use
    return PhotoRays(scene.centres[views], d, views, xy, depth, normal, use)


def plane_depth(scene: Scene, views: torch.Tensor, xy: torch.Tensor, z: float) -> torch.Tensor:
    """(B, 1) distance along each pixel's ray to the plane at height z."""
    r = pixel_rays(scene, views, xy, torch.zeros(len(xy), 1), torch.zeros(len(xy), 3))
    return ((z - r.origins[:, 2]) / r.dirs[:, 2])[:, None]


def term_on_plane(scene: Scene, ctx: PhotoContext, h: torch.Tensor,
                  cfg: PhotoConfig | None = None, view: int = 0,
                  wide: torch.Tensor | None = None):
    """The term on a grid of view `view`'s pixels, its rendered surface at z = h + 0.003
    (the Newton step then lands on z = h) and normal +z (`wide`: `photometric_term`'s)."""
    H, W = scene.height, scene.width
    ys, xs = torch.meshgrid(torch.arange(8, H - 8, 6), torch.arange(8, W - 8, 6),
                            indexing="ij")
    xy = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)
    views = torch.full((len(xy),), view)
    depth = plane_depth(scene, views, xy, h.detach().item() + 0.003)
    up = torch.tensor([[0.0, 0.0, 1.0]]).expand(len(xy), 3)
    return photometric_term(ctx, plane_sdf(h), pixel_rays(scene, views, xy, depth, up),
                            cfg or PhotoConfig(), wide)


def test_the_term_finds_the_textured_planes_depth():
    """Exact views of a textured plane: the surface on the plane costs ~0; lifted or sunk
    it costs more, and the term's gradient pushes it back towards the plane."""
    scene = plane_scene()
    ctx = PhotoContext.from_scene(scene, n_sources=3, patch=7, stride=1, best=2)
    at_zero, counted = term_on_plane(scene, ctx, torch.tensor(0.0))
    assert counted.item() > 20
    assert at_zero.item() < 0.01
    for sign in (-1.0, 1.0):
        costs = [at_zero.item()]
        for step in (0.02, 0.05, 0.1, 0.2):  # 0.4 to 4 pixels of parallax
            h = torch.tensor(sign * step, requires_grad=True)
            cost, _ = term_on_plane(scene, ctx, h)
            cost.backward()
            assert h.grad.item() * sign > 0  # descent moves h towards 0
            costs.append(cost.item())
        assert costs == sorted(costs) and costs[2] > 3 * costs[0]


def test_weighted_rays_give_the_weighted_mean_of_their_own_costs():
    """With importance weights (an error map's rays, `train.error_map.weigh_all`) the term
    is ``sum(w c) / sum(w)`` over the counted rays, each ray's cost ``c`` as it has alone;
    weights of 1 give the plain mean; a ray that does not count adds nothing."""
    scene = plane_scene()
    ctx = PhotoContext.from_scene(scene, n_sources=3, patch=5, stride=1, best=2)
    h = torch.tensor(0.1)  # off the true plane: each ray's cost is its texture's own
    xy = torch.tensor([[20, 14], [30, 20], [41, 25], [25, 30], [0, 0]])
    views = torch.zeros(5, dtype=torch.long)
    depth = plane_depth(scene, views, xy, 0.1)
    up = torch.tensor([[0.0, 0.0, 1.0]]).expand(5, 3)
    alone = [photometric_term(ctx, plane_sdf(h), pixel_rays(scene, views[i:i + 1],
                                                            xy[i:i + 1], depth[i:i + 1],
                                                            up[:1]), PhotoConfig())
             for i in range(5)]
    c = torch.tensor([float(a[0]) for a in alone])
    n = torch.tensor([float(a[1]) for a in alone])
    assert n.tolist() == [1, 1, 1, 1, 0] and len(set(c[:4].tolist())) == 4
    w = torch.tensor([0.3, 2.0, 0.7, 1.1, 5.0])
    rays = pixel_rays(scene, views, xy, depth, up)
    plain, counted = photometric_term(ctx, plane_sdf(h), rays, PhotoConfig())
    weighted, counted_w = photometric_term(ctx, plane_sdf(h), dataclasses.replace(rays,
                                                                               weight=w),
                                           PhotoConfig())
    assert counted.item() == counted_w.item() == 4
    assert plain.item() == pytest.approx(float(c[:4].mean()), rel=1e-5)
    assert weighted.item() == pytest.approx(float((w * c * n).sum() / (w * n).sum()),
                                            rel=1e-5)
    ones = dataclasses.replace(rays, weight=torch.ones(5))
    assert photometric_term(ctx, plane_sdf(h), ones, PhotoConfig())[0].item() == \
        pytest.approx(plain.item(), rel=1e-6)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 5), st.integers(1, 4))
def test_normal_fallback_against_a_plain_loop(seed, m, k):
    g = torch.Generator().manual_seed(seed)
    valid = torch.rand(12, m + k, generator=g) < 0.6
    blocked = torch.rand(12, m + k, generator=g) < 0.5
    got = normal_fallback(valid, blocked, m)
    for b in range(12):
        v, bl = valid[b].tolist(), blocked[b].tolist()
        if any(v[j] and not bl[j] for j in range(m)):  # a nearest source sees the point
            want = v[:m] + [False] * k
        else:
            want = [False] * m + [v[j] and not bl[j] for j in range(m, m + k)]
        assert got[b].tolist() == want


def noisy_nearest_scene() -> Scene:
    """`plane_scene` with view 0's nearest source showing noise (it sees a 'wall')."""
    scene = plane_scene()
    near = int(nearest_views(scene.centres, 1)[0, 0])
    noise = torch.rand(scene.height, scene.width, generator=torch.Generator().manual_seed(0))
    images = scene.images.clone()
    images[near] = noise[..., None].expand(-1, -1, 3)
    return Scene(root=None, images=images, masks=scene.masks, has_masks=False,
                 intrinsics=scene.intrinsics, c2w=scene.c2w, scale_mat=np.eye(4),
                 image_names=scene.image_names)


def test_normal_sources_stand_in_when_the_sdf_blocks_the_nearest(monkeypatch):
    """A cavity floor's nearest sources see a wall: here view 0's one nearest source shows
    noise. While the SDF leaves it a clear view, the normal's sources change next to nothing; when
    the SDF blocks it, two sources chosen by the normal stand in, find the plane, and the
    cost at the plane drops below a tenth (best 1; a few rays' patches leave both of the
    others' images); the term still pulls a lifted surface down."""
    import neus_l0.train.photometric as photometric

    scene = noisy_nearest_scene()
    alone = PhotoContext.from_scene(scene, n_sources=1, patch=5, stride=1, best=1)
    more = PhotoContext.from_scene(scene, n_sources=1, patch=5, stride=1, best=1,
                                   normal_sources=2)
    assert more.normal_sources == 2 and alone.normal_sources == 0
    cfg = PhotoConfig(occlusion_samples=4)
    cost_alone, counted = term_on_plane(scene, alone, torch.tensor(0.0), cfg)
    # the plane blocks nothing: only the few rays whose patch leaves the nearest's image
    # (no nearest source can score them) take the normal's sources
    same, _ = term_on_plane(scene, more, torch.tensor(0.0), cfg)
    assert same.item() == pytest.approx(cost_alone.item(), rel=0.05) and cost_alone.item() > 0.3

    def nearest_blocked(sdf, points, centres, samples, start):
        out = torch.zeros(centres.shape[:2], dtype=torch.bool)
        out[:, 0] = True
        return out

    monkeypatch.setattr(photometric, "occluded", nearest_blocked)
    cost_more, counted_more = term_on_plane(scene, more, torch.tensor(0.0), cfg)
    assert counted_more.item() > 20 and cost_more.item() < 0.1 * cost_alone.item()
    assert term_on_plane(scene, alone, torch.tensor(0.0), cfg)[1].item() == 0  # none left
    for step in (0.05, 0.1):  # 1 and 2 pixels of parallax
        h = torch.tensor(step, requires_grad=True)
        cost, _ = term_on_plane(scene, more, h, cfg)
        cost.backward()
        assert cost.item() > cost_more.item() and h.grad.item() > 0


def test_rays_that_may_not_count_do_not():
    scene = plane_scene()
    ctx = PhotoContext.from_scene(scene, n_sources=3, patch=5, stride=1, best=2)
    h = torch.tensor(0.0)
    xy = torch.tensor([[30, 20], [31, 22], [0, 0]])
    views = torch.zeros(3, dtype=torch.long)
    depth = plane_depth(scene, views, xy, 0.0)
    up = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)
    cfg = PhotoConfig()
    # the third ray's patch leaves the image; the second is masked out
    rays = pixel_rays(scene, views, xy, depth, up, torch.tensor([True, False, True]))
    assert photometric_term(ctx, plane_sdf(h), rays, cfg)[1].item() == 1
    # back-facing normals and a rendered point far from the zero level count nothing
    rays = pixel_rays(scene, views, xy, depth, -up)
    assert photometric_term(ctx, plane_sdf(h), rays, cfg)[1].item() == 0
    cost, counted = photometric_term(ctx, plane_sdf(h), pixel_rays(scene, views, xy,
                                                                   depth + 0.5, up), cfg)
    assert counted.item() == 0 and cost.item() == 0.0


@pytest.mark.parametrize("bend, counted", [(0.0, 1), (0.01, 1), (50.0, 0)])
def test_a_patch_off_its_plane_does_not_count_with_planar_sdf(bend, counted):
    """The SDF z + bend * (distance from the ray's point in x, y)^2 touches the plane z = 0
    at the ray's point: a slight bend keeps the ray, a sharp one (a rim) drops it."""
    scene = plane_scene()
    ctx = PhotoContext.from_scene(scene, n_sources=3, patch=5, stride=1, best=2)
    xy = torch.tensor([[30, 20]])
    views = torch.zeros(1, dtype=torch.long)
    depth = plane_depth(scene, views, xy, 0.0)
    rays = pixel_rays(scene, views, xy, depth, torch.tensor([[0.0, 0.0, 1.0]]))
    c = (rays.origins + rays.dirs * depth)[0]

    def sdf(x):
        return x[:, 2] + bend * ((x[:, 0] - c[0]) ** 2 + (x[:, 1] - c[1]) ** 2)

    got = photometric_term(ctx, sdf, rays, PhotoConfig(planar_sdf=0.005))[1].item()
    assert got == counted
    assert photometric_term(ctx, sdf, rays, PhotoConfig())[1].item() == 1  # no test: kept


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_the_term_and_its_gradient_stay_finite_whatever_the_render(seed):
    """Zero, huge and back-facing normals, depths behind the camera or far away, rays in and
    out of use: the cost and the SDF's gradient stay finite."""
    g = torch.Generator().manual_seed(seed)
    scene = plane_scene(n_views=3, size=(24, 32))
    ctx = PhotoContext.from_scene(scene, 2, 3, 1, 1)
    B = 16
    views = torch.randint(0, 3, (B,), generator=g)
    xy = torch.stack([torch.randint(0, 32, (B,), generator=g),
                      torch.randint(0, 24, (B,), generator=g)], -1)
    scale = torch.tensor([0.0, 1e-30, 1.0, 1e30])[torch.randint(0, 4, (B,), generator=g)]
    normal = torch.randn(B, 3, generator=g) * scale[:, None]
    depth = torch.tensor([-5.0, 0.0, 2.9, 1e6])[torch.randint(0, 4, (B,), generator=g)][:, None]
    h = torch.tensor(0.0, requires_grad=True)
    use = torch.rand(B, generator=g) < 0.8
    cfg = PhotoConfig(max_sdf=1e9, occlusion_samples=4, planar_sdf=1e9)
    cost, counted = photometric_term(ctx, lambda x: (x[:, 2] - h) * 1e3,
                                     pixel_rays(scene, views, xy, depth, normal, use), cfg)
    cost.backward()
    assert torch.isfinite(cost) and torch.isfinite(h.grad) and 0 <= cost.item() <= 1
    assert 0 <= counted.item() <= int(use.sum())


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_occluded_against_a_ball_between_the_point_and_the_camera(seed):
    """A ball of radius 0.3 at the origin: a point behind it is hidden from a camera on the
    far side (the segment passes within 0.3 of the centre) and seen from one beside it
    (the segment passes well clear); the point's own surface (start) is skipped."""
    g = np.random.default_rng(seed)
    d = g.normal(size=3)
    d = d / np.linalg.norm(d)
    point = torch.tensor(-0.6 * d)
    side = np.cross(d, g.normal(size=3))
    side = side / np.linalg.norm(side)
    cams = torch.tensor(np.stack([3.0 * d + 0.05 * side,  # behind the ball: hidden
                                  -0.6 * d + 3.0 * side]))  # beside it: the segment clears
    ball = lambda x: x.norm(dim=-1) - 0.3  # noqa: E731
    got = occluded(ball, point[None], cams[None], samples=16, start=0.03)
    assert got.tolist() == [[True, False]]
    # a point on the ball's own surface, seen from outside along its normal: not occluded
    on = torch.tensor(0.3 * d)
    assert occluded(ball, on[None], torch.tensor(3.0 * d)[None, None], 8, 0.03).tolist() == \
        [[False]]


def test_one_view_is_a_clear_error():
    scene = plane_scene(n_views=1)
    with pytest.raises(NeusL0Error, match="at least 2 training views"):
        PhotoContext.from_scene(scene, 4, 3, 1, 2)


def test_the_step_with_the_term(small, sphere_scene, tmp_path):
    """On: the loss holds the weighted term and the metric reports it; the hash grid's level
    counter counts one pass a step; off: the metric is 0 and the inputs carry no views."""
    scene = sphere_scene(tmp_path / "s")
    flags = ["train.compile=false", "model.sdf.gradient=analytic"]
    on = load_config("demo", small + flags + ["train.photo.weight=0.5",
                                              "train.photo.patch=5"])
    ctx = PhotoContext.from_scene(scene, on.train.photo.sources, 5, 1, on.train.photo.best)
    torch.manual_seed(0)
    model = make_model(on)
    # a few steps first, so that rays render opaque and the term counts some
    opt = make_optimizer(model, on)
    grids = [m for m in model.modules() if isinstance(m, HashGridEncoding)]
    before = [int(m.steps) for m in grids]
    g = torch.Generator().manual_seed(1)
    for it in range(30):
        train_step(model, opt, scene, on, it, g, batch_size=64, setup=StepSetup(photo=ctx))
    assert [int(m.steps) for m in grids] == [b + 30 for b in before]
    inputs = draw_step_inputs(scene, on, 3, 64, torch.Generator().manual_seed(0), None, ctx)
    assert inputs.view is not None and inputs.xy is not None
    loss, metrics, _ = render_and_loss(model, inputs, on, build_sampler(on.sampler), ())
    values = dict(zip(LOSS_NAMES, metrics.tolist(), strict=False))
    assert values["photo_loss"] > 0
    off = load_config("demo", small + flags)
    inputs_off = draw_step_inputs(scene, off, 3, 64, torch.Generator().manual_seed(0), None)
    assert inputs_off.view is None and inputs_off.photo is None
    loss_off, m_off, _ = render_and_loss(model, inputs_off, off, build_sampler(off.sampler), ())
    assert dict(zip(LOSS_NAMES, m_off.tolist(), strict=False))["photo_loss"] == 0.0
    assert loss.item() - loss_off.item() == pytest.approx(0.5 * values["photo_loss"],
                                                          rel=1e-4, abs=1e-6)


@pytest.mark.parametrize("override, match", [
    ("train.photo.patch=4", "odd"),
    ("train.photo.best=9", "at most"),
    ("train.photo.normal_sources=-1", "normal_sources"),
    ("train.photo.normal_sources=4", "occlusion_samples"),
    ("train.photo.weight=-1", "weight"),
    ("train.photo.wide_sources=3", "more than train.photo.sources"),
    ("train.photo.wide_sources=-2", "wide_sources"),
    ("train.photo.wide_after=1.5", "wide_after"),
])
def test_bad_settings_are_named(override, match):
    with pytest.raises(ConfigError, match=match):
        load_config("demo", [override])


def test_a_run_logs_the_term_and_one_view_turns_it_off(small, sphere_scene, tmp_path, capsys):
    def read_metrics(run):
        return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]

    cfg = load_config("demo", small + ["train.iters=20", "train.log_every=10"])
    assert cfg.train.photo.weight > 0  # on in demo
    train(sphere_scene(tmp_path / "s"), cfg, tmp_path / "run", progress=False)
    rows = read_metrics(tmp_path / "run")
    assert all(math.isfinite(r["photo_loss"]) for r in rows) and rows[-1]["photo_loss"] > 0
    train(sphere_scene(tmp_path / "s1", n_views=1), cfg, tmp_path / "one", progress=False)
    assert "train.photo needs at least 2 training views" in capsys.readouterr().err
    assert all(r["photo_loss"] == 0.0 for r in read_metrics(tmp_path / "one"))


def test_widened_columns():
    """The first `near` of the `m` nearest count always, the rest of them once widened;
    the normal's stand-ins after them always."""
    assert widened(6, 2, 4, torch.tensor(0.0)).tolist() == [True, True, False, False, True,
                                                            True]
    assert widened(6, 2, 4, torch.tensor(1.0)).tolist() == [True] * 6
    assert widened(3, 1, 3, torch.tensor(0.0)).tolist() == [True, False, False]


@pytest.mark.parametrize("h", [0.0, 0.06, -0.1])
def test_the_widening_term_is_the_nearest_ones_term_then_the_wider_ones(h):
    """A context of 4 nearest of which 2 count until widened: before, the term and its
    gradient are those of a context of the 2 nearest; after, those of the 4 nearest (which
    differ from the 2's off the plane)."""
    scene = plane_scene(n_views=7)
    two = PhotoContext.from_scene(scene, n_sources=2, patch=5, stride=1, best=2)
    four = PhotoContext.from_scene(scene, n_sources=4, patch=5, stride=1, best=2)
    both = PhotoContext.from_scene(scene, n_sources=2, patch=5, stride=1, best=2,
                                   wide_sources=4)
    assert both.near == 2 and both.sources.shape[1] == 4 and both.best == 2
    assert torch.equal(both.sources, four.sources) and torch.equal(both.sources[:, :2],
                                                                   two.sources)
    assert (two.near, four.near) == (0, 0)
    results = {}
    for name, ctx, wide in (("two", two, None), ("four", four, None),
                            ("before", both, torch.tensor(0.0)),
                            ("after", both, torch.tensor(1.0))):
        hh = torch.tensor(h, requires_grad=True)
        cost, counted = term_on_plane(scene, ctx, hh, wide=wide)
        cost.backward()
        results[name] = (cost.item(), counted.item(), hh.grad.item())
    assert results["before"] == pytest.approx(results["two"], rel=1e-6, abs=1e-9)
    assert results["after"] == pytest.approx(results["four"], rel=1e-6, abs=1e-9)
    if h != 0.0:
        assert results["two"][0] != pytest.approx(results["four"][0], rel=1e-3)
    # no `wide` at all: every source of the context counts
    assert term_on_plane(scene, both, torch.tensor(h))[0].item() == \
        pytest.approx(results["four"][0], rel=1e-6, abs=1e-9)


def test_the_step_widens_at_its_share_of_the_schedule(small, sphere_scene, tmp_path):
    """`photo_widened` is 0 before ``wide_after * L`` and 1 from there; the step's inputs
    carry it only when the context has wider sources, and the step has no graph break."""
    scene = sphere_scene(tmp_path / "s")
    cfg = load_config("demo", small + ["model.sdf.gradient=analytic",
                                       "train.photo.wide_sources=5",
                                       "train.photo.wide_after=0.5"])
    half = 0.5 * schedule_length(cfg)
    assert [photo_widened(cfg, at, "cpu").item() for at in (0, half - 1, half, 2 * half)] \
        == [0.0, 0.0, 1.0, 1.0]
    ph = cfg.train.photo
    ctx = PhotoContext.from_scene(scene, ph.sources, ph.patch, ph.stride, ph.best,
                                  wide_sources=ph.wide_sources)
    assert ctx.near == ph.sources and ctx.sources.shape[1] == 5
    g = torch.Generator().manual_seed(0)
    early = draw_step_inputs(scene, cfg, 3, 64, g, None, ctx)
    late = draw_step_inputs(scene, cfg, int(half) + 1, 64, g, None, ctx)
    assert early.photo_wide.item() == 0.0 and late.photo_wide.item() == 1.0
    narrow = PhotoContext.from_scene(scene, ph.sources, ph.patch, ph.stride, ph.best)
    assert draw_step_inputs(scene, cfg, 3, 64, g, None, narrow).photo_wide is None
    torch._dynamo.reset()
    ex = torch._dynamo.explain(render_and_loss)(make_model(cfg), late, cfg,
                                                build_sampler(cfg.sampler), ())
    assert ex.graph_break_count == 0, [b.reason for b in ex.break_reasons]
