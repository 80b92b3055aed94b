"""Exact unsigned distance from points to a triangle mesh's surface (point-to-triangle).

`MeshDistance` indexes a mesh once and answers chunked queries. The distance of a point q
to a triangle is the distance to its closest point: the orthogonal projection onto the
triangle's plane when that lies inside the triangle, else the nearest point of its three
edges (degenerate triangles, with zero area, are just their edges). It is exact in
float64; no sampling of the mesh is involved.

Candidate triangles come from k-d trees of the triangle centroids c_t, with
R_t = max_i |v_i - c_t| (so |q - c_t| - R_t <= dist(q, t)). The triangles are grouped by
R_t into classes a factor of two apart (small classes join the next larger one; class
bound R_k = the largest R_t in it); in each
class the k nearest centroids of every query point are tested (k = 8, doubled while the
k-th centroid is within `cap + R_k`, `cap` being the smallest distance found so far, or
before that the distance to the nearest vertex or centroid), so the minimum is exact:
every triangle left out has |q - c_t| - R_t > cap >= the true distance.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from neus_l0.errors import NeusL0Error

#: Query points handled per chunk.
QUERY_CHUNK = 262_144
#: Upper bound on the (point, triangle) candidate pairs held at once.
PAIR_BUDGET = 524_288
#: Nearest centroids tested per class in the first round.
K_START = 8
#: Size classes with fewer triangles than this (or F / 64) join the next larger class.
MIN_CLASS = 1024


def point_triangle_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray,
                            c: np.ndarray) -> np.ndarray:
    """Exact distance of each point to its paired triangle (row-wise).

    Args:
        points: (P, 3) query points.
        a, b, c: (P, 3) the corners of the triangle paired with each point.

    Returns:
        (P,) float64 distances. Degenerate triangles (zero area) are their edges.
    """
    q = np.asarray(points, dtype=np.float64)
    e1, e2, w = b - a, c - a, q - a
    n = np.cross(e1, e2)
    nn = np.einsum("ij,ij->i", n, n)
    ok = nn > 0
    inv = np.where(ok, 1.0 / np.where(ok, nn, 1.0), 0.0)
    s = np.einsum("ij,ij->i", np.cross(w, e2), n) * inv  # coefficient of e1
    t = np.einsum("ij,ij->i", np.cross(e1, w), n) * inv  # coefficient of e2
    inside = ok & (s >= 0) & (t >= 0) & (s + t <= 1)
    d2 = np.full(len(q), np.inf)
    d2[inside] = np.einsum("ij,ij->i", w[inside], n[inside]) ** 2 * inv[inside]
    out = ~inside
    if out.any():
        qo = q[out]
        d2[out] = np.minimum(np.minimum(_segment_dist2(qo, a[out], b[out]),
                                        _segment_dist2(qo, b[out], c[out])),
                             _segment_dist2(qo, c[out], a[out]))
    return np.sqrt(d2)


def _segment_dist2(q: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """(P,) squared distance of q (P, 3) to the segments p0-p1 (P, 3) (a point if p0 == p1)."""
    e = p1 - p0
    ee = np.einsum("ij,ij->i", e, e)
    u = np.einsum("ij,ij->i", q - p0, e) / np.where(ee > 0, ee, 1.0)
    u = np.clip(u, 0.0, 1.0)
    r = q - p0 - u[:, None] * e
    return np.einsum("ij,ij->i", r, r)


class MeshDistance:
    """A triangle mesh indexed for exact point-to-surface distance queries.

    Args:
        vertices: (V, 3) finite vertex positions.
        faces: (F, 3) vertex indices (F may be 0: every distance is then `inf`).

    Raises:
        NeusL0Error: bad shapes, non-finite vertices or face indices out of range.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3:
            raise NeusL0Error(f"mesh distance: vertices must be (V, 3), got shape {v.shape}")
        if f.size == 0:
            f = np.zeros((0, 3), dtype=np.int64)
        if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
            raise NeusL0Error(f"mesh distance: faces must be (F, 3) integers, got {f.shape} "
                              f"{f.dtype}")
        if len(f) and (f.min() < 0 or f.max() >= len(v)):
            raise NeusL0Error(f"mesh distance: face indices outside 0..{len(v) - 1}")
        if not np.isfinite(v).all():
            raise NeusL0Error("mesh distance: non-finite vertex coordinates")
        self.triangles = v[f.astype(np.int64)]  # (F, 3, 3)
        cen = self.triangles.mean(axis=1)  # (F, 3)
        rad = np.linalg.norm(self.triangles - cen[:, None], axis=-1).max(axis=1)  # (F,)
        _, expo = np.frexp(rad)  # rad < 2 ** expo: classes a factor of two apart
        # Small classes join the next larger one (each class costs a k-NN pass per point;
        # a larger R_k is still a valid bound, only looser).
        min_size = max(MIN_CLASS, len(f) // 64)
        groups: list[np.ndarray] = []
        pending: list[np.ndarray] = []
        for e in np.unique(expo):
            pending.append(np.flatnonzero(expo == e))
            if sum(map(len, pending)) >= min_size:
                groups.append(np.concatenate(pending))
                pending = []
        if pending:
            groups = groups[:-1] + [np.concatenate(groups[-1:] + pending)]
        self.classes = []  # (tree over centroids, face ids (F_k,), radii (F_k,), R_k)
        for ids in groups:
            self.classes.append((cKDTree(cen[ids]), ids, rad[ids], float(rad[ids].max())))
        # Points on the surface (used vertices and centroids): the nearest one bounds the
        # distance from above before any triangle is tested.
        used = np.unique(f.ravel()).astype(np.int64)
        self._samples = cKDTree(np.concatenate([v[used], cen]))

    @property
    def n_faces(self) -> int:
        """Number of triangles."""
        return len(self.triangles)

    def query(self, points: np.ndarray, upper_bound: float = math.inf,
              chunk: int = QUERY_CHUNK, workers: int = -1) -> np.ndarray:
        """Exact distance of each point to the mesh surface.

        Args:
            points: (N, 3) query points.
            upper_bound: distances >= this bound come back as `inf` (faster queries), as
                `chamfer.nearest_distances` does.
            chunk: query points per chunk (memory bound, with `PAIR_BUDGET`).
            workers: k-d tree query threads (-1: all cores).

        Returns:
            (N,) float64 distances; all `inf` for a mesh without faces.

        Raises:
            NeusL0Error: points not (N, 3) or not finite.
        """
        q = np.asarray(points, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != 3:
            raise NeusL0Error(f"mesh distance: points must be (N, 3), got shape {q.shape}")
        if not np.isfinite(q).all():
            raise NeusL0Error("mesh distance: non-finite query points")
        if not upper_bound > 0:
            raise NeusL0Error(f"mesh distance: upper bound must be positive, got {upper_bound}")
        out = np.full(len(q), np.inf)
        if self.n_faces == 0:
            return out
        for s in range(0, len(q), chunk):
            qc = q[s:s + chunk]
            d0, _ = self._samples.query(qc, k=1, distance_upper_bound=upper_bound,
                                        workers=workers)
            cap0 = np.minimum(d0, upper_bound)  # >= the exact distance, or >= upper_bound
            best = np.full(len(qc), np.inf)
            for cls in self.classes:
                self._query_class(qc, best, cap0, cls, upper_bound, workers)
            out[s:s + chunk] = np.where(best < upper_bound, best, np.inf)
        return out

    def _query_class(self, q: np.ndarray, best: np.ndarray, cap0: np.ndarray, cls: tuple,
                     ub: float, workers: int) -> None:
        """Lower `best` (n,) in place with the exact distances to one class's triangles.

        Only triangles whose lower bound |q - c_t| - R_t is <= min(best, cap0) can matter
        (cap0 (n,): an upper bound of each point's distance, capped at `ub`).
        """
        tree, ids, rad, r_k = cls
        n_cls = len(ids)
        bound = ub + r_k  # centroids farther than this cannot bring a distance < ub
        idx = np.arange(len(q))
        k_prev, k = 0, min(K_START, n_cls)
        while len(idx):
            more = []
            step = max(1, PAIR_BUDGET // k)
            for s in range(0, len(idx), step):
                sub = idx[s:s + step]
                dc, ic = tree.query(q[sub], k=k, distance_upper_bound=bound, workers=workers)
                dc, ic = dc.reshape(len(sub), k), ic.reshape(len(sub), k)
                dc, ic = dc[:, k_prev:], ic[:, k_prev:]  # only the centroids not yet tested
                cap = np.minimum(best[sub], cap0[sub])  # (m,)
                found = np.isfinite(dc)
                jc = np.where(found, ic, 0)
                test = found & (dc - rad[jc] <= cap[:, None])
                row, col = np.nonzero(test)
                if len(row):
                    tri = self.triangles[ids[jc[row, col]]]  # (P, 3, 3)
                    d = point_triangle_distance(q[sub[row]], tri[:, 0], tri[:, 1], tri[:, 2])
                    first = np.flatnonzero(np.r_[True, row[1:] != row[:-1]])  # row sorted
                    hit = sub[row[first]]
                    best[hit] = np.minimum(best[hit], np.minimum.reduceat(d, first))
                last = dc[:, -1]  # the k-th nearest centroid (inf: fewer within bound)
                more.append(sub[np.isfinite(last)
                                & (last - r_k <= np.minimum(best[sub], cap0[sub]))])
            if k >= n_cls:
                break
            idx = np.concatenate(more)
            k_prev, k = k, min(2 * k, n_cls)


def point_mesh_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                        upper_bound: float = math.inf, workers: int = -1) -> np.ndarray:
    """Exact distance of each point (N, 3) to the surface of the mesh (V, 3), (F, 3).

    One-shot form of `MeshDistance(vertices, faces).query(points, upper_bound)`: (N,)
    float64, `inf` where the distance is >= `upper_bound` or the mesh has no faces.
    """
    return MeshDistance(vertices, faces).query(points, upper_bound, workers=workers)
