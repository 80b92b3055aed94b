"""Input encodings: a module with `in_dim`, `out_dim` and `raw_dims`, built from config.

`raw_dims` is how many leading output channels are the raw input itself (the SDF network's
geometric initialisation keeps only those channels alive). A later hash-grid encoding plugs in
through `build_encoding` with the same attributes.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from neus_l0.config import EncodingConfig


class Encoding(nn.Module):
    """Base class: maps `(..., in_dim)` to `(..., out_dim)`."""

    in_dim: int
    out_dim: int
    raw_dims: int


class IdentityEncoding(Encoding):
    """The input unchanged."""

    def __init__(self, in_dim: int) -> None:
        super().__init__()
        self.in_dim = self.out_dim = self.raw_dims = in_dim

    def forward(self, x: Tensor) -> Tensor:
        """x (..., in_dim) -> (..., in_dim)."""
        return x


class FrequencyEncoding(Encoding):
    """NeRF's positional encoding: [x, sin(2^0 x), cos(2^0 x), ..., sin(2^(L-1) x), cos(...)].

    The channel order matches NeuS's embedder (per octave: sin of every input, then cos).
    """

    def __init__(self, in_dim: int, n_freqs: int, include_input: bool = True) -> None:
        super().__init__()
        self.in_dim = in_dim
        self.n_freqs = n_freqs
        self.include_input = include_input
        self.raw_dims = in_dim if include_input else 0
        self.out_dim = self.raw_dims + 2 * in_dim * n_freqs
        self.register_buffer("freqs", 2.0 ** torch.arange(n_freqs, dtype=torch.float32),
                             persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        """x (..., in_dim) -> (..., out_dim)."""
        parts = [x] if self.include_input else []
        if self.n_freqs:
            xf = x[..., None, :] * self.freqs[:, None]  # (..., L, in_dim)
            sc = torch.stack([torch.sin(xf), torch.cos(xf)], dim=-2)  # (..., L, 2, in_dim)
            parts.append(sc.flatten(-3))
        return torch.cat(parts, dim=-1)


def build_encoding(cfg: EncodingConfig, in_dim: int) -> Encoding:
    """The encoding that `cfg.kind` names, for inputs of `in_dim` channels."""
    if cfg.kind == "identity" or (cfg.kind == "frequency" and cfg.n_freqs == 0
                                  and cfg.include_input):
        return IdentityEncoding(in_dim)
    if cfg.kind == "frequency":
        return FrequencyEncoding(in_dim, cfg.n_freqs, cfg.include_input)
    raise ValueError(f"unknown encoding kind {cfg.kind!r}")
