"""Headless renders of meshes for the figures: shaded, and coloured by surface error.

Rendering is `neus_l0.figures.raster.raster_render` (a vectorised torch z-buffer rasteriser over
the triangles, on the CPU; no OpenGL, no display, no GPU). The error of a pixel is the
distance from the predicted surface point it shows to the true surface (exact
point-to-triangle distance to ``gt_mesh.ply`` near it, see `SurfaceDistance`), so the error
images are the per-vertex errors of the predicted mesh, evaluated at every visible point.
"""

from __future__ import annotations

import numpy as np
import trimesh

from neus_l0.figures.raster import raster_render
from neus_l0.figures.views import Camera

#: Colour map of the error images.
ERROR_CMAP = "turbo"
#: Grey of the background (no surface) in the pictures.
BACKGROUND = 1.0


def clip_to_ball(mesh: trimesh.Trimesh, center: np.ndarray, radius: float) -> trimesh.Trimesh:
    """The faces of `mesh` with a vertex within `radius` of `center` (removes occluders)."""
    v = np.asarray(mesh.vertices)
    near = np.linalg.norm(v - np.asarray(center)[None], axis=1) <= radius  # (V,)
    keep = near[np.asarray(mesh.faces)].any(axis=1)  # (F,)
    return trimesh.Trimesh(v, np.asarray(mesh.faces)[keep], process=False)


class SurfaceDistance:
    """Distance of world points to a true surface mesh (indexed once, queried often).

    Exact point-to-triangle distances (`neus_l0.evaluation.surface.MeshDistance`) up to
    `exact_within` (exact queries get slow far from the surface); beyond it, the distance to
    the nearest vertex or triangle centroid, which is within one triangle size of the truth.

    Args:
        gt: the true surface (world units).
        exact_within: distance below which answers are exact; default 4 % of the diagonal
            of the mesh's bounding box.
    """

    def __init__(self, gt: trimesh.Trimesh, exact_within: float | None = None):
        from scipy.spatial import cKDTree

        v, f = np.asarray(gt.vertices, np.float64), np.asarray(gt.faces)
        self.exact_within = float(exact_within or 0.04 * np.linalg.norm(np.ptp(v, axis=0)))
        try:
            from neus_l0.evaluation.surface import MeshDistance
        except ImportError:  # pragma: no cover - exact distances not available
            MeshDistance = None
        self._exact = MeshDistance(v, f) if MeshDistance is not None else None
        self._tree = cKDTree(np.concatenate([v, v[f].mean(axis=1)]))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N,) distances of (N, 3) points (NaN rows give NaN)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full(len(points), np.nan)
        ok = np.flatnonzero(np.isfinite(points).all(axis=1))
        if len(ok) == 0:
            return out
        d = np.full(len(ok), np.inf)
        if self._exact is not None:
            d = self._exact.query(points[ok], upper_bound=self.exact_within)
        far = ~np.isfinite(d)
        if far.any():
            d[far] = self._tree.query(points[ok][far])[0]
        out[ok] = d
        return out


def render_mesh(mesh: trimesh.Trimesh, cam: Camera,
                distance: SurfaceDistance | None = None) -> dict[str, np.ndarray]:
    """Shade a mesh through a camera, with the per-pixel surface error if `distance` is given.

    Returns:
        dict with ``shade`` (H, W) in [0, 1], NaN where nothing is seen, and ``error``
        (H, W) world-unit distance to the true surface (NaN where nothing is seen; absent
        without `distance`).
    """
    r = raster_render(mesh, cam.P, cam.width, cam.height)
    out = {"shade": r["shade"]}
    if distance is not None:
        out["error"] = distance(r["points"].reshape(-1, 3)).reshape(cam.height, cam.width)
    return out


def shaded_rgb(shade: np.ndarray) -> np.ndarray:
    """(H, W, 3) grey picture of a shade image, background white."""
    g = np.where(np.isnan(shade), BACKGROUND, shade)
    return np.repeat(g[..., None], 3, axis=-1)


def error_rgb(error: np.ndarray, shade: np.ndarray, vmax: float,
              cmap: str = ERROR_CMAP) -> np.ndarray:
    """(H, W, 3) error picture: colour from `cmap` on [0, vmax], lightly shaded so the shape
    stays readable; background white."""
    import matplotlib

    t = np.clip(np.nan_to_num(error, nan=0.0) / max(vmax, 1e-12), 0.0, 1.0)
    rgb = matplotlib.colormaps[cmap](t)[..., :3]
    light = 0.6 + 0.4 * np.nan_to_num(shade, nan=1.0)
    rgb = rgb * light[..., None]
    return np.where(np.isnan(shade)[..., None], BACKGROUND, rgb)
