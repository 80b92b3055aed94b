"""Free space the images see and the mesh fills, carved at mesh time (`neus-l0 mesh
--photo-carve`).

A deep pit's floor comes out raised (issue #35: the cup's cavity floor 10-16 world units
too high after 300 s on the CPU): few views see the floor, training sends it one ray in
thousands, and the colour network paints the floor's texture on whatever surface is there.
Each image is right; the views do not agree. A plane sweep settles it outside training
(`tools/sweep_depth.py`: on the cup's floor pixels, the mesh's depth is 15.6 units off in
the median, the sweep's 1.2).

For each training view, the pixels inside its mask whose mesh point lies in a concavity
(`CONCAVE_PX` pixel footprints or more inside the mesh's convex hull: pits, cavities, the
gaps between parts) are swept along their rays (`sweep_depths`): from the mesh's depth to
`REACH_PX` footprints behind it, a `PATCH` x `PATCH` patch on the plane through the point,
normal to the mesh there, is carried into every other view and scored (1 - NCC) / 2 on grey
values; the `BEST` views that agree best count (nothing here knows which views see the
point). A pixel whose best depth lies behind the mesh by more than `MARGIN_PX` footprints,
at a cost below `MAX_COST` and lower than the mesh depth's by `MIN_GAIN`, says that its ray
is empty from the mesh to a cell short of there (`interval_maps`: each swept pixel stands
for the `STRIDE` x `STRIDE` block it starts). The grid points that at least `MIN_VIEWS`
views see inside such free intervals (`free_votes`) are carved: the field becomes
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
from scipy.spatial import ConvexHull

from neus_l0.data.cameras import depth_projection, pixel_indices, to_normalised, to_world
from neus_l0.data.patches import ncc
from neus_l0.errors import NeusL0Error
from neus_l0.mesh.missed_parts import GRID_CAP, GridSolid
from neus_l0.mesh.raster import finest_footprint

FRONT_PX = 1.0
"""Samples within this many pixel footprints behind a pixel's nearest are its front surface."""
CONCAVE_PX = 4.0
"""A pixel is swept when its mesh point lies this many pixel footprints inside the convex
hull of the mesh (the open surface, which every view agrees on, is left alone)."""
REACH_PX = 24.0
"""How far behind the mesh the sweep reaches, in pixel footprints."""
BEFORE_PX = 2.0
"""How far in front of the mesh the sweep starts, in pixel footprints."""
STEP_PX = 1.0
"""The sweep's depth step, in pixel footprints."""
PATCH = 7
"""Side of the square patch, in pixels (7 x 7 and 3 views put 33 % of the carving rays'
ends more than a unit inside the cup's true surface, 5 x 5 and 2 views 48 %; session 22)."""
BEST = 3
"""How many views count at each depth: those that agree best."""
MARGIN_PX = 2.0
"""A best depth this many footprints or more behind the mesh carves."""
MAX_COST = 0.15
"""A best depth carves only when its cost (1 - NCC) / 2 is below this."""
MIN_GAIN = 0.1
"""... and lower than the cost at the mesh's depth by this much."""
MIN_VIEWS = 2
"""Views whose carving rays a grid point must lie on."""
STRIDE = 3
"""Candidate pixels are taken on every STRIDE-th row and column."""
NCC_EPS = 1e-6
"""Added to the patches' grey variances in the NCC (`neus_l0.data.patches.ncc`): the
training term's 1e-4 scores low-contrast 7x7 patches near 0 and carved a third fewer rays on
the cup (221 against 338 of 27096); 1e-6 only keeps flat patches finite."""
INVALID = 2.0
"""Cost of a view that cannot score a patch (above any real cost, at most 1)."""


