"""NeuS's up-sampling with the fine-sample draw as an object: the samplers and their registry.

NeuS refines the coarse samples of a ray in rounds: at a fixed sharpness ``inv_s = base *
2^round`` it turns the SDF at the current samples into weights of the sections
``[z_j, z_{j+1}]`` (`upsample_section_weights`, a `Sections`), draws new samples from them,
and merges. The draw is a `Sampler`, chosen by name from one registry (`SAMPLERS`) and built
once from a `neus_l0.config.schema.SamplerConfig` (`build_sampler`):

* ``hvs``: NeuS's own piecewise-constant inverse CDF of the section weights (`sample_pdf`);
* ``l0``, ``l0-inverse``, ``l0-linear``: the L0-Sampler (`sample_l0`) with exponential /
  inverse / linear interpolation of point weights made from the section weights
  (`section_to_point_weights`), after maxblur with a pad (absolute, relative or none);
* ``neus-exact``: the section weights as masses, and inside each section the exact CDF of
  NeuS's opacity with its linear SDF estimate (`sample_neus_sections`).

`up_sample` runs the rounds with any SDF function, so the same code serves training (the SDF
network) and the oracle study (analytic SDFs, `neus_l0.experiments.oracle`). The module is a leaf
above `neus_l0.sampling.kernels`: it knows no networks and no configs beyond
`SamplerConfig`'s fields.

Shapes: B rays, N samples per ray (sorted), n samples drawn per round.

The draws call the kernels with ``check=False``: the sections' ends are sorted and finite by
construction (sorted coarse positions, each round merged by one sort), and checking them
would put a host synchronisation into the training step.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Protocol

import torch
import torch.nn.functional as F
from torch import Tensor

from neus_l0.config.schema import MASSES, PAD_MODES, PLACEMENTS, SAMPLERS, SamplerConfig
from neus_l0.sampling.kernels import (
    quantiles,
    sample_l0,
    sample_l0_sections,
    sample_neus_sections,
    sample_pdf,
    sanitize_weights,
)

# ------------------------------------------------------------------------------------------
# NeuS's up-sampling pieces (pure functions).


@dataclasses.dataclass
class Sections:
    """NeuS's sections of a ray at one up-sampling round.

    Attributes:
        z: (B, N) sorted section ends.
        weights: (B, N-1) section weights (alpha times transmittance).
        prev_sdf: (B, N-1) NeuS's linear SDF estimate at the start of each section
            (its ``prev_esti``), or None until `estimates` computes it.
        next_sdf: (B, N-1) the estimate at the end (``next_esti``); <= prev_sdf; or None.
        inv_s: the fixed logistic sharpness of the round.
        dist: (B, N-1) the sections' lengths ``z[:, 1:] - z[:, :-1]``, or None (then a
            sampler that needs them computes them).
        u: (B, n) the deterministic quantiles of a draw of n samples, or None (a draw of
            another size, or without them, makes its own); `up_sample` makes them once.
        twice: (2 prev_sdf, 2 next_sdf), which `upsample_section_weights` computes on the
            way; `estimates` halves them only for a draw that reads them (hvs does not).
    """

    z: Tensor
    weights: Tensor
    prev_sdf: Tensor | None
    next_sdf: Tensor | None
    inv_s: float
    dist: Tensor | None = None
    u: Tensor | None = None
    twice: tuple[Tensor, Tensor] | None = None

    def lengths(self) -> Tensor:
        """(B, N-1) the sections' lengths (`dist`, or computed)."""
        return self.dist if self.dist is not None else self.z[:, 1:] - self.z[:, :-1]

    def estimates(self) -> tuple[Tensor, Tensor]:
        """(prev_sdf, next_sdf), (B, N-1) each, halved from `twice` on first use."""
        if self.prev_sdf is None or self.next_sdf is None:
            if self.twice is None:
                raise ValueError("Sections without SDF estimates")
            self.prev_sdf, self.next_sdf = 0.5 * self.twice[0], 0.5 * self.twice[1]
        return self.prev_sdf, self.next_sdf

    def quantiles(self, n_samples: int) -> Tensor | None:
        """`u` when it holds n_samples quantiles per ray, else None."""
        return self.u if self.u is not None and self.u.shape[-1] == n_samples else None


