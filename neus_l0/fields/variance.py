"""NeuS's single learned variance."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from neus_l0.config.schema import VarianceConfig


class SingleVariance(nn.Module):
    """One parameter `variance`; the logistic sharpness is s = exp(10 * variance)."""

    def __init__(self, cfg: VarianceConfig) -> None:
        super().__init__()
        self.variance = nn.Parameter(torch.tensor(float(cfg.init)))

    def inv_s(self) -> Tensor:
        """s = exp(10 * variance), shape (1,), clipped to [1e-6, 1e6] as NeuS does."""
        return torch.exp(self.variance * 10.0).clamp(1e-6, 1e6).reshape(1)
