"""A ray bound from the SfM points of a `neus-l0 colmap` scene: their oriented box.

A scene written by ``neus-l0 colmap`` has no visual hull unless the user gave masks, and
without masks nothing proves that space is empty. What the sparse SfM points do say is
where surface *is*; the object sphere (``scale_mat``) is already chosen from them (a high
percentile of their spread times 1.25, `neus_l0.formats.sphere`). This module goes one step
further, and only that far: the box around those points, oriented along their principal
axes and widened by a margin, clipped to the unit sphere. It is the same kind of statement
as the sphere (the object lies where its points spread), not a carving of the space
between points: SfM points are sparse on dark, blank and thin parts, so a voxel set
dilated around them would cut the object (docs/BENCHMARKS.md, "Without masks").

Why it is conservative: a point of the ray inside the box lies between the ray's entry and
exit of the box (a box is convex), so ``[max(near, t_in), min(far, t_out)]`` holds every
such point exactly (slab test); nothing is rounded to a grid.

Frames: ``sparse_points.npz`` (written by `neus_l0.photos.export.export_scene`) holds the
points in the scene's world units; `PointBound.for_scene` maps them with the scene's own
``scale_mat`` into the normalised frame (the object inside the unit sphere).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neus_l0.data.points import POINTS_FILE, read_points

#: Fewer usable points than this: no bound (the box of a handful of points says little).
MIN_POINTS = 20


class PointBound:
    """An oriented box in the normalised frame (the `neus_l0.bounds.spans.RayBounds` protocol).

    Attributes:
        center: (3,) the box centre; axes: (3, 3) its unit axes as rows; half: (3,) its
            half-extents along them.
        n_points: the points it was built from.
    """

    def __init__(self, center: Tensor, axes: Tensor, half: Tensor, n_points: int = 0) -> None:
        self.center, self.axes, self.half = center, axes, half
        self.n_points = n_points

    @classmethod
    def from_points(cls, points: np.ndarray, track_len: np.ndarray | None = None,
                    margin: float = 0.1, min_views: int = 2) -> PointBound | None:
        """The box of the points inside the unit sphere (seen by `min_views` views or more).

        Args:
            points: (M, 3) normalised frame; track_len: (M,) or None (all count).
            margin: widening of every face, as a fraction of the box's diagonal.
            min_views: least track length of a point that counts.

        Returns:
            The bound, or None with fewer than `MIN_POINTS` usable points.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        keep = np.linalg.norm(p, axis=-1) < 1.0
        if track_len is not None:
            keep &= np.asarray(track_len).reshape(-1) >= min_views
        p = p[keep]
        if len(p) < MIN_POINTS:
            return None
        mean = p.mean(0)
        _, vecs = np.linalg.eigh(np.cov((p - mean).T))  # columns: principal axes
        axes = vecs.T
        local = (p - mean) @ axes.T  # (M, 3)
        lo, hi = local.min(0), local.max(0)
        pad = margin * float(np.linalg.norm(hi - lo))
        lo, hi = lo - pad, hi + pad
        center = mean + 0.5 * (lo + hi) @ axes
        t = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
        return cls(t(center), t(axes), t(0.5 * (hi - lo)), n_points=len(p))

    @classmethod
    def for_scene(cls, scene, margin: float = 0.1, min_views: int = 2) -> PointBound | None:
        """The bound of a loaded scene whose folder holds ``sparse_points.npz`` (else None)."""
        path = Path(scene.root) / POINTS_FILE
        if not path.is_file():
            return None
        pts, track = read_points(path, np.asarray(scene.scale_mat))
        bound = cls.from_points(pts, track, margin, min_views)
        return None if bound is None else bound.to(scene.device)

    def to(self, device: str | torch.device) -> PointBound:
        """This bound on `device`."""
        return PointBound(self.center.to(device), self.axes.to(device), self.half.to(device),
                          self.n_points)

    def contains(self, points: Tensor) -> Tensor:
        """(..., 3) normalised points -> (...) bool, inside the box (closed)."""
        local = (points - self.center) @ self.axes.T
        return (local.abs() <= self.half).all(dim=-1)

    def ray_bounds(self, origins: Tensor, dirs: Tensor, near: Tensor,
                   far: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Each ray's [near, far] cut to the box (slab test; fixed shapes, no host sync).

        Args:
            origins: (B, 3); dirs: (B, 3) directions (any length > 0).
            near, far: (B, 1) the ray's interval (in units of `dirs`).

        Returns:
            lo, hi: (B, 1) with ``near <= lo <= hi <= far``; near, far where the ray misses.
            hits: (B,) bool, whether the ray meets the box inside [near, far].
        """
        o = (origins - self.center) @ self.axes.T  # (B, 3) box frame
        d = dirs @ self.axes.T
        tiny = torch.full_like(d, 1e-12)
        d = torch.where(d.abs() < 1e-12, torch.where(d < 0, -tiny, tiny), d)
        t1, t2 = (-self.half - o) / d, (self.half - o) / d  # (B, 3)
        t_in = torch.minimum(t1, t2).amax(dim=-1, keepdim=True)  # (B, 1)
        t_out = torch.maximum(t1, t2).amin(dim=-1, keepdim=True)
        lo, hi = torch.maximum(near, t_in), torch.minimum(far, t_out)
        hits = (hi > lo)[:, 0]
        lo = torch.where(hits[:, None], lo, near)
        hi = torch.where(hits[:, None], hi, far)
        return lo, hi, hits

    def fraction_of_sphere(self, n: int = 200_000, seed: int = 0) -> float:
        """Monte-Carlo fraction of the unit ball inside the box (a fixed seed)."""
        g = torch.Generator().manual_seed(seed)
        x = torch.rand(n, 3, generator=g) * 2.0 - 1.0
        x = x[x.norm(dim=-1) < 1.0].to(self.center.device)
        return float(self.contains(x).float().mean())

    def volume(self) -> float:
        """The box's volume (normalised units; the unit ball's is 4.19)."""
        return float(torch.prod(2.0 * self.half))

    def describe(self) -> str:
        """One line for the user."""
        h = self.half.tolist()
        return (f"SfM point box from {self.n_points} points, half-extents "
                f"{h[0]:.3f} x {h[1]:.3f} x {h[2]:.3f} (unit sphere: 1), keeps "
                f"{100.0 * self.fraction_of_sphere(20000):.1f} % of the sphere "
                f"(ball volume {4.0 / 3.0 * math.pi:.2f})")
