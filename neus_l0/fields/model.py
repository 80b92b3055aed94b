"""NeuS's networks of one run as a plain container, and how a run builds them.

`build_model(cfg, background=...)` returns a `NeuSModel` (it does no rendering, training
or meshing); `make_model(cfg)` builds a run's networks from its seed.
"""

from __future__ import annotations

import torch
from torch import nn

from neus_l0.config.schema import Config, ModelConfig
from neus_l0.fields.background import BackgroundNeRF
from neus_l0.fields.color import ColorNetwork
from neus_l0.fields.sdf import SDFNetwork
from neus_l0.fields.variance import SingleVariance


class NeuSModel(nn.Module):
    """The networks of one run: `sdf`, `color`, `variance` and `background` (or None)."""

    def __init__(self, sdf: SDFNetwork, color: ColorNetwork, variance: SingleVariance,
                 background: BackgroundNeRF | None = None) -> None:
        super().__init__()
        self.sdf = sdf
        self.color = color
        self.variance = variance
        self.background = background


def build_model(cfg: ModelConfig, background: bool = False) -> NeuSModel:
    """Build the networks from config; `background` adds the NeRF++ model."""
    sdf = SDFNetwork(cfg.sdf)
    return NeuSModel(
        sdf=sdf,
        color=ColorNetwork(cfg.color, feature_dim=sdf.feature_dim),
        variance=SingleVariance(cfg.variance),
        background=BackgroundNeRF(cfg.background) if background else None,
    )


def make_model(cfg: Config, device: str | torch.device = "cpu") -> NeuSModel:
    """The networks of `cfg`, initialised from `cfg.train.seed` (global RNG untouched)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.train.seed)
        model = build_model(cfg.model, background=cfg.render.n_outside > 0)
    return model.to(device)
