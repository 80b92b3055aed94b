"""NeuS's training losses and the PSNR metric (pure tensor functions)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from neus_l0.config.schema import TrainConfig

#: The names of what `neus_loss` returns, in the order the step reports them.
LOSS_NAMES = ("loss", "color_loss", "eikonal_loss", "mask_loss", "curvature_loss", "photo_loss",
              "carve_loss", "fill_loss", "psnr")

if TYPE_CHECKING:
    from neus_l0.render.volume import RenderOutput


def color_l1(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Masked L1 colour loss, summed over channels and divided by the mask's sum (NeuS).

    Args:
        pred, target: (B, 3); mask: (B, 1) in {0, 1} (all ones without masks).

    Returns:
        () loss.
    """
    return ((pred - target).abs() * mask).sum() / (mask.sum() + 1e-5)


def hit_color(color: Tensor, weight_sum: Tensor, floor: float) -> Tensor:
    """The colour of the surface a ray hits: the composite over black divided by the ray's
    opacity, floored (``train.hit_color_floor``).

    Above the floor the result is invariant to scaling all of a ray's weights, so the colour
    term no longer pulls a grazing ray's opacity towards 1 (the mask term alone sets it);
    below it, the composite scaled by ``1 / floor``.

    Args:
        color: (B, 3) ``sum_i w_i c_i``; weight_sum: (B, 1) ``sum_i w_i``; floor: in (0, 1].

    Returns:
        (B, 3).
    """
    return color / weight_sum.clamp_min(floor)


def weighted_color_l1(pred: Tensor, target: Tensor, mask: Tensor, weight: Tensor,
                      foreground: float) -> Tensor:
    """The colour term of rays drawn by an error map, each weighted by 1 / (P p).

    ``sum(w * |pred - target|_1 * mask) / (B * foreground)``: with weights of the draw, its
    expectation is the pool's masked mean colour error (``sum_j l_j m_j / sum_j m_j``, with
    ``foreground`` = sum_j m_j / P), which `color_l1` estimates under uniform draws.

    Args:
        pred, target: (B, 3); mask: (B, 1) in {0, 1}; weight: (B,) importance weights;
        foreground: the pool's share of foreground pixels, > 0.

    Returns:
        () loss.
    """
    per_ray = (pred - target).abs().sum(-1) * mask[:, 0]  # (B,)
    return (weight * per_ray).sum() / (pred.shape[0] * foreground)


def ray_errors(out: RenderOutput, target_rgb: Tensor, mask: Tensor, use_mask: bool,
               signal: str = "colour", near: Tensor | None = None) -> Tensor:
    """(B,) each ray's error for the error map (detached).

    Args:
        out: the rays' render; target_rgb: (B, 3); mask: (B, 1) in {0, 1}.
        use_mask: the run uses masks (``colour`` adds |opacity - mask|).
        signal: ``colour``: the colour L1 where the mask is on, plus |opacity - mask| with
            masks; ``depth``: ``max(0, depth - near)`` where the mask is on (times the
            opacity without masks), how deep behind its entry into the hull the ray's
            surface lies; rays off the mask take the batch's mean over the rays on it, so
            that the map moves rays within the object and leaves the rays that carve the
            hull's slack (off the mask) their uniform share; ``depth_mask``: ``depth``
            plus |opacity - mask| on every ray (with masks; without, as ``depth``), so that
            the rays whose render disagrees with the silhouette are drawn more, in the
            same units as the depth in a unit-sphere scene (a ray fully wrong adds 1).
        near: (B,) where each ray enters the static bounds (the hull); None: its first
            sample, ``out.t[:, 0]``.
    """
    if signal in ("depth", "depth_mask"):
        start = out.t[:, 0] if near is None else near
        err = (out.depth[:, 0] - start).clamp_min(0.0)
        if not use_mask:
            return (err * out.weight_sum[:, 0]).detach()
        on = mask[:, 0]
        mean_on = (err * on).sum() / on.sum().clamp_min(1.0)
        err = torch.where(on > 0.5, err, mean_on)
        if signal == "depth_mask":
            err = err + (out.weight_sum[:, 0] - on).abs()
        return err.detach()
    err = (out.color - target_rgb).abs().sum(-1) * mask[:, 0]
    if use_mask:
        err = err + (out.weight_sum[:, 0] - mask[:, 0]).abs()
    return err.detach()