def transmittance(alpha: Tensor) -> Tensor:
    """Exclusive cumulative product of (1 - alpha + 1e-7) along the last axis (NeuS's).

    Its backward is `_ExclusiveCumprod`'s (7 ops, where autograd's cumprod backward
    dispatches 34 to allow zero factors, which alpha <= 1 never gives).

    Args:
        alpha: (B, N) in [0, 1].

    Returns:
        (B, N) transmittance before each sample.
    """
    keep = 1.0 - alpha + 1e-7  # (B, N) >= 1e-7 > 0
    if not keep.requires_grad:
        return _exclusive_cumprod(keep)
    return _ExclusiveCumprod.apply(keep)


def _exclusive_cumprod(keep: Tensor) -> Tensor:
    """(B, N) -> (B, N): ``out_i = prod_{j < i} keep_j`` (out_0 = 1)."""
    return torch.cumprod(F.pad(keep[:, :-1], (1, 0), value=1.0), dim=-1)


class _ExclusiveCumprod(torch.autograd.Function):
    """`_exclusive_cumprod` of positive factors, with the backward in closed form:
    ``d loss / d keep_j = (sum_{i > j} g_i out_i) / keep_j`` (a reversed cumulative sum)."""

    @staticmethod
    def forward(keep: Tensor) -> Tensor:
        return _exclusive_cumprod(keep)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.save_for_backward(inputs[0], output)

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        keep, out = ctx.saved_tensors
        after = torch.flip(torch.cumsum(torch.flip(grad * out, [-1]), dim=-1), [-1])  # i >= j
        return F.pad(after[:, 1:], (0, 1)) / keep  # i > j


def upsample_section_weights(z: Tensor, sdf: Tensor, radius: Tensor | None,
                             inv_s: float) -> Sections:
    """NeuS's up-sampling weights of the sections [z_j, z_{j+1}] at a fixed sharpness.

    The slope of each section is the smaller (steeper descent) of its own and the previous
    section's, clipped to [-1e3, 0], and zero for sections entirely outside the unit sphere.
    The estimates are formed doubled (``2 mid -+ 2 half``, exact in floating point), and
    `inv_s / 2` scales them: the same numbers as NeuS's in fewer ops.

    Args:
        z: (B, N) sorted positions; sdf: (B, N) SDF there; radius: (B, N) distance to the
            origin there, or None when every z is inside the unit sphere (rays culled to
            its chord: no section is outside).
        inv_s: the fixed logistic sharpness (NeuS: 64 * 2^round).

    Returns:
        The `Sections`: weights (alpha times transmittance), (B, N-1), and the doubled
        estimates (`Sections.estimates` halves them).
    """
    prev_sdf, next_sdf = sdf[:, :-1], sdf[:, 1:]
    dist = z[:, 1:] - z[:, :-1]
    cos_val = (next_sdf - prev_sdf) / (dist + 1e-5)
    prev_cos = F.pad(cos_val[:, :-1], (1, 0))  # the previous section's (0 before the first)
    cos_val = torch.minimum(prev_cos, cos_val).clip(-1e3, 0.0)
    if radius is not None:
        cos_val = cos_val * (torch.minimum(radius[:, :-1], radius[:, 1:]) < 1.0)  # either end
    mid2 = prev_sdf + next_sdf  # 2 mid_sdf
    half2 = cos_val * dist  # 2 half
    prev2, next2 = mid2 - half2, mid2 + half2
    prev_cdf = torch.sigmoid(prev2 * (0.5 * inv_s))
    next_cdf = torch.sigmoid(next2 * (0.5 * inv_s))
    alpha = (prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)
    return Sections(z, alpha * transmittance(alpha), None, None, float(inv_s), dist=dist,
                    twice=(prev2, next2))


