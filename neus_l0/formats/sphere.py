"""The object sphere (NeuS's ``scale_mat``) of a scene whose format does not give one.

``x_world = radius * x_norm + center``: the sphere must hold the object, and every camera
must stay outside it. Three ways, first that applies (`find_sphere`):

1. ``sphere.json`` next to the scene's files: ``{"center": [x, y, z], "radius": r}`` in the
   scene's world units (the user's override).
2. With masks, the *visual hull* (`hull_sphere`):

   a. A generous search sphere from the cameras alone: centred on the point closest to all
      optical axes (`neus_l0.data.cameras.axes_convergence`), radius `SEARCH_FRACTION` x
      the nearest camera's distance to it (so every camera is outside).
   b. The masks (block-averaged to at most 128 pixels, `neus_l0.formats.transforms.Views`)
      are made binary (`search_foreground`: coverage >= `COVERAGE`, or any coverage where
      no neighbour reaches it) and padded with their own edge pixels (background stays
      background beyond the image frame, an object cut by the frame stays cut open) so that
      views see the whole search sphere, and `neus_l0.bounds.hull.carve_hull` carves it at
      `RESOLUTION`^3 in the search sphere's normalised frame, with a `MARGIN_PX` margin.
   c. The tight sphere: carved once more at `FINE_RESOLUTION`^3 in a sphere `REFINE_SLACK`
      x the first hull's reach; the centre of the kept (undilated) cells' bounding box, and
      the farthest kept cell corner from it plus `MARGIN` of that. The cells hold the
      carved hull, so the margin is only for the masks' rounding.
   d. When kept cells touch the search sphere's boundary, the object (or a mask error)
      reaches beyond it: the search is repeated once around the kept cells with the largest
      radius the cameras allow; if the hull still touches, a `SceneError` says how much of
      the boundary is kept and what to do.
3. Without masks, `choose_sphere` (below) on the scene's sparse points
   (nerfstudio's ``ply_file_path``) and cameras; without points, that is the optical axes'
   convergence point with half the median camera distance as radius (capped so that every
   camera stays outside).

All in float64 numpy, except the carving (torch, on the CPU).

The sphere from sparse SfM points (`choose_sphere`, also what `neus-l0 colmap` uses):

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
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from neus_l0.bounds.hull import carve_hull
from neus_l0.data.cameras import axes_convergence
from neus_l0.errors import SceneError
from neus_l0.formats.preview import sphere_outline

#: The search sphere's radius as a fraction of the nearest camera's distance.
SEARCH_FRACTION = 0.75
#: The second search's fraction (around the first hull's cells).
RETRY_FRACTION = 0.95
#: Cells per axis of the search hull.
RESOLUTION = 64
#: Cells per axis of the last, refining carve.
FINE_RESOLUTION = 128
#: Mask dilation of the search hull, in search-mask pixels (covers the thresholding below).
MARGIN_PX = 1.0
#: A search-mask pixel (a block average of the full-resolution mask) is foreground from
#: this coverage up (and below it when no pixel around it reaches it: thin parts stay).
COVERAGE = 0.5
#: The refining search sphere's radius over the first hull's farthest corner.
REFINE_SLACK = 1.1
#: The tight sphere's radius: the kept cells' farthest corner plus this fraction of it.
MARGIN = 0.03
#: The padding of the search masks, at most this many times their longer side per edge.
MAX_PAD = 1.5
#: Every camera stays outside: radii are capped at this fraction of the nearest camera's
#: distance.
MAX_CAMERA_FRACTION = 0.95
#: The user's override file.
SPHERE_FILE = "sphere.json"


@dataclasses.dataclass
class SphereFit:
    """The object sphere and how it was found.

    Attributes:
        center: (3,) world units.
        radius: world units.
        method: ``sphere.json``, ``visual hull``, ``SfM points`` or ``cameras``.
        detail: one line on how (for the user).
        points: (M, 3) world points that support it, for the preview (hull cell centres,
            sparse points; empty for ``cameras``).
        seconds: time it took.
    """

    center: np.ndarray
    radius: float
    method: str
    detail: str
    points: np.ndarray
    seconds: float = 0.0

    def scale_mat(self) -> np.ndarray:
        """(4, 4) float64 normalised -> world."""
        S = np.diag([self.radius, self.radius, self.radius, 1.0])
        S[:3, 3] = self.center
        return S

    def explain(self) -> str:
        """One line: the sphere and how it was found."""
        c = self.center
        return (f"object sphere: centre ({c[0]:.4g}, {c[1]:.4g}, {c[2]:.4g}), radius "
                f"{self.radius:.4g} ({self.method}: {self.detail})")

    def to_dict(self) -> dict:
        return {"center": [float(v) for v in self.center], "radius": float(self.radius),
                "method": self.method, "detail": self.detail,
                "seconds": round(self.seconds, 3)}


def search_sphere(centres: np.ndarray, axes: np.ndarray,
                  fraction: float = SEARCH_FRACTION) -> tuple[np.ndarray, float]:
    """The generous sphere from the cameras alone (step 2a of the module docstring).

    Args:
        centres: (V, 3) camera centres; axes: (V, 3) optical axes (camera +z), world.
        fraction: radius over the nearest camera's distance to the centre.

    Returns:
        centre (3,), radius.

    Raises:
        ValueError: the optical axes are (nearly) parallel.
    """
    c0 = axes_convergence(centres, axes)
    return c0, fraction * float(np.linalg.norm(centres - c0, axis=-1).min())


def _normalised(c2w: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """(V, 4, 4) poses in the frame where the sphere (center, radius) is the unit sphere."""
    out = c2w.copy()
    out[:, :3, 3] = (c2w[:, :3, 3] - center) / radius
    return out


def _pad(masks: np.ndarray, K: np.ndarray, c2w_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pad the masks with their edge pixels so that each view sees the unit sphere (at most
    `MAX_PAD` x the longer side per edge; one padding for all views).

    Args:
        masks: (V, h, w); K: (V, 3, 3); c2w_n: (V, 4, 4) normalised frame.

    Returns:
        padded masks (V, h + 2p, w + 2p), their K (principal point shifted by p).
    """
    V, h, w = masks.shape
    need = 0.0
    for v in range(V):
        w2c = np.linalg.inv(c2w_n[v])
        ring = sphere_outline(K[v] @ w2c[:3], np.zeros(3), 1.0)
        X = w2c[:3, 3]  # the sphere's centre in the camera frame
        if ring is None or X[2] <= 1.0 or not np.isfinite(ring).all():
            need = math.inf  # the sphere reaches behind the camera's plane
            break
        need = max(need, -ring[:, 0].min(), ring[:, 0].max() - (w - 1), -ring[:, 1].min(),
                   ring[:, 1].max() - (h - 1))
    pad = int(min(math.ceil(need + 2.0), MAX_PAD * max(h, w)))
    pad = max(pad, 0)
    out = np.stack([cv2.copyMakeBorder(m, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
                    for m in masks])
    Kp = K.copy()
    Kp[:, 0, 2] += pad
    Kp[:, 1, 2] += pad
    return out, Kp


def search_foreground(masks: np.ndarray) -> np.ndarray:
    """Binary search masks from block-averaged coverage (`COVERAGE`).

    A pixel is foreground when its coverage reaches `COVERAGE` (the silhouette as a mask
    rendered at this resolution would give it, within `MARGIN_PX` of the true one), or when
    it has any coverage and no pixel of its 3 x 3 neighbourhood reaches `COVERAGE` (a part
    thinner than half a pixel, e.g. a rod, is kept rather than lost).

    Args:
        masks: (V, h, w) float coverage in [0, 1].

    Returns:
        (V, h, w) float32 in {0, 1}.
    """
    full = masks >= COVERAGE
    near_full = np.stack([cv2.dilate(f.astype(np.uint8), np.ones((3, 3), np.uint8))
                          for f in full]).astype(bool) if len(masks) else full
    return (full | ((masks > 0) & ~near_full)).astype(np.float32)


def _carve(masks: np.ndarray, K: np.ndarray, c2w: np.ndarray, center: np.ndarray,
           radius: float, names: list[str] | None,
           resolution: int = RESOLUTION) -> tuple[np.ndarray, float, list[str]]:
    """Carve the hull in the sphere (center, radius) at `resolution`^3 cells.

    Returns:
        kept: (N, 3) centres of the cells the carving kept (not dilated), in the sphere's
            normalised frame;
        shell: the fraction of the boundary shell's cells that are kept;
        warnings: the hull's warning lines.
    """
    c2w_n = _normalised(c2w, center, radius)
    pm, pK = _pad(masks, K, c2w_n)
    hull = carve_hull(torch.from_numpy(pm).float(), torch.from_numpy(pK).float(),
                      torch.from_numpy(c2w_n).float(), resolution=resolution,
                      margin_px=MARGIN_PX, has_masks=True, names=names)
    occ = hull.carved.cpu().numpy()
    h = 2.0 / resolution
    ax = -1.0 + h * (np.arange(resolution) + 0.5)
    grid = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1)  # (R, R, R, 3)
    r = np.linalg.norm(grid, axis=-1)
    shell_cells = (r > 1.0 - 2.0 * h) & (r <= 1.0 + h)
    shell = float(occ[shell_cells].mean()) if shell_cells.any() else 0.0
    return grid[occ], shell, list(hull.report.warnings)


