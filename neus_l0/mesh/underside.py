"""The underside no training view sees, closed flat (`neus-l0 mesh --close-underside`).

Cameras that look at an object from above (DTU, a turntable, photos of a thing on a table)
never see its underside. The masks then bound it only by the visual hull, a cone under the
object along the lowest views' grazing rays, and the trained SDF fills that cone: a sag
below the base (docs/BENCHMARKS.md, "Where does the error live"). Nothing in the images
tells a flat bottom from the sag, but a user scanning an object wants the flat one, and the
sag's rim, seen a pixel outside the silhouettes, is what the visibility-based score counts.

This module finds the plane to close it at, from a first mesh (world units):

- *up* is the direction perpendicular to the cameras' image x axes (photos are upright), or
  for a rolled rig the mean direction from the mesh's centre to the cameras (`camera_up`);
- a vertex is *seen* by a view when it is the front-most surface at its pixel and that
  pixel is in the view's mask (`seen_counts`): a z-buffer of dense surface samples, its
  3x3 minimum so that no gap between samples lets a hidden vertex through, and one pixel's
  footprint of depth tolerance;
- the plane lies `margin` mean edge lengths (half of one by default) below the lowest vertex
  so seen that is not a straggler, along up (`underside_plane`): `min_ring` seen vertices
  (itself among them) must lie within one mean edge above it. The sag's rim, 1-2 pixels
  outside the silhouettes, can show a few vertices inside a mask; on the demo's seed 2
  (2026-11-29) seven such, the lowest 4.7 units under the base, put the plane 6.1 units
  under the base, and the rim it left raised the accuracy 0.74 -> 0.95.

Everything below that plane is below every vertex the views see: cutting it removes only
what no view saw. `cut_below` then intersects the SDF with the half-space above the plane
(``max(sdf, h - up . x)``), so that marching cubes closes the bottom with a flat cap.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import trimesh
from scipy.ndimage import minimum_filter

from neus_l0.data.cameras import decompose_projection, depth_projection, pixel_indices
from neus_l0.errors import NeusL0Error
from neus_l0.mesh.raster import foot_ratio, surface_samples

MIN_RING = 5
"""Seen vertices that must lie within one mean edge above the lowest one counted."""

UPRIGHT_SPREAD = 0.02
"""Largest mean squared up-component of the cameras' x axes for a rig to count as upright
(about 8 degrees of roll, root mean square)."""


def camera_up(projections: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(3,) the world's up as the cameras show it.

    Photos are taken upright: each camera's x axis (image right) is horizontal. Up is then
    the direction most perpendicular to all of them (the smallest eigenvector of
    ``sum_i x_i x_i^T``), exact whatever the azimuths, where the mean direction from the
    object to the cameras tilts with an uneven ring (1.7 degrees on the demo's 24 views) or a
    rig on one side (DTU). A rig that is not upright (rolled cameras) falls back to that mean
    direction. The sign puts the cameras above.

    Args:
        projections: (V, 3, 4) world -> pixel.
        centre: (3,) the object's centre.

    Raises:
        NeusL0Error: the cameras surround the centre (no side is unseen).
    """
    c2w = np.stack([decompose_projection(P)[1] for P in projections])  # (V, 4, 4)
    d = c2w[:, :3, 3] - np.asarray(centre, dtype=np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    mean = d.mean(axis=0)
    right = c2w[:, :3, 0]  # (V, 3) image x axes
    spread, axes = np.linalg.eigh(right.T @ right / len(right))  # ascending
    upright = spread[0] < UPRIGHT_SPREAD and spread[1] > 5 * UPRIGHT_SPREAD
    up = axes[:, 0] if upright else mean / max(np.linalg.norm(mean), 1e-12)
    side = float(mean @ up)
    if abs(side) < 0.1:
        raise NeusL0Error("--close-underside: the cameras surround the object (their mean "
                          "direction from it is near zero along up), so no side is unseen")
    return up * np.sign(side)


def seen_counts(mesh: trimesh.Trimesh, projections: np.ndarray,
                masks: Sequence[np.ndarray], tol_px: float = 1.0, seed: int = 0) -> np.ndarray:
    """(N,) how many views see each vertex of `mesh` (world units) inside their mask.

    Args:
        mesh: the mesh, N vertices.
        projections: (V, 3, 4) world -> pixel.
        masks: V (H, W) bool foreground masks.
        tol_px: how far behind the front-most sample a vertex still counts as in front,
            in pixel footprints at its depth.
        seed: the surface samples' seed.
    """
    P_n = depth_projection(np.asarray(projections, dtype=np.float64))  # camera-z depth rows
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    samples = surface_samples(mesh, projections, seed=seed)
    counts = np.zeros(len(verts), dtype=np.int64)
    for v, mask in enumerate(masks):
        h, w = mask.shape
        cs, rs, zs = pixel_indices(P_n[v], samples, h, w)
        k = cs >= 0
        zbuf = np.full((h, w), np.inf)
        np.minimum.at(zbuf, (rs[k], cs[k]), zs[k])
        zbuf = minimum_filter(zbuf, size=3, mode="nearest")  # no gaps between samples
        col, row, z = pixel_indices(P_n[v], verts, h, w)
        ok = np.flatnonzero(col >= 0)
        tol = tol_px * z[ok] * foot_ratio(projections[v])  # pixels' footprint at that depth
        front = z[ok] <= zbuf[row[ok], col[ok]] + tol
        counts[ok[front & mask[row[ok], col[ok]]]] += 1
    return counts


def lowest_firm(heights: np.ndarray, band: float, min_ring: int) -> float:
    """The lowest of (N,) `heights` (N >= 1) that has `min_ring` of them (itself included)
    within `band` above it; the lowest of all when none has (fewer than `min_ring` in any
    band)."""
    h = np.sort(np.asarray(heights, dtype=np.float64))
    ring = np.searchsorted(h, h + band, side="right") - np.arange(len(h))  # (N,) in [h, h + band]
    firm = np.flatnonzero(ring >= min_ring)
    return float(h[firm[0]] if firm.size else h[0])


def underside_plane(mesh: trimesh.Trimesh, projections: np.ndarray,
                    masks: Sequence[np.ndarray], margin: float = 0.5,
                    min_views: int = 1, min_ring: int = MIN_RING
                    ) -> tuple[np.ndarray, float] | None:
    """The plane to close the unseen underside at: (up (3,), height) with the kept side
    ``up . x >= height`` (world units), or None when no vertex lies below it.

    Args:
        mesh: the first mesh (world units).
        projections, masks: the training views (see `seen_counts`).
        margin: how far below the lowest seen vertex counted, in mean edge lengths.
        min_views: views that must see a vertex for it to count.
        min_ring: seen vertices within one mean edge above the lowest counted one, itself
            included (`lowest_firm`).

    Raises:
        NeusL0Error: no vertex is seen by `min_views` views, or the cameras surround the
            object.
    """
    up = camera_up(projections, mesh.bounds.mean(axis=0))
    counts = seen_counts(mesh, projections, masks)
    seen = counts >= min_views
    if not seen.any():
        raise NeusL0Error(f"--close-underside: no vertex of the mesh is seen by {min_views} "
                          "views inside their masks (do the masks match the scene?)")
    heights = np.asarray(mesh.vertices) @ up
    edge = float(mesh.edges_unique_length.mean())
    height = lowest_firm(heights[seen], edge, min_ring) - margin * edge
    if heights.min() >= height:
        return None
    return up, height


def underside_line(plane: dict | None) -> str:
    """What `neus-l0 mesh --close-underside` says of the plane it used (``mesh.metadata
    ["underside_plane"]``: ``up`` and ``height`` in world units, or None)."""
    if plane is None:
        return "underside: nothing below the lowest seen point"
    up = [round(float(u), 3) for u in plane["up"]]
    return f"underside closed at height {plane['height']:.3f} along up {up} (world units)"


class _CutSdf:
    """``sdf(p)`` (N, 1) = max(inner SDF, height - up . p): the SDF of the intersection with
    the half-space ``up . p >= height``."""

    def __init__(self, inner, up: np.ndarray, height: float):
        self.inner, self.height = inner, float(height)
        self.up = torch.as_tensor(np.asarray(up, dtype=np.float64), dtype=torch.float32)

    def sdf(self, p: torch.Tensor) -> torch.Tensor:
        v = self.inner.sdf(p)  # (N, 1)
        up = self.up.to(p.device)
        plane = (self.height - p.to(up.dtype) @ up).reshape(v.shape).to(v.dtype)
        return torch.maximum(v, plane)


class _CutModel:
    """What `neus_l0.mesh.extract.extract_mesh` reads of a model, its SDF cut (`cut_below`)."""

    def __init__(self, model, up: np.ndarray, height: float):
        self.sdf = _CutSdf(model.sdf, up, height)
        self.color = getattr(model, "color", None)


def cut_below(model, up: np.ndarray, height: float) -> _CutModel:
    """`model` (anything with ``sdf.sdf(p)``, normalised frame) whose SDF is intersected with
    the half-space ``up . x >= height`` (up (3,) unit, normalised frame), for
    `neus_l0.mesh.extract.extract_mesh`: the mesh is cut flat and closed there."""
    return _CutModel(model, up, height)
