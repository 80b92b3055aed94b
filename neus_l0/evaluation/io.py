"""Reading meshes and point clouds (trimesh) with one-line `NeusL0Error`s; atomic PLY writes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from neus_l0.atomic import atomic_write
from neus_l0.errors import NeusL0Error


def _load(path: str | os.PathLike):
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise NeusL0Error(f"{path}: file not found")
    try:
        return trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many exception types on bad files
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise NeusL0Error(f"{path}: cannot read ({msg})") from None


def load_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh.

    Args:
        path: any format trimesh reads (PLY, OBJ, STL, ...). A scene is merged.

    Returns:
        vertices (V, 3) float64 and faces (F, 3) int64, unprocessed (no merging/removal).

    Raises:
        NeusL0Error: missing or unreadable file, or a file without triangles.
    """
    import trimesh

    obj = _load(path)
    if isinstance(obj, trimesh.Scene):
        geoms = [g for g in obj.geometry.values() if isinstance(g, trimesh.Trimesh)]
        obj = trimesh.util.concatenate(geoms) if geoms else None
    if not isinstance(obj, trimesh.Trimesh) or len(obj.faces) == 0:
        raise NeusL0Error(f"{path}: mesh has no faces")
    v = np.asarray(obj.vertices, dtype=np.float64)
    f = np.asarray(obj.faces, dtype=np.int64)
    if not np.isfinite(v).all():
        raise NeusL0Error(f"{path}: mesh has non-finite vertex coordinates")
    return v, f


def load_points(path: str | os.PathLike) -> np.ndarray:
    """Read a point cloud (the vertices of a PLY, with or without faces).

    Returns:
        (N, 3) float64 points.

    Raises:
        NeusL0Error: missing or unreadable file, or no points.
    """
    import trimesh

    obj = _load(path)
    if isinstance(obj, trimesh.Scene):
        pts = [np.asarray(g.vertices) for g in obj.geometry.values() if hasattr(g, "vertices")]
        v = np.concatenate(pts) if pts else np.zeros((0, 3))
    elif hasattr(obj, "vertices"):
        v = np.asarray(obj.vertices)
    else:
        v = np.zeros((0, 3))
    if len(v) == 0:
        raise NeusL0Error(f"{path}: no points")
    v = np.asarray(v, dtype=np.float64)
    if not np.isfinite(v).all():
        raise NeusL0Error(f"{path}: non-finite point coordinates")
    return v


def write_ply_mesh(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray,
                   colors: np.ndarray | None = None) -> Path:
    """Write a binary PLY mesh atomically.

    Args:
        path: output file.
        vertices: (V, 3); faces: (F, 3); colors: optional (V, 4) uint8 RGBA per vertex.
    """
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colors,
                           process=False)
    return atomic_write(path, lambda p: mesh.export(str(p), file_type="ply"))


def write_ply_points(path: str | os.PathLike, points: np.ndarray,
                     colors: np.ndarray | None = None) -> Path:
    """Write a binary PLY point cloud atomically.

    Args:
        path: output file.
        points: (N, 3); colors: optional (N, 4) uint8 RGBA.
    """
    import trimesh

    cloud = trimesh.PointCloud(points, colors=colors)
    return atomic_write(path, lambda p: cloud.export(str(p), file_type="ply"))