def _tight(kept: np.ndarray, resolution: int) -> tuple[np.ndarray, float]:
    """Centre of the kept cells' box and the farthest kept cell corner's distance from it
    (normalised): the smallest ball about that centre holding every kept cell."""
    h = 2.0 / resolution
    lo, hi = kept.min(0) - 0.5 * h, kept.max(0) + 0.5 * h
    mid = 0.5 * (lo + hi)
    reach = float(np.linalg.norm(kept - mid, axis=-1).max()) + 0.5 * math.sqrt(3.0) * h
    return mid, reach


def hull_sphere(masks: np.ndarray, intrinsics: np.ndarray, c2w: np.ndarray,
                names: list[str] | None = None, where: str | Path = "scene",
                log=None) -> SphereFit:
    """The object sphere from the masks' visual hull (step 2 of the module docstring).

    Args:
        masks: (V, h, w) float32 coverage in [0, 1] (`search_foreground`).
        intrinsics: (V, 3, 3) K of those masks; c2w: (V, 4, 4) OpenCV camera-to-world in
            world units.
        names: view names for the hull's warnings.
        where: the scene's file, for messages.
        log: callable taking one line (the hull's warnings), or None.

    Raises:
        SceneError: the axes are parallel, the hull is empty, or it still touches the
            search sphere after the second search.
    """
    t0 = time.perf_counter()
    fg = search_foreground(masks)
    centres = c2w[:, :3, 3]
    center, radius, kept, warnings, tries = _search(fg, intrinsics, c2w, names, where)
    # refine: carve again, with finer cells, in a sphere just around the first hull
    res = RESOLUTION
    mid, reach = _tight(kept, res)
    fine_center, fine_radius = center + radius * mid, REFINE_SLACK * radius * reach
    fine, fine_shell, fine_warnings = _carve(fg, intrinsics, c2w, fine_center, fine_radius,
                                             names, FINE_RESOLUTION)
    if len(fine) and fine_shell == 0.0:
        center, radius, kept, warnings = fine_center, fine_radius, fine, fine_warnings
        res = FINE_RESOLUTION
    if log is not None:
        for w in warnings:
            log(f"visual hull: {w}")
    mid, reach = _tight(kept, res)
    center_w = center + radius * mid
    radius_w = (1.0 + MARGIN) * radius * reach
    nearest = float(np.linalg.norm(centres - center_w, axis=-1).min())
    detail = (f"{len(masks)} masks, {res}^3 cells in a sphere of radius {radius:.4g}"
              f"{', second search' if tries > 1 else ''}; the kept cells' farthest corner "
              f"+{MARGIN:.0%}")
    if radius_w > MAX_CAMERA_FRACTION * nearest:
        radius_w = MAX_CAMERA_FRACTION * nearest
        detail += "; capped to keep every camera outside"
    return SphereFit(center=center_w, radius=radius_w, method="visual hull", detail=detail,
                     points=center + radius * kept, seconds=time.perf_counter() - t0)


