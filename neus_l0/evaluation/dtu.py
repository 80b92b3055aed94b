"""The DTU evaluation protocol (as the widely used Python port of the MATLAB code does it).

Files, under the DTU evaluation folder (`SampleSet/MVS Data` in the download):

- `Points/stl/stl{scan:03}_total.ply`: the structured-light reference points (mm).
- `ObsMask/ObsMask{scan}_10.mat`: `ObsMask` (X, Y, Z) observability voxels, `BB` (2, 3)
  bounding box (min row, max row) and `Res` (voxel size, mm).
- `ObsMask/Plane{scan}.mat`: `P` (4,) the ground plane; reference points with
  P . [x, 1] > 0 are "above" it.

Protocol (`evaluate_dtu`), given predicted points already sampled and thinned:

1. "in box": lo = BB[0] - margin_low <= p < BB[1] + margin_high = hi (port: 60 and 2 x 60).
2. "in obs": the voxel `round((p - BB[0]) / Res)` lies inside ObsMask's shape and is set.
3. accuracy: distance of the in-box-and-in-obs predicted points to *all* STL points;
   completeness: distance of the STL points above the plane to the *in-box* predicted
   points (not restricted to ObsMask, exactly as the port); each the mean over
   distances < max_dist; overall: their mean.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.chamfer import ChamferResult, build_tree, chamfer, in_box

#: DTU protocol defaults (mm).
DTU_DENSITY = 0.2
DTU_MAX_DIST = 20.0
DTU_MARGIN_LOW = 60.0
DTU_MARGIN_HIGH = 120.0


@dataclass
class ObsMask:
    """DTU's observability mask.

    Attributes:
        mask: (X, Y, Z) bool voxels.
        bb: (2, 3) float64, rows = min corner, max corner (mm).
        res: voxel size (mm).
    """

    mask: np.ndarray
    bb: np.ndarray
    res: float


def dtu_paths(dtu_dir: str | os.PathLike, scan: int) -> dict[str, Path]:
    """The three evaluation files of `scan`: keys `stl`, `obs_mask`, `plane`."""
    root = Path(dtu_dir)
    return {
        "stl": root / "Points" / "stl" / f"stl{scan:03d}_total.ply",
        "obs_mask": root / "ObsMask" / f"ObsMask{scan}_10.mat",
        "plane": root / "ObsMask" / f"Plane{scan}.mat",
    }


def _loadmat(path: Path, keys: list[str]) -> dict[str, np.ndarray]:
    from scipy.io import loadmat

    if not path.is_file():
        raise NeusL0Error(f"{path}: file not found")
    try:
        data = loadmat(str(path))
    except Exception as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise NeusL0Error(f"{path}: cannot read .mat file ({msg})") from None
    missing = [k for k in keys if k not in data]
    if missing:
        raise NeusL0Error(f"{path}: missing key(s) {', '.join(missing)}")
    return {k: np.asarray(data[k]) for k in keys}


def load_obs_mask(path: str | os.PathLike) -> ObsMask:
    """Read `ObsMask{scan}_10.mat` (keys ObsMask, BB, Res).

    Raises:
        NeusL0Error: missing/unreadable file, missing keys or bad shapes.
    """
    path = Path(path)
    d = _loadmat(path, ["ObsMask", "BB", "Res"])
    mask, bb, res = d["ObsMask"], d["BB"], d["Res"]
    if mask.ndim != 3:
        raise NeusL0Error(f"{path}: ObsMask must be 3-D, got shape {mask.shape}")
    if bb.size != 6:
        raise NeusL0Error(f"{path}: BB must have 6 values (2x3), got shape {bb.shape}")
    if res.size != 1 or not float(res.ravel()[0]) > 0:
        raise NeusL0Error(f"{path}: Res must be one positive number")
    return ObsMask(mask=mask.astype(bool), bb=bb.astype(np.float64).reshape(2, 3),
                   res=float(res.ravel()[0]))


def load_plane(path: str | os.PathLike) -> np.ndarray:
    """Read `Plane{scan}.mat` (key P) as a (4,) float64 plane.

    Raises:
        NeusL0Error: missing/unreadable file, missing key or bad shape.
    """
    path = Path(path)
    p = _loadmat(path, ["P"])["P"]
    if p.size != 4:
        raise NeusL0Error(f"{path}: P must have 4 values, got shape {p.shape}")
    return p.astype(np.float64).reshape(4)


def box_bounds(obs: ObsMask, margin_low: float = DTU_MARGIN_LOW,
               margin_high: float = DTU_MARGIN_HIGH) -> tuple[np.ndarray, np.ndarray]:
    """(lo (3,), hi (3,)) = (BB[0] - margin_low, BB[1] + margin_high)."""
    return obs.bb[0] - margin_low, obs.bb[1] + margin_high


def in_obs_mask(points: np.ndarray, obs: ObsMask) -> np.ndarray:
    """(N,) bool: the voxel round((p - BB[0]) / Res) is inside ObsMask and set.

    Rounding is NumPy's (half to even), like the port's `np.around`.
    """
    points = np.asarray(points, dtype=np.float64)
    grid = np.rint((points - obs.bb[0]) / obs.res).astype(np.int64)  # (N, 3)
    inside = np.all((grid >= 0) & (grid < np.asarray(obs.mask.shape)), axis=1)
    out = np.zeros(len(points), dtype=bool)
    g = grid[inside]
    out[inside] = obs.mask[g[:, 0], g[:, 1], g[:, 2]]
    return out


def above_plane(points: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """(N,) bool: P . [p, 1] > 0 for the (4,) plane P."""
    points = np.asarray(points, dtype=np.float64)
    return points @ plane[:3] + plane[3] > 0


def evaluation_region(points: np.ndarray, obs: ObsMask, margin_low: float = DTU_MARGIN_LOW,
                      margin_high: float = DTU_MARGIN_HIGH) -> tuple[np.ndarray, np.ndarray]:
    """Which points are in the box and which are also in ObsMask.

    Args:
        points: (N, 3).

    Returns:
        in_box (N,) bool, in_obs (N,) bool (in_obs implies in_box).
    """
    lo, hi = box_bounds(obs, margin_low, margin_high)
    box = in_box(points, lo, hi)
    obs_in = np.zeros(len(points), dtype=bool)
    obs_in[box] = in_obs_mask(points[box], obs)
    return box, obs_in


def evaluate_dtu(pred_points: np.ndarray, stl_points: np.ndarray, obs: ObsMask,
                 plane: np.ndarray, max_dist: float = DTU_MAX_DIST,
                 margin_low: float = DTU_MARGIN_LOW, margin_high: float = DTU_MARGIN_HIGH,
                 workers: int = -1) -> tuple[ChamferResult, dict[str, np.ndarray]]:
    """Score predicted points (already sampled and thinned) with the DTU protocol.

    Args:
        pred_points: (N, 3) predicted points (mm).
        stl_points: (M, 3) STL reference points (mm).
        obs: the scan's observability mask.
        plane: (4,) ground plane.
        max_dist: truncation distance of both means.
        margin_low, margin_high: box margins below BB[0] and above BB[1].
        workers: kd-tree query threads.

    Returns:
        The result (counts: `pred_in_box`, `pred_kept`, `gt_total`, `gt_used`,
        `acc_within`, `comp_within`) and the masks `pred_in_box` (N,), `pred_kept` (N,),
        `gt_used` (M,).
    """
    box, kept = evaluation_region(pred_points, obs, margin_low, margin_high)
    gt_used = above_plane(stl_points, plane)
    res = chamfer(pred_points[kept], build_tree(stl_points), stl_points[gt_used],
                  build_tree(pred_points[box]), max_dist, workers=workers)
    res.counts = {"pred_in_box": int(box.sum()), "pred_kept": int(kept.sum()),
                  "gt_total": len(stl_points), "gt_used": int(gt_used.sum()), **res.counts}
    return res, {"pred_in_box": box, "pred_kept": kept, "gt_used": gt_used}
