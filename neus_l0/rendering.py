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

import torch
import torch.nn.functional as F
from torch import Tensor

from neus_l0.config import RenderConfig
from neus_l0.fields import NeuSModel, sdf_and_gradient
from neus_l0.occupancy import OccupancyGrid
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
                  generator: torch.Generator | None = None) -> Tensor:
    """Uniform samples in [near, far], shifted by one random offset per ray if `perturb`.

    Args:
        near, far: (B, 1).
        n_samples: samples per ray.
        perturb: jitter by U(-0.5, 0.5) * (far - near) / n_samples (NeuS's 2 / n_samples).
        generator: random source for the jitter.

    Returns:
        (B, n_samples) sorted.
    """
    lin = torch.linspace(0.0, 1.0, n_samples, device=near.device, dtype=near.dtype)
    z = near + (far - near) * lin  # (B, n)
    if perturb:
        r = torch.rand(near.shape, generator=generator, device=near.device, dtype=near.dtype)
        z = z + (r - 0.5) * (far - near) / n_samples
    return z


def outside_z_vals(far: Tensor, n_outside: int, n_samples: int, perturb: bool,
                   generator: torch.Generator | None = None) -> Tensor:
    """NeuS's background samples beyond `far`, uniform in inverse depth.

    Args:
        far: (B, 1).
        n_outside: samples per ray.
        n_samples: coarse samples (sets the gap 1 / n_samples after `far`).
        perturb: stratified jitter within each stratum.
        generator: random source.

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
        r = torch.rand(s.shape, generator=generator, device=far.device, dtype=far.dtype)
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


def _foreground(model: NeuSModel, origins: Tensor, dirs: Tensor, near: Tensor, far: Tensor,
                cfg: RenderConfig, sampler: str, cos_anneal_ratio: float, perturb: bool,
                generator: torch.Generator | None, create_graph: bool,
                sample_dist: float | Tensor) -> dict[str, Tensor]:
    """Samples in [near, far], up-sampling, and the SDF / colour networks on them.

    Args:
        origins, dirs: (b, 3); near, far: (b, 1).
        sample_dist: length of the last section (a number or (b, 1)).

    Returns:
        dict with ``z`` (b, N) sorted, ``z_fine`` (b, n_importance), ``dists`` and ``mid``
        (b, N), ``pts`` (b, N, 3) at the midpoints, ``gradients`` (b, N, 3), ``rgb``
        (b, N, 3) and ``alpha`` (b, N), all float32 (network outputs are cast back from
        any autocast precision).
    """
    b = origins.shape[0]
    z = coarse_z_vals(near, far, cfg.n_samples, perturb, generator)
    z, z_fine = up_sample(model, origins, dirs, z, cfg, sampler)
    N = z.shape[1]
    last = (sample_dist.expand(b, 1) if isinstance(sample_dist, Tensor)
            else torch.full_like(z[:, :1], sample_dist))
    dists = torch.cat([z[:, 1:] - z[:, :-1], last], dim=-1)
    mid = z + 0.5 * dists  # (b, N)
    pts = origins[:, None, :] + dirs[:, None, :] * mid[..., None]  # (b, N, 3)
    d = dirs[:, None, :].expand(b, N, 3)
    out, grad = sdf_and_gradient(model.sdf, pts.reshape(-1, 3), create_graph=create_graph)
    out, grad = out.float(), grad.float()
    sdf = out[:, 0].reshape(b, N)
    gradients = grad.reshape(b, N, 3)
    rgb = model.color(pts.reshape(-1, 3), grad, d.reshape(-1, 3), out[:, 1:])
    rgb = rgb.float().reshape(b, N, 3)
    inv_s = model.variance.inv_s()
    true_cos = (d * gradients).sum(-1)  # (b, N)
    alpha = cos_anneal_alpha(sdf, true_cos, dists, inv_s, cos_anneal_ratio)
    return {"z": z, "z_fine": z_fine, "dists": dists, "mid": mid, "pts": pts,
            "gradients": gradients, "rgb": rgb, "alpha": alpha}


def render_rays(model: NeuSModel, origins: Tensor, dirs: Tensor, cfg: RenderConfig,
                sampler: str = "l0", *, cos_anneal_ratio: float = 1.0, perturb: bool = False,
                generator: torch.Generator | None = None,
                create_graph: bool = False, occupancy: OccupancyGrid | None = None
                ) -> dict[str, Tensor]:
    """Render a batch of rays with NeuS.

    Skipping work (off by default, so NeuS is reproduced): with `cfg.cull_outside_sphere`
    or an `occupancy` grid, a ray's coarse samples lie on its chord of the unit sphere,
    tightened to the span of occupied cells (`OccupancyGrid.spans`); rays that miss the
    sphere or cross no occupied cell are *inactive*: no samples, no SDF / colour work
    (with `cfg.occupancy.compact`), zero opacity inside [near, far] (the background model,
    if any, still renders them). Their per-sample outputs hold zeros at NeuS's uniform
    positions. The coarse samples keep their number per ray (rectangular tensors), so
    a tightened span means denser coarse samples where the surface can be.

    Args:
        model: the networks; `model.background` is used when `cfg.n_outside > 0`.
        origins, dirs: (B, 3) in the normalised frame, unit `dirs`.
        cfg: sampling and compositing settings.
        sampler: the up-sampling draw, one of `SAMPLERS`.
        cos_anneal_ratio: NeuS's cos annealing (1: unbiased).
        perturb: jitter the coarse (and background) samples, drawing from `generator`.
        generator: random source of the jitter.
        create_graph: keep the graph of the SDF gradients (training: Eikonal loss).
        occupancy: an occupancy grid (None: none).

    Returns:
        dict with ``color`` (B, 3); ``weights`` (B, N [+ n_outside]); ``weight_sum`` (B, 1);
        ``gradients`` (B, N, 3) at the section midpoints; ``gradient_error`` () the Eikonal
        term over samples within radius 1.2; ``eikonal_mask`` (B, N) those samples;
        ``depth`` (B, 1) the weighted mean of the
        midpoints inside the sphere; ``normal`` (B, 3) the weighted sum of gradients inside
        the sphere (not normalised, as NeuS); ``z_vals`` (B, N) all sorted sample positions;
        ``z_fine`` (B, n_importance) the up-sampled ones; ``mid_z_vals`` (B, N);
        ``inside_sphere`` (B, N); ``active`` (B,) rays that got samples; ``s_val`` (1,)
        = 1 / s.
    """
    B = origins.shape[0]
    near, far = near_far_from_sphere(origins, dirs)
    use_bg = cfg.n_outside > 0 and model.background is not None
    z_out = (outside_z_vals(far, cfg.n_outside, cfg.n_samples, perturb, generator)
             if use_bg else None)
    args = (cfg, sampler, cos_anneal_ratio, perturb, generator, create_graph)
    cull = cfg.cull_outside_sphere or occupancy is not None
    if not cull:
        fg = _foreground(model, origins, dirs, near, far, *args, 2.0 / cfg.n_samples)
        active = torch.ones(B, dtype=torch.bool, device=origins.device)
    else:
        lo, hi, active = sphere_chord(origins, dirs)
        if occupancy is not None:
            lo, hi, crosses = occupancy.spans(origins, dirs, lo, hi)
            active = active & crosses
        step = (hi - lo) / cfg.n_samples  # (B, 1)
        if cfg.occupancy.compact:
            idx = active.nonzero().squeeze(1)  # the only host sync (CUDA) of culling
            sub = _foreground(model, origins[idx], dirs[idx], lo[idx], hi[idx], *args,
                              step[idx])
            fg = _scatter_rows(sub, idx, origins, dirs, near, far, cfg)
        else:
            fg = _foreground(model, origins, dirs, lo, hi, *args, step)
            keep = active[:, None].to(fg["alpha"].dtype)
            fg["alpha"] = fg["alpha"] * keep
            fg["rgb"] = fg["rgb"] * keep[..., None]
    z, mid, alpha, rgb, gradients = fg["z"], fg["mid"], fg["alpha"], fg["rgb"], fg["gradients"]
    N = z.shape[1]
    sample_dist = 2.0 / cfg.n_samples

    pts_norm = fg["pts"].norm(dim=-1)
    inside = (pts_norm < 1.0).to(alpha.dtype).detach()
    relax_inside = ((pts_norm < 1.2) & active[:, None]).to(alpha.dtype).detach()

    if use_bg:
        bg_alpha, bg_rgb = background_alpha_color(model, origins, dirs,
                                                  torch.cat([z, z_out], dim=-1), sample_dist)
        alpha = alpha * inside + bg_alpha[:, :N] * (1.0 - inside)
        alpha = torch.cat([alpha, bg_alpha[:, N:]], dim=-1)
        rgb = rgb * inside[..., None] + bg_rgb[:, :N] * (1.0 - inside)[..., None]
        rgb = torch.cat([rgb, bg_rgb[:, N:]], dim=1)

    weights = alpha * transmittance(alpha)  # (B, N [+ n_outside])
    weight_sum = weights.sum(-1, keepdim=True)
    color = (rgb * weights[..., None]).sum(dim=1)
    if cfg.white_background and not use_bg:
        color = color + (1.0 - weight_sum)

    eik = (gradients.norm(dim=-1) - 1.0) ** 2
    gradient_error = (relax_inside * eik).sum() / (relax_inside.sum() + 1e-5)

    w_in = weights[:, :N] * inside  # (B, N)
    w_in_sum = w_in.sum(-1, keepdim=True)
    depth = (w_in * mid).sum(-1, keepdim=True) / w_in_sum.clamp_min(1e-6)
    normal = (gradients * w_in[..., None]).sum(dim=1)
    return {
        "color": color,
        "weights": weights,
        "weight_sum": weight_sum,
        "gradients": gradients,
        "gradient_error": gradient_error,
        "eikonal_mask": relax_inside,
        "depth": depth,
        "normal": normal,
        "z_vals": z,
        "z_fine": fg["z_fine"],
        "mid_z_vals": mid,
        "inside_sphere": inside,
        "active": active,
        "s_val": 1.0 / model.variance.inv_s(),
    }


def _scatter_rows(sub: dict[str, Tensor], idx: Tensor, origins: Tensor, dirs: Tensor,
                  near: Tensor, far: Tensor, cfg: RenderConfig) -> dict[str, Tensor]:
    """Put the foreground of the active rays `idx` back among all B rays.

    Inactive rows get NeuS's uniform positions in [near, far] (no jitter), zero alpha,
    colour and gradients. Differentiable with respect to the active rows.

    Args:
        sub: `_foreground` output for the rows `idx` (b,).
        origins, dirs: (B, 3); near, far: (B, 1).
    """
    B = near.shape[0]
    N = cfg.n_samples + (cfg.n_importance if cfg.up_sample_steps else 0)
    z = coarse_z_vals(near, far, N, perturb=False)  # (B, N)
    dists = torch.cat([z[:, 1:] - z[:, :-1], torch.full_like(z[:, :1], 2.0 / cfg.n_samples)],
                      dim=-1)
    mid = z + 0.5 * dists
    full = {
        "z": z, "dists": dists, "mid": mid,
        "z_fine": near.expand(B, sub["z_fine"].shape[1]),
        "pts": origins[:, None, :] + dirs[:, None, :] * mid[..., None],
        "gradients": torch.zeros(B, N, 3, dtype=z.dtype, device=z.device),
        "rgb": torch.zeros(B, N, 3, dtype=z.dtype, device=z.device),
        "alpha": torch.zeros(B, N, dtype=z.dtype, device=z.device),
    }
    return {k: v.index_copy(0, idx, sub[k].to(v.dtype)) for k, v in full.items()}


def render_image(model: NeuSModel, origins: Tensor, dirs: Tensor, cfg: RenderConfig,
                 sampler: str = "l0", cos_anneal_ratio: float = 1.0,
                 chunk: int | None = None,
                 occupancy: OccupancyGrid | None = None) -> dict[str, Tensor]:
    """Render whole images in chunks of rays, without jitter or training graph.

    Args:
        origins, dirs: (H, W, 3).
        chunk: rays per chunk (default `cfg.chunk`).
        occupancy: an occupancy grid to skip empty space with (see `render_rays`).

    Returns:
        dict with ``color`` (H, W, 3), ``normal`` (H, W, 3), ``depth`` (H, W) and
        ``weight_sum`` (H, W), detached.
    """
    H, W, _ = origins.shape
    o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    chunk = chunk or cfg.chunk
    keys = ("color", "normal", "depth", "weight_sum")
    parts: dict[str, list[Tensor]] = {k: [] for k in keys}
    for start in range(0, o.shape[0], chunk):
        out = render_rays(model, o[start:start + chunk], d[start:start + chunk], cfg, sampler,
                          cos_anneal_ratio=cos_anneal_ratio, perturb=False,
                          occupancy=occupancy)
        for k in keys:
            parts[k].append(out[k].detach())
    res = {k: torch.cat(v, dim=0) for k, v in parts.items()}
    return {
        "color": res["color"].reshape(H, W, 3),
        "normal": res["normal"].reshape(H, W, 3),
        "depth": res["depth"].reshape(H, W),
        "weight_sum": res["weight_sum"].reshape(H, W),
    }
