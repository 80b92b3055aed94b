"""The visual hull at pixel resolution, as a point test: is a point inside every view's mask?

`neus_l0.bounds.hull` carves a grid of cells (128 per axis by default, dilated by one cell),
which is right for bounding the samples but several world units wide around a thin part. A
point test has no grid: a point ``x`` is *inside the silhouettes* when every view that sees
it (in front of the camera, its nearest pixel in the image) has a foreground pixel centre
(mask > 0) within `margin_px` pixels of that nearest pixel. Views that do not see the
point, and views whose mask is empty (`neus_l0.bounds.hull` does not trust them either),
say nothing. The object is inside the silhouettes wherever every mask covers its projection
up to `margin_px` (the hull's rule for a cell of size 0, with the nearest pixel's rounding).

Use: along a ray whose mask is 1 that sees a thin part against the background, the points
inside the silhouettes are a short segment at the part (on `pits-deep`'s r1 rod, 9 of 32
samples, 0.5-2 world units from its axis), while the grid hull's span is 18-72 units long
(issue #35; `train.fill_silhouettes`).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from neus_l0.bounds.hull import background_distance

if TYPE_CHECKING:
    from neus_l0.data.scene import Scene

__all__ = ["Silhouettes", "in_silhouettes"]


@dataclasses.dataclass(frozen=True)
class Silhouettes:
    """Every view's mask widened by a margin, flat, with its camera.

    Attributes:
        covered: (V * H * W,) bool, pixel ``view * H * W + y * W + x`` lies within
            `margin_px` of a foreground pixel centre (all True for an empty mask).
        height, width: the images' size.
        proj: (V, 3, 3) A^-1 = K R^T (world offset from the centre -> homogeneous pixel).
        centres: (V, 3) camera centres.
    """

    covered: Tensor
    height: int
    width: int
    proj: Tensor
    centres: Tensor

    @classmethod
    def from_scene(cls, scene: Scene, margin_px: float) -> Silhouettes:
        """The silhouettes of a scene's views (`neus_l0.data.scene.Scene` with masks)."""
        cover = []
        for v in range(scene.n_views):
            mask = scene.masks[v]
            if not bool((mask > 0).any()):
                cover.append(torch.ones(mask.shape, dtype=torch.bool))
                continue
            cover.append(background_distance(mask) <= margin_px)
        covered = torch.stack(cover).reshape(-1).to(scene.masks.device)
        proj = torch.linalg.inv(scene.ray_matrices.double()).to(scene.c2w.dtype)
        return cls(covered, scene.height, scene.width, proj, scene.centres)


def in_silhouettes(points: Tensor, sil: Silhouettes) -> Tensor:
    """Which points every view that sees them covers (see the module docstring).

    Args:
        points: (P, 3) points in the normalised frame.
        sil: the views' `Silhouettes`.

    Returns:
        (P,) bool.
    """
    rel = points[None, :, :] - sil.centres[:, None, :]  # (V, P, 3)
    h = rel @ sil.proj.transpose(-1, -2)  # (V, P, 3)
    z = h[..., 2]
    safe = torch.where(z > 0, z, torch.ones_like(z))
    x = torch.floor(h[..., 0] / safe + 0.5)
    y = torch.floor(h[..., 1] / safe + 0.5)
    seen = (z > 0) & (x >= 0) & (x <= sil.width - 1) & (y >= 0) & (y <= sil.height - 1)
    xi = x.clamp(0, sil.width - 1).long()
    yi = y.clamp(0, sil.height - 1).long()
    view = torch.arange(rel.shape[0], device=points.device)[:, None]
    covered = sil.covered[(view * sil.height + yi) * sil.width + xi]  # (V, P)
    return (covered | ~seen).all(dim=0)
