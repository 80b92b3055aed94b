"""NeuS volume rendering: sphere bounds, coarse-to-fine up-sampling, unbiased compositing.

The draw of the fine samples in each up-sampling round is made by a sampler chosen by name
(`SAMPLERS`): ``hvs`` is NeuS's own piecewise-constant inverse CDF
(`neus_l0.sampling.sample_pdf`), ``l0`` / ``l0-inverse`` / ``l0-linear`` are the L0-Sampler
with exponential / inverse / linear interpolation (`neus_l0.sampling.sample_l0`).

Section weights to point weights (L0 only). NeuS's up-sampling weights ``w_j`` belong to the
sections ``[z_j, z_{j+1}]``; the L0-Sampler interpolates weights given *at points*. We first
turn each section weight into a density, ``w_j * mean(D) / D_j`` with ``D_j`` the section
length (``render.weights_as_density``; on the uniform first round this is the identity, and
after it the sections near the surface are short, so their raw weights understate the
density there by the ratio of lengths), then place these values either at the section
midpoints (``render.point_weights = "midpoint"``, the default) or average the two sections
adjacent to each ``z_j`` (``"endpoint"``). The midpoint placement is the default because it
keeps the peak of a sharp surface response at one node instead of spreading it over two
intervals (the average acts as an extra blur on top of the sampler's maxblur), and its
samples stay inside the sections that carry the weight; in the sphere test
(`tests/test_rendering.py`) it gives fine samples at least as tight around the surface as
``endpoint``. The only cost is that the outer halves of the first and last section cannot
receive samples, which lie far from any surface inside the unit sphere.

Shapes: B rays, N samples per ray along the fine (sorted) `z_vals`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Protocol

import torch
import torch.nn.functional as F
from torch import Tensor

from neus_l0.config import RenderConfig
from neus_l0.fields import NeuSModel, sdf_and_gradient
from neus_l0.sampling import sample_l0, sample_pdf

#: Sampler names and the `sample_l0` kind each uses (None: NeuS's piecewise constant).
SAMPLER_KINDS: dict[str, str | None] = {
    "hvs": None,
    "l0": "exp",
    "l0-inverse": "inverse",
    "l0-linear": "linear",
}
SAMPLERS = tuple(SAMPLER_KINDS)


# ------------------------------------------------------------------------------------------
# Pure functions.


def near_far_from_sphere(origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
    """NeuS's bounds: the chord of the unit sphere centred on the ray's closest point.

    Args:
        origins: (B, 3); dirs: (B, 3).

    Returns:
        near, far: (B, 1) with far - near = 2.
    """
    a = (dirs * dirs).sum(-1, keepdim=True)  # (B, 1)
    b = 2.0 * (origins * dirs).sum(-1, keepdim=True)  # (B, 1)
    mid = -0.5 * b / a
    return mid - 1.0, mid + 1.0


def coarse_z_vals(near: Tensor, far: Tensor, n_samples: int, perturb: bool,
                  generator: torch.Generator | None = None,
                  noise: Tensor | None = None) -> Tensor:
    """Uniform samples in [near, far], shifted by one random offset per ray if `perturb`.

    Args:
        near, far: (B, 1).
        n_samples: samples per ray.
        perturb: jitter by U(-0.5, 0.5) * (far - near) / n_samples (NeuS's 2 / n_samples).
        generator: random source for the jitter.
        noise: (B, 1) pre-drawn U(0, 1) (instead of drawing from `generator`).

    Returns:
        (B, n_samples) sorted.
    """
    lin = torch.linspace(0.0, 1.0, n_samples, device=near.device, dtype=near.dtype)
    z = near + (far - near) * lin  # (B, n)
    if perturb:
        r = noise if noise is not None else torch.rand(
            near.shape, generator=generator, device=near.device, dtype=near.dtype)
        z = z + (r - 0.5) * (far - near) / n_samples
    return z


def outside_z_vals(far: Tensor, n_outside: int, n_samples: int, perturb: bool,
                   generator: torch.Generator | None = None,
                   noise: Tensor | None = None) -> Tensor:
    """NeuS's background samples beyond `far`, uniform in inverse depth.

    Args:
        far: (B, 1).
        n_outside: samples per ray.
        n_samples: coarse samples (sets the gap 1 / n_samples after `far`).
        perturb: stratified jitter within each stratum.
        generator: random source.
        noise: (B, n_outside) pre-drawn U(0, 1) (instead of drawing from `generator`).

    Returns:
        (B, n_outside) sorted, all > far.
    """
    B = far.shape[0]
    s = torch.linspace(1e-3, 1.0 - 1.0 / (n_outside + 1.0), n_outside, device=far.device,
                       dtype=far.dtype).expand(B, n_outside)
    if perturb:
        mids = 0.5 * (s[:, 1:] + s[:, :-1])
        upper = torch.cat([mids, s[:, -1:]], -1)
        lower = torch.cat([s[:, :1], mids], -1)
        r = noise if noise is not None else torch.rand(
            s.shape, generator=generator, device=far.device, dtype=far.dtype)
        s = lower + (upper - lower) * r
    return far / torch.flip(s, dims=[-1]) + 1.0 / n_samples


def upsample_section_weights(z: Tensor, sdf: Tensor, radius: Tensor, inv_s: float) -> Tensor:
    """NeuS's up-sampling weights of the sections [z_j, z_{j+1}] at a fixed sharpness.

    The slope of each section is the smaller (steeper descent) of its own and the previous
    section's, clipped to [-1e3, 0], and zero for sections entirely outside the unit sphere.

    Args:
        z: (B, N) sorted positions; sdf: (B, N) SDF there; radius: (B, N) distance to the
            origin there.
        inv_s: the fixed logistic sharpness (NeuS: 64 * 2^round).

    Returns:
        (B, N-1) section weights (alpha times transmittance).
    """
    inside = (radius[:, :-1] < 1.0) | (radius[:, 1:] < 1.0)  # (B, N-1)
    prev_sdf, next_sdf = sdf[:, :-1], sdf[:, 1:]
    dist = z[:, 1:] - z[:, :-1]
    mid_sdf = 0.5 * (prev_sdf + next_sdf)
    cos_val = (next_sdf - prev_sdf) / (dist + 1e-5)
    prev_cos = torch.cat([torch.zeros_like(cos_val[:, :1]), cos_val[:, :-1]], dim=-1)
    cos_val = torch.minimum(prev_cos, cos_val).clip(-1e3, 0.0) * inside
    prev_esti = mid_sdf - cos_val * dist * 0.5
    next_esti = mid_sdf + cos_val * dist * 0.5
    prev_cdf = torch.sigmoid(prev_esti * inv_s)
    next_cdf = torch.sigmoid(next_esti * inv_s)
    alpha = (prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)
    return alpha * transmittance(alpha)


def transmittance(alpha: Tensor) -> Tensor:
    """Exclusive cumulative product of (1 - alpha + 1e-7) along the last axis (NeuS's).

    Args:
        alpha: (B, N).

    Returns:
        (B, N) transmittance before each sample.
    """
    ones = torch.ones_like(alpha[:, :1])
    return torch.cumprod(torch.cat([ones, 1.0 - alpha + 1e-7], dim=-1), dim=-1)[:, :-1]


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


_COMPILED: dict = {}


def compiled_sample_l0():
    """`sample_l0` through `torch.compile` (compiled once per process, dynamic shapes)."""
    if "l0" not in _COMPILED:
        _COMPILED["l0"] = torch.compile(sample_l0, dynamic=True)
    return _COMPILED["l0"]


def draw_fine_samples(z: Tensor, section_weights: Tensor, n_samples: int, sampler: str,
                      placement: str = "midpoint", as_density: bool = True,
                      pad: float = 0.01, compiled: bool = False) -> Tensor:
    """Draw one round of fine samples (deterministic, as NeuS) with the named sampler.

    Args:
        z: (B, N) sorted positions; section_weights: (B, N-1).
        n_samples: samples to draw per ray.
        sampler: one of `SAMPLERS`.
        placement, as_density: see `section_to_point_weights` (L0 samplers only).
        pad: maxblur padding of the L0 samplers.
        compiled: draw with `compiled_sample_l0` (``l0`` and ``l0-linear`` only; same
            result to float rounding). ``l0-inverse`` always draws eagerly: compiled, its
            all-zero rays came out non-finite (inductor reorders its spike arithmetic).

    Returns:
        (B, n_samples) sorted, detached, inside the range of the nodes.
    """
    if sampler not in SAMPLER_KINDS:
        raise ValueError(f"unknown sampler {sampler!r} (choose from {', '.join(SAMPLERS)})")
    kind = SAMPLER_KINDS[sampler]
    if kind is None:
        return sample_pdf(z, section_weights, n_samples, det=True)
    t, w = section_to_point_weights(z, section_weights, placement, as_density)
    draw = compiled_sample_l0() if compiled and kind in ("exp", "linear") else sample_l0
    return draw(t, w, n_samples, kind=kind, det=True, pad=pad)


def merge_sorted(z: Tensor, new_z: Tensor, values: Tensor | None = None,
                 new_values: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
    """Concatenate and sort positions, carrying per-sample values along.

    Args:
        z: (B, N); new_z: (B, M); values: (B, N) or None; new_values: (B, M) or None.

    Returns:
        (B, N+M) sorted positions and the values in the same order (or None).
    """
    z_all, order = torch.sort(torch.cat([z, new_z], dim=-1), dim=-1)
    if values is None or new_values is None:
        return z_all, None
    return z_all, torch.gather(torch.cat([values, new_values], dim=-1), -1, order)


def cos_anneal_alpha(sdf: Tensor, true_cos: Tensor, dists: Tensor, inv_s: Tensor,
                     cos_anneal_ratio: float) -> Tensor:
    """NeuS's unbiased discrete opacity of the sections around mid-points.

    Args:
        sdf: (B, N) SDF at section midpoints; true_cos: (B, N) dot(dir, gradient);
            dists: (B, N) section lengths; inv_s: (1,) sharpness s.
        cos_anneal_ratio: 0 -> cos relaxed to (cos + 1) / 2 (early training), 1 -> true cos.

    Returns:
        (B, N) alpha in [0, 1].
    """
    iter_cos = -(F.relu(-true_cos * 0.5 + 0.5) * (1.0 - cos_anneal_ratio)
                 + F.relu(-true_cos) * cos_anneal_ratio)  # always <= 0
    next_sdf = sdf + iter_cos * dists * 0.5
    prev_sdf = sdf - iter_cos * dists * 0.5
    prev_cdf = torch.sigmoid(prev_sdf * inv_s)
    next_cdf = torch.sigmoid(next_sdf * inv_s)
    return ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clip(0.0, 1.0)


# ------------------------------------------------------------------------------------------
# Rendering with the networks.


def up_sample(model: NeuSModel, origins: Tensor, dirs: Tensor, z: Tensor, cfg: RenderConfig,
              sampler: str) -> tuple[Tensor, Tensor]:
    """NeuS's coarse-to-fine rounds (no gradient); the draw uses `sampler`.

    Args:
        model: the networks (only `model.sdf` is used).
        origins, dirs: (B, 3).
        z: (B, n_samples) coarse positions.
        cfg: `n_importance`, `up_sample_steps`, and the point-weight options.
        sampler: one of `SAMPLERS`.

    Returns:
        z_all: (B, n_samples + n_importance) sorted positions; z_new: (B, n_importance)
        the up-sampled positions alone, in the order drawn (sorted within each round).
    """
    steps = cfg.up_sample_steps
    if cfg.n_importance == 0 or steps == 0:
        return z, z[:, :0]
    per_round = cfg.n_importance // steps
    B = z.shape[0]
    new_all = []
    with torch.no_grad():
        pts = origins[:, None, :] + dirs[:, None, :] * z[..., None]  # (B, N, 3)
        sdf = model.sdf.sdf(pts.reshape(-1, 3)).float().reshape(B, z.shape[1])
        radius = pts.norm(dim=-1)
        for i in range(steps):
            w = upsample_section_weights(z, sdf, radius, 64.0 * 2**i)  # (B, N-1)
            new_z = draw_fine_samples(z, w, per_round, sampler, cfg.point_weights,
                                      cfg.weights_as_density, cfg.l0_pad,
                                      cfg.compile_sampler)
            new_all.append(new_z)
            if i + 1 == steps:
                z, _ = merge_sorted(z, new_z)
            else:
                new_pts = origins[:, None, :] + dirs[:, None, :] * new_z[..., None]
                new_sdf = model.sdf.sdf(new_pts.reshape(-1, 3)).float().reshape(B, per_round)
                z_all, sdf = merge_sorted(z, new_z, sdf, new_sdf)
                _, radius = merge_sorted(z, new_z, radius, new_pts.norm(dim=-1))
                z = z_all
    return z, torch.cat(new_all, dim=-1)


def background_alpha_color(model: NeuSModel, origins: Tensor, dirs: Tensor, z: Tensor,
                           sample_dist: float) -> tuple[Tensor, Tensor]:
    """The background model's alpha and colour at the midpoints of sections of `z`.

    Args:
        z: (B, M) sorted positions (inside and outside samples together).
        sample_dist: length given to the last section.

    Returns:
        alpha (B, M) and colour (B, M, 3).
    """
    B, M = z.shape
    dists = torch.cat([z[:, 1:] - z[:, :-1], torch.full_like(z[:, :1], sample_dist)], dim=-1)
    mid = z + 0.5 * dists
    pts = origins[:, None, :] + dirs[:, None, :] * mid[..., None]  # (B, M, 3)
    d = dirs[:, None, :].expand(B, M, 3)
    sigma, rgb = model.background(pts.reshape(-1, 3), d.reshape(-1, 3))
    sigma, rgb = sigma.float(), rgb.float()
    alpha = 1.0 - torch.exp(-sigma.reshape(B, M) * dists)
    return alpha, rgb.reshape(B, M, 3)


def sphere_chord(origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Where each ray is inside the unit sphere.

    Args:
        origins: (B, 3); dirs: (B, 3) unit.

    Returns:
        t_in, t_out: (B, 1) the chord's ends, clamped to t >= 0 (NeuS's near / far,
        ``mid -+ 1``, for rays that miss); hits: (B,) bool, whether the ray meets the
        sphere in front of its origin.
    """
    near, far = near_far_from_sphere(origins, dirs)
    mid = 0.5 * (near + far)  # (B, 1) closest approach
    closest = origins + mid * dirs
    half2 = 1.0 - (closest * closest).sum(-1, keepdim=True)  # (B, 1)
    half = half2.clamp_min(0.0).sqrt()
    t_in, t_out = (mid - half).clamp_min(0.0), mid + half
    hits = (half2[:, 0] > 0.0) & (t_out[:, 0] > 0.0)
    t_in = torch.where(hits[:, None], t_in, near)
    t_out = torch.where(hits[:, None], t_out, far)
    return t_in, t_out, hits


class RayBounds(Protocol):
    """Something that narrows rays' [near, far] to where the surface can be.

    `neus_l0.occupancy.OccupancyGrid` and `neus_l0.hull.VisualHull` are ones. Fixed shapes:
    no boolean indexing, no host synchronisation.
    """

    def ray_bounds(self, origins: Tensor, dirs: Tensor, near: Tensor,
                   far: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """origins, dirs (B, 3); near, far (B, 1) -> lo, hi (B, 1), hits (B,) bool."""
        ...


def ray_bounds(origins: Tensor, dirs: Tensor, cfg: RenderConfig,
               bounds: Sequence[RayBounds] = ()) -> tuple[Tensor, Tensor, Tensor]:
    """Where each ray's samples go, and whether it gets any.

    Without culling (`cfg.cull_outside_sphere` off and no `bounds`): NeuS's [mid - 1,
    mid + 1] for every ray. Otherwise the chord of the unit sphere, narrowed in turn by each
    of `bounds`; a ray that misses the sphere or any of them is inactive.

    Args:
        origins, dirs: (B, 3) unit `dirs`.
        cfg: `cull_outside_sphere`.
        bounds: narrowing objects (visual hull, occupancy grid), applied in order.

    Returns:
        near, far: (B, 1) with far > near; active: (B,) bool.
    """
    if not cfg.cull_outside_sphere and not bounds:
        near, far = near_far_from_sphere(origins, dirs)
        return near, far, torch.ones(origins.shape[0], dtype=torch.bool, device=near.device)
    near, far, active = sphere_chord(origins, dirs)
    for b in bounds:
        near, far, hits = b.ray_bounds(origins, dirs, near, far)
        active = active & hits
    far = torch.maximum(far, near + 1e-6)  # a tangent ray still gets a proper interval
    return near, far, active


@dataclasses.dataclass
class RenderNoise:
    """The uniforms one batch's jitter uses, drawn before rendering (a compiled step takes
    tensors, not a generator).

    Attributes:
        coarse: (B, 1) U(0, 1): the coarse samples' shift.
        outside: (B, n_outside) U(0, 1): the background samples' strata, or None.
    """

    coarse: Tensor
    outside: Tensor | None = None


def draw_noise(cfg: RenderConfig, n_rays: int, generator: torch.Generator | None,
               device: torch.device | str) -> RenderNoise:
    """The jitter of a batch of `n_rays` rays (see `RenderNoise`)."""
    coarse = torch.rand((n_rays, 1), generator=generator, device=device)
    outside = (torch.rand((n_rays, cfg.n_outside), generator=generator, device=device)
               if cfg.n_outside > 0 else None)
    return RenderNoise(coarse, outside)


@dataclasses.dataclass
class RenderOutput:
    """What `render_rays` rendered: B rays, N samples each in [near, far].

    Attributes:
        color: (B, 3) composited colour.
        weight_sum: (B, 1) opacity (foreground and background samples).
        depth: (B, 1) the weighted mean of the midpoints inside the unit sphere.
        normal: (B, 3) the weighted sum of gradients inside the sphere (not normalised).
        weights: (B, N [+ n_outside]) compositing weights.
        gradients: (B, N, 3) SDF gradients at the section midpoints.
        eikonal_mask: (B, N) samples the Eikonal term counts (radius < 1.2, active rays).
        t: (B, N) sorted sample positions; t_fine: (B, n_importance) the up-sampled ones
            (sorted within each round); t_mid: (B, N) section midpoints.
        inside_sphere: (B, N) midpoints inside the unit sphere.
        active: (B,) rays that got samples (inactive rays have zero opacity inside
            [near, far]; a background model still renders them).
        s_val: () 1 / s.
    """

    color: Tensor
    weight_sum: Tensor
    depth: Tensor
    normal: Tensor
    weights: Tensor
    gradients: Tensor
    eikonal_mask: Tensor
    t: Tensor
    t_fine: Tensor
    t_mid: Tensor
    inside_sphere: Tensor
    active: Tensor
    s_val: Tensor

    _OLD_NAMES = {"z_vals": "t", "z_fine": "t_fine", "mid_z_vals": "t_mid"}

    def __getitem__(self, key: str) -> Tensor:
        """``out["color"]``; the old dict names (``z_vals``, ``z_fine``, ``mid_z_vals``)."""
        return getattr(self, self._OLD_NAMES.get(key, key))

    def items(self) -> list[tuple[str, Tensor]]:
        """(name, tensor) pairs, as a dict's."""
        return [(f.name, getattr(self, f.name)) for f in dataclasses.fields(self)]


def _foreground(model: NeuSModel, origins: Tensor, dirs: Tensor, near: Tensor, far: Tensor,
                cfg: RenderConfig, sampler: str, cos_anneal_ratio: float | Tensor,
                noise: RenderNoise | None, create_graph: bool) -> dict[str, Tensor]:
    """Samples in [near, far], up-sampling, and the SDF / colour networks on them.

    Args:
        origins, dirs: (B, 3); near, far: (B, 1).

    Returns:
        dict with ``t`` (B, N) sorted, ``t_fine`` (B, n_importance), ``t_mid`` and
        ``dists`` (B, N), ``pts`` (B, N, 3) at the midpoints, ``gradients`` (B, N, 3),
        ``rgb`` (B, N, 3) and ``alpha`` (B, N), all float32 (network outputs are cast back
        from any autocast precision).
    """
    B = origins.shape[0]
    t = coarse_z_vals(near, far, cfg.n_samples, noise is not None,
                      noise=None if noise is None else noise.coarse)
    t, t_fine = up_sample(model, origins, dirs, t, cfg, sampler)
    N = t.shape[1]
    last = (far - near) / cfg.n_samples  # (B, 1) NeuS's 2 / n_samples on its own bounds
    dists = torch.cat([t[:, 1:] - t[:, :-1], last], dim=-1)
    mid = t + 0.5 * dists  # (B, N)
    pts = origins[:, None, :] + dirs[:, None, :] * mid[..., None]  # (B, N, 3)
    d = dirs[:, None, :].expand(B, N, 3)
    out, grad = sdf_and_gradient(model.sdf, pts.reshape(-1, 3), create_graph=create_graph)
    out, grad = out.float(), grad.float()
    sdf = out[:, 0].reshape(B, N)
    gradients = grad.reshape(B, N, 3)
    rgb = model.color(pts.reshape(-1, 3), grad, d.reshape(-1, 3), out[:, 1:])
    rgb = rgb.float().reshape(B, N, 3)
    true_cos = (d * gradients).sum(-1)  # (B, N)
    alpha = cos_anneal_alpha(sdf, true_cos, dists, model.variance.inv_s(), cos_anneal_ratio)
    return {"t": t, "t_fine": t_fine, "dists": dists, "t_mid": mid, "pts": pts,
            "gradients": gradients, "rgb": rgb, "alpha": alpha}


def _with_background(model: NeuSModel, origins: Tensor, dirs: Tensor, fg: dict[str, Tensor],
                     inside: Tensor, far: Tensor, cfg: RenderConfig,
                     noise: RenderNoise | None) -> tuple[Tensor, Tensor]:
    """NeuS's blend: the background model outside the unit sphere and beyond `far`.

    Returns:
        alpha (B, N + n_outside) and rgb (B, N + n_outside, 3).
    """
    N = fg["t"].shape[1]
    t_out = outside_z_vals(far, cfg.n_outside, cfg.n_samples, noise is not None,
                           noise=None if noise is None else noise.outside)
    bg_alpha, bg_rgb = background_alpha_color(model, origins, dirs,
                                              torch.cat([fg["t"], t_out], dim=-1),
                                              2.0 / cfg.n_samples)
    alpha = fg["alpha"] * inside + bg_alpha[:, :N] * (1.0 - inside)
    rgb = fg["rgb"] * inside[..., None] + bg_rgb[:, :N] * (1.0 - inside)[..., None]
    return (torch.cat([alpha, bg_alpha[:, N:]], dim=-1),
            torch.cat([rgb, bg_rgb[:, N:]], dim=1))


def render_rays(model: NeuSModel, origins: Tensor, dirs: Tensor, cfg: RenderConfig,
                sampler: str = "l0", *, cos_anneal_ratio: float | Tensor = 1.0,
                perturb: bool = False, generator: torch.Generator | None = None,
                create_graph: bool = False, occupancy: RayBounds | None = None,
                bounds: Sequence[RayBounds] = (),
                noise: RenderNoise | None = None) -> RenderOutput:
    """Render a batch of rays with NeuS.

    Skipping work without changing shapes: with `cfg.cull_outside_sphere`, a visual hull
    or an occupancy grid (`bounds`), a ray's coarse samples lie where it crosses all of
    them (`ray_bounds`), so the same number of samples is denser where the surface can
    be. Rays that cross nothing are *inactive*: masked to zero opacity inside [near, far]
    (the background model, if any, still renders them). Every batch keeps its shape (no
    compaction, no host synchronisation); callers that want to skip inactive rays' network
    work draw their rays where the surface can be (`neus_l0.data.rays`) or compact before
    calling (`render_image`).

    Args:
        model: the networks; `model.background` is used when `cfg.n_outside > 0`.
        origins, dirs: (B, 3) in the normalised frame, unit `dirs`.
        cfg: sampling and compositing settings.
        sampler: the up-sampling draw, one of `SAMPLERS`.
        cos_anneal_ratio: NeuS's cos annealing (1: unbiased).
        perturb: jitter the coarse (and background) samples, drawing from `generator`.
        generator: random source of the jitter.
        noise: the jitter's uniforms drawn beforehand (`draw_noise`); given, it is used
            whatever `perturb` says.
        create_graph: keep the graph of the SDF gradients (training: Eikonal loss).
        occupancy: an occupancy grid (appended to `bounds`; kept for older callers).
        bounds: objects that narrow the rays' bounds (see `ray_bounds`).

    Returns:
        a `RenderOutput`.
    """
    bounds = tuple(bounds) + ((occupancy,) if occupancy is not None else ())
    if noise is None and perturb:
        noise = draw_noise(cfg, origins.shape[0], generator, origins.device)
    near, far, active = ray_bounds(origins, dirs, cfg, bounds)
    fg = _foreground(model, origins, dirs, near, far, cfg, sampler, cos_anneal_ratio,
                     noise, create_graph)
    keep = active[:, None].to(fg["alpha"].dtype)  # (B, 1)
    fg["alpha"] = fg["alpha"] * keep
    N = fg["t"].shape[1]

    pts_norm = fg["pts"].norm(dim=-1)
    inside = (pts_norm < 1.0).to(keep.dtype).detach()  # (B, N)
    eikonal_mask = ((pts_norm < 1.2) & active[:, None]).to(keep.dtype).detach()
    use_bg = cfg.n_outside > 0 and model.background is not None
    if use_bg:
        alpha, rgb = _with_background(model, origins, dirs, fg, inside, far, cfg, noise)
    else:
        alpha, rgb = fg["alpha"], fg["rgb"]

    weights = alpha * transmittance(alpha)  # (B, N [+ n_outside])
    weight_sum = weights.sum(-1, keepdim=True)
    color = (rgb * weights[..., None]).sum(dim=1)
    if cfg.white_background and not use_bg:
        color = color + (1.0 - weight_sum)

    w_in = weights[:, :N] * inside  # (B, N)
    depth = (w_in * fg["t_mid"]).sum(-1, keepdim=True) / w_in.sum(-1, keepdim=True).clamp_min(1e-6)
    normal = (fg["gradients"] * w_in[..., None]).sum(dim=1)
    return RenderOutput(
        color=color, weight_sum=weight_sum, depth=depth, normal=normal, weights=weights,
        gradients=fg["gradients"], eikonal_mask=eikonal_mask, t=fg["t"],
        t_fine=fg["t_fine"], t_mid=fg["t_mid"], inside_sphere=inside, active=active,
        s_val=(1.0 / model.variance.inv_s()).reshape(()),
    )


def render_image(model: NeuSModel, origins: Tensor, dirs: Tensor, cfg: RenderConfig,
                 sampler: str = "l0", cos_anneal_ratio: float = 1.0,
                 chunk: int | None = None, occupancy: RayBounds | None = None,
                 bounds: Sequence[RayBounds] = ()) -> dict[str, Tensor]:
    """Render whole images in chunks of rays, without jitter or training graph.

    Rays that cross nothing (see `render_rays`) skip the networks when there is no
    background model: they keep zero opacity (and the background colour).

    Args:
        origins, dirs: (H, W, 3).
        chunk: rays per chunk (default `cfg.chunk`).
        occupancy, bounds: what narrows the rays (see `ray_bounds`).

    Returns:
        dict with ``color`` (H, W, 3), ``normal`` (H, W, 3), ``depth`` (H, W) and
        ``weight_sum`` (H, W), detached.
    """
    H, W, _ = origins.shape
    o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    bounds = tuple(bounds) + ((occupancy,) if occupancy is not None else ())
    use_bg = cfg.n_outside > 0 and model.background is not None
    if use_bg or not (cfg.cull_outside_sphere or bounds):
        idx = torch.arange(o.shape[0], device=o.device)
    else:  # evaluation, not training: a host sync to skip the empty rays is fine
        idx = torch.cat([ray_bounds(o[s:s + 65536], d[s:s + 65536], cfg, bounds)[2]
                         .nonzero().squeeze(1) + s for s in range(0, o.shape[0], 65536)])
    background = 1.0 if cfg.white_background and not use_bg else 0.0
    res = {
        "color": torch.full((o.shape[0], 3), background, device=o.device),
        "normal": torch.zeros(o.shape[0], 3, device=o.device),
        "depth": torch.zeros(o.shape[0], 1, device=o.device),
        "weight_sum": torch.zeros(o.shape[0], 1, device=o.device),
    }
    chunk = chunk or cfg.chunk
    for start in range(0, idx.shape[0], chunk):
        rows = idx[start:start + chunk]
        with torch.no_grad():
            out = render_rays(model, o[rows], d[rows], cfg, sampler,
                              cos_anneal_ratio=cos_anneal_ratio, perturb=False, bounds=bounds)
        for k in res:
            res[k][rows] = out[k].detach().float()
    return {
        "color": res["color"].reshape(H, W, 3),
        "normal": res["normal"].reshape(H, W, 3),
        "depth": res["depth"].reshape(H, W),
        "weight_sum": res["weight_sum"].reshape(H, W),
    }
