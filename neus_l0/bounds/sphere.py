"""The unit sphere along a ray: NeuS's near / far and the sphere's chord.

Pure functions. Shapes: B rays; `origins`, `dirs` (B, 3) in the normalised frame (the
object inside the unit sphere), `dirs` unit.
"""

from __future__ import annotations

import torch
from torch import Tensor


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


def sphere_chord(origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Where each ray is inside the unit sphere.

    Args:
        origins: (B, 3); dirs: (B, 3) unit.

    Returns:
        t_in, t_out: (B, 1) the chord's ends, clamped to t >= 0 (NeuS's near / far,
        ``mid -+ 1``, for rays that miss); hits: (B,) bool, whether the ray meets the
        sphere in front of its origin.
    """
    # the closest approach (NeuS's mid of `near_far_from_sphere`)
    mid = -(origins * dirs).sum(-1, keepdim=True) / (dirs * dirs).sum(-1, keepdim=True)
    closest = torch.addcmul(origins, mid, dirs)  # (B, 3)
    half2 = 1.0 - (closest * closest).sum(-1, keepdim=True)  # (B, 1)
    half = half2.clamp_min(0.0).sqrt()
    t_out = mid + half
    hits = (half2 > 0.0) & (t_out > 0.0)  # (B, 1)
    t_in = torch.where(hits, (mid - half).clamp_min(0.0), mid - 1.0)
    t_out = torch.where(hits, t_out, mid + 1.0)
    return t_in, t_out, hits[:, 0]