def _search(fg: np.ndarray, intrinsics: np.ndarray, c2w: np.ndarray,
            names: list[str] | None, where: str | Path):
    """Steps 2a, 2b and 2d of the module docstring: the first hull, in a search sphere that
    holds it.

    Returns:
        center (3,), radius of the search sphere; kept (N, 3) cell centres in its frame;
        the hull's warnings; how many searches it took.

    Raises:
        SceneError: as `hull_sphere`.
    """
    centres, axes = c2w[:, :3, 3], c2w[:, :3, 2]
    try:
        center, radius = search_sphere(centres, axes)
    except ValueError:
        raise SceneError(f"{where}: the cameras' optical axes are (nearly) parallel: no "
                         f"object to centre on; give the sphere in {SPHERE_FILE}") from None
    for tries in (1, 2):
        kept, shell, warnings = _carve(fg, intrinsics, c2w, center, radius, names)
        if len(kept) == 0:
            raise SceneError(f"{where}: the masks' visual hull is empty: masks and cameras "
                             f"disagree (wrong camera convention or masks of other views?)")
        if shell == 0.0:
            return center, radius, kept, warnings, tries
        mid, _ = _tight(kept, RESOLUTION)
        new_center = center + radius * mid
        nearest = float(np.linalg.norm(centres - new_center, axis=-1).min())
        if tries == 2 or RETRY_FRACTION * nearest <= radius * 1.05:
            break
        center, radius = new_center, RETRY_FRACTION * nearest
    raise SceneError(
        f"{where}: the masks' visual hull reaches the search sphere (centre "
        f"({center[0]:.4g}, {center[1]:.4g}, {center[2]:.4g}), radius {radius:.4g}, "
        f"the largest the cameras allow): {shell:.1%} of its boundary cells are kept, "
        f"so the object is cut there; check that every mask covers the object only "
        f"and that the object is whole in most views, or give the sphere in "
        f"{SPHERE_FILE} ({{\"center\": [x, y, z], \"radius\": r}}, world units)")


