"""Grey image patches compared across views: the normalised cross-correlation that the
photometric training term (`neus_l0.train.photometric`) and the mesh-time plane sweep
(`neus_l0.mesh.photo_carve`) score them with, and the luma weights of the grey values."""

from __future__ import annotations

import torch
from torch import Tensor

#: Rec. 601 luma weights (red, green, blue) of the grey images the patches compare.
LUMA = (0.299, 0.587, 0.114)


def ncc(ref: Tensor, src: Tensor, eps: float = 1e-4) -> Tensor:
    """Normalised cross-correlation of patches.

    Args:
        ref: (B, P) reference patches; src: (B, M, P) source patches.
        eps: added to both variances (flat patches score near 0, not noise).

    Returns:
        (B, M) in [-1, 1]: 1 where a source patch is an increasing affine map of the
        reference (a + b ref, b > 0), given textured patches.
    """
    r = ref - ref.mean(-1, keepdim=True)
    s = src - src.mean(-1, keepdim=True)
    cov = (r[:, None, :] * s).mean(-1)
    var_r = (r * r).mean(-1)[:, None]
    var_s = (s * s).mean(-1)
    return cov / torch.sqrt((var_r + eps) * (var_s + eps))
