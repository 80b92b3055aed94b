"""Ground truth of a synthetic scene folder and its visibility-based evaluation region.

Files read (see ARCHITECTURE.md, "A synthetic scene folder"): `gt_mesh.ply` (the exact true
surface), `gt_points.ply` (points on the true surface that some camera sees), `gt_depth.npz`
(`depth_i` (H, W): camera-z depth of the first true-surface hit through each pixel centre,
`inf` on misses) and `cameras_sphere.npz` (`world_mat_i`).

A predicted point p is *observed* by view i when, with P_n the depth-normalised projection
(`neus_l0.data.cameras.depth_projection`), z = (P_n [p, 1])_3 > 0, its pixel
(rint(x), rint(y)) lies inside the image, and z <= D_i(row, col) + depth_tol, where
D_i(row, col) is `inf` where `depth_i` is `inf` (the ray misses the object: nothing hides
the point) and otherwise the largest finite `depth_i` in the 3x3 window around the pixel
(so that a point between pixel centres on a slanted surface is not hidden by the
discretisation). The region mirrors DTU: the box is [min(gt) - margin_low, max(gt) +
margin_high); accuracy scores the predicted points in the box and observed by at least one
view; completeness scores all GT points.

Distances are point-to-mesh (`surface.MeshDistance`, exact point-to-triangle): accuracy
measures each kept predicted point to `gt_mesh.ply`, completeness each GT point to the
whole predicted mesh (the one that was sampled). The GT points are about 0.5 apart, so
nearest-GT-point distances would put a floor of about 0.25 under a perfect prediction.
A scene without `gt_mesh.ply`, or a call without the predicted mesh, falls back to
point-to-point on that side (accuracy: to all GT points; completeness: to the in-box
predicted points), and `ChamferResult.distance` says so.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neus_l0.data.cameras import (
    decompose_projection,
    depth_projection,
    pixel_indices,
    read_indexed,
    read_world_mats,
)
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.chamfer import (
    ChamferResult,
    chamfer_from_distances,
    in_box,
    nearest_distances,
)
from neus_l0.evaluation.io import load_mesh, load_points
from neus_l0.evaluation.surface import MeshDistance

#: Default depth tolerance (world units) of the visibility test.
DEPTH_TOL = 2.0
#: Points per visibility chunk.
VIS_CHUNK = 1_000_000

_DEPTH = re.compile(r"^depth_(\d+)$")


@dataclass
class SyntheticGT:
    """Ground truth of a synthetic scene.

    Attributes:
        points: (M, 3) float64 GT surface points seen by some camera.
        projections: (V, 3, 4) float64 `world_mat_i[:3, :4]`.
        depths: V arrays (H_i, W_i) float32 camera-z depth, `inf` on misses.
        surface: the exact true surface (`gt_mesh.ply`) indexed for point-to-mesh
            distances, or None when the scene has no `gt_mesh.ply`.
    """

    points: np.ndarray
    projections: np.ndarray
    depths: list[np.ndarray]
    surface: MeshDistance | None = None

    def distance_to_gt(self, points: np.ndarray, upper_bound: float,
                       workers: int = -1) -> np.ndarray:
        """(N,) distance of (N, 3) points to the true surface (`inf` if >= upper_bound).

        Point-to-mesh to `gt_mesh.ply`; nearest GT point when the scene has no mesh.
        """
        if self.surface is not None:
            return self.surface.query(points, upper_bound, workers=workers)
        return nearest_distances(points, self.points, upper_bound=upper_bound,
                                 workers=workers)


def load_depths(path: str | os.PathLike) -> list[np.ndarray]:
    """Read `gt_depth.npz` as a list of (H, W) float32 maps in index order.

    Raises:
        NeusL0Error: missing/unreadable file, no `depth_i` keys, gaps or bad shapes.
    """
    path = Path(path)
    if not path.is_file():
        raise NeusL0Error(f"{path}: file not found")
    maps = read_indexed(path, _DEPTH, np.float32, "depth_i")
    n = len(maps)
    for i in range(n):
        if maps[i].ndim != 2:
            raise NeusL0Error(f"{path}: depth_{i} must be 2-D, got shape {maps[i].shape}")
    return [maps[i] for i in range(n)]


def first_hits(scene_dir: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where every pixel's ray first meets the true surface, from `gt_depth.npz` (camera z)
    and the cameras.

    Returns:
        (V, H, W, 3) world points (NaN where the ray misses), the (V, H, W) depth maps and
        the (V, 3, 4) projections world -> pixels (`read_world_mats`).

    Raises:
        NeusL0Error: a missing or malformed file, or depth maps that do not match cameras.
    """
    root = Path(scene_dir)
    projections = read_world_mats(root)
    depths = load_depths(root / "gt_depth.npz")
    if len(depths) != len(projections) or len({d.shape for d in depths}) > 1:
        raise NeusL0Error(f"{root / 'gt_depth.npz'}: {len(depths)} depth maps of shapes "
                          f"{sorted({d.shape for d in depths})} for {len(projections)} cameras")
    depth = np.stack(depths).astype(np.float64)  # (V, H, W)
    H, W = depth.shape[1:]
    xs, ys = np.meshgrid(np.arange(W), np.arange(H))
    pix = np.stack([xs, ys, np.ones_like(xs)], -1).astype(np.float64)  # (H, W, 3)
    pts = np.empty(depth.shape + (3,))
    for v, P in enumerate(projections):
        K, c2w = decompose_projection(P)
        cam = pix @ np.linalg.inv(K).T  # (H, W, 3), z = 1
        d = np.where(np.isfinite(depth[v]), depth[v], np.nan)[..., None]
        pts[v] = (cam * d) @ c2w[:3, :3].T + c2w[:3, 3]
    return pts, depth, projections


