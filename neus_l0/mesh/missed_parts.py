"""Parts the masks see and the mesh misses, filled from the visual hull (`neus-l0 mesh
--fill-missed`).

A thin part that training never formed (issue #35: `pits-deep`'s r1 rod, 2 px across at
400x300, missing in 11 of 12 default runs) leaves a trace the masks keep: in the views that
see it against the background, its pixels are foreground while the mesh's silhouette does
not reach them. On such a *missed* pixel the object lies somewhere along the pixel's ray,
and the visual hull at pixel resolution says where: the points that every view sees inside
its mask (`neus_l0.bounds.silhouettes`' rule at margin 0). Along a missed ray these form a
short segment at the part (0.5-2 world units from the rod's axis on `pits-deep`, session 20).

This step takes the points of a regular grid that lie inside every training view's mask and
fall on missed pixels of at least `min_views` views (`missed_points`) as a solid: the signed
distance of that set of grid points (`GridSolid`), whose surface marching cubes closes half a
cell around them (`solid_model`). `neus_l0.mesh.from_run` adds its pieces to the mesh after the
other steps, as closed pieces of their own: a rod's piece meets the surface it stands on
within half a cell. Joined to the SDF by a minimum instead, the rod merged with a floater that
training left beside it, and `--drop-outside-masks` then dropped both (pits-and-thin, seed 0).
Nothing else of the mesh moves: a point the mesh already covers in a view is not on a
missed pixel there, and a missed pixel that no grid point inside every mask falls on adds
nothing.

The mesh's pieces that a view sees off its mask (`neus_l0.mesh.mask_outliers`: floaters
next to a thin part that training smeared out) are not the object and cover nothing. The
mesh's silhouette in a view is rasterised from dense surface samples
(`neus_l0.mesh.raster`) and grown by one pixel (a 3x3 dilation, so that no gap between
samples reads as missed, and a one-pixel tolerance for the mesh's own rounding at the
silhouette); `tol_px` widens it further.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import torch
import trimesh
from scipy import ndimage

from neus_l0.data.cameras import depth_projection, pixel_indices, to_world
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.cull import dilate_mask
from neus_l0.mesh.mask_outliers import mask_outliers
from neus_l0.mesh.raster import silhouette, surface_samples

MIN_VIEWS = 2
"""Views whose missed pixels a grid point must fall on (one view's mask error adds nothing)."""
GRID_CAP = 256
"""The finest grid the filled points are placed on (samples per axis): at 256 over the unit
sphere's box a cell is ~1 world unit on the synthetic scenes, a pixel at 400x300."""


def missed_pixels(mesh: trimesh.Trimesh, projections: np.ndarray,
                  masks: Sequence[np.ndarray], tol_px: int = 0,
                  seed: int = 0) -> list[np.ndarray]:
    """Per view, the foreground pixels that the mesh's silhouette does not reach (its pieces
    seen off a mask left out).

    Args:
        mesh: the first mesh, world units.
        projections: (V, 3, 4) world -> pixel of the training views.
        masks: V (H, W) bool foreground masks.
        tol_px: pixels the silhouette is grown by beyond its one-pixel 3x3 dilation.
        seed: the surface samples' seed.

    Returns:
        V (H, W) bool: mask and not (silhouette grown by 1 + `tol_px`).
    """
    P_n = depth_projection(np.asarray(projections, dtype=np.float64))
    try:
        mesh, _ = mask_outliers(mesh, projections, masks)
    except NeusL0Error:  # every piece off some mask: the masks say nothing of this mesh
        pass
    samples = surface_samples(mesh, projections, seed=seed)
    out = []
    for v, mask in enumerate(masks):
        cover = silhouette(samples, P_n[v], mask.shape)
        out.append(np.asarray(mask, bool) & ~dilate_mask(cover, tol_px))
    return out


def missed_points(points: np.ndarray, projections: np.ndarray, masks: Sequence[np.ndarray],
                  missed: Sequence[np.ndarray], min_views: int = MIN_VIEWS
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Which points lie inside every view's mask and on missed pixels of `min_views` views.

    A view that does not see a point (behind the camera, or its nearest pixel off the image)
    says nothing about it, as in `neus_l0.bounds.silhouettes.in_silhouettes`.

    Args:
        points: (N, 3) world units.
        projections: (V, 3, 4) world -> pixel.
        masks: V (H, W) bool foreground masks.
        missed: V (H, W) bool missed pixels (`missed_pixels`).
        min_views: the views a point's missed pixels must number.

    Returns:
        (N,) bool the points kept, and (N,) int how many views' missed pixels each falls on.
    """
    P_n = depth_projection(np.asarray(projections, dtype=np.float64))
    inside = np.ones(len(points), bool)
    count = np.zeros(len(points), np.int64)
    for v, mask in enumerate(masks):
        col, row, _ = pixel_indices(P_n[v], points, *mask.shape)
        seen = col >= 0
        inside[seen] &= mask[row[seen], col[seen]]
        count[seen] += missed[v][row[seen], col[seen]]
    return inside & (count >= min_views), count


@dataclasses.dataclass(frozen=True)
class GridSolid:
    """The signed distance of a set of grid points, on a box of that grid (normalised frame).

    The surface lies half a cell outside the points: ``-(distance to the nearest point not in
    the set) + h / 2`` inside, ``distance to the nearest point in the set - h / 2`` outside
    (exact Euclidean distance transforms on the grid, `scipy.ndimage.distance_transform_edt`).

    Attributes:
        values: (X, Y, Z) float32 the distance on the box's grid points.
        origin: (3,) the box's first grid point; step: the grid's cell size.
    """

    values: torch.Tensor
    origin: np.ndarray
    step: float

    @classmethod
    def from_indices(cls, index: np.ndarray, resolution: int, bound: float = 1.0) -> GridSolid:
        """The solid of the grid points `index` (K, 3) int of ``linspace(-bound, bound,
        resolution)^3`` (K >= 1)."""
        step = 2.0 * bound / (resolution - 1)
        lo = index.min(axis=0) - 2
        shape = index.max(axis=0) - lo + 3
        inside = np.zeros(shape, bool)
        inside[tuple((index - lo).T)] = True
        outside_d = ndimage.distance_transform_edt(~inside)
        inside_d = ndimage.distance_transform_edt(inside)
        values = np.where(inside, 0.5 - inside_d, outside_d - 0.5) * step
        return cls(torch.as_tensor(values, dtype=torch.float32), lo * step - bound, step)

    def sdf(self, p: torch.Tensor) -> torch.Tensor:
        """(N,) the solid's distance at points `p` (N, 3): trilinear inside the box; outside
        it, the distance to the box plus 1.5 cells (a lower bound of the distance to the
        surface, which lies at least 1.5 cells inside the box's faces), so that sparse
        extraction's block test (`neus_l0.mesh.extract.keep_blocks`) finds the solid."""
        size = torch.as_tensor((np.array(self.values.shape) - 1) * self.step, dtype=torch.float64)
        q = (p.detach().double().cpu() - torch.as_tensor(self.origin)) / size * 2.0 - 1.0
        inside = ((q >= -1.0) & (q <= 1.0)).all(dim=-1)
        grid = q.flip(-1).float()[None, :, None, None, :]  # grid_sample's (x, y, z) = (Z, Y, X)
        vals = torch.nn.functional.grid_sample(self.values[None, None], grid,
                                               align_corners=True).reshape(-1)
        lo = torch.as_tensor(self.origin)
        gap = torch.maximum(lo - p.detach().double().cpu(), p.detach().double().cpu() - lo - size)
        outside = gap.clamp(min=0.0).norm(dim=-1) + 1.5 * self.step
        return torch.where(inside, vals, outside.float()).to(p.device)


class _SolidSdf:
    def __init__(self, solid: GridSolid):
        self.solid = solid

    def sdf(self, p: torch.Tensor) -> torch.Tensor:
        return self.solid.sdf(p).reshape(-1, 1)


class _SolidModel:
    """What `neus_l0.mesh.extract.extract_mesh` reads of a model (``sdf.sdf(p)`` (N, 1),
    ``color``), for a solid alone (`solid_model`)."""

    def __init__(self, solid: GridSolid):
        self.sdf = _SolidSdf(solid)
        self.color = None


def solid_model(solid: GridSolid) -> _SolidModel:
    """`solid` as a model `neus_l0.mesh.extract.extract_mesh` extracts (its own pieces)."""
    return _SolidModel(solid)


def missed_solid(mesh: trimesh.Trimesh, projections: np.ndarray, masks: Sequence[np.ndarray],
                 scale_mat: np.ndarray, contains, resolution: int,
                 min_views: int = MIN_VIEWS, tol_px: int = 0
                 ) -> tuple[GridSolid | None, dict]:
    """The solid whose pieces `neus_l0.mesh.from_run` adds to a run's mesh, and what was found.

    Args:
        mesh: the first mesh (world units).
        projections, masks: the training views (`missed_pixels`).
        scale_mat: (4, 4) normalised -> world.
        contains: the region to search, ``contains(p (N, 3) normalised) -> (N,) bool``
            (the run's visual hull), or None for the whole box.
        resolution: the extraction's samples per axis (the grid is `GRID_CAP` at most).
        min_views, tol_px: see `missed_points` and `missed_pixels`.

    Returns:
        the solid (None when no point is found), and a report: ``missed_pixels`` (over all
        views), ``points`` (grid points added), ``pieces`` (their 26-connected groups),
        ``grid`` (samples per axis).
    """
    missed = missed_pixels(mesh, projections, masks, tol_px)
    R = min(int(resolution), GRID_CAP)
    report = {"missed_pixels": int(sum(int(m.sum()) for m in missed)), "points": 0,
              "pieces": 0, "grid": R}
    if report["missed_pixels"] == 0:
        return None, report
    axis = torch.linspace(-1.0, 1.0, R, dtype=torch.float64)
    yz = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), dim=-1).reshape(-1, 2)
    found = []
    for i in range(R):  # a slab of constant x at a time: R^2 points
        p = torch.cat([axis[i].expand(len(yz), 1), yz], dim=1)
        keep = torch.ones(len(p), dtype=torch.bool) if contains is None else contains(p).cpu()
        if not bool(keep.any()):
            continue
        pn = p[keep].numpy()
        hit, _ = missed_points(to_world(pn, scale_mat), projections, masks, missed, min_views)
        if hit.any():
            j = torch.nonzero(keep).reshape(-1).numpy()[hit]
            found.append(np.stack([np.full(len(j), i), j // R, j % R], axis=1))
    if not found:
        return None, report
    index = np.concatenate(found)
    solid = GridSolid.from_indices(index, R)
    box = np.zeros(index.max(0) - index.min(0) + 1, bool)
    box[tuple((index - index.min(0)).T)] = True
    report.update(points=len(index), pieces=int(ndimage.label(box, np.ones((3, 3, 3)))[1]))
    return solid, report
