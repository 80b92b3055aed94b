"""Similarity (Umeyama) alignment of point sets and camera pose errors after alignment.

Pure numpy float64 functions. A similarity maps ``x -> s * R @ x + t``.
"""

from __future__ import annotations

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True
            ) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity taking `src` onto `dst` (Umeyama 1991).

    Minimises ``sum_i |dst_i - (s R src_i + t)|^2`` over s > 0, R in SO(3), t.

    Args:
        src: (N, 3) points, N >= 3 and not all collinear.
        dst: (N, 3) corresponding points.
        with_scale: estimate s (otherwise s = 1, a rigid alignment).

    Returns:
        s: scale (float).
        R: (3, 3) rotation, det +1.
        t: (3,) translation.

    Raises:
        ValueError: mismatched shapes, fewer than 3 points, or degenerate (collinear) input.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama: need two (N, 3) arrays, got {src.shape} and {dst.shape}")
    if src.shape[0] < 3:
        raise ValueError(f"umeyama: need at least 3 points, got {src.shape[0]}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)  # (3, 3)
    U, D, Vt = np.linalg.svd(cov)
    if D[1] <= 1e-12 * max(D[0], 1e-300):
        raise ValueError("umeyama: degenerate input (points collinear or coincident)")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float((D * np.diag(S)).sum() / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle (degrees) of the relative rotation ``Ra^T Rb``.

    Args:
        Ra: (..., 3, 3) rotations.
        Rb: (..., 3, 3) rotations.

    Returns:
        (...) angles in [0, 180].
    """
    rel = np.swapaxes(Ra, -1, -2) @ Rb
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def pose_errors(c2w_est: np.ndarray, c2w_true: np.ndarray, object_size: float) -> dict:
    """Camera errors after a similarity alignment of the estimated centres to the true ones.

    Args:
        c2w_est: (N, 4, 4) or (N, 3, 4) estimated camera-to-world poses (any frame and scale).
        c2w_true: (N, 4, 4) or (N, 3, 4) true poses, same view order.
        object_size: length that centre errors are divided by (e.g. the object's diameter).

    Returns:
        dict with ``scale``, ``R`` (3, 3), ``t`` (3,) of the alignment (est -> true),
        ``center_err`` (N,) world units, ``rot_err_deg`` (N,), and the summaries
        ``center_err_mean_rel`` / ``center_err_max_rel`` (relative to `object_size`) and
        ``rot_err_mean_deg`` / ``rot_err_max_deg``.
    """
    c2w_est = np.asarray(c2w_est, dtype=np.float64)
    c2w_true = np.asarray(c2w_true, dtype=np.float64)
    s, R, t = umeyama(c2w_est[:, :3, 3], c2w_true[:, :3, 3])
    centres = s * c2w_est[:, :3, 3] @ R.T + t
    center_err = np.linalg.norm(centres - c2w_true[:, :3, 3], axis=-1)
    rot_err = rotation_angle_deg(R @ c2w_est[:, :3, :3], c2w_true[:, :3, :3])
    return {
        "scale": s, "R": R, "t": t,
        "center_err": center_err, "rot_err_deg": rot_err,
        "center_err_mean_rel": float(center_err.mean() / object_size),
        "center_err_max_rel": float(center_err.max() / object_size),
        "rot_err_mean_deg": float(rot_err.mean()),
        "rot_err_max_deg": float(rot_err.max()),
    }
