"""Triangle meshes as renderable surfaces: a vectorised z-buffer rasteriser in torch.

Per view and sub-pixel shift, every triangle is expanded into the pixel centres of its
bounding box (no Python loop over triangles or pixels), tested with edge functions, and the
nearest one per pixel wins (``scatter_reduce`` with ``amin`` on camera-z depth). The hit
distance and the barycentrics are then recomputed exactly by intersecting each pixel's ray
with its winning triangle (Moller-Trumbore), and the normal interpolates the vertex normals.
Triangles are two-sided (scans such as the Stanford bunny are open).
"""

from __future__ import annotations

import numpy as np
import torch

from neus_l0.synthetic.raycast import RayGrid

Tensor = torch.Tensor


class MeshSurface:
    """A triangle mesh (world units) that `neus_l0.synthetic.raycast.render_views` can draw.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) vertex indices.
        max_pairs: (triangle, pixel) candidates processed per batch (bounds memory).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, max_pairs: int = 1 << 22):
        import trimesh

        mesh = trimesh.Trimesh(vertices, faces, process=False)
        self.vertices = torch.as_tensor(np.asarray(vertices), dtype=torch.float64)
        self.faces = torch.as_tensor(np.asarray(faces), dtype=torch.int64)
        self.vertex_normals = torch.as_tensor(np.array(mesh.vertex_normals),
                                              dtype=torch.float64)
        self.max_pairs = max_pairs

    def intersect_grid(self, rays: RayGrid) -> tuple[Tensor, Tensor]:
        """First hits: t (V, S, H*W) (``inf`` on a miss) and unit normals (V, S, H*W, 3)."""
        V, S, HW, _ = rays.origins.shape
        t = torch.full((V, S, HW), float("inf"))
        n = torch.zeros((V, S, HW, 3))
        for v in range(V):
            w2c = torch.linalg.inv(rays.c2w[v].double())
            cam = self.vertices @ w2c[:3, :3].T + w2c[:3, 3]  # (NV, 3) camera coordinates
            K = rays.K[v].double()
            for s in range(S):
                face = self._rasterise(cam, K, rays.shifts[s].double(), rays.height,
                                       rays.width)  # (HW,) winning face or -1
                pix = torch.nonzero(face >= 0).squeeze(-1)
                if pix.numel() == 0:
                    continue
                o = rays.origins[v, s, pix].double()
                d = rays.dirs[v, s, pix].double()
                tt, bary = self._ray_triangle(o, d, face[pix])
                t[v, s, pix] = tt.float()
                vn = self.vertex_normals[self.faces[face[pix]]]  # (P, 3, 3)
                nn = (bary[..., None] * vn).sum(1)
                n[v, s, pix] = (nn / nn.norm(dim=-1, keepdim=True).clamp_min(1e-12)).float()
        return t, n

    def _rasterise(self, cam: Tensor, K: Tensor, shift: Tensor, H: int, W: int) -> Tensor:
        """(H*W,) index of the nearest face covering each (shifted) pixel centre, or -1."""
        tri = cam[self.faces]  # (F, 3, 3)
        z = tri[..., 2]  # (F, 3)
        ok = (z > 1e-6).all(-1)
        fid = torch.nonzero(ok).squeeze(-1)
        tri, z = tri[fid], z[fid]
        uv = (tri @ K.T)[..., :2] / z[..., None] - shift  # (F', 3, 2) pixel coordinates
        lo = torch.ceil(uv.min(1).values).clamp_min(0)
        hi = torch.floor(uv.max(1).values)
        hi = torch.minimum(hi, torch.tensor([W - 1.0, H - 1.0], dtype=hi.dtype))
        span = (hi - lo + 1).clamp_min(0).long()  # (F', 2)
        count = span[:, 0] * span[:, 1]
        keep = torch.nonzero(count > 0).squeeze(-1)
        fid, uv, z, lo, span, count = (a[keep] for a in (fid, uv, z, lo, span, count))
        zbuf = torch.full((H * W,), float("inf"), dtype=torch.float64)
        best = torch.full((H * W,), -1, dtype=torch.int64)
        # batches of faces whose candidate pairs fit in max_pairs
        csum = torch.cumsum(count, 0)
        start = 0
        while start < fid.numel():
            base = csum[start - 1] if start > 0 else 0
            stop = int(torch.searchsorted(csum, base + self.max_pairs, right=True))
            stop = max(stop, start + 1)
            sl = slice(start, stop)
            self._rasterise_batch(fid[sl], uv[sl], z[sl], lo[sl], span[sl], count[sl],
                                  W, zbuf, best)
            start = stop
        return best

    @staticmethod
    def _rasterise_batch(fid, uv, z, lo, span, count, W, zbuf, best) -> None:
        rep = torch.repeat_interleave(torch.arange(fid.numel()), count)  # (P,) face of pair
        first = torch.cumsum(count, 0) - count
        k = torch.arange(rep.numel()) - first[rep]  # (P,) index inside the face's box
        px = lo[rep, 0] + (k % span[rep, 0]).double()
        py = lo[rep, 1] + (k // span[rep, 0]).double()
        a, b, c = uv[rep, 0], uv[rep, 1], uv[rep, 2]  # (P, 2)

        def edge(p, q, x, y):
            return (q[:, 0] - p[:, 0]) * (y - p[:, 1]) - (q[:, 1] - p[:, 1]) * (x - p[:, 0])

        area = edge(a, b, c[:, 0], c[:, 1])
        w0 = edge(b, c, px, py) / area
        w1 = edge(c, a, px, py) / area
        w2 = 1.0 - w0 - w1
        tol = -1e-9
        inside = (w0 >= tol) & (w1 >= tol) & (w2 >= tol) & (area.abs() > 1e-12)
        # perspective-correct depth: 1/z is linear in screen space
        zi = 1.0 / (w0 / z[rep, 0] + w1 / z[rep, 1] + w2 / z[rep, 2])
        pix = (py * W + px).long()
        pix, zi, face = pix[inside], zi[inside], fid[rep[inside]]
        zbuf.scatter_reduce_(0, pix, zi, reduce="amin")
        win = zi <= zbuf[pix]
        best[pix[win]] = face[win]

    def _ray_triangle(self, o: Tensor, d: Tensor, face: Tensor) -> tuple[Tensor, Tensor]:
        """Distance along (P, 3) rays to their faces and barycentrics (P, 3)."""
        tri = self.vertices[self.faces[face]]  # (P, 3, 3)
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        p = torch.cross(d, e2, dim=-1)
        det = (e1 * p).sum(-1)
        det = torch.where(det.abs() < 1e-30, torch.full_like(det, 1e-30), det)
        s = o - tri[:, 0]
        u = (s * p).sum(-1) / det
        q = torch.cross(s, e1, dim=-1)
        w = (d * q).sum(-1) / det
        t = (e2 * q).sum(-1) / det
        bary = torch.stack([1 - u - w, u, w], -1).clamp(0, 1)
        return t, bary
