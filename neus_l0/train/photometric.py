"""Multi-view photometric consistency of the rendered surface (issue #35, `train.photo`).

The colour loss can be met by a wrong surface: the colour network paints the texture where
the surface happens to be (the deep pit's floor sits raised, seen right by every view one at
a time). This term ties the surface to the images themselves, as Geo-NeuS and NeuralWarp
do: a small patch around each ray's pixel is carried by the plane of the rendered surface
(its point and normal) into the nearest source views, and the normalised cross-correlation
(NCC) of the grey values scores how well the views agree there. The best `best` sources
count (the others may not see the point), each as (1 - NCC) / 2 in [0, 1].

The surface point is differentiable in the SDF the way IDR's is: from the rendered depth's
point x0 (detached), one Newton step along the ray, ``x = x0 - d f(x0) / (n . d)`` with the
detached unit normal n, so the term moves the SDF's zero level along the ray; the patch's
plane uses n as a constant. Pixel coordinates follow `neus_l0.data.rays.rays_at`: the ray
of pixel (x, y) has direction ``A [x, y, 1]`` with ``A = R K^-1`` (`Scene.ray_matrices`), and
a world point X lands at ``A^-1 (X - c)`` (homogeneous).

Pure functions of tensors, except `PhotoContext.from_scene` (reads the scene once) and
those that take the SDF network (`surface_points`, `occluded`, `photometric_term`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch
from torch import Tensor

from neus_l0.config.schema import PhotoConfig
from neus_l0.data.patches import LUMA, ncc
from neus_l0.data.scene import Scene
from neus_l0.errors import NeusL0Error

#: Where the occlusion test starts past a surface point (normalised frame, about a cell of
#: the demo's finest hash level): it skips the point's own surface.
OCCLUSION_START = 0.03
#: Cost of a source that cannot score a patch (outside the image, behind, back-facing):
#: above any real cost (which is at most 1), so the best-k draw skips it.
INVALID_COST = 2.0


@dataclasses.dataclass(frozen=True)
class PhotoContext:
    """What the term reads every step, built once per run from the training views.

    Attributes:
        gray: (V * H * W,) float32 grey values of every training image, flat
            (``view * H * W + y * W + x``, as `rays_at`'s indices).
        height, width: the images' size.
        rays: (V, 3, 3) A = R K^-1 per view (pixel -> ray direction).
        proj: (V, 3, 3) A^-1 (world offset from the centre -> homogeneous pixel).
        centres: (V, 3) camera centres.
        sources: (V, M) each view's M nearest other views (`nearest_views`).
        offsets: (P, 2) the patch's pixel offsets (`patch_offsets`).
        best: how many of a ray's sources count.
        normal_sources: per ray, this many more sources chosen by its surface normal
            (`normal_views`; 0: none).
        near: how many of the M nearest count until the term widens to all M
            (`photometric_term`'s `wide`; 0: all M, always).
    """

    gray: Tensor
    height: int
    width: int
    rays: Tensor
    proj: Tensor
    centres: Tensor
    sources: Tensor
    offsets: Tensor
    best: int
    normal_sources: int = 0
    near: int = 0

    @classmethod
    def from_scene(cls, scene: Scene, n_sources: int, patch: int, stride: int,
                   best: int, normal_sources: int = 0, wide_sources: int = 0) -> PhotoContext:
        """The context of a scene's (training) views (`wide_sources` > `n_sources`: that
        many nearest, of which `n_sources` count until the term widens).

        Raises:
            NeusL0Error: fewer than two views (a patch needs a second view to compare).
        """
        if scene.n_views < 2:
            raise NeusL0Error(f"{scene.root}: train.photo.weight > 0 needs at least 2 "
                              f"training views, the scene has {scene.n_views}")
        luma = torch.tensor(LUMA, dtype=scene.images.dtype, device=scene.images.device)
        gray = (scene.images @ luma).reshape(-1).contiguous()
        rays = scene.ray_matrices
        proj = torch.linalg.inv(rays.double()).to(rays.dtype)
        sources = nearest_views(scene.centres, max(n_sources, wide_sources))
        near = min(n_sources, sources.shape[1])
        extra = max(0, min(normal_sources, scene.n_views - 1 - sources.shape[1]))
        return cls(gray, scene.height, scene.width, rays, proj, scene.centres, sources,
                   patch_offsets(patch, stride).to(scene.images.device),
                   max(1, min(best, near + extra)), extra,
                   near if near < sources.shape[1] else 0)


def nearest_views(centres: Tensor, k: int) -> Tensor:
    """(V, min(k, V - 1)) each view's nearest other views, by the angle between the
    directions from the origin (the object's centre) to the cameras, nearest first.

    Args:
        centres: (V, 3) camera centres in the normalised frame (the object at the origin).
    """
    v = centres.shape[0]
    u = centres.double() / centres.double().norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos = u @ u.T
    cos.fill_diagonal_(-2.0)  # never its own source
    k = max(0, min(k, v - 1))
    return cos.topk(k, dim=-1).indices.to(centres.device)


def normal_views(centres: Tensor, points: Tensor, normals: Tensor, own: Tensor,
                 taken: Tensor, k: int) -> Tensor:
    """(B, k) per point, the k views that look most squarely at it: the largest cosine
    between its normal and the direction from it to the camera, never its own view nor the
    views already `taken`. A cavity's floor is seen by the views above it, which the nearest
    views of a camera that looks at it at a slant often are not (`tools/source_visibility.py`).

    Args:
        centres: (V, 3) camera centres; points, normals: (B, 3) (unit normals);
        own: (B,) each point's view; taken: (B, M) views already chosen (M may be 0);
        k: 1 <= k <= V - 1 - M.
    """
    d = centres[None, :, :] - points[:, None, :]  # (B, V, 3)
    cos = (d * normals[:, None, :]).sum(-1) / d.norm(dim=-1).clamp_min(1e-12)
    cos = cos.scatter(1, own[:, None], -3.0)
    if taken.shape[1]:
        cos = cos.scatter(1, taken, -3.0)
    return cos.topk(k, dim=-1).indices


def patch_offsets(size: int, stride: int) -> Tensor:
    """(size * size, 2) float pixel offsets (x, y) of a square patch centred on 0, `stride`
    pixels apart (size odd)."""
    if size < 1 or size % 2 == 0 or stride < 1:
        raise ValueError(f"the patch needs an odd size >= 1 and a stride >= 1, got {size}, "
                         f"{stride}")
    r = torch.arange(size, dtype=torch.float32) - size // 2
    y, x = torch.meshgrid(r * stride, r * stride, indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1)], dim=-1)


def plane_points(origins: Tensor, rays: Tensor, pix: Tensor, point: Tensor,
                 normal: Tensor) -> Tensor:
    """Where the reference view's pixels `pix` see the plane through `point` with `normal`.

    Args:
        origins: (B, 3) reference camera centres; rays: (B, 3, 3) their A = R K^-1;
        pix: (B, P, 2) pixel coordinates; point, normal: (B, 3) the plane.

    Returns:
        (B, P, 3) points on the plane (a pixel whose ray runs parallel to it gets a point
        far along its ray; callers drop such rays by their grazing angle).
    """
    xy1 = torch.cat([pix, torch.ones_like(pix[..., :1])], dim=-1)  # (B, P, 3)
    d = xy1 @ rays.transpose(1, 2)  # (B, P, 3)
    num = ((point - origins) * normal).sum(-1, keepdim=True)  # (B, 1)
    den = (d * normal[:, None, :]).sum(-1)  # (B, P)
    den = torch.where(den.abs() < 1e-8, torch.full_like(den, 1e-8), den)
    return origins[:, None, :] + (num / den)[..., None] * d


def project(points: Tensor, proj: Tensor, centres: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel coordinates of world points in views.

    Args:
        points: (B, P, 3); proj: (B, M, 3, 3) A^-1 of each ray's M views; centres: (B, M, 3).

    Returns:
        uv (B, M, P, 2) and the depth along the optical axis in A's units, z (B, M, P)
        (z <= 0: behind the camera; uv then meaningless).
    """
    rel = points[:, None, :, :] - centres[:, :, None, :]  # (B, M, P, 3)
    h = rel @ proj.transpose(-1, -2)  # (B, M, P, 3)
    z = h[..., 2]
    uv = h[..., :2] / torch.where(z.abs() < 1e-8, torch.full_like(z, 1e-8), z)[..., None]
    return uv, z


def sample_gray(gray: Tensor, height: int, width: int, view: Tensor,
                uv: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear grey values at continuous pixel coordinates, differentiable in `uv`.

    Args:
        gray: (V * H * W,) flat images; view: (...) int64 view indices (broadcast against
            uv's leading dims); uv: (..., 2) pixel coordinates (x, y); integer coordinates
            are exactly the pixels.

    Returns:
        values (...) (clamped to the border outside) and inside (...) bool: whether the
        point lies within [0, W - 1] x [0, H - 1] (a non-finite coordinate lies outside).
    """
    uv = torch.where(torch.isfinite(uv), uv, torch.full_like(uv, -1.0))  # NaN: outside
    x, y = uv[..., 0], uv[..., 1]
    inside = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    x = x.clamp(0, width - 1)
    y = y.clamp(0, height - 1)
    x0 = x.detach().floor().clamp(max=width - 2).long() if width > 1 else x.detach().long()
    y0 = y.detach().floor().clamp(max=height - 2).long() if height > 1 else y.detach().long()
    fx, fy = x - x0, y - y0
    x1 = (x0 + 1).clamp(max=width - 1)
    y1 = (y0 + 1).clamp(max=height - 1)
    base = view.expand_as(x0) * (height * width)

    def at(yy: Tensor, xx: Tensor) -> Tensor:
        return gray[base + yy * width + xx]

    top = at(y0, x0) * (1 - fx) + at(y0, x1) * fx
    bottom = at(y1, x0) * (1 - fx) + at(y1, x1) * fx
    return top * (1 - fy) + bottom * fy, inside


def best_cost(cost: Tensor, valid: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """Per ray, the mean of its k lowest valid costs.

    Args:
        cost: (B, M); valid: (B, M) bool; k: 1 <= k <= M.

    Returns:
        (B,) the mean over the k lowest valid costs (over fewer when fewer are valid; 0
        when none) and (B,) bool: whether any source was valid.
    """
    masked = torch.where(valid, cost, torch.full_like(cost, INVALID_COST))
    low = masked.topk(k, dim=-1, largest=False).values  # (B, k)
    keep = (low < INVALID_COST).to(cost.dtype)
    n = keep.sum(-1)
    return (low * keep).sum(-1) / n.clamp_min(1.0), n > 0


def widened(columns: int, near: int, m: int, wide: Tensor) -> Tensor:
    """(columns,) bool: which source columns count, the first `near` of the `m` nearest
    always, the rest of the nearest only where the () `wide` is over 0.5, and any columns
    after the nearest `m` (the normal's stand-ins) always."""
    col = torch.arange(columns, device=wide.device)
    return (col < near) | (col >= m) | (wide > 0.5)


def normal_fallback(valid: Tensor, blocked: Tensor, m: int) -> Tensor:
    """Which sources count when the normal's sources stand in for the nearest: a ray keeps
    its first `m` (nearest) sources as they are while the SDF leaves any of them a clear
    view; a ray whose valid nearest sources are all blocked counts its other (normal-chosen)
    sources instead, those that are valid and not blocked.

    Args:
        valid: (B, M + K) bool sources that can score the patch; blocked: (B, M + K) bool
            sources the SDF puts solid in front of (`occluded`); m: the nearest sources' count.

    Returns:
        (B, M + K) bool.
    """
    near_clear = (valid[:, :m] & ~blocked[:, :m]).any(-1, keepdim=True)  # (B, 1)
    keep_near = torch.zeros_like(valid)
    keep_near[:, :m] = valid[:, :m]
    use_normal = torch.zeros_like(valid)
    use_normal[:, m:] = valid[:, m:] & ~blocked[:, m:]
    return torch.where(near_clear, keep_near, use_normal)


def occluded(sdf: Callable[[Tensor], Tensor], points: Tensor, centres: Tensor, samples: int,
             start: float) -> Tensor:
    """Whether the SDF puts solid between surface points and cameras: `samples` points
    evenly spread on each segment from ``start`` past the point to where the segment leaves
    the unit sphere (or reaches the camera), occluded where any has SDF < 0. A thin occluder
    between the samples is missed; `start` skips the point's own surface.

    Args:
        sdf: (N, 3) -> (N,), evaluated without gradients; points: (B, 3);
            centres: (B, M, 3) the cameras.

    Returns:
        (B, M) bool.
    """
    seg = centres - points[:, None, :]  # (B, M, 3)
    length = seg.norm(dim=-1).clamp_min(1e-9)
    u = seg / length[..., None]
    b = (points[:, None, :] * u).sum(-1)
    c = (points * points).sum(-1)[:, None] - 1.0
    exit_t = -b + (b * b - c).clamp_min(0.0).sqrt()  # leaving the unit sphere
    end = torch.minimum(exit_t, length).clamp_min(start)
    frac = (torch.arange(samples, dtype=points.dtype, device=points.device) + 0.5) / samples
    t = start + (end - start)[..., None] * frac  # (B, M, samples)
    p = points[:, None, None, :] + u[:, :, None, :] * t[..., None]
    with torch.no_grad():
        f = sdf(p.reshape(-1, 3)).reshape(t.shape)
    return (f < 0).any(-1)


@dataclasses.dataclass(frozen=True)
class PhotoRays:
    """A step's rays as the term reads them.

    Attributes:
        origins, dirs: (B, 3) the rays (unit dirs); view: (B,) their views; xy: (B, 2)
            their pixels.
        depth: (B, 1) the rendered depth; normal: (B, 3) the rendered (unnormalised) normal.
        use: (B,) bool rays that may count (in the mask, opaque).
        weight: (B,) the rays' importance weights (an error map's draw; None: all 1): the
            term is their weighted mean over the counted rays.
    """

    origins: Tensor
    dirs: Tensor
    view: Tensor
    xy: Tensor
    depth: Tensor
    normal: Tensor
    use: Tensor
    weight: Tensor | None = None


def surface_points(sdf: Callable[[Tensor], Tensor], rays: PhotoRays, max_sdf: float
                   ) -> tuple[Tensor, Tensor, Tensor]:
    """Each ray's surface point, differentiable in the SDF (IDR's Newton step from the
    rendered depth's point along the ray), its unit normal (detached) and whether it may
    count (in use, facing the camera by more than ~17 degrees, the rendered point within
    `max_sdf` of the zero level).

    Returns:
        x (B, 3), n (B, 3), ok (B,) bool.
    """
    n = rays.normal.detach()
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos = (n * rays.dirs).sum(-1)  # (B,) < 0 where the surface faces the camera
    x0 = (rays.origins + rays.dirs * rays.depth.detach()).detach()
    f = sdf(x0)  # (B,)
    ok = rays.use & (cos < -0.3) & (f.detach().abs() < max_sdf)
    safe_cos = torch.where(ok, cos, -torch.ones_like(cos))
    return x0 - rays.dirs * (f / safe_cos)[:, None], n, ok


def photometric_term(ctx: PhotoContext, sdf: Callable[[Tensor], Tensor], rays: PhotoRays,
                     cfg: PhotoConfig, wide: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The term over a step's rays.

    Args:
        ctx: the run's `PhotoContext`.
        sdf: (N, 3) -> (N,) the SDF network's value (differentiable in its parameters).
        rays: the step's rays (`PhotoRays`).
        cfg: `max_sdf` (rays whose rendered point lies farther from the zero level, in the
            normalised frame, do not count: their depth mixes two surfaces);
            `occlusion_samples` (> 0: a source whose view of the point the SDF blocks,
            `occluded`, does not count: a cavity's floor is seen by few views, and a source
            looking at the wall instead would pull the floor to a wrong depth; with the
            context's `normal_sources`, the test only decides when the normal's sources
            stand in for the nearest, `normal_fallback`);
            `planar_sdf` (> 0: a ray whose patch's plane points lie farther than this from
            the zero level does not count: the patch straddles a rim, where the plane the
            homography assumes is not there).
        wide: () 1 once all of the context's nearest sources count, 0 while only its
            `near` do (a tensor, so that a compiled step takes both without recompiling;
            None: all count).

    Returns:
        the () mean cost over the counted rays (weighted by ``rays.weight`` when given; 0
        when none) and the () number counted.
    """
    x, n, ok = surface_points(sdf, rays, cfg.max_sdf)
    pix = rays.xy.to(ctx.offsets.dtype)[:, None, :] + ctx.offsets[None]  # (B, P, 2)
    ref, ref_in = sample_gray(ctx.gray, ctx.height, ctx.width, rays.view[:, None], pix)
    pts = plane_points(rays.origins, ctx.rays[rays.view], pix, x, n)  # (B, P, 3)
    src_views = ctx.sources[rays.view]  # (B, M)
    m = src_views.shape[1]
    stand_in = ctx.normal_sources > 0 and cfg.occlusion_samples > 0
    if stand_in:
        more = normal_views(ctx.centres, x.detach(), n, rays.view, src_views,
                            ctx.normal_sources)
        src_views = torch.cat([src_views, more], dim=1)  # (B, M + K)
    uv, z = project(pts, ctx.proj[src_views], ctx.centres[src_views])
    vals, inside = sample_gray(ctx.gray, ctx.height, ctx.width, src_views[..., None], uv)
    facing = ((ctx.centres[src_views] - x.detach()[:, None, :]) * n[:, None, :]).sum(-1) > 0
    valid = facing & (z > 0).all(-1) & inside.all(-1)  # (B, M [+ K])
    if ctx.near > 0 and wide is not None:
        valid = valid & widened(valid.shape[1], ctx.near, m, wide)
    if cfg.occlusion_samples > 0:
        blocked = occluded(sdf, x.detach(), ctx.centres[src_views], cfg.occlusion_samples,
                           OCCLUSION_START)
        if stand_in:
            valid = normal_fallback(valid, blocked, m)
        else:
            valid = valid & ~blocked
    if cfg.planar_sdf > 0:
        with torch.no_grad():
            off = sdf(pts.detach().reshape(-1, 3)).reshape(pts.shape[:2]).abs()
        ok = ok & (off.amax(-1) < cfg.planar_sdf)
    cost = (1.0 - ncc(ref, vals)) * 0.5
    per_ray, any_valid = best_cost(cost, valid, ctx.best)
    counted = (ok & any_valid & ref_in.all(-1)).to(per_ray.dtype)
    total = counted.sum()
    if rays.weight is None:
        return (per_ray * counted).sum() / total.clamp_min(1.0), total
    w = counted * rays.weight.to(per_ray.dtype)
    return (per_ray * w).sum() / w.sum().clamp_min(1e-12), total
