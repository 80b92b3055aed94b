"""Error-coloured PLY files: the prediction coloured by accuracy, the GT by completeness."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.io import write_ply_mesh, write_ply_points

#: Colour of points left out of the score (outside the region, below the plane).
EXCLUDED_RGBA = (160, 160, 160, 255)


def check_cmap(name: str) -> None:
    """Refuse a name that matplotlib's colormap registry does not hold (before any work).

    Raises:
        NeusL0Error: one line naming the flag and a few valid names.
    """
    import matplotlib

    if name not in matplotlib.colormaps:
        raise NeusL0Error(f"--cmap {name}: not a matplotlib colormap (e.g. jet, viridis, "
                          "turbo, magma)")


def colorize(distances: np.ndarray, vmax: float, cmap: str = "jet",
             include: np.ndarray | None = None) -> np.ndarray:
    """Map distances in [0, vmax] to colours (clipped above; `inf` maps to vmax).

    Args:
        distances: (N,) non-negative distances.
        vmax: distance of the top of the colour scale.
        cmap: matplotlib colormap name.
        include: optional (N,) bool; excluded points get `EXCLUDED_RGBA`.

    Returns:
        (N, 4) uint8 RGBA.
    """
    import matplotlib

    t = np.clip(np.nan_to_num(np.asarray(distances, dtype=np.float64), nan=vmax,
                              posinf=vmax) / vmax, 0.0, 1.0)
    rgba = (matplotlib.colormaps[cmap](t) * 255).round().astype(np.uint8)
    if include is not None:
        rgba[~include] = EXCLUDED_RGBA
    return rgba


def write_error_maps(out_dir: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray,
                     vertex_dist: np.ndarray, vertex_scored: np.ndarray,
                     gt_points: np.ndarray, gt_dist: np.ndarray, gt_scored: np.ndarray,
                     vmax: float, cmap: str = "jet") -> dict[str, Path]:
    """Write `accuracy.ply` (mesh, vertex colours) and `completeness.ply` (GT points).

    Args:
        out_dir: output folder (created).
        vertices: (V, 3) and faces (F, 3): the (culled) predicted mesh.
        vertex_dist: (V,) distance of each vertex to the GT points.
        vertex_scored: (V,) bool, vertices inside the evaluation region (others grey).
        gt_points: (M, 3) GT points.
        gt_dist: (M,) distance of each GT point to the prediction.
        gt_scored: (M,) bool, GT points that count for completeness (others grey).
        vmax: top of the shared colour scale.
        cmap: matplotlib colormap.

    Returns:
        {"accuracy": path, "completeness": path}.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    acc = write_ply_mesh(out / "accuracy.ply", vertices, faces,
                         colorize(vertex_dist, vmax, cmap, vertex_scored))
    comp = write_ply_points(out / "completeness.ply", gt_points,
                            colorize(gt_dist, vmax, cmap, gt_scored))
    return {"accuracy": acc, "completeness": comp}