def load_synthetic_gt(scene_dir: str | os.PathLike) -> SyntheticGT:
    """Read gt_points.ply, gt_depth.npz, the cameras and (if present) gt_mesh.ply.

    Raises:
        NeusL0Error: a missing or malformed file, or depth maps that do not match cameras.
    """
    root = Path(scene_dir)
    if not root.is_dir():
        raise NeusL0Error(f"{root}: scene folder not found")
    points = load_points(root / "gt_points.ply")
    projections = read_world_mats(root)
    depths = load_depths(root / "gt_depth.npz")
    if len(depths) != len(projections):
        raise NeusL0Error(f"{root / 'gt_depth.npz'}: {len(depths)} depth maps for "
                          f"{len(projections)} cameras")
    surface = None
    if (root / "gt_mesh.ply").is_file():
        surface = MeshDistance(*load_mesh(root / "gt_mesh.ply"))
    return SyntheticGT(points=points, projections=projections, depths=depths,
                       surface=surface)


def observed(points: np.ndarray, projections: np.ndarray, depths: list[np.ndarray],
             depth_tol: float = DEPTH_TOL, chunk: int = VIS_CHUNK) -> np.ndarray:
    """Which points at least one view observes (see the module docstring for the rule).

    Args:
        points: (N, 3) world points.
        projections: (V, 3, 4) world -> pixel projections.
        depths: V (H, W) depth maps (camera z, `inf` where the ray misses).
        depth_tol: how far (world units, camera z) behind the true surface still counts.
        chunk: points per chunk (memory bound).

    Returns:
        (N,) bool.
    """
    points = np.asarray(points, dtype=np.float64)
    p_n = depth_projection(projections)  # (V, 3, 4)
    dmax = [_max_finite_3x3(d) for d in depths]
    out = np.zeros(len(points), dtype=bool)
    for s in range(0, len(points), chunk):
        idx = np.arange(s, min(s + chunk, len(points)))
        for v in range(len(p_n)):
            if len(idx) == 0:
                break
            h, w = dmax[v].shape
            col, row, z = pixel_indices(p_n[v], points[idx], h, w)
            inside = col >= 0
            seen = np.zeros(len(idx), dtype=bool)
            seen[inside] = z[inside] <= dmax[v][row[inside], col[inside]] + depth_tol
            out[idx[seen]] = True
            idx = idx[~seen]  # only points not yet observed go on to the next view
    return out


