"""COLMAP sparse models as plain arrays: read (text or binary, via pycolmap) and write (text).

COLMAP's pixel convention puts the centre of the top-left pixel at (0.5, 0.5); NeuS (this
package) puts it at (0, 0). The arrays here keep COLMAP's convention; `neus_l0.photos.export`
converts when it writes a NeuS scene.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from neus_l0.atomic import atomic_write_text
from neus_l0.errors import NeusL0Error

#: Files that make a COLMAP sparse model, in each format.
MODEL_FILES = {"text": ("cameras.txt", "images.txt", "points3D.txt"),
               "binary": ("cameras.bin", "images.bin", "points3D.bin")}


@dataclasses.dataclass
class SparseModel:
    """The registered views and sparse points of one COLMAP reconstruction.

    Attributes:
        names: (N,) image names (paths relative to the image folder), sorted.
        camera_ids: (N,) int64 COLMAP camera id of each view.
        cameras: COLMAP camera id -> ``pycolmap.Camera`` (model, size, parameters).
        w2c: (N, 3, 4) float64 world-to-camera [R | t] of each view.
        points: (M, 3) float64 sparse points.
        track_len: (M,) int64 number of views that observe each point.
    """

    names: list[str]
    camera_ids: np.ndarray
    cameras: dict[int, Any]
    w2c: np.ndarray
    points: np.ndarray
    track_len: np.ndarray

    @property
    def n_views(self) -> int:
        return len(self.names)

    @property
    def centres(self) -> np.ndarray:
        """(N, 3) camera centres, ``-R^T t``."""
        R, t = self.w2c[:, :, :3], self.w2c[:, :, 3]
        return -np.einsum("nji,nj->ni", R, t)

    @property
    def axes(self) -> np.ndarray:
        """(N, 3) unit optical-axis directions (camera +z) in the world."""
        return self.w2c[:, 2, :3] / np.linalg.norm(self.w2c[:, 2, :3], axis=-1, keepdims=True)


def from_reconstruction(rec) -> SparseModel:
    """Convert a ``pycolmap.Reconstruction`` into a `SparseModel` (registered views only)."""
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    w2c = np.array([im.cam_from_world().matrix() for im in images], dtype=np.float64)
    pts = list(rec.points3D.values())
    points = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    track = np.array([p.track.length() for p in pts], dtype=np.int64)
    return SparseModel(
        names=[im.name for im in images],
        camera_ids=np.array([im.camera_id for im in images], dtype=np.int64),
        cameras={int(cid): cam for cid, cam in rec.cameras.items()},
        w2c=w2c.reshape(-1, 3, 4), points=points, track_len=track)


def read_model(folder: str | Path) -> SparseModel:
    """Read a COLMAP sparse model folder (``cameras``, ``images``, ``points3D``; .txt or .bin).

    Raises:
        NeusL0Error: missing folder or files, unreadable model, or no registered image.
    """
    import pycolmap

    folder = Path(folder)
    if not folder.is_dir():
        raise NeusL0Error(f"{folder}: sparse model folder not found")
    if not any(all((folder / f).is_file() for f in files) for files in MODEL_FILES.values()):
        raise NeusL0Error(f"{folder}: not a COLMAP sparse model (needs cameras, images and "
                          "points3D as .txt or .bin)")
    try:
        rec = pycolmap.Reconstruction(folder)
    except Exception as exc:  # noqa: BLE001 - any parse failure is the user's model
        raise NeusL0Error(f"{folder}: unreadable COLMAP model ({exc})") from None
    model = from_reconstruction(rec)
    if model.n_views == 0:
        raise NeusL0Error(f"{folder}: the sparse model has no registered image")
    return model


def _quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions (w, x, y, z), w >= 0, of rotations (N, 3, 3)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]  # scipy gives (x, y, z, w)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def write_text_model(folder: str | Path, cameras: dict[int, tuple[str, int, int, list[float]]],
                     names: list[str], camera_ids: np.ndarray, w2c: np.ndarray,
                     points: np.ndarray) -> Path:
    """Write a COLMAP text model (cameras.txt, images.txt, points3D.txt), atomically per file.

    Each point's track holds every view it projects into (in front of the camera, inside
    the image); its 2D observations are the exact projections. Only distortion-free models
    (``SIMPLE_PINHOLE``, ``PINHOLE``) are supported here.

    Args:
        folder: output folder (created).
        cameras: camera id -> (model name, width, height, params), COLMAP pixel convention.
        names: (N,) image names.
        camera_ids: (N,) camera id per view.
        w2c: (N, 3, 4) world-to-camera [R | t].
        points: (M, 3) world points.

    Returns:
        The folder.
    """
    folder = Path(folder)
    w2c = np.asarray(w2c, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    Ks = {}
    for cid, (model, w, h, params) in sorted(cameras.items()):
        if model == "PINHOLE":
            fx, fy, cx, cy = params
        elif model == "SIMPLE_PINHOLE":
            fx, cx, cy = params
            fy = fx
        else:
            raise ValueError(f"write_text_model: unsupported camera model {model}")
        Ks[cid] = (np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), w, h)
        lines.append(f"{cid} {model} {w} {h} " + " ".join(f"{float(p):.17g}" for p in params))
    atomic_write_text(folder / "cameras.txt", "\n".join(lines) + "\n")

    tracks: list[list[str]] = [[] for _ in range(len(points))]
    quats = _quaternion_wxyz(w2c[:, :, :3])
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, (name, cid) in enumerate(zip(names, camera_ids, strict=True)):
        K, w, h = Ks[int(cid)]
        cam = points @ w2c[i, :, :3].T + w2c[i, :, 3]  # (M, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = (cam @ K.T)[:, :2] / cam[:, 2:3]
        ok = np.nonzero((cam[:, 2] > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < w)
                        & (xy[:, 1] >= 0) & (xy[:, 1] < h))[0]
        for k, j in enumerate(ok):
            tracks[j].append(f"{i + 1} {k}")
        q, t = quats[i], w2c[i, :, 3]
        lines.append(f"{i + 1} " + " ".join(f"{v:.17g}" for v in (*q, *t)) + f" {cid} {name}")
        lines.append(" ".join(f"{xy[j, 0]:.17g} {xy[j, 1]:.17g} {j + 1}" for j in ok))
    atomic_write_text(folder / "images.txt", "\n".join(lines) + "\n")

    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    for j, p in enumerate(points):
        if tracks[j]:
            lines.append(f"{j + 1} {p[0]:.17g} {p[1]:.17g} {p[2]:.17g} 128 128 128 0 "
                         + " ".join(tracks[j]))
    atomic_write_text(folder / "points3D.txt", "\n".join(lines) + "\n")
    return folder
