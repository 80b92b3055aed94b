"""A plane sweep of the training images along rays behind a mesh (issue #35).

A deep pit's floor comes out raised (the cup's cavity floor 10-16 world units too high after
300 s on the CPU): few views see the floor, training sends it one ray in thousands, and the
colour network paints the floor's texture on whatever surface is there. Each image is right;
the views do not agree. A plane sweep asks the images directly (`tools/sweep_depth.py`: on
the cup's floor pixels the mesh's depth is 15.6 units off in the median, the sweep's 1.2).

The pixels inside a view's mask whose mesh point lies in a concavity (`concave_pixels`:
`CONCAVE_PX` pixel footprints or more inside the mesh's convex hull, i.e. pits, cavities, the
gaps between parts) are swept along their rays (`sweep_depths`): from `BEFORE_PX` footprints
in front of the mesh's depth to `REACH_PX` behind it, a `PATCH` x `PATCH` patch on the plane
through the point, normal to the mesh there, is carried into every other view and scored
(1 - NCC) / 2 on grey values; the `BEST` views that agree best count (nothing here knows
which views see the point). Which sweeps to trust: `neus_l0.mesh.sweep_consensus`; the carve:
`neus_l0.mesh.photo_carve`.

Pure functions of arrays.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh
from scipy.spatial import ConvexHull

from neus_l0.data.cameras import depth_projection
from neus_l0.data.patches import ncc

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


def concave_pixels(samples: np.ndarray, normals: np.ndarray, vertices: np.ndarray,
                   projection: np.ndarray, mask: np.ndarray, foot: float,
                   stride: int = 1) -> tuple | None:
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


def sample_count(mesh: trimesh.Trimesh, foot: float) -> int:
    """Surface samples for `depth_map`: about 4 per finest pixel footprint, 10^5 to 4 x 10^6."""
    return int(min(4e6, max(1e5, 4 * mesh.area / foot**2)))
