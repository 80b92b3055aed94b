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
