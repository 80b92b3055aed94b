"""NeRF++ background model for the space outside the unit sphere (the no-mask setting)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from neus_l0.config.schema import BackgroundConfig
from neus_l0.fields.encodings import build_encoding


def inverse_sphere(points: Tensor) -> Tensor:
    """NeRF++'s parametrisation: x (..., 3) -> (x / r, 1 / r) (..., 4), r = max(|x|, 1)."""
    r = torch.linalg.norm(points, dim=-1, keepdim=True).clamp(1.0, 1e10)
    return torch.cat([points / r, 1.0 / r], dim=-1)


class BackgroundNeRF(nn.Module):
    """NeRF MLP on inverse-sphere points with view-dependent colour.

    Attributes:
        layers: `cfg.layers` ReLU layers of width `cfg.hidden`, the encoded input
            re-concatenated after the layers listed in `cfg.skip`.
    """

    def __init__(self, cfg: BackgroundConfig) -> None:
        super().__init__()
        self.encoding = build_encoding(cfg.encoding, 4)
        self.view_encoding = build_encoding(cfg.view_encoding, 3)
        self.skip = set(cfg.skip)
        d_in, w = self.encoding.out_dim, cfg.hidden
        layers = [nn.Linear(d_in, w)]
        for i in range(cfg.layers - 1):
            layers.append(nn.Linear(w + d_in if i in self.skip else w, w))
        self.layers = nn.ModuleList(layers)
        self.density = nn.Linear(w, 1)
        self.feature = nn.Linear(w, w)
        self.view = nn.Linear(w + self.view_encoding.out_dim, w // 2)
        self.rgb = nn.Linear(w // 2, 3)

    def forward(self, points: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        """points (N, 3) (any radius), dirs (N, 3) -> sigma (N, 1) >= 0, rgb (N, 3)."""
        x = self.encoding(inverse_sphere(points))
        h = x
        for i, lin in enumerate(self.layers):
            h = F.relu(lin(h))
            if i in self.skip:
                h = torch.cat([x, h], dim=-1)
        sigma = F.softplus(self.density(h))
        h = torch.cat([self.feature(h), self.view_encoding(dirs)], dim=-1)
        h = F.relu(self.view(h))
        return sigma, torch.sigmoid(self.rgb(h))
