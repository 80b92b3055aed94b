"""How far the up-sampled (fine) samples lie from the true surface (the paper's Fig. 1c).

A fixed set of rays that hit the object (pixels well inside the training masks, drawn once
from a seeded generator, so every sampler and seed sees the same rays) is rendered with
`neus_l0.render.volume.render_rays` without jitter; its ``z_fine`` (B, n_importance) are the
up-sampled positions along each ray in the normalised frame. They are mapped to world units
with the scene's ``scale_mat`` and measured against the ground truth: the exact
point-to-triangle distance to ``gt_mesh.ply`` (`neus_l0.evaluation.surface.MeshDistance`),
or, for scenes without that file, the distance to the nearest point of ``gt_points.ply``.
`sample_dist` is the mean over all fine samples of all rays, in world units.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neus_l0.data.cameras import to_world
from neus_l0.data.rays import pixel_grid, pixel_rays
from neus_l0.data.scene import Scene

#: A mask value above which a pixel counts as surely on the object (soft after downscale).
MASK_INSIDE = 0.99


class SurfaceDistance:
    """Distance of world-unit points to a scene's true surface.

    Args:
        vertices, faces: the true surface as a triangle mesh (exact distances), or
        points: surface points (nearest-point distances) when no mesh is given.
    """

    def __init__(self, vertices: np.ndarray | None = None, faces: np.ndarray | None = None,
                 points: np.ndarray | None = None):
        if vertices is not None and faces is not None:
            from neus_l0.evaluation.surface import MeshDistance

            self.kind = "mesh"
            self._mesh = MeshDistance(vertices, faces)
        elif points is not None:
            from scipy.spatial import cKDTree

            self.kind = "points"
            self._tree = cKDTree(np.asarray(points, dtype=np.float64))
        else:
            raise ValueError("SurfaceDistance needs a mesh (vertices, faces) or points")

    @classmethod
    def from_scene_dir(cls, root: str | Path) -> SurfaceDistance | None:
        """The ground truth of a synthetic scene folder; None when it has none."""
        from neus_l0.evaluation.io import load_mesh, load_points

        root = Path(root)
        if (root / "gt_mesh.ply").is_file():
            return cls(*load_mesh(root / "gt_mesh.ply"))
        if (root / "gt_points.ply").is_file():
            return cls(points=load_points(root / "gt_points.ply"))
        return None

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N,) float64 distances of (N, 3) world points to the surface."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.kind == "mesh":
            return self._mesh.query(pts, workers=1)
        return self._tree.query(pts, k=1, workers=1)[0]


def object_rays(scene: Scene, n_rays: int, seed: int = 0) -> tuple[Tensor, Tensor]:
    """`n_rays` rays through pixels inside the scene's masks (mask > `MASK_INSIDE`).

    The pixels are drawn without replacement from a CPU generator seeded with `seed`, so the
    choice depends only on the scene and the seed.

    Returns:
        origins (B, 3), dirs (B, 3) in the normalised frame on the scene's device,
        B = min(n_rays, number of inside pixels); B = 0 when the scene has no masks.
    """
    if not scene.has_masks:
        empty = torch.zeros(0, 3, device=scene.device)
        return empty, empty
    inside = (scene.masks > MASK_INSIDE).reshape(-1).cpu()  # (V*H*W,)
    flat = inside.nonzero().reshape(-1)
    g = torch.Generator().manual_seed(seed)
    pick = flat[torch.randperm(len(flat), generator=g)[:n_rays]].sort().values
    hw = scene.height * scene.width
    view, pix = pick // hw, pick % hw
    xy = pixel_grid(scene.height, scene.width).reshape(-1, 2)[pix]  # (B, 2)
    dev = scene.device
    return pixel_rays(scene.intrinsics[view.to(dev)], scene.c2w[view.to(dev)], xy.to(dev))


def fine_points_world(origins: Tensor, dirs: Tensor, z_fine: Tensor,
                      scale_mat: np.ndarray) -> np.ndarray:
    """World positions of the fine samples.

    Args:
        origins, dirs: (B, 3) normalised frame.
        z_fine: (B, S) distances along the rays (normalised frame).
        scale_mat: (4, 4) normalised -> world.

    Returns:
        (B * S, 3) float64 world points.
    """
    pts = origins[:, None, :] + dirs[:, None, :] * z_fine[..., None]  # (B, S, 3)
    return to_world(pts.reshape(-1, 3).detach().double().cpu().numpy(), scale_mat)
