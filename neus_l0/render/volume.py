"""NeuS volume rendering: per-ray bounds, coarse samples, up-sampling, unbiased compositing.

The path of one batch: `ray_bounds` (NeuS's [mid - 1, mid + 1], or the unit sphere's chord
narrowed by a visual hull and an occupancy grid), coarse samples in those bounds,
NeuS's up-sampling rounds with the fine-sample draw of a `neus_l0.sampling.upsample.Sampler`
(``hvs``, the L0 kinds, ``neus-exact``; how section weights become point weights is
documented there), the SDF and colour networks at the section midpoints, NeuS's unbiased
opacity and alpha compositing, optionally blended with the NeRF++ background. The result is
a `RenderOutput`; the losses are computed from it in `neus_l0.train.losses`.

Shapes: B rays, N samples per ray along the (sorted) positions `t`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from neus_l0.bounds.spans import RayBounds, _ray_bounds, ray_bounds
from neus_l0.config.schema import RenderConfig
from neus_l0.fields.model import NeuSModel
from neus_l0.fields.sdf import sdf_and_gradient
from neus_l0.sampling.upsample import Sampler, transmittance, up_sample


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
    return _coarse(near, far - near, n_samples, perturb, generator, noise)


def _coarse(near: Tensor, span: Tensor, n_samples: int, perturb: bool,
            generator: torch.Generator | None = None, noise: Tensor | None = None,
            step: Tensor | None = None) -> Tensor:
    """`coarse_z_vals` with ``span = far - near`` (B, 1) given (and ``step = span /
    n_samples``, if computed already); (B, n_samples)."""
    lin = torch.linspace(0.0, 1.0, n_samples, device=near.device, dtype=near.dtype)
    z = torch.addcmul(near, span, lin)  # (B, n)
    if perturb:
        r = noise if noise is not None else torch.rand(
            near.shape, generator=generator, device=near.device, dtype=near.dtype)
        z = torch.addcmul(z, r - 0.5, span / n_samples if step is None else step)
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


def section_alpha(sdf: Tensor, slope: Tensor, half: Tensor, inv_s: Tensor,
                  skipped: Tensor | None = None) -> Tensor:
    """NeuS's unbiased discrete opacity of the sections around the midpoints.

    Section i runs from ``mid_i - half_i`` to ``mid_i + half_i`` with the linear SDF model
    ``sdf_i + slope_i (t - mid_i)``; its opacity is ``(cdf(start) - cdf(end) + 1e-5) /
    (cdf(start) + 1e-5)`` with ``cdf = sigmoid(inv_s x)`` (NeuS's, with its guards).

    A ray whose samples a visual hull or occupancy grid starts at ``near`` was inside the
    unit sphere for ``skipped`` before that; NeuS would have integrated that stretch too.
    Its first section starts there instead: the same linear model extended back to the
    sphere (SDF ``start - slope * skipped``, slope <= 0). So a ray that enters the SDF's
    negative region head-on inside the skipped stretch is opaque at once (without this, it
    would see no zero crossing and stay transparent, and a network could fill the whole hull
    at no cost; docs/BENCHMARKS.md, "What does the visual hull cost and buy?"), and one that
    enters outside the object is unchanged.

    Args:
        sdf: (B, N) SDF at the midpoints; slope: (B, N) the annealed slope (`annealed_cos`,
            <= 0); half: (B, N) half the sections' lengths; inv_s: (1,) sharpness s.
        skipped: (B, 1) length skipped before the first section (>= 0), or None.

    Returns:
        (B, N) alpha in [0, 1].
    """
    shift = slope * half
    if skipped is not None:  # the first section reaches back by `skipped`
        back = slope * (half + F.pad(skipped, (0, half.shape[1] - 1)))
    prev_cdf = torch.sigmoid((sdf - (shift if skipped is None else back)) * inv_s)
    next_cdf = torch.sigmoid((sdf + shift) * inv_s)
    # the start estimate >= the end's (slope <= 0), so alpha > 0: only the clip at 1 acts
    return ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clamp_max(1.0)


def annealed_cos(true_cos: Tensor, cos_anneal_ratio: float | Tensor) -> Tensor:
    """NeuS's annealed slope: 0 -> (cos - 1) / 2 clipped (early training), 1 -> min(cos, 0).

    Args:
        true_cos: (...) dot(dir, gradient).

    Returns:
        (...) the slope used, always <= 0.
    """
    # -relu(-x) == min(x, 0): the two slopes, then one lerp between them (a Python 0 or
    # 1, e.g. without annealing, picks one: what the lerp gives, in fewer ops)
    if not isinstance(cos_anneal_ratio, Tensor) and cos_anneal_ratio in (0.0, 1.0):
        return (true_cos if cos_anneal_ratio else true_cos * 0.5 - 0.5).clamp_max(0.0)
    early = (true_cos * 0.5 - 0.5).clamp_max(0.0)
    return torch.lerp(early, true_cos.clamp_max(0.0), cos_anneal_ratio)


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
        sdf: (B, N) the SDF at the section midpoints (with its graph).
        eikonal_mask: (B, N) samples the Eikonal term counts (radius < 1.2, active rays).
        t: (B, N) sorted sample positions; t_fine: (B, n_importance) the up-sampled ones
            (sorted within each round); t_mid: (B, N) section midpoints.
        inside_sphere: (B, N) midpoints inside the unit sphere.
        active: (B,) rays that got samples (inactive rays have zero opacity inside
            [near, far]; a background model still renders them).
        inv_s: () NeuS's sharpness s (the inverse standard deviation of its logistic
            density).
    """

    color: Tensor
    weight_sum: Tensor
    depth: Tensor
    normal: Tensor
    weights: Tensor
    gradients: Tensor
    sdf: Tensor
    eikonal_mask: Tensor
    t: Tensor
    t_fine: Tensor
    t_mid: Tensor
    inside_sphere: Tensor
    active: Tensor
    inv_s: Tensor


def _foreground(model: NeuSModel, origins: Tensor, dirs: Tensor,
                interval: tuple[Tensor, Tensor, Tensor | None], cfg: RenderConfig,
                sampler: Sampler, cos_anneal_ratio: float | Tensor,
                noise: RenderNoise | None, create_graph: bool,
                in_sphere: bool = False) -> dict[str, Tensor]:
    """Samples in [near, far], up-sampling, and the SDF / colour networks on them.

    Args:
        origins, dirs: (B, 3).
        interval: ``(near, far, skipped)``: (B, 1) each; ``skipped`` is the stretch of the
            sphere's chord before `near` (`section_alpha`), or None.
        in_sphere: [near, far] lies on the unit sphere's chord (culled rays; `up_sample`).

    Returns:
        dict with ``t`` (B, N) sorted, ``t_fine`` (B, n_importance), ``t_mid`` and
        ``dists`` (B, N), ``pts`` (B, N, 3) at the midpoints, ``sdf`` (B, N) and
        ``gradients`` (B, N, 3) there, ``rgb`` (B, N, 3) and ``alpha`` (B, N), all
        float32 (network outputs are cast back from any autocast precision).
    """
    B = origins.shape[0]
    near, far, skipped = interval
    span = far - near  # (B, 1)
    step = span / cfg.n_samples  # NeuS's 2 / n_samples on its own bounds
    t = _coarse(near, span, cfg.n_samples, noise is not None,
                noise=None if noise is None else noise.coarse, step=step)
    t, t_fine = up_sample(lambda p: model.sdf.sdf(p).float(), origins, dirs, t,
                          sampler, cfg.n_importance, cfg.up_sample_steps,
                          in_sphere=in_sphere)
    N = t.shape[1]
    dists = torch.cat([t[:, 1:] - t[:, :-1], step], dim=-1)
    half = 0.5 * dists
    mid = t + half  # (B, N)
    d = dirs[:, None, :]  # (B, 1, 3)
    pts = torch.addcmul(origins[:, None, :], d, mid[..., None])  # (B, N, 3)
    flat = pts.view(-1, 3)
    out, grad = sdf_and_gradient(model.sdf, flat, create_graph=create_graph)
    out, grad = out.float(), grad.float()
    sdf = out[:, 0].view(B, N)
    gradients = grad.view(B, N, 3)
    rgb = model.color(flat, grad, d.expand(B, N, 3).reshape(-1, 3), out[:, 1:])
    rgb = rgb.float().view(B, N, 3)
    true_cos = (d * gradients).sum(-1)  # (B, N)
    inv_s = model.variance.inv_s()
    alpha = section_alpha(sdf, annealed_cos(true_cos, cos_anneal_ratio), half, inv_s, skipped)
    return {"t": t, "t_fine": t_fine, "dists": dists, "t_mid": mid, "pts": pts,
            "sdf": sdf, "gradients": gradients, "rgb": rgb, "alpha": alpha, "inv_s": inv_s}


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
                sampler: Sampler, *,
                cos_anneal_ratio: float | Tensor = 1.0,
                create_graph: bool = False,
                bounds: Sequence[RayBounds] = (),
                noise: RenderNoise | None = None,
                span: Tensor | None = None) -> RenderOutput:
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
        sampler: the up-sampling draw (`neus_l0.sampling.upsample.build_sampler`; build it
            once per run: a compiled draw compiles at its first use).
        cos_anneal_ratio: NeuS's cos annealing (1: unbiased).
        noise: the jitter of the coarse (and background) samples, its uniforms drawn
            beforehand (`draw_noise`); None: no jitter.
        create_graph: keep the graph of the SDF gradients (training: Eikonal loss).
        bounds: objects that narrow the rays' bounds (see `ray_bounds`).
        span: (B, 4) the rays' bounds computed beforehand (`packed_spans`, e.g. kept by the
            pixel pool) under culling and static bounds not in `bounds`: every ray is
            active, and `bounds` narrows it further.

    Returns:
        a `RenderOutput`.
    """
    bounds = tuple(bounds)
    near, far, active, entry, exit_ = _ray_bounds(origins, dirs, cfg, bounds, span)
    # [near, far] on the sphere's chord; narrowed (by the hull or the grid)
    culled = cfg.cull_outside_sphere or bool(bounds) or span is not None
    narrowed = bool(bounds) or span is not None
    # the stretch skipped before the hull or grid joins the first section (`section_alpha`)
    skipped = (near - entry).clamp_min(0.0) if narrowed else None  # (B, 1)
    fg = _foreground(model, origins, dirs, (near, far, skipped), cfg, sampler,
                     cos_anneal_ratio, noise, create_graph, in_sphere=culled)
    keep = active[:, None].to(fg["alpha"].dtype)  # (B, 1)
    # the background starts where the sphere ends, never inside a narrowed interval
    bg_from = torch.maximum(far, exit_) if narrowed else far
    fg["alpha"] = fg["alpha"] * keep
    N = fg["t"].shape[1]

    pts_norm = fg["pts"].norm(dim=-1)  # comparisons: no gradient, nothing to detach
    inside = (pts_norm < 1.0).to(keep.dtype)  # (B, N)
    eikonal_mask = ((pts_norm < 1.2) & active[:, None]).to(keep.dtype)
    use_bg = cfg.n_outside > 0 and model.background is not None
    if use_bg:
        alpha, rgb = _with_background(model, origins, dirs, fg, inside, bg_from, cfg, noise)
    else:
        alpha, rgb = fg["alpha"], fg["rgb"]

    weights = alpha * transmittance(alpha)  # (B, N [+ n_outside])
    weight_sum = weights.sum(-1, keepdim=True)
    color = (rgb * weights[..., None]).sum(dim=1)
    if cfg.white_background and not use_bg:
        color = color + (1.0 - weight_sum)

    w_in = (weights[:, :N] if use_bg else weights) * inside  # (B, N)
    depth = (w_in * fg["t_mid"]).sum(-1, keepdim=True) / w_in.sum(-1, keepdim=True).clamp_min(1e-6)
    normal = (fg["gradients"] * w_in[..., None]).sum(dim=1)
    return RenderOutput(
        color=color, weight_sum=weight_sum, depth=depth, normal=normal, weights=weights,
        gradients=fg["gradients"], sdf=fg["sdf"], eikonal_mask=eikonal_mask, t=fg["t"],
        t_fine=fg["t_fine"], t_mid=fg["t_mid"], inside_sphere=inside, active=active,
        inv_s=fg["inv_s"].reshape(()),
    )


def render_image(model: NeuSModel, origins: Tensor, dirs: Tensor, cfg: RenderConfig,
                 sampler: Sampler,
                 cos_anneal_ratio: float = 1.0,
                 chunk: int | None = None,
                 bounds: Sequence[RayBounds] = ()) -> dict[str, Tensor]:
    """Render whole images in chunks of rays, without jitter or training graph.

    Rays that cross nothing (see `render_rays`) skip the networks when there is no
    background model: they keep zero opacity (and the background colour).

    Args:
        origins, dirs: (H, W, 3).
        chunk: rays per chunk (default `cfg.chunk`).
        bounds: what narrows the rays, in order (see `ray_bounds`).

    Returns:
        dict with ``color`` (H, W, 3), ``normal`` (H, W, 3), ``depth`` (H, W) and
        ``weight_sum`` (H, W), detached.
    """
    H, W, _ = origins.shape
    o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
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
                              cos_anneal_ratio=cos_anneal_ratio, bounds=bounds)
        for k in res:
            res[k][rows] = getattr(out, k).detach().float()
    return {
        "color": res["color"].reshape(H, W, 3),
        "normal": res["normal"].reshape(H, W, 3),
        "depth": res["depth"].reshape(H, W),
        "weight_sum": res["weight_sum"].reshape(H, W),
    }