def _max_finite_3x3(depth: np.ndarray) -> np.ndarray:
    """(H, W) max of the finite depths in each 3x3 window; `inf` where the pixel misses."""
    from scipy.ndimage import maximum_filter

    d = np.asarray(depth, dtype=np.float32)
    finite = np.isfinite(d)
    m = maximum_filter(np.where(finite, d, -np.inf), size=3, mode="nearest")
    return np.where(finite, m, np.inf)


def gt_box(gt_points: np.ndarray, margin_low: float,
           margin_high: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo (3,), hi (3,)) = (min(gt) - margin_low, max(gt) + margin_high)."""
    return gt_points.min(axis=0) - margin_low, gt_points.max(axis=0) + margin_high


def evaluation_region(points: np.ndarray, gt: SyntheticGT, margin_low: float,
                      margin_high: float, depth_tol: float = DEPTH_TOL
                      ) -> tuple[np.ndarray, np.ndarray]:
    """in_box (N,) bool and kept = in_box & observed (N,) bool."""
    lo, hi = gt_box(gt.points, margin_low, margin_high)
    box = in_box(points, lo, hi)
    kept = np.zeros(len(points), dtype=bool)
    kept[box] = observed(points[box], gt.projections, gt.depths, depth_tol)
    return box, kept


def evaluate_synthetic(pred_points: np.ndarray, gt: SyntheticGT, max_dist: float = 20.0,
                       margin_low: float = 60.0, margin_high: float = 120.0,
                       depth_tol: float = DEPTH_TOL, workers: int = -1,
                       pred_mesh: tuple[np.ndarray, np.ndarray] | MeshDistance | None = None
                       ) -> tuple[ChamferResult, dict[str, np.ndarray]]:
    """Score predicted points (already sampled and thinned) against a synthetic scene.

    Args:
        pred_points: (N, 3) predicted points (world units), sampled from `pred_mesh`.
        gt: the scene's ground truth.
        max_dist: truncation distance of both means.
        margin_low, margin_high: box margins around the GT points' bounding box.
        depth_tol: visibility depth tolerance.
        workers: kd-tree query threads.
        pred_mesh: the predicted mesh ((V, 3) vertices, (F, 3) faces, or an indexed
            `MeshDistance`): completeness is then the exact distance of each GT point to
            its surface (the whole mesh: any part outside the box is at least
            min(margin_low, margin_high) from every GT point). None: to the in-box points.

    Returns:
        The result (counts: `pred_in_box`, `pred_kept`, `gt_total`, `gt_used`,
        `acc_within`, `comp_within`; `distance`: "point-to-mesh" when both sides are
        measured to surfaces) and masks `pred_in_box` (N,), `pred_kept` (N,),
        `gt_used` (M,) (all true: the GT points are already restricted to what is seen).
    """
    pred_points = np.asarray(pred_points, dtype=np.float64).reshape(-1, 3)
    box, kept = evaluation_region(pred_points, gt, margin_low, margin_high, depth_tol)
    gt_used = np.ones(len(gt.points), dtype=bool)
    d_acc = gt.distance_to_gt(pred_points[kept], max_dist, workers=workers)
    if pred_mesh is not None:
        surf = pred_mesh if isinstance(pred_mesh, MeshDistance) else MeshDistance(*pred_mesh)
        d_comp = surf.query(gt.points, max_dist, workers=workers)
    else:
        d_comp = nearest_distances(gt.points, pred_points[box], upper_bound=max_dist,
                                   workers=workers)
    kinds = ("point-to-mesh" if gt.surface is not None else "point-to-point",
             "point-to-mesh" if pred_mesh is not None else "point-to-point")
    distance = (kinds[0] if kinds[0] == kinds[1]
                else f"accuracy: {kinds[0]}, completeness: {kinds[1]}")
    res = chamfer_from_distances(d_acc, d_comp, max_dist, distance)
    res.counts = {"pred_in_box": int(box.sum()), "pred_kept": int(kept.sum()),
                  "gt_total": len(gt.points), "gt_used": int(gt_used.sum()), **res.counts}
    return res, {"pred_in_box": box, "pred_kept": kept, "gt_used": gt_used}
