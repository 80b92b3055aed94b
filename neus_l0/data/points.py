"""The sparse SfM points a `neus-l0 colmap` scene carries (``sparse_points.npz``)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from neus_l0.errors import SceneError

#: The file `neus-l0 colmap` writes next to ``cameras_sphere.npz``.
POINTS_FILE = "sparse_points.npz"


def write_points(path: str | Path, points_world: np.ndarray, track_len: np.ndarray) -> Path:
    """Write ``sparse_points.npz`` atomically.

    Args:
        path: the file.
        points_world: (M, 3) sparse points in the scene's world units.
        track_len: (M,) views that observe each point.
    """
    import io

    from neus_l0.atomic import atomic_write

    buf = io.BytesIO()
    np.savez(buf, points_world=np.asarray(points_world, dtype=np.float64).reshape(-1, 3),
             track_len=np.asarray(track_len, dtype=np.int64).reshape(-1))
    data = buf.getvalue()
    return atomic_write(Path(path), lambda p: p.write_bytes(data))


def read_points(path: str | Path, scale_mat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Read ``sparse_points.npz`` into the normalised frame of `scale_mat`.

    Returns:
        points (M, 3) float64 in the normalised frame, track_len (M,) int64.
    """
    try:
        with np.load(Path(path)) as z:
            pts, track = z["points_world"].reshape(-1, 3), z["track_len"].reshape(-1)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise SceneError(f"{path}: not a readable sparse_points.npz (points_world, track_len): "
                         f"{type(exc).__name__}: {exc}") from None
    if len(pts) != len(track) or not np.isfinite(pts).all():
        raise SceneError(f"{path}: points_world must be finite and match track_len in length "
                         f"({len(pts)} points, {len(track)} track lengths)")
    sm = np.asarray(scale_mat, dtype=np.float64)
    return (pts - sm[:3, 3]) @ np.linalg.inv(sm[:3, :3]).T, track.astype(np.int64)
