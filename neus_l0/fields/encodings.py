"""Input encodings: a module with `in_dim`, `out_dim` and `raw_dims`, built from config.

`raw_dims` is how many leading output channels are the raw input itself (the SDF network's
geometric initialisation keeps only those channels alive). Kinds: `identity`, `frequency`
(NeRF's positional encoding) and `hashgrid` (Instant-NGP's multiresolution hash grid, in
plain PyTorch so that autograd gives the SDF's gradient and its double backward).

Every encoding also has `forward_jacobian(x)`, the output and its derivative with respect
to the input in closed form (an ordinary differentiable tensor expression), which the SDF
network's `analytic` gradient propagates through its MLP (no double backward).
"""

from __future__ import annotations

import itertools
import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from neus_l0.config.schema import EncodingConfig


class Encoding(nn.Module):
    """Base class: maps `(..., in_dim)` to `(..., out_dim)`."""

    in_dim: int
    out_dim: int
    raw_dims: int

    def forward_jacobian(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x (N, in_dim) -> output (N, out_dim) and its Jacobian (N, in_dim, out_dim),
        ``jac[n, j, k] = d out[n, k] / d x[n, j]``."""
        raise NotImplementedError


def _eye_jacobian(x: Tensor) -> Tensor:
    """(N, d) -> the identity's Jacobian (N, d, d), a broadcast view (no copy)."""
    n, d = x.shape
    return torch.eye(d, dtype=x.dtype, device=x.device).expand(n, d, d)


class IdentityEncoding(Encoding):
    """The input unchanged."""

    def __init__(self, in_dim: int) -> None:
        super().__init__()
        self.in_dim = self.out_dim = self.raw_dims = in_dim

    def forward(self, x: Tensor, count: bool = True) -> Tensor:
        """x (..., in_dim) -> (..., in_dim) (`count`: see `HashGridEncoding.forward`)."""
        return x

    def forward_jacobian(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x (N, in_dim) -> x and the identity (N, in_dim, in_dim)."""
        return x, _eye_jacobian(x)


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
        self.register_buffer("freq_col", self.freqs[:, None].clone(), persistent=False)  # (L,1)

    def forward(self, x: Tensor, count: bool = True) -> Tensor:
        """x (..., in_dim) -> (..., out_dim) (`count`: see `HashGridEncoding.forward`)."""
        parts = [x] if self.include_input else []
        if self.n_freqs:
            xf = x[..., None, :] * self.freq_col  # (..., L, in_dim)
            sc = torch.stack([torch.sin(xf), torch.cos(xf)], dim=-2)  # (..., L, 2, in_dim)
            parts.append(sc.flatten(-3))
        return torch.cat(parts, dim=-1)

    def forward_jacobian(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x (N, in_dim) -> output (N, out_dim) and Jacobian (N, in_dim, out_dim).

        d sin(f x_i) / d x_j = f cos(f x_i) [i = j], d cos(f x_i) / d x_j = -f sin(f x_i) [i = j].
        """
        n, d = x.shape
        vals = [x] if self.include_input else []
        jacs = [_eye_jacobian(x)] if self.include_input else []
        if self.n_freqs:
            xf = x[:, None, :] * self.freq_col  # (N, L, d)
            sin, cos = torch.sin(xf), torch.cos(xf)
            vals.append(torch.stack([sin, cos], dim=-2).flatten(1))  # (N, L * 2 * d)
            f = self.freq_col  # (L, 1)
            dsc = torch.stack([cos * f, -sin * f], dim=-2)  # (N, L, 2, d): d/dx_i of channel i
            eye = torch.eye(d, dtype=x.dtype, device=x.device)[:, None, None, :]  # (d,1,1,d)
            jacs.append((dsc[:, None] * eye).flatten(2))  # (N, d, L * 2 * d)
        return torch.cat(vals, dim=-1), torch.cat(jacs, dim=-1)


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

    Progressive levels (instant-nsr-pl's ProgressiveBandHashGrid; ``cfg.start_level`` and
    ``cfg.update_steps``): with `start_level` < L,
    only the first ``start_level + steps // update_steps`` levels are active (the others
    output 0), where ``steps`` is a persistent counter of forward passes made in training
    mode with gradients enabled (one per training iteration in `neus_l0.render.volume`; the
    up-sampling passes run without gradients and validation in eval mode, so neither counts).
    The counter lives in the state dict, so checkpoints and resumes keep the schedule.

    Table entries are stored divided by `lr_scale` and multiplied back in `forward`: with
    Adam (whose steps are about lr in parameter space) that gives the table an effective
    learning rate of ``lr * lr_scale`` while the MLPs keep ``lr`` (Instant-NGP and
    instant-nsr-pl train the grid with a ~10x larger rate than NeuS's MLPs).
    """

    def __init__(self, cfg: EncodingConfig, in_dim: int = 3) -> None:
        """The grid `cfg` describes (``kind: hashgrid``; `hashgrid_per_level_scale` when its
        ``per_level_scale`` is 0), on inputs of `in_dim` = 3 channels."""
        super().__init__()
        n_levels, n_features, n_freqs = cfg.n_levels, cfg.n_features, cfg.n_freqs
        start_level, update_steps = cfg.start_level, cfg.update_steps
        if in_dim != 3:
            raise ValueError("the hash grid encodes 3-D points")
        self.in_dim = in_dim
        self.n_levels = n_levels
        self.n_features = n_features
        self.table_size = 2**cfg.log2_hashmap_size
        self.bound = cfg.bound
        self.lr_scale = lr_scale = cfg.lr_scale
        self.start_level = n_levels if start_level is None else min(start_level, n_levels)
        self.update_steps = max(1, update_steps)
        self.bands = FrequencyEncoding(in_dim, n_freqs, include_input=False) if n_freqs else None
        self.raw_dims = in_dim if cfg.include_input else 0
        self.out_dim = (self.raw_dims + (self.bands.out_dim if self.bands else 0)
                        + n_levels * n_features)

        self.resolutions = level_resolutions(n_levels, cfg.base_resolution,
                                             hashgrid_per_level_scale(cfg))
        sizes = [min((n + 1) ** 3, self.table_size) for n in self.resolutions]
        #: levels [0, n_direct) are indexed directly, the rest through the hash
        self.n_direct = sum(1 for n in self.resolutions if (n + 1) ** 3 <= self.table_size)
        offsets = [0] + list(itertools.accumulate(sizes))
        self.level_sizes = sizes
        res = torch.tensor(self.resolutions, dtype=torch.float32)
        strides = torch.tensor([[1, n + 1, (n + 1) ** 2] for n in self.resolutions],
                               dtype=torch.int64)
        # per level: the index multipliers (direct strides, or the hash primes)
        mult = torch.tensor([[1, n + 1, (n + 1) ** 2] if lv < self.n_direct else HASH_PRIMES
                             for lv, n in enumerate(self.resolutions)], dtype=torch.int64)
        self.register_buffer("res", res, persistent=False)  # (L,)
        self.register_buffer("strides", strides, persistent=False)  # (L, 3)
        self.register_buffer("offsets", torch.tensor(offsets[:-1], dtype=torch.int64),
                             persistent=False)  # (L,)
        self.register_buffer("level_mult", mult[:, None, :], persistent=False)  # (L, 1, 3)
        self.register_buffer("level_direct", (torch.arange(n_levels) < self.n_direct)[:, None],
                             persistent=False)  # (L, 1) bool
        self.register_buffer("level", torch.arange(n_levels)[:, None], persistent=False)  # (L,1)
        # x -> pos = (x / bound) * res / 2 + res / 2 (then clamped to [0, res]), per level
        self.register_buffer("half_res", (res * 0.5)[:, None], persistent=False)  # (L, 1)
        self.register_buffer("pos_max", res[:, None].clone(), persistent=False)  # (L, 1)
        self.register_buffer("cell_max", (res - 1)[:, None], persistent=False)  # (L, 1)
        self.register_buffer("cell_max_long", (res - 1)[:, None].long(), persistent=False)
        self.register_buffer("pos_min", torch.zeros(n_levels, 1), persistent=False)
        self.register_buffer("level_scale", torch.full((n_levels, 1), float(lr_scale)),
                             persistent=False)  # (L, 1) lr_scale
        corners = torch.tensor(list(itertools.product((0, 1), repeat=3)), dtype=torch.int64)
        self.register_buffer("corners", corners, persistent=False)  # (8, 3), x major
        # the corners' part of the index product, and the offsets as a column: (L, 8, 3), (L, 1)
        self.register_buffer("corner_mult", corners * self.level_mult, persistent=False)
        self.register_buffer("offset_col", self.offsets[:, None].clone(), persistent=False)
        self.register_buffer("steps", torch.zeros((), dtype=torch.int64))
        # a tensor, so that a budget's plan can re-set it without recompiling the step
        self.register_buffer("level_every", torch.tensor(self.update_steps), persistent=False)
        table = torch.empty(offsets[-1], n_features).uniform_(-cfg.init_scale, cfg.init_scale)
        self.table = nn.Parameter(table / lr_scale)  # (sum of level sizes, F)

    def active_levels(self) -> Tensor:
        """() int64: how many levels are active now (a tensor, so no host sync)."""
        return torch.clamp(self.start_level + self.steps // self.level_every,
                           max=self.n_levels)

    def set_update_steps(self, update_steps: int) -> None:
        """Re-set the iterations between level activations (a budget's plan)."""
        self.update_steps = max(1, int(update_steps))
        self.level_every.fill_(self.update_steps)

    def finest_active_resolution(self) -> Tensor:
        """() float: cells per axis of the finest active level (a tensor, no host sync)."""
        if self.start_level >= self.n_levels:
            return self.res[-1]
        # index_select with a tensor index: no host read (compiles without a graph break)
        return self.res.index_select(0, self.active_levels().reshape(1) - 1).reshape(())

    def grid_indices(self, cell: Tensor) -> Tensor:
        """Table rows of the 8 corners of each point's cell, per level.

        Directly indexed levels use ``x + y (N+1) + z (N+1)^2``, the others `spatial_hash`;
        both come from one product with per-level multipliers (ops shared by all levels).

        Args:
            cell: (N, L, 3) int64 lower corner of the cell at each level.

        Returns:
            (N, L, 8) int64 rows of `table` (level offsets included).
        """
        # (cell + corner) * mult, as cell * mult + corner * mult in one op: (N, L, 8, 3)
        p = torch.addcmul(self.corner_mult, cell[:, :, None, :], self.level_mult)
        if self.n_direct == self.n_levels:
            idx = p.sum(-1)
        else:
            x, y, z = p.unbind(-1)
            hashed = (x ^ y ^ z) & (self.table_size - 1)  # (N, L, 8)
            idx = torch.where(self.level_direct, p.sum(-1), hashed) if self.n_direct else hashed
        return idx + self.offset_col

    def _cells(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The cell of every point at every level and its corners' table rows.

        Args:
            x: (N, 3) points.

        Returns:
            raw (N, L, 3) the continuous grid position x res_l / (2 bound) + res_l / 2; pos
            (N, L, 3) the same clamped to [0, res_l] (the box); frac (N, L, 3)
            in [0, 1] the position in the cell (differentiable wrt x); idx (N, L, 8) int64
            the corners' rows of `table`.
        """
        half_res = self.half_res.to(x.dtype)  # exact: halves of integers
        xb = x / self.bound if self.bound != 1.0 else x
        raw = torch.addcmul(half_res, xb[:, None, :], half_res)  # (N, L, 3)
        pos = torch.clamp(raw, self.pos_min.to(x.dtype), self.pos_max.to(x.dtype))
        with torch.no_grad():
            # pos >= 0, so truncation is floor; one op less than floor, minimum, long
            cell = torch.clamp_max(pos.long(), self.cell_max_long)  # (N, L, 3) int64
            idx = self.grid_indices(cell)  # (N, L, 8)
        return raw, pos, pos - cell, idx

    def _corners(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """`_cells`, with the corners' table entries v (N, L, 8, F) (as stored, i.e.
        without `lr_scale`) in place of their rows."""
        raw, pos, frac, idx = self._cells(x)
        if torch.is_grad_enabled():  # index_select: twice differentiable (autograd's path)
            v = self.table.index_select(0, idx.view(-1)).view(*idx.shape, self.n_features)
        else:  # one op, as fast as index_select (indexing, table[idx], is 2x slower on CPU)
            v = F.embedding(idx, self.table)
        return raw, pos, frac, v

    def grid_features(self, x: Tensor) -> Tensor:
        """x (N, 3) -> interpolated features (N, L, F) of every level (inactive ones too)."""
        _, _, frac, v = self._corners(x)
        feats = _trilinear(v, frac)
        return feats * self.lr_scale if self.lr_scale != 1.0 else feats

    def _level_weights(self, x: Tensor, count: bool = True) -> Tensor | None:
        """(L, 1) multipliers of the levels' features (lr_scale, 0 for inactive levels), or
        None when all are 1; counts a training pass (see the class docstring) unless
        `count` is False."""
        if self.start_level >= self.n_levels:
            return None if self.lr_scale == 1.0 else self.level_scale.to(x.dtype)
        w = self._active_weights(x.dtype)  # (L, 1)
        if count and self.training and torch.is_grad_enabled():
            self.steps += 1
        return w

    def _active_weights(self, dtype: torch.dtype) -> Tensor:
        """(L, 1): lr_scale for the active levels, 0 for the others; outside compiled code
        cached until `steps` changes (its version counter moves with every in-place
        update: the count of a training pass, `load_state_dict`), so the no-gradient
        passes of a step (up-sampling) compute it once."""
        compiling = torch.compiler.is_compiling()
        key = (self.steps._version, self.steps.data_ptr(), dtype) if not compiling else None
        cached = self.__dict__.get("_active_cache")
        if cached is not None and cached[0] == key and key is not None:
            return cached[1]
        w = torch.where(self.level < self.active_levels(), self.level_scale.to(dtype), 0.0)
        if not compiling:
            self.__dict__["_active_cache"] = (key, w)
        return w

    def _prefix(self, x: Tensor) -> list[Tensor]:
        parts = [x] if self.raw_dims else []
        if self.bands is not None:
            parts.append(self.bands(x))
        return parts

    def forward(self, x: Tensor, count: bool = True) -> Tensor:
        """x (N, 3) -> (N, out_dim). `count`: whether a training pass counts towards the
        levels' schedule (False for a second pass in the same step, e.g. the curvature
        term's points)."""
        lead = x.shape[:-1]
        x = x.reshape(-1, 3) if x.dim() != 2 else x
        weights = self._level_weights(x, count)
        _, _, frac, v = self._corners(x)
        feats = _trilinear(v, frac)  # (N, L, F)
        if weights is not None:
            feats = feats * weights
        out = torch.cat([*self._prefix(x), feats.flatten(1)], dim=-1)
        return out.reshape(*lead, self.out_dim) if len(lead) != 1 else out

    def forward_jacobian(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x (N, 3) -> output (N, out_dim) and its Jacobian (N, 3, out_dim) in closed form.

        The trilinear weights' derivatives along each axis (differences of the corner
        values, interpolated along the other two axes), times d pos / d x = res_l / (2 bound)
        where x lies inside the grid's box (0 where the clamp holds it, as autograd says);
        inactive levels have zero value and zero derivative.
        """
        weights = self._level_weights(x)
        raw, pos, frac, v = self._corners(x)
        feats, dfeats = _trilinear_and_derivative(v, frac)  # (N, L, F), (N, L, 3, F)
        gain = self.half_res.to(x.dtype)  # (L, 1): d pos / d x inside the box
        if self.bound != 1.0:
            gain = gain / self.bound
        if weights is not None:
            feats = feats * weights
            gain = gain * weights
        dpos = torch.where(raw == pos, gain, 0.0)  # (N, L, 3): 0 where the clamp holds
        dfeats = (dfeats * dpos[..., None]).transpose(1, 2).flatten(2)  # (N, 3, L * F)
        vals, jacs = [], []
        if self.raw_dims:
            vals.append(x)
            jacs.append(_eye_jacobian(x))
        if self.bands is not None:
            bv, bj = self.bands.forward_jacobian(x)
            vals.append(bv)
            jacs.append(bj)
        return (torch.cat([*vals, feats.flatten(1)], dim=-1),
                torch.cat([*jacs, dfeats], dim=-1))


def _trilinear(v: Tensor, frac: Tensor) -> Tensor:
    """Trilinear interpolation of the 8 corners (x major, then y, then z).

    Three rounds of `lerp` (one fused op each, and so is its derivative: about 3x cheaper on
    the CPU than forming the 8 weights and a weighted sum, in the forward and both backwards).

    Args:
        v: (N, L, 8, F) corner values; frac: (N, L, 3) position in the cell.

    Returns:
        (N, L, F).
    """
    n, lv, _, nf = v.shape
    fx, fy, fz = frac.unsqueeze(-1).unbind(2)  # (N, L, 1) each
    lo, hi = v.view(n, lv, 2, 4 * nf).unbind(2)
    v = torch.lerp(lo, hi, fx)  # (N, L, 4 F) over x: corners (y, z) x features
    lo, hi = v.view(n, lv, 2, 2 * nf).unbind(2)
    v = torch.lerp(lo, hi, fy)  # (N, L, 2 F) over y
    lo, hi = v.view(n, lv, 2, nf).unbind(2)
    return torch.lerp(lo, hi, fz)  # (N, L, F) over z


def _trilinear_and_derivative(v: Tensor, frac: Tensor) -> tuple[Tensor, Tensor]:
    """Trilinear interpolation and its derivative wrt the position in the cell.

    Each round interpolates the values and the derivatives of the previous rounds along
    its axis (``lo + f (hi - lo)``), and its own axis's derivative is ``hi - lo``.

    Args:
        v: (N, L, 8, F) corner values (x major, then y, then z); frac: (N, L, 3).

    Returns:
        value (N, L, F) and derivative (N, L, 3, F) along x, y, z.
    """
    n, lv, _, nf = v.shape
    fx, fy, fz = frac[..., None, None].unbind(2)  # (N, L, 1, 1) each
    lo, hi = v.view(n, lv, 2, 4, nf).unbind(2)
    d = hi - lo  # (N, L, 4, F): d/dfx
    a = torch.cat([torch.addcmul(lo, fx, d), d], dim=-1)  # (N, L, 4, 2F): value, d/dfx
    lo, hi = a.view(n, lv, 2, 2, 2 * nf).unbind(2)
    d = hi - lo
    a = torch.cat([torch.addcmul(lo, fy, d), d[..., :nf]], dim=-1)  # (N, L, 2, 3F)
    lo, hi = a.unbind(2)
    d = hi - lo
    a = torch.cat([torch.addcmul(lo, fz[:, :, 0], d), d[..., :nf]], dim=-1)  # (N, L, 4F)
    a = a.view(n, lv, 4, nf)  # value, d/dfx, d/dfy, d/dfz
    return a[:, :, 0], a[:, :, 1:]


def build_encoding(cfg: EncodingConfig, in_dim: int) -> Encoding:
    """The encoding that `cfg.kind` names, for inputs of `in_dim` channels."""
    if cfg.kind == "identity" or (cfg.kind == "frequency" and cfg.n_freqs == 0
                                  and cfg.include_input):
        return IdentityEncoding(in_dim)
    if cfg.kind == "frequency":
        return FrequencyEncoding(in_dim, cfg.n_freqs, cfg.include_input)
    if cfg.kind == "hashgrid":
        return HashGridEncoding(cfg, in_dim)
    raise ValueError(f"unknown encoding kind {cfg.kind!r}")


def hashgrid_per_level_scale(cfg: EncodingConfig) -> float:
    """`cfg.per_level_scale`, or (when it is 0) the scale that reaches `finest_resolution`
    at the last level: (finest / base)^(1 / (n_levels - 1))."""
    if cfg.per_level_scale > 0:
        return cfg.per_level_scale
    if cfg.n_levels <= 1:
        return 1.0
    return math.exp(math.log(cfg.finest_resolution / cfg.base_resolution) / (cfg.n_levels - 1))
