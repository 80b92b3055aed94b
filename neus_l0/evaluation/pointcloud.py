"""Point clouds from meshes, as the DTU evaluation does it.

`sample_mesh` puts a regular grid of points on every triangle (spacing about `density` along
both edges that leave the first vertex) and adds the mesh's vertices; `thin_points` then
keeps a subset in which no two points are closer than `radius` (greedy in a seeded random
order). Both work in bounded-size chunks so that multi-million-point clouds fit in memory.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

#: Upper bound on the number of candidate grid points handled at once in `sample_mesh`.
SAMPLE_CHUNK = 4_000_000
#: Number of points (in x order) per slab when building the radius graph in `thin_points`.
THIN_SLAB = 1_000_000
#: Peak host memory of sampling, thinning and scoring, bytes per sampled point, besides
#: `SAMPLE_FIXED_BYTES` (the measured per-point peak falls as the fixed part is spread over
#: more points; docs/benchmarks/mesh.md, "Numbers moved from code comments").
BYTES_PER_SAMPLE = 128
#: Fixed part of that peak (one `SAMPLE_CHUNK` of candidates, the k-d trees' overheads).
SAMPLE_FIXED_BYTES = 512 * 2**20


def expected_samples(vertices: np.ndarray, faces: np.ndarray, density: float) -> float:
    """About how many points `sample_mesh` returns: V + area / density^2 (an upper bound
    up to rounding, so a memory check on it errs on the safe side; docs/benchmarks/mesh.md,
    "Numbers moved from code comments")."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                                      axis=-1).sum())
    return len(vertices) + area / float(density) ** 2


def sampling_bytes(n_points: float) -> float:
    """Estimated peak host memory (bytes) of sampling, thinning and scoring `n_points`."""
    return SAMPLE_FIXED_BYTES + BYTES_PER_SAMPLE * n_points


def triangle_grid_counts(tri: np.ndarray, density: float) -> tuple[np.ndarray, np.ndarray]:
    """Grid sizes (n1, n2) per triangle for DTU-style sampling.

    With e1 = v1 - v0, e2 = v2 - v0, l1 = |e1|, l2 = |e2| and A2 = |e1 x e2| (twice the
    area), the step is `thr = density * sqrt(l1 * l2 / A2)` (the spacing grows by
    1/sqrt(sin angle) so that the point density per area stays ~1/density^2), and
    n1 = floor(l1 / thr), n2 = floor(l2 / thr). Degenerate triangles get (0, 0).

    Args:
        tri: (F, 3, 3) triangle vertex positions.
        density: target spacing in world units (> 0).

    Returns:
        n1, n2: (F,) int64 grid sizes.
    """
    e1 = tri[:, 1] - tri[:, 0]  # (F, 3)
    e2 = tri[:, 2] - tri[:, 0]  # (F, 3)
    l1 = np.linalg.norm(e1, axis=-1)
    l2 = np.linalg.norm(e2, axis=-1)
    area2 = np.linalg.norm(np.cross(e1, e2), axis=-1)
    ok = area2 > 0
    n1 = np.zeros(len(tri), dtype=np.int64)
    n2 = np.zeros(len(tri), dtype=np.int64)
    thr = density * np.sqrt(l1[ok] * l2[ok] / area2[ok])
    n1[ok] = np.floor(l1[ok] / thr).astype(np.int64)
    n2[ok] = np.floor(l2[ok] / thr).astype(np.int64)
    return n1, n2


