"""Ground truth of a synthetic scene folder and its visibility-based evaluation region.

Files read (see ARCHITECTURE.md, "A synthetic scene folder"): `gt_points.ply` (points on
the true surface that some camera sees), `gt_depth.npz` (`depth_i` (H, W): camera-z depth of
the first true-surface hit through each pixel centre, `inf` on misses) and
`cameras_sphere.npz` (`world_mat_i`).

A predicted point p is *observed* by view i when, with P_n the depth-normalised projection
(`_scene.depth_projections`), z = (P_n [p, 1])_3 > 0, its pixel (rint(x), rint(y)) lies
inside the image, and z <= D_i(row, col) + depth_tol, where D_i(row, col) is `inf` where
`depth_i` is `inf` (the ray misses the object: nothing hides the point) and otherwise the
largest finite `depth_i` in the 3x3 window around the pixel (so that a point between pixel
centres on a slanted surface is not hidden by the discretisation). The evaluation mirrors
DTU: the box is [min(gt) - margin_low, max(gt) + margin_high); accuracy scores the
predicted points in the box and observed by at least one view against all GT points;
completeness scores all GT points against the predicted points in the box.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error
from neus_l0.evaluation._scene import depth_projections, project, read_world_mats
from neus_l0.evaluation.chamfer import ChamferResult, build_tree, chamfer, in_box
from neus_l0.evaluation.io import load_points

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
    """

    points: np.ndarray
    projections: np.ndarray
    depths: list[np.ndarray]


def load_depths(path: str | os.PathLike) -> list[np.ndarray]:
    """Read `gt_depth.npz` as a list of (H, W) float32 maps in index order.

    Raises:
        NeusL0Error: missing/unreadable file, no `depth_i` keys, gaps or bad shapes.
    """
    path = Path(path)
    if not path.is_file():
        raise NeusL0Error(f"{path}: file not found")
    try:
        with np.load(path) as data:
            maps = {int(m.group(1)): np.asarray(data[k], dtype=np.float32)
                    for k in data.files if (m := _DEPTH.match(k))}
    except Exception as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise NeusL0Error(f"{path}: cannot read ({msg})") from None
    if not maps:
        raise NeusL0Error(f"{path}: no depth_i keys")
    n = len(maps)
    if sorted(maps) != list(range(n)):
        raise NeusL0Error(f"{path}: depth_i indices are not 0..{n - 1}")
    for i in range(n):
        if maps[i].ndim != 2:
            raise NeusL0Error(f"{path}: depth_{i} must be 2-D, got shape {maps[i].shape}")
    return [maps[i] for i in range(n)]


def load_synthetic_gt(scene_dir: str | os.PathLike) -> SyntheticGT:
    """Read gt_points.ply, gt_depth.npz and the cameras of a synthetic scene folder.

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
    return SyntheticGT(points=points, projections=projections, depths=depths)


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
    p_n = depth_projections(projections)
    dmax = [_max_finite_3x3(d) for d in depths]
    out = np.zeros(len(points), dtype=bool)
    for s in range(0, len(points), chunk):
        idx = np.arange(s, min(s + chunk, len(points)))
        for v in range(len(p_n)):
            if len(idx) == 0:
                break
            h, w = dmax[v].shape
            col, row, z = project(points[idx], p_n[v])
            inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
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
                       depth_tol: float = DEPTH_TOL, workers: int = -1
                       ) -> tuple[ChamferResult, dict[str, np.ndarray]]:
    """Score predicted points (already sampled and thinned) against a synthetic scene.

    Args:
        pred_points: (N, 3) predicted points (world units).
        gt: the scene's ground truth.
        max_dist: truncation distance of both means.
        margin_low, margin_high: box margins around the GT points' bounding box.
        depth_tol: visibility depth tolerance.
        workers: kd-tree query threads.

    Returns:
        The result (counts: `pred_in_box`, `pred_kept`, `gt_total`, `gt_used`,
        `acc_within`, `comp_within`) and masks `pred_in_box` (N,), `pred_kept` (N,),
        `gt_used` (M,) (all true: the GT points are already restricted to what is seen).
    """
    box, kept = evaluation_region(pred_points, gt, margin_low, margin_high, depth_tol)
    gt_used = np.ones(len(gt.points), dtype=bool)
    res = chamfer(pred_points[kept], build_tree(gt.points), gt.points,
                  build_tree(pred_points[box]), max_dist, workers=workers)
    res.counts = {"pred_in_box": int(box.sum()), "pred_kept": int(kept.sum()),
                  "gt_total": len(gt.points), "gt_used": int(gt_used.sum()), **res.counts}
    return res, {"pred_in_box": box, "pred_kept": kept, "gt_used": gt_used}
