"""``sphere_preview.png``: sparse points and the object sphere's outline over a few views.

Drawn off-screen with matplotlib's Agg canvas (no display, no global backend change).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from neus_l0.atomic import atomic_write


def sphere_outline(P: np.ndarray, center: np.ndarray, radius: float,
                   n: int = 180) -> np.ndarray | None:
    """Image outline of a sphere: the projection of its circle of tangency from the camera.

    Args:
        P: (3, 4) or (4, 4) projection K[R|t] (world -> pixels, NeuS convention).
        center: (3,) sphere centre.
        radius: sphere radius.
        n: points on the outline.

    Returns:
        (n, 2) pixel coordinates, or None when the camera is inside the sphere.
    """
    P = np.asarray(P, dtype=np.float64)[:3, :4]
    M, p4 = P[:, :3], P[:, 3]
    cam = -np.linalg.solve(M, p4)  # camera centre
    v = np.asarray(center, dtype=np.float64) - cam
    d2 = float(v @ v)
    if d2 <= radius * radius:
        return None
    k = radius * radius / d2
    mid = cam + v * (1.0 - k)  # centre of the tangency circle
    rho = radius * np.sqrt(1.0 - k)
    a = np.cross(v, [1.0, 0.0, 0.0] if abs(v[0]) < 0.9 * np.sqrt(d2) else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(v / np.sqrt(d2), a)
    th = np.linspace(0.0, 2.0 * np.pi, n)
    pts = mid + rho * (np.cos(th)[:, None] * a + np.sin(th)[:, None] * b)  # (n, 3)
    h = pts @ M.T + p4
    return h[:, :2] / h[:, 2:3]


def write_preview(path: str | Path, images: list[np.ndarray], world_mats: list[np.ndarray],
                  points: np.ndarray, center: np.ndarray, radius: float,
                  titles: list[str] | None = None) -> Path:
    """Draw each image with the sparse points (inside the sphere: green, outside: red) and
    the sphere's outline (yellow), side by side, and save a PNG atomically.

    Args:
        path: output PNG.
        images: views, (H, W, 3) uint8 RGB each.
        world_mats: (4, 4) projections of those views (NeuS convention).
        points: (M, 3) sparse points, world units.
        center: (3,) sphere centre.
        radius: sphere radius.
        titles: one caption per view.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n = len(images)
    H, W = images[0].shape[:2]
    fig = Figure(figsize=(4.0 * n, 4.0 * H / W + 0.6), dpi=100)
    FigureCanvasAgg(fig)
    inside = np.linalg.norm(points - center, axis=-1) <= radius
    for k, (img, P) in enumerate(zip(images, world_mats, strict=True)):
        ax = fig.add_subplot(1, n, k + 1)
        ax.imshow(img)
        P = np.asarray(P, dtype=np.float64)[:3, :4]
        h = points @ P[:, :3].T + P[:, 3]
        front = h[:, 2] > 0
        xy = h[front, :2] / h[front, 2:3]
        vis = (xy[:, 0] >= 0) & (xy[:, 0] < W) & (xy[:, 1] >= 0) & (xy[:, 1] < H)
        ins = inside[front]
        ax.scatter(xy[vis & ins, 0], xy[vis & ins, 1], s=2, c="lime", linewidths=0)
        ax.scatter(xy[vis & ~ins, 0], xy[vis & ~ins, 1], s=2, c="red", linewidths=0)
        ring = sphere_outline(P, center, radius)
        if ring is not None:
            ax.plot(ring[:, 0], ring[:, 1], c="yellow", lw=1.5)
        ax.set_xlim(-0.5, W - 0.5)
        ax.set_ylim(H - 0.5, -0.5)
        ax.set_axis_off()
        if titles:
            ax.set_title(titles[k], fontsize=9)
    fig.suptitle("object sphere (yellow); sparse points inside (green) / outside (red)",
                 fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    data = buf.getvalue()
    return atomic_write(path, lambda p: p.write_bytes(data))
