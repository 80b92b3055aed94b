"""The oracle sampling study: NeuS's up-sampling on analytic SDFs, every sampler, exactly.

Training noise hides what a sampler buys, so this study takes the sampler out of training:
the SDF is known, the up-sampling (`neus_l0.sampling.upsample.up_sample`, NeuS's fixed sharpness
``inv_s = base * 2^i``) runs on it as it would on a converged network, and each sampler's fine
samples are scored against the exact first hit along the ray.

Cases (all in NeuS's normalised frame, inside the unit sphere): a sphere; a plane hit at
grazing angles (60, 80, 85 degrees from the normal); pits in a slab (radius / depth 0.02 /
0.1, 0.05 / 0.2, 0.1 / 0.1) with rays towards their bottoms; rods (radius 0.005, 0.02) and
fins (thickness 0.01, 0.04) hit side-on; and the built-in synthetic scenes' exact SDFs
(`demo`, `pits-and-thin`, scaled into the unit sphere) with rays towards their pits and thin
parts. Cameras are 2.5 from the origin; the coarse samples are NeuS's uniform ones on
[mid - 1, mid + 1] with one random shift per ray (the same for every sampler).

Budgets: 16+16 and 32+32 in 2 rounds (as `demo`), 64+64 in 4 rounds (as NeuS / `wmask`).
Regimes: ``sharp`` is the exact SDF; ``soft`` multiplies it by 1/4 (a smooth early-training
field whose slope is below 1 near the surface: the same as dividing every ``inv_s`` by 4),
in the up-sampling and in the compositing.

Per case: the fraction of fine samples within eps of the first hit (eps = 0.001, 0.003, 0.01,
0.03), their mean and median distance to it, and the errors of the rendered depth and
opacity (NeuS's unbiased compositing, cos ratio 1, at ``s = FINAL_S``, over the samples inside
the unit sphere, as `render_rays`, without NeuS's 1e-5 guards: see `composite`) against a
dense reference of 4096 uniform samples.
"""

from __future__ import annotations

import dataclasses
import math
import time

import torch
import torch.nn.functional as F
from torch import Tensor

from neus_l0.bounds.sphere import near_far_from_sphere
from neus_l0.config.schema import L0Config, SamplerConfig
from neus_l0.render.volume import coarse_z_vals
from neus_l0.sampling.upsample import build_sampler, up_sample
from neus_l0.synthetic import shapes as sh

#: Distances (normalised units) at which a fine sample counts as near the first hit.
EPS = (0.001, 0.003, 0.01, 0.03)
#: (n_samples, n_importance, rounds): demo's 2 rounds for the small budgets, NeuS's 4 above.
BUDGETS = ((16, 16, 2), (32, 32, 2), (64, 64, 4))
#: SDF slope of each regime (soft: an early-training field).
REGIMES = {"sharp": 1.0, "soft": 0.25}
#: NeuS's sharpness s at which depth and opacity are composited (a converged run's order).
FINAL_S = 512.0
#: Samples per ray of the dense reference.
DENSE = 4096
#: The L0 default before this study: maxblur with the authors' absolute pad 0.001.
_BLUR = SamplerConfig(name="l0", l0=L0Config(blur=True, pad=0.001, pad_mode="absolute",
                                             masses="interpolant"))
#: The paper's draw without maxblur (the L0 default between the first study and `masses`).
_INTERP = SamplerConfig(name="l0", l0=L0Config(masses="interpolant"))


def _l0(base: SamplerConfig, name: str | None = None, **l0) -> SamplerConfig:
    """`base` with another sampler `name` and other L0 options (`sampler.l0.*`)."""
    return dataclasses.replace(base, name=name or base.name,
                               l0=dataclasses.replace(base.l0, **l0))


