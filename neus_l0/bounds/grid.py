"""The voxel grid that the visual hull and the occupancy grid share: cells, dilation, lookups
along rays.

Grid: ``R^3`` cells over the cube ``[-1, 1]^3`` of the normalised frame; cell ``(i, j, k)``
is ``x in [-1 + i c, -1 + (i + 1) c)`` with ``c = 2 / R`` along x (likewise y, z). Outside
the cube nothing is occupied. Pure tensor functions, fixed shapes (no boolean indexing, no
host synchronisation), so the lookups are safe under ``torch.compile`` and CUDA graphs.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def cell_axis(resolution: int, device: torch.device | str = "cpu") -> Tensor:
    """(R,) float32 cell-centre coordinates along one axis."""
    c = 2.0 / resolution
    return -1.0 + c * (torch.arange(resolution, device=device, dtype=torch.float32) + 0.5)


def cell_centres(resolution: int, device: torch.device | str = "cpu") -> Tensor:
    """(R, R, R, 3) cell centres, ``[i, j, k] = (x_i, y_j, z_k)``."""
    ax = cell_axis(resolution, device)
    return torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), dim=-1)


def dilate(occ: Tensor, cells: int = 1) -> Tensor:
    """Occupied cells and every cell within `cells` cells of one (26-neighbourhood).

    Args:
        occ: (R, R, R) bool.
        cells: the dilation's radius in cells (0: unchanged).

    Returns:
        (R, R, R) bool.
    """
    if cells <= 0:
        return occ.clone()
    k = 2 * int(cells) + 1
    return F.max_pool3d(occ[None, None].float(), k, stride=1, padding=int(cells))[0, 0] > 0.5


def flat_index(resolution: int, points: Tensor) -> tuple[Tensor, Tensor]:
    """The cell of each point, as a flat index into an (R, R, R) grid.

    Args:
        resolution: R.
        points: (..., 3) in the normalised frame.

    Returns:
        flat: (...,) int64, clamped into the grid; inside: (...,) bool, the point lies in
        the cube.
    """
    R = resolution
    q = torch.floor((points.float() + 1.0) * (R / 2.0))  # (..., 3) cell coordinates
    inside = (q.amin(dim=-1) >= 0) & (q.amax(dim=-1) < R)
    q = q.clamp(0, R - 1)
    if R ** 3 <= 2 ** 24:  # exact in float32
        flat = ((q[..., 0] * R + q[..., 1]) * R + q[..., 2]).long()
    else:
        q = q.long()
        flat = (q[..., 0] * R + q[..., 1]) * R + q[..., 2]
    return flat, inside


def lookup(occ: Tensor, points: Tensor) -> Tensor:
    """Whether points lie in occupied cells.

    Args:
        occ: (R, R, R) bool.
        points: (..., 3) in the normalised frame.

    Returns:
        (...,) bool; False outside the cube.
    """
    flat, inside = flat_index(occ.shape[0], points)
    return occ.reshape(-1)[flat] & inside


def occupied_span(t: Tensor, occupied: Tensor, near: Tensor, far: Tensor,
                  widen: Tensor | float) -> tuple[Tensor, Tensor, Tensor]:
    """From the first to the last occupied lookup along each ray, widened, inside [near, far].

    Args:
        t: (B, n) sorted positions of the lookups along each ray.
        occupied: (B, n) bool, the lookups that fell in occupied cells.
        near, far: (B, 1) the ray's interval.
        widen: (B, 1) or a number, added beyond the first and last occupied lookup.

    Returns:
        lo, hi: (B, 1) with ``near <= lo <= hi <= far`` (near, far where nothing is
        occupied); hits: (B,) bool, whether any lookup is occupied.
    """
    hits = occupied.any(dim=-1)  # (B,)
    first = torch.where(occupied, t, torch.full_like(t, math.inf)).amin(dim=-1, keepdim=True)
    last = torch.where(occupied, t, torch.full_like(t, -math.inf)).amax(dim=-1, keepdim=True)
    lo = torch.where(hits[:, None], torch.maximum(first - widen, near), near)
    hi = torch.where(hits[:, None], torch.minimum(last + widen, far), far)
    return lo, hi, hits