def camera_sphere(c2w: np.ndarray, points: np.ndarray | None = None,
                  where: str | Path = "scene") -> SphereFit:
    """The object sphere without masks (step 3 of the module docstring).

    Args:
        c2w: (V, 4, 4) OpenCV camera-to-world, world units.
        points: (M, 3) sparse points, world units, or None.

    Raises:
        SceneError: the optical axes are (nearly) parallel.
    """
    t0 = time.perf_counter()
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    try:
        ch = choose_sphere(pts, np.full(len(pts), 3), c2w[:, :3, 3], c2w[:, :3, 2])
    except ValueError:
        raise SceneError(f"{where}: the cameras' optical axes are (nearly) parallel: no "
                         f"object to centre on; give the sphere in {SPHERE_FILE}") from None
    if ch.n_points >= 4:
        method = "SfM points"
        detail = (f"{ch.n_points} of {ch.n_total} sparse points near the cameras' look-at "
                  f"point")
        support = pts
    else:
        method = "cameras"
        detail = ("no masks and no sparse points: the cameras' look-at point, half the "
                  "median camera distance (check the preview)")
        support = np.zeros((0, 3))
    if ch.capped:
        detail += "; capped to keep every camera outside"
    return SphereFit(center=ch.center, radius=ch.radius, method=method, detail=detail,
                     points=support, seconds=time.perf_counter() - t0)


def user_sphere(path: Path, c2w: np.ndarray) -> SphereFit:
    """The sphere of a ``sphere.json`` file (``center``, ``radius``, world units).

    Raises:
        SceneError: unreadable, malformed, or a camera inside the sphere.
    """
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
        center = np.asarray(data["center"], dtype=np.float64).reshape(3)
        radius = float(data["radius"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SceneError(f"{path}: expected {{\"center\": [x, y, z], \"radius\": r}} "
                         f"({type(exc).__name__}: {exc})") from None
    if not (np.isfinite(center).all() and math.isfinite(radius) and radius > 0):
        raise SceneError(f"{path}: centre must be finite and radius > 0")
    nearest = float(np.linalg.norm(c2w[:, :3, 3] - center, axis=-1).min())
    if nearest <= radius:
        raise SceneError(f"{path}: a camera lies inside the sphere (nearest camera at "
                         f"{nearest:.4g} from the centre, radius {radius:.4g})")
    return SphereFit(center=center, radius=radius, method=SPHERE_FILE, detail=str(path),
                     points=np.zeros((0, 3)))


def find_sphere(root: Path, c2w: np.ndarray, masks: np.ndarray | None = None,
                intrinsics: np.ndarray | None = None, points: np.ndarray | None = None,
                names: list[str] | None = None, where: str | Path = "scene",
                log=None) -> SphereFit:
    """The object sphere, the first way that applies (module docstring).

    Args:
        root: the scene folder (where ``sphere.json`` may be).
        c2w: (V, 4, 4) OpenCV camera-to-world, world units.
        masks: (V, h, w) search masks, or None; intrinsics: (V, 3, 3) their K.
        points: (M, 3) sparse points, world units, or None.
        names, where, log: as `hull_sphere`.
    """
    if (Path(root) / SPHERE_FILE).is_file():
        return user_sphere(Path(root) / SPHERE_FILE, c2w)
    if masks is not None:
        return hull_sphere(masks, intrinsics, c2w, names, where, log)
    return camera_sphere(c2w, points, where)


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


def given_sphere(center: np.ndarray, radius: float, centres: np.ndarray,
                 dirs: np.ndarray) -> SphereChoice:
    """A `SphereChoice` for a sphere given by the user (the convergence point for the record)."""
    try:
        c0 = axes_convergence(centres, dirs)
    except ValueError:
        c0 = np.asarray(center, dtype=np.float64)
    return SphereChoice(center=np.asarray(center, dtype=np.float64), radius=float(radius),
                        convergence=c0, n_points=0, n_total=0, source="user")