#: The variants compared: label -> sampler settings ("interp": the interpolant's masses, the
#: paper's draw; labels without "blur": maxblur off; bare L0 names: the default, `sections`).
VARIANTS: dict[str, SamplerConfig] = {
    "hvs": SamplerConfig(name="hvs"),
    "neus-exact": SamplerConfig(name="neus-exact"),
    "l0": SamplerConfig(name="l0"),  # the default: section masses, exponential inside
    "l0-inverse": SamplerConfig(name="l0-inverse"),
    "l0-linear": SamplerConfig(name="l0-linear"),
    "l0 interp": _INTERP,
    "l0 interp rel.01": _l0(_INTERP, pad=0.01, pad_mode="relative"),
    "l0 interp endpoint": _l0(_INTERP, placement="endpoint"),
    "l0 interp nodensity": _l0(_INTERP, as_density=False),
    "l0-inverse interp": _l0(_INTERP, name="l0-inverse"),
    "l0-linear interp": _l0(_INTERP, name="l0-linear"),
    "l0 blur abs.001": _BLUR,  # the default before the first study
    "l0 blur abs.01": _l0(_BLUR, pad=0.01),
    "l0 blur nopad": _l0(_BLUR, pad_mode="none"),
    "l0 blur rel.01": _l0(_BLUR, pad=0.01, pad_mode="relative"),
    "l0 blur rel.1": _l0(_BLUR, pad=0.1, pad_mode="relative"),
    "l0 blur endpoint": _l0(_BLUR, placement="endpoint"),
    "l0 blur nodensity": _l0(_BLUR, as_density=False),
    "l0-inverse blur": _l0(_BLUR, name="l0-inverse"),
    "l0-linear blur": _l0(_BLUR, name="l0-linear"),
}


@dataclasses.dataclass
class Case:
    """One shape and its rays.

    Attributes:
        name: label. sdf: (P, 3) -> (P,) exact SDF (float64 works).
        origins, dirs: (B, 3) float64, unit dirs. hit: (B,) first hit distance.
    """

    name: str
    sdf: sh.SDF
    origins: Tensor
    dirs: Tensor
    hit: Tensor


# ------------------------------------------------------------------------------------------
# Rays and exact first hits.


def first_hit(sdf: sh.SDF, origins: Tensor, dirs: Tensor, n: int = 20001,
              chunk: int = 64) -> Tensor:
    """First zero crossing (outside -> inside) of `sdf` on each ray's [mid - 1, mid + 1].

    A dense grid of `n` points finds the first sign change; 60 bisection steps refine it.

    Args:
        origins, dirs: (B, 3) float64. n: grid points per ray.

    Returns:
        (B,) float64 distances, NaN where the ray never enters the shape.
    """
    near, far = near_far_from_sphere(origins, dirs)  # (B, 1)
    out = torch.full((origins.shape[0],), float("nan"), dtype=torch.float64)
    lin = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
    for s in range(0, origins.shape[0], chunk):
        o, d = origins[s:s + chunk], dirs[s:s + chunk]
        t = near[s:s + chunk] + (far[s:s + chunk] - near[s:s + chunk]) * lin  # (b, n)
        f = sdf((o[:, None] + d[:, None] * t[..., None]).reshape(-1, 3)).reshape(t.shape)
        inside = f <= 0
        has = inside.any(-1) & (f[:, 0] > 0)
        k = inside.to(torch.int8).argmax(-1).clamp_min(1)  # (b,)
        lo = t.gather(1, (k - 1)[:, None])[:, 0]
        hi = t.gather(1, k[:, None])[:, 0]
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            neg = sdf(o + d * mid[:, None]) <= 0
            hi, lo = torch.where(neg, mid, hi), torch.where(neg, lo, mid)
        out[s:s + chunk] = torch.where(has, 0.5 * (lo + hi), float("nan"))
    return out


def _unit(v: Tensor) -> Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def _aim(targets: Tensor, dirs: Tensor, dist: float = 2.5) -> tuple[Tensor, Tensor]:
    """Rays ending at `targets` along `dirs`, starting `dist` before them."""
    dirs = _unit(dirs)
    return targets - dist * dirs, dirs