def section_to_point_weights(z: Tensor, section_weights: Tensor, placement: str = "midpoint",
                             as_density: bool = True) -> tuple[Tensor, Tensor]:
    """Turn weights of sections [z_j, z_{j+1}] into weights at points for the L0-Sampler.

    Args:
        z: (B, N) sorted section ends.
        section_weights: (B, N-1).
        placement: ``midpoint`` (t = section midpoints, N-1 points) or ``endpoint``
            (t = z, each point the mean of its adjacent sections, edges replicated).
        as_density: divide by the section length (times the mean length, so uniform
            sections are unchanged); lengths below 1e-3 of the mean count as 1e-3 of it.

    Returns:
        t (B, M) sorted positions and weights (B, M), M = N-1 or N.
    """
    w = section_weights
    if as_density:
        length = z[:, 1:] - z[:, :-1]  # (B, N-1)
        mean = length.mean(dim=-1, keepdim=True)
        w = w * mean / torch.maximum(length, 1e-3 * mean)
    if placement == "midpoint":
        return 0.5 * (z[:, 1:] + z[:, :-1]), w
    if placement == "endpoint":
        padded = torch.cat([w[:, :1], w, w[:, -1:]], dim=-1)  # (B, N+1)
        return z, 0.5 * (padded[:, 1:] + padded[:, :-1])
    raise ValueError(f"unknown point-weight placement {placement!r}")


class Sampler(Protocol):
    """The fine-sample draw of one up-sampling round.

    Attributes:
        name: the registry name it was built from.
        base_inv_s: NeuS's sharpness of the first round (round i uses base * 2^i).
    """

    name: str
    base_inv_s: float

    def draw(self, sections: Sections, n_samples: int) -> Tensor:
        """(B, n_samples) new positions, sorted, detached, inside [z_0, z_{N-1}]."""


@dataclasses.dataclass(frozen=True)
class HVSSampler:
    """NeuS's draw: the piecewise-constant inverse CDF of the section weights."""

    name: str = "hvs"
    base_inv_s: float = 64.0

    def draw(self, sections: Sections, n_samples: int) -> Tensor:
        """Deterministic `sample_pdf` on the sections; (B, n_samples)."""
        return sample_pdf(sections.z, sections.weights, n_samples, det=True,
                          u=sections.quantiles(n_samples), lengths=sections.dist, check=False)


@dataclasses.dataclass(frozen=True)
class NeuSExactSampler:
    """Section masses, then the exact CDF of NeuS's opacity inside each section."""

    name: str = "neus-exact"
    base_inv_s: float = 64.0

    def draw(self, sections: Sections, n_samples: int) -> Tensor:
        """Deterministic `sample_neus_sections` at the round's sharpness; (B, n_samples)."""
        prev_sdf, next_sdf = sections.estimates()
        return sample_neus_sections(sections.z, sections.weights, prev_sdf, next_sdf,
                                    sections.inv_s, n_samples, det=True, check=False)