def masked_psnr(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """PSNR (dB) over the masked pixels.

    Args:
        pred, target: (B, 3) in [0, 1]; mask: (B, 1).

    Returns:
        () PSNR.
    """
    mse = ((pred - target) ** 2 * mask).sum() / (mask.sum() * 3.0 + 1e-5)
    return -10.0 * torch.log10(mse.clamp_min(1e-10))


def mask_bce(weight_sum: Tensor, mask: Tensor, weight: Tensor | None = None) -> Tensor:
    """Binary cross-entropy between the accumulated opacity and the mask.

    Args:
        weight_sum: (B, 1) opacity along each ray; mask: (B, 1) in {0, 1}.
        weight: (B,) per-ray weights of the mean (None: the plain mean).

    Returns:
        () loss.
    """
    # F.binary_cross_entropy raises on a NaN input; a NaN opacity is a diverged run, which
    # the colour loss shows as NaN too and the loop's watchdog stops, so it is read as 0.5
    p = torch.nan_to_num(weight_sum, nan=0.5).clip(1e-3, 1.0 - 1e-3)
    return F.binary_cross_entropy(p, mask, weight=None if weight is None else weight[:, None])


def free_space(sdf: Tensor, empty: Tensor, inside: Tensor, weight: Tensor | None = None
               ) -> Tensor:
    """Silhouette carving: how far inside the surface the rays that miss the object go.

    A pixel whose mask is 0 sees no object, so the SDF is positive all along its ray (IDR's
    mask term, in its hinge limit): the term is ``sum_b e_b w_b relu(-min_n sdf_bn) / B``
    over the samples inside the unit sphere, with ``e_b`` = 1 on those rays. It is 0 for an
    SDF that agrees with the masks (no bias on a correct surface) and its gradient reaches
    the one sample that lies deepest, whatever the opacity there, so it removes surface
    that only a pixel or two outside the silhouette sees (under the object, where the mask
    BCE's gradient is faint).

    Args:
        sdf: (B, N) the SDF at the rays' samples; empty: (B,) in {0, 1}, the rays whose
            mask is 0; inside: (B, N) in {0, 1}, the samples that count (inside the unit
            sphere, on rays that got samples); weight: (B,) importance weights of the
            rays (None: uniform).

    Returns:
        () loss, a mean over the batch (rays off `empty` count as 0).
    """
    depth = (-sdf).clamp_min(0.0) * inside  # (B, N): how far inside, 0 where it doesn't count
    per_ray = depth.amax(dim=1) * empty  # (B,)
    if weight is not None:
        per_ray = per_ray * weight
    return per_ray.sum() / max(1, sdf.shape[0])


def missed_rays(sdf: Tensor, full: Tensor, inside: Tensor, opacity: Tensor,
                weight: Tensor | None = None, margin: Tensor | float = 0.0) -> Tensor:
    """Silhouette filling: how far outside the surface the rays stay that see the object
    but render as misses (the mask BCE's dead zone).

    A pixel whose mask is 1 sees the object, so the SDF goes negative somewhere along its
    ray. The mask BCE cannot say so once a ray passes a few 1/s from every surface: its
    opacity falls under the BCE's clip (1e-3) and in float32 its alpha is the guard alone,
    so its gradient is exactly 0 (a thin rod that did not form early never forms). The term
    is ``sum_b m_b u_b w_b relu(min_n sdf_bn - margin) / B`` over the samples inside the unit
    sphere, with ``m_b`` = 1 on the rays whose mask is 1 and ``u_b`` = 1 where the ray renders
    below 0.5 opacity (read detached). Its gradient, 1 whatever the distance, reaches the one
    sample that lies shallowest: the counterpart of `free_space` (IDR's mask term in its
    hinge limit). With a `margin` of a few 1/s it stops where the BCE's gradient is alive
    again (at 3/s a ray renders ~0.05), so it leaves every silhouette to the BCE and is 0 on
    every ray that hits (no bias on a correct surface).

    Args:
        sdf: (B, N) the SDF at the rays' samples; full: (B,) in {0, 1}, the rays whose mask
            is 1; inside: (B, N) in {0, 1}, the samples that count (inside the unit sphere,
            on rays that got samples); opacity: (B, 1) the rays' rendered opacity; weight:
            (B,) importance weights of the rays (None: uniform); margin: () or a number, the
            SDF under which a sample counts as close enough (normalised units).

    Returns:
        () loss, a mean over the batch (rays off `full`, rays that render 0.5 or more and
        rays without a counted sample count as 0).
    """
    missed = full * (opacity.detach()[:, 0] < 0.5).to(sdf.dtype)  # (B,)
    counted = inside > 0
    shallow = torch.where(counted, sdf, torch.full_like(sdf, float("inf"))).amin(dim=1)
    shallow = torch.where(counted.any(dim=1), shallow, torch.zeros_like(shallow))  # (B,)
    per_ray = (shallow - margin).clamp_min(0.0) * missed
    if weight is not None:
        per_ray = per_ray * weight
    return per_ray.sum() / max(1, sdf.shape[0])


def eikonal(gradients: Tensor, mask: Tensor) -> Tensor:
    """NeuS's Eikonal term: the mean of ``(|grad| - 1)^2`` over the samples `mask` keeps.

    Args:
        gradients: (B, N, 3) SDF gradients; mask: (B, N) in {0, 1}.

    Returns:
        () loss (0 when the mask is empty).
    """
    eik = (gradients.norm(dim=-1) - 1.0) ** 2
    return (mask * eik).sum() / (mask.sum() + 1e-5)


def curvature(laplacian: Tensor, mask: Tensor) -> Tensor:
    """Neuralangelo's curvature term: the mean ``|Laplacian|`` over the points `mask` keeps.

    Args:
        laplacian: (k,) the SDF's Laplacian at k points; mask: (k,) in {0, 1}.

    Returns:
        () loss (0 when the mask is empty).
    """
    return (mask * laplacian.abs()).sum() / (mask.sum() + 1e-5)


def eikonal_indices(n: int, fraction: float, generator: torch.Generator | None,
                    device: torch.device | str) -> Tensor:
    """The ``ceil(fraction * n)`` sample indices (with replacement) of `eikonal_subset`."""
    k = max(1, math.ceil(fraction * n))
    return torch.randint(0, max(1, n), (k,), generator=generator, device=device)


def eikonal_term(out: RenderOutput, cfg: TrainConfig, generator: torch.Generator | None,
                 eikonal_idx: Tensor | None, ray_weight: Tensor | None) -> Tensor:
    """`neus_loss`'s Eikonal term: over every sample (`eikonal`) or a subset
    (`eikonal_subset`, ``cfg.eikonal_fraction`` below 1); with an error map's (B,)
    `ray_weight` and ``cfg.error_map.weigh_all``, each sample weighted by its ray's weight
    (a self-normalised mean)."""
    mask = out.eikonal_mask  # (B, N)
    if ray_weight is not None and cfg.error_map.weigh_all:
        mask = mask * ray_weight[:, None].to(mask.dtype)
    if cfg.eikonal_fraction < 1.0:
        return eikonal_subset(out.gradients, mask, cfg.eikonal_fraction, generator,
                              eikonal_idx)
    return eikonal(out.gradients, mask)


class RayDraw(NamedTuple):
    """How a batch's rays were drawn, as `neus_loss` reads it (the default: uniform).

    Attributes:
        mask_scale: factor on the mask term: the fraction of all pixels that the batch was
            drawn from (1: uniform over every pixel, as NeuS). Pixels whose rays cannot
            reach the surface have zero opacity by construction, so their mask term is a
            constant without gradient; drawing only from the others and scaling by that
            fraction keeps NeuS's expected gradient.
        ray_weight: (B,) importance weights of rays drawn by an error map
            (`neus_l0.bounds.error_map`): the colour term is `weighted_color_l1` and the
            mask term the weighted mean of the rays' BCE, so both keep the pool's
            expectation; the Eikonal term (over samples) is weighted (each sample by its
            ray's weight, a self-normalised mean) only with ``cfg.error_map.weigh_all``.
            None: uniform.
        foreground: the pool's share of foreground pixels (with `ray_weight`).
        eikonal_idx: the Eikonal subset's indices drawn beforehand (`eikonal_indices`).
        generator: random source of the Eikonal subset when `eikonal_idx` is None.
    """

    mask_scale: float | Tensor = 1.0
    ray_weight: Tensor | None = None
    foreground: float | Tensor = 1.0
    eikonal_idx: Tensor | None = None
    generator: torch.Generator | None = None


#: The terms a caller computes (`neus_loss`'s ``terms``): each one's name, the config field
#: that weighs it (a dotted path) and whether the mask term's scale applies.
EXTRA_TERMS = (("curvature", "curvature_weight", False), ("photo", "photo.weight", False),
               ("carve", "carve_weight", True), ("fill", "fill_weight", True))


def add_terms(loss: Tensor, cfg: TrainConfig, terms: dict[str, Tensor],
              mask_scale: float | Tensor) -> tuple[Tensor, dict[str, Tensor]]:
    """`loss` plus the caller's terms, each weighted, and each term (zeros where absent).

    Args:
        loss: () the loss so far.
        cfg: the weights: ``curvature_weight``, ``photo.weight``, ``carve_weight`` and
            ``fill_weight`` (the last two times `mask_scale`).
        terms: () tensors by name (``curvature``, ``photo``, ``carve``, ``fill``).

    Returns:
        (() loss, {name: () term}).
    """
    each = {}
    for name, field, scaled in EXTRA_TERMS:
        each[name] = terms.get(name, torch.zeros_like(loss))
        if name in terms:
            weight = cfg
            for part in field.split("."):  # a dotted path
                weight = getattr(weight, part)
            loss = loss + (weight * mask_scale if scaled else weight) * each[name]
    return loss, each


def neus_loss(out: RenderOutput, target_rgb: Tensor, mask: Tensor, cfg: TrainConfig,
              draw: RayDraw | None = None,
              terms: dict[str, Tensor] | None = None) -> dict[str, Tensor]:
    """Every training term in one place: colour L1 + igr * Eikonal + mask_weight * mask BCE
    (+ curvature_weight * curvature + photo.weight * photometric consistency + the carve and
    fill terms).

    Args:
        out: `neus_l0.render.volume.render_rays` output.
        target_rgb: (B, 3); mask: (B, 1) binary (ones when masks are unused).
        cfg: `igr_weight`, `mask_weight`, `eikonal_fraction` (below 1: the Eikonal term
            over a random subset of the samples), `hit_color_floor` (with masks, above 0:
            the colour term on `hit_color`).
        draw: how the rays were drawn (`RayDraw`; None: uniform over every pixel).
        terms: the terms the caller computes (they need the network), () each:
            ``curvature`` (`curvature`), added with ``cfg.curvature_weight``, and ``photo``
            (`neus_l0.train.photometric.photometric_term`), added with
            ``cfg.photo.weight``, ``carve`` (`free_space`), added with
            ``cfg.carve_weight * mask_scale``, and ``fill`` (`missed_rays`), added with
            ``cfg.fill_weight * mask_scale``; a missing one is 0.

    Returns:
        dict of () tensors: ``loss``, ``color_loss``, ``eikonal_loss``, ``mask_loss``,
        ``curvature_loss``, ``photo_loss``, ``carve_loss``, ``fill_loss``, ``psnr``.
    """
    draw = draw or RayDraw()
    pred = out.color
    if cfg.hit_color_floor > 0 and cfg.mask_weight > 0:
        pred = hit_color(out.color, out.weight_sum, cfg.hit_color_floor)
    if draw.ray_weight is None:
        color = color_l1(pred, target_rgb, mask)
    else:
        color = weighted_color_l1(pred, target_rgb, mask, draw.ray_weight, draw.foreground)
    eik = eikonal_term(out, cfg, draw.generator, draw.eikonal_idx, draw.ray_weight)
    if cfg.mask_weight > 0:
        mloss = mask_bce(out.weight_sum, mask, draw.ray_weight)
    else:
        mloss = torch.zeros_like(color)
    loss = color + cfg.igr_weight * eik + cfg.mask_weight * draw.mask_scale * mloss
    loss, each = add_terms(loss, cfg, terms or {}, draw.mask_scale)
    return {  # keys: LOSS_NAMES
        "loss": loss,
        "color_loss": color,
        "eikonal_loss": eik,
        "mask_loss": mloss,
        **{f"{name}_loss": each[name] for name, _, _ in EXTRA_TERMS},
        "psnr": masked_psnr(out.color.detach(), target_rgb, mask),
    }


def eikonal_subset(gradients: Tensor, mask: Tensor, fraction: float,
                   generator: torch.Generator | None = None,
                   idx: Tensor | None = None) -> Tensor:
    """The Eikonal term over a random subset of the samples (drawn with replacement).

    A fixed number of samples, ``ceil(fraction * B * N)``, is drawn uniformly; the term is
    the mean of ``(|grad| - 1)^2`` over the drawn samples that `mask` keeps, so its
    expectation is close to the full masked mean and its shapes never depend on the data
    (no host synchronisation).

    Args:
        gradients: (B, N, 3) SDF gradients; mask: (B, N) in {0, 1} (samples that count).
        fraction: in (0, 1].
        generator: random source (on the tensors' device).

    Returns:
        () loss.
    """
    g = gradients.reshape(-1, 3)
    m = mask.reshape(-1)
    if idx is None:
        idx = eikonal_indices(m.numel(), fraction, generator, g.device)
    if m.numel() == 0:
        return g.sum() * 0.0
    eik = (g[idx].norm(dim=-1) - 1.0) ** 2
    return (m[idx] * eik).sum() / (m[idx].sum() + 1e-5)
