"""Cameras and frames: NeuS camera files, projections, camera-z depth, the world/normalised
frame conversion, look-at poses, the optical axes' convergence point and a DTU-like camera
cap.

Conventions (OpenCV / NeuS): camera x right, y down, z forward; a 3x4 projection
``P = K [R | t]`` maps homogeneous world points to homogeneous pixels; pixel (x, y) is
centred on integer coordinates. The *normalised* frame puts the object's bounding sphere
on the unit sphere: ``x_world = scale_mat[:3, :3] @ x_norm + scale_mat[:3, 3]``.
Everything here is numpy float64 (cameras are few; precision matters more than speed).

The light readers (`read_world_mats`, `read_masks`, `read_indexed`) read what evaluation and
figures need from a NeuS-format folder without torch; `neus_l0.formats.neus.load_scene` is the
training loader (images, downscaling, poses in the normalised frame).
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from neus_l0.data.image_io import imread_bytes
from neus_l0.data.patches import LUMA
from neus_l0.data.views import indexed_files
from neus_l0.errors import NeusL0Error

#: Camera files of a NeuS-format folder, in order of preference (IDR's legacy name last).
CAMERA_FILES = ("cameras_sphere.npz", "cameras.npz")

_WORLD_MAT = re.compile(r"^world_mat_(\d+)$")


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a projection matrix into intrinsics and a camera-to-world pose (as NeuS does).

    Args:
        P: (3, 4) or (4, 4) projection matrix; only the top 3x4 block is used.

    Returns:
        K: (3, 3) intrinsics normalised so that K[2, 2] == 1, with positive focal lengths
            (P and -P are the same camera: the sign is taken so that points in front of the
            camera have positive depth).
        c2w: (4, 4) camera-to-world pose in the frame P takes points from
            (rotation R^T, centre t[:3] / t[3] from ``cv2.decomposeProjectionMatrix``).
    """
    P = np.asarray(P, dtype=np.float64)[:3, :4]
    P = P / np.abs(P).max()  # a projection is defined up to scale: keep its numbers near 1
    if np.linalg.det(P[:, :3]) < 0:
        P = -P  # the same camera; with det > 0, points in front have positive depth
    K, R, t = cv2.decomposeProjectionMatrix(P)[:3]
    K = K / K[2, 2]
    flip = np.diag(np.where(np.diag(K) < 0, -1.0, 1.0))  # RQ's sign choice: K R = (K D)(D R)
    K, R = K @ flip, flip @ R
    c2w = np.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = (t[:3] / t[3])[:, 0]
    return K, c2w


