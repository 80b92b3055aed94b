"""A mesh's surface as the training views see it: dense surface samples and their silhouette
in a view (`neus_l0.mesh.underside`, `neus_l0.mesh.missed_parts`)."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import ndimage

from neus_l0.data.cameras import decompose_projection, depth_projection, pixel_indices

SAMPLES_PER_PIXEL = 4.0
"""Surface samples per pixel footprint (the finest footprint over the views, at the mesh's
centre)."""
MAX_SAMPLES = 2_000_000
"""The most surface samples drawn."""


def foot_ratio(projection: np.ndarray) -> float:
    """World size of one pixel per unit of camera depth (1 / the focal length in pixels)."""
    return 1.0 / abs(decompose_projection(projection)[0][0, 0])


def finest_footprint(mesh: trimesh.Trimesh, projections: np.ndarray) -> float:
    """The smallest pixel footprint (world units) over the views, at the mesh's centre."""
    P_n = depth_projection(np.asarray(projections, dtype=np.float64))
    centre = np.r_[np.asarray(mesh.vertices, dtype=np.float64).mean(axis=0), 1.0]
    return min(abs(float(P_n[v][2] @ centre)) * foot_ratio(projections[v])
               for v in range(len(P_n)))


def surface_samples(mesh: trimesh.Trimesh, projections: np.ndarray,
                    seed: int = 0) -> np.ndarray:
    """(n, 3) points drawn uniformly on the surface of `mesh` (world units), about
    `SAMPLES_PER_PIXEL` per finest pixel footprint (`finest_footprint`; 10^4 to
    `MAX_SAMPLES`)."""
    foot = finest_footprint(mesh, projections)
    n = int(min(MAX_SAMPLES, max(1e4, SAMPLES_PER_PIXEL * mesh.area / foot**2)))
    return trimesh.sample.sample_surface(mesh, n, seed=seed)[0]


def silhouette(samples: np.ndarray, depth_projection_row: np.ndarray,
               shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool the pixels the surface samples fall on, grown by a 3x3 dilation so that
    no gap between samples reads as empty.

    Args:
        samples: (n, 3) surface samples, world units (`surface_samples`).
        depth_projection_row: (3, 4) the view's projection (`depth_projection`'s).
        shape: the image's (H, W).
    """
    h, w = shape
    col, row, _ = pixel_indices(depth_projection_row, samples, h, w)
    ok = col >= 0
    cover = np.zeros((h, w), bool)
    cover[row[ok], col[ok]] = True
    return ndimage.binary_dilation(cover, np.ones((3, 3), bool))
