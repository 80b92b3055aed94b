"""The pixel pool: exactly the pixels whose rays can reach the surface, found cheaply."""

import torch

from neus_l0.bounds.hull import hull_from_scene
from neus_l0.bounds.pixel_pool import hull_silhouette, reachable_pixels
from neus_l0.bounds.spans import ray_bounds
from neus_l0.config.schema import RenderConfig
from neus_l0.data.rays import image_rays
from neus_l0.sampling.upsample import build_sampler


def _brute_force(scene, cfg, bounds):
    found = []
    hw = scene.height * scene.width
    for v in range(scene.n_views):
        o, d = (x.reshape(-1, 3) for x in image_rays(scene, v))
        found.append(ray_bounds(o, d, cfg, bounds)[2].nonzero().squeeze(1) + v * hw)
    return torch.cat(found)


def test_the_pool_is_every_pixel_that_reaches_the_sphere_and_the_hull(sphere_scene, tmp_path):
    scene = sphere_scene(tmp_path / "s", n_views=5, H=40, W=50, radius=0.4)
    hull = hull_from_scene(scene, 64, 2.0)
    cfg = RenderConfig(cull_outside_sphere=True)
    for bounds in [(), (hull,)]:
        pool = reachable_pixels(scene, cfg, bounds)
        ref = _brute_force(scene, cfg, bounds)
        assert torch.equal(torch.sort(pool.pixels).values, ref)
        assert pool.fraction == ref.numel() / (5 * 40 * 50)
    # the hull leaves fewer pixels than the sphere, and keeps every foreground pixel
    with_hull = reachable_pixels(scene, cfg, (hull,))
    sphere = reachable_pixels(scene, cfg)
    assert with_hull.fraction < sphere.fraction
    fg = scene.masks.reshape(-1).nonzero().squeeze(1)
    assert torch.isin(fg, with_hull.pixels).all()


def test_the_silhouette_covers_every_ray_that_meets_a_voxel(sphere_scene, tmp_path):
    scene = sphere_scene(tmp_path / "s", n_views=4, H=30, W=40)
    g = torch.Generator().manual_seed(0)
    c = -1.0 + (torch.arange(32) + 0.5) / 16
    r = (c[:, None, None] ** 2 + c[None, :, None] ** 2 + c[None, None, :] ** 2).sqrt()
    # scattered single cells near the centre: gaps between them are the hard case
    occ = (torch.rand(32, 32, 32, generator=g) < 0.05) & (r < 0.45)
    from neus_l0.bounds.hull import VisualHull

    hull = VisualHull(occ)
    cfg = RenderConfig(cull_outside_sphere=True)
    for v in range(scene.n_views):
        sil = hull_silhouette(occ, scene.intrinsics[v], scene.c2w[v], 30, 40)
        o, d = (x.reshape(-1, 3) for x in image_rays(scene, v))
        hits = ray_bounds(o, d, cfg, (hull,))[2].reshape(30, 40)
        assert not (hits & ~sil).any()
        assert sil.float().mean() < 0.9  # and it is not everything


def test_no_pool_with_a_background_model_or_without_culling(sphere_scene, tmp_path):
    scene = sphere_scene(tmp_path / "s")
    assert reachable_pixels(scene, RenderConfig()) is None
    assert reachable_pixels(scene, RenderConfig(cull_outside_sphere=True),
                            background=True) is None


def test_the_pool_keeps_each_pixels_span_and_a_step_may_use_it(sphere_model, sphere_scene,
                                                               tmp_path):
    """`PixelPool.spans` are `packed_spans` of the pixels' rays under the hull, and rendering
    with them is rendering with the hull; without static bounds nothing is kept."""

    from neus_l0.bounds.spans import packed_spans
    from neus_l0.data.rays import rays_at
    from neus_l0.render.volume import render_rays

    scene = sphere_scene(tmp_path / "s", n_views=4, H=30, W=40, radius=0.4)
    hull = hull_from_scene(scene, 64, 2.0)
    cfg = RenderConfig(n_samples=16, n_importance=16, up_sample_steps=2,
                       cull_outside_sphere=True)
    assert reachable_pixels(scene, cfg).spans is None  # the sphere alone: recomputed
    pool = reachable_pixels(scene, cfg, (hull,))
    assert pool.spans.shape == (pool.pixels.numel(), 4)
    rays = rays_at(scene, pool.pixels)
    span, active = packed_spans(rays["origins"], rays["dirs"], cfg, (hull,))
    assert active.all()  # the pool's pixels all reach the hull
    # the pool's spans are those of the very rays a step draws (`rays_at`)
    assert torch.equal(pool.spans, span)
    near, far, entry, exit_ = pool.spans.unbind(1)
    assert (entry <= near + 1e-6).all() and (near < far).all() and (far <= exit_ + 1e-6).all()
    model = sphere_model()
    pick = torch.arange(0, pool.pixels.numel(), 7)
    o, d = rays["origins"][pick], rays["dirs"][pick]
    with torch.no_grad():
        with_hull = render_rays(model, o, d, cfg, build_sampler("hvs"), bounds=(hull,))
        looked_up = render_rays(model, o, d, cfg, build_sampler("hvs"), span=span[pick])
    for key in ("color", "weight_sum", "depth", "t"):
        torch.testing.assert_close(getattr(looked_up, key), getattr(with_hull, key),
                                   rtol=0, atol=0)
