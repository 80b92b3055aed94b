"""Chunked nearest-neighbour distances and the truncated means of the DTU protocol."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

#: Query points handled per `cKDTree.query` call.
QUERY_CHUNK = 1_000_000


def build_tree(points: np.ndarray) -> cKDTree:
    """A `cKDTree` over (N, 3) points (float64), for repeated `nearest_distances` calls."""
    return cKDTree(np.asarray(points, dtype=np.float64))


def nearest_distances(query: np.ndarray, reference: np.ndarray | cKDTree,
                      upper_bound: float = math.inf, chunk: int = QUERY_CHUNK,
                      workers: int = -1) -> np.ndarray:
    """Distance from each query point to its nearest reference point.

    Args:
        query: (N, 3) points.
        reference: (M, 3) points, or a tree from `build_tree`.
        upper_bound: distances above this bound come back as `inf` (faster queries).
        chunk: query points per `cKDTree.query` call (bounds memory).
        workers: threads for the query (-1: all cores).

    Returns:
        (N,) float64 distances; all `inf` when the reference is empty.
    """
    query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
    tree = reference if isinstance(reference, cKDTree) else build_tree(reference)
    out = np.full(len(query), np.inf)
    if tree.n == 0:
        return out
    for s in range(0, len(query), chunk):
        d, _ = tree.query(query[s:s + chunk], k=1, distance_upper_bound=upper_bound,
                          workers=workers)
        out[s:s + chunk] = d
    return out


def truncated_mean(distances: np.ndarray, max_dist: float) -> float:
    """Mean of the distances below `max_dist` (DTU drops the rest); NaN when none are.

    Args:
        distances: (N,) distances (`inf` allowed).
        max_dist: strict upper bound of the distances that count.

    Returns:
        The mean as a Python float.
    """
    d = np.asarray(distances)
    d = d[d < max_dist]
    return float(d.mean()) if len(d) else math.nan


@dataclass
class ChamferResult:
    """Accuracy / completeness of a prediction, with the per-point distances behind them.

    Attributes:
        accuracy: mean distance of the scored predicted points to the ground truth,
            over distances < max_dist (NaN when there are none).
        completeness: mean distance of the scored ground-truth points to the prediction,
            over distances < max_dist (NaN when there are none).
        overall: (accuracy + completeness) / 2.
        max_dist: the truncation distance.
        dist_pred: (N_pred,) distance of each scored predicted point (`inf` beyond max_dist).
        dist_gt: (N_gt,) distance of each scored ground-truth point (`inf` beyond max_dist).
        counts: point counts of the protocol's stages (names documented in EVALUATION.md).
        distance: how distances were measured: "point-to-point" (nearest point, DTU),
            "point-to-mesh" (exact distance to the other side's surface) or, when the two
            sides differ, "accuracy: <kind>, completeness: <kind>".
    """

    accuracy: float
    completeness: float
    overall: float
    max_dist: float
    dist_pred: np.ndarray
    dist_gt: np.ndarray
    counts: dict[str, int] = field(default_factory=dict)
    distance: str = "point-to-point"


def chamfer(acc_points: np.ndarray, acc_reference: np.ndarray | cKDTree,
            comp_points: np.ndarray, comp_reference: np.ndarray | cKDTree,
            max_dist: float, workers: int = -1) -> ChamferResult:
    """Accuracy and completeness from the two point sets each is measured on.

    The DTU protocol measures accuracy and completeness on different subsets (accuracy:
    predicted points inside the observation mask against all GT points; completeness: GT
    points above the plane against the predicted points inside the box), so both pairs
    are explicit.

    Args:
        acc_points: (N, 3) predicted points scored for accuracy.
        acc_reference: (M, 3) ground-truth points (or their tree) they are measured to.
        comp_points: (K, 3) ground-truth points scored for completeness.
        comp_reference: (L, 3) predicted points (or their tree) they are measured to.
        max_dist: distances >= max_dist are left out of the means.
        workers: query threads.

    Returns:
        A `ChamferResult` (counts: `acc_within`, `comp_within`).
    """
    d_acc = nearest_distances(acc_points, acc_reference, upper_bound=max_dist, workers=workers)
    d_comp = nearest_distances(comp_points, comp_reference, upper_bound=max_dist,
                               workers=workers)
    return chamfer_from_distances(d_acc, d_comp, max_dist)


def chamfer_from_distances(d_acc: np.ndarray, d_comp: np.ndarray, max_dist: float,
                           distance: str = "point-to-point") -> ChamferResult:
    """Accuracy and completeness from per-point distances measured elsewhere.

    Args:
        d_acc: (N,) distance of each scored predicted point to the ground truth.
        d_comp: (K,) distance of each scored ground-truth point to the prediction.
        max_dist: distances >= max_dist are left out of the means.
        distance: how they were measured (stored in `ChamferResult.distance`).

    Returns:
        A `ChamferResult` (counts: `acc_within`, `comp_within`).
    """
    d_acc = np.asarray(d_acc, dtype=np.float64)
    d_comp = np.asarray(d_comp, dtype=np.float64)
    acc = truncated_mean(d_acc, max_dist)
    comp = truncated_mean(d_comp, max_dist)
    counts = {"acc_within": int((d_acc < max_dist).sum()),
              "comp_within": int((d_comp < max_dist).sum())}
    return ChamferResult(accuracy=acc, completeness=comp, overall=(acc + comp) / 2,
                         max_dist=float(max_dist), dist_pred=d_acc, dist_gt=d_comp,
                         counts=counts, distance=distance)


def in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) bool: lo <= p < hi on every axis (half-open, as DTU's port).

    Args:
        points: (N, 3).
        lo, hi: (3,) box corners.
    """
    points = np.asarray(points)
    return np.all((points >= np.asarray(lo)) & (points < np.asarray(hi)), axis=1)
