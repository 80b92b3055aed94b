"""NeuS's training losses and the PSNR metric (pure tensor functions)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def color_l1(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Masked L1 colour loss, summed over channels and divided by the mask's sum (NeuS).

    Args:
        pred, target: (B, 3); mask: (B, 1) in {0, 1} (all ones without masks).

    Returns:
        () loss.
    """
    return ((pred - target).abs() * mask).sum() / (mask.sum() + 1e-5)


def masked_psnr(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """PSNR (dB) over the masked pixels.

    Args:
        pred, target: (B, 3) in [0, 1]; mask: (B, 1).

    Returns:
        () PSNR.
    """
    mse = ((pred - target) ** 2 * mask).sum() / (mask.sum() * 3.0 + 1e-5)
    return -10.0 * torch.log10(mse.clamp_min(1e-10))


def mask_bce(weight_sum: Tensor, mask: Tensor) -> Tensor:
    """Binary cross-entropy between the accumulated opacity and the mask.

    Args:
        weight_sum: (B, 1) opacity along each ray; mask: (B, 1) in {0, 1}.

    Returns:
        () loss.
    """
    return F.binary_cross_entropy(weight_sum.clip(1e-3, 1.0 - 1e-3), mask)


def neus_loss(out: dict[str, Tensor], target_rgb: Tensor, mask: Tensor, igr_weight: float,
              mask_weight: float) -> dict[str, Tensor]:
    """Total loss: colour L1 + igr_weight * Eikonal + mask_weight * mask BCE.

    Args:
        out: `neus_l0.rendering.render_rays` output.
        target_rgb: (B, 3); mask: (B, 1) binary (ones when masks are unused).
        igr_weight, mask_weight: the loss weights.

    Returns:
        dict of () tensors: ``loss``, ``color_loss``, ``eikonal_loss``, ``mask_loss``,
        ``psnr``.
    """
    color = color_l1(out["color"], target_rgb, mask)
    eik = out["gradient_error"]
    mloss = mask_bce(out["weight_sum"], mask) if mask_weight > 0 else torch.zeros_like(color)
    loss = color + igr_weight * eik + mask_weight * mloss
    return {
        "loss": loss,
        "color_loss": color,
        "eikonal_loss": eik,
        "mask_loss": mloss,
        "psnr": masked_psnr(out["color"].detach(), target_rgb, mask),
    }


def eikonal_subset(gradients: Tensor, mask: Tensor, fraction: float,
                   generator: torch.Generator | None = None) -> Tensor:
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
    k = max(1, math.ceil(fraction * m.numel()))
    idx = torch.randint(0, max(1, m.numel()), (k,), generator=generator, device=g.device)
    if m.numel() == 0:
        return g.sum() * 0.0
    eik = (g[idx].norm(dim=-1) - 1.0) ** 2
    return (m[idx] * eik).sum() / (m[idx].sum() + 1e-5)
