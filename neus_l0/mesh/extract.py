"""Mesh extraction: SDF on a grid (dense or sparse), marching cubes, clean-up, colours, export.

Marching cubes runs in the normalised frame (the unit sphere around the object); vertices
are then mapped to world units with the scene's ``scale_mat``:
``x_world = scale_mat[:3, :3] @ x_norm + scale_mat[:3, 3]``.

Two extraction paths share one grid, ``linspace(-bound, bound, R)^3``:

- *dense* (`sdf_grid` + `marching_cubes`): the whole (R, R, R) volume; the plain reference,
  used for small resolutions.
- *sparse* (`sparse_marching_cubes`): the SDF on a coarse grid (every `block`-th sample),
  then densely only inside the blocks that `keep_blocks` says may hold the surface, marching
  cubes per block and an exact merge of the vertices on shared block faces. It never
  allocates the dense volume, and gives the dense result for any SDF that is
  `lipschitz`-Lipschitz (see `keep_blocks`).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
import trimesh
from torch import Tensor

from neus_l0.atomic import atomic_path
from neus_l0.data.cameras import to_world
from neus_l0.errors import NeusL0Error

if TYPE_CHECKING:
    from neus_l0.bounds.hull import VisualHull

SdfFn = Callable[[Tensor], Tensor]
"""Maps points (P, 3) in the normalised frame to SDF values (P,) or (P, 1)."""

SPARSE_ABOVE = 128
"""`extract_mesh(method="auto")` uses the sparse path for resolutions above this."""

_NONFINITE = np.float32(1e3)
"""Non-finite SDF values are read as this (far outside) before marching cubes."""


#: A progress bar shows only once its work has taken this long (seconds).
PROGRESS_DELAY_S = 1.0

_PROGRESS: contextvars.ContextVar[bool] = contextvars.ContextVar("neus_l0_mesh_progress",
                                                                 default=False)


@contextlib.contextmanager
def progress_bars(on: bool = True):
    """Inside, the SDF evaluations of `sdf_grid` and `sparse_marching_cubes` (so of
    `extract_mesh`) show a tqdm bar on stderr when they take over `PROGRESS_DELAY_S`,
    unless called with ``progress=False``."""
    token = _PROGRESS.set(bool(on))
    try:
        yield
    finally:
        _PROGRESS.reset(token)


def _bar(progress: bool | None, total: int, desc: str, unit: str):
    """A tqdm bar on stderr that appears only after `PROGRESS_DELAY_S` and is cleared at
    the end (the caller prints the summary); a no-op bar when `progress` is False, or None
    outside `progress_bars`."""
    from tqdm import tqdm

    on = _PROGRESS.get() if progress is None else progress
    return tqdm(total=total, desc=desc, unit=unit, unit_scale=True, leave=False,
                delay=PROGRESS_DELAY_S, disable=not on, dynamic_ncols=True)


def _sdf_on_axes(sdf_fn: SdfFn, xs: Tensor, ys: Tensor, zs: Tensor,
                 chunk: int, progress: bool | None = None) -> np.ndarray:
    """Evaluate an SDF on the tensor product grid xs x ys x zs, slab by slab.

    Args:
        sdf_fn: the SDF (called under `torch.no_grad`).
        xs, ys, zs: (nx,), (ny,), (nz,) coordinates on the evaluation device.
        chunk: points per call of `sdf_fn`.
        progress: a tqdm bar on stderr (points evaluated) when it takes over a second
            (None: inside `progress_bars` only).

    Returns:
        (nx, ny, nz) float32 values.
    """
    nx, ny, nz = len(xs), len(ys), len(zs)
    out = np.empty((nx, ny, nz), dtype=np.float32)
    yz = torch.stack(torch.meshgrid(ys, zs, indexing="ij"), dim=-1).reshape(-1, 2)  # (ny*nz, 2)
    slabs = max(1, chunk // (ny * nz))
    with torch.no_grad(), _bar(progress, nx * ny * nz, f"SDF grid {nx}^3", "pt") as bar:
        for x0 in range(0, nx, slabs):
            x = xs[x0:x0 + slabs]
            pts = torch.cat([x.repeat_interleave(ny * nz)[:, None], yz.repeat(len(x), 1)], dim=-1)
            vals = torch.cat([sdf_fn(p).reshape(-1) for p in pts.split(chunk)])
            out[x0:x0 + len(x)] = vals.reshape(len(x), ny, nz).float().cpu().numpy()
            bar.update(len(pts))
    return out


def sdf_grid(sdf_fn: SdfFn, resolution: int, bound: float = 1.0,
             device: str | torch.device = "cpu", chunk: int = 2**18,
             progress: bool | None = None) -> np.ndarray:
    """Evaluate an SDF on the regular grid ``linspace(-bound, bound, resolution)^3``.

    Points are generated and evaluated slab by slab, `chunk` points at a time, so no tensor
    larger than `chunk` x 3 floats is ever allocated besides the float32 output volume.

    Args:
        sdf_fn: the SDF (called under `torch.no_grad`).
        resolution: R, samples per axis.
        bound: half-size of the cube.
        device: where the points are evaluated.
        chunk: points per call of `sdf_fn`.
        progress: a tqdm bar on stderr when it takes over a second (None: inside
            `progress_bars` only).

    Returns:
        (R, R, R) float32 volume indexed [x, y, z].
    """
    axis = torch.linspace(-bound, bound, int(resolution), device=device)
    return _sdf_on_axes(sdf_fn, axis, axis, axis, chunk, progress)


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


@dataclasses.dataclass
class ExtractionStats:
    """What an extraction cost.

    Attributes:
        method: "dense" or "sparse".
        resolution: R, grid samples per axis.
        sdf_evals: points the SDF was evaluated at (coarse + fine for sparse).
        dense_evals: R^3, what the dense grid costs.
        blocks: blocks in the grid (sparse; 0 for dense).
        blocks_kept: blocks evaluated densely (sparse).
        blocks_surface: kept blocks whose samples cross the level (marching cubes ran).
        seconds: wall time of SDF evaluation + marching cubes + merge.
        blocks_outside_hull: blocks the SDF rule kept but the visual hull dropped (sparse
            with a hull).
    """

    method: str
    resolution: int
    sdf_evals: int
    dense_evals: int
    blocks: int = 0
    blocks_kept: int = 0
    blocks_surface: int = 0
    seconds: float = 0.0
    blocks_outside_hull: int = 0


def keep_blocks(coarse: np.ndarray, block_diag: float, lipschitz: float = 1.5,
                level: float = 0.0, dilate: int = 1) -> np.ndarray:
    """Which blocks of a grid may hold a piece of the level set, from their corner values.

    Block (i, j, k) spans the cube between coarse samples [i, i+1] x [j, j+1] x [k, k+1].
    Marching cubes puts triangles in a fine cell only when its corners lie on both sides
    of `level` (value > level against value <= level); then the continuous SDF f equals
    `level` somewhere on one of the cell's edges, at a point p inside the block. If f is
    L-Lipschitz, every corner c of the block has |f(c) - level| <= L |c - p| <= L d, with
    d the block diagonal. So a block is dropped only when some corner has
    |f(c) - level| > `lipschitz` * d, and it is **kept** when:

    - all 8 corners satisfy |f(c) - level| <= `lipschitz` * `block_diag` (exact for an
      L-Lipschitz SDF with L <= `lipschitz`: sparse and dense extraction then agree), or
    - its corners are on both sides of `level`, or it lies within `dilate` blocks
      (26-neighbourhood) of such a block (a guard for networks steeper than `lipschitz`
      near a surface that is larger than a block), or
    - a corner value is not finite.

    Args:
        coarse: (n0 + 1, n1 + 1, n2 + 1) SDF at the block corners.
        block_diag: the diagonal of a (full) block, in the SDF's units.
        lipschitz: assumed bound on |grad f| (analytic SDFs and their CSG: 1; trained
            networks are near 1 at the surface thanks to the eikonal loss).
        level: the iso-value.
        dilate: blocks of dilation around the blocks whose corners change sign.

    Returns:
        (n0, n1, n2) bool, True for blocks to evaluate densely.
    """
    g = coarse.astype(np.float32) - np.float32(level)  # (n0+1, n1+1, n2+1)
    n0, n1, n2 = (s - 1 for s in g.shape)
    corners = [g[a:a + n0, b:b + n1, c:c + n2] for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    absmax = np.zeros((n0, n1, n2), np.float32)
    n_pos = np.zeros((n0, n1, n2), np.uint8)
    bad = np.zeros((n0, n1, n2), bool)
    for c in corners:
        np.maximum(absmax, np.abs(c), out=absmax)
        n_pos += c > 0
        bad |= ~np.isfinite(c)
    straddle = (n_pos > 0) & (n_pos < 8) & ~bad  # (n0, n1, n2)
    if dilate > 0 and straddle.any():
        from scipy import ndimage

        straddle = ndimage.binary_dilation(straddle, np.ones((3, 3, 3), bool), iterations=dilate)
    near = absmax <= np.float32(lipschitz * block_diag)  # NaN compares False: caught by bad
    return near | straddle | bad


def _merge_blocks(verts: list[np.ndarray], faces: list[np.ndarray],
                  on_face: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Join per-block meshes, merging the candidate vertices that have identical coordinates.

    Args:
        verts: per block (V_b, 3) vertices in global grid units (float32 values: a block's
            local coordinates plus its integer offset, rounded as the dense path rounds).
        faces: per block (F_b, 3) indices into that block's vertices.
        on_face: per block (V_b,) bool, the vertex may have a twin: it lies on the block's
            boundary or on a grid node.

    Returns:
        vertices (V, 3) float64 in grid units and faces (F, 3) int64; faces that the merge
        made degenerate (a repeated index) are dropped.
    """
    sizes = np.array([len(v) for v in verts], np.int64)
    base = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    V = np.concatenate(verts)  # (V, 3)
    F = np.concatenate([f.astype(np.int64) + b for f, b in zip(faces, base, strict=True)])
    cand = np.flatnonzero(np.concatenate(on_face))  # vertices that may be shared
    remap = np.arange(len(V), dtype=np.int64)
    if len(cand):
        keys = np.ascontiguousarray(V[cand]).view(np.dtype((np.void, 24))).ravel()
        _, first, inv = np.unique(keys, return_index=True, return_inverse=True)
        remap[cand] = cand[first[inv.reshape(-1)]]
    used, newid = np.unique(remap, return_inverse=True)
    F = newid.reshape(-1)[F]  # (F, 3)
    ok = (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])
    return V[used], F[ok]


