"""Scenes without masks: no visual hull, a grid that never empties surface, background
samples outside the sphere whatever narrows the rays."""

from __future__ import annotations

import dataclasses

import torch

from neus_l0.bounds.hull import carve_hull
from neus_l0.bounds.occupancy import OccupancyGrid
from neus_l0.bounds.points import PointBound
from neus_l0.config.load import load_config
from neus_l0.config.schema import BackgroundConfig, OccupancyConfig, RenderConfig
from neus_l0.fields.background import BackgroundNeRF
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.loop import build_run_state
from neus_l0.train.step import update_occupancy


def test_scene_without_masks_gets_no_hull(small, sphere_scene, tmp_path):
    scene = dataclasses.replace(sphere_scene(tmp_path / "s"), has_masks=False)
    cfg = load_config("womask", small + ["model.background.hidden=16",
                                         "model.background.layers=1", "render.n_outside=4"])
    run = build_run_state(scene, cfg, tmp_path / "run", torch.device("cpu"), resume=False)
    assert run.setup.bounds == () and run.setup.pool is None
    assert not (tmp_path / "run" / "hull.pt").exists()
    # views without masks carve nothing, even when asked to carve
    hull = carve_hull(torch.zeros_like(scene.masks), scene.intrinsics, scene.c2w,
                      resolution=32, has_masks=False)
    assert hull.fraction_of_sphere() == 1.0


def test_grid_is_not_updated_before_its_start(sphere_model):
    model = sphere_model()
    cfg = load_config("demo", ["render.occupancy.enabled=true",
                               "render.occupancy.resolution=32",
                               "render.occupancy.update_every=64",
                               "render.occupancy.start=500"])
    grid = OccupancyGrid(cfg.render.occupancy)
    for it in (0, 64, 499):
        update_occupancy(grid, model, cfg, it)
        assert bool(grid.occ.all())  # nothing known yet: nothing emptied
    update_occupancy(grid, model, cfg, 500)
    assert float(grid.fraction_occupied()) < 0.5
    before = grid.occ.clone()
    grid.occ.fill_(True)
    update_occupancy(grid, model, cfg, 563)  # not on the cadence: unchanged
    assert bool(grid.occ.all())
    update_occupancy(grid, model, cfg, 564)
    assert torch.equal(grid.occ, before)


def test_coarse_rare_grid_never_empties_a_cell_of_a_moving_sphere():
    g = torch.Generator().manual_seed(0)
    grid = OccupancyGrid(OccupancyConfig(enabled=True, resolution=32, update_every=128,
                                         hold=0))
    for k in range(6):  # the surface moves and sharpens between updates
        centre = (torch.rand(3, generator=g) - 0.5) * 0.6
        radius = 0.15 + 0.4 * torch.rand((), generator=g)
        s = torch.tensor([20.0 * 4**k])
        grid.update(lambda x, c=centre, r=radius: (x - c).norm(dim=-1, keepdim=True) - r, s)
        u = torch.randn(20000, 3, generator=g)
        surface = centre + radius * u / u.norm(dim=-1, keepdim=True)
        occ = grid.occ
        ijk = torch.floor((surface + 1.0) * 16.0).long().clamp(0, 31)
        assert bool(occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]].all())
        assert bool(grid.contains(surface).all())
    assert float(grid.fraction_occupied()) < 0.2  # and it does empty the rest


def test_background_samples_start_outside_the_sphere_when_a_bound_narrows_rays(sphere_model,
                                                                               monkeypatch):
    import neus_l0.render.volume as rendering
    from neus_l0.bounds.sphere import sphere_chord

    model = sphere_model()
    model.background = BackgroundNeRF(BackgroundConfig(hidden=16, layers=1, skip=[]))
    seen = {}
    real = rendering.outside_z_vals

    def spy(far, *args, **kwargs):
        seen["far"] = far
        return real(far, *args, **kwargs)

    monkeypatch.setattr(rendering, "outside_z_vals", spy)
    box = PointBound(torch.zeros(3), torch.eye(3), torch.full((3,), 0.3))
    g = torch.Generator().manual_seed(0)
    o = torch.randn(64, 3, generator=g)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    d = torch.nn.functional.normalize(-o + 0.2 * torch.randn(64, 3, generator=g), dim=-1)
    cfg = RenderConfig(n_samples=8, n_importance=8, up_sample_steps=1, n_outside=4)
    rendering.render_rays(model, o, d, cfg, build_sampler("hvs"), bounds=(box,))
    exit_ = sphere_chord(o, d)[1]
    assert bool((seen["far"] >= exit_ - 1e-6).all())
    pts = o[:, None] + d[:, None] * real(seen["far"], 4, 8, False)[..., None]
    assert bool((pts.norm(dim=-1) >= 1.0 - 1e-5).all())
