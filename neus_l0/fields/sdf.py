"""NeuS's SDF network: an MLP with a skip connection, softplus(beta=100), geometric init."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.nn.utils.parametrizations import weight_norm

from neus_l0.config import SDFConfig
from neus_l0.errors import ConfigError
from neus_l0.fields.encodings import build_encoding


class SDFNetwork(nn.Module):
    """f(x) -> (sdf, feature). With geometric init the SDF starts as |x| - bias.

    Attributes:
        feature_dim: length of the feature vector returned after the SDF.
    """

    def __init__(self, cfg: SDFConfig) -> None:
        super().__init__()
        self.encoding = build_encoding(cfg.encoding, 3)
        self.scale = cfg.scale
        self.skip = set(cfg.skip)
        self.feature_dim = cfg.feature_dim
        d_in = self.encoding.out_dim
        if self.skip and cfg.hidden <= d_in:
            raise ConfigError(f"model.sdf.hidden={cfg.hidden} must exceed the encoded input "
                              f"size {d_in} when model.sdf.skip is used")
        dims = [d_in] + [cfg.hidden] * cfg.layers + [1 + cfg.feature_dim]
        n_lin = len(dims) - 1
        layers = []
        for i in range(n_lin):
            in_dim = dims[i]  # for a skip layer this counts the re-concatenated input
            out_dim = dims[i + 1] - d_in if (i + 1) in self.skip else dims[i + 1]
            lin = nn.Linear(in_dim, out_dim)
            if cfg.geometric_init:
                _geometric_init(lin, i, n_lin, d_in, self.encoding.raw_dims,
                                i in self.skip, cfg.bias)
            layers.append(weight_norm(lin) if cfg.weight_norm else lin)
        self.layers = nn.ModuleList(layers)
        self.activation = nn.Softplus(beta=cfg.softplus_beta)

    def forward(self, x: Tensor) -> Tensor:
        """x (N, 3) in the normalised frame -> (N, 1 + feature_dim): sdf then feature."""
        inputs = self.encoding(x * self.scale)
        h = inputs
        last = len(self.layers) - 1
        for i, lin in enumerate(self.layers):
            if i in self.skip:
                h = torch.cat([h, inputs], dim=-1) / math.sqrt(2.0)
            h = lin(h)
            if i < last:
                h = self.activation(h)
        return torch.cat([h[:, :1] / self.scale, h[:, 1:]], dim=-1)

    def sdf(self, x: Tensor) -> Tensor:
        """x (N, 3) -> sdf (N, 1)."""
        return self.forward(x)[:, :1]


def _geometric_init(lin: nn.Linear, i: int, n_lin: int, d_in: int, raw_dims: int,
                    is_skip: bool, bias: float) -> None:
    """IDR / SAL initialisation so that the network starts as the SDF |x| - bias."""
    out_dim = lin.out_features
    with torch.no_grad():
        if i == n_lin - 1:
            nn.init.normal_(lin.weight, mean=math.sqrt(math.pi) / math.sqrt(lin.in_features),
                            std=1e-4)
            nn.init.constant_(lin.bias, -bias)
            return
        nn.init.constant_(lin.bias, 0.0)
        nn.init.normal_(lin.weight, 0.0, math.sqrt(2.0) / math.sqrt(out_dim))
        if i == 0 and d_in > raw_dims:
            lin.weight[:, raw_dims:] = 0.0  # only the raw point drives the first layer
        elif is_skip and d_in > raw_dims:
            lin.weight[:, -(d_in - raw_dims):] = 0.0  # encoded part of the skip input


def sdf_and_gradient(net: SDFNetwork, x: Tensor, create_graph: bool) -> tuple[Tensor, Tensor]:
    """One forward pass and the SDF's spatial gradient.

    Args:
        net: the SDF network.
        x: (N, 3) points (need not require grad).
        create_graph: keep the graph of the gradient (for the Eikonal loss in training).

    Returns:
        output (N, 1 + feature_dim) and gradient (N, 3).
    """
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        out = net(x)
        (grad,) = torch.autograd.grad(out[:, :1], x, torch.ones_like(out[:, :1]),
                                      create_graph=create_graph)
    return out, grad
