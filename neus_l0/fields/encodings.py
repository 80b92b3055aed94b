"""Input encodings: a module with `in_dim`, `out_dim` and `raw_dims`, built from config.

`raw_dims` is how many leading output channels are the raw input itself (the SDF network's
geometric initialisation keeps only those channels alive). Kinds: `identity`, `frequency`
(NeRF's positional encoding) and `hashgrid` (Instant-NGP's multiresolution hash grid, in
plain PyTorch so that autograd gives the SDF's gradient and its double backward).
"""

from __future__ import annotations

import itertools
import math

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


#: Instant-NGP's hash primes (the first is 1, so consecutive x stay in one cache line).
HASH_PRIMES = (1, 2654435761, 805459861)


def level_resolutions(n_levels: int, base_resolution: int, per_level_scale: float) -> list[int]:
    """Cells per axis of each level: floor(base * scale^l), l = 0 .. n_levels - 1."""
    # the small epsilon keeps exact powers (e.g. 16 * 2^3) from flooring to one less
    return [int(math.floor(base_resolution * per_level_scale**lv + 1e-6))
            for lv in range(n_levels)]


def spatial_hash(corners: Tensor, table_size: int) -> Tensor:
    """Instant-NGP's spatial hash of integer grid points.

    Args:
        corners: (..., 3) int64 grid coordinates (>= 0).
        table_size: entries of the table, a power of two.

    Returns:
        (...,) int64 indices in [0, table_size): (x * 1) xor (y * p1) xor (z * p2) mod T.
    """
    h = corners[..., 0] * HASH_PRIMES[0]
    h = h ^ (corners[..., 1] * HASH_PRIMES[1])
    h = h ^ (corners[..., 2] * HASH_PRIMES[2])
    return h & (table_size - 1)


