"""The object sphere (NeuS's ``scale_mat``) from sparse SfM points and the optical axes.

How the sphere is chosen (`choose_sphere`):

1. The *convergence point* c0: the least-squares closest point to all optical axes
   (`neus_l0.data.cameras.axes_convergence`). Photos taken around an object aim at it, so
   c0 lies near the object.
2. Candidate points: sparse points seen by at least `min_views` views, lying in front of
   the cameras and closer to c0 than `near_fraction` x the median camera distance to c0.
   This drops stray points and the far background (walls, sky, a backdrop).
3. The centre: the middle of the candidates' robust bounding box (per-axis `lo_pct` ..
   `100 - lo_pct` percentiles), i.e. the middle of the object rather than where the
   cameras aim.
4. The radius: the `percentile`-th percentile of the candidates' distances to the centre
   (candidates within 2x that distance only, a second pass against background left in
   step 2), times `margin`; then capped at `max_camera_fraction` x the nearest camera's
   distance, so that every camera stays outside the sphere.

All functions are pure numpy float64.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from neus_l0.data.cameras import axes_convergence


@dataclasses.dataclass
class SphereChoice:
    """The chosen sphere and how it was found.

    Attributes:
        center: (3,) centre, world units.
        radius: radius, world units.
        convergence: (3,) the optical axes' convergence point.
        n_points: sparse points the sphere was fitted to.
        n_total: all sparse points.
        capped: whether the radius was reduced to keep the cameras outside.
        source: ``"auto"`` or ``"user"``.
    """

    center: np.ndarray
    radius: float
    convergence: np.ndarray
    n_points: int
    n_total: int
    capped: bool = False
    source: str = "auto"

    def explain(self) -> str:
        """One paragraph saying where the sphere came from."""
        c, q = self.center, self.convergence
        head = (f"object sphere: centre ({c[0]:.4g}, {c[1]:.4g}, {c[2]:.4g}), "
                f"radius {self.radius:.4g}")
        if self.source == "user":
            return head + " (given with --center/--radius)"
        text = (f"{head} (automatic: fitted to {self.n_points} of {self.n_total} sparse points "
                f"seen by several views near the point the optical axes converge to, "
                f"({q[0]:.4g}, {q[1]:.4g}, {q[2]:.4g}); a high percentile of their distance "
                f"to the centre plus a margin)")
        if self.capped:
            text += "; radius capped to keep every camera outside the sphere"
        return text


def choose_sphere(points: np.ndarray, track_len: np.ndarray, centres: np.ndarray,
                  dirs: np.ndarray, min_views: int = 3, percentile: float = 99.0,
                  margin: float = 1.25, near_fraction: float = 0.8, lo_pct: float = 2.0,
                  max_camera_fraction: float = 0.9) -> SphereChoice:
    """Choose the object sphere from sparse points and cameras (see the module docstring).

    Args:
        points: (M, 3) sparse points, world units.
        track_len: (M,) number of views that see each point.
        centres: (N, 3) camera centres.
        dirs: (N, 3) optical-axis directions (camera +z in the world).
        min_views: a point counts when at least this many views see it (lowered to 2 when
            fewer than 20 points qualify).
        percentile: percentile of the candidates' distance to the centre taken as the
            object's radius.
        margin: factor on that radius.
        near_fraction: candidates lie within this fraction of the median camera distance
            from the convergence point.
        lo_pct: lower percentile of the robust bounding box (upper: ``100 - lo_pct``).
        max_camera_fraction: the radius is at most this fraction of the nearest camera's
            distance to the centre.

    Returns:
        The `SphereChoice`. With no usable point it falls back to a sphere at the
        convergence point with radius 0.5 x the median camera distance.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    track_len = np.asarray(track_len).reshape(-1)
    centres = np.asarray(centres, dtype=np.float64)
    dirs = np.asarray(dirs, dtype=np.float64)
    dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    c0 = axes_convergence(centres, dirs)
    cam_dist = np.linalg.norm(centres - c0, axis=-1)  # (N,)
    near = near_fraction * np.median(cam_dist)

    # in front of most cameras: positive depth along the axis for the majority of views
    depth = np.einsum("nk,mk->mn", dirs, points) - (dirs * centres).sum(-1)  # (M, N)
    in_front = (depth > 0).mean(-1) > 0.5
    close = np.linalg.norm(points - c0, axis=-1) < near
    keep = close & in_front
    cand = keep & (track_len >= min_views)
    if cand.sum() < 20:
        cand = keep & (track_len >= 2)
    pts = points[cand]
    if len(pts) < 4:
        center, radius = c0, 0.5 * float(np.median(cam_dist))
        n_used = int(len(pts))
    else:
        lo, hi = np.percentile(pts, [lo_pct, 100.0 - lo_pct], axis=0)
        center = 0.5 * (lo + hi)
        dist = np.linalg.norm(pts - center, axis=-1)
        r0 = np.percentile(dist, percentile)
        inner = dist <= 2.0 * r0
        radius = float(np.percentile(dist[inner], percentile)) * margin
        n_used = int(inner.sum())
    nearest = float(np.linalg.norm(centres - center, axis=-1).min())
    capped = radius > max_camera_fraction * nearest
    if capped:
        radius = max_camera_fraction * nearest
    return SphereChoice(center=np.asarray(center, dtype=np.float64), radius=float(radius),
                        convergence=c0, n_points=n_used, n_total=len(points), capped=capped)


def user_sphere(center: np.ndarray, radius: float, centres: np.ndarray,
                dirs: np.ndarray) -> SphereChoice:
    """A `SphereChoice` for a sphere given by the user (the convergence point for the record)."""
    try:
        c0 = axes_convergence(centres, dirs)
    except ValueError:
        c0 = np.asarray(center, dtype=np.float64)
    return SphereChoice(center=np.asarray(center, dtype=np.float64), radius=float(radius),
                        convergence=c0, n_points=0, n_total=0, source="user")
