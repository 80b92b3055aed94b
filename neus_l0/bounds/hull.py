"""The visual hull: where the object can be, carved once from the masks at scene load.

Grid. ``R^3`` cells over the cube ``[-1, 1]^3`` of the normalised frame (the object inside
the unit sphere); cell ``(i, j, k)`` is ``x in [-1 + i h, -1 + (i + 1) h)`` with
``h = 2 / R`` along x (likewise y, z). Only cells whose bounding ball meets the unit sphere
are candidates; the rest of the cube is empty.

Carving rule (conservative, exact). A cell is removed when at least one *carving view*
proves that the cell's whole footprint, widened by `margin_px`, is background:

- The cell lies inside the ball of radius ``r = sqrt(3) h / 2`` around its centre ``c``.
  With ``c`` at camera depth ``z > r`` and normalised image point ``p = (X / Z, Y / Z)``,
  every point of that ball projects within ``rho = ||A||_2 r sqrt(1 + |p|^2) / (z - r)``
  pixels of the projection ``u`` of ``c`` (``A`` the upper-left 2x2 block of K; for
  ``c + d``, ``|d| <= r``, the offset is ``A (Z d_xy - (X, Y) d_z) / (Z (Z + d_z))`` and
  ``[I | -p]`` has largest singular value ``sqrt(1 + |p|^2)``).
- A view carves the cell only when (a) ``z > r`` (the whole ball in front of the camera),
  (b) the disc of radius ``rho + margin_px`` around ``u`` lies inside the image's pixel
  area ``[-0.5, W - 0.5] x [-0.5, H - 0.5]`` (anything else is *unknown* to that view), and
  (c) no foreground pixel centre (mask > 0: any coverage counts) lies within
  ``rho + margin_px`` of ``u``. (c) is read from the Euclidean distance transform ``D`` of
  the background at the pixel ``q`` nearest to ``u``: ``D(q) - sqrt(2) / 2 > rho + margin``
  implies it, since ``|u - q| <= sqrt(2) / 2``. ``D`` is stored rounded down.
- Carving views: all views when the scene has masks, except those whose mask is empty
  (see below) and those excluded as suspicious. Without masks nothing is carved.

After carving, the kept cells are dilated by one cell (26-neighbourhood); `VisualHull`
holds that dilated grid (and the undilated one as ``carved``). Everything in it follows
from the masks and `margin_px`: the object is inside the hull wherever every mask covers
the object's projection up to `margin_px` pixels (mask error plus calibration error).

Suspicious views (`check_hull`, and the exclusion in `carve_hull`):

- *empty mask*: the view carves nothing (warning naming it). An empty mask is true data when
  the object has left the frame; then the other views carve that space anyway. A wrong
  empty mask would remove everything the view sees, so it is never trusted.
- *all foreground* (>= `FULL_MASK` of the pixels): warning only; such a mask carves
  nothing inside its image, so it cannot cut the object.
- *cuts*: the fraction of the other views' foreground rays (pixels with mask > 0.5) that
  miss the hull but cross a cell that this view alone carved, i.e. that would meet the hull
  without this view. It is 0 for correct masks (the object is inside every view's cone, so
  every foreground ray meets the hull); a mask of the wrong view (swapped masks) cuts away
  object that the others see. Views above `SUSPICIOUS_CUTS` are excluded from the carving
  (the hull only grows), one at a time, worst first, re-carving each time, and named.
- *explained*: the fraction of a view's foreground rays that meet the final hull: 1 for a
  hull that contains the object; a view below `EXPLAINED_MIN` gets a warning.

Cost: coarse to fine (cells of the R/4 grid first; see `_carve`), one Euclidean distance
transform per mask (OpenCV), and cells carved by two views are dropped from further tests.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from neus_l0.atomic import atomic_torch_save
from neus_l0.bounds.grid import (
    cell_axis,
    cell_centres,
    dilate,
    flat_index,
    lookup,
    occupied_span,
)
from neus_l0.errors import NeusL0Error

DEFAULT_RESOLUTION = 128
"""Cells per axis of the default hull grid."""

DEFAULT_MARGIN_PX = 2.0
"""Default dilation margin of the masks, in pixels (mask and calibration error)."""

FULL_MASK = 0.99
"""A mask with at least this foreground fraction is reported as all foreground."""

SUSPICIOUS_CUTS = 0.002
"""A view whose mask alone makes more than this fraction of the other views' foreground
rays miss the hull is excluded from the carving."""

EXPLAINED_MIN = 0.98
"""A view whose foreground rays meet the hull less often than this gets a warning."""

MAX_EXCLUDED = 4
"""At most this many suspicious views are excluded (each exclusion re-carves)."""

_VERSION = 1


@dataclasses.dataclass
class HullReport:
    """Per-view diagnostics of a carving.

    Attributes:
        coverage: per view, the fraction of mask pixels that are foreground.
        status: per view, "ok", "empty" (carves nothing), "full" (all foreground),
            "excluded" (suspicious, left out of the carving) or "no masks".
        cuts: per view, the fraction of the other views' foreground rays that miss the
            hull only because of this view's mask (0 for views that do not carve).
        explained: per view, the fraction of its foreground pixels whose rays meet the hull
            (1.0 where there is no foreground).
        fraction_kept: fraction of the unit sphere the (dilated) hull keeps.
        seconds: wall time of the carving and the checks.
        warnings: one line per problem, naming the view.
    """

    coverage: list[float]
    status: list[str]
    cuts: list[float]
    explained: list[float]
    fraction_kept: float
    seconds: float = 0.0
    warnings: list[str] = dataclasses.field(default_factory=list)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


class VisualHull:
    """A carved occupancy grid over ``[-1, 1]^3`` (already dilated by one cell).

    Attributes:
        occupancy: (R, R, R) bool, True where the object may be.
        margin_px: the mask margin it was carved with.
        report: the `HullReport` of the carving (None when loaded from an old file).
        carved: (R, R, R) bool, the cells the carving kept before the dilation (None when
            loaded or derived from another hull).
    """

    def __init__(self, occupancy: Tensor, margin_px: float = DEFAULT_MARGIN_PX,
                 report: HullReport | None = None, carved: Tensor | None = None) -> None:
        if occupancy.dim() != 3 or len(set(occupancy.shape)) != 1:
            raise NeusL0Error(f"visual hull: occupancy must be (R, R, R), got "
                              f"{tuple(occupancy.shape)}")
        self.occupancy = occupancy.bool()
        self.margin_px = float(margin_px)
        self.report = report
        self.carved = carved
        self._integral: Tensor | None = None

    # --- basics -------------------------------------------------------------------------
    @property
    def resolution(self) -> int:
        return int(self.occupancy.shape[0])

    @property
    def cell(self) -> float:
        """Cell edge h in normalised units."""
        return 2.0 / self.resolution

    @property
    def device(self) -> torch.device:
        return self.occupancy.device

    def to(self, device: str | torch.device) -> VisualHull:
        """A copy on `device`."""
        return VisualHull(self.occupancy.to(device), self.margin_px, self.report)

    def state_dict(self) -> dict:
        """Everything needed to rebuild the hull (tensors on the CPU, packed bits)."""
        occ = self.occupancy.detach().cpu().numpy().reshape(-1)
        return {"version": _VERSION, "resolution": self.resolution,
                "margin_px": self.margin_px,
                "bits": torch.from_numpy(np.packbits(occ)),
                "report": self.report.to_dict() if self.report is not None else None}

    @classmethod
    def from_state_dict(cls, state: dict, device: str | torch.device = "cpu") -> VisualHull:
        """Inverse of `state_dict`."""
        try:
            R = int(state["resolution"])
            bits = np.asarray(state["bits"].cpu().numpy() if torch.is_tensor(state["bits"])
                              else state["bits"], dtype=np.uint8)
            occ = np.unpackbits(bits, count=R ** 3).astype(bool).reshape(R, R, R)
            rep = state.get("report")
            report = HullReport(**rep) if rep is not None else None
            margin = float(state["margin_px"])
        except (KeyError, TypeError, ValueError) as exc:
            raise NeusL0Error(f"visual hull: malformed state ({exc})") from None
        return cls(torch.from_numpy(occ).to(device), margin, report)

    def save(self, path: str | Path) -> Path:
        """Write the hull atomically (torch.save of `state_dict`)."""
        return atomic_torch_save(path, self.state_dict(), within=Path(path).parent)

    @classmethod
    def load(cls, path: str | Path, device: str | torch.device = "cpu") -> VisualHull:
        """Read a hull written by `save`.

        Raises:
            NeusL0Error: the file is missing or unreadable.
        """
        path = Path(path)
        if not path.is_file():
            raise NeusL0Error(f"{path}: visual hull file not found")
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - a damaged file is the user's problem
            torch_talk = ("Weights only load failed", "Please file an issue", "Check the doc")
            why = next((ln.strip() for ln in str(exc).splitlines()
                        if ln.strip() and not ln.strip().startswith(torch_talk)),
                       type(exc).__name__)[:160]
            raise NeusL0Error(f"{path}: unreadable visual hull ({why})") from None
        return cls.from_state_dict(state, device)

    # --- queries ------------------------------------------------------------------------
    def contains(self, points: Tensor) -> Tensor:
        """Whether points (..., 3) in the normalised frame lie in the hull: (...,) bool."""
        return lookup(self.occupancy, points.to(self.device))

    def fraction_of_sphere(self) -> float:
        """The fraction of the unit sphere's cells (centre inside the sphere) that are kept."""
        R = self.resolution
        c = cell_axis(R, self.device)
        r2 = c[:, None, None] ** 2 + c[None, :, None] ** 2 + c[None, None, :] ** 2
        inside = r2 <= 1.0
        return float((self.occupancy & inside).sum()) / float(inside.sum())

    def ray_bounds(self, origins: Tensor, dirs: Tensor, near: Tensor,
                   far: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """First entry and last exit of each ray in the hull, inside [near, far].

        Fixed shapes throughout (no boolean indexing, no host sync): safe under
        ``torch.compile`` and CUDA graphs.

        Method: [near, far] is clipped to the unit sphere (where the object is, by the
        normalised frame's definition); M = ceil(R / 2) + 2 points spaced evenly on that
        (so at most 2h apart in space, for any direction length) are looked up; the bounds
        are the first and last occupied points, widened by one cell. Why this never cuts
        the object: a point x of the ray inside the unit sphere and in a cell kept by the
        carving has the ball of radius h around it inside the dilated grid, so the ray's
        stretch of length 2h centred at x (or its part inside the clipped interval, which
        then holds an end point) holds an occupied lookup point, within h of x.

        Args:
            origins: (B, 3) ray origins; dirs: (B, 3) directions (any length > 0).
            near, far: (B, 1) the ray's interval (in units of `dirs`).

        Returns:
            lo, hi: (B, 1) with ``near <= lo <= hi <= far``; near, far where the ray misses.
            hits: (B,) bool, whether the ray meets the hull inside [near, far].
        """
        t, pts, ok = _ray_points(origins, dirs, near, far, self.resolution)
        occ = self.contains(pts) & ok  # (B, n)
        widen = self.cell / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # (B, 1)
        return occupied_span(t, occ, near, far, widen)

    # --- boxes (for meshing) ------------------------------------------------------------
    def dilated(self, cells: int) -> VisualHull:
        """This hull dilated by `cells` more cells (26-neighbourhood); report not kept.

        The cost does not grow with `cells` (`dilate_box`)."""
        return VisualHull(dilate_box(self.occupancy, cells), self.margin_px, None)

    def for_grid(self, step: float) -> VisualHull:
        """The region a grid of spacing `step` may be restricted to without changing its
        marching cubes inside the carved hull.

        The carved (undilated) hull dilated by n = ceil(sqrt(3) step / h) cells holds every
        point within n h >= sqrt(3) step of it, so every corner of every grid cube that
        meets the carved hull: marching cubes there sees the SDF's own values. This hull is
        already dilated by one cell, so it is dilated by n - 1 more. A coarse grid (large n)
        costs no more than a fine one (`dilate_box`).
        """
        n = max(1, math.ceil(math.sqrt(3.0) * step / self.cell - 1e-9))
        out = self.dilated(n - 1)
        out.report = self.report
        return out

    def cells_in_boxes(self, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
        """Occupied and total cells that meet each closed box [lo, hi] (clipped to the cube).

        Args:
            lo, hi: (K, 3) box corners in the normalised frame.

        Returns:
            occupied, total: (K,) int64.
        """
        R = self.resolution
        if self._integral is None:
            s = self.occupancy.long()
            s = s.cumsum(0).cumsum(1).cumsum(2)
            self._integral = F.pad(s, (1, 0, 1, 0, 1, 0))  # (R+1, R+1, R+1)
        S = self._integral
        i0 = torch.floor((lo.to(self.device) + 1.0) / self.cell).long().clamp(0, R)
        i1 = (torch.floor((hi.to(self.device) + 1.0) / self.cell).long() + 1).clamp(0, R)
        i1 = torch.maximum(i1, i0)
        x0, y0, z0 = i0.unbind(-1)
        x1, y1, z1 = i1.unbind(-1)
        occ = (S[x1, y1, z1] - S[x0, y1, z1] - S[x1, y0, z1] - S[x1, y1, z0]
               + S[x0, y0, z1] + S[x0, y1, z0] + S[x1, y0, z0] - S[x0, y0, z0])
        total = (x1 - x0) * (y1 - y0) * (z1 - z0)
        return occ, total

    # --- export -------------------------------------------------------------------------
    def to_mesh(self, scale_mat: np.ndarray | None = None):
        """The hull's surface as a watertight `trimesh.Trimesh` (world units with `scale_mat`).

        Marching cubes (level 0.5) of the occupancy zero-padded by one cell, on the cell
        centres; ``v_world = scale_mat[:3, :3] @ v + scale_mat[:3, 3]``.

        Raises:
            NeusL0Error: the hull is empty.
        """
        import trimesh
        from skimage import measure

        occ = self.occupancy.detach().cpu().numpy()
        if not occ.any():
            raise NeusL0Error("visual hull: empty, nothing to mesh")
        vol = np.pad(occ.astype(np.float32), 1)
        h = self.cell
        # occupancy grows inward ("ascent"), so the faces are wound with outward normals
        v, f, _, _ = measure.marching_cubes(vol, level=0.5, spacing=(h, h, h),
                                            gradient_direction="ascent")
        v = v.astype(np.float64) - 1.0 - 0.5 * h  # padded index j -> -1 + (j - 0.5) h
        if scale_mat is not None:
            S = np.asarray(scale_mat, dtype=np.float64)
            v = v @ S[:3, :3].T + S[:3, 3]
        mesh = trimesh.Trimesh(v, f.astype(np.int64), process=True)
        return mesh


def dilate_box(occ: Tensor, cells: int) -> Tensor:
    """`neus_l0.bounds.grid.dilate` by any number of cells, in time independent of it.

    The 26-neighbourhood dilation by n cells is the maximum over a cube of side 2n + 1,
    which is three 1-D windows, one per axis; each window is a difference of prefix sums, so
    the work is three passes over the R^3 grid whatever n is (a max-pool's kernel of
    (2n + 1)^3 made `mesh --resolution 8` dilate for minutes). n is clamped to R - 1, beyond
    which a window spans its whole axis anyway.

    Args:
        occ: (R, R, R) bool.
        cells: the dilation's radius in cells (0 or less: unchanged).

    Returns:
        (R, R, R) bool.
    """
    occ = occ.bool()
    R = int(occ.shape[0])
    n = min(int(cells), R - 1)
    if n <= 0:
        return occ.clone()
    i = torch.arange(R, device=occ.device)
    hi, lo = (i + n + 1).clamp_max(R), (i - n).clamp_min(0)
    out = occ
    for dim in range(3):
        pre = F.pad(out.to(torch.int32).cumsum(dim), [0, 0] * (2 - dim) + [1, 0])  # R + 1
        out = (pre.index_select(dim, hi) - pre.index_select(dim, lo)) > 0
    return out


def _ray_points(origins: Tensor, dirs: Tensor, near: Tensor, far: Tensor,
                R: int) -> tuple[Tensor, Tensor, Tensor]:
    """Lookup points of `VisualHull.ray_bounds`: [near, far] clipped to the unit sphere,
    ``ceil(R / 2) + 2`` points evenly spaced on it (so at most ``2 h`` apart in space, as the
    chord is at most 2 long).

    Returns:
        t: (B, n); pts: (B, n, 3); ok: (B, 1) bool, the clipped interval is not empty.
    """
    dd = (dirs * dirs).sum(-1, keepdim=True).clamp_min(1e-24)  # (B, 1)
    b = (origins * dirs).sum(-1, keepdim=True) / dd
    c = ((origins * origins).sum(-1, keepdim=True) - 1.0) / dd
    disc = b * b - c
    root = disc.clamp_min(0.0).sqrt()
    lo = torch.maximum(near, -b - root)
    hi = torch.minimum(far, -b + root)
    n = int(math.ceil(R / 2.0)) + 2
    lin = torch.linspace(0.0, 1.0, n, device=near.device, dtype=near.dtype)
    t = lo + (hi - lo).clamp_min(0.0) * lin  # (B, n)
    pts = origins[:, None, :] + dirs[:, None, :] * t[..., None]  # (B, n, 3)
    return t, pts, (disc >= 0) & (hi >= lo)


def background_distance(mask: Tensor) -> Tensor:
    """(H, W) int16: distance from each pixel centre to the nearest foreground pixel centre.

    Rounded down to whole pixels and capped at 32767 (both conservative); foreground is
    mask > 0.
    """
    import cv2

    bg = (mask <= 0).to(torch.uint8).cpu().numpy()
    if bg.all():
        return torch.full(bg.shape, 32767, dtype=torch.int16)
    d = cv2.distanceTransform(bg, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    np.minimum(d, 32767.0, out=d)
    return torch.from_numpy(d.astype(np.int16))  # truncation: floor of a distance >= 0


def _camera_terms(intrinsics: Tensor, c2w: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """World-to-camera rotation (V, 3, 3), translation (V, 3), A = K[:2, :2] (V, 2, 2),
    and ||A||_2 (V,), in float64."""
    K = intrinsics.double()
    T = c2w.double()
    Rwc = T[:, :3, :3].transpose(1, 2)
    t = -torch.einsum("vij,vj->vi", Rwc, T[:, :3, 3])
    A = K[:, :2, :2]
    norm = torch.linalg.matrix_norm(A, ord=2)
    return Rwc, t, A, norm


def _carve_counts(centres: Tensor, radius: float, dists: list[Tensor], intrinsics: Tensor,
                  c2w: Tensor, views: list[int], margin_px: float,
                  prior: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """How many of `views` carve each cell, and which one when it is one.

    Args:
        centres: (N, 3) cell centres; radius: their bounding-ball radius.
        dists: per view, the (H, W) `background_distance` of its mask.
        intrinsics (V, 3, 3); c2w (V, 4, 4); views: the carving views.
        prior: (count (N,), carver (N,)) already proved (by an enclosing coarse cell):
            those views are not counted twice.

    Returns:
        count: (N,) int32, exact up to 2 (cells carved twice are not tested further);
        carver: (N,) int32, the carving view + 1 where count == 1.
    """
    dev = centres.device
    Rwc, tr, A, Anorm = (x.to(dev).float() for x in _camera_terms(intrinsics, c2w))
    K = intrinsics.to(dev).float()
    N = len(centres)
    half = math.sqrt(2.0) / 2.0
    # the cells carved by at most one view so far, and their tallies
    n_act = torch.zeros(N, dtype=torch.int32, device=dev) if prior is None else prior[0].int()
    who = torch.zeros_like(n_act) if prior is None else prior[1].int()
    sel = n_act <= 1
    act, pts, n_act, who = torch.arange(N, device=dev)[sel], centres[sel], n_act[sel], who[sel]
    for i, v in enumerate(views):
        H, W = dists[v].shape
        dist = dists[v].reshape(-1)  # (H*W,)
        X = pts @ Rwc[v].T + tr[v]  # (M, 3)
        z = X[:, 2]
        front = z > radius
        zs = torch.where(front, z, torch.ones_like(z))
        px, py = X[:, 0] / zs, X[:, 1] / zs  # (M,)
        u = A[v, 0, 0] * px + A[v, 0, 1] * py + K[v, 0, 2]
        w = A[v, 1, 0] * px + A[v, 1, 1] * py + K[v, 1, 2]
        rho = Anorm[v] * radius * torch.sqrt(1.0 + px * px + py * py)
        reach = rho / torch.where(front, z - radius, torch.ones_like(z)) + margin_px  # (M,)
        seen = (front & (u - reach >= -0.5) & (u + reach <= W - 0.5)
                & (w - reach >= -0.5) & (w + reach <= H - 0.5) & (who != v + 1))
        qx = torch.round(u).clamp(0, W - 1).long()
        qy = torch.round(w).clamp(0, H - 1).long()
        carve = (seen & (dist[qy * W + qx] - half > reach)).int()  # (M,)
        n_act += carve
        who += carve * (v + 1)
        if i % 4 == 3:  # a cell carved twice is out, and no single view's doing: drop it
            sel = n_act <= 1
            act, pts, n_act, who = act[sel], pts[sel], n_act[sel], who[sel]
    count = torch.full((N,), 2, dtype=torch.int32, device=dev)
    carver = torch.zeros_like(count)
    count[act] = n_act.clamp_max(2)
    carver[act] = who
    return count, carver


def _candidates(R: int, device: torch.device | str) -> tuple[Tensor, Tensor]:
    """Flat indices (N,) and centres (N, 3) of the cells whose ball meets the unit sphere."""
    g = cell_centres(R, device).reshape(-1, 3)
    radius = math.sqrt(3.0) / R
    idx = torch.nonzero(g.norm(dim=-1) <= 1.0 + radius).squeeze(1)
    return idx, g[idx]


def _carve(R: int, dists: list[Tensor], intrinsics: Tensor, c2w: Tensor, views: list[int],
           margin_px: float, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """Carve the candidate cells of an R^3 grid, coarse to fine.

    With R divisible by 4 and >= 32, cells of the R/4 grid are carved first: a coarse cell
    carved by view v proves every fine cell inside it background for v (a fine cell lies in
    its coarse cell, and the coarse test covers the coarse cell's whole footprint), so fine
    cells inside coarse cells carved twice are out without a test, and the others start
    from their coarse cell's tally.

    Returns:
        idx: (N,) flat indices of the candidate cells; count, carver: (N,) as
        `_carve_counts` gives them.
    """
    idx, centres = _candidates(R, device)
    if R % 4 or R < 32:
        return (idx, *_carve_counts(centres, math.sqrt(3.0) / R, dists, intrinsics, c2w,
                                    views, margin_px))
    Rc = R // 4
    cidx, ccent = _candidates(Rc, device)
    ccount, ccarver = _carve_counts(ccent, math.sqrt(3.0) / Rc, dists, intrinsics, c2w,
                                    views, margin_px)
    cfull_count = torch.full((Rc ** 3,), 2, dtype=torch.int32, device=device)
    cfull_carver = torch.zeros_like(cfull_count)
    cfull_count[cidx] = ccount
    cfull_carver[cidx] = ccarver
    i, j, k = idx // (R * R), (idx // R) % R, idx % R
    parent = ((i // 4) * Rc + j // 4) * Rc + k // 4  # (N,)
    prior = (cfull_count[parent], cfull_carver[parent])
    return (idx, *_carve_counts(centres, math.sqrt(3.0) / R, dists, intrinsics, c2w, views,
                                margin_px, prior))


def _view_name(v: int, names: list[str] | None) -> str:
    return f"view {v} ({names[v]})" if names is not None and v < len(names) else f"view {v}"


def _foreground_rays(masks: Tensor, intrinsics: Tensor, c2w: Tensor,
                     samples: int) -> tuple[Tensor, Tensor, Tensor]:
    """Rays through up to `samples` evenly strided foreground pixels (mask > 0.5) per view.

    Returns:
        origins, dirs: (B, 3); view: (B,) int64.
    """
    from neus_l0.data.rays import pixel_rays

    V, H, W = masks.shape
    os_, ds, vs = [], [], []
    for v in range(V):
        fg = torch.nonzero(masks[v].reshape(-1) > 0.5).squeeze(1)
        if len(fg) == 0:
            continue
        pick = fg[torch.linspace(0, len(fg) - 1, min(samples, len(fg)),
                                 device=fg.device).long()]
        xy = torch.stack([pick % W, pick // W], dim=-1).float()
        o, d = pixel_rays(intrinsics[v].float(), c2w[v].float(), xy)
        os_.append(o)
        ds.append(d)
        vs.append(torch.full((len(pick),), v, dtype=torch.long, device=o.device))
    if not os_:
        z = torch.zeros(0, 3, device=masks.device)
        return z, z, torch.zeros(0, dtype=torch.long, device=masks.device)
    return torch.cat(os_), torch.cat(ds), torch.cat(vs)


def _audit(hull: VisualHull, labels: Tensor | None, origins: Tensor, dirs: Tensor,
           view: Tensor, n_views: int) -> tuple[list[float], list[float]]:
    """Foreground rays against the hull.

    Args:
        hull: the (dilated) hull.
        labels: (R^3,) int32 per undilated cell: 0 kept, v + 1 carved by view v alone, -1
            otherwise; None: no blame.
        origins, dirs: (B, 3) foreground rays; view: (B,) their views.

    Returns:
        explained: per view, the fraction of its foreground rays that meet the hull (1.0
        without rays); cuts: per view w, the fraction of the other views' foreground rays
        that miss the hull but cross a cell that w alone carved (so would meet the hull
        without w).
    """
    V = n_views
    dev = hull.device
    origins, dirs, view = origins.to(dev), dirs.to(dev), view.to(dev)
    B = len(origins)

    def cells(o: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
        """The cells of the lookups along whole rays: flat (b, n), inside (b, n)."""
        zeros = torch.zeros(len(o), 1, device=dev)
        _, pts, ok = _ray_points(o, d, zeros, zeros + 1e6, hull.resolution)
        flat, inside = flat_index(hull.resolution, pts)
        return flat, inside & ok

    occ = hull.occupancy.reshape(-1)
    hit = torch.zeros(B, dtype=torch.bool, device=dev)
    for s in range(0, B, 8192):
        flat, inside = cells(origins[s:s + 8192], dirs[s:s + 8192])
        hit[s:s + 8192] = (occ[flat] & inside).any(dim=-1)
    through = torch.zeros(B, V, dtype=torch.bool, device=dev)  # missing rays only
    missed = torch.nonzero(~hit).squeeze(1)
    if labels is not None:
        for s in range(0, len(missed), 8192):
            m = missed[s:s + 8192]
            flat, inside = cells(origins[m], dirs[m])
            lab = torch.where(inside, labels[flat], -1)  # (b, n)
            onehot = torch.zeros(len(m), V + 2, dtype=torch.bool, device=dev)
            onehot.scatter_(1, (lab + 1).long(), True)
            through[m] = onehot[:, 2:]
    n_rays = torch.bincount(view, minlength=V).float()  # (V,)
    n_hit = torch.bincount(view, weights=hit.float(), minlength=V)
    explained = torch.where(n_rays > 0, n_hit / n_rays.clamp_min(1), 1.0)
    miss = (through & ~hit[:, None]).float()  # (B, V)
    own = torch.zeros(V, device=dev)
    if B:
        own = torch.zeros(V, V, device=dev).index_add_(0, view, miss).diagonal()
    cut = (miss.sum(0) - own) / (B - n_rays).clamp_min(1)  # other views' rays only
    return explained.cpu().tolist(), cut.cpu().tolist()


def carve_hull(masks: Tensor, intrinsics: Tensor, c2w: Tensor,
               resolution: int = DEFAULT_RESOLUTION, margin_px: float = DEFAULT_MARGIN_PX,
               has_masks: bool = True, exclude_suspicious: bool = True,
               names: list[str] | None = None, samples: int = 1024) -> VisualHull:
    """Carve the visual hull of a scene (see the module docstring for the rule).

    Args:
        masks: (V, H, W) float in [0, 1], 1 = foreground (soft masks: any coverage > 0
            counts as foreground).
        intrinsics: (V, 3, 3) pixel units; c2w: (V, 4, 4) in the normalised frame.
        resolution: R, cells per axis over [-1, 1]^3.
        margin_px: mask dilation in pixels (>= 0).
        has_masks: False: nothing is carved (the hull is every cell meeting the sphere).
        exclude_suspicious: leave out, worst first, views whose mask cuts more than
            `SUSPICIOUS_CUTS` of the other views' foreground rays (re-carving each time).
        names: image names, used in the warnings.
        samples: foreground pixels per view in the audit (`HullReport.explained`, ``cuts``).

    Returns:
        The `VisualHull` (on the masks' device), with its `HullReport`.
    """
    t_start = time.perf_counter()
    if not margin_px >= 0 or not math.isfinite(margin_px):
        raise NeusL0Error(f"visual hull: margin must be >= 0 pixels, got {margin_px}")
    R = int(resolution)
    if R < 4:
        raise NeusL0Error(f"visual hull: resolution must be >= 4, got {resolution}")
    dev = masks.device
    V = int(masks.shape[0])
    cover = (masks > 0).float().mean(dim=(1, 2)).cpu().tolist() if V else []
    status = ["ok" if c < FULL_MASK else "full" for c in cover]
    status = [("empty" if c == 0.0 else st) if has_masks else "no masks"
              for c, st in zip(cover, status, strict=True)]
    carving = [v for v in range(V) if status[v] in ("ok", "full")]
    dists = [background_distance(masks[v]).to(dev) if v in carving else None
             for v in range(V)]
    rays = _foreground_rays(masks, intrinsics, c2w, samples) if carving else None
    cuts = [0.0] * V
    while True:
        idx, count, carver = _carve(R, dists, intrinsics, c2w, carving, margin_px, dev)
        occ = torch.zeros(R ** 3, dtype=torch.bool, device=dev)
        occ[idx] = count == 0
        hull = VisualHull(dilate(occ.reshape(R, R, R)), margin_px,
                          carved=occ.reshape(R, R, R))
        if rays is None:
            explained = [1.0] * V
            break
        labels = torch.full((R ** 3,), -1, dtype=torch.int32, device=dev)
        labels[idx] = torch.where(count == 0, 0, torch.where(count == 1, carver, -1))
        explained, new_cuts = _audit(hull, labels, *rays, V)
        cuts = [new_cuts[v] if v in carving else cuts[v] for v in range(V)]
        worst = max(carving, key=lambda v: cuts[v]) if carving else None
        if (worst is None or not exclude_suspicious or cuts[worst] <= SUSPICIOUS_CUTS
                or status.count("excluded") >= MAX_EXCLUDED):
            break
        status[worst] = "excluded"
        carving.remove(worst)
    hull.report = _report(hull, status, cover, cuts, explained, names)
    hull.report.seconds = time.perf_counter() - t_start
    return hull


def _report(hull: VisualHull, status: list[str], cover: list[float], cuts: list[float],
            explained: list[float], names: list[str] | None) -> HullReport:
    """The `HullReport` with one warning line per problem."""
    warns = []
    for v in range(len(status)):
        who = _view_name(v, names)
        if status[v] == "empty":
            warns.append(f"{who}: mask is empty; it carves nothing (fine if the object is "
                         f"out of frame there)")
        elif status[v] == "full":
            warns.append(f"{who}: mask is all foreground ({cover[v]:.1%}); it carves nothing "
                         f"inside its image")
        elif status[v] == "excluded":
            warns.append(f"{who}: mask cuts away {cuts[v]:.1%} of the other views' foreground "
                         f"(wrong view's mask?); left out of the visual hull")
        elif cuts[v] > SUSPICIOUS_CUTS:
            warns.append(f"{who}: mask cuts away {cuts[v]:.1%} of the other views' foreground "
                         f"(wrong view's mask?)")
        if explained[v] < EXPLAINED_MIN and status[v] not in ("full", "excluded"):
            warns.append(f"{who}: only {explained[v]:.1%} of its mask's foreground rays meet "
                         f"the visual hull: masks disagree, the hull may cut the object")
    return HullReport(coverage=[float(c) for c in cover], status=list(status),
                      cuts=[float(c) for c in cuts], explained=[float(e) for e in explained],
                      fraction_kept=hull.fraction_of_sphere(), warnings=warns)


def check_hull(hull: VisualHull, masks: Tensor, intrinsics: Tensor, c2w: Tensor,
               names: list[str] | None = None, samples: int = 1024) -> HullReport:
    """Audit a hull (e.g. one loaded from a run) against masks: which views' foreground
    rays miss it. ``cuts`` is unknown here (0); `carve_hull` computes it while carving.

    Args:
        hull: the hull; masks (V, H, W), intrinsics (V, 3, 3), c2w (V, 4, 4): the scene's.
        names: image names for the warnings; samples: foreground pixels tested per view.

    Returns:
        The `HullReport` (status "ok" or "empty"/"full" from the masks alone).
    """
    V = int(masks.shape[0])
    cover = (masks > 0).float().mean(dim=(1, 2)).cpu().tolist()
    status = ["empty" if c == 0.0 else "full" if c >= FULL_MASK else "ok" for c in cover]
    explained, _ = _audit(hull, None, *_foreground_rays(masks, intrinsics, c2w, samples), V)
    return _report(hull, status, cover, [0.0] * V, explained, names)


def hull_from_scene(scene, resolution: int = DEFAULT_RESOLUTION,
                    margin_px: float = DEFAULT_MARGIN_PX) -> VisualHull:
    """`carve_hull` on a `neus_l0.data.scene.Scene` (on the scene's device)."""
    return carve_hull(scene.masks, scene.intrinsics, scene.c2w, resolution, margin_px,
                      has_masks=scene.has_masks, names=list(scene.image_names))


def hull_for_run(scene, path: str | Path, resolution: int = DEFAULT_RESOLUTION,
                 margin_px: float = DEFAULT_MARGIN_PX, reuse: bool = True,
                 check: Callable[[VisualHull], None] | None = None) -> VisualHull:
    """The run's hull: loaded from `path` when it exists (resume and `mesh` then use the
    hull the run started with), else carved from `scene` and saved there atomically.

    Args:
        scene: the `Scene` (the hull goes to its device).
        path: the run's hull file (e.g. ``RUN/hull.pt``).
        resolution, margin_px: used only when carving.
        reuse: load an existing `path` (False: carve anew and replace it; a run that starts
            afresh must not take the hull of an earlier start, maybe on another scene).
        check: called with the hull before it is used; it raises to refuse it. A carved
            hull is saved only once it passes, so a refused scene leaves no hull.pt behind.

    Returns:
        The `VisualHull`; its ``report.warnings`` are the lines to show the user.
    """
    path = Path(path)
    if reuse and path.is_file():
        hull = VisualHull.load(path, scene.device)
        if check is not None:
            check(hull)
        return hull
    hull = hull_from_scene(scene, resolution, margin_px)
    if check is not None:
        check(hull)
    hull.save(path)
    return hull


def load_run_hull(run_dir: str | Path, device: str | torch.device = "cpu") -> VisualHull | None:
    """The hull a training run carved (``RUN/hull.pt``), or None when it has none."""
    path = Path(run_dir) / "hull.pt"
    return VisualHull.load(path, device) if path.is_file() else None
