"""`train --viewer`: the page follows the run (curves at log steps, a coarse mesh from a
copy of the weights at validation steps), fed from a worker thread."""

from __future__ import annotations

from neus_l0.config.load import load_config
from neus_l0.train.loop import train
from neus_l0.viewer.live import LiveViewer


def test_the_live_page_gets_the_curves_and_a_mesh(sphere_scene, small, tmp_path):
    scene = sphere_scene(tmp_path / "scene")
    cfg = load_config("demo", [*small, "train.iters=10", "train.val_every=5",
                               "train.val_downscale=2"])
    live = LiveViewer(0, resolution=32, finish=True)
    train(scene, cfg, tmp_path / "run", progress=False, callbacks=[live])
    assert not live.worker.is_alive()
    assert {"loss", "PSNR (dB)", "validation PSNR (dB)", "sharpness inv_s",
            "learning rate"} <= set(live.page.plots)
    assert live.state.shown in (5, 10)
    assert "last PSNR" in live.page.status.content


def test_the_live_mesh_is_coloured_with_the_steps_view_weight(small):
    """A run in its view warm-up shows the colours it trains with: the job carries the view
    weight (not in the state dict), and the mesh's colours follow it."""
    import types

    import numpy as np
    import torch

    from neus_l0.fields.model import make_model
    from neus_l0.viewer.live import coarse_mesh

    cfg = load_config("demo", [*small, "model.color.view_warmup=0.5", "train.val_every=1"])
    model = make_model(cfg)
    with torch.no_grad():  # a colour that depends on the view direction
        for p in model.color.parameters():
            p.add_(0.3 * torch.randn_like(p))
    model.color.view_scale.fill_(0.25)
    live = LiveViewer(0)
    live.after_step(types.SimpleNamespace(iteration=1, cfg=cfg, model=model))
    kind, it, (weights, view_scale) = live.jobs.get_nowait()
    assert (kind, it, view_scale) == ("mesh", 1, 0.25)
    colours = {s: coarse_mesh(cfg, weights, np.eye(4), None, 24, s).visual.vertex_colors
               for s in (0.25, 1.0)}
    assert colours[0.25].shape == colours[1.0].shape
    assert not np.array_equal(colours[0.25], colours[1.0])
    assert np.array_equal(coarse_mesh(cfg, weights, np.eye(4), None, 24, 0.25)
                          .visual.vertex_colors, colours[0.25])