def _disk(g: torch.Generator, B: int, radius: float) -> Tensor:
    """(B, 2) points uniform in a disk."""
    r = radius * torch.rand(B, generator=g, dtype=torch.float64).sqrt()
    a = 2 * math.pi * torch.rand(B, generator=g, dtype=torch.float64)
    return torch.stack([r * a.cos(), r * a.sin()], -1)


def _sphere_rays(g, B):
    v = _unit(torch.randn(B, 3, generator=g, dtype=torch.float64))
    # a point in the disk of radius 0.45 through the centre, perpendicular to v
    a = _unit(torch.cross(v, torch.tensor([[0.3, 0.5, 0.8]], dtype=torch.float64)
                          .expand(B, 3), dim=-1))
    b = torch.cross(v, a, dim=-1)
    p = _disk(g, B, 0.45)
    return _aim(p[:, :1] * a + p[:, 1:] * b, -v)


def _plane_rays(g, B, deg):
    th = math.radians(deg)
    phi = 2 * math.pi * torch.rand(B, generator=g, dtype=torch.float64)
    d = torch.stack([math.sin(th) * phi.cos(), math.sin(th) * phi.sin(),
                     torch.full_like(phi, -math.cos(th))], -1)
    p = _disk(g, B, 0.3)
    return _aim(torch.cat([p, torch.zeros(B, 1, dtype=torch.float64)], -1), d)


def _pit_rays(g, B, r, depth):
    p = _disk(g, B, 0.6 * r)
    targets = torch.cat([p, torch.full((B, 1), -depth, dtype=torch.float64)], -1)
    tilt = _disk(g, B, 0.3 * r / depth)
    return _aim(targets, torch.cat([tilt, -torch.ones(B, 1, dtype=torch.float64)], -1))


def _side_rays(g, B, half_width, normal_axis):
    """Rays towards a thin vertical part at the origin, within 60 degrees of `normal_axis`."""
    off = (2 * torch.rand(B, generator=g, dtype=torch.float64) - 1) * 0.8 * half_width
    h = (2 * torch.rand(B, generator=g, dtype=torch.float64) - 1) * 0.3
    ang = (2 * torch.rand(B, generator=g, dtype=torch.float64) - 1) * math.radians(60)
    n = torch.tensor(normal_axis, dtype=torch.float64)
    side = torch.tensor([n[1].item(), -n[0].item(), 0.0], dtype=torch.float64)
    d = -(ang.cos()[:, None] * n + ang.sin()[:, None] * side)
    d = d + 0.2 * torch.randn(B, 1, generator=g, dtype=torch.float64) * torch.tensor(
        [0.0, 0.0, 1.0], dtype=torch.float64)
    targets = off[:, None] * side + h[:, None] * torch.tensor([0.0, 0.0, 1.0],
                                                               dtype=torch.float64)
    return _aim(targets, d)


class _Scaled:
    """A world-unit SDF seen in the unit sphere: ``f(x * scale + centre) / scale``."""

    def __init__(self, sdf: sh.SDF, centre: Tensor, scale: float):
        self.sdf, self.centre, self.scale = sdf, centre, scale

    def __call__(self, x: Tensor) -> Tensor:
        return self.sdf(x * self.scale + self.centre.to(x.dtype)) / self.scale


class _Sloped:
    """`sdf` times a slope (the soft regime)."""

    def __init__(self, sdf: sh.SDF, slope: float):
        self.sdf, self.slope = sdf, slope

    def __call__(self, x: Tensor) -> Tensor:
        return self.slope * self.sdf(x)


