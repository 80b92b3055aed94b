"""Fixtures of the training tests."""

import pytest
import torch

from neus_l0.bounds.silhouettes import Silhouettes
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.losses import LOSS_NAMES
from neus_l0.train.step import draw_step_inputs, render_and_loss


@pytest.fixture
def step_term():
    """A function (model, scene, cfg, name) -> (the step's inputs, its loss, its metric
    `name`): one step's rays drawn from seed 0 at iteration 3, rendered and scored."""

    def run(model, scene, cfg, name):
        sil = (Silhouettes.from_scene(scene, cfg.render.hull.margin_px)
               if cfg.train.fill_silhouettes else None)
        inputs = draw_step_inputs(scene, cfg, 3, 64, torch.Generator().manual_seed(0), None,
                                  silhouettes=sil)
        loss, metrics, _ = render_and_loss(model, inputs, cfg, build_sampler(cfg.sampler), ())
        return inputs, loss.item(), dict(zip(LOSS_NAMES, metrics.tolist(), strict=False))[name]

    return run
