"""NeuS's networks: SDF, colour, single variance, NeRF++ background, and input encodings.

`build_model(cfg, background=...)` returns a `NeuSModel`, a plain container of the
networks (it does no rendering, training or meshing).
"""

from __future__ import annotations

from torch import nn

from neus_l0.config import ModelConfig
from neus_l0.fields.background import BackgroundNeRF, inverse_sphere
from neus_l0.fields.color import ColorNetwork
from neus_l0.fields.encodings import (
    Encoding,
    FrequencyEncoding,
    HashGridEncoding,
    IdentityEncoding,
    build_encoding,
)
from neus_l0.fields.sdf import SDFNetwork, sdf_and_gradient
from neus_l0.fields.variance import SingleVariance

__all__ = [
    "BackgroundNeRF", "ColorNetwork", "Encoding", "FrequencyEncoding", "HashGridEncoding",
    "IdentityEncoding",
    "NeuSModel", "SDFNetwork", "SingleVariance", "build_encoding", "build_model",
    "inverse_sphere", "sdf_and_gradient",
]


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
