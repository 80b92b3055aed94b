"""Camera math: projection-matrix decomposition, look-at poses, a DTU-like camera cap.

Conventions (OpenCV / NeuS): camera x right, y down, z forward; a 3x4 projection
``P = K [R | t]`` maps homogeneous world points to homogeneous pixels; pixel (x, y) is
centred on integer coordinates. Everything here is numpy float64 (cameras are few; precision
matters more than speed).
"""

from __future__ import annotations

import cv2
import numpy as np


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a projection matrix into intrinsics and a camera-to-world pose (as NeuS does).

    Args:
        P: (3, 4) or (4, 4) projection matrix; only the top 3x4 block is used.

    Returns:
        K: (3, 3) intrinsics normalised so that K[2, 2] == 1.
        c2w: (4, 4) camera-to-world pose in the frame P takes points from
            (rotation R^T, centre t[:3] / t[3] from ``cv2.decomposeProjectionMatrix``).
    """
    P = np.asarray(P, dtype=np.float64)[:3, :4]
    K, R, t = cv2.decomposeProjectionMatrix(P)[:3]
    K = K / K[2, 2]
    c2w = np.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = (t[:3] / t[3])[:, 0]
    return K, c2w


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


def camera_z_depth(world_mat: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates and camera-z depth (world units) of world points.

    Args:
        world_mat: (4, 4) or (3, 4) projection, world -> pixels.
        points: (N, 3) world points.

    Returns:
        xy: (N, 2) pixel coordinates (pixel centres at integers).
        z: (N,) depth along the optical axis, positive in front of the camera
            (``(P_n @ [X, 1])[2]`` with ``P_n = P / norm(P[2, :3])``, sign fixed by det).
    """
    P = np.asarray(world_mat, dtype=np.float64)[:3, :4]
    P = P / np.linalg.norm(P[2, :3]) * np.sign(np.linalg.det(P[:, :3]))
    h = points @ P[:, :3].T + P[:, 3]
    z = h[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = h[:, :2] / z[:, None]
    return xy, z
