"""Free space the images see and the mesh fills, carved at mesh time (`neus-l0 mesh
--photo-carve`; issue #35).

The concave pixels of every training view are swept behind the mesh
(`neus_l0.mesh.plane_sweep`), and the rays whose neighbourhood agrees on free space behind
it carve (`neus_l0.mesh.sweep_consensus.consensus_rays`): each such ray is empty from the
mesh to a cell short of its best depth (`interval_maps`). The grid points that at least
`MIN_VIEWS` views see inside such free intervals (`free_votes`) are carved: the field becomes
``max(sdf, -d)`` with d the signed distance of the carved points
(`neus_l0.mesh.missed_parts.GridSolid`), so the new surface lies half a cell beyond them.

Pure functions of arrays, except `carve_solid` (a whole mesh and its views) and
`carved_model` (wraps a model for `neus_l0.mesh.extract.extract_mesh`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import trimesh

from neus_l0.data.cameras import depth_projection, pixel_indices, to_normalised, to_world
from neus_l0.errors import NeusL0Error
from neus_l0.mesh.missed_parts import GRID_CAP, GridSolid
from neus_l0.mesh.plane_sweep import (
    BEFORE_PX,
    REACH_PX,
    STEP_PX,
    concave_pixels,
    pixel_rays,
    sample_count,
)
from neus_l0.mesh.raster import finest_footprint
from neus_l0.mesh.sweep_consensus import consensus_rays

MIN_VIEWS = 2
"""Views whose carving rays a grid point must lie on."""


def interval_maps(pix: np.ndarray, z_from: np.ndarray, z_to: np.ndarray,
                  shape: tuple[int, int], stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) near and far camera depths of a view's free intervals (NaN: none), each
    carving pixel `pix` (N, 2) (x, y) standing for the `stride` x `stride` block it starts
    (the pixels the sweep skipped)."""
    near = np.full(shape, np.nan)
    far = np.full(shape, np.nan)
    for dy in range(stride):
        for dx in range(stride):
            x, y = pix[:, 0] + dx, pix[:, 1] + dy
            ok = (x < shape[1]) & (y < shape[0])
            near[y[ok], x[ok]] = z_from[ok]
            far[y[ok], x[ok]] = z_to[ok]
    return near, far


def free_votes(points: np.ndarray, projections: np.ndarray,
               maps: Sequence[tuple[np.ndarray, np.ndarray] | None]) -> np.ndarray:
    """(N,) how many views see the world points (N, 3) inside a free interval: the point's
    nearest pixel has one (`interval_maps`; None: the view has none) and the point's camera
    depth lies within it."""
    P_n = depth_projection(np.asarray(projections, dtype=np.float64))
    votes = np.zeros(len(points), np.int64)
    for v, m in enumerate(maps):
        if m is None:
            continue
        near, far = m
        col, row, z = pixel_indices(P_n[v], points, *near.shape)
        seen = col >= 0
        lo = np.full(len(points), np.nan)
        hi = np.full(len(points), np.nan)
        lo[seen], hi[seen] = near[row[seen], col[seen]], far[row[seen], col[seen]]
        with np.errstate(invalid="ignore"):
            votes += (z >= lo) & (z <= hi)
    return votes


def carve_solid(mesh: trimesh.Trimesh, projections: np.ndarray, masks: Sequence[np.ndarray],
                gray: np.ndarray, scale_mat: np.ndarray, resolution: int,
                min_views: int = MIN_VIEWS, seed: int = 0) -> tuple[GridSolid | None, dict]:
    """The free space to carve from a run's field, and what was found.

    Args:
        mesh: the first mesh (world units).
        projections: (V, 3, 4) world -> pixel; masks: V (H, W) bool; gray: (V, H, W)
            grey images in [0, 1] of the training views.
        scale_mat: (4, 4) normalised -> world.
        resolution: the extraction's samples per axis (the grid is `GRID_CAP` at most).

    Returns:
        the carved points' solid (None when none), and a report: `consensus_rays`'s, with
        ``points`` (grid points carved) and ``grid``.

    Raises:
        NeusL0Error: the images and the masks disagree in number or size.
    """
    shapes = {m.shape for m in masks}
    if len(gray) != len(masks) or shapes != {tuple(np.shape(gray)[1:])}:
        raise NeusL0Error(f"--photo-carve: {len(gray)} images of {np.shape(gray)[1:]} for "
                          f"{len(masks)} masks of {sorted(shapes)}: they must match")
    R = min(int(resolution), GRID_CAP)
    foot = finest_footprint(mesh, projections)
    samples, face = trimesh.sample.sample_surface(mesh, sample_count(mesh, foot), seed=seed)
    normals = np.asarray(mesh.face_normals)[face]
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    found = [concave_pixels(samples, normals, verts, projections[v], m, foot, stride=1)
             for v, m in enumerate(masks)]
    offsets = np.arange(-BEFORE_PX, REACH_PX + 1e-9, STEP_PX) * foot
    rays, carve, report = consensus_rays(found, torch.as_tensor(np.asarray(gray, np.float32)),
                                         projections, offsets, foot, samples)
    report.update(points=0, grid=R)
    if not carve.any():
        return None, report
    cell = 2.0 / (R - 1) * float(np.cbrt(abs(np.linalg.det(scale_mat[:3, :3]))))
    maps: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(masks)
    ends = []
    for v in np.unique(rays["view"][carve]):
        k = carve & (rays["view"] == v)
        z_from, z_to = rays["z0"][k], rays["z_best"][k] - cell
        maps[v] = interval_maps(rays["pix"][k], z_from, z_to, masks[v].shape, stride=1)
        centre, dirs = pixel_rays(projections[v], rays["pix"][k].astype(np.float64))
        ends += [centre + dirs * z_from[:, None], centre + dirs * z_to[:, None]]
    box = to_normalised(np.concatenate(ends), scale_mat)
    lo = np.clip(np.floor((box.min(0) + 1) / 2 * (R - 1)).astype(int) - 1, 0, R - 1)
    hi = np.clip(np.ceil((box.max(0) + 1) / 2 * (R - 1)).astype(int) + 1, 0, R - 1)
    index = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi, strict=True)],
                                 indexing="ij"), -1).reshape(-1, 3)
    points = to_world(index / (R - 1) * 2.0 - 1.0, scale_mat)
    index = index[free_votes(points, projections, maps) >= min_views]
    if not len(index):
        return None, report
    report["points"] = len(index)
    return GridSolid.from_indices(index, R), report


class _CarvedSdf:
    """``sdf(p)`` (N, 1) = max(inner SDF, -solid's distance): the difference of the two."""

    def __init__(self, inner, solid: GridSolid):
        self.inner, self.solid = inner, solid

    def sdf(self, p: torch.Tensor) -> torch.Tensor:
        v = self.inner.sdf(p)  # (N, 1)
        d = self.solid.sdf(p).reshape(v.shape).to(v.dtype)
        return torch.maximum(v, -d)


class _CarvedModel:
    """What `neus_l0.mesh.extract.extract_mesh` reads of a model, its SDF carved."""

    def __init__(self, model, solid: GridSolid):
        self.sdf = _CarvedSdf(model.sdf, solid)
        self.color = getattr(model, "color", None)


def carved_model(model, solid: GridSolid) -> _CarvedModel:
    """`model` (anything with ``sdf.sdf(p)``, normalised frame) less the solid's points, for
    `neus_l0.mesh.extract.extract_mesh`."""
    return _CarvedModel(model, solid)
