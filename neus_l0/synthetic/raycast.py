"""A small offline renderer for synthetic scenes: textured, shaded, anti-aliased, backdrop.

The surface is anything that can report, for a batch of world-space rays, the first hit
distance and the normal there (`SdfSurface` sphere-traces an analytic SDF; meshes use
`neus_l0.synthetic.meshes.MeshSurface`). The renderer adds

* albedo from a solid (3D) value-noise texture with detail down to about two pixels, so
  multi-view matching has something to lock on to and it is the same from every view;
* Lambert + a little Blinn-Phong specular under one fixed directional light and ambient;
* a textured backdrop (a large sphere around the scene with a vertical gradient, a soft
  checker and noise) so that reconstruction without masks is meaningful;
* anti-aliasing: each pixel averages ``spp x spp`` stratified sub-samples in
  [x - 0.5, x + 0.5] x [y - 0.5, y + 0.5] (regular grid, so a rasteriser can do the same).

Also returned: the camera-z depth through each pixel centre (``inf`` on a miss) and the
object coverage per pixel (fraction of sub-samples that hit the object).
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import numpy as np
import torch

from neus_l0.data.rays import pixel_grid, pixel_rays
from neus_l0.synthetic.shapes import SDF, sdf_gradient

Tensor = torch.Tensor


@dataclasses.dataclass
class RayGrid:
    """The rays of a few views, each sampled at pixel centres plus a few sub-pixel shifts.

    Attributes:
        K: (V, 3, 3) intrinsics; c2w: (V, 4, 4) camera-to-world poses (world units).
        height, width: image size.
        shifts: (S, 2) sub-pixel offsets (x, y) added to every pixel centre.
        origins, dirs: (V, S, H*W, 3) the rays (unit directions).
    """

    K: Tensor
    c2w: Tensor
    height: int
    width: int
    shifts: Tensor
    origins: Tensor
    dirs: Tensor


class Surface(Protocol):
    """Something rays can hit."""

    def intersect_grid(self, rays: RayGrid) -> tuple[Tensor, Tensor]:
        """First hits: t (V, S, H*W) (``inf`` on a miss) and normals (V, S, H*W, 3)."""


@dataclasses.dataclass
class SdfSurface:
    """Sphere tracing of an analytic SDF (world units).

    Attributes:
        sdf: the signed distance function.
        lo, hi: (3,) corners of an axis-aligned box that contains the surface; rays start
            where they enter it and are dropped where they leave it.
        eps: a hit is declared when the SDF falls below this (world units).
        max_steps: sphere-tracing iterations (rays still marching after that count as a hit
            when their SDF is below 20 eps, otherwise as a miss).
        chunk: points per SDF call (bounds memory; all rays march together).
    """

    sdf: SDF
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    eps: float = 1e-3
    max_steps: int = 160
    chunk: int = 1 << 18

    def intersect_grid(self, rays: RayGrid) -> tuple[Tensor, Tensor]:
        shape = rays.origins.shape
        t, n = self.intersect(rays.origins.reshape(-1, 3), rays.dirs.reshape(-1, 3))
        return t.reshape(shape[:-1]), n.reshape(shape)

    def intersect(self, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        """First hits of (N, 3) rays: t (N,) (``inf`` on a miss), unit normals (N, 3)."""
        t = self._trace(origins, dirs)
        n = torch.zeros_like(origins)
        hit = torch.nonzero(torch.isfinite(t)).squeeze(-1)
        for i in hit.split(self.chunk):
            n[i] = self._normals(origins[i] + t[i, None] * dirs[i])
        return t, n

    def _trace(self, o: Tensor, d: Tensor) -> Tensor:
        """(N,) first-hit distance along unit rays, inf where they miss."""
        lo = torch.as_tensor(self.lo, dtype=o.dtype, device=o.device)
        hi = torch.as_tensor(self.hi, dtype=o.dtype, device=o.device)
        inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
        ta, tb = (lo - o) * inv, (hi - o) * inv  # (N, 3) slab test
        t_in = torch.minimum(ta, tb).max(-1).values.clamp_min(0)
        t_out = torch.maximum(ta, tb).min(-1).values
        t = torch.full_like(t_in, float("inf"))
        live = torch.nonzero(t_in < t_out).squeeze(-1)  # (M,) rays that enter the box
        near, far = t_in[live], t_out[live]
        tc = near.clone()  # (M,) current distance of each live ray
        idx = torch.arange(live.numel(), device=o.device)  # rays still marching
        o_l, d_l = o[live], d[live]
        for _ in range(self.max_steps):
            if idx.numel() == 0:
                break
            s = torch.cat([self.sdf(o_l[i] + tc[i, None] * d_l[i])
                           for i in idx.split(self.chunk)])  # (A,) bounded memory per call
            tc[idx] += s
            hit = s < self.eps
            gone = tc[idx] > far[idx]
            t[live[idx[hit]]] = tc[idx[hit]]
            idx = idx[~(hit | gone)]
        if idx.numel():
            s = self.sdf(o_l[idx] + tc[idx, None] * d_l[idx])
            ok = s.abs() < 20 * self.eps
            t[live[idx[ok]]] = tc[idx[ok]]
        return t

    def _normals(self, x: Tensor) -> Tensor:
        """(N, 3) unit normals from a tetrahedral finite-difference gradient."""
        h = 0.5 * self.eps + 1e-5 * float(max(np.subtract(self.hi, self.lo)))
        g = sdf_gradient(self.sdf, x, h)
        return g / g.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _noise_table(seed: int, size: int = 32, channels: int = 3) -> Tensor:
    """(1, C, G+1, G+1, G+1) random lattice, wrapped by one sample for `value_noise`."""
    g = torch.Generator().manual_seed(seed)
    t = torch.rand((channels, size, size, size), generator=g)
    t = torch.cat([t, t[:, :1]], 1)
    t = torch.cat([t, t[:, :, :1]], 2)
    t = torch.cat([t, t[:, :, :, :1]], 3)
    return t[None]


def value_noise(x: Tensor, table: Tensor, cell: float) -> Tensor:
    """3D value noise: trilinear interpolation of a random lattice that tiles space.

    Args:
        x: (N, 3) points.
        table: (1, C, G+1, G+1, G+1) lattice from `_noise_table` (period G cells).
        cell: lattice spacing, in the units of x.

    Returns:
        (N, C) values in [0, 1].
    """
    G = table.shape[-1] - 1
    u = torch.remainder(x / cell, G) * (2.0 / G) - 1.0  # (N, 3) in [-1, 1)
    # grid_sample wants (x, y, z) = (W, H, D) order
    grid = u.flip(-1).reshape(1, -1, 1, 1, 3).to(table.dtype)
    v = torch.nn.functional.grid_sample(table, grid, mode="bilinear", align_corners=True)
    return v.reshape(table.shape[1], -1).T.to(x.dtype)


@dataclasses.dataclass
class Style:
    """Look of a synthetic scene (all lengths in world units).

    Attributes:
        scale: characteristic object size (the bounding-sphere radius); texture cells
            are fractions of it.
        center: (3,) object centre (the backdrop sphere is centred here).
        backdrop_radius: radius of the backdrop sphere (must contain every camera).
        light: (3,) direction towards the light.
        ambient, diffuse, specular, shininess: the shading model.
        seed: texture seed.
    """


    scale: float
    center: tuple[float, float, float]
    backdrop_radius: float
    light: tuple[float, float, float] = (0.45, -0.35, 0.82)
    ambient: float = 0.35
    diffuse: float = 0.65
    specular: float = 0.15
    shininess: float = 40.0
    seed: int = 0

    def __post_init__(self):
        self._tables = [_noise_table(self.seed * 7 + k) for k in range(5)]

    def albedo(self, x: Tensor) -> Tensor:
        """(N, 3) surface albedo at (N, 3) world points."""
        s = self.scale
        low = value_noise(x, self._tables[0], 0.35 * s)  # (N, 3) broad colour patches
        mid = value_noise(x, self._tables[1], 0.07 * s)[:, :1]
        high = value_noise(x, self._tables[2], 0.016 * s)  # ~2 px at 400x300
        base = 0.25 + 0.55 * low
        a = base * (0.55 + 0.6 * mid) + 0.35 * (high - 0.5)
        return a.clamp(0.03, 0.97)

    def backdrop(self, o: Tensor, d: Tensor) -> Tensor:
        """(N, 3) colour where rays (N, 3) meet the backdrop sphere."""
        c = torch.as_tensor(self.center, dtype=o.dtype, device=o.device)
        oc = o - c
        b = (oc * d).sum(-1)
        disc = (b * b - ((oc * oc).sum(-1) - self.backdrop_radius ** 2)).clamp_min(0)
        p = oc + (-b + disc.sqrt())[:, None] * d  # (N, 3) point on the backdrop
        R = self.backdrop_radius
        h = (p[:, 2:3] / R).clamp(-1, 1)
        sky = torch.tensor([0.62, 0.70, 0.80], device=o.device)
        ground = torch.tensor([0.42, 0.36, 0.30], device=o.device)
        grad = ground + (sky - ground) * (0.5 + 0.5 * h)
        n1 = value_noise(p, self._tables[3], 0.08 * R)
        n2 = value_noise(p, self._tables[4], 0.02 * R)[:, :1]
        q = p / (0.12 * R)
        checker = (torch.sin(q[:, 0]) * torch.sin(q[:, 1]) * torch.sin(q[:, 2]))[:, None]
        col = grad * (0.75 + 0.25 * n2) + 0.12 * (n1 - 0.5) + 0.06 * checker
        return col.clamp(0.0, 1.0)

    def shade(self, x: Tensor, n: Tensor, d: Tensor) -> Tensor:
        """(N, 3) colour of surface points x with normals n seen along ray directions d."""
        light = torch.as_tensor(self.light, dtype=x.dtype, device=x.device)
        light = light / light.norm()
        n = torch.where(((n * d).sum(-1, keepdim=True) > 0), -n, n)  # face the viewer
        lam = (n @ light).clamp_min(0)[:, None]
        half = light - d
        half = half / half.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        spec = (n * half).sum(-1).clamp_min(0)[:, None] ** self.shininess
        col = self.albedo(x) * (self.ambient + self.diffuse * lam) + self.specular * spec
        return col.clamp(0.0, 1.0)


def render_views(surface: Surface, style: Style, K: np.ndarray, c2w: np.ndarray,
                 height: int, width: int, spp: int = 2) -> dict:
    """Render a few views at once (one `intersect` call shares per-step overheads).

    Args:
        surface: the object (world units).
        style: texture, lighting and backdrop.
        K: (V, 3, 3) intrinsics; c2w: (V, 4, 4) camera-to-world poses in world units.
        height, width: image size.
        spp: sub-samples per axis (spp^2 per pixel) for anti-aliasing.

    Returns:
        dict of numpy arrays: ``rgb`` (V, H, W, 3) float32 in [0, 1], ``coverage``
        (V, H, W) float32 object fraction, ``depth`` (V, H, W) float32 camera-z depth of
        the first hit through each pixel centre (``inf`` on a miss).
    """
    V = K.shape[0]
    hw = height * width
    Kt = torch.as_tensor(K, dtype=torch.float32)
    Tt = torch.as_tensor(c2w, dtype=torch.float32)
    grid = pixel_grid(height, width).reshape(-1, 2)  # (HW, 2)
    offsets = (torch.arange(spp, dtype=torch.float32) + 0.5) / spp - 0.5
    oy, ox = torch.meshgrid(offsets, offsets, indexing="ij")
    # sub-sample offsets, then the pixel centre (for the depth map): (S, 2), S = spp^2 + 1
    shifts = torch.cat([torch.stack([ox.flatten(), oy.flatten()], -1), torch.zeros(1, 2)])
    S = shifts.shape[0]
    xy = (grid[None, None] + shifts[None, :, None]).expand(V, S, hw, 2).reshape(-1, 2)
    view = torch.arange(V).repeat_interleave(S * hw)  # (V * S * HW,)
    o, d = pixel_rays(Kt[view], Tt[view], xy)
    o, d = o.reshape(V, S, hw, 3), d.reshape(V, S, hw, 3)
    t, n = surface.intersect_grid(RayGrid(Kt, Tt, height, width, shifts, o, d))
    t = t[..., None]
    t_centre, o_centre, d_centre = t[:, -1, :, 0], o[:, -1], d[:, -1]  # (V, HW[, 3])
    o, d, t, n = (a[:, :-1].reshape(-1, a.shape[-1]) for a in (o, d, t, n))
    t = t[:, 0]
    hit = torch.isfinite(t)
    # the backdrop is smooth at the pixel scale: shade it once per pixel (centre ray)
    back = style.backdrop(o_centre.reshape(-1, 3), d_centre.reshape(-1, 3))  # (V * HW, 3)
    col = back.reshape(V, 1, hw, 3).expand(V, S - 1, hw, 3).reshape(-1, 3).clone()
    if hit.any():
        col[hit] = style.shade(o[hit] + t[hit, None] * d[hit], n[hit], d[hit])
    rgb = col.reshape(V, S - 1, hw, 3).mean(1)
    cover = hit.float().reshape(V, S - 1, hw).mean(1)
    # camera z = t * cos(angle to the optical axis)
    depth = t_centre * torch.einsum("vpi,vi->vp", d_centre, Tt[:, :3, 2])
    return {"rgb": rgb.reshape(V, height, width, 3).numpy(),
            "coverage": cover.reshape(V, height, width).numpy(),
            "depth": depth.reshape(V, height, width).numpy()}