def _blocks_in_region(region: VisualHull, keep: np.ndarray, coarse: np.ndarray,
                      cidx: np.ndarray, step: float, bound: float,
                      level: float) -> tuple[np.ndarray, int]:
    """Restrict the blocks `keep_blocks` kept to those meeting a hull region.

    A block is evaluated when its box meets the region and either `keep` says it may hold
    the level set, or it straddles the region's boundary with a corner at or below `level`
    (the cap of a negative region that the region cuts).

    Args:
        region: the hull's region for this grid (`VisualHull.for_grid`).
        keep: (n0, n1, n2) bool from `keep_blocks`; coarse: (n0+1, n1+1, n2+1) values.
        cidx: (n + 1,) grid index of each block corner along an axis.
        step, bound: the grid spacing and half-size.

    Returns:
        the new keep mask, and how many blocks of `keep` the region dropped.
    """
    n = keep.shape[0]
    ax = torch.as_tensor(-bound + cidx * step, dtype=torch.float32)  # (n + 1,)
    ii = torch.stack(torch.meshgrid(*(torch.arange(n),) * 3, indexing="ij"), -1).reshape(-1, 3)
    occ, total = region.cells_in_boxes(ax[ii], ax[ii + 1])
    touch = (occ > 0).cpu().numpy().reshape(keep.shape)
    edge = (occ < total).cpu().numpy().reshape(keep.shape) & touch
    g = coarse - np.float32(level)
    neg = np.zeros(keep.shape, bool)
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                neg |= g[a:a + n, b:b + n, c:c + n] <= 0
    new = touch & (keep | (edge & neg))
    return new, int((keep & ~touch).sum())


