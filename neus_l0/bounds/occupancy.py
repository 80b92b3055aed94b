"""An occupancy grid over the unit sphere's bounding box, kept from the SDF network.

Space far from the zero level set of the SDF gets no coarse samples: every `update_every`
iterations the SDF is evaluated at cell centres and a cell is *occupied* when

    |sdf(centre)| <= margin * half_diagonal + widths / s,

with ``half_diagonal = sqrt(3) * cell / 2`` and ``s`` the current logistic sharpness
(NeuS's ``inv_s``). Why this is safe: for a true signed distance function (1-Lipschitz) a
cell that the surface passes through has a surface point within ``half_diagonal`` of its
centre, so ``|sdf(centre)| <= half_diagonal``; ``margin >= 1`` is slack for a network SDF
that is only approximately 1-Lipschitz, and ``widths / s`` keeps the band where NeuS's
logistic density is not negligible (the weight it puts at ``|sdf| > widths / s`` is about
``exp(-widths)``). A cell stays occupied for ``hold`` further updates after it last passed
the test (a grace period while the surface moves).

The update is hierarchical: blocks of ``block`` x ``block`` x ``block`` cells are tested
first with the same bound at the block's size, and only the cells of blocks that pass are
evaluated. A cell that contains surface lies in a block that contains surface, so the
coarse test never discards it (same Lipschitz argument); the work drops from ``R^3`` to
``(R / block)^3`` plus the cells near the surface.

Along a ray (`grid_spans`), the grid is dilated by one cell and looked up at points spaced
at most one cell apart; the span from the first to the last occupied point, widened by one
spacing at each end, contains every occupied cell the ray crosses (a point of the ray
inside an occupied cell is within half a spacing, so within one cell in every axis, of a
lookup point, which therefore lies in the dilated set).

Frames: the normalised frame (the object inside the unit sphere); the grid covers
``[-1, 1]^3``; cell ``(i, j, k)`` is ``x in [-1 + i c, -1 + (i + 1) c)`` with
``c = 2 / R`` along x (likewise y, z). Outside the box nothing is occupied.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from neus_l0.bounds.grid import cell_centres, dilate, lookup, occupied_span
from neus_l0.config.schema import OccupancyConfig

#: Points per SDF call of the grid update.
UPDATE_CHUNK = 65536


def occupancy_threshold(cell: float, inv_s: Tensor, margin: float, widths: float) -> Tensor:
    """The |SDF| bound below which a cell of side `cell` may contain the surface.

    Args:
        cell: the cell side (normalised units).
        inv_s: (1,) or () the sharpness s (a tensor: no host synchronisation).
        margin: slack on the 1-Lipschitz bound (>= 1).
        widths: logistic widths 1 / s added to the bound.

    Returns:
        () threshold, ``margin * sqrt(3) * cell / 2 + widths / s``.
    """
    return margin * math.sqrt(3.0) * 0.5 * cell + widths / inv_s.reshape(())


def _eval_abs_sdf(sdf_fn: Callable[[Tensor], Tensor], pts: Tensor) -> Tensor:
    """|sdf| at (P, 3) points in chunks, without gradient -> (P,)."""
    out = [sdf_fn(pts[i:i + UPDATE_CHUNK]).reshape(-1).float().abs()
           for i in range(0, pts.shape[0], UPDATE_CHUNK)]
    return torch.cat(out) if out else pts.new_zeros(0)


def occupied_cells(sdf_fn: Callable[[Tensor], Tensor], resolution: int, inv_s: Tensor,
                   margin: float, widths: float, block: int = 4) -> Tensor:
    """Which cells may contain the surface of `sdf_fn` (hierarchical test, no gradient).

    Args:
        sdf_fn: maps (P, 3) points to (P, 1) or (P,) SDF values.
        resolution: R, cells per axis (a multiple of `block`).
        inv_s: (1,) sharpness s.
        margin, widths: see `occupancy_threshold`.
        block: cells per axis of the coarse blocks tested first (1: test every cell).

    Returns:
        (R, R, R) bool.
    """
    R = resolution
    with torch.no_grad():
        device = inv_s.device
        if block <= 1 or R % block:
            centres = cell_centres(R, device).reshape(-1, 3)
            thr = occupancy_threshold(2.0 / R, inv_s, margin, widths)
            return (_eval_abs_sdf(sdf_fn, centres) <= thr).reshape(R, R, R)
        Rb = R // block
        coarse = cell_centres(Rb, device).reshape(-1, 3)
        thr_b = occupancy_threshold(2.0 / Rb, inv_s, margin, widths)
        keep = _eval_abs_sdf(sdf_fn, coarse) <= thr_b  # (Rb^3,)
        # Cells of the kept blocks: (n_kept, block^3) flat indices into the fine grid.
        blocks = keep.nonzero().squeeze(1)  # a sync on CUDA, once per update
        bi, bj, bk = blocks // (Rb * Rb), (blocks // Rb) % Rb, blocks % Rb
        o = torch.arange(block, device=device)
        oi, oj, ok = torch.meshgrid(o, o, o, indexing="ij")
        ci = (bi[:, None] * block + oi.reshape(1, -1)).reshape(-1)
        cj = (bj[:, None] * block + oj.reshape(1, -1)).reshape(-1)
        ck = (bk[:, None] * block + ok.reshape(1, -1)).reshape(-1)
        c = 2.0 / R
        pts = -1.0 + c * (torch.stack([ci, cj, ck], dim=-1).float() + 0.5)
        thr = occupancy_threshold(c, inv_s, margin, widths)
        occ = torch.zeros(R * R * R, dtype=torch.bool, device=device)
        occ[(ci * R + cj) * R + ck] = _eval_abs_sdf(sdf_fn, pts) <= thr
        return occ.reshape(R, R, R)


def grid_spans(occ_dilated: Tensor, origins: Tensor, dirs: Tensor, near: Tensor,
              far: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The part of each ray's [near, far] that crosses occupied cells.

    Args:
        occ_dilated: (R, R, R) bool, the grid after `dilate`.
        origins, dirs: (B, 3) unit `dirs`; near, far: (B, 1).

    Returns:
        lo, hi: (B, 1) with ``near <= lo <= hi <= far`` (equal to near, far where the ray
        crosses nothing); active: (B,) bool, whether the ray crosses an occupied cell.
    """
    R = occ_dilated.shape[0]
    cell = 2.0 / R
    length = (far - near).clamp_min(0.0)  # (B, 1)
    # Spacing at most one cell: n points over the longest chord (2: the unit sphere).
    n = int(math.ceil(2.0 / cell)) + 2
    lin = torch.linspace(0.0, 1.0, n, device=near.device, dtype=near.dtype)
    t = near + length * lin  # (B, n)
    pts = origins[:, None, :] + dirs[:, None, :] * t[..., None]  # (B, n, 3)
    hit = lookup(occ_dilated, pts)  # (B, n)
    return occupied_span(t, hit, near, far, length / (n - 1))