def _sample_chunk(tri: np.ndarray, n1: np.ndarray, n2: np.ndarray) -> np.ndarray:
    """Grid points on a chunk of triangles (all with n1, n2 >= 1).

    Candidate (i, j) in [0, n1] x [0, n2] gives barycentric-like coordinates
    u = (i + 0.5) / n1, v = (j + 0.5) / n2; it is kept when u + v < 1 and becomes
    v0 + u e1 + v e2.

    Args:
        tri: (F, 3, 3) triangles.
        n1, n2: (F,) grid sizes, >= 1.

    Returns:
        (M, 3) points.
    """
    cols = n2 + 1
    counts = (n1 + 1) * cols  # (F,)
    tri_idx = np.repeat(np.arange(len(tri)), counts)  # (C,)
    starts = np.cumsum(counts) - counts
    k = np.arange(int(counts.sum()), dtype=np.int64) - starts[tri_idx]  # local index
    c = cols[tri_idx]
    u = (k // c + 0.5) / n1[tri_idx]
    v = (k % c + 0.5) / n2[tri_idx]
    keep = (u + v) < 1.0
    tri_idx, u, v = tri_idx[keep], u[keep, None], v[keep, None]
    t = tri[tri_idx]  # (M, 3, 3)
    return t[:, 0] + u * (t[:, 1] - t[:, 0]) + v * (t[:, 2] - t[:, 0])


def sample_mesh(vertices: np.ndarray, faces: np.ndarray, density: float = 0.2,
                chunk: int = SAMPLE_CHUNK,
                progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Sample a triangle mesh as the DTU evaluation does: per-triangle grids plus vertices.

    Args:
        vertices: (V, 3) vertex positions (world units).
        faces: (F, 3) integer vertex indices.
        density: grid spacing in world units (DTU: 0.2 mm).
        chunk: at most this many candidate grid points are materialised at once (a single
            triangle that needs more is still done in one piece).
        progress: called with the number of points each chunk adds (a progress bar).

    Returns:
        (V + M, 3) float64: all vertices followed by the grid points.
    """
    if density <= 0:
        raise ValueError(f"density must be positive, got {density}")
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    out = [vertices]
    n_faces = len(faces)
    face_step = max(1, chunk // 8)
    for f0 in range(0, n_faces, face_step):
        tri = vertices[faces[f0:f0 + face_step]]  # (f, 3, 3)
        n1, n2 = triangle_grid_counts(tri, density)
        ok = (n1 > 0) & (n2 > 0)
        tri, n1, n2 = tri[ok], n1[ok], n2[ok]
        if len(tri) == 0:
            continue
        cum = np.cumsum((n1 + 1) * (n2 + 1))
        start = 0
        while start < len(tri):
            base = cum[start - 1] if start > 0 else 0
            stop = int(np.searchsorted(cum, base + chunk, side="right"))
            stop = max(stop, start + 1)
            out.append(_sample_chunk(tri[start:stop], n1[start:stop], n2[start:stop]))
            if progress is not None:
                progress(len(out[-1]))
            start = stop
    return np.concatenate(out, axis=0)


def radius_pairs(points: np.ndarray, radius: float, slab: int = THIN_SLAB,
                 progress: Callable[[int], None] | None = None) -> np.ndarray:
    """All index pairs (i, j), i != j, with |p_i - p_j| <= radius, each pair once.

    Built slab by slab along x (each slab's tree holds its points plus the next `radius`
    of x), so peak memory is one slab's tree plus the int32 pair list.

    Args:
        points: (N, 3) positions.
        radius: pair distance bound.
        slab: points per slab.
        progress: called with the number of points of each slab done (a progress bar).

    Returns:
        (P, 2) int32 (int64 when N >= 2^31) indices into `points`.
    """
    n = len(points)
    idx_dtype = np.int32 if n < 2**31 - 1 else np.int64
    if n < 2:
        return np.zeros((0, 2), dtype=idx_dtype)
    order = np.argsort(points[:, 0], kind="stable")
    xs = points[order, 0]
    chunks = []
    for s in range(0, n, slab):
        e = min(s + slab, n)
        stop = int(np.searchsorted(xs, xs[e - 1] + radius, side="right"))
        cand = order[s:stop]
        pairs = cKDTree(points[cand]).query_pairs(radius, output_type="ndarray")
        if progress is not None:
            progress(e - s)
        if len(pairs) == 0:
            continue
        # A pair with both ends beyond the core [s, e) belongs to a later slab.
        core = (pairs < (e - s)).any(axis=1)
        chunks.append(cand[pairs[core]].astype(idx_dtype))
    if not chunks:
        return np.zeros((0, 2), dtype=idx_dtype)
    return np.concatenate(chunks, axis=0)


def thin_points(points: np.ndarray, radius: float = 0.2, seed: int | None = 0,
                slab: int = THIN_SLAB,
                progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Radius-based down-sampling: greedy in a random order, as DTU's Python port does.

    Visit the points in a random order (a permutation drawn from `seed`); a point is kept
    unless a point kept earlier lies within `radius` of it. The result is computed by the
    equivalent parallel rounds (each round keeps every undecided point that has no
    undecided earlier neighbour and drops the later neighbours of those), which gives the
    same set as the sequential loop.

    Args:
        points: (N, 3) positions.
        radius: minimum spacing of the kept points (DTU: 0.2 mm).
        seed: seed of the visiting order (`None`: fresh entropy).
        slab: points per slab when building the radius graph (memory bound).
        progress: called with the number of points of each slab of the radius graph done.

    Returns:
        (M, 3) float64 kept points, in their input order.
    """
    points = np.asarray(points, dtype=np.float64)
    keep = thin_mask(points, radius, seed=seed, slab=slab, progress=progress)
    return points[keep]


def thin_mask(points: np.ndarray, radius: float = 0.2, seed: int | None = 0,
              slab: int = THIN_SLAB,
              progress: Callable[[int], None] | None = None) -> np.ndarray:
    """The boolean mask (N,) of the points `thin_points` keeps (see there)."""
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=bool)
    rng = np.random.default_rng(seed)
    prio = np.empty(n, dtype=np.int64)
    prio[rng.permutation(n)] = np.arange(n)  # visiting rank of each point
    pairs = radius_pairs(points, radius, slab=slab, progress=progress)
    a, b = pairs[:, 0], pairs[:, 1]
    swap = prio[a] > prio[b]
    a, b = np.where(swap, b, a), np.where(swap, a, b)  # a is visited before b
    del pairs, swap
    state = np.zeros(n, dtype=np.int8)  # 0 undecided, 1 kept, 2 dropped
    while len(a):
        blocked = np.zeros(n, dtype=bool)
        blocked[b] = True  # has an undecided earlier neighbour
        new = (state == 0) & ~blocked
        state[new] = 1
        state[b[new[a]]] = 2
        alive = (state[a] == 0) & (state[b] == 0)
        a, b = a[alive], b[alive]
    return state != 2
