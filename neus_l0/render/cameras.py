"""Camera paths for novel views: a turntable orbit fitted to the training cameras, and the
intrinsics of an output size (pure numpy float64 functions, no IO).

Conventions (those of `neus_l0.data.rays.pixel_rays`): OpenCV axes (camera x right, y down,
z forward), ``c2w`` (4, 4) camera-to-world in the *normalised* frame (the object's bounding
sphere is the unit sphere, centred on the origin), ``K`` (3, 3) upper-triangular in pixel
units with K[2, 2] == 1, pixel (x, y) centred on integer coordinates.

The normalised frame has no "up" of its own: `up_direction` takes the training cameras'
mean image-up direction (their -y axis), which is what a photographer held level.
"""

from __future__ import annotations

import numpy as np

from neus_l0.data.cameras import look_at


def up_direction(c2w: np.ndarray) -> np.ndarray:
    """The scene's "up": the training cameras' mean image-up axis (-y), normalised.

    Args:
        c2w: (V, 4, 4) camera-to-world poses.

    Returns:
        (3,) unit vector; +z when the cameras' up axes cancel out.
    """
    up = -np.asarray(c2w, dtype=np.float64)[:, :3, 1].mean(axis=0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-6 else np.array([0.0, 0.0, 1.0])


def camera_elevations(c2w: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Each camera centre's elevation above the plane through the origin normal to `up`.

    Args:
        c2w: (V, 4, 4) camera-to-world poses; up: (3,) unit vector.

    Returns:
        (V,) degrees in [-90, 90].
    """
    centres = np.asarray(c2w, dtype=np.float64)[:, :3, 3]
    unit = centres / np.linalg.norm(centres, axis=-1, keepdims=True).clip(1e-12)
    return np.degrees(np.arcsin(np.clip(unit @ np.asarray(up, np.float64), -1.0, 1.0)))


def _plane_basis(up: np.ndarray, start: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (e1, e2) spanning the plane normal to `up`, e1 towards `start`'s
    projection (any when it has none), with (e1, e2, up) right-handed."""
    ref = np.array([1.0, 0.0, 0.0]) if start is None else np.asarray(start, np.float64)
    e1 = ref - (ref @ up) * up
    if np.linalg.norm(e1) < 1e-6:  # `start` along `up`: any direction in the plane
        e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 = e1 / np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def orbit_poses(n_frames: int, distance: float, elevation_deg: float, up: np.ndarray,
                start: np.ndarray | None = None) -> np.ndarray:
    """Cameras on a circle around the origin, all looking at it, turning about `up`.

    Frame k sits at azimuth ``2 pi k / n_frames`` (counter-clockwise seen from above; the
    last frame stops one step short of the first, so the video loops), at `distance` from
    the origin and `elevation_deg` above the plane normal to `up`; its image-up axis (-y)
    leans towards `up`.

    Args:
        n_frames: number of cameras (>= 1).
        distance: distance from the origin (> 0), normalised units.
        elevation_deg: elevation in (-90, 90) degrees.
        up: (3,) unit vector.
        start: (3,) direction whose azimuth frame 0 takes (e.g. the first training camera's
            centre); default any.

    Returns:
        (n_frames, 4, 4) float64 camera-to-world poses.
    """
    up = np.asarray(up, np.float64)
    e1, e2 = _plane_basis(up, start)
    az = 2.0 * np.pi * np.arange(n_frames) / n_frames
    el = np.radians(elevation_deg)
    ring = np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2  # (F, 3)
    eyes = distance * (np.cos(el) * ring + np.sin(el) * up)  # (F, 3)
    return np.stack([np.linalg.inv(look_at(eye, np.zeros(3), up)) for eye in eyes])


def orbit_from_training(c2w: np.ndarray, n_frames: int,
                        elevation_deg: float | None = None) -> np.ndarray:
    """A turntable orbit at the training cameras' mean distance and mean elevation.

    Args:
        c2w: (V, 4, 4) the training cameras' poses.
        n_frames: number of orbit cameras.
        elevation_deg: the orbit's elevation instead of the cameras' mean.

    Returns:
        (n_frames, 4, 4) float64 camera-to-world poses (see `orbit_poses`); frame 0 at the
        first training camera's azimuth.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    up = up_direction(c2w)
    distance = float(np.linalg.norm(c2w[:, :3, 3], axis=-1).mean())
    if elevation_deg is None:
        elevation_deg = float(camera_elevations(c2w, up).mean())
    return orbit_poses(n_frames, distance, elevation_deg, up, start=c2w[0, :3, 3])


def mean_intrinsics(K: np.ndarray) -> np.ndarray:
    """(3, 3) the entry-wise mean of (V, 3, 3) intrinsics (one camera model for an orbit)."""
    return np.asarray(K, dtype=np.float64).reshape(-1, 3, 3).mean(axis=0)


def resize_intrinsics(K: np.ndarray, src_hw: tuple[int, int],
                      dst_hw: tuple[int, int]) -> np.ndarray:
    """Intrinsics of the same cameras imaging onto a resized sensor.

    With pixel centres on integers, new pixel (x', y') covers old ``(x' + 0.5) W / W' - 0.5``
    (so an integer downscale s gives `neus_l0.data.scene`'s ``S @ K``).

    Args:
        K: (..., 3, 3) for images of `src_hw` = (H, W) pixels.
        dst_hw: the output (H', W').

    Returns:
        (..., 3, 3) float64.
    """
    sy, sx = dst_hw[0] / src_hw[0], dst_hw[1] / src_hw[1]
    S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return S @ np.asarray(K, dtype=np.float64)


def depth_range(c2w: np.ndarray, box: np.ndarray | None = None) -> tuple[float, float]:
    """One camera-z range for a whole path, so that depth colours agree across frames.

    The unit sphere's range at the cameras' distances d (``min d - 1`` to ``max d + 1``),
    narrowed to the camera-z range of `box`'s corners when a box is given (e.g. around the
    visual hull); the near end is kept above 0.

    Args:
        c2w: (F, 4, 4) the rendered cameras.
        box: (2, 3) the lower and upper corner of an axis-aligned box, or None.

    Returns:
        (near, far) with 0 < near < far.
    """
    c2w = np.asarray(c2w, np.float64)
    d = np.linalg.norm(c2w[:, :3, 3], axis=-1)
    near, far = max(float(d.min()) - 1.0, 1e-3), float(d.max()) + 1.0
    if box is not None:
        lo, hi = np.asarray(box, np.float64)
        corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1)
        corners = corners.reshape(8, 3)
        z = np.einsum("fpk,fk->fp", corners[None] - c2w[:, None, :3, 3], c2w[:, :3, 2])
        lo_z, hi_z = max(near, float(z.min())), min(far, float(z.max()))
        if lo_z < hi_z:
            near, far = lo_z, hi_z
    return near, far
