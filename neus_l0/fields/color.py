"""NeuS's colour network (IDR's rendering network)."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn.utils.parametrizations import weight_norm

from neus_l0.config.schema import ColorConfig
from neus_l0.fields.encodings import build_encoding


class ColorNetwork(nn.Module):
    """c(x, v, n, feature) -> rgb in [0, 1] (ReLU MLP, sigmoid output)."""

    def __init__(self, cfg: ColorConfig, feature_dim: int) -> None:
        super().__init__()
        self.mode = cfg.mode
        self.view_encoding = build_encoding(cfg.view_encoding, 3)
        d_in = 3 + feature_dim  # point and feature
        if cfg.mode != "no_view_dir":
            d_in += self.view_encoding.out_dim
        if cfg.mode != "no_normal":
            d_in += 3
        dims = [d_in] + [cfg.hidden] * cfg.layers + [3]
        layers = []
        for i in range(len(dims) - 1):
            lin = nn.Linear(dims[i], dims[i + 1])
            layers.append(weight_norm(lin) if cfg.weight_norm else lin)
        self.layers = nn.ModuleList(layers)
        # the view encoding's weight (`ColorConfig.view_warmup`; the step sets it): a
        # tensor, so that a compiled step reads its value instead of guarding on it
        self.register_buffer("view_scale", torch.ones(()), persistent=False)

    def forward(self, points: Tensor, normals: Tensor, view_dirs: Tensor,
                features: Tensor) -> Tensor:
        """points, normals, view_dirs (N, 3), features (N, F) -> rgb (N, 3)."""
        if self.mode == "idr":
            views = self.view_encoding(view_dirs) * self.view_scale
            h = torch.cat([points, views, normals, features], dim=-1)
        elif self.mode == "no_view_dir":
            h = torch.cat([points, normals, features], dim=-1)
        else:
            h = torch.cat([points, self.view_encoding(view_dirs) * self.view_scale, features],
                          dim=-1)
        last = len(self.layers) - 1
        for i, lin in enumerate(self.layers):
            h = lin(h)
            if i < last:
                h = torch.relu(h)
        return torch.sigmoid(h)
