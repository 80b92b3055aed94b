"""The validation PSNR inside the masks (``val_psnr_mask``): what the object alone scores,
beside the whole image's ``val_psnr``, computed from the very pixels the validation PNG
holds; the viewer's "last PSNR" prefers it."""

from __future__ import annotations

import json

import cv2
import numpy as np

from neus_l0.config.load import load_config
from neus_l0.formats.neus import load_scene
from neus_l0.render.views import psnr
from neus_l0.train.loop import train
from neus_l0.viewer.run_files import last_psnr


def test_validation_logs_the_psnr_inside_the_mask(tiny_scene, small_overrides, tmp_path):
    cfg = load_config("demo", [*small_overrides, "train.iters=4", "train.val_every=2",
                               "train.val_downscale=2"])
    scene = load_scene(tiny_scene)
    assert scene.has_masks
    run = tmp_path / "run"
    train(scene, cfg, run, progress=False)
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    val = [m for m in lines if "val_psnr" in m]
    assert [m["iter"] for m in val] == [2, 4]
    for m in val:
        png = run / "validation" / f"{m['iter']:07d}_v{m['val_view']:03d}.png"
        img = cv2.imread(str(png))[..., ::-1] / 255.0
        w = img.shape[1] // 3
        fg = (scene.masks[m["val_view"], ::2, ::2] > 0.5).numpy()
        assert fg.any() and not fg.all()
        assert m["val_psnr_mask"] == psnr(img[:, w:2 * w], img[:, :w], fg)
        assert m["val_psnr"] == psnr(img[:, w:2 * w], img[:, :w])
    assert last_psnr(run) == (4, val[-1]["val_psnr_mask"], "val_psnr_mask")
    assert np.isfinite(val[-1]["val_psnr_mask"])