class OccupancyGrid(torch.nn.Module):
    """The grid's state (buffers, so it moves with ``.to`` and checkpoints by state_dict).

    Attributes:
        occ: (R, R, R) bool, cells that may contain the surface.
        occ_dilated: (R, R, R) bool, `occ` and its neighbours (what rays look up).
        counter: (R, R, R) uint8, updates each cell stays occupied.
    """

    def __init__(self, cfg: OccupancyConfig, device: torch.device | str = "cpu") -> None:
        super().__init__()
        self.cfg = cfg
        R = cfg.resolution
        # Everything occupied until the first update (which replaces it entirely).
        self.register_buffer("counter", torch.ones((R, R, R), dtype=torch.uint8,
                                                   device=device))
        self.register_buffer("occ", torch.ones((R, R, R), dtype=torch.bool, device=device))
        self.register_buffer("occ_dilated", self.occ.clone())

    @property
    def resolution(self) -> int:
        return self.cfg.resolution

    def update(self, sdf_fn: Callable[[Tensor], Tensor], inv_s: Tensor) -> None:
        """Re-test every cell against the current SDF and sharpness (no gradient)."""
        c = self.cfg
        now = occupied_cells(sdf_fn, c.resolution, inv_s.detach(), c.margin, c.widths,
                             c.block)
        fresh = torch.full_like(self.counter, c.hold + 1)
        self.counter.copy_(torch.where(now, fresh, (self.counter.int() - 1).clamp_min(0)
                                       .to(torch.uint8)))
        self.occ.copy_(self.counter > 0)
        self.occ_dilated.copy_(dilate(self.occ))

    def ray_bounds(self, origins: Tensor, dirs: Tensor, near: Tensor,
                   far: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """`grid_spans` on this grid (the `neus_l0.bounds.spans.RayBounds` protocol)."""
        return grid_spans(self.occ_dilated, origins, dirs, near, far)

    def contains(self, points: Tensor) -> Tensor:
        """(..., 3) normalised points -> (...) bool: in a cell of the dilated grid (what
        rays look up); False outside ``[-1, 1]^3``."""
        return lookup(self.occ_dilated, points)

    def fraction_occupied(self) -> Tensor:
        """() fraction of occupied cells (a tensor: read it when logging)."""
        return self.occ.float().mean()