class L0Sampler:
    """The L0-Sampler on point weights made from NeuS's section weights.

    The pad of maxblur is scaled by ``pad_mode``: ``absolute`` adds ``pad`` to the point
    weights as they are (NeuS's section weights sum to at most 1, so the pad's share of the
    samples grows as the ray's weight shrinks); ``relative`` adds ``pad`` times the ray's
    mean point weight (implemented by dividing each ray's weights by their mean first, which
    changes nothing else, since the draw does not depend on the weights' scale), so the pad
    holds at most a fraction ``pad / (1 + pad)`` of the draw whatever the weights; ``none``
    adds nothing. Without blur the pad is added to the point weights directly.

    Args:
        name: the registry name. kind: ``exp``, ``inverse`` or ``linear``.
        pad, pad_mode, blur: maxblur's pad, how it scales, and whether to blur at all.
        placement, as_density: see `section_to_point_weights`.
        base_inv_s: NeuS's first-round sharpness.
        masses: ``sections`` (the default: NeuS's section weights decide the shares, the
            interpolant only the place inside a section: `sample_l0_sections`; placement,
            as_density, blur and pad are then unused) or ``interpolant`` (the interpolant's
            mass decides each stretch's share, the paper's draw: `sample_l0`).
    """

    def __init__(self, name: str = "l0", kind: str = "exp", pad: float = 0.0,
                 pad_mode: str = "relative", blur: bool = False, placement: str = "midpoint",
                 as_density: bool = True, base_inv_s: float = 64.0,
                 masses: str = "sections"):
        if masses not in MASSES:
            raise ValueError(f"unknown L0 masses {masses!r} (choose from {MASSES})")
        if pad_mode not in PAD_MODES:
            raise ValueError(f"unknown pad mode {pad_mode!r} (choose from {PAD_MODES})")
        if placement not in PLACEMENTS:
            raise ValueError(f"unknown placement {placement!r} (choose from {PLACEMENTS})")
        self.name, self.kind, self.base_inv_s = name, kind, float(base_inv_s)
        self.pad = 0.0 if pad_mode == "none" else float(pad)
        self.pad_mode, self.blur = pad_mode, blur
        self.placement, self.as_density, self.masses = placement, as_density, masses
        self._draw = sample_l0

    def __repr__(self) -> str:
        return (f"L0Sampler(name={self.name!r}, kind={self.kind!r}, pad={self.pad}, "
                f"pad_mode={self.pad_mode!r}, blur={self.blur}, placement={self.placement!r}, "
                f"as_density={self.as_density}, masses={self.masses!r}, "
                f"base_inv_s={self.base_inv_s})")

    def point_weights(self, sections: Sections) -> tuple[Tensor, Tensor]:
        """The nodes and weights the L0 interpolation runs on, before maxblur; (B, M) each.

        Without a pad the draw does not depend on each ray's scale of the weights (they are
        divided by their maximum), so the mean-length factor of ``as_density`` and the
        ``relative`` division by the mean are left out there (fewer ops, same samples to
        rounding; a ray holding a non-finite weight then loses that weight only, where
        the division by its non-finite mean made it uniform).
        """
        if self.pad == 0.0 and self.placement == "midpoint":
            length = sections.lengths()  # (B, N-1)
            w = sections.weights
            if self.as_density:
                w = w / torch.maximum(length, 1e-3 * length.mean(dim=-1, keepdim=True))
            return torch.add(sections.z[:, :-1], length, alpha=0.5), w
        t, w = section_to_point_weights(sections.z, sections.weights, self.placement,
                                        self.as_density)
        if self.pad_mode == "relative":
            mean = w.mean(dim=-1, keepdim=True)  # (B, 1)
            w = w / torch.where(mean > 0, mean, 1.0)
        if not self.blur and self.pad > 0:  # no maxblur to add the pad: add it here
            w = sanitize_weights(w) + self.pad
        return t, w

    def draw(self, sections: Sections, n_samples: int) -> Tensor:
        """Deterministic `sample_l0` on the point weights (or `sample_l0_sections` on the
        sections); (B, n_samples)."""
        if self.masses == "sections":
            return sample_l0_sections(sections.z, sections.weights, n_samples, self.kind,
                                      u=sections.quantiles(n_samples), check=False)
        t, w = self.point_weights(sections)
        return self._draw(t, w, n_samples, kind=self.kind, det=True, blur=self.blur,
                          pad=self.pad, u=sections.quantiles(n_samples), check=False)


def _l0(cfg: SamplerConfig) -> L0Sampler:
    o = cfg.l0
    return L0Sampler(cfg.name, cfg.l0_kind(), o.pad, o.pad_mode, o.blur, o.placement,
                     o.as_density, cfg.base_inv_s, o.masses)