def depth_map(samples: np.ndarray, normals: np.ndarray, projection: np.ndarray,
              shape: tuple[int, int], foot: float) -> tuple[np.ndarray, np.ndarray]:
    """A mesh's depth in one view, from dense surface samples: per pixel, of the samples on
    the front surface (within `FRONT_PX` footprints of the nearest), the one that lands
    nearest the pixel's centre (the nearest alone reads a tilted face up to half a pixel's
    depth range too near).

    Args:
        samples: (n, 3) surface samples, world units; normals: (n, 3) their unit normals.
        projection: (3, 4) world -> pixel.
        shape: the image's (H, W).
        foot: a pixel's footprint, world units (`neus_l0.mesh.raster.finest_footprint`).

    Returns:
        (H, W) camera-z depth (NaN where no sample lands) and (H, W, 3) that sample's
        normal, turned towards the camera.
    """
    H, W = shape
    P = depth_projection(projection)
    uvw = samples @ P[:, :3].T + P[:, 3]
    z = uvw[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = uvw[:, 0] / z, uvw[:, 1] / z
    ok = (z > 0) & (u > -0.5) & (u < W - 0.5) & (v > -0.5) & (v < H - 0.5)
    idx = np.flatnonzero(ok)
    col, row = np.rint(u[idx]).astype(np.int64), np.rint(v[idx]).astype(np.int64)
    flat = row * W + col
    front = np.full(H * W, np.inf)
    np.minimum.at(front, flat, z[idx])
    near = z[idx] <= front[flat] + FRONT_PX * foot
    idx, flat = idx[near], flat[near]
    off = (u[idx] - col[near]) ** 2 + (v[idx] - row[near]) ** 2
    order = np.lexsort((off, flat))  # by pixel, nearest the centre first
    first = np.ones(order.size, bool)
    first[1:] = flat[order][1:] != flat[order][:-1]
    pick, at = idx[order[first]], flat[order[first]]
    depth = np.full(H * W, np.nan)
    depth[at] = z[pick]
    centre = -np.linalg.solve(P[:, :3], P[:, 3])
    n = normals[pick]
    n = np.where((((centre - samples[pick]) * n).sum(-1) < 0)[:, None], -n, n)
    nrm = np.zeros((H * W, 3))
    nrm[at] = n
    return depth.reshape(H, W), nrm.reshape(H, W, 3)


def hull_depth(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """(N,) how far the points (N, 3) lie inside the convex hull of `vertices` (M, 3): the
    least distance to the hull's facet planes (exact for points inside; <= 0 outside)."""
    eq = ConvexHull(vertices).equations  # (F, 4): n . x + b <= 0 inside, n unit
    out = np.empty(len(points))
    for s in range(0, len(points), 65536):
        p = points[s:s + 65536]
        out[s:s + 65536] = (-(p @ eq[:, :3].T + eq[:, 3])).min(axis=1)
    return out


def pixel_rays(projection: np.ndarray, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera centre (3,) and the rays (..., 3) of pixels `pix` (..., 2) (x, y), scaled
    to camera-z 1: the point at depth z is ``centre + z * ray``."""
    P = depth_projection(projection)
    M_inv = np.linalg.inv(P[:, :3])
    h = np.concatenate([pix, np.ones(pix.shape[:-1] + (1,))], axis=-1)
    return M_inv @ -P[:, 3], h @ M_inv.T


def view_costs(gray: torch.Tensor, P: torch.Tensor, centres: torch.Tensor, ref: torch.Tensor,
               pts: torch.Tensor, X: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """(V, n) the cost (1 - NCC) / 2 of each view's patch against the reference, `INVALID`
    where the view cannot score it (a patch point behind it or off its image, or the plane
    facing away).

    Args:
        gray: (V, H, W) grey images; P: (V, 3, 4) float64 depth-normalised projections
            (`depth_projection`); centres: (V, 3) the cameras' centres.
        ref: (n, Q) the reference patches; pts: (n, Q, 3) the patches' plane points, world
            units; X: (n, 3) the patches' centres; normal: (n, 3) the planes' normals.
    """
    V, H, W = gray.shape
    uvw = torch.einsum("vij,nqj->vnqi", P[:, :, :3], pts) + P[:, None, None, :, 3]
    zc = uvw[..., 2]
    u = uvw[..., 0] / zc.clamp_min(1e-9)
    v = uvw[..., 1] / zc.clamp_min(1e-9)
    grid = torch.stack([u / (W - 1) * 2 - 1, v / (H - 1) * 2 - 1], -1).float()
    vals = torch.nn.functional.grid_sample(gray[:, None], grid.reshape(V, -1, 1, 2),
                                           align_corners=True).reshape(u.shape)
    inside = ((u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1) & (zc > 0)).all(-1)
    facing = ((centres[:, None] - X[None]) * normal[None]).sum(-1) > 0  # (V, n)
    score = ncc(ref.double(), vals.double().permute(1, 0, 2), NCC_EPS).T  # (V, n)
    return torch.where(inside & facing, (1 - score) / 2,
                       torch.full_like(score, INVALID))


def sweep_depths(gray: torch.Tensor, projections: np.ndarray, view: int, pix: np.ndarray,
                 normal: np.ndarray, z0: np.ndarray, offsets: np.ndarray,
                 patch: int = PATCH, best: int = BEST, chunk: int = 1024
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A plane sweep along the rays of one view's pixels.

    Args:
        gray: (V, H, W) float32 grey images of every view.
        projections: (V, 3, 4) world -> pixel.
        view: the pixels' view.
        pix: (N, 2) integer pixel coordinates (x, y); normal: (N, 3) unit plane normals.
        z0: (N,) the starting camera depth (the mesh's); offsets: (T,) depths swept
            around it.
        patch: odd patch side; best: how many views count at a depth.

    Returns:
        (N,) the depth of least cost, (N,) that cost, and (N,) the cost at `z0` itself
        (`INVALID` where fewer than `best` views can score the patch).
    """
    V, H, W = gray.shape
    P = torch.as_tensor(depth_projection(projections))  # (V, 3, 4) float64
    centres = torch.linalg.solve(P[:, :, :3], -P[:, :, 3:]).squeeze(-1)  # (V, 3)
    h = patch // 2
    dy, dx = np.meshgrid(np.arange(-h, h + 1), np.arange(-h, h + 1), indexing="ij")
    off = np.stack([dx.ravel(), dy.ravel()], -1)  # (Q, 2)
    z_best = np.asarray(z0, np.float64).copy()
    c_best = np.full(len(pix), INVALID)
    c_zero = np.full(len(pix), INVALID)
    for s in range(0, len(pix), chunk):
        q = pix[s:s + chunk, None, :] + off[None]  # (n, Q, 2)
        c, rays = pixel_rays(projections[view], q.astype(np.float64))
        c, rays = torch.as_tensor(c), torch.as_tensor(rays)  # (3,), (n, Q, 3)
        qi = torch.as_tensor(q)
        inside_ref = ((qi[..., 0] >= 0) & (qi[..., 0] < W) & (qi[..., 1] >= 0)
                      & (qi[..., 1] < H)).all(-1)
        ref = gray[view][qi[..., 1].clamp(0, H - 1), qi[..., 0].clamp(0, W - 1)]  # (n, Q)
        n = torch.as_tensor(normal[s:s + chunk], dtype=torch.float64)
        zs = torch.as_tensor(z0[s:s + chunk], dtype=torch.float64)
        ray0 = rays[:, (patch * patch) // 2]  # (n, 3)
        denom = (rays * n[:, None]).sum(-1)  # (n, Q)
        for k, dz in enumerate(np.concatenate([[0.0], offsets])):
            X = c + ray0 * (zs + dz)[:, None]  # (n, 3)
            t = ((X - c) * n).sum(-1, keepdim=True) / denom  # (n, Q)
            cost = view_costs(gray, P, centres, ref, c + rays * t[..., None], X, n)
            cost[:, ~(t > 0).all(-1)] = INVALID
            cost[view] = INVALID  # the pixel's own view
            kept = torch.topk(cost, min(best, V - 1), dim=0, largest=False).values
            score = torch.where((kept < INVALID).all(0) & inside_ref, kept.mean(0),
                                torch.full_like(kept[0], INVALID)).numpy()
            sl = slice(s, s + len(score))
            if k == 0:
                c_zero[sl] = score
                continue
            better = score < c_best[sl]
            c_best[sl] = np.where(better, score, c_best[sl])
            z_best[sl] = np.where(better, z0[sl] + dz, z_best[sl])
    return z_best, c_best, c_zero


def carve_rays(z0: np.ndarray, z_best: np.ndarray, c_best: np.ndarray, c_zero: np.ndarray,
               foot: float) -> np.ndarray:
    """(N,) bool the rays that carve: best depth `MARGIN_PX` footprints (`foot` world units
    each) or more behind the mesh's `z0`, its cost below `MAX_COST` and below the mesh
    depth's by `MIN_GAIN`."""
    return ((z_best - z0 >= MARGIN_PX * foot) & (c_best < MAX_COST)
            & (c_zero - c_best >= MIN_GAIN))


def interval_maps(pix: np.ndarray, z_from: np.ndarray, z_to: np.ndarray,
                  shape: tuple[int, int], stride: int = STRIDE) -> tuple[np.ndarray, np.ndarray]:
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


def concave_pixels(samples: np.ndarray, normals: np.ndarray, vertices: np.ndarray,
                   projection: np.ndarray, mask: np.ndarray, foot: float,
                   stride: int = STRIDE) -> tuple | None:
    """One view's pixels to sweep: every `stride`-th row and column inside the mask, where
    the mesh (its surface samples (n, 3) with normals (n, 3), and its vertices (M, 3)) is
    seen `CONCAVE_PX` footprints or more inside its convex hull.

    Returns:
        None when there are none, else the (N, 2) pixels (x, y), the camera centre (3,),
        their rays (N, 3) (`pixel_rays`), the mesh's camera depth (N,) and normal (N, 3).
    """
    depth, nrm = depth_map(samples, normals, projection, mask.shape, foot)
    pick = np.zeros(mask.shape, bool)
    pick[::stride, ::stride] = True
    ys, xs = np.nonzero(pick & mask & np.isfinite(depth))
    if not len(xs):
        return None
    pix = np.stack([xs, ys], -1)
    centre, rays = pixel_rays(projection, pix.astype(np.float64))
    z0 = depth[ys, xs]
    deep = hull_depth(centre + rays * z0[:, None], vertices) >= CONCAVE_PX * foot
    if not deep.any():
        return None
    return pix[deep], centre, rays[deep], z0[deep], nrm[ys[deep], xs[deep]]


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
        the carved points' solid (None when none), and a report: ``swept`` (pixels),
        ``carving`` (rays that carve), ``points`` (grid points carved), ``grid``.

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
    g = torch.as_tensor(np.asarray(gray, np.float32))
    offsets = np.arange(-BEFORE_PX, REACH_PX + 1e-9, STEP_PX) * foot
    cell = 2.0 / (R - 1) * float(np.cbrt(abs(np.linalg.det(scale_mat[:3, :3]))))
    report = {"swept": 0, "carving": 0, "points": 0, "grid": R}
    maps: list[tuple[np.ndarray, np.ndarray] | None] = []
    ends = []
    for v, mask in enumerate(masks):
        maps.append(None)
        found = concave_pixels(samples, normals, verts, projections[v], mask, foot)
        if found is None:
            continue
        pix, centre, rays, z0, n = found
        z_best, c_best, c_zero = sweep_depths(g, projections, v, pix, n, z0, offsets)
        carve = carve_rays(z0, z_best, c_best, c_zero, foot)
        report["swept"] += len(pix)
        report["carving"] += int(carve.sum())
        if carve.any():
            z_from, z_to = z0[carve], z_best[carve] - cell
            maps[-1] = interval_maps(pix[carve], z_from, z_to, mask.shape)
            ends += [centre + rays[carve] * z_from[:, None], centre + rays[carve] * z_to[:, None]]
    if not ends:
        return None, report
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


def sample_count(mesh: trimesh.Trimesh, foot: float) -> int:
    """Surface samples for `depth_map`: about 4 per finest pixel footprint, 10^5 to 4 x 10^6."""
    return int(min(4e6, max(1e5, 4 * mesh.area / foot**2)))


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