def _scene_case(g, B, name):
    shape = sh.builtin_shape(name)
    lo, hi = (torch.tensor(v, dtype=torch.float64) for v in shape.bounds)
    centre = 0.5 * (lo + hi)
    scale = float(0.5 * (hi - lo).norm()) * 1.05  # the box's corners inside the unit sphere
    sdf = _Scaled(shape.sdf, centre, scale)
    feats = shape.features
    idx = torch.randint(len(feats), (B,), generator=g)
    c = torch.tensor([f["center"] for f in feats], dtype=torch.float64)[idx]
    rad = torch.tensor([f["radius"] for f in feats], dtype=torch.float64)[idx]
    targets = (c - centre) / scale + 0.3 * (rad / scale)[:, None] * torch.randn(
        B, 3, generator=g, dtype=torch.float64)
    v = _unit(torch.randn(B, 3, generator=g, dtype=torch.float64))
    v[:, 2] = v[:, 2].abs() + 0.3  # cameras above the table, as the synthetic scenes' are
    o, d = _aim(targets, -v)
    return sdf, o, d


def make_cases(n_rays: int = 128, seed: int = 0, names: list[str] | None = None) -> list[Case]:
    """The study's shapes with `n_rays` rays each that hit them (fewer if some miss)."""
    g = torch.Generator().manual_seed(seed)
    slab = sh.Box((0.0, 0.0, -0.25), (0.7, 0.7, 0.25))
    specs = {
        "sphere": lambda: (sh.Sphere((0.0, 0.0, 0.0), 0.5), *_sphere_rays(g, n_rays)),
        **{f"plane {a}deg": (lambda a=a: (lambda x: x[:, 2], *_plane_rays(g, n_rays, a)))
           for a in (60, 80, 85)},
        **{f"pit r{r:g} d{dp:g}": (lambda r=r, dp=dp: (
            sh.Difference(slab, (sh.CappedCone((0.0, 0.0, -dp), (0.0, 0.0, 0.2), r, r),)),
            *_pit_rays(g, n_rays, r, dp))) for r, dp in ((0.02, 0.1), (0.05, 0.2), (0.1, 0.1))},
        **{f"rod r{r:g}": (lambda r=r: (
            sh.CappedCone((0.0, 0.0, -0.5), (0.0, 0.0, 0.5), r, r),
            *_side_rays(g, n_rays, r, (1.0, 0.0, 0.0)))) for r in (0.005, 0.02)},
        **{f"fin t{t:g}": (lambda t=t: (
            sh.Box((0.0, 0.0, 0.0), (0.5, t / 2, 0.5)),
            *_side_rays(g, n_rays, 0.5, (0.0, 1.0, 0.0)))) for t in (0.01, 0.04)},
        **{f"scene {s}": (lambda s=s: _scene_case(g, n_rays, s))
           for s in ("demo", "pits-and-thin")},
    }
    cases = []
    for name, make in specs.items():
        if names is not None and name not in names:
            continue
        sdf, o, d = make()
        hit = first_hit(sdf, o, d)
        keep = torch.isfinite(hit)
        cases.append(Case(name, sdf, o[keep], d[keep], hit[keep]))
    return cases


# ------------------------------------------------------------------------------------------
# Compositing and scoring.


def composite(sdf: sh.SDF, origins: Tensor, dirs: Tensor, z: Tensor, dist_last: float,
              s: float) -> tuple[Tensor, Tensor]:
    """NeuS's rendered depth and opacity of sorted samples `z` (B, N), as `render_rays`.

    NeuS's unbiased alpha (cos ratio 1) at sharpness `s` at the section midpoints, weights over
    the samples inside the unit sphere, but without NeuS's 1e-5 guards in the alpha and 1e-7
    in the transmittance: they add about 1e-5 opacity per sample, so they would bias a
    4096-sample reference (by ~4 % of the opacity) and not a 32-sample ray.

    Returns:
        depth (B,) and opacity (B,).
    """
    B, N = z.shape
    dists = torch.cat([z[:, 1:] - z[:, :-1], torch.full_like(z[:, :1], dist_last)], -1)
    mid = z + 0.5 * dists
    pts = (origins[:, None] + dirs[:, None] * mid[..., None]).reshape(-1, 3)
    f = sdf(pts).reshape(B, N)
    grad = sh.sdf_gradient(sdf, pts, 1e-5).reshape(B, N, 3)
    cos = (dirs[:, None] * grad).sum(-1).clamp_max(0.0)  # NeuS's iter_cos at ratio 1
    prev, nxt = s * (f - 0.5 * cos * dists), s * (f + 0.5 * cos * dists)
    # 1 - sigmoid(nxt) / sigmoid(prev), in log space, without NeuS's 1e-5 guards
    alpha = (-torch.expm1(F.logsigmoid(nxt) - F.logsigmoid(prev))).clamp(0.0, 1.0)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1]], -1),
                          -1)
    w = alpha * trans * (pts.reshape(B, N, 3).norm(dim=-1) < 1.0)
    op = w.sum(-1)
    return (w * mid).sum(-1) / op.clamp_min(1e-6), op