#: The one registry of sampler names: name -> builder from a `SamplerConfig`.
REGISTRY: dict[str, Callable[[SamplerConfig], Sampler]] = {
    "hvs": lambda cfg: HVSSampler(base_inv_s=cfg.base_inv_s),
    "l0": _l0,
    "l0-inverse": _l0,
    "l0-linear": _l0,
    "neus-exact": lambda cfg: NeuSExactSampler(base_inv_s=cfg.base_inv_s),
}
if tuple(REGISTRY) != SAMPLERS:  # the config's choice list and the registry are one list
    raise ImportError(f"sampler registry {tuple(REGISTRY)} differs from the config's "
                      f"choices {SAMPLERS} (neus_l0.config.schema.SAMPLERS)")


def build_sampler(cfg: SamplerConfig | str) -> Sampler:
    """Build the sampler a `SamplerConfig` (or a bare name, with defaults) describes."""
    if isinstance(cfg, str):
        cfg = SamplerConfig(name=cfg)
    if cfg.name not in REGISTRY:
        raise ValueError(f"unknown sampler {cfg.name!r} (choose from {', '.join(SAMPLERS)})")
    return REGISTRY[cfg.name](cfg)


# ------------------------------------------------------------------------------------------
# The rounds.


def up_sample(sdf_fn: Callable[[Tensor], Tensor], origins: Tensor, dirs: Tensor, z: Tensor,
              sampler: Sampler, n_importance: int, steps: int,
              in_sphere: bool = False) -> tuple[Tensor, Tensor]:
    """NeuS's coarse-to-fine rounds (no gradient), drawing with `sampler`.

    Round i computes the `Sections` at ``inv_s = sampler.base_inv_s * 2^i`` and draws
    ``n_importance / steps`` new samples; the SDF is evaluated at the new samples of every
    round but the last.

    Args:
        sdf_fn: maps (P, 3) points to (P,) SDF values (cast to z's dtype).
        origins, dirs: (B, 3).
        z: (B, n_samples) sorted coarse positions.
        sampler: the draw (see `build_sampler`).
        n_importance: fine samples in total (a multiple of `steps`).
        steps: rounds.
        in_sphere: every z lies on the rays' chords of the unit sphere (culled rays), so
            no section is outside it and the distances to the origin are not needed.

    Returns:
        z_all: (B, n_samples + n_importance) sorted positions; z_new: (B, n_importance) the
        up-sampled positions alone, in the order drawn (sorted within each round).
    """
    if n_importance == 0 or steps == 0:
        return z, z[:, :0]
    per_round = n_importance // steps
    B = z.shape[0]
    o, d = origins[:, None, :], dirs[:, None, :]  # (B, 1, 3)

    def sdf_at(t: Tensor) -> tuple[Tensor, Tensor | None]:
        """(B, n) positions -> the SDF and (unless `in_sphere`) the distance to the origin
        there, (B, n) each."""
        pts = torch.addcmul(o, d, t[..., None])  # (B, n, 3)
        sdf = sdf_fn(pts.view(-1, 3)).to(t.dtype).view(B, t.shape[1])
        return sdf, None if in_sphere else pts.norm(dim=-1)

    new_all = []
    with torch.no_grad():
        u = quantiles((B,), per_round, True, None, z.dtype, z.device)  # shared by the rounds
        sdf, radius = sdf_at(z)
        for i in range(steps):
            sections = upsample_section_weights(z, sdf, radius, sampler.base_inv_s * 2**i)
            sections.u = u
            new_z = sampler.draw(sections, per_round)  # (B, per_round)
            new_all.append(new_z)
            z, order = torch.sort(torch.cat([z, new_z], dim=-1), dim=-1)  # one sort a round
            if i + 1 < steps:  # the values follow the same order
                new_sdf, new_radius = sdf_at(new_z)
                sdf = torch.gather(torch.cat([sdf, new_sdf], dim=-1), -1, order)
                if radius is not None and new_radius is not None:
                    radius = torch.gather(torch.cat([radius, new_radius], dim=-1), -1, order)
    return z, torch.cat(new_all, dim=-1)
