"""Mesh extraction: SDF on a grid (chunked), marching cubes, clean-up, colours, export.

Marching cubes runs in the normalised frame (the unit sphere around the object); vertices
are then mapped to world units with the scene's ``scale_mat``:
``x_world = scale_mat[:3, :3] @ x_norm + scale_mat[:3, 3]``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import trimesh
from torch import Tensor

from neus_l0.atomic import atomic_path
from neus_l0.errors import NeusL0Error

SdfFn = Callable[[Tensor], Tensor]
"""Maps points (P, 3) in the normalised frame to SDF values (P,) or (P, 1)."""


def sdf_grid(sdf_fn: SdfFn, resolution: int, bound: float = 1.0,
             device: str | torch.device = "cpu", chunk: int = 2**18) -> np.ndarray:
    """Evaluate an SDF on the regular grid ``linspace(-bound, bound, resolution)^3``.

    Points are generated and evaluated slab by slab, `chunk` points at a time, so no tensor
    larger than `chunk` x 3 floats is ever allocated besides the float32 output volume.

    Args:
        sdf_fn: the SDF (called under `torch.no_grad`).
        resolution: R, samples per axis.
        bound: half-size of the cube.
        device: where the points are evaluated.
        chunk: points per call of `sdf_fn`.

    Returns:
        (R, R, R) float32 volume indexed [x, y, z].
    """
    R = int(resolution)
    axis = torch.linspace(-bound, bound, R, device=device)
    out = np.empty((R, R, R), dtype=np.float32)
    yz = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), dim=-1).reshape(-1, 2)  # (R*R, 2)
    slabs = max(1, chunk // (R * R))
    with torch.no_grad():
        for x0 in range(0, R, slabs):
            xs = axis[x0:x0 + slabs]
            pts = torch.cat([xs.repeat_interleave(R * R)[:, None], yz.repeat(len(xs), 1)], dim=-1)
            vals = torch.cat([sdf_fn(p).reshape(-1) for p in pts.split(chunk)])
            out[x0:x0 + len(xs)] = vals.reshape(len(xs), R, R).float().cpu().numpy()
    return out


def to_world(vertices: np.ndarray, scale_mat: np.ndarray) -> np.ndarray:
    """Map (V, 3) normalised-frame points to world units with the 4x4 `scale_mat`."""
    S = np.asarray(scale_mat, dtype=np.float64)
    return vertices @ S[:3, :3].T + S[:3, 3]


def marching_cubes(volume: np.ndarray, bound: float = 1.0,
                   level: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of a grid SDF (negative inside) in the normalised frame.

    Args:
        volume: (R, R, R) SDF on ``linspace(-bound, bound, R)^3``, indexed [x, y, z].
        bound: half-size of the cube.
        level: the iso-value.

    Returns:
        vertices (V, 3) float64 and faces (F, 3) int64, wound so normals point outward.

    Raises:
        NeusL0Error: when the volume has no crossing of `level` (no surface inside).
    """
    from skimage import measure

    finite = np.isfinite(volume)
    if not finite.all():
        volume = np.where(finite, volume, np.float32(1e3))
    if not (volume.min() < level < volume.max()):
        raise NeusL0Error(f"no surface: the SDF does not cross {level} inside the cube "
                          f"[-{bound}, {bound}]^3 (range {volume.min():.3g}..{volume.max():.3g})")
    R = volume.shape[0]
    step = 2.0 * bound / (R - 1)
    verts, faces, _, _ = measure.marching_cubes(volume, level=level, spacing=(step,) * 3,
                                                gradient_direction="descent")
    return verts.astype(np.float64) - bound, faces.astype(np.int64)


def clean_mesh(mesh: trimesh.Trimesh, keep_largest: bool = True,
               min_fraction: float = 0.01) -> trimesh.Trimesh:
    """Drop floating specks.

    Args:
        mesh: the mesh.
        keep_largest: keep only the connected component with the most faces.
        min_fraction: otherwise keep components with at least this fraction of the largest
            component's faces.

    Returns:
        the cleaned mesh (vertex colours kept).
    """
    parts = mesh.split(only_watertight=False)
    if len(parts) <= 1:
        return mesh
    sizes = np.array([len(p.faces) for p in parts])
    if keep_largest:
        return parts[int(sizes.argmax())]
    keep = [p for p, n in zip(parts, sizes, strict=True) if n >= min_fraction * sizes.max()]
    return trimesh.util.concatenate(keep)


def vertex_colors(model, vertices: np.ndarray, device: str | torch.device = "cpu",
                  chunk: int = 2**16) -> np.ndarray:
    """Colours from the colour network, looking along the inward normal (view = -normal).

    Args:
        model: a `neus_l0.fields.NeuSModel`.
        vertices: (V, 3) in the normalised frame.

    Returns:
        (V, 4) uint8 RGBA.
    """
    from neus_l0.fields import sdf_and_gradient

    out = []
    for part in torch.from_numpy(vertices.astype(np.float32)).split(chunk):
        x = part.to(device)
        h, grad = sdf_and_gradient(model.sdf, x, create_graph=False)
        with torch.no_grad():
            n = torch.nn.functional.normalize(grad, dim=-1)
            rgb = model.color(x, grad, -n, h[:, 1:])
        out.append(rgb.detach().cpu())
    rgb = torch.cat(out).clamp(0, 1).numpy() if out else np.zeros((0, 3), np.float32)
    rgba = np.concatenate([rgb, np.ones_like(rgb[:, :1])], axis=1)
    return (rgba * 255 + 0.5).astype(np.uint8)


def extract_mesh(model, scale_mat: np.ndarray, resolution: int = 512, bound: float = 1.0,
                 clean: bool = True, colors: bool = False, device: str | torch.device = "cpu",
                 chunk: int = 2**18) -> trimesh.Trimesh:
    """The trained SDF's zero level set in world units.

    Args:
        model: a `neus_l0.fields.NeuSModel` (only `sdf`, and `color` when `colors`).
        scale_mat: (4, 4) normalised -> world.
        resolution: grid samples per axis over [-bound, bound].
        clean: keep only the largest connected component.
        colors: vertex colours from the colour network.
        device, chunk: where and how many points at a time the SDF is evaluated.

    Returns:
        the mesh in world units.
    """
    volume = sdf_grid(lambda p: model.sdf.sdf(p), resolution, bound, device, chunk)
    verts, faces = marching_cubes(volume, bound)
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if clean:
        mesh = clean_mesh(mesh)
    if colors:
        mesh.visual.vertex_colors = vertex_colors(model, np.asarray(mesh.vertices), device)
    mesh.vertices = to_world(np.asarray(mesh.vertices), scale_mat)
    return mesh


def export_mesh(mesh: trimesh.Trimesh, path: str | Path) -> Path:
    """Write a PLY or OBJ file atomically (format from the suffix)."""
    path = Path(path)
    kind = path.suffix.lower().lstrip(".")
    if kind not in ("ply", "obj"):
        raise NeusL0Error(f"{path}: unsupported mesh format '.{kind}' (use .ply or .obj)")
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=kind)
    return path