def axes_convergence(centres: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Least-squares point closest to all lines ``centres_i + s * dirs_i``.

    Minimises ``sum_i |(I - d_i d_i^T)(p - c_i)|^2``, i.e. solves
    ``(sum_i A_i) p = sum_i A_i c_i`` with ``A_i = I - d_i d_i^T``.

    Args:
        centres: (N, 3) points on the lines (camera centres).
        dirs: (N, 3) line directions (need not be unit length), not all parallel.

    Returns:
        (3,) the closest point.

    Raises:
        ValueError: all lines parallel (the system is singular).
    """
    c = np.asarray(centres, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    A = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (N, 3, 3)
    lhs = A.sum(0)
    rhs = np.einsum("nij,nj->i", A, c)
    if np.linalg.cond(lhs) > 1e10:
        raise ValueError("axes_convergence: the optical axes are (nearly) parallel")
    return np.linalg.solve(lhs, rhs)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera matrix of a camera at `eye` looking at `target` (OpenCV axes).

    Args:
        eye: (3,) camera centre.
        target: (3,) point on the optical axis.
        up: (3,) world direction that appears "up" (towards -y) in the image.

    Returns:
        (4, 4) world-to-camera matrix [R | -R eye].
    """
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:  # looking straight along `up`
        right = np.cross(fwd, np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([right, down, fwd])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    return w2c


def cap_centres(n_views: int, center: np.ndarray, distance: tuple[float, float],
                elevation_deg: tuple[float, float] = (20.0, 70.0),
                azimuth_span_deg: float = 360.0, seed: int = 0) -> np.ndarray:
    """Camera centres on a spherical cap (zone) above an object, like DTU's robot arm.

    Elevations are spread evenly in area (uniform in sin(elevation)) over `elevation_deg`,
    azimuths follow the golden angle (wrapped into `azimuth_span_deg`), distances are drawn
    uniformly in `distance`; `seed` jitters the layout slightly.

    Args:
        n_views: number of cameras.
        center: (3,) point the cap is centred on (the object centre); +z is up.
        distance: (min, max) camera-to-centre distance, world units.
        elevation_deg: (min, max) elevation above the horizontal plane, degrees.
        azimuth_span_deg: azimuth range, degrees (360 = all around).
        seed: random seed of the jitter.

    Returns:
        (n_views, 3) camera centres.
    """
    rng = np.random.default_rng(seed)
    k = (np.arange(n_views) + 0.5 + rng.uniform(-0.25, 0.25, n_views)) / n_views
    s0, s1 = np.sin(np.radians(elevation_deg))
    elev = np.arcsin(np.clip(s0 + (s1 - s0) * k, -1, 1))
    golden = np.pi * (3.0 - np.sqrt(5.0))
    phase = rng.uniform(0, 2 * np.pi)
    if azimuth_span_deg >= 360.0:
        azim = phase + golden * np.arange(n_views)
    else:
        frac = np.mod(np.arange(n_views) * golden / (2 * np.pi), 1.0)
        azim = phase + np.radians(azimuth_span_deg) * (frac - 0.5)
    dist = rng.uniform(distance[0], distance[1], n_views)
    dirs = np.stack([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)], -1)
    return np.asarray(center, dtype=np.float64) + dist[:, None] * dirs


def intrinsics_to_fit(width: int, height: int, radius: float, distance: float,
                      fill: float = 0.95) -> np.ndarray:
    """DTU-like intrinsics whose view just holds a sphere of `radius` at `distance`.

    The focal length makes the sphere's silhouette span `fill` of the image's shorter side
    (about 1.4-1.5 x the width at 4:3 with this package's scene scales); the principal
    point sits at the image centre ((W - 1) / 2, (H - 1) / 2) plus 1 % of the width to the
    right and down, as real calibrations are never exactly centred.

    Returns:
        (3, 3) intrinsics.
    """
    half_angle = np.arcsin(min(radius / distance, 0.999))
    f = fill * 0.5 * min(width, height) / np.tan(half_angle)
    return np.array([[f, 0.0, (width - 1) / 2 + 0.01 * width],
                     [0.0, f, (height - 1) / 2 + 0.01 * height],
                     [0.0, 0.0, 1.0]])


def projection_matrix(K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """(4, 4) NeuS ``world_mat``: [[K @ w2c[:3]], [0, 0, 0, 1]]."""
    world_mat = np.eye(4)
    world_mat[:3, :4] = K @ w2c[:3, :4]
    return world_mat


def sphere_scale_mat(center: np.ndarray, radius: float) -> np.ndarray:
    """(4, 4) NeuS ``scale_mat``: maps the unit sphere onto the sphere (center, radius)."""
    s = np.diag([radius, radius, radius, 1.0])
    s[:3, 3] = center
    return s


def depth_projection(world_mats: np.ndarray) -> np.ndarray:
    """Scale projections so that their third row gives camera-z depth.

    ``P_n = P / norm(P[2, :3])`` with the sign of det(P[:, :3]) (1 where it is 0), so that
    points in front of the camera have positive depth (``P = K [R | t]`` with K's diagonal
    positive has det > 0). Applying it twice changes nothing.

    Args:
        world_mats: (..., 3, 4) or (..., 4, 4) projections world -> pixels.

    Returns:
        (..., 3, 4) float64 ``P_n``.
    """
    P = np.asarray(world_mats, dtype=np.float64)[..., :3, :4]
    sign = np.sign(np.linalg.det(P[..., :3]))
    sign = np.where(sign == 0, 1.0, sign)
    norm = np.linalg.norm(P[..., 2, :3], axis=-1)
    return P * (sign / norm)[..., None, None]


def camera_z_depth(world_mat: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates and camera-z depth (world units) of world points.

    Args:
        world_mat: (4, 4) or (3, 4) projection, world -> pixels.
        points: (N, 3) world points.

    Returns:
        xy: (N, 2) pixel coordinates (pixel centres at integers; not finite where z = 0).
        z: (N,) depth along the optical axis, positive in front of the camera
            (``(P_n @ [X, 1])[2]`` with ``P_n`` from `depth_projection`).
    """
    P = depth_projection(world_mat)
    h = np.asarray(points, dtype=np.float64) @ P[:, :3].T + P[:, 3]  # (N, 3)
    z = h[:, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        xy = h[:, :2] / z[:, None]
    return xy, z


def pixel_indices(world_mat: np.ndarray, points: np.ndarray, height: int | None = None,
                  width: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixel (column, row) each world point falls in, and its camera-z depth.

    Args:
        world_mat: (4, 4) or (3, 4) projection, world -> pixels.
        points: (N, 3) world points.
        height, width: the image size; when given, pixels outside [0, W) x [0, H) count as
            missed.

    Returns:
        col: (N,) int64 ``rint(x)``; row: (N,) int64 ``rint(y)``; both -1 where the point
            is not in front of the camera (z <= 0) or, with a size, not inside the image.
        z: (N,) camera-z depth (`camera_z_depth`).
    """
    xy, z = camera_z_depth(world_mat, points)
    front = z > 0
    big = 2.0**40  # avoids int overflow for points next to the camera plane
    pix = np.full((len(z), 2), -1, dtype=np.int64)
    pix[front] = np.rint(np.clip(xy[front], -big, big)).astype(np.int64)
    col, row = pix[:, 0], pix[:, 1]
    if height is not None and width is not None:
        out = (col < 0) | (col >= width) | (row < 0) | (row >= height)
        col[out] = -1
        row[out] = -1
    return col, row, z


def scale_projection(world_mat: np.ndarray, factor: float) -> np.ndarray:
    """The same camera at `factor` times the resolution, pixel centres kept at integers.

    Pixel (x, y) becomes ``factor * (x, y) + (factor - 1) / 2``: new pixel centres split
    each old pixel into factor x factor ones (for an integer factor).

    Args:
        world_mat: (3, 4) or (4, 4) projection, world -> pixels.
        factor: resolution factor (> 0).

    Returns:
        (3, 4) float64 projection.
    """
    S = np.diag([factor, factor, 1.0])
    S[:2, 2] = (factor - 1.0) / 2.0
    return S @ np.asarray(world_mat, dtype=np.float64)[:3, :4]


def to_world(points: np.ndarray, scale_mat: np.ndarray) -> np.ndarray:
    """Normalised-frame points to world units: ``scale_mat[:3, :3] @ x + scale_mat[:3, 3]``.

    Args:
        points: (..., 3) normalised-frame points.
        scale_mat: (4, 4) normalised -> world.

    Returns:
        (..., 3) float64 world points.
    """
    S = np.asarray(scale_mat, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ S[:3, :3].T + S[:3, 3]


def to_normalised(points_world: np.ndarray, scale_mat: np.ndarray) -> np.ndarray:
    """World points to the normalised frame (the inverse of `to_world`).

    Args:
        points_world: (..., 3) world points.
        scale_mat: (4, 4) normalised -> world.

    Returns:
        (..., 3) float64 normalised-frame points.
    """
    S = np.asarray(scale_mat, dtype=np.float64)
    x = np.asarray(points_world, dtype=np.float64) - S[:3, 3]
    return np.linalg.solve(S[:3, :3], x.reshape(-1, 3).T).T.reshape(x.shape)


def world_scale(scale_mat: np.ndarray) -> float:
    """World units per normalised unit: ``|det(scale_mat[:3, :3])|^(1/3)``.

    NeuS's scale_mat scales uniformly, so distances along a ray (and SDF values) convert by
    this one factor; directions are the same in both frames.
    """
    return float(abs(np.linalg.det(np.asarray(scale_mat, dtype=np.float64)[:3, :3]))
                 ** (1.0 / 3.0))


def camera_file(scene_dir: str | Path) -> Path:
    """The camera file of a NeuS-format folder (`CAMERA_FILES`, first found).

    Raises:
        NeusL0Error: neither file exists.
    """
    root = Path(scene_dir)
    for name in CAMERA_FILES:
        if (root / name).is_file():
            return root / name
    raise NeusL0Error(f"{root / CAMERA_FILES[0]}: file not found")


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
    except Exception as exc:  # noqa: BLE001 - any parse failure is the user's file
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise NeusL0Error(f"{path}: cannot read ({msg})") from None
    if not arrays:
        raise NeusL0Error(f"{path}: no {what} keys")
    n = len(arrays)
    if sorted(arrays) != list(range(n)):
        raise NeusL0Error(f"{path}: {what} indices are not 0..{n - 1}")
    return arrays


def read_world_mats(scene_dir: str | Path) -> np.ndarray:
    """Projections world -> pixels of every view of a NeuS-format folder, in index order.

    Args:
        scene_dir: folder with `cameras_sphere.npz` (or legacy `cameras.npz`).

    Returns:
        (V, 3, 4) float64: `world_mat_i[:3, :4]` for i = 0 .. V-1.

    Raises:
        NeusL0Error: missing/unreadable file, no `world_mat_i`, gaps or bad shapes.
    """
    path = camera_file(scene_dir)
    mats = read_indexed(path, _WORLD_MAT, np.float64, "world_mat_i")
    out = np.empty((len(mats), 3, 4))
    for i in range(len(mats)):
        m = mats[i]
        if m.shape not in ((4, 4), (3, 4)) or not np.isfinite(m).all():
            raise NeusL0Error(f"{path}: world_mat_{i} must be a finite 3x4 or 4x4 matrix")
        out[i] = m[:3, :4]
    return out


def indexed_images(scene_dir: str | Path, name: str) -> dict[int, np.ndarray]:
    """The images of the folder ``scene_dir/name`` by view index (`neus_l0.data.views`), as
    decoded (any depth and channels).

    Raises:
        NeusL0Error: no such folder or no files, a file without a view number, two files of
            one view, or an unreadable image (each named).
    """
    folder = Path(scene_dir) / name
    files = indexed_files(folder) if folder.is_dir() else {}
    if not files:
        raise NeusL0Error(f"{folder}: no {name} files")
    out = {}
    for i, f in files.items():
        img = imread_bytes(Path(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise NeusL0Error(f"{f}: cannot read image")
        out[i] = img
    return out


def read_masks(scene_dir: str | Path) -> dict[int, np.ndarray]:
    """Foreground masks ``mask/*`` by view index (`neus_l0.data.views`; > 127 = foreground).

    Returns:
        {view index: (H, W) bool}, in index order.

    Raises:
        NeusL0Error: no mask folder/files, a file without a view number, two files of one
            view, or an unreadable image.
    """
    return {i: (img[..., :3].max(axis=-1) if img.ndim == 3 else img) > 127
            for i, img in indexed_images(scene_dir, "mask").items()}


def read_grays(scene_dir: str | Path) -> dict[int, np.ndarray]:
    """Grey images ``image/*`` by view index (`neus_l0.data.views`): the luma
    (`neus_l0.data.patches.LUMA`) of the colour in [0, 1] (8- or 16-bit; an alpha channel
    is ignored).

    Returns:
        {view index: (H, W) float32}, in index order.

    Raises:
        NeusL0Error: no image folder/files, or an unreadable image.
    """
    bgr = np.asarray(LUMA[::-1], np.float32)  # OpenCV's channel order
    grays = {}
    for i, img in indexed_images(scene_dir, "image").items():
        scale = 65535.0 if img.dtype == np.uint16 else 255.0
        img = img.astype(np.float32) / np.float32(scale)
        grays[i] = img if img.ndim == 2 else img[..., :3] @ bgr
    return grays