def _block_surface(vals: np.ndarray, extent: np.ndarray, origin: np.ndarray,
                   level: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marching cubes of one block of `sparse_marching_cubes`.

    Args:
        vals: (B+1, B+1, B+1) SDF samples; extent: (3,) samples per axis inside the grid;
        origin: (3,) the block's first grid index; level: the iso-value.

    Returns:
        vertices (V_b, 3) float64 in global grid units, faces (F_b, 3), and (V_b,) bool:
        the merge candidates.
    """
    from skimage import measure

    e = extent
    v, f, _, _ = measure.marching_cubes(vals[:e[0], :e[1], :e[2]], level=level,
                                        gradient_direction="descent")
    # global grid units rounded to float32 like the dense path's vertices: a vertex at a
    # node can come out at local 0 + 1e-15 in one block and at B in the next
    lo = origin.astype(np.float32)
    gv = v + lo  # (V_b, 3) float32
    # merge candidates: on the block's boundary (shared with a neighbour), or on a grid node
    # (sdf == level there: scikit-image emits one vertex per edge)
    face = ((gv == lo) | (gv == lo + (e - 1))).any(1) | (gv == np.round(gv)).all(1)
    return gv.astype(np.float64), f, face


def _block_values(sdf_fn: SdfFn, axis: Tensor, blocks: Tensor, B: int, chunk: int,
                  region: VisualHull | None) -> np.ndarray:
    """The SDF on the (B + 1)^3 grid samples of each block of `sparse_marching_cubes`.

    Args:
        axis: (R,) the grid's coordinates; blocks: (m, 3) block indices; B: cells a block.
        region: samples outside it read as far outside (None: no hull).

    Returns:
        (m, B + 1, B + 1, B + 1) float32, non-finite values read as far outside; indices
        past the grid's end repeat its last sample.
    """
    ar = torch.arange(B + 1, device=axis.device)
    idx = (blocks[:, :, None] * B + ar).clamp_max(len(axis) - 1)  # (m, 3, B+1)
    c = axis[idx]  # (m, 3, B+1)
    pts = torch.stack(torch.broadcast_tensors(c[:, 0, :, None, None], c[:, 1, None, :, None],
                                              c[:, 2, None, None, :]), dim=-1)
    pts = pts.reshape(-1, 3)  # (m * (B+1)^3, 3)
    with torch.no_grad():
        vals = torch.cat([sdf_fn(p).reshape(-1) for p in pts.split(chunk)])
        if region is not None:
            vals = torch.where(region.contains(pts).to(vals.device), vals.float(),
                               float(_NONFINITE))
    vals = vals.float().cpu().numpy().reshape(len(blocks), B + 1, B + 1, B + 1)
    vals[~np.isfinite(vals)] = _NONFINITE
    return vals


def sparse_marching_cubes(sdf_fn: SdfFn, resolution: int, bound: float = 1.0,
                          device: str | torch.device = "cpu",
                          chunk: int = 2**18, block: int = 8, lipschitz: float = 1.5,
                          dilate: int = 1, hull: VisualHull | None = None,
                          progress: bool | None = None
                          ) -> tuple[np.ndarray, np.ndarray, ExtractionStats]:
    """Marching cubes of an SDF's zero level set on ``linspace(-bound, bound, R)^3``, evaluated
    near the surface.

    1. The SDF at every `block`-th grid sample per axis (the last sample always included):
       ((R - 1) / block + 1)^3 evaluations.
    2. `keep_blocks` picks the blocks that may hold the surface.
    3. Kept blocks are evaluated on their (block + 1)^3 grid samples (one sample of overlap
       with each neighbour; blocks at the far end are cut to the grid), in batches of at
       most `chunk` points on `device`; the grid coordinates are the dense path's own, so a
       sample has the same value in both paths.
    4. scikit-image marching cubes per block that crosses `level`; vertices on shared block
       faces come from the same grid edge and values in both blocks, hence have identical
       coordinates (float32 grid units, as the dense path's), and are merged exactly.

    With a visual `hull`, only blocks that meet ``hull.for_grid(step)`` are evaluated, and
    samples outside it read as far outside (+1e3): nothing is exported outside (a negative
    region that leaks out is capped at its boundary). Inside the carved hull the mesh is the
    one without a hull: every grid cube that meets it has all its corners in the region.

    Memory: the coarse grid, one batch of blocks and the mesh; never the R^3 volume.
    Args:
        sdf_fn: the SDF, (P, 3) -> (P,) or (P, 1) (called under `torch.no_grad`).
        resolution: R, samples per axis.
        bound: half-size of the cube.
        device: where points are evaluated.
        chunk: the most points per call of `sdf_fn`.
        block: cells per block edge.
        lipschitz, dilate: the block rule (see `keep_blocks`).
        hull: optional visual hull: evaluate and export only inside it.
        progress: a tqdm bar on stderr (blocks done) when it takes over a second (None:
            inside `progress_bars` only).

    Returns:
        vertices (V, 3) float64 (normalised frame), faces (F, 3) int64, `ExtractionStats`.

    Raises:
        NeusL0Error: when no block crosses 0 (no surface inside the cube).
    """
    level = 0.0
    t0 = time.perf_counter()
    R, B = int(resolution), int(block)
    if R < 2 or B < 1:
        raise NeusL0Error(f"resolution {R} and block {B}: need resolution >= 2 and block >= 1")
    cells = R - 1
    nb = -(-cells // B)  # blocks per axis
    step = 2.0 * bound / cells
    axis = torch.linspace(-bound, bound, R, device=device)  # the dense path's coordinates
    cidx = torch.as_tensor(np.minimum(np.arange(nb + 1) * B, cells), device=device)
    ca = axis[cidx]
    coarse = _sdf_on_axes(sdf_fn, ca, ca, ca, chunk)  # (nb+1, nb+1, nb+1)
    evals = (nb + 1) ** 3
    keep = keep_blocks(coarse, math.sqrt(3.0) * B * step, lipschitz, level, dilate)
    region, n_outside = None, 0
    if hull is not None:
        region = hull.for_grid(step)
        keep, n_outside = _blocks_in_region(region, keep, coarse, cidx.cpu().numpy(),
                                            step, bound, level)
    kept = np.argwhere(keep)  # (K, 3)
    del coarse
    verts, faces, on_face, evals_kept, n_surface = _march_blocks(
        sdf_fn, axis, kept, (B, cells), chunk, region, _bar(progress, len(kept),
                                                            f"marching cubes {R}^3", "block"))
    evals += evals_kept
    if not verts:
        raise NeusL0Error(f"no surface: the SDF does not cross {level} inside the cube "
                          f"[-{bound}, {bound}]^3 (sparse extraction at {R}^3)")
    V, F = _merge_blocks(verts, faces, on_face)
    stats = ExtractionStats("sparse", R, evals, R**3, nb**3, len(kept), n_surface,
                            time.perf_counter() - t0, n_outside)
    return V * step - bound, F, stats


def _march_blocks(sdf_fn: SdfFn, axis: Tensor, kept: np.ndarray, shape: tuple[int, int],
                  chunk: int, region, bar) -> tuple[list, list, list, int, int]:
    """The kept blocks' marching cubes, in batches of at most `chunk` points.

    Args:
        axis: (R,) the grid coordinates; kept: (K, 3) block indices; shape: (block, cells).
        region: the hull's region for the grid, or None; bar: the progress bar.

    Returns:
        per crossing block its grid-unit vertices, faces and shared-face flags; the SDF
        evaluations made; the number of blocks that cross 0.
    """
    B, cells = shape
    extent = np.minimum(B, cells - kept * B) + 1  # (K, 3) samples per axis in each block
    m = max(1, chunk // (B + 1) ** 3)  # blocks per batch
    verts, faces, on_face = [], [], []
    evals = n_surface = 0
    for s in range(0, len(kept), m):
        bi = torch.as_tensor(kept[s:s + m], device=axis.device)  # (m, 3)
        vals = _block_values(sdf_fn, axis, bi, B, chunk, region)
        evals += vals.size
        # clamped samples repeat the last layer, so min/max over the padded block are exact
        g = vals.reshape(len(bi), -1)
        cross = (g.max(1) > 0.0) & (g.min(1) <= 0.0)  # (m,)
        for j in np.flatnonzero(cross):
            gv, f, face = _block_surface(vals[j], extent[s + j], kept[s + j] * B, 0.0)
            verts.append(gv)
            faces.append(f)
            on_face.append(face)
        n_surface += int(cross.sum())
        bar.update(len(bi))
    bar.close()
    return verts, faces, on_face, evals, n_surface


#: `clean_mesh` keeps the pieces whose bounding-box diagonal is at least this fraction of
#: the main piece's (the one with the most faces): floating specks go, and only they. On
#: pits-and-thin meshed at 128 the grid cut the r 1 rod (and once a fin with the r 6 rod)
#: off the body in pieces of 7.5-18 % of its diagonal, which stay; the floaters beside them
#: measured 0.2-2.7 % (docs/BENCHMARKS.md, "Where does the error live").
MIN_PIECE_DIAGONAL = 0.05


def _diagonal(mesh: trimesh.Trimesh) -> float:
    lo, hi = mesh.bounds
    return float(np.linalg.norm(hi - lo))


def clean_mesh(mesh: trimesh.Trimesh,
               min_diagonal: float = MIN_PIECE_DIAGONAL) -> trimesh.Trimesh:
    """Drop floating specks: the connected pieces whose bounding-box diagonal is below
    `min_diagonal` times the main piece's (the piece with the most faces, always kept).

    Args:
        mesh: the mesh.
        min_diagonal: the fraction (0 keeps every piece; 1 keeps the main piece and any as
            long as it).

    Returns:
        the cleaned mesh (vertex colours kept).
    """
    parts = mesh.split(only_watertight=False)
    if len(parts) <= 1:
        return mesh
    main = int(np.argmax([len(p.faces) for p in parts]))
    reach = min_diagonal * _diagonal(parts[main])
    keep = [p for k, p in enumerate(parts) if k == main or _diagonal(p) >= reach]
    return keep[0] if len(keep) == 1 else trimesh.util.concatenate(keep)


def vertex_colors(model, vertices: np.ndarray, device: str | torch.device = "cpu",
                  chunk: int = 2**16) -> np.ndarray:
    """Colours from the colour network, looking along the inward normal (view = -normal).

    Args:
        model: a `neus_l0.fields.model.NeuSModel`.
        vertices: (V, 3) in the normalised frame.

    Returns:
        (V, 4) uint8 RGBA.
    """
    from neus_l0.fields.sdf import sdf_and_gradient

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
                 chunk: int = 2**18, method: str = "auto",
                 hull: VisualHull | None = None) -> trimesh.Trimesh:
    """The trained SDF's zero level set in world units.

    Args:
        model: a `neus_l0.fields.model.NeuSModel` (only `sdf`, and `color` when `colors`).
        scale_mat: (4, 4) normalised -> world.
        resolution: grid samples per axis over [-bound, bound].
        clean: drop floating specks (`clean_mesh`: pieces much smaller than the main one).
        colors: vertex colours from the colour network.
        device, chunk: where and how many points at a time the SDF is evaluated.
        method: "dense" (the whole grid), "sparse" (`sparse_marching_cubes`) or "auto"
            (sparse above `SPARSE_ABOVE` samples per axis).
        hull: optional `neus_l0.bounds.hull.VisualHull` (normalised frame): nothing is exported
            outside ``hull.for_grid(step)`` (see `sparse_marching_cubes`; the dense path
            reads samples outside it as far outside too).

    Inside `progress_bars`, the SDF's evaluation shows a tqdm bar on stderr when it takes
    over a second.

    Returns:
        the mesh in world units; ``mesh.metadata["extraction"]`` holds the
        `ExtractionStats` as a dict (method, SDF evaluations, seconds, ...).
    """
    if method not in ("auto", "dense", "sparse"):
        raise NeusL0Error(f"mesh method '{method}': use auto, dense or sparse")
    if method == "auto":
        method = "sparse" if resolution > SPARSE_ABOVE else "dense"

    def f(p: Tensor) -> Tensor:
        return model.sdf.sdf(p)

    if method == "sparse":
        verts, faces, stats = sparse_marching_cubes(f, resolution, bound, device=device,
                                                    chunk=chunk, hull=hull)
    else:
        t0 = time.perf_counter()
        g = f
        if hull is not None:
            region = hull.for_grid(2.0 * bound / (int(resolution) - 1))

            def g(p: Tensor) -> Tensor:
                v = f(p).reshape(-1).float()
                return torch.where(region.contains(p).to(v.device), v, float(_NONFINITE))

        verts, faces = marching_cubes(sdf_grid(g, resolution, bound, device, chunk), bound)
        R = int(resolution)
        stats = ExtractionStats("dense", R, R**3, R**3, seconds=time.perf_counter() - t0)
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if clean:
        mesh = clean_mesh(mesh)
    if colors:
        mesh.visual.vertex_colors = vertex_colors(model, np.asarray(mesh.vertices), device)
    mesh.vertices = to_world(np.asarray(mesh.vertices), scale_mat)
    mesh.metadata["extraction"] = dataclasses.asdict(stats)
    return mesh


#: Mesh file formats `export_mesh` writes, by suffix: PLY and GLB keep vertex colours (GLB is
#: what web viewers and Blender import; it stores float32 positions), OBJ, STL and OFF keep
#: the geometry.
MESH_FORMATS = ("ply", "obj", "glb", "stl", "off")


def export_mesh(mesh: trimesh.Trimesh, path: str | Path) -> Path:
    """Write a mesh file atomically, its format from the suffix (`MESH_FORMATS`)."""
    path = Path(path)
    kind = path.suffix.lower().lstrip(".")
    if kind not in MESH_FORMATS:
        raise NeusL0Error(f"{path}: unsupported mesh format '.{kind}' "
                          f"(use {', '.join('.' + k for k in MESH_FORMATS)})")
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=kind)
    return path