class HashGridEncoding(Encoding):
    """Instant-NGP multiresolution hash grid, with the raw input (and optionally NeRF
    frequency bands) in front, as instant-nsr-pl does.

    Output channels: ``[x (raw_dims), sin/cos bands (n_freqs), level 0 features, ...,
    level L-1 features]``. Points are mapped from the box [-bound, bound]^3 to [0, 1]^3
    (clamped); level l has N_l = floor(base * scale^l) cells per axis and (N_l + 1)^3 grid
    points. A level whose grid points fit in the table (``(N_l + 1)^3 <= 2^log2_hashmap_size``)
    is indexed directly (x + y (N+1) + z (N+1)^2, no collisions) with a table of exactly that
    size; finer levels share nothing and use a table of 2^log2_hashmap_size entries indexed
    by `spatial_hash`. Features are trilinearly interpolated from the 8 corners of the cell,
    with ordinary tensor ops, so autograd differentiates them to any order (the SDF's
    gradient is piecewise polynomial in x, and the Eikonal loss backpropagates through it).

    Progressive levels (instant-nsr-pl's ProgressiveBandHashGrid): with `start_level` < L,
    only the first ``start_level + steps // update_steps`` levels are active (the others
    output 0), where ``steps`` is a persistent counter of forward passes made in training
    mode with gradients enabled (one per training iteration in `neus_l0.rendering`; the
    up-sampling passes run without gradients and validation in eval mode, so neither counts).
    The counter lives in the state dict, so checkpoints and resumes keep the schedule.

    Table entries are stored divided by `lr_scale` and multiplied back in `forward`: with
    Adam (whose steps are about lr in parameter space) that gives the table an effective
    learning rate of ``lr * lr_scale`` while the MLPs keep ``lr`` (Instant-NGP and
    instant-nsr-pl train the grid with a ~10x larger rate than NeuS's MLPs).
    """

    def __init__(self, in_dim: int = 3, n_levels: int = 16, n_features: int = 2,
                 log2_hashmap_size: int = 19, base_resolution: int = 16,
                 per_level_scale: float = 1.3819, bound: float = 1.0, n_freqs: int = 0,
                 include_input: bool = True, init_scale: float = 1e-4, lr_scale: float = 1.0,
                 start_level: int | None = None, update_steps: int = 1000) -> None:
        super().__init__()
        if in_dim != 3:
            raise ValueError("the hash grid encodes 3-D points")
        self.in_dim = in_dim
        self.n_levels = n_levels
        self.n_features = n_features
        self.table_size = 2**log2_hashmap_size
        self.bound = bound
        self.lr_scale = lr_scale
        self.start_level = n_levels if start_level is None else min(start_level, n_levels)
        self.update_steps = max(1, update_steps)
        self.bands = FrequencyEncoding(in_dim, n_freqs, include_input=False) if n_freqs else None
        self.raw_dims = in_dim if include_input else 0
        self.out_dim = (self.raw_dims + (self.bands.out_dim if self.bands else 0)
                        + n_levels * n_features)

        self.resolutions = level_resolutions(n_levels, base_resolution, per_level_scale)
        sizes = [min((n + 1) ** 3, self.table_size) for n in self.resolutions]
        #: levels [0, n_direct) are indexed directly, the rest through the hash
        self.n_direct = sum(1 for n in self.resolutions if (n + 1) ** 3 <= self.table_size)
        offsets = [0] + list(itertools.accumulate(sizes))
        self.level_sizes = sizes
        res = torch.tensor(self.resolutions, dtype=torch.float32)
        strides = torch.tensor([[1, n + 1, (n + 1) ** 2] for n in self.resolutions],
                               dtype=torch.int64)
        self.register_buffer("res", res, persistent=False)  # (L,)
        self.register_buffer("strides", strides, persistent=False)  # (L, 3)
        self.register_buffer("offsets", torch.tensor(offsets[:-1], dtype=torch.int64),
                             persistent=False)  # (L,)
        corners = torch.tensor(list(itertools.product((0, 1), repeat=3)), dtype=torch.int64)
        self.register_buffer("corners", corners, persistent=False)  # (8, 3), x major
        self.register_buffer("steps", torch.zeros((), dtype=torch.int64))
        table = torch.empty(offsets[-1], n_features).uniform_(-init_scale, init_scale)
        self.table = nn.Parameter(table / lr_scale)  # (sum of level sizes, F)

    def active_levels(self) -> Tensor:
        """() int64: how many levels are active now (a tensor, so no host sync)."""
        return torch.clamp(self.start_level + self.steps // self.update_steps,
                           max=self.n_levels)

    def grid_indices(self, cell: Tensor) -> Tensor:
        """Table rows of the 8 corners of each point's cell, per level.

        Args:
            cell: (N, L, 3) int64 lower corner of the cell at each level.

        Returns:
            (N, L, 8) int64 rows of `table` (level offsets included).
        """
        c = cell[:, :, None, :] + self.corners  # (N, L, 8, 3)
        k = self.n_direct
        parts = []
        if k:
            parts.append((c[:, :k] * self.strides[:k, None, :]).sum(-1))  # (N, k, 8)
        if k < self.n_levels:
            parts.append(spatial_hash(c[:, k:], self.table_size))  # (N, L - k, 8)
        idx = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
        return idx + self.offsets[:, None]

    def grid_features(self, x: Tensor) -> Tensor:
        """x (N, 3) -> interpolated features (N, L, F) of every level (inactive ones too)."""
        u = ((x / self.bound + 1.0) * 0.5).clamp(0.0, 1.0)  # (N, 3) in the unit cube
        pos = u[:, None, :] * self.res[:, None].to(u.dtype)  # (N, L, 3)
        with torch.no_grad():
            cell = torch.minimum(pos.floor(), self.res[:, None].to(u.dtype) - 1)  # (N, L, 3)
            idx = self.grid_indices(cell.long())  # (N, L, 8)
        f = (pos - cell)[..., None]  # (N, L, 3, 1) in [0, 1], differentiable wrt x
        table = self.table * self.lr_scale if self.lr_scale != 1.0 else self.table
        v = table.index_select(0, idx.reshape(-1)).view(*idx.shape, self.n_features)
        # trilinear = three rounds of lerps over the corners (x major, then y, then z);
        # `lerp` is one fused op (and so is its derivative), about 3x cheaper on the CPU than
        # forming the 8 weights and a weighted sum, in the forward and both backwards
        v = torch.lerp(v[:, :, :4], v[:, :, 4:], f[:, :, 0:1])  # (N, L, 4, F) over x
        v = torch.lerp(v[:, :, :2], v[:, :, 2:], f[:, :, 1:2])  # (N, L, 2, F) over y
        v = torch.lerp(v[:, :, :1], v[:, :, 1:], f[:, :, 2:3])  # (N, L, 1, F) over z
        return v[:, :, 0]  # (N, L, F)

    def forward(self, x: Tensor) -> Tensor:
        """x (N, 3) -> (N, out_dim)."""
        lead = x.shape[:-1]
        x = x.reshape(-1, 3)
        feats = self.grid_features(x)  # (N, L, F)
        if self.start_level < self.n_levels:
            level = torch.arange(self.n_levels, device=x.device)
            mask = (level < self.active_levels()).to(feats.dtype)  # (L,)
            feats = feats * mask[:, None]
            if self.training and torch.is_grad_enabled():
                self.steps += 1
        parts = [x] if self.raw_dims else []
        if self.bands is not None:
            parts.append(self.bands(x))
        parts.append(feats.flatten(1))
        return torch.cat(parts, dim=-1).reshape(*lead, self.out_dim)


def build_encoding(cfg: EncodingConfig, in_dim: int) -> Encoding:
    """The encoding that `cfg.kind` names, for inputs of `in_dim` channels."""
    if cfg.kind == "identity" or (cfg.kind == "frequency" and cfg.n_freqs == 0
                                  and cfg.include_input):
        return IdentityEncoding(in_dim)
    if cfg.kind == "frequency":
        return FrequencyEncoding(in_dim, cfg.n_freqs, cfg.include_input)
    if cfg.kind == "hashgrid":
        return HashGridEncoding(
            in_dim, n_levels=cfg.n_levels, n_features=cfg.n_features,
            log2_hashmap_size=cfg.log2_hashmap_size, base_resolution=cfg.base_resolution,
            per_level_scale=hashgrid_per_level_scale(cfg), bound=cfg.bound,
            n_freqs=cfg.n_freqs, include_input=cfg.include_input, init_scale=cfg.init_scale,
            lr_scale=cfg.lr_scale, start_level=cfg.start_level, update_steps=cfg.update_steps)
    raise ValueError(f"unknown encoding kind {cfg.kind!r}")


def hashgrid_per_level_scale(cfg: EncodingConfig) -> float:
    """`cfg.per_level_scale`, or (when it is 0) the scale that reaches `finest_resolution`
    at the last level: (finest / base)^(1 / (n_levels - 1))."""
    if cfg.per_level_scale > 0:
        return cfg.per_level_scale
    if cfg.n_levels <= 1:
        return 1.0
    return math.exp(math.log(cfg.finest_resolution / cfg.base_resolution) / (cfg.n_levels - 1))
