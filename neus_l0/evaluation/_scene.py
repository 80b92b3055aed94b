"""A tiny private reader of what evaluation needs from a NeuS-format scene folder.

Kept separate from `neus_l0.data` on purpose: evaluation reads world-unit projections
(`world_mat_i[:3, :4]`) and raw masks only, and must not depend on the training loader.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error

_WORLD_MAT = re.compile(r"^world_mat_(\d+)$")


def read_world_mats(scene_dir: str | Path) -> np.ndarray:
    """Projections world -> pixels of every view, in index order.

    Args:
        scene_dir: folder with `cameras_sphere.npz` (or legacy `cameras.npz`).

    Returns:
        (V, 3, 4) float64: `world_mat_i[:3, :4]` for i = 0 .. V-1.

    Raises:
        NeusL0Error: missing/unreadable file, no `world_mat_i`, gaps or bad shapes.
    """
    root = Path(scene_dir)
    path = root / "cameras_sphere.npz"
    if not path.is_file() and (root / "cameras.npz").is_file():
        path = root / "cameras.npz"
    if not path.is_file():
        raise NeusL0Error(f"{path}: file not found")
    mats = read_indexed(path, _WORLD_MAT, np.float64, "world_mat_i")
    n = len(mats)
    out = np.empty((n, 3, 4))
    for i in range(n):
        m = mats[i]
        if m.shape not in ((4, 4), (3, 4)) or not np.isfinite(m).all():
            raise NeusL0Error(f"{path}: world_mat_{i} must be a finite 3x4 or 4x4 matrix")
        out[i] = m[:3, :4]
    return out


def read_masks(scene_dir: str | Path, n_views: int | None = None) -> list[np.ndarray]:
    """Foreground masks `mask/*.png` in sorted name order (> 127 = foreground).

    Args:
        scene_dir: scene folder.
        n_views: expected number of masks (checked when given).

    Returns:
        n_views (H, W) bool arrays.

    Raises:
        NeusL0Error: no mask folder/files, unreadable image, or a count mismatch.
    """
    import cv2

    folder = Path(scene_dir) / "mask"
    files = sorted(folder.glob("*.png"))
    if not files:
        raise NeusL0Error(f"{folder}: no mask/*.png files")
    if n_views is not None and len(files) != n_views:
        raise NeusL0Error(f"{folder}: {len(files)} masks for {n_views} cameras")
    masks = []
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise NeusL0Error(f"{f}: cannot read image")
        if img.ndim == 3:
            img = img[..., :3].max(axis=-1)
        masks.append(img > 127)
    return masks


def depth_projections(projections: np.ndarray) -> np.ndarray:
    """Scale each P so that row 3 gives camera-z depth: P / norm(P[2, :3]), sign fixed.

    The sign is that of det(P[:, :3]), so that points in front of the camera have
    positive depth (P = K[R|t] with K's diagonal positive has det > 0).

    Args:
        projections: (V, 3, 4).

    Returns:
        (V, 3, 4) float64.
    """
    p = np.asarray(projections, dtype=np.float64)
    sign = np.sign(np.linalg.det(p[:, :, :3]))
    sign[sign == 0] = 1.0
    norm = np.linalg.norm(p[:, 2, :3], axis=-1)
    return p * (sign / norm)[:, None, None]


def project(points: np.ndarray, p_n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project points with one normalised projection.

    Args:
        points: (N, 3) world points.
        p_n: (3, 4) from `depth_projections`.

    Returns:
        col (N,) int64 = rint(x), row (N,) int64 = rint(y), z (N,) camera-z depth.
        Points with z <= 0 get col = row = -1.
    """
    h = points @ p_n[:, :3].T + p_n[:, 3]  # (N, 3)
    z = h[:, 2]
    front = z > 0
    col = np.full(len(points), -1, dtype=np.int64)
    row = np.full(len(points), -1, dtype=np.int64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        x = h[front, 0] / z[front]
        y = h[front, 1] / z[front]
    big = 2.0**40  # avoids int overflow for points next to the camera plane
    col[front] = np.rint(np.clip(x, -big, big)).astype(np.int64)
    row[front] = np.rint(np.clip(y, -big, big)).astype(np.int64)
    return col, row, z


def read_indexed(path: Path, pattern: re.Pattern, dtype: type, what: str) -> dict:
    """Arrays stored as ``name_i`` keys of an npz file, checked to be numbered 0..n-1.

    Args:
        path: the .npz file (must exist).
        pattern: regex whose group 1 is the index i.
        dtype: NumPy dtype of the returned arrays.
        what: the key family's name for error messages (e.g. ``world_mat_i``).

    Returns:
        {i: array} for i in 0..n-1.

    Raises:
        NeusL0Error: unreadable file, no matching keys, or gaps in the numbering.
    """
    try:
        with np.load(path) as data:
            arrays = {int(m.group(1)): np.asarray(data[k], dtype=dtype)
                      for k in data.files if (m := pattern.match(k))}
    except Exception as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise NeusL0Error(f"{path}: cannot read ({msg})") from None
    if not arrays:
        raise NeusL0Error(f"{path}: no {what} keys")
    n = len(arrays)
    if sorted(arrays) != list(range(n)):
        raise NeusL0Error(f"{path}: {what} indices are not 0..{n - 1}")
    return arrays