def score(case: Case, slope: float, budget: tuple[int, int, int], cfg: SamplerConfig,
          reference: tuple[Tensor, Tensor], seed: int = 0) -> dict:
    """Run NeuS's up-sampling with one sampler on one case and score its fine samples."""
    n_samples, n_importance, rounds = budget
    sdf = _Sloped(case.sdf, slope)
    o, d = case.origins.float(), case.dirs.float()
    near, far = near_far_from_sphere(o, d)
    g = torch.Generator().manual_seed(seed)
    z = coarse_z_vals(near, far, n_samples, perturb=True, generator=g)
    t0 = time.perf_counter()
    z_all, z_new = up_sample(sdf, o, d, z, build_sampler(cfg), n_importance, rounds)
    secs = time.perf_counter() - t0
    dist = (z_new.double() - case.hit[:, None]).abs()  # (B, n_importance)
    depth, op = composite(sdf, case.origins, case.dirs, z_all.double(), 2.0 / n_samples,
                          FINAL_S * slope)
    near_hit = {e: (dist <= e).double().mean(-1) for e in EPS}  # (B,) per ray
    row = {f"within_{e:g}": float(v.mean()) for e, v in near_hit.items()}
    row["_per_ray"] = {f"within_{e:g}": v for e, v in near_hit.items()}  # not in the CSV
    row.update(mean_dist=float(dist.mean()), median_dist=float(dist.median()),
               depth_err=float((depth - reference[0]).abs().mean()),
               opacity_err=float((op - reference[1]).abs().mean()), draw_s=secs)
    return row


def dense_reference(case: Case, slope: float) -> tuple[Tensor, Tensor]:
    """Depth and opacity of `DENSE` uniform samples on [mid - 1, mid + 1]; (B,) each."""
    near, far = near_far_from_sphere(case.origins, case.dirs)
    z = coarse_z_vals(near, far, DENSE, perturb=False)
    return composite(_Sloped(case.sdf, slope), case.origins, case.dirs, z, 2.0 / DENSE,
                     FINAL_S * slope)


def run_study(n_rays: int = 128, cases: list[str] | None = None,
              variants: dict[str, SamplerConfig] | None = None,
              budgets: tuple = BUDGETS, regimes: dict[str, float] | None = None,
              log=print) -> list[dict]:
    """Every case x regime x budget x variant; one row (dict) each."""
    variants = VARIANTS if variants is None else variants
    regimes = REGIMES if regimes is None else regimes
    rows = []
    for case in make_cases(n_rays, names=cases):
        for regime, slope in regimes.items():
            ref = dense_reference(case, slope)
            for budget in budgets:
                for label, cfg in variants.items():
                    row = {"case": case.name, "rays": case.hit.numel(), "regime": regime,
                           "budget": f"{budget[0]}+{budget[1]}", "rounds": budget[2],
                           "sampler": label}
                    row.update(score(case, slope, budget, cfg, ref))
                    rows.append(row)
        log(f"  {case.name}: {case.hit.numel()} rays")
    return rows
